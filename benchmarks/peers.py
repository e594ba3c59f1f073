"""Peer benchmark: svelive's default colour reconstruction against cr2hdr, Magic Lantern's dual-ISO converter.

    scripts/build-cr2hdr.sh /path/to/magiclantern_simplified      # once: out/cr2hdr/cr2hdr (docs/peers.md)
    python benchmarks/peers.py -o out/peers.json                  # every RGB image of ../shared/data/hdr
    python benchmarks/peers.py --quick                            # two images

Dual-ISO frames (RGGB, exposures 1/1/8/8 by line pairs, 12 bits, the colour
benchmark's sensor and simulation: svelive.bench.colour) of central crops
(640x400) of the HDR images, bright and 5 stops dim. Each raw frame is also
written as the 14-bit DNG a Canon dual-ISO shot converts to (black 2048,
optical-black margins left and top, 12-bit DN times 3), which cr2hdr reads; its
CFA output is developed with OpenCV's demosaicing, bilinear or edge-aware,
whichever scores better on the frame. Both are scored on the same frames
against the RGB truth:

- per-site PU21-PSNR: each pixel's own CFA channel only (no interpolated value);
- all-channel PU21-PSNR: R, G and B of every pixel;
- the median (r, b) chromaticity error of the brightest 1 % of unclipped pixels;
- time per frame: svelive in-process (median of runs, prepare + reconstruction,
  one OpenCV thread), cr2hdr one run of the program (wall and CPU time, with the
  dcraw and exiftool it calls).

cr2hdr's output is in its own unit: one factor per frame (the median ratio to
the truth over well-exposed unclipped sites) takes it to the truth's unit, a help
svelive does not get. Without a built cr2hdr (or dcraw, exiftool) the script says
so in one line and exits with status 2.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import resource
import shutil
import subprocess
import sys
import tempfile
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Callable

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))  # this checkout, not an editable install's

from svelive.bench.colour import DEFAULT_LABEL, ColourCondition, ColourSetting, data_scenes, time_colour  # noqa: E402
from svelive.bench.scenes import BENCH_SENSOR, NOISE_LEVELS, default_data_dir  # noqa: E402
from svelive.core.cfa import ColourFilter  # noqa: E402
from svelive.core.errors import SveliveError  # noqa: E402
from svelive.core.sensor import Sensor  # noqa: E402
from svelive.metrics import display_scale, luminance, pu21_encode, pu21_psnr  # noqa: E402
from svelive.reconstruction.colour import joint  # noqa: E402
from svelive.reconstruction.input import prepare  # noqa: E402
from svelive.reconstruction.methods.base import SveInput  # noqa: E402
from svelive.reconstruction.single import method_spec  # noqa: E402

#: Where scripts/build-cr2hdr.sh puts the binary by default.
DEFAULT_CR2HDR = ROOT / "out" / "cr2hdr" / "cr2hdr"
#: The programs cr2hdr runs.
RUNTIME_TOOLS = ("dcraw", "exiftool")
#: --quick: a lamp-lit desk (small bright light) and a landscape, where present.
QUICK_IMAGES = ("Desk", "MtTamWest")
#: OpenCV demosaicing variants tried on cr2hdr's output: name -> conversion code suffix.
DEMOSAICS = {"bilinear": "", "edge-aware": "_EA"}
#: DNG tag codes (TIFF/EP and DNG 1.4 specifications).
TAG = {"Make": 271, "Model": 272, "CFARepeatPatternDim": 33421, "CFAPattern": 33422, "DNGVersion": 50706,
       "DNGBackwardVersion": 50707, "UniqueCameraModel": 50708, "CFAPlaneColor": 50710, "CFALayout": 50711,
       "BlackLevelRepeatDim": 50713, "BlackLevel": 50714, "WhiteLevel": 50717, "ColorMatrix1": 50721,
       "AsShotNeutral": 50728, "CalibrationIlluminant1": 50778, "ActiveArea": 50829}
PHOTOMETRIC_CFA = 32803
#: XYZ (D65) to linear sRGB: the benchmark takes camera RGB as linear sRGB, so this is its ColorMatrix1.
XYZ_TO_SRGB = ((3.2406, -1.5372, -0.4986), (-0.9689, 1.8758, 0.0415), (0.0557, -0.2040, 1.0570))


@dataclass(frozen=True)
class CanonLayout:
    """How a simulated 12-bit frame is stored as a Canon-like 14-bit raw for cr2hdr.

    cr2hdr takes the black level of every row from the left optical-black columns and a
    column drift from the top optical-black rows ((top - 11) & ~3 onwards), and assumes
    14-bit data with black near 2048 (Canon bodies).
    """

    left: int = 128  # optical-black columns
    top: int = 40  # optical-black rows; a multiple of 4 keeps the line-pair phase
    black: int = 2048  # 14-bit DN
    step: int = 3  # 14-bit DN per 12-bit DN: white 4095 -> 14333, Canon-like, below 16383
    model: str = "Canon EOS 5D Mark III"  # a body cr2hdr knows

    def __post_init__(self) -> None:
        if self.top % 4 or self.left % 2 or self.top < 20 or self.left < 24:
            raise SveliveError(f"optical-black margins {self.left}x{self.top}: left even >= 24, top a multiple "
                               "of 4 >= 20")

    def white(self, sensor: Sensor) -> int:
        """14-bit white level of ``sensor``'s full scale."""
        return self.black + self.step * int(round(sensor.range_dn))


