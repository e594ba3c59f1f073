"""Publishers of the pipeline's frames to the outside, one module per kind, each over the pipeline's ports and
stages: ``mjpeg`` (the MJPEG fan-out), ``rtsp`` (H.264 over RTSP), ``snapshot`` (the EXR and JPEG snapshots),
``state`` (the JSON state) and ``metrics`` (the state in Prometheus's format). The routers only call them."""
