"""Live sample sources behind the device URLs: the trakSTAR driver, the Aurora driver
(:mod:`.aurora_driver`), a replayed recording, an OpenIGTLink server. Each calls ``callback(sample)``
from its own thread for every sensor sample.
"""

from __future__ import annotations

import threading
import time
from abc import ABC, abstractmethod
from collections.abc import Callable

import numpy as np

from ..errors import EMRegError
from ..io.recording import read_recording
from ..tracking import SAME_MOMENT_LIMIT_S, sensor_pair
from .device_url import DeviceURL, parse_device_url
from .samples import STATUS_OK, SensorSample

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

    def __enter__(self) -> SampleSource:
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()


class DriverSource(SampleSource):
    """A source over a tracker driver that reads on its own thread and reports a failure in ``driver.error``.

    Subclasses set ``self.driver`` and implement :meth:`_start_driver`; a watch thread turns the driver's
    error into ``self.error`` and ``finished``.
    """

    watch_name = "tracker-watch"

    def __init__(self) -> None:
        super().__init__()
        self.driver = None
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


class TrakstarSource(DriverSource):
    """A trakSTAR (or the simulator) streaming every sensor in group mode."""

    watch_name = "trakstar-watch"

    def __init__(self, url: DeviceURL) -> None:
        super().__init__()
        from .trakstar_driver import TrakstarDriver

        options = url.options
        self.driver = TrakstarDriver(url.path, url.baud, max_gap_ms=float(options.get("gap_ms", 50)))
        self.driver.open()
        try:
            self.driver.configure(
                options.get("format", "POSITION/ANGLES"), metal=options.get("metal", "1") not in ("0", "false", "no"),
                group=True, rate_hz=float(options["rate"]) if "rate" in options else None,
                scale_inches=int(options["scale"]) if "scale" in options else None)
        except BaseException:
            self.driver.close()
            raise
        self.period_s = 1.0 / self.driver.rate_hz
        self.description = f"trakSTAR on {url.path} at {url.baud} baud, {self.driver.rate_hz:g} Hz"

    def attached_ports(self) -> tuple[int, ...]:
        """Ports with a sensor plugged in (the tracker's sensor serial number is non-zero)."""
        return tuple(s for s in self.driver.group_sensors if self.driver.sensor_attached(s))

    def link_counts(self) -> tuple[int, int]:
        """Cumulative (accepted, rejected) records of the serial link (for the link-quality monitor)."""
        stats = self.driver.stats
        return stats.records, stats.rejected

    def _start_driver(self, callback: SampleCallback) -> None:
        self.driver.start_stream(callback)


class ReplaySource(SampleSource):
    """A tracking recording played at its own rate (``fast``: as fast as possible; ``loop``: again and again).

    Rows of one moment (``time_s`` within 1 ms) form a frame and are delivered together with the
    same ``frame`` index; ``time_s`` is the recording's own (plus the loop offset).
    """

    def __init__(self, path: str, fast: bool = False, loop: bool = False) -> None:
        super().__init__()
        self.recording = read_recording(path)
        self.fast = fast
        self.loop = loop
        rec = self.recording
        order = np.argsort(rec.time_s, kind="stable")
        self._order = order
        times = rec.time_s[order]
        starts = np.flatnonzero(np.concatenate([[True], np.diff(times) > SAME_MOMENT_LIMIT_S]))
        self._frames = [order[a:b] for a, b in zip(starts, list(starts[1:]) + [len(order)], strict=True)]
        self._frame_times = times[starts]
        steps = np.diff(self._frame_times)
        self.period_s = float(np.median(steps)) if len(steps) else 0.05
        self.duration_s = float(self._frame_times[-1] - self._frame_times[0]) + self.period_s
        self.description = f"replay of {path} ({len(self._frames)} frames, {1 / self.period_s:.0f} Hz" + \
            (", fast" if fast else "") + (", loop" if loop else "") + ")"
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.frames_sent = 0

    def check_ports(self, reference_port: int, probe_port: int) -> None:
        """Refuse (:class:`EMRegError`, exit 2) the port mistakes an offline command refuses on this recording:
        the same port twice, an absent port, a probe that never moves relative to the reference, swapped ports."""
        sensor_pair(self.recording, reference_port, probe_port)

    def start(self, callback: SampleCallback) -> None:
        self._thread = threading.Thread(target=self._run, args=(callback,), name="replay", daemon=True)
        self._thread.start()

    def _run(self, callback: SampleCallback) -> None:
        rec = self.recording
        t0 = time.monotonic()
        first = self._frame_times[0]
        loop_index = 0
        frame_index = 0
        try:
            while not self._stop.is_set():
                offset = loop_index * self.duration_s
                for rows, t_frame in zip(self._frames, self._frame_times, strict=True):
                    if self._stop.is_set():
                        return
                    if not self.fast:
                        delay = t0 + offset + (t_frame - first) - time.monotonic()
                        if delay > 0 and self._stop.wait(delay):
                            return
                    now_ns = time.monotonic_ns()
                    for i in rows:
                        callback(SensorSample(
                            int(rec.sensor[i]), float(rec.time_s[i] + offset), rec.position_mm[i].copy(),
                            rec.rotation[i].copy(), float(rec.quality[i]), label=str(rec.label[i] or ""),
                            frame=frame_index, received_ns=now_ns))
                    frame_index += 1
                    self.frames_sent += 1
                if not self.loop:
                    return
                loop_index += 1
        finally:
            self.finished.set()

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join(timeout=2.0)
        self.finished.set()