@dataclass(frozen=True)
class PeerConfig:
    """What a peer benchmark run covers."""

    images: tuple[str, ...] = ()  # image stems; empty: every RGB image of the data directory
    crop: tuple[int, int] = (400, 640)  # (rows, columns) of the central crop, at most the image
    noise_levels: tuple[str, ...] = tuple(NOISE_LEVELS)
    layout: str = "dual-iso"
    repeats: int = 3  # svelive timing runs per frame (median, after a warm-up)
    seed: int = 0
    site_chroma: bool = False  # svelive with the opt-in chroma per site (colour.joint's site_chroma)
    directional: bool = False  # svelive with the directional demosaicing stage (colour.joint's directional)


@dataclass(frozen=True)
class SiteChromaSetting(ColourSetting):
    """The joint default with chroma per site (``--site-chroma``)."""

    def run(self, inp: SveInput) -> np.ndarray:
        return joint(inp, method_spec(self.method), site_chroma=True).estimate.image


@dataclass(frozen=True)
class DirectionalSetting(ColourSetting):
    """The joint default with the directional demosaicing stage (``--directional``)."""

    def run(self, inp: SveInput) -> np.ndarray:
        return joint(inp, method_spec(self.method), directional=True).estimate.image


# ----- the DNG -------------------------------------------------------------------------------

def canon_raw(raw: np.ndarray, sensor: Sensor, layout: CanonLayout, rng: np.random.Generator) -> np.ndarray:
    """A 12-bit frame (uint16 (H, W), DN with ``sensor``'s black) as a Canon-like 14-bit raw, uint16
    (top + H, left + W): the frame at the bottom right, optical black (read noise only, not clipped
    at black, as a sensor with a pedestal delivers it) in the margins."""
    h, w = raw.shape
    out = np.empty((layout.top + h, layout.left + w), np.float64)
    out[:] = np.rint(rng.normal(0.0, sensor.effective_read_noise, out.shape))
    out[layout.top:, layout.left:] = raw.astype(np.float64) - sensor.black_level
    return np.clip(layout.black + layout.step * out, 0, 2**14 - 1).astype(np.uint16)


