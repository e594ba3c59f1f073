"""The benchmark pieces: baseline, bracketing reference, runner, writers, CLI errors (small frames only)."""

import csv
import json
import sys

import numpy as np
import pytest

from svelive import Pattern, Sensor, simulate
from svelive.bench import report
from svelive.bench.colour import (
    ColourBenchConfig,
    ColourCondition,
    ColourSetting,
    data_scenes,
    markdown_colour,
    run_colour_benchmark,
    time_colour,
)
from svelive.bench.reference import bracketing_merge, bracketing_reference
from svelive.bench.runner import BenchConfig, Setting, pareto_front, run_benchmark
from svelive.cli import main
from svelive.core.errors import SveliveError
from svelive.exr import write_exr
from svelive.metrics import pu21_psnr
from svelive.reconstruction.input import prepare
from svelive.reconstruction.methods import baseline
from svelive.simulation import exposure_scale, load_sample_scene

SENSOR = Sensor.from_full_well(12, 10_000, 3)


def test_pareto_front_keeps_only_undominated_points():
    points = [(10.0, 30.0), (20.0, 29.0), (5.0, 25.0), (40.0, 35.0), (10.0, 30.0)]
    flags = pareto_front(points)
    # (20, 29) is slower and worse than (10, 30); equal points do not dominate each other
    assert flags == [True, False, True, True, True]


@pytest.mark.parametrize("pattern", ["1,4/16,64", "1/1/8/8"])
def test_baseline_upsampling_places_each_phase_where_it_was_sampled(pattern):
    # bilinear interpolation reproduces a linear ramp exactly away from the borders
    p = Pattern.parse(pattern)
    th, tw = p.shape
    y, x = np.mgrid[0:40, 0:48].astype(np.float32)
    ramp = 3.0 * x + 2.0 * y
    for py in range(th):
        for px in range(tw):
            up = baseline.upsample_phase(np.ascontiguousarray(ramp[py::th, px::tw]), (py, px), (th, tw), ramp.shape)
            inner = (slice(th, -th), slice(tw, -tw))
            np.testing.assert_allclose(up[inner], ramp[inner], atol=1e-3)


def test_baseline_flat_field_and_all_saturated_bound():
    frame = simulate(np.full((64, 64), 200.0, np.float32), "1,4/16,64", SENSOR, seed=3)
    est = baseline.run(prepare(frame.raw, "1,4/16,64", SENSOR))
    assert np.mean(est.image) == pytest.approx(200.0, rel=0.01)
    saturated = np.full((8, 8), 4095, np.uint16)
    est = baseline.run(prepare(saturated, "1,4/16,64", SENSOR))
    assert est.lower_bound.all() and np.allclose(est.image, 4095.0)


def test_bracketing_merge_is_inverse_variance_and_skips_censored():
    exposures = [1.0, 8.0]
    signals = [np.full((4, 4), 100.0, np.float32), np.full((4, 4), 800.0, np.float32)]
    merged = bracketing_merge(signals, exposures, SENSOR)
    np.testing.assert_allclose(merged, 100.0, rtol=1e-6)
    signals[1][:] = SENSOR.white_level  # censored: only the short exposure counts
    signals[0][:] = 600.0
    np.testing.assert_allclose(bracketing_merge(signals, exposures, SENSOR), 600.0, rtol=1e-6)


def test_bracketing_reference_beats_every_sve_method_on_a_bright_real_scene():
    scene = np.maximum(load_sample_scene("desk"), 0)
    pattern = "1,4/16,64"
    radiance = scene * exposure_scale(scene, Pattern.parse(pattern), SENSOR)
    frame = simulate(radiance, pattern, SENSOR, seed=2)
    ref = pu21_psnr(bracketing_reference(radiance, pattern, SENSOR, seed=2), frame.truth)
    inp = prepare(frame.raw, pattern, SENSOR)
    for name in ("weighted", "aggregate", "adaptive", "baseline"):
        assert pu21_psnr(Setting(name, name).run(inp).image, frame.truth) < ref, name


@pytest.fixture(scope="module")
def small_run(tmp_path_factory):
    data = tmp_path_factory.mktemp("hdr")
    write_exr(data / "Cannon.exr", {"Y": load_sample_scene("cannon")[:64, :96]})
    config = BenchConfig(patterns=("1,2/4,8",), noise_levels=("bright", "dim"), repeats=1)
    settings = [Setting("aggregate", "aggregate"), Setting("adaptive", "adaptive")]
    return run_benchmark(data, config, settings, log=lambda line: None)


def test_runner_rows_cover_every_setting_and_condition(small_run):
    rows = small_run["rows"]
    assert {(r["method"], r["noise"]) for r in rows} == {(m, n) for m in ("aggregate", "adaptive")
                                                        for n in ("bright", "dim")}
    for r in rows:
        assert r["ms_per_frame"] > 0 and np.isfinite(r["pu21_psnr"]) and r["error_stops_p99"] >= 0
        assert r["below_reference_db"] == pytest.approx(r["reference_pu21_psnr"] - r["pu21_psnr"])
    summary = {s["method"]: s for s in small_run["summary"]}
    mine = [r["pu21_psnr"] for r in rows if r["method"] == "adaptive"]
    assert summary["adaptive"]["pu21_psnr"] == pytest.approx(np.mean(mine))
    assert any(s["pareto"] for s in small_run["summary"])


