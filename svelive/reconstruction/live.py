"""The live settings ladder: the reconstruction settings a live stream may run, costliest and most accurate first.

A live service that cannot keep its camera's rate with the configured method and
temporal fusion steps down this ladder (service.pipeline.quality decides when);
``svelive bench --live`` charts each step's speed against its accuracy. Every step
is an ordinary ``Reconstructor(camera, method=..., temporal=...)``: nothing here
changes what a method computes.
"""

from __future__ import annotations

from dataclasses import dataclass

from svelive.core.errors import SveliveError

#: The live service's ``Reconstructor(refresh=...)`` for streams with fusion and ``adaptive`` (the top
#: step of :data:`LADDER`; svelive.reconstruction.settle): a settled band of a still view runs the method every 8th
#: frame, once per ``max_history`` frames (so its history's mean takes a fresh estimate as often as it holds
#: frames), moving and unsettled bands every frame. Chosen on ``benchmarks/settle_cost.py`` and
#: ``benchmarks/settle_accuracy.py`` (docs/benchmarks.md): on the still 1920x1200 demo K = 8 costs x0.70 of the
#: stream without it, K = 4 x0.76; on issue 26's cases both within 0.04 dB PU21 of off. Colour streams take it on
#: their folded luminance (``colour_refresh``; the service's colour reconstruction CPU a frame x0.78-0.88,
#: docs/benchmarks.md).
LIVE_REFRESH = 8

#: The method's share of the top step's CPU per frame, the part the band refresh saves on the bands it keeps:
#: ``benchmarks/settle_cost.py --refresh 4,8`` (still 1920x1200 demo, 2026-11-29) put K = 4 at x0.75 with 24.9 % of
#: the bands computed and K = 8 at x0.69 with 12.4 %: 1 - x = 0.33-0.35 of (1 - computed).
REFRESH_METHOD_SHARE = 0.34

#: ``--live-quality`` values: ``adaptive`` steps down and up the ladder, ``fixed`` keeps the configured setting.
QUALITY_MODES = ("adaptive", "fixed")


def check_live_quality(mode: str) -> None:
    """Raise a one-line SveliveError unless ``mode`` is one of QUALITY_MODES."""
    if mode not in QUALITY_MODES:
        raise SveliveError(f"live quality must be one of {', '.join(QUALITY_MODES)}, got {mode!r}")


@dataclass(frozen=True)
class LiveStep:
    """One live setting: a reconstruction method with or without temporal fusion.

    ``cost``: its CPU per frame relative to the top of :data:`LADDER` (measured with
    ``benchmarks/live_ladder.py``, without the band refresh: :meth:`cost_at`), used only to predict which
    step would fit before trying it.
    """

    method: str
    temporal: bool
    cost: float = 1.0

    @property
    def name(self) -> str:
        return f"{self.method}+fusion" if self.temporal else self.method

    def cost_at(self, method_rows: float) -> float:
        """``cost`` when the method ran on ``method_rows`` (0..1) of the frame's rows: the band refresh keeps
        settled bands, so a still view's top step can cost less than steps below it."""
        return self.cost * (1.0 - REFRESH_METHOD_SHARE * (1.0 - min(max(method_rows, 0.0), 1.0)))


#: The declared ladder, costliest first. ``cost``: CPU per frame relative to the top, the mean of monochrome and
#: colour over two runs of ``benchmarks/live_ladder.py --data ../shared/data/hdr`` (1920x1200, 2 workers,
#: 2026-11-28, the 2-core VM at load 2-5): CPU ms monochrome 102 / 76 / 64 / 33 and 92 / 71 / 62 / 34, colour
#: 188 / 173 / 121 / 98 and 151 / 131 / 118 / 98.
LADDER: tuple[LiveStep, ...] = (
    LiveStep("adaptive", True, 1.0),
    LiveStep("weighted", True, 0.83),
    LiveStep("adaptive", False, 0.68),
    LiveStep("weighted", False, 0.47),
)


def ladder_for(method: str, temporal: bool, mode: str = "adaptive") -> tuple[LiveStep, ...]:
    """The steps for a configured ``method`` and ``temporal``: that setting first, then every step of
    :data:`LADDER` below it (cheaper), without fusion where the configuration has none; ``fixed``, or a
    setting outside the ladder (``aggregate``, ``cubic``: no step is known to be cheaper than it), the
    configured setting alone."""
    check_live_quality(mode)
    names = [(step.method, step.temporal) for step in LADDER]
    if mode == "fixed" or (method, temporal) not in names:
        return (LADDER[names.index((method, temporal))] if (method, temporal) in names
                else LiveStep(method, temporal),)
    below = LADDER[names.index((method, temporal)) + 1:]
    return (LADDER[names.index((method, temporal))], *(step for step in below if temporal or not step.temporal))
