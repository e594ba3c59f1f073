"""Recording and replay of raw SVE frames: the container, its writer and reader.

    from replay import RecordingWriter, RecordingReader
    with RecordingWriter("run.sverec", pattern="1,4/16,64") as w:
        for frame in source.frames(100):
            w.append(frame)
    with RecordingReader("run.sverec") as r:
        frame = r.read(42)          # constant-time seek

The layout is in replay/container.py and docs/recording-format.md.
"""

from replay.container import RecordingError
from replay.reader import CorruptFrameError, RecordingReader
from replay.writer import RecordingWriter, WriterConfig

__all__ = ["CorruptFrameError", "RecordingError", "RecordingReader", "RecordingWriter", "WriterConfig"]
