"""The simulated frame a study varies sessions on, and the simulated sessions themselves.

A study simulates ONE case (CT + recordings, :mod:`EMRegModule.simulation`), detects its
markers ONCE, and then varies only the tracking: each session is a new trakSTAR session from the
simulator's own session model (hand-held travel, dwells, per-dwell systematic error, correlated
jitter, bad samples) with the reference sensor somewhere else in the transmitter's field, run
through the real calibration, pairing/registration and evaluation code. Errors are measured
against the simulator's ground truth (``truth.json``).

Frames: the Reference frame is the Body of the simulated sessions (``ReferenceToBody = I``), so
calibration points, targets and board holes are expressed in it; image space is CT LPS (mm).
"""

from __future__ import annotations

import hashlib
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from ..core.calibration import calibrate_frame
from ..core.detection.result import DetectionResult
from ..core.registration import RegistrationResult, register
from ..core.tracking import TrackingRecording
from ..core.transforms import (
    apply_rotation,
    apply_transform,
    axis_angle_to_rotation,
    invert_rigid,
    make_transform,
    random_rotation,
)
from ..errors import EMRegError
from ..io.case import open_case
from ..io.markers_json import read_detection, write_detection
from ..marker_model import MarkerModel
from ..names import DEFAULT_PROBE_PORT, DEFAULT_REFERENCE_PORT, MARKERS_JSON
from ..pipeline.controller import EMRegController
from ..settings import Settings
from ..simulation.case import load_truth, simulate_case
from ..simulation.distortion import FieldDistortion
from ..simulation.stylus import shaft_rotation
from ..simulation.tracking import (
    DwellTruth,
    FieldOnset,
    FrameBump,
    NoiseModel,
    ReferenceSlip,
    Visit,
    probe_rotation_into,
    simulate_session,
)

#: Options of the smaller frame of ``--quick`` studies (as the CI-sized test cases).
QUICK_FRAME = {"frame_size_mm": (220.0, 220.0, 140.0), "n_markers": 16}


@dataclass
class Frame:
    """The simulated frame in the Reference frame (mm), with the CT detection of its markers (LPS, mm)."""

    case_dir: Path
    truth: dict
    model: MarkerModel
    detection: DetectionResult
    reference_to_image: np.ndarray  # the truth
    labels: list[str]  # calibrated marker labels
    pinholes: np.ndarray  # (N, 3) true sensor points in the Reference frame
    axes: np.ndarray  # (N, 3) marker +Y in the Reference frame
    in_ct: np.ndarray  # (N,) bool
    targets_image: np.ndarray  # (K, 3) LPS
    target_labels: list[str]
    #: the case's ``case.toml`` settings: the sessions are calibrated, registered and checked with them (the
    #: simulated sessions' sensors are on the default ports)
    settings: Settings = field(default_factory=Settings)

    @property
    def targets_reference(self) -> np.ndarray:
        return apply_transform(invert_rigid(self.reference_to_image), self.targets_image)


def prepare_frame(work: Path, case_dir: Path | None = None, seed: int = 1, quick: bool = False,
                  log: Callable[[str], None] = print) -> Frame:
    """Simulate (or reuse) the case, detect its markers once (cached under ``work``; the case stays untouched)."""
    if case_dir is None:
        case_dir = Path(work) / f"case-seed{seed}{'-quick' if quick else ''}"
        if not (case_dir / "truth.json").is_file():
            log(f"simulating the study's case into {case_dir}")
            simulate_case(case_dir, seed=seed, difficulty="standard", **(QUICK_FRAME if quick else {}))
    truth = load_truth(case_dir)
    case = open_case(case_dir)
    key = hashlib.sha1(str(Path(case_dir).resolve()).encode()).hexdigest()[:8]
    markers_json = Path(work) / f"detection-{Path(case_dir).name}-{key}" / MARKERS_JSON
    if markers_json.is_file():
        detection = read_detection(markers_json)
    else:
        log("detecting the markers in the study's CT (once)")
        controller = EMRegController.for_case(case)
        controller.give(ct=case.ct)
        detection = controller.make("detect")
        write_detection(detection, markers_json.parent)
    reference_to_image = np.asarray(truth["ReferenceToImage"], dtype=float)
    calibrated = [m for m in truth["markers"] if m.get("calibrated", True)]
    return Frame(
        case_dir=Path(case_dir), truth=truth, model=MarkerModel.from_settings(truth.get("marker_model")),
        detection=detection, reference_to_image=reference_to_image,
        labels=[m["label"] for m in calibrated],
        pinholes=np.array([m["pinhole_in_reference"] for m in calibrated], dtype=float),
        axes=apply_rotation(invert_rigid(reference_to_image), np.array([m["axis"] for m in calibrated], dtype=float)),
        in_ct=np.array([bool(m.get("in_ct", True)) for m in calibrated]),
        targets_image=np.array([t["position"] for t in truth["targets"]], dtype=float).reshape(-1, 3),
        target_labels=[t["label"] for t in truth["targets"]], settings=case.settings,
    )


