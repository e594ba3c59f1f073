# svelive: live HDR video service for SVE cameras. See docs/container.md.
#   docker build -t svelive .                                  (online: wheels from PyPI)
#   docker build --build-arg WHEELS=wheels -t svelive .        (offline: wheels in ./wheels)
#   docker run --rm -p 127.0.0.1:8000:8000 svelive             -> http://127.0.0.1:8000/
# Debian's python3 (3.11) so that Debian's PyGObject (python3-gi) and the Aravis
# typelib match the interpreter; everything else comes from wheels.

FROM debian:bookworm-slim AS build
RUN apt-get update \
 && apt-get install -y --no-install-recommends python3 python3-venv ca-certificates \
 && rm -rf /var/lib/apt/lists/*
# WHEELS: a folder of the build context holding every dependency as a wheel (and
# setuptools, the project's build backend); empty: pip fetches them from PyPI.
ARG WHEELS=
COPY . /src
# --system-site-packages: the venv sees Debian's python3-gi (installed in the runtime stage).
# pip and setuptools are needed only here: leave them out of the runtime venv.
RUN python3 -m venv --system-site-packages /opt/svelive \
 && if [ -n "$WHEELS" ]; then \
      /opt/svelive/bin/pip install --no-cache-dir --no-index --find-links "/src/$WHEELS" /src; \
    else \
      /opt/svelive/bin/pip install --no-cache-dir /src; \
    fi \
 && /opt/svelive/bin/pip uninstall --yes setuptools pip
# Compile the numba kernels once here so that neither `svelive serve`'s start nor the first live
# frame does: what serve warms (every mono and colour reconstruction kernel, the preview tone maps)
# and the demo camera's render pass, compiled when the default `demo` source opens.
# numba reuses this cache on a CPU like the build machine's and recompiles into it otherwise.
# One thread for OpenCV and BLAS: the build machine may be shared.
ENV NUMBA_CACHE_DIR=/opt/svelive/numba-cache
RUN OMP_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1 /opt/svelive/bin/python -c "\
import cv2; cv2.setNumThreads(1); \
from svelive.reconstruction.warmup import warm_up; from svelive.tonemap import warm_up as warm_up_preview; \
from svelive.capture import open_source; \
warm_up(); warm_up_preview(); open_source('demo').open().close()"

FROM debian:bookworm-slim
# Runtime only: the interpreter, PyGObject, the Aravis 0.8 typelib (GigE Vision cameras) and
# GStreamer's RTSP server with x264 (`--rtsp`).
RUN apt-get update \
 && apt-get install -y --no-install-recommends python3 python3-gi gir1.2-aravis-0.8 \
      gir1.2-gst-rtsp-server-1.0 gir1.2-gst-plugins-base-1.0 gstreamer1.0-plugins-base \
      gstreamer1.0-plugins-good gstreamer1.0-plugins-ugly \
 && rm -rf /var/lib/apt/lists/* \
 && useradd --system --no-create-home --home-dir /nonexistent --shell /usr/sbin/nologin svelive
COPY --from=build /opt/svelive /opt/svelive
RUN chown -R svelive /opt/svelive/numba-cache

LABEL org.opencontainers.image.title="svelive" \
      org.opencontainers.image.description="HDR video service for cameras with spatially varying pixel exposures (SVE)" \
      org.opencontainers.image.licenses="BSD-3-Clause"
# Every `svelive serve` setting is also SVELIVE_<NAME> (docs/service.md); the command line wins
# over the environment, so the default command names no option and `-e SVELIVE_PORT=...` works.
# 0.0.0.0 inside the container is needed for port publishing: publish on the host's loopback
# (-p 127.0.0.1:8000:8000) or set SVELIVE_TOKEN before exposing it further.
ENV PATH=/opt/svelive/bin:$PATH \
    PYTHONUNBUFFERED=1 \
    NUMBA_CACHE_DIR=/opt/svelive/numba-cache \
    SVELIVE_HOST=0.0.0.0 \
    SVELIVE_PORT=8000
USER svelive
WORKDIR /tmp
EXPOSE 8000 8554
HEALTHCHECK --interval=30s --timeout=5s --start-period=300s \
  CMD python3 -c "import os, urllib.request as u; u.urlopen('http://127.0.0.1:%s/healthz' % os.environ.get('SVELIVE_PORT', '8000'), timeout=4)"
CMD ["svelive", "serve"]