def dng_tags(shape: tuple[int, int], cfa: ColourFilter, layout: CanonLayout, white: int) -> list[tuple]:
    """tifffile ``extratags`` of a 14-bit CFA DNG of ``shape`` (rows, cols) with ``layout``'s margins."""
    th, tw = cfa.shape
    matrix = [v for row in XYZ_TO_SRGB for x in row for v in (int(round(x * 10000)), 10000)]
    return [(TAG["Make"], 2, 0, layout.model.split(" ", 1)[0], True), (TAG["Model"], 2, 0, layout.model, True),
            (TAG["DNGVersion"], 1, 4, (1, 4, 0, 0), True), (TAG["DNGBackwardVersion"], 1, 4, (1, 1, 0, 0), True),
            (TAG["UniqueCameraModel"], 2, 0, layout.model, True),
            (TAG["CFARepeatPatternDim"], 3, 2, (th, tw), True),
            (TAG["CFAPattern"], 1, th * tw, tuple(int(c) for c in cfa.tile.ravel()), True),
            (TAG["CFAPlaneColor"], 1, 3, (0, 1, 2), True), (TAG["CFALayout"], 3, 1, 1, True),
            (TAG["BlackLevelRepeatDim"], 3, 2, (1, 1), True), (TAG["BlackLevel"], 4, 1, layout.black, True),
            (TAG["WhiteLevel"], 4, 1, white, True),
            (TAG["ActiveArea"], 4, 4, (layout.top, layout.left, shape[0], shape[1]), True),
            (TAG["ColorMatrix1"], 10, 9, tuple(matrix), True), (TAG["CalibrationIlluminant1"], 3, 1, 21, True),
            (TAG["AsShotNeutral"], 5, 3, (1, 1, 1, 1, 1, 1), True)]


def write_dng(path: Path, raw14: np.ndarray, cfa: ColourFilter, layout: CanonLayout, white: int) -> None:
    """Write ``raw14`` (uint16 (H, W), margins included) as an uncompressed 14-bit CFA DNG.

    ``cfa``: the colour filter in the phase of the raw's top-left pixel (margins included).
    """
    import tifffile

    # 14-bit values in 16-bit samples, as uncompressed DNGs of Canon raws store them.
    tifffile.imwrite(path, raw14, photometric=PHOTOMETRIC_CFA, software="svelive benchmarks/peers.py",
                     metadata=None, subfiletype=0, extratags=dng_tags(raw14.shape, cfa, layout, white))


@dataclass
class DngRaw:
    """The CFA image of a DNG: values uint16 (H, W) with margins, black and white level in its DN,
    ActiveArea (top, left, bottom, right), CFA tile (channel indices, uint8)."""

    values: np.ndarray
    black: float
    white: float
    active: tuple[int, int, int, int]
    cfa: np.ndarray


def read_dng(path: Path) -> DngRaw:
    """The first CFA image of a DNG (IFD0 or a SubIFD, as cr2hdr writes it), with its levels."""
    import tifffile

    with tifffile.TiffFile(path) as tif:
        pages = [p for top in tif.pages for p in (top, *(top.pages or ()))]
        page = next((p for p in pages if p.photometric == PHOTOMETRIC_CFA), None)
        if page is None:
            raise SveliveError(f"{path}: holds no CFA image")
        tags = {t.code: t.value for t in page.tags}
        values = page.asarray()

        def first(code: int, default: float) -> float:
            v = tags.get(code, default)
            return float(np.mean(v)) if isinstance(v, (tuple, list)) else float(v)

        active = tuple(int(v) for v in tags.get(TAG["ActiveArea"], (0, 0, *values.shape)))
        dim = tuple(int(v) for v in tags[TAG["CFARepeatPatternDim"]])
        tile = np.frombuffer(bytes(tags[TAG["CFAPattern"]]), np.uint8).reshape(dim)
        return DngRaw(values, first(TAG["BlackLevel"], 0), first(TAG["WhiteLevel"], 2**16 - 1),
                      active, tile)  # type: ignore[arg-type]


# ----- cr2hdr --------------------------------------------------------------------------------

