"""The sample sources behind the device URLs (:mod:`.device_url`), and :func:`open_source`, which picks one: the
trakSTAR (:mod:`.trakstar.source`), the Aurora (:mod:`.aurora.source`), a replayed recording
(:class:`ReplaySource`), an OpenIGTLink server (:class:`IGTLSource`). Each calls ``callback(sample)`` from its own
thread for every sensor sample (``SensorToTracker``, mm).
"""

from __future__ import annotations

import threading
import time

import numpy as np

from ..core.tracking import SAME_MOMENT_LIMIT_S, sensor_pair
from ..errors import EMRegError
from ..io.recording import read_recording
from ..names import DEFAULT_PROBE_PORT, DEFAULT_REFERENCE_PORT
from .aurora.source import AuroraSource
from .device_url import DeviceURL, parse_device_url
from .igtl_client import IGTLReceiver
from .igtl_server import TRANSFORM_OK, transform_status
from .samples import STATUS_OK, SensorSample
from .source_base import SampleCallback, SampleSource
from .trakstar.source import TrakstarSource


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


def open_source(url: str | DeviceURL, reference_sensor: int = DEFAULT_REFERENCE_PORT,
                probe_sensor: int = DEFAULT_PROBE_PORT, fast: bool = False, loop: bool = False) -> SampleSource:
    """The source behind a device URL (the trakSTAR is opened and configured here)."""
    parsed = parse_device_url(url) if isinstance(url, str) else url
    if parsed.kind == "trakstar":
        return TrakstarSource(parsed)
    if parsed.kind == "aurora":
        return AuroraSource(parsed)
    if parsed.kind == "replay":
        return ReplaySource(parsed.path, fast=fast, loop=loop)
    if parsed.kind == "igtl":
        return IGTLSource(parsed, reference_sensor, probe_sensor)
    raise EMRegError(f"device {parsed.text!r}: unknown kind {parsed.kind}")
