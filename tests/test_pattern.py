import math

import numpy as np
import pytest

from svelive import Pattern, SveliveError
from svelive.core.pattern import PAPER_DR_DB, PRESETS, dynamic_range_db, dynamic_range_stops, unique_levels


def test_parse_text_form_rows_and_values():
    p = Pattern.parse("1,4/16,64")
    assert p.tile.tolist() == [[1, 4], [16, 64]]
    assert p.shape == (2, 2)
    assert p.levels.tolist() == [1, 4, 16, 64]
    assert str(p) == "1,4/16,64"


def test_line_interleaved_and_larger_tiles():
    assert Pattern.parse("1/1/8/8").shape == (4, 1)
    p = Pattern.parse("1,2,4/8,16,32/1,2,4")
    assert p.shape == (3, 3)
    assert p.levels.tolist() == [1, 2, 4, 8, 16, 32]


def test_fractions_and_presets():
    assert Pattern.parse("0.5,1").tile.tolist() == [[0.5, 1.0]]
    for name, text in PRESETS.items():
        assert Pattern.parse(name) == Pattern.parse(text)


@pytest.mark.parametrize("text, words", [
    ("1,0/2,3", "must be > 0"),
    ("1,-4/16,64", "must be > 0"),
    ("1,x/16,64", "not a number"),
    ("1,4/16", "different lengths"),
    ("", "non-empty"),
    ("1,,4", "not a number"),
    ("1,inf", "not a number"),
    ("nan,1", "not a number"),
])
def test_bad_patterns_say_what_is_wrong(text, words):
    with pytest.raises(SveliveError, match=words):
        Pattern.parse(text)


def test_exposure_map_cuts_partial_tiles():
    m = Pattern.parse("1,4/16,64").exposure_map((3, 5))
    assert m.dtype == np.float32 and m.shape == (3, 5)
    assert m[0].tolist() == [1, 4, 1, 4, 1]
    assert m[1].tolist() == [16, 64, 16, 64, 16]
    assert m[2].tolist() == [1, 4, 1, 4, 1]


def test_level_index_map_matches_exposures():
    p = Pattern.parse("8,1/4,2")
    idx = p.level_index_map((4, 6))
    assert np.array_equal(p.levels[idx], p.exposure_map((4, 6)))


def test_pixel_map_overrides_tile_and_checks_shape():
    pmap = np.full((4, 4), 2.0, np.float32)
    p = Pattern.parse("1,4/16,64").with_pixel_map(pmap)
    assert np.array_equal(p.exposure_map((4, 4)), pmap)
    with pytest.raises(SveliveError, match="frame is 5x4"):
        p.exposure_map((4, 5))
    with pytest.raises(SveliveError, match="> 0"):
        Pattern.parse("1,4").with_pixel_map(np.zeros((2, 2)))


def test_paper_dynamic_range():
    p = Pattern.parse("nayar-r4")
    assert dynamic_range_db(p, 8) == pytest.approx(PAPER_DR_DB, abs=0.005)
    assert dynamic_range_stops(p, 8) == pytest.approx(math.log2(255 * 64))


def test_unique_levels_by_enumeration():
    # independent count: union of q / e as exact fractions
    from fractions import Fraction

    p = Pattern.parse("nayar-r4")
    union = {Fraction(q, int(e)) for e in p.levels for q in range(256)}
    assert unique_levels(p, 8) == len(union)
    # a single exposure has exactly 2^bits levels; equal exposures add nothing
    assert unique_levels(Pattern.parse("1,1/1,1"), 10) == 1024
    # non-integer ratios are counted exactly too
    q = Pattern.parse("1,1.5")
    assert unique_levels(q, 4) == len({Fraction(v, 1) for v in range(16)} | {Fraction(2 * v, 3) for v in range(16)})
