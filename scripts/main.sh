#!/usr/bin/env bash
# Set up svelive on a fresh Debian 12 machine and run its main job.
set -euo pipefail
cd "$(dirname "$0")/.."
scripts/setup.sh
exec .venv/bin/svelive serve "$@"
