# svelive: live HDR video service for SVE cameras.
#   docker build -t svelive .                      (online: wheels from PyPI)
#   docker build --build-arg WHEELS=wheels -t svelive .   (offline: wheels in ./wheels)
#   docker run --rm -p 127.0.0.1:8000:8000 svelive  -> http://127.0.0.1:8000/
FROM debian:bookworm-slim

# Aravis (GigE Vision) through PyGObject from Debian; Python 3.11.
RUN apt-get update \
 && apt-get install -y --no-install-recommends \
      python3 python3-venv python3-gi gir1.2-aravis-0.8 ca-certificates \
 && rm -rf /var/lib/apt/lists/*

ARG WHEELS=
WORKDIR /src
COPY . /src
# --system-site-packages: the venv sees Debian's python3-gi (Aravis bindings)
RUN python3 -m venv --system-site-packages /opt/svelive \
 && if [ -n "$WHEELS" ]; then \
      /opt/svelive/bin/pip install --no-cache-dir --no-index --find-links "/src/$WHEELS" /src; \
    else \
      /opt/svelive/bin/pip install --no-cache-dir /src; \
    fi \
 && rm -rf /src \
 && useradd --system --no-create-home svelive

ENV PATH=/opt/svelive/bin:$PATH PYTHONUNBUFFERED=1
USER svelive
WORKDIR /tmp
EXPOSE 8000
HEALTHCHECK --interval=30s --timeout=5s CMD python3 -c "import urllib.request; urllib.request.urlopen('http://127.0.0.1:8000/healthz', timeout=4)"
# Inside the container 0.0.0.0 is needed for the port mapping; publish it on the host's loopback
# (-p 127.0.0.1:8000:8000) or set SVELIVE_TOKEN before exposing it further.
CMD ["svelive", "serve", "--host", "0.0.0.0", "--port", "8000"]
