"""The live chart (svelive.bench.live): every ladder step, mono and colour, on tiny frames (no wall-clock checks)."""

import csv
import json
import math

import pytest

from svelive.bench import live, report
from svelive.bench.scenes import BENCH_SENSOR
from svelive.cli import main
from svelive.core.errors import SveliveError
from svelive.exr import write_exr
from svelive.reconstruction.live import LADDER, LIVE_REFRESH
from svelive.simulation import load_sample_scene

TINY = (96, 128)  # rows, cols: whole tiles of every pattern and layout
TINY_CONFIG = live.LiveBenchConfig(mono_patterns=("1,4/16,64",), timing_size=TINY, timing_frames=4, warmup=1)


def tiny_scenes():
    mono, colour, _ = live.live_scenes(None)
    return live.cropped_scenes(mono, TINY), live.cropped_scenes(colour, TINY)


@pytest.fixture(scope="module")
def tiny_run():
    mono, colour = tiny_scenes()
    return live.run_live_benchmark(mono, colour, TINY_CONFIG, log=lambda line: None)


def rows_by(results, key="rows"):
    return {(r["step"], r["kind"]): r for r in results[key]}


def test_rows_cover_every_ladder_step_mono_and_colour(tiny_run):
    rows = rows_by(tiny_run)
    assert set(rows) == {(step.name, kind) for step in LADDER for kind in ("mono", "colour")}
    assert [r["step"] for r in tiny_run["rows"] if r["kind"] == "mono"] == [step.name for step in LADDER]
    scenes = len(tiny_run["mono_images"])
    for r in tiny_run["rows"]:
        assert all(math.isfinite(r[k]) for k in ("pu21", "pu21_bright", "pu21_dim", "fps", "wall_ms", "cpu_ms"))
        assert r["fps"] > 0 and r["cpu_ms"] >= 0
        assert r["fps"] == pytest.approx(1e3 / r["wall_ms"])
        assert r["pu21"] == pytest.approx((r["pu21_bright"] + r["pu21_dim"]) / 2)
        assert r["timed_frames"] == (TINY_CONFIG.timing_frames - TINY_CONFIG.warmup) * 2  # bright and dim
        assert r["scored"] == scenes * 2
    assert rows[("adaptive+fusion", "colour")]["camera"] == "dual-iso"


def test_fusion_gains_over_its_single_frame_step_on_a_static_dim_scene(tiny_run):
    # by design: 8 frames of a still scene average the noise where nothing moves, and a dim scene is noise-limited
    rows = rows_by(tiny_run)
    for kind in ("mono", "colour"):
        for method in ("adaptive", "weighted"):
            fused, single = rows[(f"{method}+fusion", kind)], rows[(method, kind)]
            assert fused["pu21_dim"] > single["pu21_dim"] + 0.5, (kind, method)


def test_without_fusion_the_last_frame_alone_is_scored():
    # a stream without fusion keeps no history: scoring only the last frame equals running all of them
    mono, _ = tiny_scenes()
    camera = live.case_camera("1,4/16,64")
    frames, truth = live.static_frames(live.case_radiance("1,4/16,64", "dim", mono["desk"]), camera, 3, seed=4)
    single = next(step for step in LADDER if not step.temporal)
    with live.stream(single, camera, workers=1) as s:
        results = [s.process(raw).image for raw in frames]
    assert live.step_accuracy(single, camera, frames, truth, workers=1) == live.score(results[-1], truth)
    assert frames[0].shape == TINY and frames[0].dtype.kind == "u" and frames[0].max() <= BENCH_SENSOR.white_level
    assert not (frames[0] == frames[1]).all()  # new noise in each frame


def test_time_step_counts_the_frames_after_the_warm_up():
    mono, _ = tiny_scenes()
    camera = live.case_camera("1/1/8/8")
    frames, _ = live.static_frames(live.case_radiance("1/1/8/8", "bright", mono["cannon"]), camera, 5, seed=0)
    walls, cpus = live.time_step(LADDER[0], camera, frames, warmup=2, workers=2)
    assert len(walls) == len(cpus) == 3 and min(walls) > 0 and min(cpus) >= 0


def test_config_refusals_are_one_line():
    with pytest.raises(SveliveError, match="more timing frames than warm-up"):
        live.LiveBenchConfig(timing_frames=3, warmup=3)
    with pytest.raises(SveliveError, match="unknown colour layout 'nope'"):
        live.LiveBenchConfig(colour_layouts=("nope",))