class IGTLSource(SampleSource):
    """Transforms from another OpenIGTLink server (``emreg serve`` or PLUS).

    ``ReferenceToTracker`` / ``ProbeToTracker`` (or the names given in the URL) become samples of
    the reference and probe ports. They are tracker-frame transforms and are taken as sent, in
    millimetres, with no RAS/LPS change (the Tracker frame is the transmitter's own, neither LPS
    nor RAS; ``emreg serve`` sends it unchanged too). Transforms sharing a timestamp (within 1 ms)
    form one frame. A sensor the server stops sending (not attached, out of range) shows up as
    missing in the watchdog.
    """

    def __init__(self, url: DeviceURL, reference_sensor: int, probe_sensor: int) -> None:
        super().__init__()
        self.url = url
        self.names = {url.options.get("reference", "ReferenceToTracker"): reference_sensor,
                      url.options.get("probe", "ProbeToTracker"): probe_sensor}
        self.description = f"OpenIGTLink server {url.host}:{url.port} ({', '.join(self.names)})"
        self.receiver = None
        self._frame = -1
        self._frame_stamp = None
        self._t0: float | None = None

    def start(self, callback: SampleCallback) -> None:
        from .igtl_client import IGTLReceiver
        from .igtl_server import TRANSFORM_OK, transform_status

        def on_message(message) -> None:
            sensor = self.names.get(message.device_name)
            if sensor is None:
                return
            now_ns = time.monotonic_ns()
            if getattr(message, "message_type", "") != "TRANSFORM":
                return
            stamp = float(message.timestamp)
            if self._frame_stamp is None or abs(stamp - self._frame_stamp) > SAME_MOMENT_LIMIT_S:
                self._frame += 1
                self._frame_stamp = stamp
            matrix = np.asarray(message.matrix, dtype=float)
            # PLUS's status metadata (header version 2): a transform whose TransformStatus is not OK
            # (or TransformValid false) carries no valid pose and is never used as one
            status = transform_status(message)
            callback(SensorSample(sensor, self._time(stamp), matrix[:3, 3].copy(), matrix[:3, :3].copy(),
                                  status=STATUS_OK if status == TRANSFORM_OK else status.lower(),
                                  frame=self._frame, received_ns=now_ns))

        self.receiver = IGTLReceiver(self.url.host, self.url.port, on_message)

    def _time(self, stamp: float) -> float:
        if self._t0 is None:
            self._t0 = stamp
        return stamp - self._t0

    def stop(self) -> None:
        if self.receiver is not None:
            self.receiver.close()
        self.finished.set()


def open_source(url: str | DeviceURL, reference_sensor: int = 1, probe_sensor: int = 2, fast: bool = False,
                loop: bool = False) -> SampleSource:
    """The source behind a device URL (the trakSTAR is opened and configured here)."""
    parsed = parse_device_url(url) if isinstance(url, str) else url
    if parsed.kind == "trakstar":
        return TrakstarSource(parsed)
    if parsed.kind == "aurora":
        from .aurora_driver import AuroraSource

        return AuroraSource(parsed)
    if parsed.kind == "replay":
        return ReplaySource(parsed.path, fast=fast, loop=loop)
    if parsed.kind == "igtl":
        return IGTLSource(parsed, reference_sensor, probe_sensor)
    raise EMRegError(f"device {parsed.text!r}: unknown kind {parsed.kind}")
