"""Monitoring HDR frames as HDR: a pixel's radiance, log2 histograms, clipping and exposure maps.

Small pure functions over one reconstructed frame (svelive.core.frame.HdrFrame's ``image``: float32
(H, W) radiance, or (H, W, 3) linear camera RGB, in DN at relative exposure 1) and the camera it
was reconstructed with. The service calls them once per frame for the viewers that ask
(service/routers/monitor.py); nothing here keeps state.

Two levels bound what a frame can tell, both in the frame's unit:

- :func:`clip_level`: the radiance at which the shortest exposure's readings are censored
  (``Sensor.censor_level / e_min``). Above it every exposure of a pixel was clipped, and the
  reconstruction gives the lower bound the censored readings imply (exactly this level or more:
  ``svelive.reconstruction.methods.base.censored_lower_bound``). For colour, a pixel is clipped
  when its brightest channel is there: where every channel is censored the joint reconstruction
  sets the channels to a neutral white at the largest bound
  (svelive/reconstruction/colour/highlights.py), which puts the brightest at or above the level.
- :func:`noise_floor`: the radiance whose signal in the longest exposure equals the sensor's
  signal-independent noise (read noise and quantisation, ``sqrt(Sensor.floor_variance) / e_max``):
  below it no exposure measures the pixel with an SNR of 1 or more.

"Stops from mid-grey" use the preview tone mapper's mid-grey: the radiance it maps to its key,
``2^(log2 average - exposure_ev)`` (svelive.tonemap.curve_constants), here from the frame's own
statistics (:func:`mid_grey`), which the tone mapper's smoothed ones follow.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from svelive.core.camera import Camera
from svelive.core.errors import SveliveError
from svelive.jit import kernel
from svelive.tonemap import ToneSettings, frame_statistics, luminance_weights
from svelive.whitebalance import ColourSettings, WhiteBalance, exr_output, output_matrix

#: A histogram samples every ``stride``-th row and column, the smallest stride that leaves at most this many pixels.
MAX_SAMPLES = 300_000

#: Histogram bins per stop.
BINS_PER_STOP = 4

#: The false-colour exposure map: (lowest stop from mid-grey, RGB) per band, ascending; a band runs to the next one's
#: lowest stop. Pixels clipped in every exposure take :data:`CLIPPED_RGB`, pixels with no light (<= 0) black.
FALSE_COLOUR: tuple[tuple[float, tuple[int, int, int]], ...] = (
    (-math.inf, (72, 0, 110)),
    (-6.0, (30, 40, 220)),
    (-4.0, (0, 140, 255)),
    (-2.0, (0, 170, 90)),
    (-0.5, (128, 128, 128)),
    (0.5, (150, 210, 40)),
    (2.0, (255, 225, 0)),
    (4.0, (255, 130, 0)),
    (6.0, (230, 20, 20)),
)
CLIPPED_RGB = (255, 0, 255)

#: Overlay colour (RGB) of the motion mask.
MOTION_RGB = (0, 230, 255)

#: The confidence overlay's levels: (lowest signal-to-noise ratio L / sigma, RGB), ascending; confidence c = SNR /
#: (1 + SNR), 0 where the value is only a lower bound (clipped in every exposure). Below SNR 1 the noise is as large
#: as the value; 9 is a tenth of it, 99 a hundredth.
CONFIDENCE_LEVELS: tuple[tuple[float, tuple[int, int, int]], ...] = (
    (0.0, (230, 20, 20)),
    (1.0, (255, 150, 0)),
    (9.0, (240, 230, 0)),
    (99.0, (0, 190, 60)),
)


def exposure_range(camera: Camera) -> tuple[float, float]:
    """(shortest, longest) relative exposure of the camera's pattern (its per-pixel map where it has one)."""
    pattern = camera.require_pattern()
    low, high = float(pattern.tile.min()), float(pattern.tile.max())
    if pattern.pixel_map is not None:
        low, high = min(low, float(pattern.pixel_map.min())), max(high, float(pattern.pixel_map.max()))
    return low, high


