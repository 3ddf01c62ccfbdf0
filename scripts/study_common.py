"""Shared machinery of the accuracy studies (scripts/study_*.py); not a study itself.

To keep the studies fast they simulate ONE case (CT + recordings, ``EMRegModule.simulation``),
detect its markers ONCE, and then vary only the tracking: every repetition simulates a new
trakSTAR session with the simulator's own session model (``simulate_session``: hand-held
travel, dwells, per-dwell systematic error, correlated jitter, bad samples), with the
reference sensor placed somewhere else in the transmitter's field, and runs the real
calibration, pairing/registration and evaluation code on it. Errors are measured against the
simulator's ground truth (``truth.json``).

Frames: the Reference frame is the Body of the simulated sessions (``ReferenceToBody = I``),
so calibration points, targets and board holes are expressed in it; image space is LPS.
"""

from __future__ import annotations

import argparse
import sys
import time
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from EMRegModule.errors import EMRegError  # noqa: E402
from EMRegModule.marker_model import MarkerModel  # noqa: E402
from EMRegModule.transforms import (  # noqa: E402
    apply_rotation,
    apply_transform,
    axis_angle_to_rotation,
    invert_rigid,
    make_transform,
    random_rotation,
)

PAPER = {
    "calibration_fre_mean_mm": 1.38,
    "calibration_repetitions": 30,
    "tre_mean_mm": 1.38,
    "tre_std_mm": 0.32,
    "board": {  # Table 1: EM-measured mean, sigma; caliper mean, sigma; abs error mean +/- sd (mm)
        "L1": (75.32, 0.18, 75.12, 0.31, 0.18, 0.13), "L2": (60.43, 0.21, 60.25, 0.44, 0.19, 0.11),
        "L3": (75.51, 0.16, 75.21, 0.39, 0.21, 0.13), "L4": (60.36, 0.19, 60.16, 0.48, 0.16, 0.12),
    },
}


def add_common_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--case", type=Path, help="reuse this simulated case folder (with truth.json)")
    parser.add_argument("--work", type=Path, default=Path("study-work"),
                        help="folder for the simulated case and its detection (reused between runs)")
    parser.add_argument("--seed", type=int, default=1, help="seed of the simulated case")
    parser.add_argument("--quick", action="store_true",
                        help="a smaller frame (220 x 220 x 140 mm, 16 markers) and fewer repetitions")
    parser.add_argument("--noise-scale", type=float, default=1.0,
                        help="multiply the simulated tracker's error magnitudes (about 4 gives the paper's FRE)")


@dataclass
class Frame:
    """The simulated frame in the Reference frame, with the CT detection of its markers."""

    case_dir: Path
    truth: dict
    model: MarkerModel
    detection: object  # DetectionResult
    reference_to_image: np.ndarray  # the truth
    labels: list[str]  # calibrated marker labels
    pinholes: np.ndarray  # (N, 3) true sensor points in the Reference frame
    axes: np.ndarray  # (N, 3) marker +Y in the Reference frame
    in_ct: np.ndarray  # (N,) bool
    targets_image: np.ndarray  # (K, 3) LPS
    target_labels: list[str]

    @property
    def targets_reference(self) -> np.ndarray:
        return apply_transform(invert_rigid(self.reference_to_image), self.targets_image)


def prepare_frame(args: argparse.Namespace, log=print) -> Frame:
    """Simulate (or reuse) the case, detect its markers once (cached in the work folder)."""
    from EMRegModule.controller import EMRegController
    from EMRegModule.detection import read_detection, write_detection
    from EMRegModule.io.case import open_case
    from EMRegModule.simulation import load_truth, simulate_case

    if args.case is not None:
        case_dir = Path(args.case)
    else:
        case_dir = Path(args.work) / f"case-seed{args.seed}{'-quick' if args.quick else ''}"
        if not (case_dir / "truth.json").is_file():
            options = {"frame_size_mm": (220.0, 220.0, 140.0), "n_markers": 16} if args.quick else {}
            start = time.perf_counter()
            log(f"simulating the case into {case_dir} ...")
            simulate_case(case_dir, seed=args.seed, difficulty="standard", **options)
            log(f"  done in {time.perf_counter() - start:.0f} s")
    truth = load_truth(case_dir)
    import hashlib

    key = hashlib.sha1(str(case_dir.resolve()).encode()).hexdigest()[:8]
    markers_json = Path(args.work) / f"detection-{case_dir.name}-{key}" / "markers.json"  # the case stays untouched
    if markers_json.is_file():
        detection = read_detection(markers_json)
    else:
        start = time.perf_counter()
        log("detecting the markers in the CT (once) ...")
        case = open_case(case_dir)
        controller = EMRegController.for_case(case)
        controller.load_ct(case.ct)
        detection = controller.detect_markers()
        write_detection(detection, markers_json.parent)
        log(f"  {len(detection.markers)} markers in {time.perf_counter() - start:.0f} s")
    reference_to_image = np.asarray(truth["ReferenceToImage"], dtype=float)
    image_to_reference = invert_rigid(reference_to_image)
    calibrated = [m for m in truth["markers"] if m.get("calibrated", True)]
    return Frame(
        case_dir=case_dir, truth=truth, model=MarkerModel.from_settings(truth.get("marker_model")),
        detection=detection, reference_to_image=reference_to_image,
        labels=[m["label"] for m in calibrated],
        pinholes=np.array([m["pinhole_in_reference"] for m in calibrated], dtype=float),
        axes=apply_rotation(image_to_reference, np.array([m["axis"] for m in calibrated], dtype=float)),
        in_ct=np.array([bool(m.get("in_ct", True)) for m in calibrated]),
        targets_image=np.array([t["position"] for t in truth["targets"]], dtype=float).reshape(-1, 3),
        target_labels=[t["label"] for t in truth["targets"]],
    )


