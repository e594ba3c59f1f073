#!/usr/bin/env bash
# Set up everything the tests need on a fresh Debian 12 machine and run the whole test suite.
# With arguments, they go to pytest as they are (one run: scripts/test.sh tests/test_cli.py -x).
# Without, the tests that only compute run on two workers (pytest-xdist, a file per worker at a time),
# then the tests marked serial (tests/conftest.py: a camera streaming over loopback, RTSP, live
# frame rates, a browser) run alone, on a machine no other test is loading.
set -euo pipefail
cd "$(dirname "$0")/.."
scripts/setup.sh test
if [ "$#" -gt 0 ]; then
  exec .venv/bin/python -m pytest "$@"
fi
status=0
.venv/bin/python -m pytest -n 2 --dist loadfile -m "not serial" || status=$?
.venv/bin/python -m pytest -m serial || status=$((status > 0 ? status : $?))
exit "$status"
