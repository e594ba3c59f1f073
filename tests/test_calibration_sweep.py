"""The live exposure sweep (issue 14): POST /api/calibrate/response {"sweep": [...]} steps the camera's
exposure time, keeps one frame captured after each change, fits them together in the background,
reports progress in /api/state, and puts the exposure back. Against a real uvicorn server on
127.0.0.1: a simulated camera with exposure control whose frames go through a known response, the
fake GigE camera of Aravis, and a source without exposure control (409)."""

from __future__ import annotations

import time

import httpx
import numpy as np
import pytest

from svelive.calibrate import CURVES, simulate_nonlinear
from svelive.core.frame import Frame
from tests import test_service_helpers as helpers
from tests.test_service_helpers import PATTERN, SENSOR, Camera, ServerThread, SimSource, make_camera

URL = "/api/calibrate/response"


def server(monkeypatch, factory, **config) -> ServerThread:
    """The shared ServerThread, its pipeline opening sources from ``factory`` (it looks SimSource up
    whenever it connects, so the test replaces that name for as long as it runs)."""
    monkeypatch.setattr(helpers, "SimSource", lambda camera: factory())
    return ServerThread(Camera(), **config)


def chart(shape=(192, 224)) -> np.ndarray:
    """A grey-patch chart (10 stops) in DN at exposure 1, its brightest patch at the sensor's white."""
    rng = np.random.default_rng(5)
    patches = np.kron(2.0 ** rng.uniform(-10, 0, (shape[0] // 16, shape[1] // 16)), np.ones((16, 16)))
    return (patches * SENSOR.range_dn / patches.max()).astype(np.float32)


class ExposureSource(SimSource):
    """A simulated camera with an exposure time (microseconds; 10 000 renders the chart at exposure 1)
    and the gamma 2.2 response. A change takes effect from the frame after the one in flight, like a
    camera that exposes the next frame while the current one is read out."""

    def __init__(self, camera: Camera, exposure_us: float = 10_000.0) -> None:
        super().__init__(camera)
        self.scene = chart()
        self.exposure_us = exposure_us
        self._exposing = exposure_us  # exposure of the frame in flight
        self.exposure_of: dict[int, float] = {}  # frame id -> exposure it was taken at
        self.changes: list[float] = []
        self._rendered: dict[float, np.ndarray] = {}

    def exposure_time(self) -> float | None:
        return self.exposure_us

    def set_exposure_time(self, value: float) -> float:
        self.changes.append(float(value))
        self.exposure_us = float(value)
        return self.exposure_us

    def _next(self) -> Frame | None:
        frame = super()._next()
        if frame is None:
            return None
        used, self._exposing = self._exposing, self.exposure_us
        if used not in self._rendered:
            self._rendered[used] = simulate_nonlinear(self.scene * (used / 10_000.0), PATTERN, SENSOR,
                                                      CURVES["gamma2.2"], seed=int(used))
        self.exposure_of[frame.frame_id] = used
        return Frame(raw=self._rendered[used], frame_id=frame.frame_id, host_time_ns=frame.host_time_ns,
                     pixel_format=frame.pixel_format, camera=frame.camera, exposure_time=used)


def wait_job(srv: ServerThread, job_id: int, timeout: float = 120.0) -> tuple[dict, list[int]]:
    """Poll /api/state until the sweep ``job_id`` is done or failed: (its state, the steps seen)."""
    deadline = time.monotonic() + timeout
    seen: list[int] = []
    while True:
        job = srv.state()["calibration"]
        assert job is not None and job["id"] == job_id
        if not seen or seen[-1] != job["step"]:
            seen.append(job["step"])
        if job["state"] != "running":
            return job, seen
        assert time.monotonic() < deadline, f"the sweep did not finish: {job}"
        time.sleep(0.02)


def test_sweep_steps_the_exposure_fits_every_frame_applies_and_restores(monkeypatch):
    camera = Camera(fps=25.0, raws=[np.zeros((192, 224), np.uint16)], paused=True)
    sources: list[ExposureSource] = []

    def factory() -> ExposureSource:
        sources.append(ExposureSource(camera))
        return sources[-1]

    with server(monkeypatch, factory) as srv:
        assert srv.state()["calibration"] is None
        assert httpx.post(srv.url + URL, json={"sweep": [10_000, 15_000]}, timeout=10).status_code == 422  # no frame
        camera.paused = False
        srv.wait_for(lambda s: s["frames"]["captured"] > 2)
        source = sources[-1]
        camera.paused = True  # the job waits for frames: a second request meets it running
        sweep = [10_000.0, 15_000.0, 22_500.0]
        r = httpx.post(srv.url + URL, json={"sweep": sweep, "apply": True}, timeout=10)
        assert r.status_code == 202, r.text
        job = r.json()
        assert job["state"] == "running" and job["steps"] == 3 and job["sweep"] == sweep
        assert job["exposure_time_before"] == 10_000.0
        busy = httpx.post(srv.url + URL, json={"sweep": sweep}, timeout=10)
        assert busy.status_code == 409 and "already running" in busy.json()["detail"]
        assert srv.state()["calibration"]["state"] == "running"
        camera.paused = False
        done, steps = wait_job(srv, job["id"])
        assert done["state"] == "done", done
        assert steps == sorted(steps) and steps[-1] == 3
        assert done["exposure_times"] == sweep
        # every kept frame was exposed at its step's time, not the one in flight during the change
        assert [source.exposure_of[i] for i in done["frame_ids"]] == sweep
        # the exposure went back, last
        assert source.changes == sweep + [10_000.0] and done["restored"] == 10_000.0
        assert source.exposure_time() == 10_000.0

        result = httpx.get(srv.url + URL, timeout=10).json()
        assert result["job"] == done and result["applied"] is True
        stats = result["stats"]
        assert stats["frames"] == 3 and stats["exposure_times"] == sweep and stats["common_ratio"] is None
        lo, hi = stats["measured_range"]
        assert hi - lo > 0.9
        m = np.asarray(result["curve"]["brightness"])
        inside = (m >= lo) & (m <= hi)
        error = np.abs(np.asarray(result["curve"]["linear"]) - CURVES["gamma2.2"].inverse(m))[inside]
        assert error.max() < 0.02, error.max()
        band = stats["band"]
        assert band["brightness"][0] == lo and band["brightness"][-1] == hi
        assert all(0 <= se < 0.01 for se in band["standard_error"])
        state = srv.state()
        assert state["response"]["origin"] == "calibrated live"
        assert state["response"]["coefficients"] == result["coefficients"]

        # back to the configured response (none): nothing says "applied" any more (issue 13 item 13)
        assert httpx.delete(srv.url + URL, timeout=10).json() == {"response": None}
        assert srv.state()["response"] is None
        assert httpx.get(srv.url + URL, timeout=10).json()["applied"] is False


def test_a_source_without_exposure_control_gets_409_and_bad_sweeps_422():
    with ServerThread(make_camera(fps=20.0, n=2)) as srv:
        srv.wait_for(lambda s: s["frames"]["captured"] > 1)
        r = httpx.post(srv.url + URL, json={"sweep": [1000, 1500]}, timeout=10)
        assert r.status_code == 409, r.text
        detail = r.json()["detail"]
        assert "source sim cannot set its exposure time" in detail and "\n" not in detail
        for body, word in (({"sweep": []}, "sweep"), ({"sweep": [1, -2]}, "positive"), ({"sweep": [5, 5]}, "differ"),
                           ({"sweep": list(range(1, 30))}, "sweep"), ({"sweep": "fast"}, "sweep"),
                           ({"max_knots": 6}, "max_knots needs a sweep"), ({"sweep": [1, 2], "max_knots": 40}, "max_knots")):
            r = httpx.post(srv.url + URL, json=body, timeout=10)
            assert r.status_code in (409, 422) and word in r.text, (body, r.status_code, r.text)
        assert srv.state()["calibration"] is None



# ----- a replayed recording whose frames carry their exposure times --------------------------------------

def record_sweep(path, times: list[float], per_time: int = 3, scene=None) -> None:
    """A recording of the chart through gamma 2.2 (the tests' 12-bit sensor), ``per_time`` frames (new
    noise each) at every exposure time in ``times`` (microseconds; 10 000 is the chart at exposure 1),
    each with its time, as a camera stepped through them would give."""
    from replay import RecordingWriter
    from svelive.core.camera import Camera as SveCamera

    scene = chart() if scene is None else scene
    cam = SveCamera.build(PATTERN, None, SENSOR)
    with RecordingWriter(path, source="test") as writer:
        n = 0
        for t in times:
            for k in range(per_time):
                raw = simulate_nonlinear(scene * (t / 10_000.0), PATTERN, SENSOR, CURVES["gamma2.2"], seed=n)
                writer.append(Frame(raw=raw, frame_id=n, host_time_ns=n * 40_000_000, device_time_ns=None,
                                    pixel_format="Mono12", camera=cam), exposure_time=t)
                n += 1


def test_sweep_over_a_replay_plays_the_frames_recorded_at_each_time(monkeypatch, tmp_path):
    from svelive.capture import open_source

    recorded = [10_000.0, 15_000.0, 22_500.0]
    path = tmp_path / "sweep.sverec"
    record_sweep(path, recorded)
    opened = []

    def factory():
        opened.append(open_source(f"replay:{path}", loop=True, speed=1.0))
        return opened[-1]

    with server(monkeypatch, factory) as srv:
        srv.wait_for(lambda s: s["frames"]["captured"] > 2)
        assert opened[-1].exposure_time() in recorded  # the time of the frame playing
        # a time the recording does not hold: refused at once (409) with the times it has, in one
        # line, before any exposure was changed or a job started
        r = httpx.post(srv.url + URL, json={"sweep": [10_000, 40_000]}, timeout=10)
        assert r.status_code == 409, r.text
        detail = r.json()["detail"]
        assert "no frame was recorded at exposure time 40000" in detail and "22500" in detail and "\n" not in detail
        assert srv.state()["calibration"] is None and srv.state()["response"] is None

        # the camera rounds: 15 050 asked, 15 000 recorded and used
        # the log-spline offered to the fit too (its power law is exact for gamma 2.2)
        r = httpx.post(srv.url + URL, json={"sweep": [10_000, 15_050, 22_500], "apply": True, "max_knots": 6},
                       timeout=10)
        assert r.status_code == 202, r.text
        assert r.json()["max_knots"] == 6
        done, steps = wait_job(srv, r.json()["id"])
        assert done["state"] == "done", done
        assert steps[-1] == 3 and done["exposure_times"] == recorded
        # each kept frame is one recorded at its step's time (ids are recorded ids shifted by whole spans)
        assert [recorded[(i % 9) // 3] for i in done["frame_ids"]] == recorded
        before = done["exposure_time_before"]  # the time of the frame playing when the sweep began
        assert before in recorded
        assert done["restored"] == before and opened[-1].exposure_time() == before
        result = httpx.get(srv.url + URL, timeout=10).json()
        stats = result["stats"]
        assert stats["frames"] == 3 and stats["exposure_times"] == recorded and result["applied"] is True
        assert {"log-spline 2", "log-spline 6"} <= set(stats["held_out_error"])
        lo, hi = stats["measured_range"]
        m = np.asarray(result["curve"]["brightness"])
        inside = (m >= lo) & (m <= hi)
        error = np.abs(np.asarray(result["curve"]["linear"]) - CURVES["gamma2.2"].inverse(m))[inside]
        assert hi - lo > 0.9 and error.max() < 0.02, (lo, hi, error.max())
        # after the sweep the replay goes on with the frames of the time it had before
        last = srv.state()["frames"]["last_frame_id"]
        later = srv.wait_for(lambda s: s["frames"]["last_frame_id"] > last + 3)["frames"]["last_frame_id"]
        assert recorded[(later % 9) // 3] == before


def test_sweep_over_a_replay_without_exposure_times_gets_409(monkeypatch, tmp_path):
    from replay import RecordingWriter
    from svelive.capture import open_source

    path = tmp_path / "plain.sverec"
    with RecordingWriter(path, pattern=PATTERN, source="test") as writer:
        for i in range(3):
            writer.append(Frame(raw=np.full((32, 32), 100 * i, np.uint16), frame_id=i, host_time_ns=i * 10**8,
                                pixel_format="Mono12"))
    with server(monkeypatch, lambda: open_source(f"replay:{path}", loop=True)) as srv:
        srv.wait_for(lambda s: s["frames"]["captured"] > 1)
        r = httpx.post(srv.url + URL, json={"sweep": [1000, 1500]}, timeout=10)
        assert r.status_code == 409, r.text
        detail = r.json()["detail"]
        assert f"source replay:{path} cannot set its exposure time" in detail and "\n" not in detail
        assert srv.state()["calibration"] is None

# ----- the fake GigE camera of Aravis --------------------------------------------------------------

from tests.test_capture_gige import _MISSING, ADDRESS, FakeCamera  # noqa: E402


@pytest.mark.skipif(_MISSING is not None, reason=str(_MISSING))
def test_sweep_steps_the_fake_gige_cameras_exposure_time_and_restores_it(monkeypatch):
    from svelive.capture import open_source

    with FakeCamera("SVESWEEP"):
        opened = []

        def factory():
            opened.append(open_source(f"gige:{ADDRESS}", pixel_format="Mono8", width=64, height=48, fps=40,
                                      exposure_us=8000, pattern="1,4/16,64"))
            return opened[-1]

        with server(monkeypatch, factory, offline_after_s=2.0) as srv:
            srv.wait_for(lambda s: s["frames"]["captured"] > 2, timeout=15)
            source = opened[-1]
            assert source.exposure_time() == 8000.0
            r = httpx.post(srv.url + URL, json={"sweep": [4000, 6000, 9000]}, timeout=10)
            assert r.status_code == 202, r.text
            job, steps = wait_job(srv, r.json()["id"], timeout=60)
            assert steps[-1] == 3 and job["exposure_times"] == [4000.0, 6000.0, 9000.0]
            assert len(job["frame_ids"]) == 3 and job["frame_ids"] == sorted(job["frame_ids"])
            assert job["restored"] == 8000.0 and source.exposure_time() == 8000.0
            # the frames carry the exposure they were taken at (what a recording keeps for a replayed sweep)
            restored_from = srv.pipeline.captured.count
            srv.wait_for(lambda s: s["frames"]["captured"] > restored_from + 2, timeout=15)
            assert srv.pipeline.latest_raw().exposure_time == 8000.0
            # the fake camera's moving ramp is no still SVE scene: the fit refuses it, with the reason
            assert job["state"] in ("done", "failed")
            if job["state"] == "failed":
                assert job["error"] and "\n" not in job["error"]
            # the camera itself reports the restored value
            from svelive.capture.gige import load_aravis

            assert load_aravis().Camera.new(ADDRESS).get_exposure_time() == 8000.0


@pytest.mark.skipif(_MISSING is not None, reason=str(_MISSING))
def test_record_steps_the_fake_gige_cameras_exposure_and_tags_every_frame(tmp_path, capsys):
    import json

    from replay import RecordingReader
    from svelive.capture.gige import load_aravis
    from svelive.cli import main

    with FakeCamera("SVEREC"):
        out = tmp_path / "steps.sverec"
        rc = main(["record", "--source", f"gige:{ADDRESS}", "--pixel-format", "Mono8", "--width", "64",
                   "--height", "48", "--fps", "40", "--pattern", "1,4/16,64", "--opt", "exposure_us=8000",
                   "--exposure-times", "4000,6000", "--frames", "3", "-o", str(out), "-q"])
        assert rc == 0
        summary = json.loads(capsys.readouterr().out)
        assert summary["exposure_times"] == [4000.0, 6000.0] and summary["exposure_time_restored"] == 8000.0
        assert load_aravis().Camera.new(ADDRESS).get_exposure_time() == 8000.0  # put back on the camera
        with RecordingReader(out) as reader:
            times = list(reader.exposure_times())
            frames = [reader.read(i) for i in range(len(reader))]
        assert times == [4000.0] * 3 + [6000.0] * 3
        # each frame carries the time the camera reported applying, as the recording does
        assert [f.exposure_time for f in frames] == times


def test_record_steps_the_demo_exposure_and_refuses_before_writing(tmp_path, capsys):
    import json

    from replay import RecordingReader
    from svelive.cli import main

    out = tmp_path / "demo.sverec"
    args = ["record", "--source", "demo", "--width", "96", "--height", "64", "--fps", "0", "--cfa", "none",
            "--opt", "period_s=0", "--opt", "exposure_us=10000", "-q"]
    assert main(args + ["--exposure-times", "2000,4000", "--frames", "2", "-o", str(out)]) == 0
    assert json.loads(capsys.readouterr().out)["exposure_time_restored"] == 10000.0
    with RecordingReader(out) as reader:
        assert list(reader.exposure_times()) == [2000.0, 2000.0, 4000.0, 4000.0]
        raws = [reader.read(i).raw.astype(float) for i in range(4)]
    dark = np.minimum(raws[0], raws[2]) < 1000  # unclipped at both times
    ratio = (raws[2][dark].mean() + raws[3][dark].mean()) / (raws[0][dark].mean() + raws[1][dark].mean())
    assert ratio == pytest.approx(2.0, rel=0.1)  # twice the time, twice the light
    # refused in one line, and no file written: no --frames, a time a replay lacks, a bad list
    for extra, words in ((["--exposure-times", "2000,3000"], "needs --frames"),
                         (["--exposure-times", "2000,x", "--frames", "1"], "numbers separated by commas"),
                         (["--exposure-times", "2000,0", "--frames", "1"], "must be positive numbers")):
        bad = tmp_path / "bad.sverec"
        try:
            code = main(args + extra + ["-o", str(bad)])
        except SystemExit as exc:  # argparse refuses a bad --exposure-times itself
            code = exc.code
        assert code == 2
        err = capsys.readouterr().err.strip().splitlines()[-1]
        assert words in err and "\n" not in err and not bad.exists()
    bad = tmp_path / "bad.sverec"
    assert main(["record", "--source", f"replay:{out}", "--exposure-times", "2000,3000", "--frames", "1",
                 "-o", str(bad), "-q"]) == 2
    err = capsys.readouterr().err.strip()
    assert "no frame was recorded at exposure time 3000" in err and not bad.exists()


# ----- frames for the offline sweep: simulate writes the sensor's bit depth into its PNG ----------------

def test_calibrate_response_of_colour_frames_reads_one_filters_pixels(tmp_path, capsys):
    from svelive.calibrate import load_response
    from svelive.capture import open_source
    from svelive.cli import main

    paths = []
    for t in (10_000, 15_000):  # the colour demo (dual-ISO on RGGB), linear, at two global exposures
        with open_source("demo", width=640, height=360, fps=0, period_s=0, exposure_us=t) as source:
            paths.append(tmp_path / f"f{t}.npy")
            np.save(paths[-1], source.read().raw)
    args = ["calibrate", "response", *map(str, paths), "--exposure-times", "10000,15000", "--pattern", "1/1/8/8",
            "--bits", "12", "-q"]
    assert main(args + ["--cfa", "RGGB", "-o", str(tmp_path / "r.json")]) == 0
    response = load_response(tmp_path / "r.json")
    lo, hi = response.stats["measured_range"]
    m = np.linspace(lo, hi, 200)
    assert hi - lo > 0.9 and np.abs(response(m) - m).max() < 0.01
    # read as monochrome, the filters' differences look like exposure differences: no fit of a linear camera
    code = main(args + ["-o", str(tmp_path / "mono.json")])
    capsys.readouterr()
    if code == 0:
        mono = load_response(tmp_path / "mono.json")
        assert np.abs(mono(m) - m).max() > 0.01
    else:
        assert code == 2 and not (tmp_path / "mono.json").exists()


def test_calibrate_response_from_a_recorded_sweep(tmp_path, capsys):
    """Record a sweep of the colour demo, then fit from the recording alone: its camera and times."""
    from svelive.calibrate import load_response
    from svelive.cli import main

    sweep = tmp_path / "sweep.sverec"
    assert main(["record", "--source", "demo", "--width", "640", "--height", "360", "--fps", "0",
                 "--opt", "period_s=0", "--exposure-times", "10000,15000", "--frames", "3", "-o", str(sweep),
                 "-q"]) == 0
    assert main(["calibrate", "response", str(sweep), "-q", "-o", str(tmp_path / "r.json")]) == 0
    assert "from 2 frames" in capsys.readouterr().out
    response = load_response(tmp_path / "r.json")
    lo, hi = response.stats["measured_range"]
    m = np.linspace(lo, hi, 200)
    assert response.stats["exposure_times"] == [10000.0, 15000.0]
    assert hi - lo > 0.9 and np.abs(response(m) - m).max() < 0.01
    # refusals in one line: times given twice, a recording without times
    assert main(["calibrate", "response", str(sweep), "--exposure-times", "1,2", "-o", str(tmp_path / "x.json")]) == 2
    assert "drop --exposure-times" in capsys.readouterr().err
    from replay import RecordingWriter

    plain = tmp_path / "plain.sverec"
    with RecordingWriter(plain, pattern=PATTERN, source="test") as writer:
        writer.append(Frame(raw=np.full((32, 32), 100, np.uint16), frame_id=0, host_time_ns=0, pixel_format="Mono12"))
    assert main(["calibrate", "response", str(plain), "-o", str(tmp_path / "x.json")]) == 2
    assert "has no exposure times" in capsys.readouterr().err


def test_a_recorded_sweep_keeps_its_own_black_level_unless_one_is_given(tmp_path):
    """calibrate response reads a recording's levels from it: --black-level left out is not 0."""
    from replay import RecordingWriter
    from svelive.cli.calibrate import _recorded_sweep
    from svelive.cli import build_parser
    from svelive.core.camera import Camera as CameraDescription
    from svelive.core.sensor import Sensor

    camera = CameraDescription.build(PATTERN, None, Sensor(bits=12, black_level=64))
    sweep = tmp_path / "sweep.sverec"
    with RecordingWriter(sweep, source="test") as writer:
        for i, time_us in enumerate((10000.0, 20000.0)):
            writer.append(Frame(raw=np.full((32, 32), 100 * (i + 1), np.uint16), frame_id=i, host_time_ns=i,
                                pixel_format="Mono12", camera=camera), exposure_time=time_us)
    command = ["calibrate", "response", str(sweep), "-o", str(tmp_path / "r.json")]
    assert _recorded_sweep(build_parser().parse_args(command))[2].sensor.black_level == 64
    assert _recorded_sweep(build_parser().parse_args(command + ["--black-level", "32"]))[2].sensor.black_level == 32


def test_simulated_png_says_its_bit_depth_and_calibrate_reads_it(tmp_path, capsys):
    import json

    import cv2

    from svelive.cli.calibrate import png_significant_bits
    from svelive.cli import main
    from svelive.cli.reconstruct import png_with_sbit, write_raw
    from svelive.core.errors import SveliveError
    from svelive.simulation import sample_scene_path

    raw = np.random.default_rng(1).integers(0, 3000, (40, 48)).astype(np.uint16)  # nothing saturated
    write_raw(tmp_path / "f.png", raw, bits=12)
    assert png_significant_bits(tmp_path / "f.png") == 12
    assert np.array_equal(cv2.imread(str(tmp_path / "f.png"), cv2.IMREAD_UNCHANGED), raw)
    write_raw(tmp_path / "g.png", raw)  # without bits: no chunk
    assert png_significant_bits(tmp_path / "g.png") is None
    write_raw(tmp_path / "f.tif", raw, bits=12)  # other formats: ignored
    assert np.array_equal(cv2.imread(str(tmp_path / "f.tif"), cv2.IMREAD_UNCHANGED), raw)
    # one chunk, replaced rather than repeated
    twice = png_with_sbit(png_with_sbit((tmp_path / "g.png").read_bytes(), 10), 12)
    assert twice.count(b"sBIT") == 1 and twice.index(b"sBIT") < twice.index(b"IDAT")
    (tmp_path / "h.png").write_bytes(twice)
    assert png_significant_bits(tmp_path / "h.png") == 12
    with pytest.raises(SveliveError, match="do not fit a 8-bit"):
        write_raw(tmp_path / "x.png", raw.astype(np.uint8), bits=12)
    assert not (tmp_path / "x.png").exists()

    # svelive simulate -> svelive calibrate without --bits: the white level of 12 bits, from the file
    out = tmp_path / "a.png"
    scene = str(sample_scene_path("desk"))
    assert main(["simulate", scene, "--pattern", "1,4/16,64", "--bits", "12", "--stops-below-fill", "9",
                 "-o", str(out)]) == 0
    assert png_significant_bits(out) == 12
    simulated = cv2.imread(str(out), cv2.IMREAD_UNCHANGED)
    assert simulated.max() < 4095  # 9 stops below fill: no saturated cluster says 12 bits
    code = main(["calibrate", "response", str(out), "--pattern", "1,4/16,64", "-q", "-o", str(tmp_path / "r.json")])
    err = capsys.readouterr().err
    assert "--bits" not in err, err
    if code == 0:
        assert json.loads((tmp_path / "r.json").read_text())["white_level"] == 4095


# ----- the demo camera's exposure time -----------------------------------------------------------------

def test_demo_exposure_time_scales_the_light_it_collects():
    from svelive.capture import open_source
    from svelive.capture.demo import REFERENCE_EXPOSURE_US
    from svelive.core.errors import SveliveError

    with open_source("demo", cfa="none", width=320, height=180, fps=0, period_s=0) as s:
        assert s.exposure_time() == REFERENCE_EXPOSURE_US == 10_000.0
        a = s.read().raw.astype(float)
        assert s.set_exposure_time(15_000) == 15_000.0 and s.exposure_time() == 15_000.0
        b = s.read().raw.astype(float)
        assert s.stats()["exposure_us"] == 15_000.0
        with pytest.raises(SveliveError, match="outside the demo's range") as err:
            s.set_exposure_time(0)
        assert "\n" not in str(err.value) and s.exposure_time() == 15_000.0
        black, white = s.sensor.black_level, s.sensor.white_level
    # a still scene: the mean signal of pixels far from white in both grows by the exposure ratio
    ok = (a > black + 20) & ((a - black) * 1.5 < 0.8 * (white - black))
    assert ok.sum() > 10_000
    assert (b[ok] - black).mean() / (a[ok] - black).mean() == pytest.approx(1.5, rel=0.005)
    with pytest.raises(SveliveError, match="period_s"):
        open_source("demo", period_s=-1)
    with pytest.raises(SveliveError, match="exposure time 5 us"):
        open_source("demo", exposure_us=5)


@pytest.mark.parametrize("cfa", ["none", "RGGB"])  # RGGB: the colour demo, dual-ISO on a Bayer mosaic
def test_sweep_on_the_demo_camera_recovers_its_linear_response(monkeypatch, cfa):
    from svelive.capture import open_source

    opened = []

    def factory():
        opened.append(open_source("demo", cfa=cfa, width=640, height=360, fps=20, period_s=0))
        return opened[-1]

    with server(monkeypatch, factory) as srv:
        srv.wait_for(lambda s: s["frames"]["captured"] > 2)
        r = httpx.post(srv.url + URL, json={"sweep": [10_000, 15_000]}, timeout=10)
        assert r.status_code == 202, r.text
        done, steps = wait_job(srv, r.json()["id"])
        assert done["state"] == "done", done
        assert done["exposure_times"] == [10_000.0, 15_000.0] and steps[-1] == 2
        assert done["restored"] == 10_000.0 and opened[-1].exposure_time() == 10_000.0
        result = httpx.get(srv.url + URL, timeout=10).json()
        assert result["degree"] == 1 and result["applied"] is False
        lo, hi = result["stats"]["measured_range"]
        m = np.asarray(result["curve"]["brightness"])
        inside = (m >= lo) & (m <= hi)
        assert hi - lo > 0.9 and np.abs(np.asarray(result["curve"]["linear"]) - m)[inside].max() < 0.01


def test_after_change_keeps_frames_captured_after_it_from_the_settle_th_on():
    from svelive.capture import AfterChange

    raw = np.zeros((2, 2), np.uint16)
    frames = [Frame(raw, frame_id=i, host_time_ns=100 * i) for i in range(10)]
    settled = AfterChange(changed_ns=250, settle=1)
    # 0-2 were captured before the change; 3 was in flight at it; 4 on show it
    assert [f.frame_id for f in frames if settled.shows(f)] == [4, 5, 6, 7, 8, 9]
    # polling the newest frame only: a frame missed in between counts towards the settling
    newest = AfterChange(changed_ns=250, settle=2)
    assert [newest.shows(f) for f in (frames[1], frames[3], frames[4], frames[6])] == [False, False, False, True]
    assert AfterChange(changed_ns=250, settle=0).shows(frames[3])
    # ids that start again (a source rebuilt after a failure) count from the new start, not from the old ids
    restarted = AfterChange(changed_ns=250, settle=1)
    assert not restarted.shows(frames[5])
    again = [Frame(raw, frame_id=i, host_time_ns=1000 + 100 * i) for i in range(3)]
    assert [restarted.shows(f) for f in again] == [False, True, True]