def clip_level(camera: Camera) -> float:
    """Radiance (DN at exposure 1) at and above which a pixel is clipped in every exposure (see the module)."""
    return float(camera.sensor.censor_level) / exposure_range(camera)[0]


def noise_floor(camera: Camera) -> float:
    """Radiance (DN at exposure 1) whose signal in the longest exposure equals the read and quantisation noise."""
    return math.sqrt(camera.sensor.floor_variance) / exposure_range(camera)[1]


def display_matrix(balance: WhiteBalance | None, colour: ColourSettings) -> np.ndarray | None:
    """float32 (3, 3) from camera RGB to the preview's linear display RGB (white balance, then the colour matrix),
    as the encoder gives the tone mapper; None for a monochrome frame (``balance`` None)."""
    return None if balance is None else output_matrix(balance.multipliers, colour.matrix)


def luminance(image: np.ndarray, matrix: np.ndarray | None = None) -> np.ndarray:
    """float32 (H, W): ``image`` itself when (H, W); for (H, W, 3) the display luminance the tone mapper measures
    (Rec. 709 weights after ``matrix``, :func:`svelive.tonemap.luminance_weights`)."""
    if image.ndim == 2:
        return image
    weights = luminance_weights(matrix).reshape(1, 3)
    return cv2.transform(np.ascontiguousarray(image, np.float32), weights).reshape(image.shape[:2])


def mid_grey(image: np.ndarray, tone: ToneSettings, matrix: np.ndarray | None = None) -> float | None:
    """The radiance (DN at exposure 1, display luminance for colour) the tone mapper maps to its key for this
    frame: ``2^(log2 average - exposure_ev)``; None when the frame has no positive pixel.

    Args:
        image: float32 (H, W) or (H, W, 3) camera RGB.
        tone: the tone mapping settings (``exposure_ev``, ``white_percentile``).
        matrix: for colour, :func:`display_matrix`.
    """
    stats = frame_statistics(image, tone.white_percentile, matrix)
    if stats is None:
        return None
    return float(2.0 ** (stats[0] - tone.exposure_ev))


def brightest(image: np.ndarray) -> np.ndarray:
    """float32 (H, W): the image, or for (H, W, 3) its largest channel."""
    if image.ndim == 2:
        return image
    return np.maximum(np.maximum(image[:, :, 0], image[:, :, 1]), image[:, :, 2])


def clipped_mask(image: np.ndarray, level: float) -> np.ndarray:
    """bool (H, W): pixels clipped in every exposure (brightest channel >= ``level``, :func:`clip_level`)."""
    return brightest(image) >= np.float32(level)


def stops(values: np.ndarray | float, grey: float) -> np.ndarray:
    """float32 log2(values / grey): stops from mid-grey ``grey`` (> 0); -inf where a value is <= 0."""
    values = np.asarray(values, np.float32)
    with np.errstate(divide="ignore", invalid="ignore"):
        out = np.log2(np.maximum(values, np.float32(0)) / np.float32(grey))
    return out.astype(np.float32, copy=False)


def check_pixel(shape: tuple[int, ...], x: int, y: int) -> None:
    """A one-line SveliveError unless (x, y) (column, row) is a pixel of a frame of ``shape`` (H, W[, 3])."""
    height, width = shape[0], shape[1]
    if not 0 <= x < width:
        raise SveliveError(f"x={x} is outside the frame: 0..{width - 1}")
    if not 0 <= y < height:
        raise SveliveError(f"y={y} is outside the frame: 0..{height - 1}")