def noise_model(scale: float = 1.0):
    """The simulator's trakSTAR error model with every magnitude multiplied by ``scale``."""
    from EMRegModule.simulation.tracking import NoiseModel

    base = NoiseModel()
    fields = ("probe_dwell_mm", "probe_dwell_deg", "probe_jitter_mm", "probe_jitter_deg", "reference_static_mm",
              "reference_static_deg", "reference_jitter_mm", "reference_jitter_deg")
    return replace(base, **{f: getattr(base, f) * scale for f in fields})


def reference_placement(rng: np.random.Generator) -> np.ndarray:
    """A ``ReferenceToTracker`` somewhere in the transmitter's field (250-400 mm away, any heading)."""
    rotation = random_rotation(rng, 6.0) @ axis_angle_to_rotation([0, 0, 1], rng.uniform(-np.pi, np.pi)) \
        @ np.diag([1.0, -1.0, -1.0])
    position = np.array([rng.uniform(250, 400), rng.uniform(-100, 100), rng.uniform(-60, 80)])
    return make_transform(rotation, position)


def simulate_calibration(frame: Frame, rng: np.random.Generator, noise=None, subset: np.ndarray | None = None):
    """A calibration recording: the probe into each (selected) pinhole in turn, labelled by marker."""
    from EMRegModule.simulation.tracking import Visit, probe_rotation_into, simulate_session

    index = np.arange(len(frame.labels)) if subset is None else np.asarray(subset)
    visits = []
    for i in index:
        rotation = probe_rotation_into(-frame.axes[i], rng.uniform(0, 2 * np.pi))
        visits.append(Visit(make_transform(rotation, frame.pinholes[i]), float(rng.uniform(1.0, 2.0)),
                            frame.labels[i], frame.labels[i]))
    recording, _, _ = simulate_session(rng, visits, reference_placement(rng), np.eye(4),
                                       frame.pinholes[index].mean(axis=0), lift_mm=25.0, noise=noise)
    return recording


def simulate_navigation(frame: Frame, rng: np.random.Generator, rounds: int = 15, noise=None):
    """A navigation recording: the probe tip-first onto each target, ``rounds`` times, hand-held."""
    from EMRegModule.simulation.tracking import Visit, probe_rotation_into, simulate_session

    targets = frame.targets_reference
    centre = targets.mean(axis=0)
    visits = []
    for _ in range(rounds):
        for label, target in zip(frame.target_labels, targets, strict=True):
            inward = centre - target if np.linalg.norm(centre - target) > 1 else np.array([0.0, 0.0, 1.0])
            rotation = probe_rotation_into(inward, rng.uniform(0, 2 * np.pi), 25.0, rng)
            visits.append(Visit(make_transform(rotation, target), float(rng.uniform(1.0, 2.0)), label, label,
                                tremor_mm=0.08))
    recording, _, _ = simulate_session(rng, visits, reference_placement(rng), np.eye(4), centre, lift_mm=20.0,
                                       noise=noise)
    return recording


@dataclass
class Session:
    """One calibration + registration: the result or the refusal, and its errors against the truth."""

    registration: object | None
    refused: str | None
    target_errors_mm: np.ndarray | None  # true registration error at each target (no navigation noise)
    l_error_mm: float | None


def calibrate_and_register(frame: Frame, rng: np.random.Generator, noise=None, subset=None) -> Session:
    """Simulate a calibration session, then the real calibration and registration; errors vs the truth."""
    from EMRegModule.calibration import calibrate_frame
    from EMRegModule.registration import register

    recording = simulate_calibration(frame, rng, noise, subset)
    try:
        calibration = calibrate_frame(recording, 1, 2, None)
        registration = register(frame.detection, calibration, frame.model, None, targets_image=frame.targets_image)
    except EMRegError as exc:
        return Session(None, str(exc), None, None)
    errors = np.linalg.norm(apply_transform(registration.reference_to_image, frame.targets_reference)
                            - frame.targets_image, axis=1)
    return Session(registration, None, errors, registration.sensor_offset_l_mm - frame.truth["sensor_offset_l_mm"])


def table(header: list[str], rows: list[list[str]]) -> str:
    """A Markdown table (also readable as plain text)."""
    widths = [max(len(str(h)), *(len(str(r[i])) for r in rows)) for i, h in enumerate(header)]
    lines = ["| " + " | ".join(str(h).ljust(w) for h, w in zip(header, widths, strict=True)) + " |",
             "|" + "|".join("-" * (w + 2) for w in widths) + "|"]
    lines += ["| " + " | ".join(str(c).ljust(w) for c, w in zip(r, widths, strict=True)) + " |" for r in rows]
    return "\n".join(lines)


def mean_std(values) -> str:
    values = np.asarray(values, dtype=float)
    if values.size == 0:
        return "-"
    return f"{values.mean():.2f} +/- {values.std(ddof=1) if values.size > 1 else 0.0:.2f}"
