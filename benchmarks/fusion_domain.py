"""Still scenes at frame n: the stream's mean of single-frame estimates against the estimate of the mean readings.

    python benchmarks/fusion_domain.py [--frames 8] [--size 256]

For each shipped crop (desk, cannon, mttamwest; central ``--size`` px), 4 and 5
stops under, two sensors the streams are given (3 000 e- / 2 e- and 40 000 e- /
6 e-, 12-bit, black level 64), 1,4/16,64, a still view with new noise in every
frame, PU21-PSNR gain over the single-frame default at the last frame of:

- ``fused``: ``svelive.Reconstructor`` as it is (the running mean of each frame's
  estimate, then the detail step towards the fused own readings);
- ``means``: the default method run once on the frames' mean readings, with the
  noise model of a mean of n readings (gain x n, floor variance / n): what the
  frames' light allows when nothing moves (issue 26's "approach what the frame
  count allows"). Not a stream mode: every pixel is taken as still for n frames.
  The method's floor evidence reads the mean readings and stops at the
  quantisation's 1/12 DN^2, above a mean of n readings' floor where the read
  noise is under 1 DN: there this column smooths more than the model says.

Exact figures (fixed seeds); about a minute on 2 cores.
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import sys

import numpy as np

_HERE = os.path.dirname(os.path.abspath(__file__))
sys.path[:] = [p for p in sys.path if os.path.abspath(p or ".") != _HERE]
sys.path.insert(0, os.path.dirname(_HERE))  # this checkout, not an editable install's

from svelive import Pattern, Sensor  # noqa: E402
from svelive.core.sensor import QUANTISATION_VARIANCE  # noqa: E402
from svelive.metrics import pu21_psnr  # noqa: E402
from svelive.reconstruction.input import prepare  # noqa: E402
from svelive.reconstruction.methods.base import SveInput  # noqa: E402
from svelive.reconstruction.single import run_method  # noqa: E402
from svelive.reconstruction.stream import Reconstructor  # noqa: E402
from svelive.scenes import render_sequence, static  # noqa: E402
from svelive.simulation import exposure_scale, load_sample_scene  # noqa: E402

PATTERN = "1,4/16,64"


def scene(name: str, stops: float, sensor: Sensor, size: int) -> np.ndarray:
    """float32 (size, size) radiance in DN at exposure 1: the crop's centre, ``stops`` under fill."""
    image = np.maximum(load_sample_scene(name), 0)
    h, w = image.shape
    y, x = max((h - size) // 2, 0), max((w - size) // 2, 0)
    image = image[y:y + size, x:x + size]
    return image * np.float32(exposure_scale(image, Pattern.parse(PATTERN), sensor, stops_below_fill=stops))


def mean_input(inputs: list[SveInput], sensor: Sensor) -> SveInput:
    """The frames' mean readings as one input, with the noise model of a mean of n readings (gain x n, floor
    variance / n); censored where any frame's reading was."""
    n = len(inputs)
    floor = sensor.floor_variance / n
    mean_sensor = dataclasses.replace(sensor, gain=sensor.effective_gain * n,
                                      read_noise=float(np.sqrt(max(floor - QUANTISATION_VARIANCE, 0.0))))
    signal = np.mean([i.signal for i in inputs], axis=0, dtype=np.float32)
    censored = np.any([i.censored for i in inputs], axis=0)
    return dataclasses.replace(inputs[-1], signal=signal, censored=censored, sensor=mean_sensor)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--frames", type=int, default=8)
    ap.add_argument("--size", type=int, default=256)
    args = ap.parse_args()
    print("| scene | stops | full well | single | fused | means |")
    print("| --- | --- | --- | --- | --- | --- |")
    gains = []
    for name in ("desk", "cannon", "mttamwest"):
        for stops in (4, 5):
            for full_well, read in ((3000, 2), (40000, 6)):
                sensor = Sensor.from_full_well(12, full_well, read, black_level=64)
                given = dict(black_level=sensor.black_level, white_level=sensor.white_level, gain=sensor.gain,
                             read_noise=sensor.read_noise)
                frames = list(render_sequence(static(scene(name, stops, sensor, args.size)), args.frames,
                                              PATTERN, sensor, seed=1))
                with Reconstructor(PATTERN, **given) as stream:
                    fused = [stream.process(f.raw) for f in frames][-1]
                with Reconstructor(PATTERN, temporal=False, **given) as single_stream:
                    single = single_stream.process(frames[-1].raw)
                inputs = [prepare(f.raw, Pattern.parse(PATTERN), sensor) for f in frames]
                means = run_method(mean_input(inputs, sensor), stream.method)
                truth = frames[-1].truth
                base = pu21_psnr(single.image, truth)
                gain = (pu21_psnr(fused.image, truth) - base, pu21_psnr(means.image, truth) - base)
                gains.append(gain)
                print(f"| {name} | {stops} | {full_well} e- | {base:.2f} | {gain[0]:+.2f} | {gain[1]:+.2f} |",
                      flush=True)
    fused_mean, means_mean = np.mean(gains, axis=0)
    print(f"\nmean gain over the single frame at frame {args.frames}: fused {fused_mean:+.2f} dB, "
          f"means {means_mean:+.2f} dB")
    return 0


if __name__ == "__main__":
    sys.exit(main())
