"""One sensor sample as every live source delivers it (trakSTAR driver, replay, OpenIGTLink client)."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

#: Sample status values: ``ok``; ``out_of_range`` (the sensor left the tracker's position range);
#: ``not_attached`` (no sensor on the port); ``bad_quality`` is decided by the watchdog from ``quality``.
STATUS_OK = "ok"
STATUS_OUT_OF_RANGE = "out_of_range"
STATUS_NOT_ATTACHED = "not_attached"
#: Finer reasons a tracker gives for a pose it does not vouch for, in ``SensorSample.extra["flag"]`` (the status
#: stays ``out_of_range``): the Aurora's handle status - no solution (MISSING), out of the characterised volume
#: (port status 0x40), partly out of it (0x80).
FLAG_MISSING = "missing"
FLAG_OUT_OF_VOLUME = "out_of_volume"
FLAG_PARTLY_OUT_OF_VOLUME = "partly_out_of_volume"
#: PLUS ``TransformStatus`` names of the flags (``OK``, ``MISSING``, ``OUT_OF_VOLUME`` are PLUS's own; PLUS has
#: no "partly": EMReg's name, read by PLUS and 3D Slicer as not OK, like any other).
FLAG_TRANSFORM_STATUS = {FLAG_MISSING: "MISSING", FLAG_OUT_OF_VOLUME: "OUT_OF_VOLUME",
                         FLAG_PARTLY_OUT_OF_VOLUME: "PARTIALLY_OUT_OF_VOLUME"}


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

    @property
    def transform_status(self) -> str:
        """PLUS's ``TransformStatus`` for this sample: ``OK`` for a usable pose, else the tracker's reason (the
        Aurora's MISSING / OUT_OF_VOLUME / PARTIALLY_OUT_OF_VOLUME, else the status: OUT_OF_RANGE, NOT_ATTACHED...)."""
        if self.valid:
            return "OK"
        flag = self.extra.get("flag")
        return FLAG_TRANSFORM_STATUS.get(flag) or str(self.status).upper() or "INVALID"

    def transform(self) -> np.ndarray:
        """``SensorToTracker`` 4x4."""
        out = np.eye(4)
        out[:3, :3] = self.rotation
        out[:3, 3] = self.position_mm
        return out
