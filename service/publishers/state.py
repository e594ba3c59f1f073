"""The state of one camera's service as JSON (``/api/state``; ``/metrics`` reads the same dict).

Assembled here from what the pipeline's stages and ports and the camera's publishers count; nothing here keeps
state of its own. :func:`pipeline_state` is the pipeline's part (source, counters, rates, drops, latencies,
settings in use), :func:`camera_state` the whole: that, the noise model, the MJPEG publisher's clients and
rates, the RTSP publisher's (with one) and the server process. Keys and meanings: docs/service.md.
"""

from __future__ import annotations

import asyncio
import os
import time
from typing import TYPE_CHECKING, Any

import cv2
from starlette.concurrency import run_in_threadpool

from svelive.reconstruction.single import methods as method_names

if TYPE_CHECKING:  # types only: the pipeline's own ``state()`` calls pipeline_state
    from service.pipeline import Pipeline
    from service.routers import ServedCamera
    from service.settings import ServerSettings


def pipeline_state(pipeline: Pipeline) -> dict[str, Any]:
    """The pipeline's part of the state, JSON-ready (any thread)."""
    drops = pipeline.drops.snapshot()
    encoder, capture, colour = pipeline.encoder, pipeline.capture, pipeline.colour
    for cause, n in capture.source_drops().items():
        drops[f"source_{cause}"] = n
    latest = pipeline.latest()
    balance = colour.white_balance(latest)  # colour frames only
    warming = pipeline.warming_up
    config, reconstruction = pipeline.config, pipeline.reconstruction
    camera = capture.camera
    return {
        "warming_up": warming,
        "source": {
            "spec": config.source,
            **capture.status(),
            # not started yet: no source opened, nothing offline about it
            **({"state": "warming_up", "error": None} if warming else {}),
            "width": None if latest is None else int(latest.hdr.image.shape[1]),
            "height": None if latest is None else int(latest.hdr.image.shape[0]),
            "pixel_format": capture.stats.get("pixel_format"),
            # the exposure the newest frame was taken at (the camera's unit), null when the source cannot tell
            "exposure_time": getattr(capture.latest_raw(), "exposure_time", None),
        },
        "fps": {"captured": round(pipeline.captured.rate(), 2), "reconstructed": round(pipeline.reconstructed.rate(), 2),
                "encoded": round(pipeline.encoded.rate(), 2)},
        "frames": {"captured": pipeline.captured.count, "reconstructed": pipeline.reconstructed.count,
                   "encoded": pipeline.encoded.count, "tone_mapped": encoder.previews.count,
                   "not_watched": encoder.not_watched,
                   "last_frame_id": None if latest is None else latest.hdr.frame_id},
        "drops": drops,
        "dropped": sum(drops.values()),
        "latency_ms": {name: window.summary() for name, window in pipeline.latency.items()},
        "method": pipeline.quality.configured.method,
        "methods": method_names(),
        "temporal": config.temporal,
        # what runs now: the configured method and fusion, or a cheaper step while the camera's rate is not kept
        "live_quality": pipeline.quality.state(),
        "motion_fraction": reconstruction.motion_fraction,
        "response": pipeline.calibration.response_state(),
        "calibration": pipeline.calibration.job_state(),
        "mask": config.mask,
        "workers": pipeline.workers,
        "parallel_frames": reconstruction.frames,
        # a monochrome stream with fusion skips the settled bands (Reconstructor(refresh=K)); None: off
        "refresh": reconstruction.refresh_state(),
        "reconstruct_error": reconstruction.error,
        "pattern": None if camera is None else str(camera.pattern),
        "cfa": None if camera is None or camera.cfa is None else camera.cfa.name,
        "sensor": None if latest is None else {"bits": latest.camera.sensor.bits,
                                               "black_level": latest.camera.sensor.black_level,
                                               "white_level": latest.camera.sensor.white_level},
        "tone": dict(vars(encoder.tone)),
        "white_balance": None if balance is None else balance.public(),
        **{name: value for name, value in colour.public().items() if name != "white_balance"},
        "jpeg_quality": encoder.jpeg_quality,
        "preview_width": config.preview_width,
        "publisher_nice": config.publisher_nice,
        "publisher_priority": encoder.priority.public(),
        "watchers": encoder.watchers,
        "preview_watchers": encoder.preview_watchers,
        "opencv_threads": cv2.getNumThreads(),
        "uptime_s": round((time.monotonic_ns() - pipeline.started_ns) / 1e9, 1),
    }


def process_stats() -> dict[str, float]:
    """Resident memory (MB) and CPU time (s) of this process."""
    with open("/proc/self/statm") as f:
        rss_pages = int(f.read().split()[1])
    times = os.times()
    return {"rss_mb": round(rss_pages * os.sysconf("SC_PAGE_SIZE") / 2**20, 1),
            "cpu_s": round(times.user + times.system, 2)}


async def camera_state(cam: ServedCamera, settings: ServerSettings) -> dict[str, Any]:
    """The whole state of ``cam`` (on the event loop): the pipeline's, the noise model, the MJPEG and RTSP
    publishers' and the server process's."""
    out = await run_in_threadpool(pipeline_state, cam.pipeline)
    mjpeg = cam.hub.state()
    out["camera_name"] = cam.name
    out["noise"] = cam.pipeline.reconstruction.noise_state()
    out["fps"]["streamed"] = mjpeg["streamed_fps"]
    out["frames"]["streamed"] = mjpeg["streamed"]
    out["latency_ms"]["arrival_to_sent"] = mjpeg["arrival_to_sent"]
    out["clients"] = mjpeg["clients"]
    out["client_list"] = mjpeg["client_list"]
    out["drops"]["client_skipped"] = mjpeg["client_skipped"]
    if cam.rtsp is not None:
        out["rtsp"] = cam.rtsp.state()
        out["fps"]["rtsp"] = out["rtsp"]["fps"]
    out["server"] = {"tasks": len(asyncio.all_tasks()), "host": settings.host, "port": settings.port,
                     "auth": settings.token is not None, **process_stats()}
    return out


def latency_histograms(cam: ServedCamera) -> dict[str, tuple[list[tuple[float, int]], float, int]]:
    """Each stage's latency histogram of ``cam`` (``LatencyWindow.histogram``) for /metrics."""
    return {stage: window.histogram() for stage, window in cam.pipeline.latency.items()}
