"""What every live loop shares (``emreg record``, ``serve``, ``sim-tracker``, live ``navigate``, the robot): the
options its command line gives, the stop flag that SIGINT / SIGTERM set, the wait until the source ends or a limit is
reached, the check that the sensors it needs are attached, and the tracker link's framing counters.

Every loop stops by itself with ``duration_s`` / ``max_samples`` (or on Ctrl-C / SIGTERM), and its caller releases
the serial port, the sockets and the pty.
"""

from __future__ import annotations

import signal
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import TextIO

from ..core.tool import ToolCalibration
from ..devices.source_base import SampleSource
from ..errors import EMRegError
from .guide_setup import check_tool_on_port
from .navigator import DEFAULT_MAX_QUALITY


@dataclass(frozen=True)
class LiveOptions:
    """What the command line tells a live loop: replay speed, the limits that end it (s, samples), the watchdog's
    staleness (sample periods) and quality limit (None: the source's own scale; negative: not checked), and whether
    it says what it does on stderr."""

    fast: bool = False
    loop: bool = False
    duration_s: float | None = None
    max_samples: int | None = None
    stale_periods: float = 3.0
    max_quality: float | None = None
    quiet: bool = False

    def say(self, text: str) -> None:
        """One line on stderr, unless quiet."""
        if not self.quiet:
            print(text, file=sys.stderr, flush=True)

    @property
    def log(self) -> TextIO | None:
        """Where the servers and the watchdog write their lines (None when quiet)."""
        return None if self.quiet else sys.stderr


def max_quality_limit(given: float | None, source_default: float | None) -> float | None:
    """The tracker quality number above which a sample is withheld: ``given`` (negative: None, not checked), else the
    source's own scale (the Aurora's RMS error, mm), else the trakSTAR's METAL number."""
    if given is None:
        return float(source_default or DEFAULT_MAX_QUALITY)
    return None if given < 0 else given


class StopFlag:
    """Set by SIGTERM / SIGINT so loops end cleanly (the previous handlers come back afterwards)."""

    def __init__(self) -> None:
        self.event = threading.Event()
        self._previous: dict[int, object] = {}

    def __enter__(self) -> StopFlag:
        if threading.current_thread() is threading.main_thread():
            for sig in (signal.SIGTERM, signal.SIGINT):
                self._previous[sig] = signal.signal(sig, lambda *_: self.event.set())
        return self

    def __exit__(self, *exc: object) -> None:
        for sig, handler in self._previous.items():
            signal.signal(sig, handler)


def run_loop(source, stop: StopFlag, duration_s: float | None, done: Callable[[], bool],
             tick: Callable[[], object] | None = None, interval_s: float = 0.01) -> str:
    """Wait until the source ends, a limit is reached or a signal arrives; returns why."""
    deadline = None if duration_s is None else time.monotonic() + duration_s
    while True:
        if stop.event.wait(interval_s):
            return "interrupted"
        if tick is not None:
            tick()
        if source.error:
            raise EMRegError(source.error)
        if done():
            return "sample limit reached"
        if deadline is not None and time.monotonic() >= deadline:
            return "duration reached"
        if source.finished.is_set():
            return "source finished"


def run_until_stopped(sim) -> None:
    """Run a simulator until it ends by itself or SIGINT/SIGTERM asks it to stop; close it either way."""
    with StopFlag() as stop:
        watcher = threading.Thread(target=lambda: (stop.event.wait(), sim._stop.set()), daemon=True)
        watcher.start()
        try:
            sim.run()
        finally:
            stop.event.set()
            sim.close()


def check_ports_attached(source: SampleSource, reference: int, probe: int,
                         tool: ToolCalibration | None = None) -> None:
    """Refuse (exit 2) a reference or probe port without a sensor, when the source can tell; a replay's
    recording is judged whole, as the offline commands judge it (absent, still or swapped ports). ``tool``: the
    tool on the probe port, refused on a 5-DOF sensor unless its tip lies on the sensor's axis
    (:func:`~EMRegModule.live.guide_setup.check_tool_on_port`). The source is stopped when refused."""
    attached = source.attached_ports()
    try:
        source.check_ports(reference, probe)
        for role, port in (("reference", reference), ("probe", probe)) if attached is not None else ():
            if port not in attached:
                what = "" if tool is None or role == "reference" else f" for the tool of {tool.source}"
                raise EMRegError(f"{source.description}: no sensor on the {role} port {port}{what} (sensors on "
                                 f"ports {', '.join(map(str, attached)) or 'none'}); plug it in or set --{role}-sensor")
        if tool is not None:
            check_tool_on_port(source, probe, tool)
    except EMRegError:
        source.stop()
        raise


def framing_text(source) -> str | None:
    """The tracker driver's framing counters in one line (None for a source without a serial link)."""
    if hasattr(source, "framing_summary"):  # the Aurora's own counters
        return source.framing_summary().removeprefix("[emreg] ")
    driver = getattr(source, "driver", None)
    if driver is None:
        return None
    st = driver.stats
    return (f"trakSTAR records: {st.records} accepted, {st.rejected} rejected (phase {st.phase_errors}, address "
            f"{st.address_errors}, follow {st.follow_errors}, gap {st.gap_errors}, values {st.value_errors}), "
            f"{st.stray_bytes} stray bytes")


@dataclass(frozen=True)
class LiveOutcome:
    """How a live loop ended: its summary line (stdout) and the tracker link's framing counters (stderr; None
    without a serial link)."""

    summary: str
    framing: str | None = None
