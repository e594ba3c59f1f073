"""Hard guarantees of every method, checked on the stability sweeps (small frames, fixed seeds)."""

import numpy as np
import pytest

from svelive import Pattern, Sensor, simulate
from svelive.bench.runner import Setting
from svelive.bench.stability import (CAMERA_WHITE, SWEEPS, chroma_error, colour_sweeps, edge_across_saturation,
                                     low_light, luminance_error, magenta_shift, reconstruct_with, saturated_fraction,
                                     stability_settings)
from svelive.reconstruction.input import sensor_for

SETTINGS = stability_settings()
LABELS = [s.label for s in SETTINGS]
PATTERNS = ["1,4/16,64", "1,2/4,8", "1/1/8/8"]
SENSOR = Sensor.from_full_well(12, 10_000, 3)

# (sweep, method): cliffs the sweeps found and that are not fixed in that method (docs/stability.md).
KNOWN_CLIFFS = {
    ("edge", "cubic"): "once the long exposure is discarded on the bright side the under-determined local "
                       "solve rings (cubic.py's documented weakness near discarded readings)",
    ("low_light", "baseline"): "hat weights vanish at black: the merge keeps the noisiest exposures",
    ("low_light", "cubic"): "the dark discard (2x read noise) keeps only the upper tail of the noise: a bias up",
}


@pytest.fixture(scope="module")
def sweeps():
    return {name: make(SETTINGS) for name, make in SWEEPS.items() if name in ("edge", "low_light", "saturation")}


@pytest.mark.parametrize("label", LABELS)
@pytest.mark.parametrize("pattern", PATTERNS)
@pytest.mark.parametrize("shape", [(1, 1), (1, 5), (3, 2), (5, 7), (17, 33)])
@pytest.mark.parametrize("dtype", [np.uint8, np.uint16, np.float32])
def test_any_valid_frame_gives_finite_non_negative_output(label, pattern, shape, dtype):
    rng = np.random.default_rng(sum(shape))
    top = 255 if dtype == np.uint8 else 4095
    setting = next(s for s in SETTINGS if s.label == label)
    for raw in (rng.integers(0, top + 1, shape).astype(dtype), np.zeros(shape, dtype), np.full(shape, top, dtype)):
        sensor = sensor_for(raw, white_level=top)
        out = reconstruct_with(setting, raw, pattern, sensor)
        assert out.shape == shape and out.dtype == np.float32
        assert np.all(np.isfinite(out)) and np.all(out >= 0), (label, raw)


@pytest.mark.parametrize("label", LABELS)
def test_black_frame_is_black(label):
    setting = next(s for s in SETTINGS if s.label == label)
    for pattern in PATTERNS:
        out = reconstruct_with(setting, np.zeros((32, 48), np.uint16), pattern, SENSOR)
        assert np.all(out == 0), (pattern, float(out.max()))


@pytest.mark.parametrize("label", LABELS)
@pytest.mark.parametrize("pattern", PATTERNS)
def test_flat_scene_scale_within_2_percent_across_every_saturation_threshold(label, pattern):
    # From 16 DN up to just below the shortest exposure's saturation, in quarter-stop steps: every
    # exposure but the shortest saturates somewhere on the way; the frame mean must track the truth.
    setting = next(s for s in SETTINGS if s.label == label)
    shortest = float(Pattern.parse(pattern).levels[0])
    top = 0.95 * SENSOR.censor_level / shortest
    levels = 16.0 * 2.0 ** np.arange(0, np.log2(top / 16.0), 0.25)
    ratios = []
    for i, level in enumerate(levels):
        raw = simulate(np.full((64, 64), level, np.float32), pattern, SENSOR, seed=i).raw
        ratios.append(float(np.mean(reconstruct_with(setting, raw, pattern, SENSOR))) / level)
    worst = int(np.argmax(np.abs(np.array(ratios) - 1)))
    assert abs(ratios[worst] - 1) <= 0.02, (levels[worst], ratios[worst])