def pixel_readout(image: np.ndarray, x: int, y: int, *, balance: WhiteBalance | None, colour: ColourSettings,
                  grey: float | None, clip: float, floor: float, motion: np.ndarray | None = None,
                  confidence: np.ndarray | None = None) -> dict[str, object]:
    """What the frame says at pixel (x, y) (column, row), JSON-ready.

    Args:
        image: float32 (H, W) or (H, W, 3) camera RGB, DN at exposure 1.
        balance, colour: the white balance and colour settings the EXR snapshot uses: the values are
            :func:`svelive.whitebalance.exr_output` of the pixel, the EXR's channels (``Y``, or ``R``,
            ``G``, ``B`` in ``colour.output_space``), so they equal the snapshot's at that pixel.
        grey: :func:`mid_grey` (None: no EV).
        clip, floor: :func:`clip_level`, :func:`noise_floor`.
        motion: bool (H, W) or None; confidence: float32 (H, W) in [0, 1] or None.

    Returns:
        ``{"x", "y", "values": {channel: float}, "luminance", "ev", "clipped", "below_noise_floor",
        "motion", "confidence"}``; ``luminance`` is in the preview's display space (its mid-grey's unit),
        ``ev`` log2(luminance / grey) (None when it is 0 or there is no mid-grey).
    """
    check_pixel(image.shape, x, y)
    crop = image[y:y + 1, x:x + 1]
    channels, _ = exr_output(crop, balance, colour)
    lum = float(luminance(crop, display_matrix(balance, colour))[0, 0])
    top = float(brightest(crop)[0, 0])
    ev = None
    if grey is not None and lum > 0:
        ev = round(float(stops(lum, grey)), 4)
    return {
        "x": x, "y": y,
        "values": {name: float(plane[0, 0]) for name, plane in channels.items()},
        "luminance": lum,
        "ev": ev,
        "clipped": bool(top >= np.float32(clip)),
        "below_noise_floor": bool(top < np.float32(floor)),
        "motion": None if motion is None else bool(motion[y, x]),
        "confidence": None if confidence is None else float(confidence[y, x]),
    }


