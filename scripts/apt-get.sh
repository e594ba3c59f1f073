#!/usr/bin/env bash
# apt-get "$@" (run it as root), waiting at most 5 minutes while another apt job (unattended-upgrades, someone's
# apt-get) holds a package lock: `install` waits by itself (DPkg::Lock::Timeout), `update` fails at once on the
# lists lock, so it is tried again every 3 s; one line says what it waits for.
set -uo pipefail
wait_s=${APT_LOCK_WAIT_S:-300}
deadline=$((SECONDS + wait_s))
said=""
while true; do
    rc=0
    err=$({ DEBIAN_FRONTEND=noninteractive apt-get -o DPkg::Lock::Timeout="$wait_s" "$@" 2>&1 1>&3; } 3>&1) || rc=$?
    [ $rc -eq 0 ] && exit 0
    if [[ "$err" != *"Could not get lock"* ]] || [ $SECONDS -ge $deadline ]; then
        printf '%s\n' "$err" >&2
        echo "apt-get failed${said:+: another apt job still held the package lock after $wait_s s}" >&2
        exit 1
    fi
    if [ -z "$said" ]; then
        said=yes
        holder=$(printf '%s' "$err" | grep -o 'held by process [0-9]* ([^)]*)' | head -1)
        echo "another apt job holds the package lock${holder:+ ($holder)}: waiting for it, at most $wait_s s" >&2
    fi
    sleep 3
done