def _cliff_free(label, sweep_name, sweeps, check):
    """Run ``check``; a known cliff must still fail it (then xfail), and must be taken off the list once fixed."""
    known = KNOWN_CLIFFS.get((sweep_name, label))
    if known is None:
        check(sweeps[sweep_name])
        return
    try:
        check(sweeps[sweep_name])
    except AssertionError as exc:
        pytest.xfail(f"{known} ({exc})")
    pytest.fail(f"{label} no longer has its {sweep_name} cliff: remove it from KNOWN_CLIFFS and docs/stability.md")


@pytest.mark.parametrize("label", LABELS)
def test_edge_error_grows_no_faster_than_the_contrast(label, sweeps):
    # A cliff: half a stop more contrast making the error near the edge jump by more than half a stop.
    def check(sweep):
        errors = np.array(sweep.errors[label])
        steps = np.diff(sweep.difficulty)
        jumps = np.diff(errors)
        i = int(np.argmax(jumps - steps))
        assert jumps[i] <= steps[i], (sweep.difficulty[i], sweep.difficulty[i + 1], errors[i], errors[i + 1])

    _cliff_free(label, "edge", sweeps, check)


@pytest.mark.parametrize("label", LABELS)
def test_low_light_error_at_most_doubles_per_stop(label, sweeps):
    # Halving the light at constant read noise at most doubles the relative error of an unbiased
    # method; 10% on top covers the sampling noise of an RMS over 9216 pixels.
    def check(sweep):
        errors = np.array(sweep.errors[label])
        growth = errors[1:] / errors[:-1]
        i = int(np.argmax(growth))
        assert growth[i] <= 2.0 * 1.1, (sweep.difficulty[i + 1], errors[i], errors[i + 1])

    _cliff_free(label, "low_light", sweeps, check)


@pytest.mark.parametrize("label", LABELS)
def test_saturated_frame_reports_at_least_its_bound(label, sweeps):
    # Up to a fully saturated frame the error against what the frame can tell stays small and smooth:
    # below 0.1 stop (7%) everywhere, and no step more than 0.05 stop worse than the previous.
    errors = np.array(sweeps["saturation"].errors[label])
    assert errors.max() < 0.1, errors
    assert np.diff(errors).max() < 0.05, errors


def test_sweeps_cover_every_setting_and_are_reproducible():
    one = [Setting("aggregate", "aggregate"), Setting("adaptive", "adaptive")]
    first = edge_across_saturation(one)
    second = edge_across_saturation(one)
    assert first.errors == second.errors
    assert all(len(v) == len(first.difficulty) for v in first.errors.values())
    assert set(low_light(one).errors) == {"aggregate", "adaptive"}
    assert saturated_fraction(one).difficulty[-1] == 1.0


# ----- colour cases (issue 11: edges no worse than the split baseline, highlights not magenta) ------------

COLOUR_LAYOUTS_TESTED = ("dual-iso", "quad-bayer", "column-bayer", "assorted-4x4")
#: Differences below this (stops, about 0.7%) are not visible: "no worse than the baseline" allows them.
INVISIBLE_STOPS = 0.01
#: A highlight may shift towards magenta/pink by at most this (stops, about 7% green against red or blue).
MAGENTA_LIMIT_STOPS = 0.1

# (case, layout): failures the colour cases found and that are not fixed (docs/stability.md).
_ZIPPER = ("joint's chroma is computed per cell of the joint tile and taken as the median of 3x3 cells; "
           "assorted-4x4's cells are 4x4 pixels, so near the edge its luminance error stays above the split "
           "baseline's at low contrast (1 stop: 0.074 against 0.062 stop)")
KNOWN_COLOUR_FAILURES: dict[tuple[str, str], str] = {
    ("colour_edge_luma", "assorted-4x4"): _ZIPPER,
}

@pytest.fixture(scope="module")
def colour_cases():
    return {sweep.name: sweep for sweep in colour_sweeps()}


