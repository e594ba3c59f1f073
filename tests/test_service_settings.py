"""Service settings precedence and validation, the newest-frame hand-off, and the serve verb's errors."""

from __future__ import annotations

import asyncio
import subprocess
import sys
import threading
import time

import pytest

from service.pipeline import Newest, NewestSlot, no_signal_image, opencv_threads
from service.settings import resolve
from svelive.core.errors import SveliveError


def test_precedence_cli_over_env_over_file_over_defaults(tmp_path):
    config = tmp_path / "svelive.toml"
    config.write_text('[serve]\nport = 9001\njpeg_quality = 60\nmethod = "aggregate"\nkey = 0.25\n'
                      'source-options = { fps = 12, width = 320 }\n')
    env = {"SVELIVE_CONFIG": str(config), "SVELIVE_PORT": "9002", "SVELIVE_JPEG_QUALITY": "70",
           "SVELIVE_TOKEN": "abc"}
    settings = resolve({"port": 9003, "method": None}, env)
    assert settings.server.port == 9003  # CLI
    assert settings.pipeline.jpeg_quality == 70 and settings.server.token == "abc"  # environment
    assert settings.pipeline.method == "aggregate" and settings.pipeline.tone.key == 0.25  # file
    assert settings.pipeline.source_options == {"fps": 12, "width": 320}
    assert settings.server.host == "127.0.0.1" and settings.pipeline.source == "demo"  # defaults
    assert resolve({}, {}).server.port == 8000 and resolve({}, {}).server.token is None
    assert settings.public()["server"]["token"] == "***"


@pytest.mark.parametrize("cli, env, word", [
    ({"port": 70000}, {}, "port"),
    ({}, {"SVELIVE_PORT": "eighty"}, "SVELIVE_PORT"),
    ({"host": "example.com"}, {}, "host"),
    ({"method": "magic"}, {}, "unknown method"),
    ({"jpeg_quality": 101}, {}, "JPEG quality"),
    ({}, {"SVELIVE_PUBLISHER_NICE": "20"}, "publisher_nice"),
    ({}, {"SVELIVE_PUBLISHER_IDLE": "sometimes"}, "SVELIVE_PUBLISHER_IDLE"),
    ({"pattern": "1,0/2,4"}, {}, "pattern"),
    ({"key": 5.0}, {}, "key"),
    ({"token": "has space"}, {}, "token"),
    ({"source_options": "fps"}, {}, "KEY=VALUE"),
    ({}, {"SVELIVE_TEMPORAL": "maybe"}, "SVELIVE_TEMPORAL"),
    ({"white_balance": "2,1"}, {}, "--white-balance"),
    ({}, {"SVELIVE_COLOUR_MATRIX": "1,0,0"}, "SVELIVE_COLOUR_MATRIX"),
    ({"output_space": "rec709"}, {}, "needs a colour matrix"),
    ({"output_space": "xyz"}, {}, "output space"),
])
def test_bad_settings_are_one_line_errors(cli, env, word):
    with pytest.raises(SveliveError, match=word) as info:
        resolve(cli, env)
    assert "\n" not in str(info.value)


def test_colour_settings_from_file_environment_and_command_line(tmp_path):
    config = tmp_path / "svelive.toml"
    config.write_text('[serve]\nwhite_balance = [2.0, 1.0, 1.5]\n'
                      'colour_matrix = [[1.6, -0.4, -0.2], [-0.3, 1.5, -0.2], [0.0, -0.5, 1.5]]\n')
    colour = resolve({}, {"SVELIVE_CONFIG": str(config)}).pipeline.colour
    assert colour.white_balance == (2.0, 1.0, 1.5) and colour.colour_matrix[:3] == (1.6, -0.4, -0.2)
    assert colour.output_space == "camera"
    colour = resolve({"output_space": "rec709"}, {"SVELIVE_CONFIG": str(config), "SVELIVE_WHITE_BALANCE": "auto"}
                     ).pipeline.colour
    assert colour.auto and colour.output_space == "rec709"
    colour = resolve({"white_balance": "4,2,3", "colour_matrix": "none"}, {"SVELIVE_CONFIG": str(config)}).pipeline.colour
    assert colour.white_balance == (2.0, 1.0, 1.5) and colour.colour_matrix is None
    json_config = tmp_path / "svelive.json"
    json_config.write_text('{"white_balance": "auto", "colour_matrix": [1, 0, 0, 0, 1, 0, 0, 0, 1], '
                           '"output_space": "rec709"}')
    assert resolve({}, {}, config=json_config).pipeline.colour.output_space == "rec709"
    assert resolve({}, {}).pipeline.colour.auto  # default


