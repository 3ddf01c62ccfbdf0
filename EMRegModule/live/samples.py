"""One sensor sample as every live source delivers it (trakSTAR driver, replay, OpenIGTLink client)."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

#: Sample status values: ``ok``; ``out_of_range`` (the sensor left the tracker's position range);
#: ``not_attached`` (no sensor on the port); ``bad_quality`` is decided by the watchdog from ``quality``.
STATUS_OK = "ok"
STATUS_OUT_OF_RANGE = "out_of_range"
STATUS_NOT_ATTACHED = "not_attached"


@dataclass
class SensorSample:
    """A sensor pose ``SensorToTracker`` at one moment: position (mm) and rotation (3x3).

    ``time_s``: seconds on the source's clock (tracker: since the stream started; replay: the
    recording's ``time_s``). ``received_ns``: ``time.monotonic_ns()`` when the sample's last byte
    was read (for latency figures). ``quality``: the tracker's quality number (0 = best; NaN when
    the source has none). ``frame``: index of the measurement cycle the sample belongs to (samples
    of one cycle share ``time_s``).
    """

    sensor: int
    time_s: float
    position_mm: np.ndarray
    rotation: np.ndarray
    quality: float = float("nan")
    status: str = STATUS_OK
    label: str = ""
    frame: int = -1
    received_ns: int = 0
    angles_deg: np.ndarray | None = None
    extra: dict = field(default_factory=dict)

    @property
    def valid(self) -> bool:
        """True when the pose can be used (status ok and finite numbers)."""
        return (self.status == STATUS_OK and bool(np.all(np.isfinite(self.position_mm)))
                and bool(np.all(np.isfinite(self.rotation))))

    def transform(self) -> np.ndarray:
        """``SensorToTracker`` 4x4."""
        out = np.eye(4)
        out[:3, :3] = self.rotation
        out[:3, 3] = self.position_mm
        return out
