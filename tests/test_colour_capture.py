"""Colour at capture: a Bayer pixel format sets the frames' colour filter; contradictions are refused.

Against the real fake GigE camera (arv-fake-gv-camera-0.8 on 127.0.0.1, see
tests/test_capture_gige.py), which offers BayerRG8, BayerGR8, BayerBG8 and
BayerGB8. Its mosaic renders both green sites of a 2x2 cell alike, so the data
itself shows which sites are green: the colour filter a frame carries must put
G there, also at odd region offsets.
"""

from __future__ import annotations

import itertools
import os
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from svelive.capture.source import resolve_cfa
from svelive.core import formats
from svelive.core.cfa import ColourFilter
from svelive.core.errors import SveliveError
from tests.test_capture_gige import _MISSING, ADDRESS, FakeCamera

#: the GigE tests skip where Aravis is missing, except under CI=true (as in test_capture_gige)
gige = pytest.mark.skipif(bool(_MISSING) and os.environ.get("CI") != "true", reason=_MISSING or "")


@pytest.fixture
def camera() -> Iterator[FakeCamera]:
    with FakeCamera("SVECOLOUR") as cam:
        yield cam


def green_sites_in_data(raw: np.ndarray) -> tuple[tuple[int, int], tuple[int, int]]:
    """The two sites of the 2x2 cell whose values agree best: the fake camera's greens."""
    r = raw.astype(np.float64)
    planes = {(i, j): r[i::2, j::2] for i in range(2) for j in range(2)}
    pairs = itertools.combinations(planes, 2)
    return min(pairs, key=lambda p: float(np.abs(planes[p[0]] - planes[p[1]]).mean()))


def green_sites_in_filter(cfa: ColourFilter) -> tuple[tuple[int, int], ...]:
    return tuple((i, j) for i in range(2) for j in range(2) if cfa.tile[i, j] == 1)


@gige
@pytest.mark.parametrize("pixel_format, offset", [("BayerRG8", (0, 0)), ("BayerGR8", (0, 0)), ("BayerBG8", (0, 0)),
                                                  ("BayerGB8", (0, 0)), ("BayerRG8", (1, 1)), ("BayerGB8", (0, 1))])
def test_bayer_format_sets_the_colour_filter_in_the_delivered_phase(camera: FakeCamera, pixel_format: str,
                                                                     offset: tuple[int, int]) -> None:
    from svelive.capture import open_source

    with open_source(f"gige:{ADDRESS}", pixel_format=pixel_format, width=160, height=120, offset_x=offset[1],
                     offset_y=offset[0], fps=30) as s:
        frames = list(s.frames(limit=3, seconds=10))
        stats = s.stats()
    assert len(frames) == 3 and stats["camera"]["region"][:2] == [offset[1], offset[0]]
    named = ColourFilter.parse(formats.lookup(pixel_format).cfa)
    for frame in frames:
        # the format names the first delivered pixel: an odd offset does not shift the layout
        assert frame.camera.cfa == named and frame.pixel_format == pixel_format
        assert green_sites_in_data(frame.raw) == green_sites_in_filter(frame.camera.cfa)
    assert stats["cfa"] == named.name


@gige
def test_contradictions_are_refused_at_open_with_the_fix(camera: FakeCamera) -> None:
    from svelive.capture import open_source

    cases = [
        (dict(pixel_format="BayerRG8", cfa="none"), "BayerRG8, a Bayer format .* drop --cfa none, or choose a Mono"),
        (dict(pixel_format="Mono8", cfa="RGGB"), "Mono8, a monochrome format, but a colour filter .* drop --cfa"),
        (dict(pixel_format="BayerRG8", cfa="GRBG"), "BayerRG8 .*RGGB.* but --cfa GRBG was given: drop --cfa"),
        (dict(pixel_format="Mono8", pattern="dual-iso"), "Mono8, a monochrome format, but a colour filter"),
    ]
    for opts, message in cases:
        source = open_source(f"gige:{ADDRESS}", width=64, height=48, **opts)
        with pytest.raises(SveliveError, match=message) as info:
            source.open()
        assert "\n" not in str(info.value)
        source.close()
    # agreeing or refining layouts are accepted
    with open_source(f"gige:{ADDRESS}", pixel_format="BayerRG8", cfa="rggb", width=64, height=48) as s:
        assert s.read(10).camera.cfa.name == "RGGB"
    with open_source(f"gige:{ADDRESS}", pixel_format="BayerRG8", pattern="quad-bayer", width=64, height=48) as s:
        frame = s.read(10)
    assert frame.camera.cfa.name == "quad-RGGB" and str(frame.camera.pattern) == "1,8/8,1"
    with open_source(f"gige:{ADDRESS}", pixel_format="Mono8", cfa="none", width=64, height=48) as s:
        assert s.read(10).camera.cfa is None


