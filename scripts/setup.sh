#!/usr/bin/env bash
# Set up svelive on Debian 12: system packages (as root, or through sudo), then a
# virtual environment in .venv with the project and its extras installed.
#   scripts/setup.sh            the service, the library and what the README's commands use (bench, Dask)
#   scripts/setup.sh test       also what the tests need (pytest, browser, GigE fake camera)
set -euo pipefail
cd "$(dirname "$0")/.."

# Aravis: GigE Vision cameras; GStreamer's RTSP server and x264: `svelive serve --rtsp`.
packages=(python3 python3-venv python3-dev gcc pkg-config libgirepository1.0-dev libcairo2-dev
          gir1.2-aravis-0.8 aravis-tools
          gir1.2-gst-rtsp-server-1.0 gir1.2-gst-plugins-base-1.0 gstreamer1.0-plugins-base
          gstreamer1.0-plugins-good gstreamer1.0-plugins-ugly)
if [ "${1:-}" = test ]; then
    # a browser for the viewer tests; H.264 decoders and ffmpeg as RTSP clients in the tests; dcraw, the reader
    # cr2hdr uses, for the test that it reads the DNGs benchmarks/peers.py writes
    packages+=(chromium chromium-driver gstreamer1.0-libav ffmpeg dcraw)
fi
missing=()
for p in "${packages[@]}"; do
    dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed" || missing+=("$p")
done
if [ ${#missing[@]} -gt 0 ]; then
    sudo_cmd=""
    [ "$(id -u)" -eq 0 ] || sudo_cmd="sudo"
    echo "installing Debian packages: ${missing[*]}"
    # waits (at most 5 minutes, saying so) while another apt job holds the package lock
    $sudo_cmd scripts/apt-get.sh update -q
    $sudo_cmd scripts/apt-get.sh install -y -q "${missing[@]}"
fi

python=${PYTHON:-python3}
[ -x .venv/bin/python ] || "$python" -m venv .venv
.venv/bin/pip install -q --upgrade pip
# bench and cluster: the README's commands run as written (svelive bench needs matplotlib and scikit-image,
# reconstruct-sequence --workers needs Dask)
extras="gige,bench,cluster,hdr"
[ "${1:-}" = test ] && extras="gige,test,bench,cluster,hdr"
.venv/bin/pip install -q -e ".[${extras}]"
# compile the numba kernels now (cached on disk), so that the first `svelive serve` starts in seconds
.venv/bin/python -c 'from service.commands import warm_up_kernels; warm_up_kernels("setup")'