def cr2hdr_problem(binary: Path) -> str | None:
    """Why cr2hdr cannot run here (one line), or None."""
    if not (binary.is_file() and os.access(binary, os.X_OK)):
        return (f"cr2hdr is not built ({binary} missing): run scripts/build-cr2hdr.sh /path/to/magiclantern_simplified"
                " (docs/peers.md), or pass --cr2hdr PATH")
    missing = [t for t in RUNTIME_TOOLS if shutil.which(t) is None]
    if missing:
        return (f"cr2hdr needs {' and '.join(missing)} on PATH: scripts/apt-get.sh install -y "
                "--no-install-recommends dcraw libimage-exiftool-perl")
    return None


@dataclass
class PeerRun:
    """One cr2hdr run: its output DNG (None when it made none), wall and CPU seconds, what it printed."""

    output: Path | None
    wall_s: float
    cpu_s: float
    log: str


def run_cr2hdr(binary: Path, dng: Path) -> PeerRun:
    """Run cr2hdr on ``dng`` (a lowercase .dng; it writes NAME.DNG beside it) with default settings."""
    output = dng.with_suffix(".DNG")
    output.unlink(missing_ok=True)  # a kept earlier output must not pass for this run's
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    start = time.perf_counter()
    done = subprocess.run([str(binary), dng.name], cwd=dng.parent, capture_output=True, text=True, errors="replace")
    wall = time.perf_counter() - start
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    ok = done.returncode == 0 and output.is_file() and output != dng
    return PeerRun(output if ok else None, wall, cpu, (done.stdout + done.stderr).strip())


def active_crop(dng: DngRaw, layout: CanonLayout, shape: tuple[int, int]) -> np.ndarray:
    """cr2hdr's output CFA over the frame: uint16 (H, W), black included, in its own unit."""
    top, left = dng.active[:2]
    if (top, left) != (layout.top, layout.left):
        raise SveliveError(f"cr2hdr's output moved the active area to {top}, {left}")
    return np.ascontiguousarray(dng.values[top:top + shape[0], left:left + shape[1]])


def develop(values: np.ndarray, black: float, cfa: ColourFilter) -> dict[str, np.ndarray]:
    """RGB of a Bayer CFA image (uint16 (H, W), black included) by each OpenCV demosaicing, float32
    (H, W, 3), black subtracted (after interpolating: the pedestal passes through unchanged)."""
    return {name: cv2.demosaicing(values, getattr(cv2, f"COLOR_Bayer{cfa.name}2RGB{suffix}")).astype(np.float32)
            - np.float32(black) for name, suffix in DEMOSAICS.items()}


def fit_scale(estimate: np.ndarray, truth: np.ndarray, clip: float, display: float) -> float:
    """The factor taking ``estimate`` (per site, float (H, W)) to ``truth``'s unit (per site, DN at
    exposure 1) that maximises the per-site PU21-PSNR at the display scale ``display``: searched within a
    stop of the median ratio over the unclipped sites brighter than the median one, to 0.01 stop.

    A single factor only: where cr2hdr's output is not proportional to the scene (a misjudged ISO
    difference) no factor fits, and the best one is taken."""
    ok = (truth < clip) & (truth > 0)
    bright = ok & (truth >= np.median(truth[ok])) & (estimate > 0)
    if not np.any(bright):
        raise SveliveError("no well-exposed site to match cr2hdr's output level to the truth")
    best = float(np.exp(np.median(np.log(truth[bright] / estimate[bright]))))
    reference = pu21_encode(truth * display)

    def error(factor: float) -> float:
        return float(np.mean((pu21_encode(estimate * (factor * display)) - reference) ** 2))

    for stops in (1.0, 0.1):
        best = min(best * 2.0 ** np.linspace(-stops, stops, 21), key=error)
    return float(best)


def iso_difference(log: str) -> float | None:
    """The ISO difference (EV) cr2hdr reports having measured (its line ``ISO difference  : 3.03 EV``)."""
    found = re.search(r"^ISO difference\s*:\s*([-\d.]+) EV", log, re.MULTILINE)
    return float(found.group(1)) if found else None


