"""Per-stage timing, the one progress line per stage printed on stderr, and warnings.

A stitch never lets a raw Python warning reach the user: :class:`WarningLog` records
library warnings (numpy, torch, Pillow, ...) and pis3r's own notes as one plain line each,
printed as ``[pis3r] warning: ...`` (unless quiet) and kept for ``report.json``.
"""

from __future__ import annotations

import sys
import time
import warnings
from contextlib import contextmanager


class StageTimer:
    """Times named stages; prints ``[pis3r] stage ... 0.42 s`` unless ``quiet``.

    A line said while a stage runs (a warning) goes on a line of its own; the stage then
    ends with ``[pis3r] stage done 0.42 s``."""

    def __init__(self, quiet: bool = False, prefix: str = "") -> None:
        self.quiet = quiet
        self.prefix = prefix
        self.seconds: dict[str, float] = {}
        self._open_line = False

    def child(self, prefix: str) -> "StageTimer":
        """A timer for sub-stages, printing with ``prefix`` and this timer's quietness."""
        return StageTimer(quiet=self.quiet, prefix=prefix)

    def say(self, message: str) -> None:
        if not self.quiet:
            print(("\n" if self._open_line else "") + f"[pis3r] {self.prefix}{message}", file=sys.stderr, flush=True)
            self._open_line = False

    @contextmanager
    def stage(self, name: str):
        start = time.perf_counter()
        if not self.quiet:
            print(f"[pis3r] {self.prefix}{name} ...", end="", file=sys.stderr, flush=True)
            self._open_line = True
        try:
            yield
        finally:
            elapsed = time.perf_counter() - start
            self.seconds[name] = self.seconds.get(name, 0.0) + elapsed
            if not self.quiet:
                ending = f" {elapsed:.2f} s" if self._open_line else f"[pis3r] {self.prefix}{name} done {elapsed:.2f} s"
                print(ending, file=sys.stderr, flush=True)
                self._open_line = False


class WarningLog:
    """One-line warnings of a stitch, in the order they happened, each said once."""

    def __init__(self, timer: StageTimer) -> None:
        self.timer = timer
        self.lines: list[str] = []

    def add(self, line: str) -> None:
        line = " ".join(str(line).split())
        if line and line not in self.lines:
            self.lines.append(line)
            self.timer.say(f"warning: {line}")

    @contextmanager
    def capture(self):
        """Record every Python warning raised inside the block as one line (category: message)."""
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("default")
            try:
                yield self
            finally:
                for record in caught:
                    self.add(f"{record.category.__name__}: {record.message}")