def test_bad_config_file(tmp_path):
    path = tmp_path / "c.toml"
    path.write_text("prot = 80\n")
    with pytest.raises(SveliveError, match="unknown setting 'prot'"):
        resolve({}, {}, config=path)
    with pytest.raises(SveliveError, match="does not exist"):
        resolve({}, {"SVELIVE_CONFIG": str(tmp_path / "missing.toml")})


def test_newest_slot_keeps_the_newest_and_counts_drops():
    slot = NewestSlot(capacity=2)
    assert [slot.put(i) for i in range(5)] == [0, 0, 1, 1, 1]
    assert slot.dropped == 3
    assert [slot.get(0.01), slot.get(0.01), slot.get(0.01)] == [3, 4, None]
    # a waiting reader wakes on put and on close
    got = []
    reader = threading.Thread(target=lambda: got.append(slot.get(5)))
    reader.start()
    slot.put("x")
    reader.join(5)
    assert got == ["x"]
    reader = threading.Thread(target=lambda: got.append(slot.get(5)))
    reader.start()
    slot.close()
    reader.join(5)
    assert not reader.is_alive() and got == ["x", None]


def test_newest_hands_every_reader_the_newest_item_in_threads_and_on_event_loops():
    port = Newest()
    assert port.seq == 0 and port.latest() is None and port.get_newest(0, 0.01) is None
    assert [port.put(c) for c in "abc"] == [1, 2, 3]
    assert port.get_newest(0, 0) == (3, "c") and port.newest(3) is None  # the newest only: a and b skipped
    # a waiting thread wakes on put (within far less than its timeout) and on wake (None: look again)
    got = []
    reader = threading.Thread(target=lambda: got.append(port.get_newest(3, 5)))
    reader.start()
    time.sleep(0.05)
    port.put("d")
    reader.join(5)
    assert got == [(4, "d")]
    reader = threading.Thread(target=lambda: got.append(port.get_newest(4, 5)))
    reader.start()
    time.sleep(0.05)
    port.wake()
    reader.join(5)
    assert not reader.is_alive() and got[-1] is None

    async def readers() -> list:
        # many readers on one loop, woken by a put from another thread, each with the newest item
        waits = [asyncio.create_task(port.wait_newest(4, 5)) for _ in range(20)]
        await asyncio.sleep(0.05)
        threading.Thread(target=port.put, args=("e",)).start()
        results = await asyncio.gather(*waits)
        timed_out = await port.wait_newest(5, 0.05)
        return [*results, timed_out]

    started = time.monotonic()
    results = asyncio.run(readers())
    assert results == [(5, "e")] * 20 + [None] and time.monotonic() - started < 2


def test_helpers():
    assert opencv_threads(2) == 1 and opencv_threads(8) == 7 and opencv_threads(1) == 1
    image = no_signal_image(320, 180)
    assert image.shape == (180, 320) and image.max() > image.min()  # the text is drawn


def test_serve_rejects_bad_options_with_one_line_and_status_2():
    for args, word in ((["--source", "nosuch:thing"], "unknown source"), (["--port", "99999"], "port"),
                       (["--source-option", "colour=red"], "colour"),
                       (["--output-space", "rec709"], "needs a colour matrix"),
                       (["--white-balance", "1,1,0"], "must be > 0")):
        proc = subprocess.run([sys.executable, "-m", "svelive.cli", "serve", *args], capture_output=True,
                              text=True, timeout=60)
        assert proc.returncode == 2, proc.stderr
        assert word in proc.stderr and len(proc.stderr.strip().splitlines()) == 1, proc.stderr


def test_state_names_the_method_really_in_use():
    from service.pipeline import Pipeline, PipelineConfig
    from svelive.reconstruction.stream import Reconstructor

    for temporal in (True, False):
        pipeline = Pipeline(PipelineConfig(temporal=temporal))
        used = Reconstructor("1,4/16,64", temporal=temporal).method
        assert pipeline.settings()["method"] == used
        assert pipeline.state()["method"] == used
    # the live service runs the library's default (issue 12): with and without temporal fusion
    from svelive.reconstruction.single import methods

    assert Reconstructor("1,4/16,64", temporal=True).method == methods()[0]
    assert Reconstructor("1,4/16,64", temporal=False).method == methods()[0]
