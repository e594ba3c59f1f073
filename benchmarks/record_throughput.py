"""Recording throughput: how fast RecordingWriter appends 1920x1200 16-bit frames.

    .venv/bin/python benchmarks/record_throughput.py [--frames 240] [--dir /tmp] [--sync-every 0]

Writes ``--frames`` distinct frames (pre-generated, so only the recorder is
timed) to a temporary recording in ``--dir``, reports frames per second and
MB/s for the appends alone and including the final fsync (the data on disk),
then reads every frame back to check it. The target is 60 fps (276 MB/s).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))  # this checkout, not an editable install's

from replay import RecordingReader, RecordingWriter, WriterConfig  # noqa: E402
from svelive.core.camera import Camera  # noqa: E402
from svelive.core.frame import Frame  # noqa: E402
from svelive.core.sensor import Sensor  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=240)
    ap.add_argument("--width", type=int, default=1920)
    ap.add_argument("--height", type=int, default=1200)
    ap.add_argument("--dir", default=tempfile.gettempdir())
    ap.add_argument("--sync-every", type=int, default=0)
    args = ap.parse_args()
    rng = np.random.default_rng(0)
    pool = [rng.integers(0, 4096, (args.height, args.width), dtype=np.uint16) for _ in range(8)]
    sensor = Sensor(bits=12)
    frames = [Frame(raw=pool[i % 8], frame_id=i, host_time_ns=i * 16_666_667, device_time_ns=i * 16_666_667,
                    pixel_format="Mono12", camera=Camera(sensor=sensor)) for i in range(args.frames)]
    fd, name = tempfile.mkstemp(suffix=".sverec", dir=args.dir)
    os.close(fd)
    try:
        writer = RecordingWriter(name, pattern="1,4/16,64",
                                 config=WriterConfig(overwrite=True, sync_every=args.sync_every))
        t0 = time.perf_counter()
        for f in frames:
            writer.append(f)
        t_append = time.perf_counter() - t0
        writer.close()  # index + fsync
        t_total = time.perf_counter() - t0
        mb = args.frames * args.width * args.height * 2 / 1e6
        t1 = time.perf_counter()
        with RecordingReader(name) as r:
            assert len(r) == args.frames
            for i in range(args.frames):
                assert r.read(i).frame_id == i
        t_read = time.perf_counter() - t1
        print(json.dumps({
            "frames": args.frames, "size": f"{args.width}x{args.height} uint16", "sync_every": args.sync_every,
            "append_fps": round(args.frames / t_append, 1), "append_MB_s": round(mb / t_append, 1),
            "with_fsync_fps": round(args.frames / t_total, 1), "with_fsync_MB_s": round(mb / t_total, 1),
            "read_verify_fps": round(args.frames / t_read, 1), "target_fps": 60,
        }, indent=2))
    finally:
        os.unlink(name)


if __name__ == "__main__":
    main()
