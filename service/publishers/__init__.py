"""Publishers of the pipeline's frames to the outside: one module per kind (MJPEG here; EXR snapshots and
the state are served by the routers straight from the pipeline's newest frame)."""
