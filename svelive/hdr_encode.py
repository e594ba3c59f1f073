"""HDR stills for HDR displays: a frame as a PQ or HLG AVIF and as an Ultra HDR JPEG (svelive.hdr_encode).

Small pure functions from one reconstructed frame (float32 (H, W) radiance or (H, W, 3) linear camera RGB,
DN at exposure 1) to the signal an HDR display takes, and the two encoders, both from imagecodecs (libavif
and Google's libultrahdr; the optional extra ``hdr``).

Colour: camera RGB goes to linear Rec.709 by the preview's display matrix (white balance, then the
configured colour matrix; without one, white-balanced camera RGB is taken as Rec.709), then to linear
BT.2020 by :data:`REC709_TO_BT2020` (ITU-R BT.2087), one 3x3 pass. A monochrome frame is grey in all
three channels.

Brightness: the preview tone mapper's mid-grey of the frame (svelive.monitor.mid_grey: the radiance it maps
to its key) is put where ITU-R BT.2408 puts the 18 % grey card: :data:`GREY_NITS` (26 cd/m2) for PQ, whose
reference (100 %) diffuse white is :data:`REFERENCE_WHITE_NITS` (203 cd/m2); :data:`HLG_GREY_SIGNAL`
(38 %) of the HLG signal (its reference white is 75 %). The Ultra HDR JPEG takes linear light with the
reference white at 1.0 (libultrahdr's SDR white), so mid-grey is at 26 / 203.
"""

from __future__ import annotations

import numpy as np

from svelive.core.errors import SveliveError

#: The pip extra that installs the encoders (pyproject.toml's optional dependencies).
EXTRA = "hdr"
INSTALL = f'pip install "svelive[{EXTRA}]"'

#: Linear Rec.709 RGB -> linear BT.2020 RGB (ITU-R BT.2087-0, Table 2; each row sums to 1: white stays white).
REC709_TO_BT2020 = np.array([[0.627403895934699, 0.329283038377884, 0.043313065687417],
                             [0.069097289358232, 0.919540395075459, 0.011362315566309],
                             [0.016391438875150, 0.088013307877226, 0.895595253247624]])

#: ITU-R BT.2408: the 18 % grey card and 100 % diffuse (reference) white of PQ HDR, cd/m2.
GREY_NITS = 26.0
REFERENCE_WHITE_NITS = 203.0

#: SMPTE ST 2084's peak, cd/m2.
PQ_PEAK_NITS = 10000.0

#: ITU-R BT.2408: the HLG signal of the 18 % grey card (reference white: 0.75).
HLG_GREY_SIGNAL = 0.38

#: CICP (ITU-T H.273) code points: BT.2020 primaries, the transfer of each ``transfer``, BT.2020 non-constant
#: luminance matrix coefficients.
PRIMARIES_BT2020 = 9
TRANSFERS = {"pq": 16, "hlg": 18}
MATRIX_BT2020_NCL = 9

#: Bit depths an AVIF snapshot can have.
AVIF_BITS = (10, 12)

# SMPTE ST 2084 constants
_M1, _M2 = 2610 / 16384, 2523 / 4096 * 128
_C1, _C2, _C3 = 3424 / 4096, 2413 / 4096 * 32, 2392 / 4096 * 32
# ITU-R BT.2100 HLG constants
_A = 0.17883277
_B = 1 - 4 * _A
_C = 0.5 - _A * np.log(4 * _A)


class MissingEncoder(SveliveError):
    """The encoders' library (imagecodecs, the extra ``hdr``) is not installed (one line)."""


def pq_oetf(nits: np.ndarray | float) -> np.ndarray:
    """SMPTE ST 2084 inverse EOTF: float32 signal in [0, 1] of display light ``nits`` (cd/m2, clipped to
    0..10 000), any shape."""
    y = np.clip(np.asarray(nits, np.float32) / np.float32(PQ_PEAK_NITS), 0, 1)
    p = y ** np.float32(_M1)
    return ((np.float32(_C1) + np.float32(_C2) * p) / (1 + np.float32(_C3) * p)) ** np.float32(_M2)


def hlg_oetf(light: np.ndarray | float) -> np.ndarray:
    """ITU-R BT.2100 HLG OETF: float32 signal in [0, 1] of normalised scene light ``light`` (clipped to 0..1),
    any shape."""
    e = np.clip(np.asarray(light, np.float32), 0, 1)
    with np.errstate(invalid="ignore", divide="ignore"):
        high = np.float32(_A) * np.log(np.maximum(12 * e - np.float32(_B), np.float32(1e-12))) + np.float32(_C)
    return np.where(e <= np.float32(1 / 12), np.sqrt(3 * e), high).astype(np.float32)


def hlg_light_of_signal(signal: float) -> float:
    """The normalised scene light (0..1) whose HLG signal is ``signal`` (0..1): inverse of :func:`hlg_oetf`."""
    if signal <= 0.5:
        return signal * signal / 3
    return float((np.exp((signal - _C) / _A) + _B) / 12)


def bt2020_matrix(display_matrix: np.ndarray | None) -> np.ndarray | None:
    """float64 (3, 3) from camera RGB to linear BT.2020: :data:`REC709_TO_BT2020` @ ``display_matrix`` (camera
    RGB -> linear Rec.709, svelive.monitor.display_matrix); None for a monochrome frame (None given)."""
    return None if display_matrix is None else REC709_TO_BT2020 @ np.asarray(display_matrix, np.float64)