# ----- scores --------------------------------------------------------------------------------

@dataclass
class Scores:
    """One peer on one frame: PU21-PSNR (dB) per site and over all channels, the brightest-1 %
    chromaticity error, seconds per frame; for cr2hdr also its CPU seconds, the demosaicing chosen,
    the factor fitted to its output, the ISO difference it measured (EV; the frames' is 3), or why it
    failed (then the scores are NaN)."""

    pu21_site: float
    pu21_rgb: float
    chroma_p1: float
    seconds: float = float("nan")
    cpu_seconds: float | None = None
    demosaic: str | None = None
    scale: float | None = None
    iso_ev: float | None = None
    error: str | None = None


def sites(rgb: np.ndarray, cfa: ColourFilter) -> np.ndarray:
    """Each pixel's own CFA channel of ``rgb`` (H, W, 3): float32 (H, W)."""
    channels = cfa.channel_map(rgb.shape[:2])[..., None].astype(np.intp)
    return np.take_along_axis(rgb, channels, axis=2)[..., 0].astype(np.float32)


def chroma_error(estimate: np.ndarray, truth: np.ndarray, clip: float, fraction: float = 0.01) -> float:
    """Median distance between the (r, b) = (R, B) / (R + G + B) chromaticities of ``estimate`` and ``truth``
    (float (H, W, 3)) over the brightest ``fraction`` (truth luminance) of the pixels with every truth
    channel below ``clip`` (the radiance that saturates the shortest exposure)."""
    ok = np.all(truth < clip, axis=2) & (truth.sum(axis=2) > 0)
    y = luminance(truth)[ok]
    if y.size == 0:
        return float("nan")
    keep = y >= np.quantile(y, 1.0 - fraction)

    def rb(rgb: np.ndarray) -> np.ndarray:
        rgb = rgb[ok][keep].astype(np.float64)
        return rgb[:, [0, 2]] / np.maximum(rgb.sum(axis=1, keepdims=True), 1e-12)

    return float(np.median(np.linalg.norm(rb(estimate) - rb(truth), axis=1)))


def scores(rgb: np.ndarray, site_values: np.ndarray, truth: np.ndarray, cfa: ColourFilter, clip: float) -> Scores:
    """Per-site and all-channel PU21-PSNR (every value at the scale that takes the truth's luminance to
    the display, as svelive.metrics.pu21_psnr_colour) and the brightest-1 % chromaticity error of an
    estimate ``rgb`` (H, W, 3) with ``site_values`` (H, W), against ``truth`` (H, W, 3)."""
    scale = display_scale(luminance(truth))
    return Scores(pu21_psnr(site_values, sites(truth, cfa), scale=scale), pu21_psnr(rgb, truth, scale=scale),
                  chroma_error(rgb, truth, clip))


# ----- the benchmark -------------------------------------------------------------------------

def central_crop(image: np.ndarray, rows: int, cols: int, period: int = 4) -> np.ndarray:
    """The central (rows, cols) of ``image`` (H, W, ...), each at most the image's, whole ``period`` tiles."""
    h, w = image.shape[:2]
    rows, cols = min(rows, h) // period * period, min(cols, w) // period * period
    y, x = (h - rows) // 2, (w - cols) // 2
    return image[y:y + rows, x:x + cols]


@dataclass
class PeerRow:
    """One frame: both peers' scores (cr2hdr's None when it was not run)."""

    image: str
    noise: str
    shape: tuple[int, int]
    svelive: Scores
    cr2hdr: Scores | None = None


@dataclass(frozen=True)
class FrameSetup:
    """What both peers of a frame share: the colour filter, the clipping radiance, the truth."""

    cfa: ColourFilter
    clip: float  # radiance (DN at exposure 1) that saturates the shortest exposure
    truth: np.ndarray  # float32 (H, W, 3)


