"""The options of a response fit (:class:`ResponseFitConfig`) and the sweeps' default knot count."""

from __future__ import annotations

from dataclasses import dataclass

#: knots of the log-spline a sweep's fit is offered by default (ResponseFitConfig.max_knots): held-out error
#: flattens from about 6 knots on, and 12 follow a film's toe and shoulder (docs/calibration.md)
SWEEP_KNOTS = 12


@dataclass(frozen=True)
class ResponseFitConfig:
    """Options of :func:`fit_response`.

    Attributes:
        max_degree: highest polynomial degree tried (1..10).
        window: side of the local window, in tiles (odd, >= 3).
        flat_quantile: a window is flat when its variance is below this quantile
            of what noise alone would give.
        folds: number of spatial folds for the held-out degree choice.
        fold_block: side, in windows, of the square blocks assigned to one fold.
        min_locations: fewest flat locations with two or more usable exposures.
        min_span: least width of the measured brightness range.
        refine_ratios: re-estimate the intermediate exposure ratios from the data.
        max_uncertainty: largest standard error of the fitted curve (fraction of full
            scale) inside the measured range.
        coverage_bins, coverage_count: the measured range is made of brightness bins
            (``coverage_bins`` over [0, 1]) each holding at least ``coverage_count``
            ends of equations; a gap in the data ends it.
        seed: seed of the fold assignment.
        max_equations: with several frames, locations are left out at random beyond this
            many ratio equations (time and memory grow with them; one frame is never cut).
        max_knots: knots of the log-spline model (:data:`SWEEP_KNOTS` by default; below 2: none, the
            polynomials alone), offered with that many knots and as a power law (2 knots), which then
            compete with the polynomials by held-out error on sweeps without a common exposure ratio
            (never on one frame). With it, sweeps recover S-shaped curves within 1 % at 8 and 12 bits on
            the benchmark's photographs (0.6-6.5 % with polynomials alone), and a gamma camera on a
            narrow range (BrightRings) within 0.06 % (3.5-10.4 %); it moves polynomial cameras' fits by
            up to 0.05 % (docs/calibration.md).
        dark_snr: when the log-spline is offered, equations whose darker window value is under
            this many single-reading noise standard deviations are left out (for every model).
        rounding_tolerance: when the log-spline is offered, the held-out errors that choose among the
            models count only equations whose darker value is at least half a quantisation step divided
            by this (0.01: 50 DN): there rounding, whatever the noise, moves it by less than this
            fraction. Rounding leaves an error that every window of one brightness shares, which a
            flexible model follows and held-out locations (sharing it) cannot reveal.
    """

    max_degree: int = 6
    window: int = 3
    flat_quantile: float = 0.95
    folds: int = 5
    fold_block: int = 8
    min_locations: int = 100
    min_span: float = 0.3
    refine_ratios: bool = False
    max_uncertainty: float = 0.01
    coverage_bins: int = 16
    coverage_count: int = 1
    seed: int = 0
    max_equations: int = 250_000
    max_knots: int = SWEEP_KNOTS
    dark_snr: float = 3.0
    rounding_tolerance: float = 0.01
