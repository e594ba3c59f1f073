"""The service's encoder thread, call by call, on reconstructed demo frames: CPU time of each call a frame.

    python benchmarks/encoder_cost.py [--size 1920x1200] [--cfa RGGB] [--frames 8] [--rounds 5] [--quality 80]
                                      [--frames-file PATH.npy]

Reconstructs ``--frames`` frames of the still demo scene (temporal fusion, as the service does), then runs
what :class:`service.pipeline.encoder.EncoderStage` runs for each frame while MJPEG clients watch, on those
frames cycled for ``--rounds`` rounds at 30 fps of frame time: the colour stage's white balance and matrix
(``ColourStage.preview_matrix``: an estimate every third frame), the tone map's statistics
(``ToneMapper.update``), its curve (``ToneMapper.apply``, BGR) and the JPEG (``encode_jpeg``), each timed
by the thread's CPU time (``time.thread_time_ns``); and ``estimate_white_balance`` alone on every frame.
Prints the median and mean of each over the rounds after the first (kernel loading), in ms, and a hash of
the previews and JPEGs of the first round. The demo's frames differ from run to run (which of them the
reader gets depends on timing). To compare two versions' outputs, pass the same ``--frames-file``: the
frames are read from it if it exists, otherwise reconstructed and saved to it.
"""

from __future__ import annotations

import argparse
import hashlib
import os
import sys
import time

import numpy as np

_HERE = os.path.dirname(os.path.abspath(__file__))
sys.path[:] = [p for p in sys.path if os.path.abspath(p or ".") != _HERE]
sys.path.insert(0, os.path.dirname(_HERE))  # this checkout, not an editable install's

from service.pipeline.colour import ColourStage  # noqa: E402
from service.pipeline.encoder import encode_jpeg  # noqa: E402
from svelive.capture.demo import DemoSource  # noqa: E402
from svelive.reconstruction.stream import Reconstructor  # noqa: E402
from svelive.tonemap import ToneMapper, ToneSettings  # noqa: E402
from svelive.whitebalance import ColourSettings, estimate_white_balance  # noqa: E402


class _Hdr:
    """What the encoder reads of an HdrFrame."""

    def __init__(self, image: np.ndarray, host_time_ns: int) -> None:
        self.image, self.host_time_ns = image, host_time_ns


class _Published:
    """What the encoder reads of a Published frame."""

    def __init__(self, image: np.ndarray, host_time_ns: int) -> None:
        self.hdr = _Hdr(image, host_time_ns)


def frames(size: tuple[int, int], cfa: str, n: int) -> list[np.ndarray]:
    """``n`` reconstructed frames (float32 (H, W) or (H, W, 3)) of the still demo scene, after two to settle."""
    demo = DemoSource("demo", width=size[0], height=size[1], fps=0, period_s=1e9, cfa=cfa)
    demo.open()
    out = []
    try:
        with Reconstructor(demo.camera) as reconstructor:
            while len(out) < n + 2:
                out.append(np.array(reconstructor.process(demo.read(timeout=10.0).raw).image))
    finally:
        demo.close()
    return out[2:]


def encoder_cost(images: list[np.ndarray], rounds: int, quality: int) -> tuple[dict[str, list[int]], str]:
    """Thread CPU ns of each call a frame (rounds after the first), and a hash of the first round's outputs."""
    colour, mapper = ColourStage(ColourSettings()), ToneMapper(ToneSettings())
    clock, times, digest = time.thread_time_ns, {}, hashlib.sha256()
    frame_ns = 1_000_000_000 // 30
    for r in range(rounds):
        for i, image in enumerate(images):
            time_ns = (r * len(images) + i + 1) * frame_ns
            t0 = clock()
            matrix = colour.preview_matrix(_Published(image, time_ns))  # type: ignore[arg-type]
            t1 = clock()
            mapper.update(image, time_ns, matrix)
            t2 = clock()
            display = mapper.apply(image, matrix, bgr=matrix is not None)
            t3 = clock()
            jpeg = encode_jpeg(display, quality)
            t4 = clock()
            if image.ndim == 3:
                estimate_white_balance(image)
            t5 = clock()
            if r == 0:
                digest.update(display.tobytes())
                digest.update(jpeg)
                continue
            calls = [("preview_matrix", t1 - t0), ("tone statistics", t2 - t1), ("tone apply", t3 - t2),
                     ("jpeg", t4 - t3), ("encoder total", t4 - t0)]
            if image.ndim == 3:
                calls.append(("estimate_white_balance", t5 - t4))
            for name, ns in calls:
                times.setdefault(name, []).append(ns)
    return times, digest.hexdigest()[:16]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--size", default="1920x1200")
    parser.add_argument("--cfa", default="RGGB", help="the demo's colour filter (none: monochrome)")
    parser.add_argument("--frames", type=int, default=8)
    parser.add_argument("--rounds", type=int, default=5)
    parser.add_argument("--quality", type=int, default=80)
    parser.add_argument("--frames-file", help="frames read from this .npy if it exists, else saved to it")
    args = parser.parse_args()
    width, height = (int(x) for x in args.size.lower().split("x"))
    if args.frames_file and os.path.exists(args.frames_file):
        images = list(np.load(args.frames_file))
    else:
        images = frames((width, height), args.cfa, args.frames)
        if args.frames_file:
            np.save(args.frames_file, np.stack(images))
    times, digest = encoder_cost(images, args.rounds, args.quality)
    print(f"# load average {' '.join(open('/proc/loadavg').read().split()[:3])}, {os.cpu_count()} cores")
    for name, values in times.items():
        print(f"{name:24s} median {np.median(values) / 1e6:6.2f} ms   mean {np.mean(values) / 1e6:6.2f} ms")
    print(f"outputs {digest}")


if __name__ == "__main__":
    main()