def score_svelive(raw: np.ndarray, condition: ColourCondition, setup: FrameSetup, repeats: int,
                  site_chroma: bool = False, directional: bool = False) -> Scores:
    """svelive's default colour reconstruction of ``raw`` (uint16 (H, W)), scored and timed; with ``site_chroma``
    the opt-in chroma per site, with ``directional`` the directional demosaicing stage."""
    kind = SiteChromaSetting if site_chroma else DirectionalSetting if directional else ColourSetting
    setting = kind(DEFAULT_LABEL, "joint")
    camera = condition.camera()
    rgb = setting.run(prepare(raw, camera))
    got = scores(rgb, sites(rgb, setup.cfa), setup.truth, setup.cfa, setup.clip)
    got.seconds = time_colour(setting, raw, camera, repeats) / 1e3
    return got


def score_cr2hdr(binary: Path, dng: Path, setup: FrameSetup, layout: CanonLayout) -> Scores:
    """cr2hdr run on ``dng``, its CFA output scaled to the truth's unit and developed by the better
    OpenCV demosaicing (all-channel PU21)."""
    run = run_cr2hdr(binary, dng)
    if run.output is None:
        nan = float("nan")
        last = "\n".join(run.log.splitlines()[-4:])
        return Scores(nan, nan, nan, run.wall_s, run.cpu_s, error=last or "cr2hdr wrote no output")
    out = read_dng(run.output)
    values = active_crop(out, layout, setup.truth.shape[:2])
    mosaic = values.astype(np.float32) - np.float32(out.black)
    scale = fit_scale(mosaic, sites(setup.truth, setup.cfa), setup.clip, display_scale(luminance(setup.truth)))
    best: Scores | None = None
    for name, rgb in develop(values, out.black, setup.cfa).items():
        got = scores(rgb * np.float32(scale), mosaic * np.float32(scale), setup.truth, setup.cfa, setup.clip)
        if best is None or got.pu21_rgb > best.pu21_rgb:
            best, best.demosaic = got, name
    assert best is not None
    best.seconds, best.cpu_seconds, best.scale, best.iso_ev = run.wall_s, run.cpu_s, scale, iso_difference(run.log)
    return best


def run_frame(name: str, scene: np.ndarray, noise: str, config: PeerConfig, binary: Path | None,
              workdir: Path, layout: CanonLayout) -> PeerRow:
    """Simulate one frame of ``scene`` (float32 (H, W, 3)), reconstruct it with svelive and (``binary``
    given) cr2hdr, score both."""
    condition = ColourCondition(config.layout, noise)
    frame = condition.simulate(condition.radiance(scene), config.seed)
    levels = condition.camera().require_pattern().levels
    setup = FrameSetup(ColourFilter.parse(condition.cfa), BENCH_SENSOR.range_dn / float(min(levels)), frame.truth)
    row = PeerRow(name, noise, frame.raw.shape, score_svelive(frame.raw, condition, setup, config.repeats,
                                                                  config.site_chroma, config.directional))
    if binary is not None:
        dng = workdir / f"{name}-{noise}.dng"
        raw14 = canon_raw(frame.raw, BENCH_SENSOR, layout, np.random.default_rng(config.seed + 1))
        write_dng(dng, raw14, setup.cfa, layout, layout.white(BENCH_SENSOR))
        row.cr2hdr = score_cr2hdr(binary, dng, setup, layout)
    return row


def frame_line(row: PeerRow) -> str:
    """One progress line of a finished frame."""
    line = f"{row.image} {row.noise}: svelive {row.svelive.pu21_rgb:.2f} dB {row.svelive.seconds:.2f} s"
    peer = row.cr2hdr
    if peer is None:
        return line
    if peer.error:
        return f"{line}; cr2hdr failed: {peer.error.splitlines()[-1]}"
    return f"{line}; cr2hdr {peer.pu21_rgb:.2f} dB ({peer.demosaic}) {peer.seconds:.2f} s"


