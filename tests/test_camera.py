"""The camera description and colour filter layouts: text forms, presets, phases, stored form, refusals."""

import numpy as np
import pytest

import svelive
from svelive.capture.source import resolve_cfa
from svelive.core.camera import COLOUR_LAYOUTS, Camera, camera_for_raw
from svelive.core.cfa import PRESETS, ColourFilter, joint_period
from svelive.core.errors import SveliveError
from svelive.core.sensor import Sensor
from svelive.reconstruction.input import prepare


@pytest.mark.parametrize("name", list(PRESETS))
def test_presets_parse_and_print_back(name):
    cfa = ColourFilter.parse(name)
    assert ColourFilter.parse(str(cfa)) == cfa and cfa.name == name
    counts = np.bincount(cfa.tile.ravel(), minlength=3)
    assert counts[1] == 2 * counts[0] == 2 * counts[2]  # twice as many greens as reds and blues


def test_text_form_and_channel_map():
    cfa = ColourFilter.parse("g, r / b, g")
    assert str(cfa) == "G,R/B,G" and cfa.name == "GRBG" and cfa.is_bayer()
    channels = cfa.channel_map((3, 5))
    assert channels.dtype == np.uint8 and channels.shape == (3, 5)
    np.testing.assert_array_equal(channels, [[1, 0, 1, 0, 1], [2, 1, 2, 1, 2], [1, 0, 1, 0, 1]])
    assert not ColourFilter.parse("quad-RGGB").is_bayer()


def test_region_offsets_shift_the_bayer_phase():
    rggb = ColourFilter.parse("RGGB")
    assert rggb.shifted(0, 1).name == "GRBG"
    assert rggb.shifted(1, 0).name == "GBRG"
    assert rggb.shifted(1, 1).name == "BGGR"
    assert rggb.shifted(2, 4) == rggb
    # the shifted layout is what the frame's top-left pixel sees
    full = rggb.channel_map((8, 8))
    np.testing.assert_array_equal(rggb.shifted(3, 5).channel_map((4, 2)), full[3:7, 5:7])


@pytest.mark.parametrize("text, word", [("R,G/G,X", "'X'"), ("R,G/G", "different lengths"), ("R,G/G,G", "missing: B"),
                                        ("", "colour filter"), ("rgbg-quad", "preset")])
def test_bad_layouts_are_one_line_errors(text, word):
    with pytest.raises(SveliveError, match=word) as info:
        ColourFilter.parse(text)
    assert "\n" not in str(info.value)


def test_joint_period_of_exposure_and_colour():
    assert joint_period((4, 1), (2, 2)) == (4, 2)  # dual-ISO rows on a Bayer mosaic
    assert Camera.build("dual-iso").period == (4, 2)
    assert Camera.build("quad-bayer").period == (4, 4)
    assert Camera.build("1,4/16,64").period == (2, 2)


@pytest.mark.parametrize("layout", list(COLOUR_LAYOUTS))
def test_colour_layouts_give_every_colour_every_exposure(layout):
    camera = Camera.build(layout)
    assert camera.colour and camera.channels == 3
    h, w = camera.period
    exposure = camera.pattern.exposure_map((h, w))
    channels = camera.cfa.channel_map((h, w))
    for c in range(3):
        assert set(np.unique(exposure[channels == c])) == set(camera.pattern.levels), (layout, c)


def test_layout_name_with_a_contradicting_cfa_is_refused():
    assert Camera.build("dual-iso", "RGGB").cfa.name == "RGGB"
    with pytest.raises(SveliveError, match="drop --cfa"):
        Camera.build("dual-iso", "BGGR")


def test_stored_form_round_trips():
    from svelive.calibrate import Response

    camera = Camera.build("1/1/8/8", "GBRG", Sensor(12, 64.0, 4000.0, 2.5, 1.5),
                          Response((0.0, 0.5, 0.5), (0.0, 1.0), 64.0, 4000.0))
    again = Camera.from_dict(camera.to_dict())
    assert again == camera
    assert Camera.from_dict(Camera().to_dict()) == Camera()
    for bad in ([1, 2], {"sensor": [12, 0]}, {"sensor": {"bits": "x"}}, {"pattern": "1,0"}):
        with pytest.raises(SveliveError):
            Camera.from_dict(bad)


def test_camera_checks_raw_frames():
    camera = camera_for_raw(np.zeros((4, 4), np.uint16), "1,4/16,64", cfa="RGGB", white_level=4095)
    assert camera.sensor.bits == 16 and camera.sensor.white_level == 4095
    with pytest.raises(SveliveError, match="demosaiced colour image"):
        camera.check(np.zeros((4, 4, 3), np.uint16))
    with pytest.raises(SveliveError, match="exceeds"):
        camera_for_raw(np.zeros((4, 4), np.uint8), "1,4/16,64", white_level=4095)
    with pytest.raises(SveliveError, match="pattern of these frames is unknown"):
        prepare(np.zeros((4, 4), np.uint16), Camera())


def test_prepare_gives_channels_only_with_a_cfa():
    raw = np.arange(16, dtype=np.uint16).reshape(4, 4)
    mono = prepare(raw, Camera.build("1,4/16,64", sensor=Sensor(12)))
    colour = prepare(raw, Camera.build("1,4/16,64", "BGGR", Sensor(12)))
    assert mono.channels is None and mono.cfa is None
    np.testing.assert_array_equal(colour.channels, ColourFilter.parse("BGGR").channel_map((4, 4)))
    np.testing.assert_array_equal(colour.signal, mono.signal)
    assert colour.period == (2, 2)
    piece = colour.crop(slice(2, 4), slice(0, 2))
    np.testing.assert_array_equal(piece.channels, colour.channels[2:4, :2])