def sample_stride(shape: tuple[int, ...], max_samples: int = MAX_SAMPLES) -> int:
    """The smallest stride s >= 1 such that every s-th row and column of a frame of ``shape`` leave <= max_samples."""
    height, width = shape[0], shape[1]
    stride = 1
    while -(-height // stride) * -(-width // stride) > max_samples:
        stride += 1
    return stride


@dataclass(frozen=True)
class Histogram:
    """A log2-radiance histogram of one frame (or of every ``stride``-th row and column of it).

    Attributes:
        edges: float64 (B + 1,), log2 of radiance (DN at exposure 1); bin i holds log2 values in
            [edges[i], edges[i + 1]), the first bin also everything below, the last everything above.
        counts: {channel: int64 (B,)}: ``Y`` for mono, ``R``, ``G``, ``B`` (camera RGB) for colour.
        zero: {channel: count of pixels <= 0} (no log); counts[c].sum() + zero[c] == pixels.
        pixels: pixels sampled; stride: the sampling step (1: every pixel).
        clipped: fraction of the sampled pixels clipped in every exposure (:func:`clipped_mask`).
        below_noise_floor: fraction whose brightest channel is below :func:`noise_floor`.
        clip_level, noise_floor: the two levels, DN at exposure 1.
    """

    edges: np.ndarray
    counts: dict[str, np.ndarray]
    zero: dict[str, int]
    pixels: int
    stride: int
    clipped: float
    below_noise_floor: float
    clip_level: float
    noise_floor: float

    def to_dict(self) -> dict[str, object]:
        return {"edges_log2": [round(float(e), 4) for e in self.edges], "bins_per_stop": BINS_PER_STOP,
                "counts": {c: v.tolist() for c, v in self.counts.items()}, "zero": self.zero,
                "pixels": self.pixels, "stride": self.stride, "clipped": self.clipped,
                "below_noise_floor": self.below_noise_floor, "clip_level": self.clip_level,
                "noise_floor": self.noise_floor}


def histogram_edges(clip: float, floor: float) -> np.ndarray:
    """float64 bin edges in log2 radiance, :data:`BINS_PER_STOP` per stop, from 2 stops below the noise floor to
    1 stop above the clip level (whole stops)."""
    low = math.floor(math.log2(floor)) - 2
    high = max(math.ceil(math.log2(clip)) + 1, low + 1)
    return low + np.arange((high - low) * BINS_PER_STOP + 1) / BINS_PER_STOP


def histogram(image: np.ndarray, clip: float, floor: float, max_samples: int = MAX_SAMPLES) -> Histogram:
    """The log2-radiance histogram of ``image`` (float32 (H, W) or (H, W, 3)) per channel, with the fractions
    clipped in every exposure and below the noise floor (:func:`clip_level`, :func:`noise_floor`).

    Frames of more than ``max_samples`` pixels are sampled on a regular grid (:func:`sample_stride`:
    1920x1200 takes every 3rd row and column, 256 000 pixels): the fractions' sampling error is then about
    sqrt(f (1 - f) / 256 000), 0.07 % at f = 15 %.
    """
    stride = sample_stride(image.shape, max_samples)
    sample = np.ascontiguousarray(image[::stride, ::stride])
    edges = histogram_edges(clip, floor)
    names = ("Y",) if sample.ndim == 2 else ("R", "G", "B")
    planes = (sample,) if sample.ndim == 2 else tuple(cv2.split(sample))
    bins = edges.size - 1
    counts, zero = {}, {}
    for name, plane in zip(names, planes):
        positive = plane[plane > 0]
        index = ((np.log2(positive) - np.float32(edges[0])) * np.float32(BINS_PER_STOP)).astype(np.int64)
        np.clip(index, 0, bins - 1, out=index)
        counts[name] = np.bincount(index, minlength=bins).astype(np.int64)
        zero[name] = int(plane.size - positive.size)
    top = planes[0] if len(planes) == 1 else np.maximum(np.maximum(planes[0], planes[1]), planes[2])
    pixels = int(top.size)
    return Histogram(edges, counts, zero, pixels, stride,
                     clipped=float(np.count_nonzero(top >= np.float32(clip))) / pixels,
                     below_noise_floor=float(np.count_nonzero(top < np.float32(floor))) / pixels,
                     clip_level=clip, noise_floor=floor)


#: Low bits of a float32 dropped to index the band table (as svelive.tonemap's curve: steps of 0.4 % in radiance).
BAND_SHIFT = 15

#: Bits of :func:`overlay_map`: the low four hold the band, these two the masks, the top two the confidence level.
CLIPPED_BIT = 16
MOTION_BIT = 32
CONFIDENCE_SHIFT = 6


def band_table(grey: float) -> np.ndarray:
    """uint8 table of the false-colour band (0: no light, i + 1: band i of :data:`FALSE_COLOUR`) of every float32
    radiance, indexed by ``float32 bits >> BAND_SHIFT``; ``grey`` > 0 is mid-grey. A value's band is that of
    the middle of its table bin: exact to 0.4 % of the radiance."""
    index = np.arange(1 << (32 - BAND_SHIFT), dtype=np.uint32)
    with np.errstate(invalid="ignore", over="ignore"):
        centres = ((index << BAND_SHIFT) | np.uint32(1 << (BAND_SHIFT - 1))).view(np.float32)
        table = (centres > 0).astype(np.uint8)  # negative and NaN bins: 0
        for stop, _ in FALSE_COLOUR[1:]:
            table += centres >= np.float32(grey * 2.0 ** stop)
    table[0] = 0  # the bin of +0 (and of denormals below 2^-133): no light
    return table


def overlay_map(image: np.ndarray, grey: float | None, clip: float, motion: np.ndarray | None = None,
                matrix: np.ndarray | None = None, confidence: np.ndarray | None = None) -> np.ndarray:
    """Every overlay of a frame in one byte per pixel, uint8 (H, W): the false-colour band of its display
    luminance (low four bits; :func:`band_table` of mid-grey ``grey``, 0 where the luminance is 0, and all 0
    when ``grey`` is None), | :data:`CLIPPED_BIT` where it is clipped in every exposure (brightest channel >=
    ``clip``), | :data:`MOTION_BIT` where ``motion`` (bool (H, W) or None), | the index of its level of
    :data:`CONFIDENCE_LEVELS` << :data:`CONFIDENCE_SHIFT` (0 without ``confidence``).

    Args:
        image: float32 (H, W) radiance, or (H, W, 3) camera RGB (DN at exposure 1).
        matrix: for colour, :func:`display_matrix` (the luminance the tone mapper measures).
        confidence: float32 (H, W) in [0, 1] (SNR / (1 + SNR)), or None.

    One compiled pass (about 1 ms for 1920x1200 mono, 3 ms colour, on one core).
    """
    pixels = np.ascontiguousarray(image, np.float32)
    channels = 1 if pixels.ndim == 2 else 3
    weights = luminance_weights(matrix) if channels == 3 else np.ones(3, np.float32)
    table = band_table(grey) if grey is not None else np.zeros(1 << (32 - BAND_SHIFT), np.uint8)
    moving = np.zeros(1, np.uint8) if motion is None else np.ascontiguousarray(motion).view(np.uint8).reshape(-1)
    sure = (np.zeros(1, np.float32) if confidence is None
            else np.ascontiguousarray(confidence, np.float32).reshape(-1))
    # the levels' lowest confidences, c = SNR / (1 + SNR), the first (0) left out: every value is at least it
    bounds = np.array([snr / (1 + snr) for snr, _ in CONFIDENCE_LEVELS[1:]], np.float32)
    out = np.empty(pixels.shape[:2], np.uint8)
    _overlay(pixels.reshape(-1), channels, np.ascontiguousarray(weights, np.float32), table, BAND_SHIFT,
             np.float32(clip), moving, motion is not None, sure, confidence is not None, bounds, out.reshape(-1))
    return out


@kernel
def _overlay(pixels: np.ndarray, channels: int, weights: np.ndarray, table: np.ndarray, shift: int,
             clip: np.float32, moving: np.ndarray, has_motion: bool, sure: np.ndarray, has_confidence: bool,
             bounds: np.ndarray, out: np.ndarray) -> None:
    """out[i] = band | clipped bit | motion bit | confidence level of pixel i of ``pixels`` (float32 (channels N,),
    interleaved); the level: how many of ``bounds`` the confidence reaches."""
    zero = np.float32(0.0)
    buffer = np.empty(1, np.float32)
    bits = buffer.view(np.uint32)
    for i in range(out.size):
        if channels == 1:
            lum = pixels[i]
            top = lum
        else:
            r, g, b = pixels[3 * i], pixels[3 * i + 1], pixels[3 * i + 2]
            lum = weights[0] * r + weights[1] * g + weights[2] * b
            top = r if r > g else g
            top = top if top > b else b
        buffer[0] = lum if lum > zero else zero
        value = table[bits[0] >> shift]
        if top >= clip:
            value |= 16
        if has_motion and moving[i]:
            value |= 32
        if has_confidence:
            level = 0
            for bound in bounds:
                level += sure[i] >= bound
            value |= level << 6
        out[i] = value


def overlay_legend() -> dict[str, object]:
    """How to read :func:`overlay_map`, JSON-ready: ``bands`` (byte & 15: 0 no light, i + 1 the band
    ``{"from": stop or None, "to": stop or None, "rgb": [r, g, b]}`` of :data:`FALSE_COLOUR`, stops from
    mid-grey), ``clipped`` and ``motion`` (``{"bit": mask of the byte, "rgb": [r, g, b]}``), ``confidence``
    (``{"shift": s, "levels": [{"snr_from": lowest SNR, "snr_to": next or None, "rgb": [r, g, b]}]}``: level
    byte >> s, present in maps made with confidence)."""
    bands: list[dict[str, object]] = [{"from": None, "to": None, "rgb": [0, 0, 0], "no_light": True}]
    for i, (stop, rgb) in enumerate(FALSE_COLOUR):
        upper = FALSE_COLOUR[i + 1][0] if i + 1 < len(FALSE_COLOUR) else None
        bands.append({"from": None if stop == -math.inf else stop, "to": upper, "rgb": list(rgb)})
    return {"bands": bands, "band_mask": 15, "clipped": {"bit": CLIPPED_BIT, "rgb": list(CLIPPED_RGB)},
            "motion": {"bit": MOTION_BIT, "rgb": list(MOTION_RGB)},
            "confidence": {"shift": CONFIDENCE_SHIFT, "levels": [
                {"snr_from": snr, "snr_to": CONFIDENCE_LEVELS[i + 1][0] if i + 1 < len(CONFIDENCE_LEVELS) else None,
                 "rgb": list(rgb)} for i, (snr, rgb) in enumerate(CONFIDENCE_LEVELS)]}}