def run_peers(scenes: dict[str, np.ndarray], config: PeerConfig, binary: Path | None,
              workdir: Path, layout: CanonLayout = CanonLayout(),
              log: Callable[[str], None] = print) -> list[PeerRow]:
    """Every scene (name -> float32 (H, W, 3) linear RGB) at every noise level; one progress line a frame."""
    cv2.setNumThreads(1)
    rows = []
    total = len(scenes) * len(config.noise_levels)
    for name, scene in scenes.items():
        crop = np.ascontiguousarray(central_crop(scene, *config.crop))
        for noise in config.noise_levels:
            rows.append(run_frame(name, crop, noise, config, binary, workdir, layout))
            log(f"[{len(rows)}/{total}] {frame_line(rows[-1])}")
    return rows


def summary(rows: list[PeerRow]) -> dict[str, object]:
    """Over the frames cr2hdr converted: mean PU21, median chromaticity error and times, and the frames
    where svelive is below cr2hdr + 2 dB (all channels) or worse in chromaticity (and above 0.01)."""
    done = [r for r in rows if r.cr2hdr is not None and not r.cr2hdr.error]
    out: dict[str, object] = {"frames": len(rows), "converted": len(done),
                              "cr2hdr_failed": [f"{r.image} {r.noise}" for r in rows if r.cr2hdr and r.cr2hdr.error]}
    for key, agg in (("pu21_site", np.mean), ("pu21_rgb", np.mean), ("chroma_p1", np.median),
                     ("seconds", np.median), ("cpu_seconds", np.median)):
        for peer in ("svelive", "cr2hdr"):
            values = [getattr(getattr(r, peer), key) for r in done]
            out[f"{peer}_{key}"] = float(agg(values)) if values and None not in values else None
    out["below_target_pu21"] = [f"{r.image} {r.noise}" for r in done
                                if r.svelive.pu21_rgb < r.cr2hdr.pu21_rgb + 2.0]  # type: ignore[union-attr]
    out["worse_chroma"] = [f"{r.image} {r.noise}" for r in done
                           if r.svelive.chroma_p1 > max(r.cr2hdr.chroma_p1, 0.01)]  # type: ignore[union-attr]
    return out


def _f(value: float | None, fmt: str) -> str:
    return "-" if value is None or np.isnan(value) else format(value, fmt)


def table_line(r: PeerRow) -> str:
    """One Markdown table row of a frame."""
    mine, peer = r.svelive, r.cr2hdr or Scores(float("nan"), float("nan"), float("nan"))
    demosaic = "failed" if peer.error else peer.demosaic or "-"
    return (f"| {r.image} | {r.noise} | {mine.pu21_site:.2f} | {_f(peer.pu21_site, '.2f')} | {mine.pu21_rgb:.2f} |"
            f" {_f(peer.pu21_rgb, '.2f')} | {_f(mine.pu21_rgb - peer.pu21_rgb, '+.2f')} | {mine.chroma_p1:.3f} |"
            f" {_f(peer.chroma_p1, '.3f')} | {mine.seconds:.3f} | {_f(peer.seconds, '.2f')} |"
            f" {_f(peer.cpu_seconds, '.2f')} | {demosaic} | {_f(peer.iso_ev, '.2f')} |")


def markdown(rows: list[PeerRow], summ: dict[str, object]) -> str:
    """The per-frame table and the summary as Markdown."""
    s = summ
    lines = ["| image | exposure | PU21 site svelive | cr2hdr | PU21 RGB svelive | cr2hdr | gain (dB) |"
             " chroma 1 % svelive | cr2hdr | s / frame svelive | cr2hdr wall | cr2hdr CPU | cr2hdr demosaic |"
             " cr2hdr ISO (EV) |", "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---|---:|", *map(table_line, rows), "",
             f"Over the {s['converted']} of {s['frames']} frames cr2hdr converted (failed:"
             f" {', '.join(s['cr2hdr_failed']) or 'none'}): mean PU21 per site {_f(s['svelive_pu21_site'], '.2f')}"
             f" against {_f(s['cr2hdr_pu21_site'], '.2f')}, all channels {_f(s['svelive_pu21_rgb'], '.2f')} against"
             f" {_f(s['cr2hdr_pu21_rgb'], '.2f')}; median chroma error {_f(s['svelive_chroma_p1'], '.3f')} against"
             f" {_f(s['cr2hdr_chroma_p1'], '.3f')}; median time {_f(s['svelive_seconds'], '.3f')} s against"
             f" {_f(s['cr2hdr_seconds'], '.2f')} s ({_f(s['cr2hdr_cpu_seconds'], '.2f')} s CPU).",
             f"Below cr2hdr + 2 dB (all channels): {', '.join(s['below_target_pu21']) or 'none'}.",
             f"Chromaticity worse than cr2hdr's (and > 0.01): {', '.join(s['worse_chroma']) or 'none'}."]
    return "\n".join(lines) + "\n"


