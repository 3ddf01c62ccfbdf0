"""Options of the case simulator and their defaults per difficulty (``standard`` / ``hard``)."""

from __future__ import annotations

from dataclasses import dataclass, field, fields, replace
from typing import Any

import numpy as np

from ..errors import EMRegError

DIFFICULTIES = ("standard", "hard")
DISTORTION_DURING = ("calibration", "navigation", "both")


@dataclass(frozen=True)
class SimulationOptions:
    """Every knob of :func:`EMRegModule.simulation.simulate_case` (mm, degrees, HU).

    Pass any of these as keyword options to ``simulate_case``; the difficulty sets the
    defaults.
    """

    frame_size_mm: tuple[float, float, float] = (350.0, 350.0, 200.0)
    n_markers: int = 28
    marker: dict[str, float] = field(default_factory=dict)  # MarkerModel fields; {} = the paper's marker
    spacing: tuple[float, float, float] = (0.6, 0.6, 0.6)
    noise_hu: float = 20.0
    psf_fwhm_mm: float = 1.0
    oblique_deg: float = 2.0  # largest rotation of the voxel grid's axes away from LPS
    flip: bool = False  # a left-handed voxel grid (det(direction) = -1) before writing
    direction: tuple[float, ...] | None = None  # explicit 9 direction cosines (row-major); overrides the two above
    frame_tilt_deg: float = 4.0  # largest rotation of the frame in the scanner
    ct_format: str = "nrrd"  # "nrrd" -> ct.nrrd, "dicom" -> ct/ series
    patient: bool = True
    couch: bool = True  # the scanner couch under the frame
    metal_streaks: bool = True
    pvc_hu: float = 1100.0  # the markers' density (a low-kVp scan reads PVC at 1700-1900 HU)
    marker_streaks: int = 0  # markers crossed at their shoulder by a dark streak (issue 13)
    marker_streak_hu: float = -1000.0  # the dark streaks' strength on their line (HU)
    n_decoys: int = 0
    n_absent: int = 0  # calibrated markers absent from the CT (removed before the scan)
    n_uncalibrated: int = 0  # markers in the CT that the calibration recording skips
    calibration_labels: bool = True
    n_bumps: int = 0  # times the frame is bumped during the calibration recording
    hesitation_rate: float = 0.0  # chance of a short mid-air pause in a transition
    bad_sample_rate: float = 0.002
    tracker_noise_scale: float = 1.0  # multiplies every tracker error magnitude (0: exact poses)
    sensor_offset_l_mm: float | None = None  # None: drawn in [a + 1, b - 1]
    n_targets: int = 6
    navigation_rounds: int = 15
    board_rounds: int = 60
    board_edges_mm: tuple[float, float, float, float] = (75.3, 60.4, 75.5, 60.4)
    board_quaternions: bool = False  # write board.csv with qw,qx,qy,qz columns
    probe_axis: str = "+x_in"  # probe convention in the recordings: "+x_in", "+x_out" or "none" (position only)
    #: a stylus instead of the pinhole probe: its tip in the sensor's frame (mm); the calibration's touches put the
    #: tip where the pinhole probe's sensor would be and pivot about it through ``pivot_swing_deg`` (full cone),
    #: the navigation's touch the targets with the tip; ``tool_calibration.json`` (the true tip), a pivot
    #: recording ``pivot.csv`` and ``[tool] calibration`` are written. None: the paper's probe.
    tool_tip_mm: tuple[float, float, float] | None = None
    pivot_swing_deg: float = 30.0
    navigation_checkpoints: int = 0  # unlabelled rests of the probe in marker pinholes during navigation
    reference_slip_mm: float = 0.0  # the reference sensor slips in its slot during navigation by this much ...
    reference_slip_deg: float = 0.0  # ... and this rotation (random directions)
    reference_slip_at: float = 0.5  # ... at this fraction of the navigation recording (while the probe moves)
    # field distortion by a steel rod near the frame (:mod:`.distortion`): RMS (mm) of the non-rigid error at the
    # calibrated pinholes after the best rigid fit (0: none); in which recordings; when it is rolled in (s after
    # the start of the first of them; None: there from the start). The navigation is then recorded with the frame
    # where it was calibrated (the same field).
    distortion_mm: float = 0.0
    distortion_during: str = "both"  # "calibration", "navigation" or "both"
    distortion_onset_s: float | None = None

    def check(self) -> None:
        """Refuse impossible values with an :class:`EMRegError` naming the option."""
        for option in fields(self):  # NaN slips through every range test below (its comparisons are false)
            value = getattr(self, option.name)
            numbers = value if isinstance(value, tuple) else (value,)
            if any(isinstance(v, float) and not np.isfinite(v) for v in numbers):
                raise EMRegError(f"simulate: {option.name} must be finite numbers, got {value}")
        size = np.asarray(self.frame_size_mm, dtype=float)
        if size.shape != (3,) or np.any(size < 80) or np.any(size > 1000):
            raise EMRegError(f"simulate: frame_size_mm must be three lengths of 80..1000 mm, got {self.frame_size_mm}")
        spacing = np.asarray(self.spacing, dtype=float)
        if spacing.shape != (3,) or np.any(spacing < 0.1) or np.any(spacing > 3.0):
            raise EMRegError(f"simulate: spacing must be 0.1..3 mm per axis, got {self.spacing}")
        if not 4 <= self.n_markers <= 60:
            raise EMRegError(f"simulate: n_markers must be 4..60, got {self.n_markers}")
        if self.n_absent + self.n_uncalibrated > self.n_markers - 4:
            raise EMRegError("simulate: too many absent/uncalibrated markers for the number of markers")
        if self.ct_format not in ("nrrd", "dicom"):
            raise EMRegError(f"simulate: ct_format must be 'nrrd' or 'dicom', got {self.ct_format!r}")
        if self.direction is not None:
            matrix = np.asarray(self.direction, dtype=float)
            if matrix.size != 9 or not np.allclose(matrix.reshape(3, 3) @ matrix.reshape(3, 3).T, np.eye(3),
                                                   atol=1e-6):
                raise EMRegError("simulate: direction must be 9 numbers forming an orthonormal 3x3 matrix")
        if self.noise_hu < 0 or self.psf_fwhm_mm < 0 or self.tracker_noise_scale < 0 or self.bad_sample_rate < 0:
            raise EMRegError("simulate: noise_hu, psf_fwhm_mm, tracker_noise_scale and bad_sample_rate must not be "
                             "negative")
        if self.probe_axis not in ("+x_in", "+x_out", "none"):
            raise EMRegError(f"simulate: probe_axis must be '+x_in', '+x_out' or 'none', got {self.probe_axis!r}")
        if not 0.0 <= self.distortion_mm <= 20.0:
            raise EMRegError(f"simulate: distortion_mm must lie in 0..20 mm, got {self.distortion_mm}")
        if self.distortion_during not in DISTORTION_DURING:
            raise EMRegError(f"simulate: distortion_during must be one of {', '.join(DISTORTION_DURING)}, "
                             f"got {self.distortion_during!r}")
        if self.distortion_onset_s is not None and self.distortion_onset_s < 0:
            raise EMRegError(f"simulate: distortion_onset_s must not be negative, got {self.distortion_onset_s}")
        if len(self.board_edges_mm) != 4:
            raise EMRegError("simulate: board_edges_mm needs four edge lengths")
        if not 300.0 <= self.pvc_hu <= 2800.0:
            raise EMRegError(f"simulate: pvc_hu must lie in 300..2800 HU, got {self.pvc_hu}")
        if self.marker_streaks > self.n_markers:
            raise EMRegError("simulate: marker_streaks cannot exceed n_markers")
        if self.reference_slip_mm < 0 or self.reference_slip_deg < 0 or not 0.0 < self.reference_slip_at < 1.0:
            raise EMRegError("simulate: reference_slip_mm and reference_slip_deg must not be negative, "
                             "reference_slip_at must lie strictly between 0 and 1")
        for name in ("n_decoys", "marker_streaks", "n_bumps", "n_targets", "navigation_rounds", "board_rounds",
                     "navigation_checkpoints"):
            if getattr(self, name) < 0:
                raise EMRegError(f"simulate: {name} must not be negative")