def test_writers_produce_readable_files(small_run, tmp_path):
    report.write_json(tmp_path / "results.json", small_run)
    report.write_csv(tmp_path / "results.csv", small_run["rows"])
    assert json.loads((tmp_path / "results.json").read_text())["rows"] == json.loads(json.dumps(small_run["rows"]))
    with open(tmp_path / "results.csv") as f:
        lines = list(csv.DictReader(f))
    assert len(lines) == len(small_run["rows"]) and lines[0]["method"] == small_run["rows"][0]["method"]
    assert "| adaptive |" in report.markdown_table(small_run["summary"])
    assert [p.name for p in tmp_path.iterdir()] and not list(tmp_path.glob(".*.tmp"))


def test_chart_is_a_png(small_run, tmp_path):
    pytest.importorskip("matplotlib")
    report.plot_speed_accuracy(small_run["summary"], tmp_path / "chart.png", "adaptive")
    assert (tmp_path / "chart.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_cli_bench_errors_are_one_line(tmp_path, capsys):
    missing = tmp_path / "nothing"
    assert main(["bench", "-o", str(tmp_path / "out"), "--data", str(missing), "--no-chart"]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "nothing" in err and "no such directory" in err
    data = tmp_path / "hdr"
    data.mkdir()
    write_exr(data / "Other.exr", {"Y": load_sample_scene("desk")[:16, :16]})
    assert main(["bench", "--quick", "-o", str(tmp_path / "out"), "--data", str(data), "--no-chart"]) == 2
    assert "holds none of the images Cannon, Desk, MtTamWest" in capsys.readouterr().err
    a_file = tmp_path / "file"
    a_file.write_text("x")
    assert main(["bench", "-o", str(a_file), "--no-chart"]) == 2
    assert "not a directory" in capsys.readouterr().err


# ----- colour ------------------------------------------------------------------------------------

COLOUR_SETTINGS = [ColourSetting("joint", "joint"), ColourSetting("split", "split")]


@pytest.fixture(scope="module")
def colour_run():
    scenes = {"desk": load_sample_scene("desk", rgb=True)[64:128, 32:128]}
    config = ColourBenchConfig(layouts=("dual-iso", "assorted-4x4"), repeats=0)
    return run_colour_benchmark(scenes, config, COLOUR_SETTINGS, skipped={"Garden": "luminance only"},
                                log=lambda line: None)


def test_colour_rows_cover_every_setting_layout_and_noise_level(colour_run):
    rows = colour_run["rows"]
    assert {(r["method"], r["layout"], r["noise"]) for r in rows} == {
        (s.label, layout, noise) for s in COLOUR_SETTINGS for layout in ("dual-iso", "assorted-4x4")
        for noise in ("bright", "dim")}
    for r in rows:
        assert r["ms_per_frame"] is None  # repeats=0: not timed
        assert all(np.isfinite(r[k]) for k in ("pu21_y", "pu21_r", "pu21_g", "pu21_b"))
        assert 0 < r["de2000_mean"] <= r["de2000_p99"]
    assert colour_run["skipped"] == {"Garden": "luminance only"}


def test_colour_summary_and_comparison_are_means_of_the_rows(colour_run):
    rows = colour_run["rows"]
    summary = {s["method"]: s for s in colour_run["summary"]}
    joint = [r for r in rows if r["method"] == "joint"]
    assert summary["joint"]["pu21_y"] == pytest.approx(np.mean([r["pu21_y"] for r in joint]))
    assert summary["joint"]["de2000_p99"] == pytest.approx(np.mean([r["de2000_p99"] for r in joint]))
    assert summary["joint"]["ms_per_frame"] is None
    by_group = {(c["layout"], c["noise"]): c for c in colour_run["comparison"]}
    assert set(by_group) == {(lay, n) for lay in ("dual-iso", "assorted-4x4") for n in ("bright", "dim")} | {
        ("all", "all")}
    for (layout, noise), c in by_group.items():
        mine = [r for r in rows if layout in ("all", r["layout"]) and noise in ("all", r["noise"])]
        split = np.mean([r["pu21_y"] for r in mine if r["method"] == "split"])
        assert c["pu21_y_baseline"] == pytest.approx(split)
        assert c["gain_db"] == pytest.approx(c["pu21_y_default"] - c["pu21_y_baseline"])
        assert c["met"] == (c["gain_db"] >= 2.0 and c["de2000_mean_default"] < c["de2000_mean_baseline"])
    table = markdown_colour(colour_run)
    assert "| joint |" in table and "| dual-iso | dim |" in table and "Garden (luminance only)" in table


def test_colour_scaling_fills_the_shortest_exposure_with_the_brightest_channel():
    scene = np.maximum(load_sample_scene("cannon", rgb=True), 0)
    for layout in ("dual-iso", "assorted-4x4"):
        shortest = float(ColourCondition(layout, "bright").camera().require_pattern().levels[0])
        bright = ColourCondition(layout, "bright").radiance(scene)
        dim = ColourCondition(layout, "dim").radiance(scene)
        peak = float(np.percentile(bright.max(axis=-1), 99.9))
        assert peak * shortest == pytest.approx(SENSOR.range_dn, rel=1e-4)
        np.testing.assert_allclose(dim * 32, bright, rtol=1e-5)


def test_colour_scenes_skip_luminance_only_images(tmp_path):
    rgb = load_sample_scene("desk", rgb=True)[:18, :23]
    write_exr(tmp_path / "Rgb.exr", {c: rgb[..., i] for i, c in enumerate("RGB")})
    write_exr(tmp_path / "Grey.exr", {"Y": rgb[..., 1]})
    scenes, skipped = data_scenes(tmp_path)
    assert list(scenes) == ["Rgb"] and scenes["Rgb"].shape == (16, 20, 3)  # whole 4x4 tiles
    assert list(skipped) == ["Grey"] and "luminance only" in skipped["Grey"]
    with pytest.raises(SveliveError, match="holds none of the images Nothing"):
        data_scenes(tmp_path, ("Nothing",))


def test_colour_timing_is_a_median_in_ms():
    condition = ColourCondition("dual-iso", "bright")
    scene = load_sample_scene("desk", rgb=True)[:32, :32]
    raw = condition.simulate(condition.radiance(scene), seed=0).raw
    assert time_colour(COLOUR_SETTINGS[0], raw, condition.camera(), repeats=2) > 0


def test_colour_chart_is_a_png(colour_run, tmp_path):
    pytest.importorskip("matplotlib")
    report.plot_colour(colour_run, tmp_path / "colour.png")
    assert (tmp_path / "colour.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_cli_bench_without_scikit_image_stops_before_the_run(tmp_path, capsys, monkeypatch):
    monkeypatch.setitem(sys.modules, "skimage", None)
    assert main(["bench", "-o", str(tmp_path / "out"), "--no-chart", "--no-mono", "--no-stability"]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "scikit-image" in err
    assert not (tmp_path / "out").exists()


def test_quick_bench_images_ship_with_the_package():
    # without ../shared (a user's machine) `svelive bench --quick` falls back to the shipped crops
    from svelive.bench.runner import quick_config
    from svelive.bench.scenes import find_images, shipped_data_dir

    stems = {p.stem.lower() for p in find_images(shipped_data_dir())}
    assert {name.lower() for name in quick_config().images} <= stems


# ----- the default's guard grid ----------------------------------------------------------------------


def test_grid_covers_every_cell_and_its_outputs(tmp_path, capsys):
    from svelive.bench.stability import GRID_SENSORS, GridConfig, markdown_grid, run_grid

    config = GridConfig(patterns=("1,2/4,8", "1/1/8/8"), stops=(0.0, 5.0), models=("estimated", "true", "read x2"),
                        sensors=GRID_SENSORS)
    results = run_grid({"desk": load_sample_scene("desk")[:64, :96]}, config, log=None)
    rows, summary = results["rows"], results["summary"]
    assert len(rows) == 2 * 2 * 3 * len(GRID_SENSORS) == summary["cells"]
    assert {(r["pattern"], r["stops"], r["model"], r["sensor"]) for r in rows} == {
        (p, -s, m, t.name) for p in config.patterns for s in config.stops for m in config.models for t in GRID_SENSORS}
    key = lambda r: min(r["margin_pu21"], r["margin_log"])  # noqa: E731
    assert summary["failing"] == sum(key(r) < -0.3 for r in rows)
    assert [key(r) for r in summary["worst"]] == sorted(key(r) for r in rows)[:len(summary["worst"])]
    assert summary["means"]["adaptive_pu21"] == pytest.approx(np.mean([r["adaptive_pu21"] for r in rows]))
    assert "| desk |" in markdown_grid(summary)
    # aggregate does not use the noise model: one score per frame
    for p in config.patterns:
        for s in config.stops:
            same = {r["aggregate_pu21"] for r in rows if r["pattern"] == p and r["stops"] == -s
                    and r["sensor"] == GRID_SENSORS[0].name}
            assert len(same) == 1
    pytest.importorskip("matplotlib")
    report.plot_grid(results, tmp_path / "grid.png")
    assert (tmp_path / "grid.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_cli_bench_grid_alone_writes_its_files(tmp_path):
    data = tmp_path / "hdr"
    data.mkdir()
    write_exr(data / "Desk.exr", {"Y": load_sample_scene("desk")[:48, :48]})
    out = tmp_path / "out"
    assert main(["bench", "--quick", "--no-mono", "--no-colour", "--no-stability", "--no-live", "--no-chart",
                 "-o", str(out), "--data", str(data)]) == 0
    grid = json.loads((out / "grid.json").read_text())
    assert len(grid["rows"]) == 4 * 4 * 6 and {r["sensor"] for r in grid["rows"]} == {"10000e-/2DN"}
    assert (out / "grid.csv").exists() and "mean PU21-PSNR" in (out / "grid.md").read_text()
