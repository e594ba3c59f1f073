#!/usr/bin/env bash
# Build the svelive container image with Podman on a Debian 12 machine that has
# no Docker engine and no image registry, then smoke-test it (docs/container.md).
#
#   scripts/build-image.sh [all|base|wheels|build|online|smoke|clean]     (as root; default: all)
#
#   base    debian:bookworm-slim made locally: debootstrap --variant=minbase, slimmed like
#           the official image, imported as localhost/debian:bookworm and tagged
#           docker.io/library/debian:bookworm-slim (skipped when it exists)
#   wheels  the wheelhouse: every dependency as a cp311 manylinux x86_64 wheel, plus the
#           build backend, downloaded on the host (pip in the build cannot verify TLS here)
#   build   podman build --isolation chroot --build-arg WHEELS=wheels (the offline path)
#   online  podman build of the default online path as $IMAGE-online (pip given the host's CA
#           bundle through build-time volumes); not part of `all`
#   smoke   unpack the image into a directory, run its CMD with its ENV, USER and WORKDIR in
#           a chroot (podman run cannot start containers here), fetch /healthz, /api/state,
#           /snapshot.jpg (a colour JPEG: 3 components) and /snapshot.exr (R, G, B), both read
#           back with the image's own Python, check that serving compiled no numba kernel
#           the build had not, run the HEALTHCHECK command, stop the server
#   clean   remove the work directory (the image and the base image stay)
#
# Environment: WORK (default /tmp/svelive-image; never inside the repository), IMAGE
# (localhost/svelive), PORT (default: the first free port from 8000), MIRROR (default: the
# Debian archive apt uses on this machine).
set -euo pipefail

REPO=$(cd "$(dirname "$0")/.." && pwd)
WORK=${WORK:-/tmp/svelive-image}
IMAGE=${IMAGE:-localhost/svelive}
BASE=localhost/debian:bookworm
SUITE=bookworm
PYTHON=${PYTHON:-python3}
STARTUP_TIMEOUT=90

