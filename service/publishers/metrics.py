"""Prometheus exposition of the service's state: the same truths as /api/state, as metric families.

A scrape takes one snapshot of every camera's state (the dict /api/state serves)
and turns it into metric families labelled by camera; nothing is counted twice and
nothing here keeps state of its own. Stage latencies are histograms of the
pipeline's latency windows' cumulative buckets (``LatencyWindow.histogram``).
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator, Mapping
from typing import Any

from svelive.core.errors import SveliveError

try:
    from prometheus_client import CollectorRegistry, generate_latest
    from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily, HistogramMetricFamily, Metric
    from prometheus_client.exposition import CONTENT_TYPE_LATEST
    from prometheus_client.process_collector import ProcessCollector
except ImportError:  # pragma: no cover - the dependency is declared; this names it if it is missing
    CollectorRegistry = None  # type: ignore[assignment,misc]
    CONTENT_TYPE_LATEST = "text/plain; version=0.0.4; charset=utf-8"

STAGES = ("captured", "reconstructed", "encoded", "streamed")


def _counter(name: str, doc: str, labels: list[str]) -> CounterMetricFamily:
    return CounterMetricFamily(name, doc, labels=labels)


def families(snapshots: Mapping[str, dict[str, Any]],
             histograms: Mapping[str, Mapping[str, tuple[list[tuple[float, int]], float, int]]] | None = None
             ) -> list[Metric]:
    """Metric families from each camera's state.

    Args:
        snapshots: camera name -> the dict its /api/state serves.
        histograms: camera name -> stage -> (cumulative buckets [(upper bound ms, count)], sum ms, count).
    """
    frames = _counter("svelive_frames", "Frames that passed each stage, since start", ["camera", "stage"])
    fps = GaugeMetricFamily("svelive_fps", "Frames per second at each stage, recent", labels=["camera", "stage"])
    drops = _counter("svelive_drops", "Frames a watcher should have had and did not, by cause", ["camera", "cause"])
    online = GaugeMetricFamily("svelive_source_online", "1 while the camera delivers frames", labels=["camera"])
    reconnects = _counter("svelive_source_reconnects", "Times the source was reopened", ["camera"])
    clients = GaugeMetricFamily("svelive_clients", "Connected stream clients", labels=["camera", "kind"])
    motion = GaugeMetricFamily("svelive_motion_fraction", "Fraction of pixels the motion tests flagged, last frame",
                               labels=["camera"])
    info = GaugeMetricFamily("svelive_camera_info", "The camera's description (value 1)",
                             labels=["camera", "source", "pattern", "cfa", "method"])
    noise = GaugeMetricFamily("svelive_noise_estimate", "Noise model in use: gain (e-/DN), read noise (DN), "
                              "and their standard errors", labels=["camera", "quantity"])
    balance = GaugeMetricFamily("svelive_white_balance", "White-balance multipliers in use (colour cameras)",
                                labels=["camera", "channel"])
    quality = GaugeMetricFamily("svelive_live_quality_step", "Step of the live-quality ladder that runs (0: the "
                                "configured setting; higher: cheaper, while the camera's rate is not kept)",
                                labels=["camera", "mode"])
    # one series per step of the ladder, 1 for the step that runs (a state set): a label that changed with the step
    # would end one series and start another at every step
    steps = GaugeMetricFamily("svelive_live_quality", "1 for the live-quality ladder's step that runs, 0 for the "
                              "others", labels=["camera", "step_name"])
    warming = GaugeMetricFamily("svelive_warming_up", "1 while the service prepares its kernels (no frames yet; "
                                "/healthz answers 503)", labels=["camera"])
    latency = HistogramMetricFamily("svelive_stage_latency_seconds", "Time each stage took per frame",
                                    labels=["camera", "stage"])
    for name, state in snapshots.items():
        counts = state.get("frames", {})
        for stage in STAGES:
            value = counts.get(stage)
            if value is not None:
                frames.add_metric([name, stage], float(value))
        for stage, value in state.get("fps", {}).items():
            fps.add_metric([name, stage], float(value))
        for cause, value in state.get("drops", {}).items():
            drops.add_metric([name, cause], float(value))
        source = state.get("source", {})
        online.add_metric([name], 1.0 if source.get("online") else 0.0)
        reconnects.add_metric([name], float(source.get("reconnects") or 0))
        clients.add_metric([name, "mjpeg"], float(state.get("clients", 0)))
        rtsp = state.get("rtsp") or {}
        if rtsp:
            clients.add_metric([name, "rtsp"], float(rtsp.get("clients", 0)))
        if state.get("motion_fraction") is not None:
            motion.add_metric([name], float(state["motion_fraction"]))
        info.add_metric([name, str(source.get("spec", "")), str(state.get("pattern") or ""),
                         str(state.get("cfa") or "none"), str(state.get("method") or "")], 1.0)
        live = state.get("live_quality")
        if live:
            quality.add_metric([name, str(live["mode"])], float(live["step"]))
            for step in live.get("steps") or [live["name"]]:
                steps.add_metric([name, str(step)], 1.0 if step == live["name"] else 0.0)
        warming.add_metric([name], 1.0 if state.get("warming_up") else 0.0)
        for quantity, value in _noise_values(state.get("noise")):
            noise.add_metric([name, quantity], value)
        wb = state.get("white_balance") or {}
        for channel, value in zip("rgb", wb.get("multipliers") or ()):
            balance.add_metric([name, channel], float(value))
        for stage, (buckets, total_ms, count) in (histograms or {}).get(name, {}).items():
            seconds = [(_bound(le), float(n)) for le, n in buckets]
            if not seconds or seconds[-1][0] != "+Inf":
                seconds.append(("+Inf", float(count)))
            latency.add_metric([name, stage], seconds, total_ms / 1e3)
    return [frames, fps, drops, online, reconnects, clients, motion, info, noise, balance, quality, steps, warming,
            latency]


def _bound(ms: float) -> str:
    return "+Inf" if ms == float("inf") else repr(ms / 1e3)


def _noise_values(noise: Any) -> Iterator[tuple[str, float]]:
    if not isinstance(noise, Mapping):
        return
    for key in ("gain", "read_noise", "gain_sigma", "read_noise_sigma"):
        value = noise.get(key)
        if isinstance(value, (int, float)):
            yield key, float(value)


class _Snapshot:
    """A collector that yields families made beforehand (a scrape is one consistent snapshot)."""

    def __init__(self, made: Iterable[Metric]) -> None:
        self._made = list(made)

    def collect(self) -> Iterator[Metric]:
        yield from self._made


def exposition(made: Iterable[Metric], *, process: bool = True) -> bytes:
    """The Prometheus text format of ``made``, with this process's CPU, memory and file descriptors."""
    if CollectorRegistry is None:
        raise SveliveError("/metrics needs the prometheus-client package: run scripts/setup.sh")
    registry = CollectorRegistry(auto_describe=False)
    registry.register(_Snapshot(made))
    if process:
        ProcessCollector(namespace="svelive", registry=registry)
    return generate_latest(registry)
