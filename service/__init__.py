"""The svelive HTTP service: live HDR reconstruction with an MJPEG preview, EXR snapshots and state.

``create_app(pipeline, settings)`` builds the FastAPI app; ``Pipeline`` runs the
capture, reconstruction and encoder threads; ``ServiceSettings`` holds the
configuration (CLI > environment > config file > defaults).
"""
