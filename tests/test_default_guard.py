"""The default method never loses to the paper's methods: the guard grid of issue 12, reduced to the shipped crops.

Every cell (crop x pattern x light x noise model given to the methods) is
simulated like ``svelive bench``'s grid (12 bits, black 64, 10 000 e- full
well, read noise 2 DN); the default must be within GRID_TOLERANCE_DB of the
better of ``aggregate`` and ``weighted`` in PU21-PSNR and in log-PSNR, with a
noise model wrong by a factor 0.5 or 2 in gain or read noise, bright and
5 and 7 stops darker.
"""

import numpy as np
import pytest

from svelive.bench.stability import (GRID_RIVALS, GRID_SENSORS, GRID_TOLERANCE_DB, GridConfig, _Scores,
                                     given_noise, grid_scene_rows)
from svelive.metrics import log_psnr, pu21_psnr
from svelive.reconstruction.methods import DEFAULT_METHOD
from svelive.simulation import load_sample_scene

CROPS = ("desk", "mttamwest", "cannon")
#: (crop, pattern, stops, model): cells where the default still loses by more than the tolerance (strict: each
#: must still fail, and comes off the list once fixed). Five of six dark 1,2/4,8 cells at 7 stops (the default's
#: estimate of L >= 0 where a 3x3 window cannot tell the level from 0) came off with the wide fallback; the sixth
#: (cannon 1,2/4,8 at 7 stops, gain assumed twice the true one: -0.52 dB) with the floor evidence of integer
#: readings (-0.24).
KNOWN: dict[tuple[str, str, float, str], str] = {}
CONFIG = GridConfig(patterns=("1,4/16,64", "1,2/4,8", "1/1/8/8", "1,4,16/16,1,4/4,16,1"), stops=(0.0, 5.0, 7.0),
                    models=("read x0.5", "read x2", "gain x0.5", "gain x2"), sensors=GRID_SENSORS[:1])


@pytest.fixture(scope="module")
def rows():
    return [row for name in CROPS for row in grid_scene_rows(name, load_sample_scene(name), CONFIG)]


def _cell(row):
    return row["image"], row["pattern"], row["stops"] + 0.0, row["model"]  # + 0.0: -0.0 as 0.0


def test_the_default_is_within_the_tolerance_of_the_best_rival_in_every_cell(rows):
    assert len(rows) == len(CROPS) * 4 * 3 * 4
    failing = {_cell(r): (round(r["margin_pu21"], 2), round(r["margin_log"], 2))
               for r in rows if min(r["margin_pu21"], r["margin_log"]) < -GRID_TOLERANCE_DB}
    unexpected = {cell: margins for cell, margins in failing.items() if cell not in KNOWN}
    assert not unexpected, unexpected
    fixed = set(KNOWN) - set(failing)
    assert not fixed, f"no longer failing, take them off KNOWN: {sorted(fixed)}"


def test_margins_are_the_default_against_the_better_rival(rows):
    for r in rows:
        for metric in ("pu21", "log"):
            best = max(r[f"{m}_{metric}"] for m in GRID_RIVALS)
            assert r[f"margin_{metric}"] == pytest.approx(r[f"{DEFAULT_METHOD}_{metric}"] - best)


def test_scores_equal_the_metrics_module():
    rng = np.random.default_rng(0)
    truth = rng.lognormal(2, 2, (40, 50)).astype(np.float32)
    test = (truth * rng.lognormal(0, 0.3, truth.shape)).astype(np.float32)
    test[0, :5] = 0  # zeros hit the floors
    pu21, logp = _Scores(truth)(test)
    assert pu21 == pytest.approx(pu21_psnr(test, truth), rel=1e-9)
    assert logp == pytest.approx(log_psnr(test, truth), rel=1e-9)


def test_noise_models_given():
    true = GRID_SENSORS[0].sensor()
    assert given_noise(true, "estimated") == {"gain": None, "read_noise": None}
    assert given_noise(true, "read x2") == {"gain": true.gain, "read_noise": 2 * true.read_noise}
    assert given_noise(true, "gain x0.5") == {"gain": 0.5 * true.gain, "read_noise": true.read_noise}
    assert true.read_noise == 2.0 and true.black_level == 64 and true.gain * true.range_dn == pytest.approx(10_000)
