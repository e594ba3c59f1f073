"""Small clipped lights' colour (svelive.reconstruction.colour, step c''', single frames): one colour per light,
pooled from every site the light lights, instead of the cells' (:func:`light_colours`).

A light smaller than two cells (a lamp a few pixels across) lights only some sites of each cell it falls on,
and in each cell only some colours; where it clips the longer exposure the cells keep only its unclipped sites.
Each cell's shares are then those of the few sites it saw (one cell of a 3x3 orange light on dual-ISO sees a
long row of green and blue: pure blue), and the 3x3 median of the cells, which removes colour features narrower
than two cells, does the rest: a light came out blue, green, red or white by where it fell (issue 27.1;
docs/peers.md). Here the light's sites are found from the readings and pooled, where the readings show that
pooling is right:

1. Candidates: connected groups of BLOCK x BLOCK blocks that hold a censored reading, at most two cells and a
   block on a side. Only lights that clip are taken: an unclipped light's measured readings are in the cells'
   colour already, and a first version that took every small bright feature lost 0.6 dB on StarField dim.
2. Around each, a site is *lit* where its reading x = s / e (a censored one: its bound) is at least LIT_CONTRAST
   times the background of its CFA phase (the median of that phase's uncensored readings within
   BACKGROUND_RADIUS pixels: a light is small, so most of them are its surroundings) and LIT_Z noise standard
   deviations above it. The light is the lit sites within a pixel of each other and of the candidate's
   censored ones; it is left where its box is two cells or more on a side.
3. Its colour: per channel, the mean of its uncensored lit readings; a channel with no lit reading takes the
   mean of its uncensored readings within the light's box (dark in this light: an orange light's blue); where
   the box holds none, the colour is unknown and the light is left. A channel with only censored lit readings
   takes the highlight rule's level (shares.py: the white-balanced level of the brightest measured channel, so
   a clipped highlight is neutral, never magenta); where its bound is above that level, what it means is
   ambiguous (a saturated colour, or a bright core that only that channel samples) and the light is left.
4. Only a flat light is pooled: its lit readings must agree with one level per channel within their noise
   (:func:`_flat`). On a peaked light (a star: a core site of one colour, a fainter halo of the others) each
   channel's mean says where its sites fall on the profile, not the colour: such lights keep the cells'.
5. The light's colour replaces the cells' by a garrote on its noise: chi2 = sum_c (q_c - d_c)^2 / var q_c (q, d
   the light's and the cells' colour at unit luminance sum_c n_c, var q_c from the noise model), beta = max(0,
   1 - 3 / chi2), as the package's other garrotes. Each lit pixel keeps its own channel's value, its other two
   follow the colour, and its luminance becomes sum_c n_c RGB_c.

Measured (tests/test_colour_artefacts.py's 3x3 orange lights on black at every phase, mean over the phases of
the chromaticity error; a white light scores 0.43): at -1 stop dual-ISO 0.405 -> 0.053, column-Bayer 0.404 ->
0.053, quad-Bayer 0.378 -> 0.049, assorted-4x4 0.522 -> 0.351; at -2 stops 0.376 -> 0.145 on dual-ISO. The
peer frames (benchmarks/peers.py): one light recoloured on Desk bright, none elsewhere. Cost (thread CPU, one
thread): 2 ms on the demo camera's 1920x1200 frame, about 45 us a candidate (StarField bright's 640x400 crop
holds 317: 15 ms). Single frames only: the stream does not call it (a star field would cost a live frame tens
of milliseconds).
"""

from __future__ import annotations

import cv2
import numpy as np

from svelive.reconstruction.colour.cells import CellLayout
from svelive.reconstruction.methods.base import SveInput

#: A lit site reads at least this many times the background of its CFA phase (2 stops).
LIT_CONTRAST = 4.0
#: ... and this many noise standard deviations above it.
LIT_Z = 5.0
#: Pixels around a candidate in which its background (the median reading of each CFA phase) is measured.
BACKGROUND_RADIUS = 8
#: Standard deviations of its noise within which a light's readings must agree with one level per channel.
FLAT_Z = 3.0
#: Side (pixels) of the blocks in which candidates are looked for.
BLOCK = 4
#: Degrees of freedom the garrote subtracts (three channels compared).
GARROTE_DOF = 3.0