@pytest.mark.parametrize("dtype, bits, black, order", [(np.uint16, 12, 64, "C"), (np.uint8, 8, 3, "C"),
                                                        (np.uint16, 16, 17, "F"), (np.float64, 12, 64.5, "C")])
def test_prepare_signal_and_censoring_are_numpys(dtype, bits, black, order):
    """The signal is the raw as float32 minus the float32 black level, and the censoring compares it with the
    censor level in float32, as numpy's own arithmetic does (the compiled pass must not round differently)."""
    rng = np.random.default_rng(3)
    top = 2 ** bits
    raw = np.asarray(rng.integers(0, top, (48, 40)).astype(dtype) + (0.25 if dtype == np.float64 else 0), order=order)
    sensor = Sensor(bits, black_level=black, white_level=top - 1)
    inp = prepare(raw, Camera.build("1,4/16,64", sensor=sensor))
    signal = raw.astype(np.float32) - np.float32(black)
    np.testing.assert_array_equal(inp.signal, signal)
    np.testing.assert_array_equal(inp.censored, signal >= sensor.censor_level)
    assert inp.censored.any() and not inp.censored.all()
def test_a_frame_carries_its_camera_into_the_stream():
    camera = Camera.build("1,4/16,64", sensor=Sensor(12))
    raw = np.full((8, 8), 100, np.uint16)
    frame = svelive.Frame(raw, 0, 0, camera=camera)
    assert frame.sensor is camera.sensor
    stream = svelive.Reconstructor(camera, temporal=False)
    np.testing.assert_array_equal(stream.process(frame).image, stream.process(raw).image)
    with pytest.raises(SveliveError, match="give the colour filter and sensor levels inside the Camera"):
        svelive.Reconstructor(camera, cfa="RGGB")


def test_a_colour_frame_is_never_reconstructed_as_mono():
    mono = svelive.Reconstructor("1,4/16,64", white_level=4095, temporal=False)
    bayer = svelive.Frame(np.full((8, 8), 100, np.uint16), 3, 0, camera=Camera.build("1,4/16,64", "RGGB"))
    with pytest.raises(SveliveError, match=r"frame 3 is colour \(RGGB\) but this stream reconstructs monochrome"):
        mono.process(bayer)


@pytest.mark.parametrize("given, fmt_cfa, fmt, offset, expect", [
    (None, "RGGB", "BayerRG12", (0, 0), "RGGB"),
    (None, "RGGB", "BayerRG12", (1, 0), "GBRG"),
    ("RGGB", "RGGB", "BayerRG8", (0, 0), "RGGB"),
    ("quad-RGGB", "RGGB", "BayerRG8", (0, 0), "quad-RGGB"),  # a layout PFNC has no name for
    ("GRBG", None, None, (0, 0), "GRBG"),  # image files: the user's word stands
    (None, None, "Mono12", (0, 0), None),
    ("none", None, None, (0, 0), None),
])
def test_colour_filter_from_format_and_user(given, fmt_cfa, fmt, offset, expect):
    cfa = resolve_cfa(given, fmt_cfa, fmt, offset)
    assert (None if cfa is None else cfa.name) == expect


@pytest.mark.parametrize("given, fmt_cfa, fmt, word", [
    ("RGGB", None, "Mono12", "monochrome format"),
    ("none", "RGGB", "BayerRG12", "cannot be reconstructed as monochrome"),
    ("BGGR", "RGGB", "BayerRG12", "drop --cfa"),
])
def test_contradictions_are_refused_with_the_fix(given, fmt_cfa, fmt, word):
    with pytest.raises(SveliveError, match=word) as info:
        resolve_cfa(given, fmt_cfa, fmt, where="gige:x")
    assert str(info.value).startswith("gige:x: ") and "\n" not in str(info.value)


@pytest.mark.parametrize("layout, sub_pattern, first_cols", [
    ("dual-iso", "1/8", [1, 3, 5, 7]),        # G of RGGB (row 0, odd columns): rows 1, 1, 8, 8 -> 1/8
    ("quad-bayer", "1,8/8,1", [2, 3, 6, 7]),  # the first G block of quad-RGGB, whole 2x2 blocks
    ("column-bayer", "1,8", [1, 3, 5, 7]),
    ("assorted-4x4", "1,4/16,64", [1, 3, 5, 7]),
])
def test_one_colour_plane_keeps_one_filters_pixels_with_their_exposures(layout, sub_pattern, first_cols):
    from svelive.core.camera import one_colour_plane

    camera = Camera.build(layout)
    raw = np.arange(16 * 16, dtype=np.uint16).reshape(16, 16)
    plane, pattern = one_colour_plane(raw, camera)
    assert str(pattern) == sub_pattern and plane.shape == (8, 8)
    assert plane[0, :4].tolist() == first_cols
    # every kept pixel is behind the same filter, and has the exposure its sub-pattern says
    channels = camera.cfa.channel_map(raw.shape)
    exposures = camera.pattern.exposure_map(raw.shape)
    kept = np.isin(raw, plane)
    assert np.unique(channels[kept]).tolist() == [1]
    assert np.array_equal(exposures[kept].reshape(plane.shape), pattern.exposure_map(plane.shape))
    mono = Camera.build("1,4/16,64")
    assert one_colour_plane(raw, mono)[0] is raw