def test_a_kind_without_scenes_is_skipped_and_named():
    mono, _ = tiny_scenes()
    config = live.LiveBenchConfig(mono_patterns=("1,4/16,64",), timing_size=TINY, timing_frames=2, warmup=1,
                                  frames=2, noise_levels=("dim",))
    results = live.run_live_benchmark({"desk": mono["desk"]}, {}, config, ladder=LADDER[-1:], log=lambda line: None)
    assert [(r["step"], r["kind"]) for r in results["rows"]] == [(LADDER[-1].name, "mono")]
    assert results["skipped"] == ["dual-iso"] and results["rows"][0]["pu21_bright"] is None
    assert "Skipped (no scenes of that kind): dual-iso" in live.markdown_live(results)
    with pytest.raises(SveliveError, match="no scenes for the live chart"):
        live.run_live_benchmark({}, {}, config, log=lambda line: None)


def test_table_csv_and_json_outputs(tiny_run, tmp_path):
    table = live.markdown_live(tiny_run)
    for step in LADDER:
        assert f"| {step.name} | mono |" in table and f"| {step.name} | colour |" in table
    assert "live ladder at 128x96, 2 workers: 30 fps reached by" in table
    report.write_csv(tmp_path / "live.csv", live.csv_rows(tiny_run))
    with open(tmp_path / "live.csv") as f:
        lines = list(csv.DictReader(f))
    assert len(lines) == 2 * len(LADDER) and {line["kind"] for line in lines} == {"mono", "colour"}
    report.write_json(tmp_path / "live.json", tiny_run)
    assert json.loads((tmp_path / "live.json").read_text())["rows"] == tiny_run["rows"]


def test_live_chart_is_a_png(tiny_run, tmp_path):
    pytest.importorskip("matplotlib")
    report.plot_live(tiny_run, tmp_path / "live.png")
    assert (tmp_path / "live.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_cli_bench_runs_the_live_chart_by_default_and_skips_it_with_no_live(tmp_path, capsys, monkeypatch):
    monkeypatch.setattr(live, "quick_live_config", lambda: TINY_CONFIG)
    off = ["--no-mono", "--no-colour", "--no-grid", "--no-stability", "--no-chart"]
    out = tmp_path / "out"
    assert main(["bench", "--quick", *off, "-o", str(out)]) == 0
    printed = capsys.readouterr()
    assert "live mono 1,4/16,64 adaptive+fusion:" in printed.err  # a progress line per step
    assert "30 fps reached by" in printed.out
    results = json.loads((out / "live.json").read_text())
    assert results["source"] == "shipped 256x256 crops" and len(results["rows"]) == 2 * len(LADDER)
    assert (out / "live.csv").exists() and "| adaptive+fusion | colour |" in (out / "live.md").read_text()
    skipped = tmp_path / "skipped"
    assert main(["bench", "--quick", *off, "--no-live", "-o", str(skipped)]) == 0
    assert not (skipped / "live.json").exists()


def test_cli_bench_live_on_images_without_colour_charts_mono_only(tmp_path, monkeypatch):
    monkeypatch.setattr(live, "LiveBenchConfig", lambda: TINY_CONFIG)
    (tmp_path / "hdr").mkdir()
    write_exr(tmp_path / "hdr" / "Desk.exr", {"Y": load_sample_scene("desk")[:96, :128]})  # luminance only
    off = ["--no-mono", "--no-colour", "--no-grid", "--no-stability", "--no-chart"]
    assert main(["bench", *off, "-o", str(tmp_path / "out"), "--data", str(tmp_path / "hdr")]) == 0
    results = json.loads((tmp_path / "out" / "live.json").read_text())
    assert results["skipped"] == ["dual-iso"] and {r["kind"] for r in results["rows"]} == {"mono"}


def test_the_top_monochrome_step_runs_the_services_band_refresh():
    """The chart's top step is the service's: once a still view's bands settle, its method runs on some of
    them only (``method_rows`` < 1); the steps the refresh does not apply to run it everywhere."""
    scene = load_sample_scene("desk")[:320, :256]
    camera = live.case_camera("1,4/16,64")
    frames, _ = live.static_frames(live.case_radiance("1,4/16,64", "bright", scene), camera, 12, seed=0)
    for step, skips in ((LADDER[0], True), (LADDER[1], False)):
        with live.stream(step, camera, 1) as s:
            rows = [s.process(raw).method_rows for raw in frames]
        assert (min(rows) < 1.0) == skips, (step.name, rows)
    assert live.LiveBenchConfig().refresh == LIVE_REFRESH