def bt2020_nits(image: np.ndarray, display_matrix: np.ndarray | None, grey: float) -> np.ndarray:
    """float32 (H, W, 3) linear BT.2020 display light in cd/m2, mid-grey ``grey`` at :data:`GREY_NITS`.

    Args:
        image: float32 (H, W) radiance or (H, W, 3) camera RGB, DN at exposure 1.
        display_matrix: float (3, 3) camera RGB -> linear Rec.709 for colour (svelive.monitor.display_matrix);
            None for mono.
        grey: mid-grey (svelive.monitor.mid_grey), > 0, in the image's unit (display luminance for colour).

    Negative values (a colour matrix's out-of-gamut) become 0.
    """
    import cv2

    scale = GREY_NITS / float(grey)
    if image.ndim == 2:
        plane = np.maximum(np.asarray(image, np.float32) * np.float32(scale), np.float32(0))
        return np.repeat(plane[:, :, None], 3, axis=2)
    matrix = (bt2020_matrix(display_matrix) * scale).astype(np.float32)
    out = cv2.transform(np.ascontiguousarray(image, np.float32), matrix)
    return np.maximum(out, np.float32(0), out=out)


def signal(nits: np.ndarray, transfer: str) -> np.ndarray:
    """float32 non-linear signal in [0, 1] of display light ``nits`` (cd/m2, any shape): PQ, or HLG with
    :data:`GREY_NITS` at :data:`HLG_GREY_SIGNAL` (scene light above 1, about 4.4 stops over mid-grey, clips)."""
    transfer = check_transfer(transfer)
    if transfer == "pq":
        return pq_oetf(nits)
    return hlg_oetf(np.asarray(nits, np.float32) * np.float32(hlg_light_of_signal(HLG_GREY_SIGNAL) / GREY_NITS))


def quantise(values: np.ndarray, bits: int) -> np.ndarray:
    """uint16 full-range codes round(values * (2^bits - 1)) of a signal in [0, 1]."""
    top = (1 << bits) - 1
    return np.rint(np.clip(values, 0, 1) * np.float32(top)).astype(np.uint16)


def check_transfer(transfer: str) -> str:
    """``transfer`` lower-cased, or a one-line SveliveError naming the choices."""
    name = str(transfer).strip().lower()
    if name not in TRANSFERS:
        raise SveliveError(f"transfer must be one of {', '.join(TRANSFERS)}, got {transfer!r}")
    return name


def check_bits(bits: int) -> int:
    if bits not in AVIF_BITS:
        raise SveliveError(f"bits must be one of {', '.join(map(str, AVIF_BITS))}, got {bits}")
    return bits


def _codecs():
    try:
        import imagecodecs
    except ImportError:
        raise MissingEncoder(f"HDR snapshots need imagecodecs: {INSTALL}") from None
    return imagecodecs


def available() -> bool:
    """Whether the encoders can be imported."""
    try:
        _codecs()
    except MissingEncoder:
        return False
    return True


def encode_avif(image: np.ndarray, display_matrix: np.ndarray | None, grey: float, *, transfer: str = "pq",
                bits: int = 10, quality: int = 90, speed: int = 8) -> bytes:
    """An AVIF (libavif via imagecodecs) of a frame: ``bits``-bit full-range YUV 4:4:4, BT.2020 primaries
    and matrix, PQ or HLG (CICP 9/16/9 or 9/18/9 in the file). Arguments as :func:`bt2020_nits`; ``quality``
    0..100, ``speed`` 0 (slowest) ..10."""
    transfer, bits = check_transfer(transfer), check_bits(bits)
    codecs = _codecs()
    codes = quantise(signal(bt2020_nits(image, display_matrix, grey), transfer), bits)
    return codecs.avif_encode(codes, level=quality, speed=speed, bitspersample=bits,
                              primaries=PRIMARIES_BT2020, transfer=TRANSFERS[transfer], matrix=MATRIX_BT2020_NCL)


def encode_ultrahdr(image: np.ndarray, display_matrix: np.ndarray | None, grey: float, *,
                    quality: int = 90) -> bytes:
    """An Ultra HDR JPEG (libultrahdr via imagecodecs): an SDR JPEG that libultrahdr tone-maps from the HDR
    picture, plus a gain map as a second JPEG (MPF) with ISO 21496-1 metadata. The HDR picture given is
    linear BT.2020 with the reference white (:data:`REFERENCE_WHITE_NITS`) at 1.0. Arguments as
    :func:`bt2020_nits`."""
    codecs = _codecs()
    nits = bt2020_nits(image, display_matrix, grey)
    rgba = np.empty(nits.shape[:2] + (4,), np.float16)
    np.multiply(np.minimum(nits, np.float32(PQ_PEAK_NITS)), np.float32(1 / REFERENCE_WHITE_NITS), out=rgba[:, :, :3],
                casting="unsafe")
    rgba[:, :, 3] = 1
    uhdr = codecs.ULTRAHDR
    return codecs.ultrahdr_encode(rgba, level=quality, gamut=uhdr.CG.BT_2100, transfer=uhdr.CT.LINEAR)