case "$WORK" in "$REPO"|"$REPO"/*) echo "WORK must be outside the repository" >&2; exit 2 ;; esac
[ "$(id -u)" = 0 ] || { echo "run as root (debootstrap, podman, chroot)" >&2; exit 2; }

log() { printf '\n== %s\n' "$*"; }

need() {
    local missing=()
    for pkg in "$@"; do dpkg -s "$pkg" >/dev/null 2>&1 || missing+=("$pkg"); done
    if [ ${#missing[@]} -gt 0 ]; then
        apt-get update -qq && apt-get install -y --no-install-recommends "${missing[@]}"
    fi
}

mirror() {
    # The first archive URI apt uses here (deb822 or one-line sources), else deb.debian.org.
    local uri
    uri=$(grep -hs -m1 -E '^URIs:' /etc/apt/sources.list.d/*.sources | awk '{print $2}' | head -1 || true)
    [ -n "$uri" ] || uri=$(grep -hs -m1 -E '^deb ' /etc/apt/sources.list | awk '{print $2}' || true)
    echo "${MIRROR:-${uri:-http://deb.debian.org/debian}}"
}

base() {
    need podman
    if podman image exists "$BASE"; then
        log "base image $BASE exists"
    else
        need debootstrap
        local root="$WORK/base-rootfs" url
        url=$(mirror)
        log "debootstrap $SUITE from $url"
        rm -rf --one-file-system "$root"
        debootstrap --variant=minbase "$SUITE" "$root" "$url"
        # What the official -slim image does: security updates in the sources, no package
        # lists or .deb cache, no documentation, manual pages or translations.
        rm -f "$root/etc/apt/sources.list"
        cat > "$root/etc/apt/sources.list.d/debian.sources" <<EOF
Types: deb
URIs: $url
Suites: $SUITE $SUITE-updates
Components: main
Signed-By: /usr/share/keyrings/debian-archive-keyring.gpg

Types: deb
URIs: ${url%/debian}/debian-security
Suites: $SUITE-security
Components: main
Signed-By: /usr/share/keyrings/debian-archive-keyring.gpg
EOF
        cat > "$root/etc/dpkg/dpkg.cfg.d/docker" <<'EOF'
path-exclude /usr/share/doc/*
path-include /usr/share/doc/*/copyright
path-exclude /usr/share/man/*
path-exclude /usr/share/groff/*
path-exclude /usr/share/info/*
path-exclude /usr/share/lintian/*
path-exclude /usr/share/locale/*
path-include /usr/share/locale/locale.alias
EOF
        cat > "$root/etc/apt/apt.conf.d/docker-clean" <<'EOF'
DPkg::Post-Invoke { "rm -f /var/cache/apt/archives/*.deb /var/cache/apt/archives/partial/*.deb /var/cache/apt/*.bin || true"; };
APT::Update::Post-Invoke { "rm -f /var/cache/apt/archives/*.deb /var/cache/apt/archives/partial/*.deb /var/cache/apt/*.bin || true"; };
Dir::Cache::pkgcache "";
Dir::Cache::srcpkgcache "";
EOF
        echo 'Acquire::Languages "none";' > "$root/etc/apt/apt.conf.d/docker-no-languages"
        rm -rf "$root"/var/lib/apt/lists/* "$root"/var/cache/apt/archives/*.deb "$root"/var/cache/apt/*.bin \
               "$root"/usr/share/man/* "$root"/usr/share/info/* "$root"/usr/share/groff/* "$root"/usr/share/lintian/*
        find "$root/usr/share/doc" -mindepth 1 -not -name copyright -not -type d -delete
        find "$root/usr/share/locale" -mindepth 1 -maxdepth 1 -not -name locale.alias -exec rm -rf {} +
        log "import $BASE"
        tar -C "$root" -c . | podman import \
            --change 'ENV PATH=/usr/local/sbin:/usr/local/bin:/usr/sbin:/usr/bin:/sbin:/bin' \
            --change 'CMD ["bash"]' - "$BASE"
        rm -rf --one-file-system "$root"
    fi
    podman tag "$BASE" docker.io/library/debian:bookworm-slim
}

wheels() {
    local house="$WORK/wheels"
    mkdir -p "$house"
    log "wheelhouse $house"
    # The dependencies as pyproject.toml states them, for Debian 12's CPython 3.11 on x86_64;
    # setuptools is the project's build backend (pip builds /src inside the image).
    mapfile -t reqs < <("$PYTHON" - "$REPO/pyproject.toml" <<'EOF'
import sys, tomllib
with open(sys.argv[1], "rb") as f:
    project = tomllib.load(f)
print(*project["project"]["dependencies"], *project["build-system"]["requires"], sep="\n")
EOF
)
    "$PYTHON" -m pip download --quiet --dest "$house" --only-binary=:all: \
        --implementation cp --python-version 3.11 --abi cp311 \
        --platform manylinux_2_36_x86_64 --platform manylinux_2_28_x86_64 \
        --platform manylinux_2_17_x86_64 --platform manylinux2014_x86_64 \
        "${reqs[@]}"
    ls "$house"
    du -sh "$house"
}

build() {
    need podman
    [ -d "$WORK/wheels" ] || wheels
    # The wheelhouse goes into the build context only for the build (.dockerignore allows
    # `wheels`); it is never committed. Refuse to touch a wheels/ that is not ours.
    if [ -e "$REPO/wheels" ]; then
        echo "$REPO/wheels exists already; move it away first" >&2
        exit 2
    fi
    trap 'rm -rf --one-file-system "$REPO/wheels"' EXIT
    cp -al "$WORK/wheels" "$REPO/wheels" 2>/dev/null || cp -r "$WORK/wheels" "$REPO/wheels"
    log "podman build $IMAGE"
    local start=$SECONDS
    # --format docker keeps HEALTHCHECK; --layers=false leaves no cache images on a shared machine.
    podman build --isolation chroot --format docker --layers=false --pull=never \
        --build-arg WHEELS=wheels -t "$IMAGE" "$REPO"
    echo "build took $((SECONDS - start)) s"
    rm -rf --one-file-system "$REPO/wheels"
    trap - EXIT
    podman images --filter reference="$IMAGE" --filter reference=docker.io/library/debian:bookworm-slim
}

online() {
    # The Dockerfile's default path (pip fetches from PyPI). pip in the build cannot verify
    # this machine's TLS interception with its own CA list, so give it the host's bundle
    # through build-time volumes (nothing of it stays in the image; the Dockerfile is unchanged).
    need podman
    local conf="$WORK/pip.conf"
    mkdir -p "$WORK"
    printf '[global]\ncert = /etc/ssl/certs/host-ca.crt\n' > "$conf"
    log "podman build $IMAGE-online (online pip)"
    local start=$SECONDS
    podman build --isolation chroot --format docker --layers=false --pull=never \
        -v "$conf:/etc/pip.conf:ro" -v /etc/ssl/certs/ca-certificates.crt:/etc/ssl/certs/host-ca.crt:ro \
        -t "$IMAGE-online" "$REPO"
    echo "build took $((SECONDS - start)) s; smoke-test it with IMAGE=$IMAGE-online $0 smoke"
}

free_port() {
    "$PYTHON" - <<'EOF'
import socket
for port in range(8000, 8100):
    with socket.socket() as s:
        try:
            s.bind(("0.0.0.0", port))
        except OSError:
            continue
        print(port)
        break
EOF
}

inspect() { podman image inspect --format "$1" "$IMAGE"; }

root="$WORK/root"   # the unpacked image; global, as the EXIT trap needs it
server=""           # pid of the server under test

smoke() {
    local port=${PORT:-$(free_port)} cid uid user workdir envs cmd health
    mountpoint -q "$root/proc" 2>/dev/null && umount "$root/proc"
    rm -rf --one-file-system "$root"
    mkdir -p "$root"
    log "unpack $IMAGE into $root"
    cid=$(podman create --no-healthcheck "$IMAGE")   # no systemd here for health timers
    podman export "$cid" | tar -C "$root" -x
    podman rm "$cid" >/dev/null
    echo "unpacked: $(du -sh "$root" | cut -f1); the largest parts:"
    du -s "$root/opt/svelive/lib/python3.11/site-packages"/* "$root/usr/lib/x86_64-linux-gnu"/libicu* \
        "$root/usr/lib/python3.11" | sort -n | tail -6 | awk '{printf "  %4d MB  %s\n", $1 / 1024, $2}' | sed "s|$root||"
    # What a container runtime would provide: /proc and the basic device nodes.
    mkdir -p "$root/proc" "$root/dev"
    mount -t proc proc "$root/proc"
    for node in "null 1 3" "zero 1 5" "random 1 8" "urandom 1 9"; do
        set -- $node
        [ -e "$root/dev/$1" ] || mknod -m 666 "$root/dev/$1" c "$2" "$3"
    done
    stop() {
        if [ -n "$server" ] && kill -0 "$server" 2>/dev/null; then
            kill -TERM "$server"
            for _ in $(seq 50); do kill -0 "$server" 2>/dev/null || break; sleep 0.2; done
            kill -0 "$server" 2>/dev/null && kill -KILL "$server"
            wait "$server" 2>/dev/null || true
        fi
        mountpoint -q "$root/proc" && umount "$root/proc"
        # The unpacked image is only needed while the server runs.
        mountpoint -q "$root/proc" || rm -rf --one-file-system "$root"
    }
    trap stop EXIT

    mapfile -t envs < <(inspect '{{range .Config.Env}}{{println .}}{{end}}' | sed '/^$/d')
    mapfile -t cmd < <(inspect '{{range .Config.Cmd}}{{println .}}{{end}}' | sed '/^$/d')
    user=$(inspect '{{.Config.User}}')
    workdir=$(inspect '{{.Config.WorkingDir}}')
    uid=$(awk -F: -v u="$user" '$1 == u {print $3 ":" $4}' "$root/etc/passwd")
    [ -n "$uid" ] || { echo "user $user not in the image" >&2; exit 1; }
    echo "image: CMD ${cmd[*]}; USER $user ($uid); WORKDIR $workdir; ENV ${envs[*]}"
    run_in() {  # run_in COMMAND...: as the image's user, with its environment, in its WORKDIR
        env -i "${envs[@]}" SVELIVE_PORT="$port" "$(command -v chroot)" --userspec="$uid" "$root" \
            /bin/sh -c 'cd "$0" && exec "$@"' "$workdir" "$@"
    }

    log "in the image: interpreter, PyGObject + Aravis, wheels; no build-only packages"
    run_in python3 -c '
import sys, cv2, numpy, OpenEXR, fastapi, uvicorn, gi
gi.require_version("Aravis", "0.8")
from gi.repository import Aravis
import svelive
print("python", sys.version.split()[0], "| numpy", numpy.__version__, "| cv2", cv2.__version__,
      "| gi", gi.__version__, "| Aravis", gi.get_required_version("Aravis"), "interfaces", Aravis.get_n_interfaces(),
      "| svelive", svelive.__file__)'
    run_in sh -c 'for p in python3-venv python3.11-venv python3-pip; do
        dpkg -s "$p" >/dev/null 2>&1 && { echo "build-only package $p in the image"; exit 1; }; done
        [ ! -e /opt/svelive/bin/pip ] || { echo "pip in the runtime venv"; exit 1; }
        echo "no python3-venv, python3-pip or venv pip in the image"'

    local cache=/opt/svelive/numba-cache
    echo "numba cache from the build: $(find "$root$cache" -name '*.nbc' | wc -l) compiled kernels" \
        "($(du -sh "$root$cache" | cut -f1))"
    touch "$WORK/cache.stamp"

    log "run CMD (${cmd[*]}) with SVELIVE_PORT=$port"
    # Not through run_in: $! must be the server itself (env, chroot and sh exec it).
    env -i "${envs[@]}" SVELIVE_PORT="$port" "$(command -v chroot)" --userspec="$uid" "$root" \
        /bin/sh -c 'cd "$0" && exec "$@"' "$workdir" "${cmd[@]}" > "$WORK/serve.log" 2>&1 &
    server=$!
    local url="http://127.0.0.1:$port" ok=""
    for _ in $(seq $((STARTUP_TIMEOUT * 2))); do
        kill -0 "$server" 2>/dev/null || break
        if curl -fs --max-time 2 "$url/healthz" -o "$WORK/healthz"; then ok=1; break; fi
        sleep 0.5
    done
    if [ -z "$ok" ]; then
        if kill -0 "$server" 2>/dev/null; then
            echo "the server did not answer /healthz within ${STARTUP_TIMEOUT} s; its log:" >&2
        else
            echo "the server exited before answering /healthz; its log:" >&2
        fi
        cat "$WORK/serve.log" >&2
        exit 1
    fi
    echo "GET /healthz -> $(cat "$WORK/healthz")"
    ss -ltn "sport = :$port" | tail -n +2 | awk '{print "listening on " $4}'
    sleep 2   # let a few frames through so the state shows rates
    curl -fsS --max-time 5 "$url/api/state" -o "$WORK/state.json"
    echo "GET /api/state ->"
    "$PYTHON" -m json.tool "$WORK/state.json"
    curl -fsS --max-time 10 -D "$WORK/snapshot.headers" "$url/snapshot.jpg" -o "$WORK/snapshot.jpg"
    echo "GET /snapshot.jpg -> $(grep -i '^content-type' "$WORK/snapshot.headers" | tr -d '\r'); $(file -b "$WORK/snapshot.jpg")"
    # The default command serves the colour demo camera: the preview must be a colour image.
    run_in python3 -c '
import sys, cv2, numpy as np
data = sys.stdin.buffer.read()
img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
if img is None or img.ndim != 3 or img.shape[2] != 3:
    sys.exit(f"snapshot.jpg is not a 3-channel colour image: {None if img is None else img.shape}")
b, g, r = (img[:, :, i].astype(np.int16) for i in range(3))
print(f"  decoded: {img.shape[1]}x{img.shape[0]}x{img.shape[2]} {img.dtype}, {len(data) / 1000:.1f} kB;",
      "mean B, G, R %.1f, %.1f, %.1f;" % tuple(img.reshape(-1, 3).mean(axis=0)),
      f"mean |R-G| {np.abs(r - g).mean():.1f}, |B-G| {np.abs(b - g).mean():.1f}")' < "$WORK/snapshot.jpg"
    curl -fsS --max-time 10 -D "$WORK/snapshot-exr.headers" "$url/snapshot.exr" -o "$WORK/snapshot.exr"
    echo "GET /snapshot.exr -> $(grep -i '^content-type' "$WORK/snapshot-exr.headers" | tr -d '\r'); $(stat -c %s "$WORK/snapshot.exr") bytes"
    run_in python3 -c '
import sys, numpy as np
from svelive.exr import read_exr
channels, header = read_exr(sys.stdin.buffer.read())
if sorted(channels) != ["B", "G", "R"]:
    sys.exit(f"snapshot.exr channels {sorted(channels)}, not R, G, B")
for name in "RGB":
    c = channels[name]
    print(f"  {name}: {c.shape[1]}x{c.shape[0]} {c.dtype}, min {c.min():.3g}, median {np.median(c):.3g}, max {c.max():.4g}")
standard = ("channels", "compression", "dataWindow", "displayWindow", "lineOrder", "pixelAspectRatio",
            "screenWindowCenter", "screenWindowWidth", "type")
for key, value in sorted(header.items()):
    if key not in standard:
        print(f"  {key}: {np.array2string(value, precision=4) if isinstance(value, np.ndarray) else value}")' \
        < "$WORK/snapshot.exr"
    local compiled
    compiled=$(find "$root$cache" -type f -newer "$WORK/cache.stamp" | sed "s|$root$cache/||")
    if [ -n "$compiled" ]; then
        echo "warning: serving compiled kernels the build did not (the first frames waited for them):"
        echo "$compiled" | sed 's/^/  /'
    else
        echo "numba cache: nothing compiled while serving (every kernel came from the build)"
    fi
    health=$(inspect '{{range .Config.Healthcheck.Test}}{{println .}}{{end}}' | sed -n 2p)
    if run_in sh -c "$health"; then echo "HEALTHCHECK command: exit 0"; else echo "HEALTHCHECK command failed" >&2; exit 1; fi
    log "server log"
    cat "$WORK/serve.log"
    stop
    trap - EXIT
    log "stopped; server log tail"
    tail -n 3 "$WORK/serve.log"
    log "size"
    podman images --format '{{.Repository}}:{{.Tag}} {{.Size}}' --filter reference="$IMAGE" \
        --filter reference=docker.io/library/debian:bookworm-slim
}

clean() {
    rm -rf --one-file-system "$WORK"
}

case "${1:-all}" in
    base) base ;;
    wheels) wheels ;;
    build) build ;;
    online) online ;;
    smoke) smoke ;;
    clean) clean ;;
    all) base; wheels; build; smoke ;;
    *) echo "usage: $0 [all|base|wheels|build|online|smoke|clean]" >&2; exit 2 ;;
esac
