"""EMReg's settings: the one typed tree parsed from ``case.toml``, validated when it is read.

:class:`Settings` holds one frozen table per ``case.toml`` table; every default lives here, in
the field that defines the key. Reading a file (:func:`load_settings`) or a mapping
(:meth:`Settings.from_mapping`) refuses an unknown table or key, a value of the wrong type and a
value out of range, with one line naming the file, the table and the key (see
:mod:`EMRegModule.tables`), so a typo can never loosen a safety limit silently. The stages take
their own table (``settings.registration`` ...), never a raw dict.

Adding a key is one line: a field with its default (and range) in its table class below.
The stage modules re-export their table (``EMRegModule.core.registration.RegistrationSettings`` ...).
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import tomllib
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any, ClassVar

from .errors import EMRegError
from .marker_model import MarkerModel
from .names import DEFAULT_PROBE_PORT, DEFAULT_REFERENCE_PORT, REGISTRATION_JSON
from .tables import SettingError, fraction, non_negative, one_of, parse_table, port, positive

# --- [sensors] ---------------------------------------------------------------------------------


@dataclass(frozen=True)
class SensorSettings:
    """``[sensors]``: the tracker ports of the reference sensor (Model 800) and of the probe (Model 90);
    ``probe_axis`` (``auto``, ``+x_in``, ``+x_out``, ``none``; None: ``auto`` for a calibration, the
    calibration's own for a registration; see :mod:`EMRegModule.core.probe_axis`); the transform names of
    the two sensors in a PLUS sequence file (None: ``ReferenceToTracker``, ``ProbeToTracker``)."""

    reference: int = port(DEFAULT_REFERENCE_PORT)
    probe: int = port(DEFAULT_PROBE_PORT)
    probe_axis: str | None = one_of(None, "auto", "+x_in", "+x_out", "none")
    reference_transform: str | None = None
    probe_transform: str | None = None

    def validate(self) -> None:
        if self.reference == self.probe:
            raise SettingError(f"reference and probe are both port {self.reference}; give two different ports")
        for key in ("reference_transform", "probe_transform"):
            value = getattr(self, key)
            if value is not None and not value.strip().isidentifier():
                raise SettingError(f"must be a transform name such as 'ProbeToTracker', got {value!r}", key)


# --- [detection] -------------------------------------------------------------------------------


@dataclass(frozen=True)
class DetectionSettings:
    """``[detection]``: thresholds of the marker detection (HU, mm, fractions).

    - ``low_hu`` (600): the band's lower edge, well above POM (the frame's plastic, about 340 HU),
      soft tissue (< 100) and fat; PVC markers read far higher (about 1000-1500 HU).
    - ``high_hu`` (1800): the band's upper edge, the cortical-bone cut; PVC stays below it.
    - ``metal_hu`` (2800): saturated / metal voxels (the reference sensor and its streaks).
    - ``coarse_step_mm``: the step of the coarse candidate search, a third of the marker's narrowest
      diameter (at most 2 mm; :meth:`for_model`), so that every part of a marker is sampled.
    - ``volume_tolerance`` (0.25): a candidate's volume must lie within +/- this fraction of
      ``MarkerModel.volume_mm3``.
    - ``shape_tolerance`` (0.15): relative tolerance on each principal spread (square root of the
      principal moments) against the model's, plus 0.6 of the largest voxel side (mm).
    - ``max_fit_rms_mm`` (0.35): largest RMS distance of the edge points to the fitted CAD surface.
    - ``min_inlier_fraction`` (0.8): share of edge points within ``3 * max_fit_rms_mm`` of the surface.
    - ``bone_fraction`` (0.02): voxels above ``high_hu`` touching the blob, per blob voxel, above
      which the blob is taken for bone.
    - ``metal_distance_mm`` (10): a blob with metal voxels this close is checked with halved fit
      tolerances and rejected as wrecked by metal streaks if it fails them.
    - ``smoothing_sigma_mm`` (0.3) and ``opening_radius_mm`` (0.5): the Gaussian smoothing and
      binary opening applied (inside candidate regions only) before the band threshold's
      connected components, which drop noise and the thin partial-volume shells of bone.
    - ``min_markers`` (1): fewer markers found is "no safe answer" (exit 3).
    - ``estimate_band`` (true): when the markers read far from the middle of the default band
      (a low-kVp scan: PVC at 1700-1900 HU), detect again with the band scaled to their measured
      intensity; a band given in the table (``low_hu``/``high_hu`` not the defaults) is used as given.
    """

    low_hu: float = 600.0
    high_hu: float = 1800.0
    metal_hu: float = 2800.0
    coarse_step_mm: float = positive(2.0)
    volume_tolerance: float = positive(0.25)
    shape_tolerance: float = positive(0.15)
    max_fit_rms_mm: float = positive(0.35)
    min_inlier_fraction: float = fraction(0.8)
    bone_fraction: float = non_negative(0.02)
    metal_distance_mm: float = positive(10.0)
    smoothing_sigma_mm: float = non_negative(0.3)
    opening_radius_mm: float = non_negative(0.5)
    min_markers: int = non_negative(1)
    estimate_band: bool = True

    @classmethod
    def for_model(cls, model: MarkerModel) -> DetectionSettings:
        """Defaults for ``model``: the coarse step resolves the narrowest part of the marker."""
        return cls(coarse_step_mm=min(2.0, model.top_diameter_mm / 3.0))

    def validate(self) -> None:
        if not self.low_hu < self.high_hu <= self.metal_hu:
            raise SettingError(f"need low_hu < high_hu <= metal_hu, got {self.low_hu}, {self.high_hu}, "
                               f"{self.metal_hu}")
        if self.volume_tolerance >= 1:
            raise SettingError(f"must be below 1, got {self.volume_tolerance}", "volume_tolerance")

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


# --- dwells: [calibration] and [evaluation] ----------------------------------------------------


@dataclass(frozen=True)
class DwellSettings:
    """How dwells are found (the dwell keys of ``[calibration]`` and ``[evaluation]``).

    ``min_duration_s``: an unlabelled still period shorter than this is a pause, not a dwell.
    ``still_radius_mm``: the probe counts as still while the median distance of the samples in
    a ``window_s`` window from their median stays below this (tracker jitter is ~0.1 mm).
    ``max_gap_s``: still periods split by a shorter interruption (a burst of wild or bad-quality
    samples) at the same place are one dwell. ``merge_radius_mm``: dwells closer than this are
    at the same hole (revisits). ``max_quality``: samples whose tracker quality number exceeds it
    are ignored (None: an automatic limit from the recording's own quality distribution).
    ``min_samples``: fewer good samples than this make no dwell. ``max_drift_mm``: a still
    period whose first and last quarters (medians) lie farther apart than this is slow motion,
    not a dwell (None: twice ``still_radius_mm``).
    """

    min_duration_s: float = positive(0.5)
    still_radius_mm: float = positive(0.5)
    window_s: float = positive(0.25)
    max_gap_s: float = positive(0.3)
    merge_radius_mm: float = positive(3.0)
    max_quality: float | None = non_negative(None)
    min_samples: int = positive(5)
    max_drift_mm: float | None = positive(None)

    @property
    def drift_limit_mm(self) -> float:
        """The drift above which a still period is slow motion (mm)."""
        return 2.0 * self.still_radius_mm if self.max_drift_mm is None else float(self.max_drift_mm)

    @classmethod
    def from_settings(cls, settings: Any, section: str = "calibration") -> DwellSettings:
        """The dwell keys of a table (its other keys are left to their owner)."""
        return parse_table(cls, settings, section, ignore_unknown=True)


@dataclass(frozen=True)
class CalibrationSettings(DwellSettings):
    """``[calibration]``: the dwell keys, and ``revisit_tolerance_mm`` (1.0): visits of one pinhole
    whose averages differ by more than this earn a warning."""

    revisit_tolerance_mm: float = positive(1.0)


@dataclass(frozen=True)
class EvaluationSettings(DwellSettings):
    """``[evaluation]``: the dwell keys (hand-held touches at targets shake more than a probe resting in
    a pinhole: ``still_radius_mm`` defaults to 1 mm here; targets and holes are tens of mm apart), and
    ``max_target_distance_mm`` (15): an unlabelled dwell farther than this from every target is not
    counted for TRE.

    The error model's priors (:mod:`EMRegModule.core.error_model`): ``reference_error_mm`` and
    ``reference_error_deg``, the reference sensor's per-axis pose error (default: a quarter of the
    probe's measured per-dwell error, and the rotation that moves a point 160 mm away by as much, the
    proportion of the trakSTAR's specified static accuracy, 1.4 mm and 0.5 degree RMS);
    ``placement_error_mm`` (0), the 3D RMS error of putting the probe on a target.

    ``min_duration_s`` defaults to 0.35 s here: a hand-held probe held still for 0.4 s at 80 Hz
    (32 samples, 0.39 s from first to last) is a dwell; a mid-air hesitation of up to 0.3 s is not,
    nor is transit motion (it drifts more than twice the stillness radius)."""

    min_duration_s: float = positive(0.35)
    still_radius_mm: float = positive(1.0)
    max_target_distance_mm: float = positive(15.0)
    reference_error_mm: float | None = non_negative(None)
    reference_error_deg: float | None = non_negative(None)
    placement_error_mm: float = non_negative(0.0)


# --- [navigation] ------------------------------------------------------------------------------


@dataclass(frozen=True)
class NavigationSettings(DwellSettings):
    """``[navigation]``: what EMReg checks while it navigates (:mod:`EMRegModule.core.checkpoints`).

    Checkpoints: a rest of the probe (the dwell keys; a probe resting in a pinhole: 0.5 s within
    0.5 mm, as at calibration) whose centre lies within ``checkpoint_radius_mm`` (5) of a detected
    marker's pinhole at the solved depth l (image space), with the probe axis within
    ``checkpoint_angle_deg`` (20) of the marker axis when the probe has an orientation. Its error is
    the distance from there to the pinhole; above ``max_checkpoint_error_mm`` (1.5: three times the
    simulated end-to-end RMS TRE, so a clean checkpoint fails about once in 10^5, while a 2 mm slip
    of the reference moves every pinhole by about 2 mm) the checkpoint fails and every pose is
    INVALID until a later checkpoint passes. ``max_quality`` (20, the trakSTAR's METAL scale as the
    live watchdog takes it; the Aurora's RMS error is in mm: set e.g. 1): a sample with a worse
    quality number is an INVALID pose and no part of a checkpoint. ``reference_jump_mm`` (0.5) /
    ``reference_jump_deg`` (0.3): a step of the reference sensor between two samples larger than
    this, and than 8 times the recording's own sample-to-sample noise, that stays (not a lone wild
    sample) is warned about as a possible slip of the reference in its slot.

    ``plan``: a plan file (a Slicer markups JSON: a Line Entry -> Target, points labelled Entry and Target, or one
    target point; :mod:`EMRegModule.core.plan`), relative to ``case.toml``'s folder; None: no plan, no guidance
    columns. Left out of the settings' JSON and digest when not given (settings without it stay as they were)."""

    min_duration_s: float = positive(0.5)
    still_radius_mm: float = positive(0.5)
    max_quality: float | None = non_negative(20.0)
    max_checkpoint_error_mm: float = positive(1.5)
    checkpoint_radius_mm: float = positive(5.0)
    checkpoint_angle_deg: float = positive(20.0)
    reference_jump_mm: float = positive(0.5)
    reference_jump_deg: float = positive(0.3)
    plan: str | None = None

    def validate(self) -> None:
        if self.plan is not None and not self.plan.strip():
            raise SettingError("must be a markups file name, got an empty string", "plan")
        if self.max_checkpoint_error_mm >= self.checkpoint_radius_mm:
            raise SettingError(f"must be below checkpoint_radius_mm ({self.checkpoint_radius_mm:g}), got "
                               f"{self.max_checkpoint_error_mm:g}", "max_checkpoint_error_mm")


# --- [registration] ----------------------------------------------------------------------------


@dataclass(frozen=True)
class PairingSettings:
    """Pairing tolerances and safety margins (``[registration]`` keys of the same names).

    ``tracker_error_mm`` / ``image_error_mm``: RMS 3D localisation error of a calibration point
    and of an image marker's pinhole; ``direction_error_deg``: RMS angular error of a direction
    (probe or marker axis); ``n_sigma``: how many error units a constraint tolerates;
    ``min_pairs``: fewest pairs accepted; ``ambiguity_margin``: a rival pairing must explain at
    least this many points fewer than the best, else the pairing is refused as ambiguous.
    """

    tracker_error_mm: float = positive(0.5)
    image_error_mm: float = positive(0.3)
    direction_error_deg: float = positive(2.5)
    n_sigma: float = positive(4.0)
    min_pairs: int = positive(4)
    ambiguity_margin: int = positive(2)
    max_seeds: int = positive(60)
    rival_seeds: int = positive(24)

    @classmethod
    def from_settings(cls, settings: Any) -> PairingSettings:
        """The pairing keys of the ``[registration]`` table (its other keys are ignored here)."""
        return parse_table(cls, settings, "registration", ignore_unknown=True)

    @property
    def point_sigma_mm(self) -> float:
        """RMS 3D error of the difference between a calibration point and its image pinhole."""
        return float(math.hypot(self.tracker_error_mm, self.image_error_mm))

    @property
    def distance_tolerance_mm(self) -> float:
        """Tolerance on an inter-point distance (two points' errors projected on the line)."""
        return self.n_sigma * self.point_sigma_mm * math.sqrt(2.0 / 3.0)

    @property
    def point_tolerance_mm(self) -> float:
        """Largest residual of a paired point after the fit."""
        return self.n_sigma * self.point_sigma_mm

    @property
    def angle_tolerance_deg(self) -> float:
        """Tolerance on an angle between two directions, or between a mapped direction and an axis."""
        return self.n_sigma * self.direction_error_deg * math.sqrt(2.0)


@dataclass(frozen=True)
class RegistrationSettings:
    """``[registration]``: ``max_fre_mm`` (2.0, FRE above it is refused), ``sensor_offset_l_mm`` (fix l
    instead of solving it), outlier flagging (``outlier_factor`` x robust RMS, at least
    ``outlier_min_mm``; ``exclude_outliers`` refits without them), the l uncertainty that earns a warning
    (``warn_l_std_mm``) or a refusal (``max_l_std_mm``), and the pairing keys (:class:`PairingSettings`).

    Field distortion (:mod:`EMRegModule.core.distortion`): a detected one (false-alarm rate
    ``distortion_false_alarm``, 0.002) whose RMS at the pinholes beyond the rigid fit is above
    ``max_distortion_mm`` (1.5 mm) is refused: alone it would take most of a 2 mm accuracy budget (the
    FRE limit), so the field is no place to navigate in; below, it is warned about and predicted.

    The probe's per-dwell error known apart from the residuals (the test's noise, issue 37): ``dwell_error_ratio``
    (1.8) times the within-dwell spread of the calibration samples (per axis). The tracker's per-dwell error and its
    sample-to-sample jitter are both its own; their ratio is a property of the tracker, measured on clean simulated
    trakSTAR sessions as 1.63 +/- 0.08 (28 pinholes, noise x1-x2) and set above it so that an error larger than the
    spread predicts is not read as a distortion. Calibration residuals whose per-dwell error (beside any fitted
    field) is more than ``max_fle_ratio`` (2.5) times that are refused: the predicted TRE explains them by nothing
    it models.

    A registration that detected no distortion vouches only for fields its test could have seen: when the smallest
    field it finds in 90 % of random smooth fields at this session's noise and pinholes
    (:func:`.distortion.power.detectable_rms`) is above ``max_undetectable_distortion_mm`` (1.0 mm RMS at
    the pinholes), the registration warns and its predicted TRE is marked not to be trusted; with
    ``refuse_undetectable_distortion`` (false) it is refused instead. Not refused by default: a frame of few markers
    (8 at the simulator's standard noise: 1.6 mm) cannot see a 1 mm field at any noise a tracker has, and a clean
    registration there is still a registration."""

    max_fre_mm: float = positive(2.0)
    outlier_factor: float = positive(2.5)
    outlier_min_mm: float = positive(1.0)
    warn_l_std_mm: float = positive(0.3)
    max_l_std_mm: float = positive(1.0)
    sensor_offset_l_mm: float | None = positive(None)
    exclude_outliers: bool = False
    max_distortion_mm: float = positive(1.5)
    distortion_false_alarm: float = positive(0.002)
    dwell_error_ratio: float = positive(1.8)
    max_fle_ratio: float = positive(2.5)
    max_undetectable_distortion_mm: float = positive(1.0)
    refuse_undetectable_distortion: bool = False
    pairing: PairingSettings = field(default_factory=PairingSettings)

    def validate(self) -> None:
        if not self.distortion_false_alarm < 0.5:
            raise SettingError(f"must be a probability below 0.5, got {self.distortion_false_alarm}",
                               "distortion_false_alarm")

    @classmethod
    def from_settings(cls, settings: Any) -> RegistrationSettings:
        return parse_table(cls, settings, "registration")


# --- [board], [report], [ct] -------------------------------------------------------------------


@dataclass(frozen=True)
class BoardSettings:
    """``[board]``: ``edges_mm``, the nominal edge lengths L1..Ln of the board phantom (mm), if known."""

    edges_mm: tuple[float, ...] | None = None

    def validate(self) -> None:
        if self.edges_mm is not None and (len(self.edges_mm) < 3 or min(self.edges_mm) <= 0):
            raise SettingError(f"must be three or more positive lengths, got {list(self.edges_mm)}", "edges_mm")


@dataclass(frozen=True)
class ReportSettings:
    """``[report]``: ``iso_value``, the HU of the 3D view's CT surface (None: Otsu's threshold)."""

    iso_value: float | None = None


@dataclass(frozen=True)
class CTSettings:
    """``[ct]``: ``series``, the DICOM series to use (UID or series number; None: chosen automatically)."""

    series: str | int | None = None


@dataclass(frozen=True)
class ToolSettings:
    """``[tool]``: a tracked tool instead of the paper's pinhole probe (:mod:`EMRegModule.core.tool`).

    - ``calibration``: the tool file (``tool_calibration.json``, an ITK/Slicer ``TipToProbe`` transform, or a
      PLUS device-set XML), relative to ``case.toml``'s folder; None: the pinhole probe (sensor at depth l).
    - ``name``: the tool's transform name (``Stylus``: ``StylusToTracker`` in a sequence file, the
      ``StylusTip`` -> ``Stylus`` transform of a device set); None: the tool file's own, if it names one.
    - ``still_radius_mm`` (1.0): a touch is the tip within this of its median (a ``[calibration]`` dwell with
      this ``still_radius_mm``). On PLUS's hand-held landmark recording the tip wanders about 1 mm over each
      5-6 s touch: 0.5 mm (the pinhole probe's default) finds 5 of its 8 touches, 0.7 to 2 mm find all 8 and
      the same registration (0.11 to 0.14 mm from PLUS's at the landmarks).
    """

    calibration: str | None = None
    name: str | None = None
    still_radius_mm: float = positive(1.0)

    def validate(self) -> None:
        if self.name is not None and not self.name.strip().isidentifier():
            raise SettingError(f"must be a transform name such as 'Stylus', got {self.name!r}", "name")


# --- [handeye] ---------------------------------------------------------------------------------


@dataclass(frozen=True)
class HandEyeSettings:
    """``[handeye]``: hand-eye and robot-world calibration with the EM tracker (:mod:`EMRegModule.core.handeye`).

    - ``flange_transform`` (``FlangeToBase``): the robot flange's transform name in a PLUS sequence file of
      robot poses; ``sensor`` (None): the flange sensor in the tracker recording (a transform name or a port;
      ``--sensor`` overrides it; None: the recording's only sensor).
    - ``max_time_offset_s`` (None): the largest clock offset searched, s (None: any offset that keeps the two
      recordings overlapping, for clocks with different epochs).
    - ``timing_jitter_s`` (0): the least uncertainty of a tracker time stamp, s; a moving frame's residual
      allows ``speed x jitter`` more, so the still frames of dwells count most. The jitter is estimated from how
      the residuals grow with the flange's speed, never below this.
    - ``min_frames`` (20), ``min_rotation_deg`` (10), ``min_second_axis_deg`` (3): below these (frames used;
      the largest rotation of the flange from its mean orientation; the RMS rotation about the second axis)
      the motion cannot determine the answer (exit 3).
    - ``min_correlation`` (0.5): a weaker peak of the angular-speed cross-correlation finds no clock offset.
    - ``outlier_limit`` (9.0): a frame whose noise-normalised residual (over its 6 components) exceeds this is
      rejected; 9 is as unlikely under the refinement's heavy-tailed noise model (a Student-t of 4 degrees of
      freedom) as 4 standard deviations of Gaussian noise.
    - ``max_noise_mm`` (5.0), ``max_noise_deg`` (3.0): a still frame's typical residual above these means the
      two recordings disagree (not the same motion, the wrong sensor, a moved field generator): exit 3.
    - ``tool_tip_mm`` (0, 0, 150): the tool point (Sensor frame, mm) whose predicted error is reported;
      ``max_tip_uncertainty_mm`` (2.0): above this predicted RMS error there is no safe answer (exit 3).
    """

    flange_transform: str = "FlangeToBase"
    sensor: str | int | None = None
    max_time_offset_s: float | None = positive(None)
    timing_jitter_s: float = non_negative(0.0)
    min_frames: int = positive(20)
    min_rotation_deg: float = positive(10.0)
    min_second_axis_deg: float = positive(3.0)
    min_correlation: float = fraction(0.5)
    outlier_limit: float = positive(9.0)
    max_noise_mm: float = positive(5.0)
    max_noise_deg: float = positive(3.0)
    tool_tip_mm: tuple[float, ...] = (0.0, 0.0, 150.0)
    max_tip_uncertainty_mm: float = positive(2.0)

    def validate(self) -> None:
        if not self.flange_transform.strip().isidentifier():
            raise SettingError(f"must be a transform name such as 'FlangeToBase', got {self.flange_transform!r}",
                               "flange_transform")
        if len(self.tool_tip_mm) != 3:
            raise SettingError("must be three numbers (x, y, z in the Sensor frame, mm)", "tool_tip_mm")


# --- [robot] -----------------------------------------------------------------------------------


@dataclass(frozen=True)
class RobotSettings:
    """``[robot]``: targeting with the robot (``emreg robot-target``, :mod:`EMRegModule.core.robot_target`).

    - ``standoff_mm`` (0): the guide's exit this far before Entry, back along the planned axis (0: on Entry).
    - ``max_tracker_distance_mm`` (660): Entry and Target must lie within this distance of the field generator
      (the tracker's characterised volume; 660 mm is a trakSTAR mid-range transmitter's), else exit 3.
    - ``reach_mm`` (None): the flange must stay within this distance of the robot's base (None: not checked).
    - ``positioning_mm`` (0), ``positioning_deg`` (0): the robot's own RMS positioning error (commanded against
      reached flange pose), part of the predicted error at the target when the calibration did not measure it
      (``robot-calibrate`` does, at its poses).
    - ``model`` (None): the robot's kinematic model, ``fr3`` or ``panda``: the roll about the needle's axis is then
      the one that keeps the robot furthest from its joint limits, and a plan it cannot reach is refused (exit 3);
      ``end_effector_mm`` (0, 0, 0) and ``end_effector_rpy_deg`` (0, 0, 0): the end effector set on the robot
      (Franka's ``F_T_EE``: translation, then roll-pitch-yaw about the flange's fixed x, y, z), for a flange
      pose reported and commanded at it.

    Driving the robot (``emreg robot-calibrate``, ``emreg robot-go``; :mod:`EMRegModule.core.robot_motion`):

    - ``flange_sensor`` (3): the tracker port of the EM sensor on the flange's guide (``--sensor`` overrides it).
    - ``max_velocity_mm_s`` (50), ``max_acceleration_mm_s2`` (250), ``max_rotation_deg_s`` (20),
      ``max_rotation_acceleration_deg_s2`` (90): every move's limits (the robot's own maxima cap them).
    - ``stale_s`` (0.25): a sensor without a sample for this long stops the robot.
    - ``calibration_poses`` (12), ``calibration_angle_deg`` (25), ``calibration_translation_mm`` (20): the poses
      ``robot-calibrate`` plans; ``sensor_radius_mm`` (150): the farthest the sensor may sit from the flange's
      origin, for keeping it in the tracker's volume before the calibration knows; ``dwell_s`` (0.8): the still
      time recorded at each pose (``robot-calibrate`` stays ``measure_s`` longer and then reads where the robot
      put its flange: the robot's positioning error as settled as ``robot-go`` measures it);
      ``motion_jitter_s`` (0.05): while the robot moves, its reported flange pose runs ahead of the real flange
      (the controller's tracking error) by up to this time: ``robot-calibrate`` solves with ``[handeye]
      timing_jitter_s`` at least this, so that the still frames of the dwells count most.
    - ``approach_mm`` (30): ``robot-go`` first goes this far back along the planned axis, then along it;
      ``tolerance_mm`` (0.5), ``tolerance_deg`` (0.5): the guide is on the plan when its exit and its needle tip
      at the planned depth are within ``tolerance_mm`` and its axis within ``tolerance_deg``; ``max_corrections``
      (5): corrections before giving up (exit 3); ``measure_s`` (0.5): the tracker's samples averaged per
      measurement; ``max_correction_mm`` (20), ``max_correction_deg`` (5): a larger correction is refused.
    """

    standoff_mm: float = non_negative(0.0)
    max_tracker_distance_mm: float = positive(660.0)
    reach_mm: float | None = positive(None)
    positioning_mm: float = non_negative(0.0)
    positioning_deg: float = non_negative(0.0)
    model: str | None = one_of(None, "fr3", "panda")
    end_effector_mm: tuple[float, ...] = (0.0, 0.0, 0.0)
    end_effector_rpy_deg: tuple[float, ...] = (0.0, 0.0, 0.0)
    flange_sensor: int = port(3)
    max_velocity_mm_s: float = positive(50.0)
    max_acceleration_mm_s2: float = positive(250.0)
    max_rotation_deg_s: float = positive(20.0)
    max_rotation_acceleration_deg_s2: float = positive(90.0)
    stale_s: float = positive(0.25)
    calibration_poses: int = positive(12)
    calibration_angle_deg: float = positive(25.0)
    calibration_translation_mm: float = non_negative(20.0)
    sensor_radius_mm: float = non_negative(150.0)
    dwell_s: float = positive(0.8)
    motion_jitter_s: float = non_negative(0.05)
    approach_mm: float = non_negative(30.0)
    tolerance_mm: float = positive(0.5)
    tolerance_deg: float = positive(0.5)
    max_corrections: int = non_negative(5)
    measure_s: float = positive(0.5)
    max_correction_mm: float = positive(20.0)
    max_correction_deg: float = positive(5.0)

    def validate(self) -> None:
        for name in ("end_effector_mm", "end_effector_rpy_deg"):
            if len(getattr(self, name)) != 3:
                raise SettingError("must be three numbers", name)


# --- the tree ----------------------------------------------------------------------------------


@dataclass(frozen=True)
class Settings:
    """Every ``case.toml`` table, typed (defaults where a table or key is absent).

    ``source`` names the file the settings were read from (empty: defaults only); ``given`` the keys that file
    gives (``"sensors.probe"``...): the one answer to "was this key given by the user?" (:meth:`gives`).
    """

    sensors: SensorSettings = field(default_factory=SensorSettings)
    marker: MarkerModel = field(default_factory=MarkerModel)
    detection: DetectionSettings = field(default_factory=DetectionSettings)
    calibration: CalibrationSettings = field(default_factory=CalibrationSettings)
    registration: RegistrationSettings = field(default_factory=RegistrationSettings)
    evaluation: EvaluationSettings = field(default_factory=EvaluationSettings)
    navigation: NavigationSettings = field(default_factory=NavigationSettings)
    board: BoardSettings = field(default_factory=BoardSettings)
    report: ReportSettings = field(default_factory=ReportSettings)
    ct: CTSettings = field(default_factory=CTSettings)
    tool: ToolSettings = field(default_factory=ToolSettings)
    handeye: HandEyeSettings = field(default_factory=HandEyeSettings)
    robot: RobotSettings = field(default_factory=RobotSettings)
    source: str = ""
    given: frozenset[str] = field(default=frozenset(), compare=False)

    #: The tables, by TOML name (every field but ``source``).
    TABLES: ClassVar[tuple[str, ...]] = ("sensors", "marker", "detection", "calibration", "registration",
                                         "evaluation", "board", "report", "ct", "tool", "navigation",
                                         "handeye", "robot")

    @classmethod
    def from_mapping(cls, mapping: Any, source: str = "case.toml") -> Settings:
        """Settings from a parsed TOML document; :class:`EMRegError` (one line) for anything unknown or bad."""
        if mapping is None:
            mapping = {}
        if not isinstance(mapping, dict):
            raise EMRegError(f"{source}: settings must be TOML tables, got {mapping!r:.60}")
        unknown = sorted(set(mapping) - set(cls.TABLES))
        if unknown:
            raise EMRegError(f"{source}: unknown table{'s' if len(unknown) > 1 else ''} "
                             f"{', '.join(f'[{name}]' for name in unknown)}; known: "
                             f"{', '.join(f'[{name}]' for name in sorted(cls.TABLES))}")
        tables: dict[str, Any] = {}
        for name in cls.TABLES:
            table_class = _TABLE_CLASSES[name]
            base = None
            if name == "detection":
                base = DetectionSettings.for_model(tables["marker"])
            tables[name] = parse_table(table_class, mapping.get(name), name, source, base=base)
        fixed_l, model = tables["registration"].sensor_offset_l_mm, tables["marker"]
        if fixed_l is not None and not model.pinhole_bottom_mm <= fixed_l <= model.pinhole_top_mm:
            raise EMRegError(f"{source}: [registration] sensor_offset_l_mm = {fixed_l:g} lies outside the "
                             f"marker's pinhole {model.pinhole_bottom_mm:g}..{model.pinhole_top_mm:g} mm ([marker]): "
                             "the probe sensor cannot sit there")
        given = frozenset(f"{name}.{key}" for name, table in mapping.items() if isinstance(table, dict)
                          for key in table)
        return cls(**tables, source=str(source), given=given)

    def gives(self, table: str, key: str) -> bool:
        """Whether the settings file itself gives ``[table] key`` (a default is not a user's choice)."""
        return f"{table}.{key}" in self.given

    def file_path(self, name: str | None) -> Path | None:
        """A file the settings name (``[tool] calibration``, ``[navigation] plan``): relative to the settings file's
        folder, unless absolute, read from no file, or ``auto`` (``[tool] calibration = "auto"``: no file); None when
        they name none."""
        if not name:
            return None
        path = Path(name)
        if name != "auto" and not path.is_absolute() and self.source:
            path = Path(self.source).parent / path
        return path

    def with_sensors(self, reference: int | None = None, probe: int | None = None) -> Settings:
        """These settings with the ports overridden (command line); checked like ``[sensors]``."""
        values = {k: v for k, v in (("reference", reference), ("probe", probe)) if v is not None}
        if not values:
            return self
        sensors = parse_table(SensorSettings, values, "sensors", "command line", base=self.sensors)
        return replace(self, sensors=sensors)

    def to_json(self) -> dict[str, Any]:
        """Every table and value (defaults included), as a JSON-ready dict (tuples as lists)."""
        document = json.loads(json.dumps({name: asdict(getattr(self, name)) for name in self.TABLES}))
        for table, key in ADDED_LATER:  # settings without them keep the JSON and digest they had
            given, default = getattr(self, table), type(getattr(self, table))()
            if key is None and given == default:
                del document[table]
            elif key is not None and getattr(given, key) == getattr(default, key):
                del document[table][key]
        return document

    def digest(self) -> str:
        """sha256 of :meth:`to_json` in canonical form: equal digests, equal settings."""
        text = json.dumps(self.to_json(), sort_keys=True, separators=(",", ":"))
        return hashlib.sha256(text.encode("utf-8")).hexdigest()


#: ``(table, key)`` added to the settings later, left out of :meth:`Settings.to_json` (and so of the digest, the
#: provenance of every output) while at its default; key None: the whole table (the robot's, which no registration
#: stage reads).
ADDED_LATER: tuple[tuple[str, str | None], ...] = (("navigation", "plan"), ("handeye", None), ("robot", None),
                                                   ("registration", "dwell_error_ratio"),
                                                   ("registration", "max_fle_ratio"),
                                                   ("registration", "max_undetectable_distortion_mm"),
                                                   ("registration", "refuse_undetectable_distortion"))


def sensor_ports_given(settings: Settings) -> tuple[int | None, int | None]:
    """The ports (reference, probe) that the settings file itself gives in ``[sensors]`` (None where it gives
    none, or when the settings are the defaults): a port left out there is not a user's choice, so a
    consumer may take it from the registration (:meth:`EMRegModule.pipeline.controller.EMRegController.use_ports`)."""
    return (settings.sensors.reference if settings.gives("sensors", "reference") else None,
            settings.sensors.probe if settings.gives("sensors", "probe") else None)


def choose_ports(given: tuple[int | None, int | None], recorded: tuple[int | None, int | None],
                 source: str = REGISTRATION_JSON) -> tuple[tuple[int, int], list[str]]:
    """The (reference, probe) ports of a consumer of a registration: for each sensor the port the user gave
    (command line, else ``case.toml [sensors]``; None: not given), else the port the registration's
    calibration used (``recorded``; None in files older than the keys), else the spec's default (1, 2).
    A given port that differs from the recorded one is used (a re-cabled tracker) with a one-line warning,
    returned with the ports."""
    defaults = (DEFAULT_REFERENCE_PORT, DEFAULT_PROBE_PORT)
    chosen = tuple(g if g is not None else r if r is not None else d
                   for g, r, d in zip(given, recorded, defaults, strict=True))
    warnings = []
    if any(g is not None and r is not None and g != r for g, r in zip(given, recorded, strict=True)):
        warnings.append(f"the ports given (reference {chosen[0]}, probe {chosen[1]}) differ from those of the "
                        f"registration's calibration (reference {recorded[0]}, probe {recorded[1]}, {source}); "
                        "using the ports given (a re-cabled tracker?)")
    return chosen, warnings  # type: ignore[return-value]


def with_series(settings: Settings, series: str | int | None) -> Settings:
    """``settings`` with ``[ct] series`` overridden (``--series UID|NUMBER``); unchanged when ``series`` is None."""
    if series is None:
        return settings
    return replace(settings, ct=parse_table(CTSettings, {"series": series}, "ct", "--series", base=settings.ct))


_TABLE_CLASSES: dict[str, type] = {
    "sensors": SensorSettings, "marker": MarkerModel, "detection": DetectionSettings,
    "calibration": CalibrationSettings, "registration": RegistrationSettings, "evaluation": EvaluationSettings,
    "board": BoardSettings, "report": ReportSettings, "ct": CTSettings, "tool": ToolSettings,
    "navigation": NavigationSettings, "handeye": HandEyeSettings,
    "robot": RobotSettings,
}


def load_settings(path: str | os.PathLike[str] | None, required: bool = False) -> Settings:
    """Read and check a ``case.toml``; defaults when ``path`` is None or (unless ``required``) absent.

    Malformed TOML, an unknown table or key, or a bad value is an :class:`EMRegError` naming the file.
    """
    if path is None:
        return Settings()
    path = Path(path)
    if not path.is_file():
        if required:
            raise EMRegError(f"{path}: settings file not found")
        return Settings()
    try:
        with path.open("rb") as f:
            document = tomllib.load(f)
    except tomllib.TOMLDecodeError as exc:
        raise EMRegError(f"{path}: malformed TOML ({exc})") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise EMRegError(f"{path}: cannot read the settings ({exc})") from None
    return Settings.from_mapping(document, str(path))