def pick_scenes(data_dir: Path, images: tuple[str, ...],
                quick: bool) -> tuple[dict[str, np.ndarray], dict[str, str]]:
    """The RGB scenes to run (svelive.bench.colour.data_scenes), two with ``quick``; the skipped ones."""
    if quick and not images:
        stems = {p.stem for p in data_dir.glob("*.exr")}
        images = tuple(n for n in QUICK_IMAGES if n in stems)
    scenes, skipped = data_scenes(data_dir, images)
    if quick:
        scenes = dict(list(scenes.items())[:2])
    return scenes, skipped


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=default_data_dir(), help="directory of HDR EXR images")
    parser.add_argument("--images", nargs="*", default=[], help="image stems (default: every RGB image)")
    parser.add_argument("--quick", action="store_true", help=f"two images ({', '.join(QUICK_IMAGES)} if present)")
    parser.add_argument("--cr2hdr", type=Path, default=DEFAULT_CR2HDR, help="the cr2hdr binary")
    parser.add_argument("--repeats", type=int, default=PeerConfig.repeats, help="svelive timing runs per frame")
    parser.add_argument("--seed", type=int, default=PeerConfig.seed)
    parser.add_argument("--keep", type=Path, help="keep the DNGs (input and cr2hdr's output) in this directory")
    parser.add_argument("--site-chroma", action="store_true",
                        help="svelive with the opt-in chroma per site (docs/peers.md)")
    parser.add_argument("--directional", action="store_true",
                        help="svelive with the directional demosaicing stage (docs/peers.md)")
    parser.add_argument("-o", "--output", type=Path, help="write the results as JSON here")
    args = parser.parse_args(argv)
    problem = cr2hdr_problem(args.cr2hdr)
    if problem:
        print(f"peers: {problem}", file=sys.stderr)
        return 2
    config = PeerConfig(images=tuple(args.images), repeats=args.repeats, seed=args.seed, site_chroma=args.site_chroma,
                        directional=args.directional)
    scenes, skipped = pick_scenes(args.data, config.images, args.quick)
    if skipped:
        print("skipped: " + "; ".join(f"{k} ({v})" for k, v in skipped.items()), file=sys.stderr)
    with tempfile.TemporaryDirectory(prefix="svelive-peers-") as tmp:
        workdir = args.keep or Path(tmp)
        workdir.mkdir(parents=True, exist_ok=True)
        rows = run_peers(scenes, config, args.cr2hdr.resolve(), workdir,
                         log=lambda line: print(line, file=sys.stderr, flush=True))
    summ = summary(rows)
    print(markdown(rows, summ), end="")
    if args.output:
        args.output.parent.mkdir(parents=True, exist_ok=True)
        commit = args.cr2hdr.resolve().parent / "COMMIT"
        args.output.write_text(json.dumps({
            "config": asdict(config), "canon_layout": asdict(CanonLayout()), "skipped": skipped,
            "cr2hdr": str(args.cr2hdr), "cr2hdr_commit": commit.read_text().strip() if commit.is_file() else None,
            "rows": [asdict(r) for r in rows], "summary": summ}, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
