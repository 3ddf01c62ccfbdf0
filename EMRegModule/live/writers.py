"""CSV files written while data arrive: flushed (and synced) at least once a second.

A live recording cannot be written atomically at the end without risking the whole session on a
crash, so these files are written in place: the header first, then rows, flushed to disk every
``flush_interval_s`` so that a crash loses at most the last second. (Files produced in one go
elsewhere in EMReg are written atomically.)
"""

from __future__ import annotations

import contextlib
import os
import threading
import time
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from ..core.tracking import TrackingRecording
from ..core.transforms import rotation_to_angles
from ..devices.samples import SensorSample
from ..io.atomic import atomic_write_text
from ..io.navigation_csv import GUIDANCE_COLUMNS, NAVIGATION_HEADER, guidance_fields
from ..io.sequence_metafile import format_sequence_metafile
from ..io.tracking_csv import HEADER_ANGLES
from ..names import DEFAULT_PROBE_PORT, DEFAULT_REFERENCE_PORT


class StreamingCSV:
    """Append rows to a CSV file, flushing and fsync-ing at least every ``flush_interval_s``."""

    def __init__(self, path: str | os.PathLike[str], header: Sequence[str], flush_interval_s: float = 1.0) -> None:
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._file = open(self.path, "w", encoding="utf-8", newline="")  # noqa: SIM115 (closed in close())
        self._file.write(",".join(header) + "\n")
        self._lock = threading.Lock()
        self.flush_interval_s = flush_interval_s
        self._last_flush = time.monotonic()
        self.rows = 0
        self._sync()

    def write_row(self, cells: Sequence[str]) -> None:
        with self._lock:
            if self._file.closed:
                return
            self._file.write(",".join(cells) + "\n")
            self.rows += 1
            if time.monotonic() - self._last_flush >= self.flush_interval_s:
                self._sync()

    def _sync(self) -> None:
        self._file.flush()
        with contextlib.suppress(OSError):
            os.fsync(self._file.fileno())
        self._last_flush = time.monotonic()

    def close(self) -> None:
        with self._lock:
            if not self._file.closed:
                self._sync()
                self._file.close()

    def __enter__(self) -> StreamingCSV:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class RecordingWriter(StreamingCSV):
    """The spec's tracking CSV (``time_s,sensor,x_mm,...,roll_deg,quality,label``) from live samples."""

    def __init__(self, path: str | os.PathLike[str], flush_interval_s: float = 1.0) -> None:
        super().__init__(path, HEADER_ANGLES, flush_interval_s)

    def write_sample(self, sample: SensorSample) -> bool:
        """Write one sample; samples without a usable pose are skipped (returns False)."""
        if not sample.valid:
            return False
        angles = sample.angles_deg if sample.angles_deg is not None else rotation_to_angles(sample.rotation)
        quality = "" if np.isnan(sample.quality) else f"{sample.quality:g}"
        self.write_row([f"{sample.time_s:.4f}", str(sample.sensor), *(f"{v:.4f}" for v in sample.position_mm),
                        *(f"{v:.6f}" for v in angles), quality, sample.label])
        return True


class SequenceRecordingWriter(RecordingWriter):
    """A PLUS sequence metafile (``.seq.mha``) recorded live: the valid samples also stream into a
    sidecar CSV (``<path>.partial.csv``, flushed like every live file, so a crash keeps them); at
    :meth:`close` every sample, with its status (``OK``, or the source's reason for an unusable
    pose: :attr:`~.samples.SensorSample.transform_status`, e.g. ``OUT_OF_VOLUME``), is written into the
    sequence metafile atomically (its header needs the frame count) and the sidecar is removed."""

    def __init__(self, path: str | os.PathLike[str], flush_interval_s: float = 1.0,
                 reference_port: int = DEFAULT_REFERENCE_PORT, probe_port: int = DEFAULT_PROBE_PORT) -> None:
        self.target = Path(path)
        self.reference_port, self.probe_port = reference_port, probe_port
        self._samples: list[tuple] = []
        super().__init__(self.target.with_name(self.target.name + ".partial.csv"), flush_interval_s)

    def write_sample(self, sample: SensorSample) -> bool:
        with self._lock:
            if not self._file.closed:
                self._samples.append((sample.time_s, sample.sensor, np.asarray(sample.position_mm, dtype=float),
                                      np.asarray(sample.rotation, dtype=float), sample.quality,
                                      sample.transform_status))
        return super().write_sample(sample)

    def close(self) -> None:
        with self._lock:
            was_open = not self._file.closed
        super().close()
        if not was_open:
            return
        if self._samples:
            time_s, sensor, position, rotation, quality, status = zip(*self._samples, strict=True)
            recording = TrackingRecording(np.array(time_s), np.array(sensor), np.array(position).reshape(-1, 3),
                                          np.array(rotation).reshape(-1, 3, 3), np.array(quality, dtype=float),
                                          np.full(len(time_s), "", dtype=object), source=str(self.target))
            statuses = np.array(status, dtype=object)
            text = format_sequence_metafile(recording, reference_port=self.reference_port,
                                            probe_port=self.probe_port,
                                            statuses={int(p): statuses for p in np.unique(recording.sensor)})
            atomic_write_text(self.target, text)
        self.path.unlink(missing_ok=True)


class NavigationWriter(StreamingCSV):
    """``navigation.csv`` (``time_s,x_mm,y_mm,z_mm,label,status``): the probe position (a tool's tip) in LPS image
    space and the pose's status (``OK``, or ``INVALID`` after a failed checkpoint), as the offline ``emreg
    navigate``; ``guidance``: with a plan, the guidance columns follow (mm, degrees; empty where undefined)."""

    def __init__(self, path: str | os.PathLike[str], flush_interval_s: float = 1.0, guidance: bool = False) -> None:
        super().__init__(path, (*NAVIGATION_HEADER.split(","), *(GUIDANCE_COLUMNS if guidance else ())),
                         flush_interval_s)

    def write_position(self, time_s: float, position_image_mm: np.ndarray, label: str = "", status: str = "OK",
                       numbers: tuple[float, ...] | None = None) -> None:
        cells = [f"{time_s:.4f}", *(f"{v:.4f}" for v in position_image_mm), label, status]
        if numbers is not None:
            cells.append(guidance_fields(numbers))
        self.write_row(cells)