def _known_colour(case, layout, check):
    """Run ``check``; a known failure must still fail it (then xfail), and be taken off the list once fixed."""
    known = KNOWN_COLOUR_FAILURES.get((case, layout))
    if known is None:
        check()
        return
    try:
        check()
    except AssertionError as exc:
        pytest.xfail(f"{known} ({exc})")
    pytest.fail(f"{layout} no longer fails {case}: remove it from KNOWN_COLOUR_FAILURES and docs/stability.md")


@pytest.mark.parametrize("layout", COLOUR_LAYOUTS_TESTED)
@pytest.mark.parametrize("case", ["colour_edge", "colour_edge_luma"])
def test_colour_edge_no_more_false_colour_or_zipper_than_split(case, layout, colour_cases):
    # At every contrast with an edge (>= 1 stop), the joint default's chroma error (false colour) and
    # luminance error (zipper) within 3 px of a slanted black/white edge stay at or below the split baseline's.
    sweep = colour_cases[case]
    joint = np.array(sweep.errors[f"joint {layout}"])
    split = np.array(sweep.errors[f"split {layout}"])
    edges = np.array(sweep.difficulty) >= 1

    def check():
        worse = (joint - split)[edges]
        i = int(np.argmax(worse))
        assert worse[i] <= INVISIBLE_STOPS, (np.array(sweep.difficulty)[edges][i], joint[edges][i], split[edges][i])

    _known_colour(case, layout, check)


@pytest.mark.parametrize("layout", COLOUR_LAYOUTS_TESTED)
def test_clipped_white_highlight_does_not_turn_magenta(layout, colour_cases):
    # Wherever some channel of the highlight is still measured (peaks up to +0.75 stop: red, at half of
    # green, clips in every exposure from +1 stop), green may not fall behind red or blue.
    sweep = colour_cases["colour_highlight"]
    shift = np.array(sweep.errors[f"joint {layout}"])
    measured = np.array(sweep.difficulty) < 1.0

    def check():
        i = int(np.argmax(shift[measured]))
        assert shift[measured][i] <= MAGENTA_LIMIT_STOPS, (sweep.difficulty[i], shift[measured][i])

    _known_colour("colour_highlight", layout, check)


def test_colour_measures_see_what_they_measure():
    truth = np.full((4, 4, 3), 100.0, np.float32) * CAMERA_WHITE
    mask = np.ones((4, 4), bool)
    assert chroma_error(truth * 3, truth, mask) == pytest.approx(0, abs=1e-9)  # brightness only
    assert luminance_error(truth * 2, truth, truth, mask) == pytest.approx(1.0)
    # between a lower bound and the truth nothing counts; below the bound and above the truth it does
    assert luminance_error(truth * 2, truth, truth * 4, mask) == 0.0
    assert luminance_error(truth * 0.5, truth, truth * 4, mask) == pytest.approx(1.0)
    assert luminance_error(truth * 16, truth, truth * 4, mask) == pytest.approx(2.0)
    magenta = truth.copy()
    magenta[..., 1] *= 0.5  # green one stop low
    assert chroma_error(magenta, truth, mask) == pytest.approx(1.0)
    assert magenta_shift(magenta, truth, mask) == pytest.approx(1.0)
    greenish = truth.copy()
    greenish[..., 1] *= 2.0
    assert magenta_shift(greenish, truth, mask) == 0.0 and chroma_error(greenish, truth, mask) == pytest.approx(1.0)


def test_colour_sweeps_cover_both_modes_and_repeat():
    one = colour_sweeps(layouts=("dual-iso",))
    again = colour_sweeps(layouts=("dual-iso",))
    assert [s.name for s in one] == ["colour_edge", "colour_edge_luma", "colour_highlight"]
    for a, b in zip(one, again):
        assert set(a.errors) == {"joint dual-iso", "split dual-iso"} and a.errors == b.errors
        assert all(len(v) == len(a.difficulty) and np.all(np.isfinite(v)) for v in a.errors.values())
