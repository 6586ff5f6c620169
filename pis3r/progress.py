"""Per-stage timing and the one progress line per stage printed on stderr."""

from __future__ import annotations

import sys
import time
from contextlib import contextmanager


class StageTimer:
    """Times named stages; prints ``[pis3r] stage ... 0.42 s`` unless ``quiet``."""

    def __init__(self, quiet: bool = False, prefix: str = "") -> None:
        self.quiet = quiet
        self.prefix = prefix
        self.seconds: dict[str, float] = {}

    def say(self, message: str) -> None:
        if not self.quiet:
            print(f"[pis3r] {self.prefix}{message}", file=sys.stderr, flush=True)

    @contextmanager
    def stage(self, name: str):
        start = time.perf_counter()
        if not self.quiet:
            print(f"[pis3r] {self.prefix}{name} ...", end="", file=sys.stderr, flush=True)
        try:
            yield
        finally:
            elapsed = time.perf_counter() - start
            self.seconds[name] = self.seconds.get(name, 0.0) + elapsed
            if not self.quiet:
                print(f" {elapsed:.2f} s", file=sys.stderr, flush=True)