HARD_DEFAULTS: dict[str, Any] = {
    "spacing": (0.5, 0.5, 0.8), "noise_hu": 35.0, "oblique_deg": 25.0, "flip": True, "frame_tilt_deg": 6.0,
    "ct_format": "dicom", "n_decoys": 6, "n_absent": 2, "n_uncalibrated": 1, "calibration_labels": False,
    "n_bumps": 2, "hesitation_rate": 0.25, "bad_sample_rate": 0.004, "board_quaternions": True,
}


def resolve_options(difficulty: str, spacing_mm: float | Any | None, options: dict[str, Any]) -> SimulationOptions:
    """Defaults of ``difficulty``, then ``spacing_mm`` (isotropic number or three values), then ``options``."""
    if difficulty not in DIFFICULTIES:
        raise EMRegError(f"simulate: difficulty must be one of {', '.join(DIFFICULTIES)}, got {difficulty!r}")
    known = {f.name for f in fields(SimulationOptions)}
    unknown = sorted(set(options) - known)
    if unknown:
        raise EMRegError(f"simulate: unknown option(s) {', '.join(unknown)}; known: {', '.join(sorted(known))}")
    resolved = SimulationOptions()
    if difficulty == "hard":
        resolved = replace(resolved, **HARD_DEFAULTS)
    if spacing_mm is not None:
        spacing = np.broadcast_to(np.asarray(spacing_mm, dtype=float), (3,))
        resolved = replace(resolved, spacing=tuple(float(v) for v in spacing))
    clean = dict(options)
    if "spacing" in clean:
        clean["spacing"] = tuple(float(v) for v in np.broadcast_to(np.asarray(clean["spacing"], dtype=float), (3,)))
    if clean.get("direction") is not None:
        clean["direction"] = tuple(float(v) for v in np.asarray(clean["direction"], dtype=float).ravel())
    if "frame_size_mm" in clean:
        clean["frame_size_mm"] = tuple(float(v) for v in clean["frame_size_mm"])
    resolved = replace(resolved, **clean)
    resolved.check()
    return resolved