def light_colours(inp: SveInput, luminance: np.ndarray, rgb: np.ndarray, white: np.ndarray,
                  layout: CellLayout) -> int:
    """Recolour small clipped lights in place (module docstring).

    Args:
        inp: the colour frame (``cfa`` and ``channels`` set).
        luminance: float32 (H, W), Y; updated where a light's pixels change.
        rgb: float32 (H, W, 3), camera RGB (DN at relative exposure 1); updated in place.
        white: float32 (3,), the frame's white balance (camera RGB of a neutral surface).
        layout: the chroma's cells (a light is under two cells on each side) and each channel's share n_c of the
            CFA tile.

    Returns:
        The number of lights recoloured.
    """
    if inp.cfa is None or inp.channels is None or not inp.censored.any():
        return 0
    h, w = inp.shape
    max_side = 2 * max(layout.cell) - 1
    # candidates on a grid of BLOCK x BLOCK blocks (any censored reading in a block), whose components are found
    # at a sixteenth of the frame's pixels: a full-resolution labelling cost 12 ms at 1920x1200
    near = cv2.dilate(inp.censored.view(np.uint8), np.ones((BLOCK, BLOCK), np.uint8), anchor=(0, 0))
    count, _, boxes, _ = cv2.connectedComponentsWithStats(np.ascontiguousarray(near[::BLOCK, ::BLOCK]),
                                                          connectivity=8)
    done = np.zeros((h, w), bool)
    py, px = inp.cfa.shape
    share = layout.share.astype(np.float64)
    r = BACKGROUND_RADIUS
    recoloured = 0
    for bx, by, bw, bh, _ in boxes[1:]:
        if (bw - 1) * BLOCK > max_side or (bh - 1) * BLOCK > max_side:
            continue
        y0, x0, y1, x1 = by * BLOCK, bx * BLOCK, min(h, (by + bh) * BLOCK), min(w, (bx + bw) * BLOCK)
        top, left = max(0, (y0 - r) // py * py), max(0, (x0 - r) // px * px)  # whole CFA tiles: phases hold
        rows, cols = slice(top, min(h, y1 + r)), slice(left, min(w, x1 + r))
        candidate = np.zeros((rows.stop - top, cols.stop - left), bool)
        candidate[y0 - top:y1 - top, x0 - left:x1 - left] = True
        recoloured += _recolour(inp, luminance, rgb, white, share, rows, cols, candidate, done[rows, cols], max_side)
    return recoloured


def _recolour(inp: SveInput, luminance: np.ndarray, rgb: np.ndarray, white: np.ndarray, share: np.ndarray,
              rows: slice, cols: slice, candidate: np.ndarray, done: np.ndarray, max_side: int) -> int:
    """One candidate's light in the window (rows, cols): steps 2-5 of the module docstring; ``done`` (a view)
    marks the pixels of lights already recoloured. Returns 1 if it was recoloured, else 0."""
    e = inp.exposure[rows, cols].astype(np.float64)
    s = inp.signal[rows, cols].astype(np.float64)
    censored, channels = inp.censored[rows, cols], inp.channels[rows, cols]
    x = s / e
    sd = np.sqrt(inp.sensor.signal_variance(s)) / e
    py, px = inp.cfa.shape
    hh, ww = x.shape[0] // py * py, x.shape[1] // px * px  # (the window starts on a CFA tile)
    tiles = np.where(censored, np.nan, x)[:hh, :ww].reshape(hh // py, py, ww // px, px)
    phases = np.sort(tiles.transpose(1, 3, 0, 2).reshape(py * px, -1), axis=1)  # (NaN, censored, sort last)
    counts = np.count_nonzero(~np.isnan(phases), axis=1)
    median = np.where(counts > 0, phases[np.arange(py * px), np.maximum(counts - 1, 0) // 2], np.inf).reshape(py, px)
    background = np.tile(median, (-(-x.shape[0] // py), -(-x.shape[1] // px)))[:x.shape[0], :x.shape[1]]
    floor = np.maximum(background, 0)
    lit = np.isfinite(background) & (x > LIT_CONTRAST * floor) & (x - floor > LIT_Z * sd)
    lit &= ~done
    seeds = candidate & censored & lit
    if not seeds.any():
        return 0
    # lit sites one pixel apart belong together (a pure red light lights every other pixel)
    _, labels = cv2.connectedComponents(cv2.dilate(lit.view(np.uint8), np.ones((3, 3), np.uint8)), connectivity=8)
    keep = np.zeros(labels.max() + 1, bool)
    keep[labels[seeds]] = True
    light = lit & keep[labels]
    ys, xs = np.nonzero(light)
    if np.ptp(ys) + 1 > max_side or np.ptp(xs) + 1 > max_side:
        return 0
    box = (slice(ys.min(), ys.max() + 1), slice(xs.min(), xs.max() + 1))
    colour, variance = np.zeros(3), np.zeros(3)
    bounded = np.zeros(3, bool)
    lit_by = [light & (channels == c) for c in range(3)]  # each channel's lit sites
    for c, own in enumerate(lit_by):
        measured = own & ~censored
        if measured.any():
            n = np.count_nonzero(measured)
            colour[c], variance[c] = x[measured].mean(), np.sum(sd[measured] ** 2) / n**2
        elif (own & censored).any():
            bounded[c] = True
            colour[c] = x[own & censored].max()
        else:
            dark = (channels[box] == c) & ~censored[box]
            if not dark.any():
                return 0  # the light samples no site of this channel: its colour is unknown
            n = np.count_nonzero(dark)
            colour[c], variance[c] = max(x[box][dark].mean(), 0.0), np.sum(sd[box][dark] ** 2) / n**2
    if bounded.all() or colour.max() <= 0 or not _flat(x, sd, censored, lit_by, colour, bounded):
        return 0
    measured_level = max(colour[c] / white[c] for c in range(3) if not bounded[c])
    if np.any(colour[bounded] > measured_level * white[bounded]):
        return 0  # a bound above a neutral light's level: a bright core only that channel samples, or its colour?
    colour[bounded] = measured_level * white[bounded]  # the highlight rule: the white-balanced brightest level
    window = rgb[rows, cols]
    cells = window[light].astype(np.float64).mean(axis=0)
    level, cells_level = share @ colour, share @ cells
    if level <= 0 or cells_level <= 0:
        return 0
    q, d = colour / level, cells / cells_level
    # a bound has no variance: where it moves the colour, beyond doubt
    spread = np.where(bounded, 0.0, variance) / level**2
    with np.errstate(divide="ignore", invalid="ignore"):
        chi2 = float(np.sum(np.where(q == d, 0.0, (q - d) ** 2 / spread)))
    beta = max(0.0, 1.0 - GARROTE_DOF / chi2) if chi2 > 0 else 0.0
    q = d + beta * (q - d)
    own = np.take_along_axis(window[light], channels[light][:, None].astype(np.intp), axis=-1)[:, 0]
    new = (own / q[channels[light]])[:, None] * q[None, :]
    if not np.all(np.isfinite(new)):
        return 0
    window[light] = new.astype(np.float32)
    luminance[rows, cols][light] = (new @ share).astype(np.float32)
    done |= light
    return 1


def _flat(x: np.ndarray, sd: np.ndarray, censored: np.ndarray, lit_by: list[np.ndarray], colour: np.ndarray,
          bounded: np.ndarray) -> bool:
    """Whether the light's lit readings are those of one level per channel (``colour``) within their noise: the
    sum of their squared z-scores is within the chi-square quantile at FLAT_Z normal deviations (its degrees of
    freedom: each channel's measured lit sites less one; 99.87 % at FLAT_Z = 3), and no censored lit reading's
    bound is more than FLAT_Z of its channel's deviations above that level. A peaked light (a star: a core pixel
    of one colour and a fainter halo of the others) fails it: each channel's mean then says where its sites fall
    on the profile, not the light's colour, and the cells' colour stays. With nothing to test it on, it fails
    too."""
    chi2, dof = 0.0, 0
    for c, own in enumerate(lit_by):
        measured = own & ~censored
        n = np.count_nonzero(measured)
        if n == 0 or bounded[c]:
            continue
        if n > 1:
            chi2 += float(np.sum(((x[measured] - colour[c]) / sd[measured]) ** 2))
            dof += n - 1
        lost = own & censored
        if lost.any() and np.any(x[lost] > colour[c] + FLAT_Z * np.max(sd[measured])):
            return False
    # the chi-square quantile at FLAT_Z standard normal deviations (Wilson and Hilferty's cube-root approximation)
    return dof > 0 and chi2 <= dof * (1.0 - 2.0 / (9.0 * dof) + FLAT_Z * np.sqrt(2.0 / (9.0 * dof))) ** 3
