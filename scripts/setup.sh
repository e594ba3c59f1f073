#!/usr/bin/env bash
# Set up svelive on Debian 12: system packages (as root, or through sudo), then a
# virtual environment in .venv with the project and its extras installed.
#   scripts/setup.sh            the service and the library
#   scripts/setup.sh test       also what the tests need (pytest, browser, GigE fake camera)
set -euo pipefail
cd "$(dirname "$0")/.."

packages=(python3 python3-venv python3-dev gcc pkg-config libgirepository1.0-dev libcairo2-dev
          gir1.2-aravis-0.8 aravis-tools)
if [ "${1:-}" = test ]; then
    packages+=(chromium chromium-driver)
fi
missing=()
for p in "${packages[@]}"; do
    dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed" || missing+=("$p")
done
if [ ${#missing[@]} -gt 0 ]; then
    sudo_cmd=""
    [ "$(id -u)" -eq 0 ] || sudo_cmd="sudo"
    echo "installing Debian packages: ${missing[*]}"
    $sudo_cmd apt-get update -q
    DEBIAN_FRONTEND=noninteractive $sudo_cmd apt-get install -y -q "${missing[@]}"
fi

python=${PYTHON:-python3}
[ -x .venv/bin/python ] || "$python" -m venv .venv
.venv/bin/pip install -q --upgrade pip
extras="gige"
[ "${1:-}" = test ] && extras="gige,test,bench"
.venv/bin/pip install -q -e ".[${extras}]"
