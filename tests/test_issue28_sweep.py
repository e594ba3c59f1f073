"""Issue 28.12: a sweep is refused at request time, in one line, when it cannot run. After an ``images:``
source has ended (a one-frame calibration still works) the answer says the source has ended (before: 422
"no frame yet: the sweep needs a connected camera"); times outside the demo camera's range (``[1]``,
``[1e30, 1e31]``) get a 409 naming the range before any job starts (before: 202, the job failed later)."""

from __future__ import annotations

import time
from pathlib import Path

import httpx
import numpy as np

from svelive.capture import open_source
from svelive.cli.reconstruct import write_raw
from tests.test_calibration_sweep import URL, server


def refused(srv, body: dict, status: int) -> str:
    """The one-line detail of the refusal of ``body``; no job was started."""
    r = httpx.post(srv.url + URL, json=body, timeout=10)
    assert r.status_code == status, r.text
    detail = r.json()["detail"]
    assert "\n" not in detail and srv.state()["calibration"] is None, detail
    return detail


def test_sweep_after_an_images_source_ended_says_it_ended(monkeypatch, tmp_path: Path) -> None:
    rng = np.random.default_rng(1)
    for i in range(2):
        write_raw(tmp_path / f"f{i}.png", rng.integers(50, 4000, (96, 128), dtype=np.uint16), bits=12)
    factory = lambda: open_source(f"images:{tmp_path}", pattern="1,4/16,64", fps=20, bits=12)  # noqa: E731
    with server(monkeypatch, factory) as srv:
        srv.wait_for(lambda s: s["frames"]["captured"] >= 2)
        deadline = time.monotonic() + 10
        while "cannot set its exposure time" in (detail := refused(srv, {"sweep": [1000, 2000]}, 409)) \
                and time.monotonic() < deadline:  # the folder's last frame read, its end not yet seen
            time.sleep(0.1)
        assert "the source has ended" in detail and "no frame yet" not in detail, detail
        assert httpx.post(srv.url + URL, timeout=30).status_code != 503  # the one-frame calibration has its frame


def test_sweep_times_outside_the_demo_range_are_refused_at_once(monkeypatch) -> None:
    factory = lambda: open_source("demo", cfa="none", width=128, height=96, fps=20)  # noqa: E731
    with server(monkeypatch, factory) as srv:
        srv.wait_for(lambda s: s["frames"]["captured"] >= 2)
        for times in ([1], [1e30, 1e31], [10_000, 2e6]):
            detail = refused(srv, {"sweep": times}, 409)
            assert "outside the demo's range 10..1e+06 us" in detail, detail
