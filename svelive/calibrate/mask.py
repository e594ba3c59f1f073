"""The exposure mask from flat fields: per-tile-position exposures, vignetting and per-pixel deviation.

Flat fields are frames of a uniformly lit target. Pixel x of flat j reads
``F_j(x) = s_j m(x)`` DN above black plus noise, with s_j the flat's (unknown)
brightness and m(x) the pixel's exposure: the mask cell's transmittance times
the lens's vignetting. Readings that are saturated or too dark are left out,
so flats at several brightness levels together serve every exposure level; the
rank-one factorisation is fitted by alternating weighted least squares with
Poisson weights.

m is then split into ``tile_exposure[position] * vignetting(x) * deviation(x)``:
a smooth 2-D polynomial for the vignetting (maximum 1), the median per tile
position for the exposures (the lowest 1), and the per-pixel rest. The product,
in those units, is the per-pixel exposure map for
:meth:`svelive.core.pattern.Pattern.with_pixel_map`.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.polynomial import polynomial as P

from svelive.core.atomic import atomic_path
from svelive.core.errors import SveliveError
from svelive.core.sensor import Sensor


@dataclass(frozen=True)
class MaskConfig:
    """Options of :func:`estimate_mask`.

    Attributes:
        min_signal: fraction of the range (white - black) below which a reading is too dark to use.
        iterations: alternating least-squares iterations.
        vignetting_degree: total degree of the 2-D polynomial vignetting surface.
        max_cell_spread: largest robust relative spread of the per-pixel deviation
            within one tile position; above it the flats do not repeat with the tile.
    """

    min_signal: float = 0.02
    iterations: int = 30
    vignetting_degree: int = 4
    max_cell_spread: float = 0.15


@dataclass(frozen=True)
class MaskEstimate:
    """A calibrated exposure mask.

    Attributes:
        pixel_map: float32 (H, W), exposure of every pixel, relative (tile_exposures * vignetting * deviation).
        tile_exposures: float64 (th, tw), exposure of each tile position, the lowest 1.
        vignetting: float32 (H, W), smooth falloff, maximum 1.
        deviation: float32 (H, W), per-pixel deviation from tile exposure times vignetting (median 1 per position).
        flat_levels: float64 (N,), relative brightness of every flat.
        coverage: int (H, W), number of flats in which the pixel was usable.
    """

    pixel_map: np.ndarray
    tile_exposures: np.ndarray
    vignetting: np.ndarray
    deviation: np.ndarray
    flat_levels: np.ndarray
    coverage: np.ndarray


def parse_tile(text: str) -> tuple[int, int]:
    """``"HxW"`` (e.g. ``"2x2"``) to (rows, columns)."""
    try:
        h, w = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise SveliveError(f"tile must be written HxW, e.g. 2x2, got {text!r}") from None
    if h < 1 or w < 1:
        raise SveliveError(f"tile {text!r}: both sides must be >= 1")
    return h, w


def _vignetting_surface(ratio: np.ndarray, weight: np.ndarray, degree: int) -> np.ndarray:
    """Least-squares 2-D polynomial (total degree ``degree``) fitted to ``ratio``, float64 (H, W)."""
    h, w = ratio.shape
    y = np.linspace(-1.0, 1.0, h)
    x = np.linspace(-1.0, 1.0, w)
    step = max(1, int(np.sqrt(h * w / 40000)))
    ys, xs = np.meshgrid(y[::step], x[::step], indexing="ij")
    terms = [(i, j) for i in range(degree + 1) for j in range(degree + 1 - i)]
    A = np.stack([ys.ravel() ** i * xs.ravel() ** j for i, j in terms], axis=1)
    wt = weight[::step, ::step].ravel()
    coef, *_ = np.linalg.lstsq(A * wt[:, None], ratio[::step, ::step].ravel() * wt, rcond=None)
    cmat = np.zeros((degree + 1, degree + 1))
    for (i, j), c in zip(terms, coef):
        cmat[i, j] = c
    return P.polygrid2d(y, x, cmat)


def estimate_mask(flats: list[np.ndarray], tile: tuple[int, int], sensor: Sensor,
                  config: MaskConfig = MaskConfig()) -> MaskEstimate:
    """Per-pixel exposure map from flat fields.

    Args:
        flats: one or more (H, W) raw frames of a uniformly lit target, DN including
            black, all the same size; brightness may differ between them.
        tile: (rows, columns) of the exposure tile.
        sensor: black and white level.
        config: options.
    """
    if not flats:
        raise SveliveError("mask calibration needs at least one flat-field frame")
    shape = np.shape(flats[0])
    th, tw = tile
    if len(shape) != 2:
        raise SveliveError(f"flat fields must be single-channel 2-D frames, got shape {shape}")
    for i, f in enumerate(flats):
        if np.shape(f) != shape:
            raise SveliveError(f"flat {i + 1} is {np.shape(f)[1]}x{np.shape(f)[0]}, flat 1 is {shape[1]}x{shape[0]}")
    if shape[0] < 2 * th or shape[1] < 2 * tw:
        raise SveliveError(f"a {th}x{tw} tile does not fit twice into a {shape[1]}x{shape[0]} frame")
    black, white = float(sensor.black_level), float(sensor.white_level)
    low = config.min_signal * sensor.range_dn
    signal = np.stack([np.asarray(f, np.float64) - black for f in flats])
    valid = (signal >= low) & (signal < sensor.censor_level)
    for i in range(len(flats)):
        frac = valid[i].mean()
        if frac < 0.01:
            sat = float(np.mean(signal[i] + black >= white))
            what = "saturated" if sat > 0.5 else "too dark"
            raise SveliveError(f"flat {i + 1} is {what} almost everywhere ({frac:.1%} usable pixels): "
                               f"light flats so that readings lie between {config.min_signal:.0%} of the range and white")
    coverage = valid.sum(axis=0)
    if np.any(coverage == 0):
        n = int(np.sum(coverage == 0))
        raise SveliveError(f"{n} pixels are saturated or too dark in every flat: add flats at other brightness "
                           "levels so that every exposure is read between dark and white in at least one")
    # alternating weighted least squares for F_j = s_j m, Poisson weights 1 / F
    weight = np.where(valid, 1.0 / np.maximum(signal, 1.0), 0.0)
    s = np.ones(len(flats))
    m = np.sum(weight * signal, axis=0) / np.sum(weight, axis=0)
    for _ in range(config.iterations):
        s = np.sum(weight * signal * m, axis=(1, 2)) / np.sum(weight * m * m, axis=(1, 2))
        m_new = np.sum(weight * signal * s[:, None, None], axis=0) / np.sum(weight * s[:, None, None] ** 2, axis=0)
        done = np.max(np.abs(m_new / m - 1)) < 1e-7
        m = m_new
        if done:
            break
    # split m into tile exposures, vignetting and per-pixel deviation
    h, w = shape
    reps = (-(-h // th), -(-w // tw))
    pos = np.arange(th * tw).reshape(th, tw)
    pos_map = np.tile(pos, reps)[:h, :w]
    vig = np.ones(shape)
    tile_exp = np.ones(th * tw)
    info = coverage.astype(np.float64)
    for _ in range(3):
        ratio = m / vig
        tile_exp = np.array([np.median(ratio[pos_map == p]) for p in range(th * tw)])
        vig = _vignetting_surface(m / tile_exp[pos_map], info, config.vignetting_degree)
    vig_scale = float(vig.max())
    vig /= vig_scale
    tile_exp = tile_exp * vig_scale
    deviation = m / (tile_exp[pos_map] * vig)
    for p in range(th * tw):
        d = deviation[pos_map == p]
        spread = 1.4826 * np.median(np.abs(d - np.median(d)))
        if spread > config.max_cell_spread:
            raise SveliveError(f"the flats do not repeat with a {th}x{tw} tile (pixels of tile position "
                               f"{p // tw},{p % tw} spread {spread:.0%}): check --tile against the sensor's pattern")
    unit = float(tile_exp.min())
    pixel_map = (m / unit).astype(np.float32)
    return MaskEstimate(pixel_map=pixel_map, tile_exposures=(tile_exp / unit).reshape(th, tw),
                        vignetting=vig.astype(np.float32), deviation=deviation.astype(np.float32),
                        flat_levels=s * unit, coverage=coverage)


def save_mask(mask: MaskEstimate, path: str | os.PathLike) -> Path:
    """Write ``mask`` as .npz (temporary file, then rename: svelive.core.atomic)."""
    with atomic_path(path) as tmp, open(tmp, "wb") as f:
        np.savez_compressed(f, pixel_map=mask.pixel_map, tile_exposures=mask.tile_exposures,
                            vignetting=mask.vignetting, deviation=mask.deviation,
                            flat_levels=mask.flat_levels, coverage=mask.coverage)
    return Path(path)


def load_mask(path: str | os.PathLike) -> np.ndarray:
    """Per-pixel exposure map, float32 (H, W), from a mask file (``svelive calibrate mask``),
    for :meth:`svelive.core.pattern.Pattern.with_pixel_map`."""
    path = Path(path)
    try:
        with np.load(path) as data:
            pixel_map = np.asarray(data["pixel_map"], dtype=np.float32)
    except (OSError, ValueError) as exc:
        raise SveliveError(f"{path}: not a readable mask file ({exc})") from None
    except KeyError:
        raise SveliveError(f"{path}: mask file has no 'pixel_map' array") from None
    if pixel_map.ndim != 2 or not np.all(np.isfinite(pixel_map)) or np.any(pixel_map <= 0):
        raise SveliveError(f"{path}: pixel_map must be a 2-D array of finite exposures > 0")
    return pixel_map