def noise_model(scale: float = 1.0) -> NoiseModel:
    """The simulator's trakSTAR error model with every magnitude multiplied by ``scale``."""
    return NoiseModel().scaled(scale)


def reference_placement(rng: np.random.Generator) -> np.ndarray:
    """A ``ReferenceToTracker`` somewhere in the transmitter's field (250-400 mm away, any heading)."""
    rotation = random_rotation(rng, 6.0) @ axis_angle_to_rotation([0, 0, 1], rng.uniform(-np.pi, np.pi)) \
        @ np.diag([1.0, -1.0, -1.0])
    position = np.array([rng.uniform(250, 400), rng.uniform(-100, 100), rng.uniform(-60, 80)])
    return make_transform(rotation, position)


def _touch(rotation: np.ndarray, point: np.ndarray, tip_mm: np.ndarray | None) -> np.ndarray:
    """The sensor pose (4x4) that puts the pinhole probe's sensor, or a stylus's tip (``tip_mm``, shaft along
    ``rotation``'s +X), at ``point``."""
    if tip_mm is None:
        return make_transform(rotation, point)
    rotation = rotation @ shaft_rotation(tip_mm)
    return make_transform(rotation, np.asarray(point) - rotation @ tip_mm)


def simulate_calibration(frame: Frame, rng: np.random.Generator, noise: NoiseModel | None = None,
                         subset: np.ndarray | None = None, tip_mm: np.ndarray | None = None,
                         pivot_swing_deg: float = 30.0, reference_to_tracker: np.ndarray | None = None,
                         distortion: FieldDistortion | None = None) -> TrackingRecording:
    """A calibration recording: the probe into each (selected) pinhole in turn, labelled by marker; with a
    stylus (``tip_mm``) its tip at the pinhole point, pivoting through ``pivot_swing_deg``.

    ``reference_to_tracker``: where the frame is (default: a random placement); ``distortion``: a metal
    object distorting the field (:mod:`EMRegModule.simulation.distortion`)."""
    index = np.arange(len(frame.labels)) if subset is None else np.asarray(subset)
    visits = []
    for i in index:
        rotation = probe_rotation_into(-frame.axes[i], rng.uniform(0, 2 * np.pi))
        visits.append(Visit(_touch(rotation, frame.pinholes[i], tip_mm),
                            float(rng.uniform(1.0, 2.0) if tip_mm is None else rng.uniform(2.0, 3.0)),
                            frame.labels[i], frame.labels[i], tip_mm=tip_mm,
                            pivot_swing_deg=0.0 if tip_mm is None else pivot_swing_deg))
    placement = reference_placement(rng) if reference_to_tracker is None else reference_to_tracker
    recording, _, _ = simulate_session(rng, visits, placement, np.eye(4), frame.pinholes[index].mean(axis=0),
                                       lift_mm=25.0, noise=noise, distortion=distortion)
    return recording


def _target_visits(frame: Frame, rng: np.random.Generator, rounds: int,
                   tip_mm: np.ndarray | None) -> tuple[np.ndarray, list[Visit]]:
    """``rounds`` rounds of hand-held touches, tip first, on each target (Reference frame, mm), the probe tilted
    25 degrees about the inward direction; the targets' centre and the visits (``tip_mm``: a stylus's tip)."""
    targets = frame.targets_reference
    centre = targets.mean(axis=0)
    visits = []
    for _ in range(rounds):
        for label, target in zip(frame.target_labels, targets, strict=True):
            inward = centre - target if np.linalg.norm(centre - target) > 1 else np.array([0.0, 0.0, 1.0])
            rotation = probe_rotation_into(inward, rng.uniform(0, 2 * np.pi), 25.0, rng)
            visits.append(Visit(_touch(rotation, target, tip_mm), float(rng.uniform(1.0, 2.0)), label, label,
                                tremor_mm=0.08))
    return centre, visits


