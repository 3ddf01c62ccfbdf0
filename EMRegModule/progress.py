"""Terminal progress for long work (reading a large CT, detection, batch reports).

On a terminal it redraws one line with a bar; elsewhere (logs, CI) it prints one line
per step start so that output stays short. Always on stderr.
"""

from __future__ import annotations

import sys
import time
from typing import TextIO


class Progress:
    """A step counter with a bar: ``with progress.step("detect", total=28) as step: step.advance()``."""

    def __init__(self, stream: TextIO | None = None, enabled: bool = True) -> None:
        self.stream = stream or sys.stderr
        self.enabled = enabled
        self.interactive = bool(getattr(self.stream, "isatty", lambda: False)())

    def step(self, name: str, total: int | None = None, per_minute: str | None = None) -> _Step:
        """Start a named step of ``total`` units (None: unknown length).

        ``per_minute`` names the units (e.g. "cases") to show the throughput in units per minute.
        """
        return _Step(self, name, total, per_minute)

    def message(self, text: str) -> None:
        """One line of information."""
        if self.enabled:
            print(text, file=self.stream, flush=True)


class _Step:
    def __init__(self, progress: Progress, name: str, total: int | None, per_minute: str | None = None) -> None:
        self.progress = progress
        self.per_minute = per_minute
        self.name = name
        self.total = total
        self.done = 0
        self.start = time.perf_counter()
        self._last_draw = 0.0

    def __enter__(self) -> _Step:
        if self.progress.enabled and not self.progress.interactive:
            print(f"[emreg] {self.name} ...", file=self.progress.stream, flush=True)
        self._draw(force=True)
        return self

    def advance(self, units: int = 1) -> None:
        self.done += units
        self._draw()

    def _draw(self, force: bool = False, final: bool = False) -> None:
        if not (self.progress.enabled and self.progress.interactive):
            return
        now = time.perf_counter()
        if not (force or final) and now - self._last_draw < 0.1:
            return
        self._last_draw = now
        elapsed = now - self.start
        if self.total:
            fraction = min(1.0, self.done / self.total)
            bar = "#" * int(24 * fraction) + "-" * (24 - int(24 * fraction))
            text = f"\r[emreg] {self.name:<22} [{bar}] {self.done}/{self.total} {elapsed:6.1f}s"
        else:
            text = f"\r[emreg] {self.name:<22} {elapsed:6.1f}s"
        text += self._rate(elapsed)
        self.progress.stream.write(text + ("\n" if final else ""))
        self.progress.stream.flush()

    def __exit__(self, exc_type, exc, tb) -> None:
        if self.progress.interactive:
            self._draw(final=True)
        elif self.progress.enabled and exc_type is None:
            elapsed = time.perf_counter() - self.start
            print(f"[emreg] {self.name} done in {elapsed:.1f}s{self._rate(elapsed)}", file=self.progress.stream,
                  flush=True)

    def _rate(self, elapsed: float) -> str:
        if not self.per_minute or not self.done or elapsed <= 0:
            return ""
        return f", {60.0 * self.done / elapsed:.1f} {self.per_minute}/min"


QUIET = Progress(enabled=False)
