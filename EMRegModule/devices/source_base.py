"""What every live sample source is: :class:`SampleSource` (a running source of
:class:`~.samples.SensorSample`, ``SensorToTracker`` in mm, delivered to a callback from the source's own
thread) and :class:`DriverSource` (a source over a serial tracker driver that reads on its own thread).
The device sources (:mod:`.trakstar.source`, :mod:`.aurora.source`) and the others (:mod:`.sources`) build
on it.
"""

from __future__ import annotations

import threading
import time
from abc import ABC, abstractmethod
from collections.abc import Callable
from typing import Protocol

from .samples import SensorSample

SampleCallback = Callable[[SensorSample], None]


class SampleSource(ABC):
    """A running source of :class:`SensorSample` (``SensorToTracker``, mm)."""

    #: Nominal time between samples of one sensor (None: unknown, the watchdog estimates it).
    period_s: float | None = None
    description: str = ""

    def __init__(self) -> None:
        self.finished = threading.Event()
        self.error: str | None = None

    @abstractmethod
    def start(self, callback: SampleCallback) -> None:
        """Start delivering samples to ``callback`` (from a background thread)."""

    @abstractmethod
    def stop(self) -> None:
        """Stop delivering and release the device (idempotent)."""

    def check_ports(self, reference_port: int, probe_port: int) -> None:
        """Refuse (:class:`~EMRegModule.errors.EMRegError`, one line) ports the source can judge before it starts (a
        replay's whole recording: absent, still or swapped); a device judges its ports live instead."""
        return None

    def attached_ports(self) -> tuple[int, ...] | None:
        """The ports with a sensor plugged in, when the device can tell (None: it cannot, as over OpenIGTLink or a
        replay)."""
        return None

    def port_dof(self, port: int) -> int | None:
        """The degrees of freedom (5 or 6) of the sensor on ``port``, when the device can tell (None otherwise)."""
        return None

    def __enter__(self) -> SampleSource:
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()


class TrackerDriver(Protocol):
    """What :class:`DriverSource` needs of a driver: its failure (None while it works) and ``close()``."""

    error: str | None

    def close(self) -> None: ...


class DriverSource(SampleSource):
    """A source over a tracker driver that reads on its own thread and reports a failure in ``driver.error``.

    Subclasses set ``self.driver`` and implement :meth:`_start_driver`; a watch thread turns the driver's
    error into ``self.error`` and ``finished``.
    """

    watch_name = "tracker-watch"

    def __init__(self) -> None:
        super().__init__()
        self.driver: TrackerDriver | None = None
        self._watch: threading.Thread | None = None

    @abstractmethod
    def _start_driver(self, callback: SampleCallback) -> None:
        """Start the driver delivering samples to ``callback``."""

    def start(self, callback: SampleCallback) -> None:
        self._start_driver(callback)
        self._watch = threading.Thread(target=self._watch_errors, name=self.watch_name, daemon=True)
        self._watch.start()

    def _watch_errors(self) -> None:
        while not self.finished.is_set():
            if self.driver.error:
                self.error = self.driver.error
                self.finished.set()
                return
            time.sleep(0.05)

    def stop(self) -> None:
        self.finished.set()
        self.driver.close()
        if self._watch is not None:
            self._watch.join(timeout=1.0)
