"""A sweep's same-pixel evidence at white (:class:`_Censored`: per darker reading, how many of those pixels
read at white in a brighter frame) and the probit likelihood of it, maximised by Newton's method
(:func:`_probit_newton`), which pins a log-spline's scale at white (step 6 of svelive.calibrate.response)."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable

import numpy as np

from svelive.core.sensor import Sensor


@dataclass(frozen=True)
class _Censored:
    """Same-pixel evidence at white from a sweep: per raw code of a reading in a darker frame, how many
    of those pixels read at white in a brighter frame (one row per code and pair of frames).

    A reading at white says only that the pixel's light reached the white threshold, and the same
    pixel's reading in the darker frame says how much light that pixel had: no texture and no window
    selection come in, so these rows pin the curve's value at white against its value at the darker
    readings (the scale of the whole curve) without the windows that white removes.
    """

    m: np.ndarray          # float64 (C,), brightness of the darker reading
    log_ratio: np.ndarray  # float64 (C,), log of the brighter frame's exposure over the darker's
    total: np.ndarray      # float64 (C,), pixels with that reading
    clipped: np.ndarray    # float64 (C,), of them, those at white in the brighter frame
    pair: np.ndarray       # int (C,), index of the pair of frames (0..pairs - 1)
    threshold: float       # brightness from which a reading rounds to white
    width: np.ndarray | None = None  # float64 (C,), sd of the probit in log light (both readings' noise)


def _censored_at_white(raws: list[np.ndarray], times: np.ndarray, sensor: Sensor) -> _Censored:
    """:class:`_Censored` rows of every two frames of a sweep (the darker reading strictly between black
    and white; every pixel, whatever its neighbours, since both readings are of the same pixel).

    Args:
        raws: J (H, W) frames of one still scene.
        times: (J,) their exposure times.
    """
    white = float(sensor.white_level)
    black = float(sensor.black_level)
    # the ADC rounds: a reading is at white from half a step under it
    threshold = 1.0 - 0.5 / sensor.range_dn
    parts = []
    for j, k in _frame_pairs(times):
        dark, bright = raws[j].ravel(), raws[k].ravel()
        inside = (dark > black) & (dark < white)
        codes = dark[inside].astype(np.int64)
        total = np.bincount(codes, minlength=int(white) + 1).astype(np.float64)
        clipped = np.bincount(codes, weights=(bright[inside] >= white).astype(np.float64), minlength=total.size)
        code = np.nonzero(total)[0]
        parts.append(((code - black) / sensor.range_dn, np.full(code.size, math.log(times[k] / times[j])),
                      total[code], clipped[code], np.full(code.size, len(parts))))
    cols = [np.concatenate([p[i] for p in parts]) for i in range(5)]
    return _Censored(*cols[:4], cols[4].astype(np.int64), threshold=threshold)


def _probit_sides(z: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(log Phi(z), log Phi(-z), phi(z) / Phi(z), phi(z) / Phi(-z)) of the standard normal, float64 like
    ``z``; accurate in both tails (the smaller side from erfc), clipped at |z| = 35."""
    z = np.clip(np.asarray(z, np.float64), -35.0, 35.0)
    tail = 0.5 * np.vectorize(math.erfc, otypes=[np.float64])(np.abs(z) / math.sqrt(2.0))
    low, high = np.where(z < 0, tail, 1.0 - tail), np.where(z < 0, 1.0 - tail, tail)
    density = np.exp(-0.5 * z * z) / math.sqrt(2.0 * math.pi)
    return np.log(low), np.log(high), density / low, density / high


def _probit_newton(predictor: Callable[[np.ndarray], np.ndarray], rows: np.ndarray, start: np.ndarray,
                   total: np.ndarray, hits: np.ndarray, quadratic: tuple[np.ndarray, np.ndarray, float] | None = None,
                   steps: int = 50) -> np.ndarray:
    """Minimise ``-2 log L(p) (+ p'Np - 2 p'r + c)`` by Newton's method, L the probit likelihood of ``hits``
    out of ``total`` with ``z = predictor(p)`` linear in p with rows ``rows`` (C, n) (so z = rows @ p +
    const); ``quadratic`` = (N, r, c) of a least-squares term. Convex.

    Returns p.
    """
    normal, rhs, constant = quadratic if quadratic is not None else (np.zeros((start.size,) * 2),
                                                                      np.zeros(start.size), 0.0)

    def objective(p: np.ndarray) -> float:
        up, down, _, _ = _probit_sides(predictor(p))
        return float(p @ normal @ p - 2.0 * p @ rhs + constant - 2.0 * np.sum(hits * up + (total - hits) * down))

    p = start.copy()
    value = objective(p)
    for _ in range(steps):
        z = predictor(p)
        _, _, up, down = _probit_sides(z)
        slope = -hits * up + (total - hits) * down
        curvature = hits * up * (z + up) + (total - hits) * down * (down - z)
        gradient = 2.0 * (normal @ p - rhs) + 2.0 * rows.T @ slope
        hessian = 2.0 * normal + 2.0 * (rows.T * curvature) @ rows
        # no ridge: the weakest direction (the scale, eigenvalue ~1e-12 of the largest) is the one that matters
        step = np.linalg.lstsq(hessian, gradient, rcond=None)[0]
        if gradient @ step < 1e-9:  # Newton decrement: the objective (a chi-square) cannot fall further
            break
        t = 1.0
        while t > 1e-6:
            trial = objective(p - t * step)
            if trial <= value:
                break
            t *= 0.5
        else:
            break
        p, value = p - t * step, trial
    return p


def _frame_pairs(times: np.ndarray) -> list[tuple[int, int]]:
    """(darker, brighter) frame indices of every two frames of a sweep with different exposure times."""
    return [(a, b) for a in range(len(times)) for b in range(len(times)) if times[a] < times[b]]