@gige
def test_bayer_camera_recorded_and_replayed_keeps_its_filter(camera: FakeCamera, tmp_path: Path,
                                                              capsys: pytest.CaptureFixture[str]) -> None:
    import json

    from replay import RecordingReader
    from svelive.cli import main

    out = tmp_path / "bayer.sverec"
    assert main(["record", "--source", f"gige:{ADDRESS}", "--pixel-format", "BayerGR8", "--pattern", "1/1/8/8",
                 "--width", "64", "--height", "48", "--frames", "4", "-o", str(out)]) == 0
    capsys.readouterr()
    assert main(["replay-info", str(out)]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["cfa"] == "GRBG" and info["pixel_format"] == "BayerGR8" and info["pattern"] == "1/1/8/8"
    with RecordingReader(out) as r:
        assert r.camera.cfa.name == "GRBG" and r.read(0).camera.cfa.name == "GRBG"
    # the CLI verbs pass --cfa to the source: a monochrome reading of the Bayer camera is refused
    assert main(["record", "--source", f"gige:{ADDRESS}", "--pixel-format", "BayerGR8", "--cfa", "none",
                 "--frames", "1", "-o", str(tmp_path / "no.sverec")]) == 2
    err = capsys.readouterr().err
    assert "cannot be reconstructed as monochrome" in err and err.count("\n") == 1
    assert not (tmp_path / "no.sverec").exists()


def test_resolve_cfa_for_gige_and_v4l2_names() -> None:
    for name, layout in [("BayerRG12Packed", "RGGB"), ("BayerGR12p", "GRBG"), ("BA81", "BGGR"), ("GB16", "GBRG"),
                         ("RG10", "RGGB"), ("BA12", "GRBG")]:
        fmt = formats.lookup(name)
        assert resolve_cfa(None, fmt.cfa, fmt.name).name == layout
    fmt = formats.lookup("Y16")
    assert resolve_cfa(None, fmt.cfa, fmt.name) is None and resolve_cfa("none", fmt.cfa, fmt.name) is None
    # a source that knows its layout only at the sensor's origin passes the region offset
    assert resolve_cfa(None, "RGGB", "BayerRG8", offset=(1, 0)).name == "GBRG"
    assert resolve_cfa(None, "RGGB", "BayerRG8", offset=(2, 4)).name == "RGGB"
    # an image sequence cannot tell: the user's word stands, monochrome by default
    assert resolve_cfa("quad-RGGB", None, None).name == "quad-RGGB" and resolve_cfa(None, None, None) is None
    assert resolve_cfa("none", None, None) is None


def test_images_source_takes_the_users_cfa(tmp_path: Path) -> None:
    import cv2

    from svelive.capture import open_source

    folder = tmp_path / "seq"
    folder.mkdir()
    for i in range(2):
        cv2.imwrite(str(folder / f"f{i}.png"), np.full((8, 12), 100 * (i + 1), np.uint16))
    with open_source(f"images:{folder}") as s:
        frame = s.read()
    assert frame.camera.cfa is None and frame.pixel_format == "Mono16"
    with open_source(f"images:{folder}", cfa="BGGR", pattern="1/1/8/8") as s:
        frame = s.read()
    assert frame.camera.cfa.name == "BGGR" and frame.pixel_format == "BayerBG16" and s.stats()["cfa"] == "BGGR"
    with open_source(f"images:{folder}", pixel_format="BayerGB16") as s:
        assert s.read().camera.cfa.name == "GBRG"
    with pytest.raises(SveliveError, match="Mono16, a monochrome format, but a colour filter"):
        open_source(f"images:{folder}", pixel_format="Mono16", cfa="RGGB").open()
    with pytest.raises(SveliveError, match="colour filter 'RGB'"):
        open_source(f"images:{folder}", cfa="RGB")
