"""A line-updating progress counter for long commands, on stderr (standard library only).

    with Progress("reconstructing", total=len(frames), quiet=args.quiet) as progress:
        for frame in frames:
            ...
            progress.update()

On a terminal the line is rewritten in place (carriage return) at most every
``interval_s``; into a file or pipe (a log) a full line is written at most every
``log_interval_s``, so logs stay readable. ``close()`` ends with one final line
(count, elapsed time, rate), unless quiet or the command failed (its error is
then the last line). stdout is never touched:
commands keep printing their results there.
"""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TextIO


def format_progress(label: str, done: int, total: int | None, elapsed_s: float, unit: str = "frames",
                    skipped: int = 0) -> str:
    """One status line, e.g. ``reconstructing: 120/300 frames (40%), 8.1 frames/s, 22 s left``.

    ``skipped`` (counted in ``done``) is named and left out of the rate, which counts the
    work done in ``elapsed_s`` seconds.
    """
    count = f"{done}/{total} {unit}" if total else f"{done} {unit}"
    if total:
        count += f" ({100 * done // total}%)"
    if skipped:
        count += f", {skipped} skipped"
    worked = done - skipped
    parts = [f"{label}: {count}"]
    if elapsed_s > 0 and worked > 0:
        rate = worked / elapsed_s
        parts.append(f"{rate:.3g} {unit}/s")
        if total and done < total:
            parts.append(f"{_duration((total - done) / rate)} left")
    else:
        parts.append(f"{_duration(elapsed_s)}")
    return ", ".join(parts)


def _duration(seconds: float) -> str:
    """``42 s``, ``3 min 05 s``, ``1 h 02 min``."""
    s = int(round(seconds))
    if s < 60:
        return f"{s} s"
    if s < 3600:
        return f"{s // 60} min {s % 60:02d} s"
    return f"{s // 3600} h {s % 3600 // 60:02d} min"


@dataclass
class Progress:
    """A progress counter; see the module docstring.

    Attributes:
        label: what is being done, first on the line.
        total: the count at the end, or None when unknown (a live source).
        unit: what is counted (plural), e.g. ``frames``.
        quiet: print nothing at all.
        stream: where to write (default: stderr at construction).
        interval_s: least time between two rewrites of a terminal line.
        log_interval_s: least time between two lines into a file or pipe.
        clock: seconds, monotonic (injectable for tests).
    """

    label: str
    total: int | None = None
    unit: str = "frames"
    quiet: bool = False
    stream: TextIO | None = None
    interval_s: float = 0.2
    log_interval_s: float = 10.0
    clock: Callable[[], float] = time.monotonic
    done: int = field(default=0, init=False)
    skipped: int = field(default=0, init=False)

    def __post_init__(self) -> None:
        if self.stream is None:
            self.stream = sys.stderr
        isatty = getattr(self.stream, "isatty", None)
        self._tty = bool(isatty and isatty())
        self._start = self.clock()
        self._shown = self._start
        self._width = 0
        self._closed = False

    @property
    def elapsed_s(self) -> float:
        """Seconds since the counter was made."""
        return self.clock() - self._start

    def line(self) -> str:
        """The current status line."""
        return format_progress(self.label, self.done, self.total, self.elapsed_s, self.unit, self.skipped)

    def update(self, n: int = 1, *, skipped: bool = False) -> None:
        """Count ``n`` more done (``skipped``: done without work, e.g. an output that already existed)."""
        self.done += n
        if skipped:
            self.skipped += n
        if self.quiet:
            return
        now = self.clock()
        if now - self._shown >= (self.interval_s if self._tty else self.log_interval_s):
            self._shown = now
            self._show(final=False)

    def _show(self, final: bool) -> None:
        assert self.stream is not None
        text = self.line()
        if self._tty:
            pad = " " * max(0, self._width - len(text))
            self._width = len(text)
            self.stream.write(f"\r{text}{pad}" + ("\n" if final else ""))
        else:
            self.stream.write(text + "\n")
        self.stream.flush()

    def close(self, failed: bool = False) -> None:
        """Write the final line (once), unless quiet. ``failed``: the command is ending with an error,
        which is then the last line: only a line shown on a terminal is ended."""
        if self._closed:
            return
        self._closed = True
        if self.quiet:
            return
        if not failed:
            self._show(final=True)
        elif self._tty and self._width:
            assert self.stream is not None
            self.stream.write("\n")
            self.stream.flush()

    def __enter__(self) -> Progress:
        return self

    def __exit__(self, kind: object, *exc: object) -> None:
        self.close(failed=kind is not None)


def add_quiet_argument(parser: argparse.ArgumentParser) -> None:
    """Add ``-q/--quiet`` (no progress output) to a command's parser; read it as ``args.quiet``."""
    parser.add_argument("-q", "--quiet", action="store_true", help="no progress output on stderr")