def simulate_navigation(frame: Frame, rng: np.random.Generator, rounds: int = 15,
                        noise: NoiseModel | None = None, tip_mm: np.ndarray | None = None,
                        reference_to_tracker: np.ndarray | None = None,
                        distortion: FieldDistortion | None = None) -> TrackingRecording:
    """A navigation recording: the probe tip-first onto each target, ``rounds`` times, hand-held (with a stylus,
    ``tip_mm``: its tip on the targets; ``reference_to_tracker``, ``distortion``: as for
    :func:`simulate_calibration`)."""
    centre, visits = _target_visits(frame, rng, rounds, tip_mm)
    placement = reference_placement(rng) if reference_to_tracker is None else reference_to_tracker
    recording, _, _ = simulate_session(rng, visits, placement, np.eye(4), centre, lift_mm=20.0, noise=noise,
                                       distortion=distortion)
    return recording


def simulate_checked_navigation(frame: Frame, rng: np.random.Generator, rounds: int, checkpoints: int,
                                noise: NoiseModel | None = None, reference_to_tracker: np.ndarray | None = None,
                                slip: ReferenceSlip | None = None, distortion: FieldDistortion | None = None,
                                onset: FieldOnset | None = None, hesitation_rate: float = 0.0,
                                bump: FrameBump | None = None) -> tuple[TrackingRecording, list[DwellTruth]]:
    """A navigation recording with ``checkpoints`` unlabelled rests of the probe in pinholes (markers in the CT,
    evenly among ``rounds`` rounds of the targets), and the dwells' truth. ``slip``: the reference sensor slips
    in its slot; ``distortion`` with ``onset``: a metal object rolled in mid-recording (both have their times
    set); ``reference_to_tracker``: as for :func:`simulate_calibration`; ``hesitation_rate``: the chance of a
    short mid-air pause in a transition (the hard difficulty's); ``bump``: the frame knocked as a whole (its time
    set)."""
    centre, visits = _target_visits(frame, rng, rounds, None)
    available = np.nonzero(frame.in_ct)[0]
    chosen = rng.choice(available, size=checkpoints, replace=len(available) < checkpoints)
    where = np.linspace(0, len(visits), checkpoints + 2)[1:-1].round().astype(int)
    for k, (i, at) in enumerate(zip(chosen, where, strict=True)):
        rotation = probe_rotation_into(-frame.axes[i], rng.uniform(0, 2 * np.pi))
        visits.insert(int(at) + k, Visit(_touch(rotation, frame.pinholes[i], None), float(rng.uniform(1.0, 2.0)),
                                         "", frame.labels[i]))
    placement = reference_placement(rng) if reference_to_tracker is None else reference_to_tracker
    recording, dwells, _ = simulate_session(rng, visits, placement, np.eye(4), centre, lift_mm=20.0, noise=noise,
                                            hesitation_rate=hesitation_rate, reference_slip=slip,
                                            distortion=distortion, distortion_onset=onset, frame_bump=bump)
    return recording, dwells


@dataclass
class Session:
    """One calibration + registration: the result or the refusal, and its errors against the truth."""

    registration: RegistrationResult | None
    calibration: object | None  # FrameCalibration
    refused: str | None
    target_errors_mm: np.ndarray | None  # true registration error at each target (no navigation noise)
    l_error_mm: float | None


def calibrate_and_register(frame: Frame, rng: np.random.Generator, noise: NoiseModel | None = None,
                           subset: np.ndarray | None = None, tool: object | None = None,
                           true_tip_mm: np.ndarray | None = None, reference_to_tracker: np.ndarray | None = None,
                           distortion: FieldDistortion | None = None) -> Session:
    """Simulate a calibration session, then the real calibration and registration; errors vs the truth.
    ``tool`` (a :class:`~EMRegModule.core.tool.ToolCalibration`): the session touches with a stylus whose tip is
    truly at ``true_tip_mm`` and is calibrated with ``tool``'s; ``reference_to_tracker``, ``distortion``: as
    for :func:`simulate_calibration`."""
    recording = simulate_calibration(frame, rng, noise, subset, tip_mm=true_tip_mm,
                                     reference_to_tracker=reference_to_tracker, distortion=distortion)
    try:
        calibration = calibrate_frame(recording, DEFAULT_REFERENCE_PORT, DEFAULT_PROBE_PORT,
                                      frame.settings.calibration, tool=tool)
        registration = register(frame.detection, calibration, frame.model, frame.settings.registration,
                                targets_image=frame.targets_image)
    except EMRegError as exc:
        return Session(None, None, str(exc), None, None)
    errors = np.linalg.norm(apply_transform(registration.reference_to_image, frame.targets_reference)
                            - frame.targets_image, axis=1)
    return Session(registration, calibration, None, errors,
                   registration.sensor_offset_l_mm - frame.truth["sensor_offset_l_mm"])


def with_noise(noise: NoiseModel, **changes: float) -> NoiseModel:
    """``noise`` with some magnitudes changed (e.g. a jittery reference sensor)."""
    return replace(noise, **changes)
