#!/usr/bin/env bash
# Set up everything the tests need on a fresh Debian 12 machine and run the whole test suite.
set -euo pipefail
cd "$(dirname "$0")/.."
scripts/setup.sh test
exec .venv/bin/python -m pytest "$@"
