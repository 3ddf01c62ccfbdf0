"""Assemble and write a complete simulated case folder with its ground truth (``truth.json``).

Frames: ``Frame`` (the fiducial frame's CAD frame, see :mod:`.frame`), ``Image`` (CT, LPS),
``Reference`` (Model 800), ``Probe`` (Model 90), ``Tracker`` (transmitter), ``Board``.
"""

from __future__ import annotations

import shutil
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from ..core.tool import ToolCalibration
from ..core.transforms import apply_transform, axis_angle_to_rotation, invert_rigid, random_rotation
from ..errors import EMRegError
from ..io.atomic import atomic_write_json, atomic_write_text, read_json
from ..io.markups import write_markups
from ..io.tool_files import write_tool_calibration
from ..io.tracking_csv import write_tracking_csv
from ..marker_model import MarkerModel
from ..names import CT_FILE_NAMES, CT_FOLDER_NAME, TARGETS_FILE
from ..progress import QUIET, Progress
from . import ct
from .distortion import FieldDistortion, nonrigid_errors, place_object, truth_at_points
from .frame import REFERENCE_SENSOR_DIAMETER_MM, REFERENCE_SENSOR_LENGTH_MM, Phantom, build_phantom
from .options import SimulationOptions, resolve_options
from .shapes import pose
from .stylus import shaft_rotation, simulate_pivot_recording
from .tracking import NoiseModel, ReferenceSlip, Visit, apply_probe_convention, probe_rotation_into, simulate_session

# independent random streams, so that e.g. a new spacing does not change the recordings
STREAM_LAYOUT, STREAM_PLACEMENT, STREAM_NOISE, STREAM_STREAKS = 1, 2, 3, 4
STREAM_CALIBRATION, STREAM_NAVIGATION, STREAM_BOARD, STREAM_OFFSET = 5, 6, 7, 8
STREAM_MARKER_STREAKS = 9
STREAM_CHECKPOINTS = 10  # and 11: the reference slip
STREAM_DISTORTION = 12
MAX_VOXELS = 1_500_000_000


def _rng(seed: int, stream: int) -> np.random.Generator:
    return np.random.default_rng([int(seed) & 0xFFFFFFFF, stream])


def simulate_case(out_dir: Path, seed: int = 0, difficulty: str = "standard", spacing_mm: float | None = None,
                  progress: Progress | None = None, **options: Any) -> dict:
    """Write a simulated case into ``out_dir`` and return its ground truth (the content of ``truth.json``).

    ``options``: any field of :class:`SimulationOptions` (e.g. ``frame_size_mm``,
    ``n_markers``, ``noise_hu``, ``ct_format``); ``spacing_mm`` is the CT voxel size, a
    number (isotropic) or three values (i, j, k). Raises :class:`EMRegError` for bad options.
    """
    progress = progress or QUIET
    opts = resolve_options(difficulty, spacing_mm, options)
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    (out_dir / "truth.json").unlink(missing_ok=True)  # written last: present only for a complete case
    model = MarkerModel.from_settings(opts.marker)
    start = time.perf_counter()

    with progress.step("simulate: frame layout"):
        phantom = _phantom(seed, opts, model)
        placement = _rng(seed, STREAM_PLACEMENT)
        frame_to_image = _frame_to_image(placement, phantom, opts)
        # at least half the requested obliqueness, so that no seed gets a grid that is nearly LPS by chance
        direction = (random_rotation(placement, opts.oblique_deg, min_angle_deg=opts.oblique_deg / 2)
                     if opts.oblique_deg > 0 else np.eye(3))
        if opts.flip:
            direction = direction @ np.diag([-1.0, 1.0, 1.0])
        if opts.direction is not None:
            direction = np.asarray(opts.direction, dtype=float).reshape(3, 3)
        extent_image = apply_transform(frame_to_image, phantom.extent_points)
        grid = ct.grid_around(extent_image, np.asarray(opts.spacing), direction, margin_mm=8.0)

    image, grid = _synthesise_ct(seed, opts, phantom, frame_to_image, grid, progress)
    ct_written = _write_ct(image, grid, out_dir, opts, seed, progress)
    del image

    with progress.step("simulate: tracking recordings"):
        l_mm, calibration, navigation, board = _write_recordings(out_dir, seed, opts, phantom, model)
        targets_image = navigation["targets_image"]
        if len(targets_image):
            write_markups(out_dir / TARGETS_FILE, [f"T{i + 1}" for i in range(len(targets_image))],
                          targets_image, name="T")
        else:
            (out_dir / TARGETS_FILE).unlink(missing_ok=True)
        atomic_write_text(out_dir / "case.toml", _case_toml(seed, difficulty, opts, model))
        _write_tool(out_dir, seed, opts)

    truth = _truth(seed, difficulty, opts, model, phantom, frame_to_image, ct_written, l_mm,
                   calibration, navigation, board)
    atomic_write_json(out_dir / "truth.json", truth)
    progress.message(f"[emreg] simulated {difficulty} case (seed {seed}) in {time.perf_counter() - start:.1f}s "
                     f"-> {out_dir}")
    return truth


def simulate_recordings(out_dir: Path, seed: int = 0, difficulty: str = "standard", **options: Any) -> dict:
    """Write only the tracking recordings (``calibration.csv``, ``navigation.csv``, ``board.csv``) of the
    case ``simulate_case`` makes with the same seed, difficulty and options: the same recordings,
    e.g. in another probe convention (``probe_axis``), beside an existing case's CT and truth.
    Returns the navigation's ground truth (``truth.json``'s ``"navigation"`` without its pose)."""
    opts = resolve_options(difficulty, None, options)
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    model = MarkerModel.from_settings(opts.marker)
    navigation = _write_recordings(out_dir, seed, opts, _phantom(seed, opts, model), model)[2]
    return {"dwells": _dwell_list(navigation["dwells"]),
            **({"reference_slip": navigation["reference_slip"]} if navigation.get("reference_slip") else {})}


def _write_recordings(out_dir: Path, seed: int, opts: SimulationOptions, phantom: Phantom,
                      model: MarkerModel) -> tuple[float, dict, dict, dict]:
    l_mm = opts.sensor_offset_l_mm
    if l_mm is None:
        l_mm = float(_rng(seed, STREAM_OFFSET).uniform(model.pinhole_bottom_mm + 1, model.pinhole_top_mm - 1))
    calibration = _calibration(seed, opts, phantom, l_mm)
    navigation = _navigation(seed, opts, phantom, _frame_to_image(_rng(seed, STREAM_PLACEMENT), phantom, opts),
                             l_mm, calibration["distortion"])
    board = _board(seed, opts, phantom)
    _write_recording(calibration.pop("recording"), out_dir / "calibration.csv", probe_axis=opts.probe_axis)
    _write_recording(navigation.pop("recording"), out_dir / "navigation.csv", probe_axis=opts.probe_axis)
    _write_recording(board.pop("recording"), out_dir / "board.csv",
                     orientation="quaternion" if opts.board_quaternions else "angles", probe_axis=opts.probe_axis)
    return l_mm, calibration, navigation, board


def load_truth(case_dir: str | Path) -> dict:
    """The ground truth of a simulated case (``truth.json``), numbers as lists."""
    return read_json(Path(case_dir) / "truth.json", "simulation truth")


# --- phantom and CT ---------------------------------------------------------------------------


def _phantom(seed: int, opts: SimulationOptions, model: MarkerModel) -> Phantom:
    layout = _rng(seed, STREAM_LAYOUT)
    chosen = layout.permutation(opts.n_markers)
    absent = [int(i) for i in chosen[:opts.n_absent]]
    uncalibrated = [int(i) for i in chosen[opts.n_absent:opts.n_absent + opts.n_uncalibrated]]
    try:
        return build_phantom(layout, model, opts.frame_size_mm, opts.n_markers, opts.n_decoys, absent,
                             uncalibrated, opts.n_targets, opts.patient, opts.couch, pvc_hu=opts.pvc_hu)
    except ValueError as exc:
        raise EMRegError(f"simulate: {exc}") from None


def _frame_to_image(rng: np.random.Generator, phantom: Phantom, opts: SimulationOptions) -> np.ndarray:
    """``FrameToImage``: frame X -> patient left/right, Y -> head (S) or feet, Z (up) -> anterior (-P)."""
    sign = 1.0 if rng.random() < 0.5 else -1.0
    base = np.array([[sign, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, sign, 0.0]])
    tilt = random_rotation(rng, opts.frame_tilt_deg) if opts.frame_tilt_deg > 0 else np.eye(3)
    rotation = tilt @ base
    centre_frame = np.array([0.0, 0.0, phantom.geometry.size[2] / 2])
    centre_image = np.array([rng.uniform(-40, 40), rng.uniform(-60, 20), rng.uniform(-900, -150)])
    return pose(rotation, centre_image - rotation @ centre_frame)


def _synthesise_ct(seed: int, opts: SimulationOptions, phantom: Phantom, frame_to_image: np.ndarray,
                   grid: ct.Grid, progress: Progress):
    if grid.n_voxels > MAX_VOXELS:
        raise EMRegError(f"simulate: a CT of {grid.size} voxels is too large; use a coarser --spacing")
    start = time.perf_counter()
    volume = np.full(grid.shape_kji, ct.AIR_HU, dtype=np.float32)
    ct.paint_layers(volume, grid, invert_rigid(frame_to_image), phantom.layers, progress)
    with progress.step("simulate: blur + noise"):
        ct.blur_and_noise(volume, grid, opts.psf_fwhm_mm, opts.noise_hu, _rng(seed, STREAM_NOISE))
    if opts.metal_streaks:
        reference_to_image = frame_to_image @ phantom.reference_to_frame
        axis = reference_to_image[:3, 0]
        half_z = abs(axis[2]) * REFERENCE_SENSOR_LENGTH_MM / 2 + REFERENCE_SENSOR_DIAMETER_MM / 2
        ct.add_metal_streaks(volume, grid, reference_to_image[:3, 3], half_z, _rng(seed, STREAM_STREAKS),
                             radius_mm=110.0 * min(phantom.geometry.size[:2]) / 350.0 + 20.0)
    if opts.marker_streaks:
        _streak_markers(volume, grid, phantom, frame_to_image, opts, _rng(seed, STREAM_MARKER_STREAKS))
    array = ct.to_int16(volume)
    del volume
    elapsed = time.perf_counter() - start
    progress.message(f"[emreg] CT {grid.size[0]}x{grid.size[1]}x{grid.size[2]} ({grid.n_voxels / 1e6:.0f} M voxels, "
                     f"spacing {', '.join(f'{v:g}' for v in grid.spacing)} mm) synthesised in {elapsed:.1f}s")
    if opts.ct_format == "dicom":
        array, grid = ct.flip_to_right_handed(array, grid)
        array = np.ascontiguousarray(array)
    return ct.to_sitk(array, grid), grid


def _streak_markers(volume, grid: ct.Grid, phantom: Phantom, frame_to_image: np.ndarray, opts: SimulationOptions,
                    rng: np.random.Generator) -> None:
    """Dark streaks crossing ``opts.marker_streaks`` markers at their shoulder (where the top meets the bottom).

    A streak lies in the scanner's axial plane (constant LPS z), across the marker's axis as
    the plane shows it, over the slices within 4 mm of the shoulder: it cuts the narrow top off
    the wide bottom, as a streak from the reference sensor's metal does. Markers whose axis is
    within 30 degrees of z are not chosen (an axial streak cannot cut their top off). The
    markers chosen are recorded as ``streaked`` in ``truth.json``.
    """
    model = phantom.model
    candidates = []
    for m in phantom.markers:
        axis = (frame_to_image @ m.marker_to_frame)[:3, 1]
        if m.in_ct and abs(axis[2]) < np.cos(np.radians(30.0)):
            candidates.append(m)
    for m in rng.permutation(len(candidates))[:opts.marker_streaks]:
        marker = candidates[int(m)]
        marker_to_image = frame_to_image @ marker.marker_to_frame
        shoulder = marker_to_image[:3, 3] + model.bottom_height_mm * marker_to_image[:3, 1]
        axis_in_plane = marker_to_image[:3, 1] * np.array([1.0, 1.0, 0.0])
        line_angle = float(np.arctan2(axis_in_plane[1], axis_in_plane[0])) + np.pi / 2  # across the axis
        ct.add_dark_streak(volume, grid, shoulder, line_angle, opts.marker_streak_hu, half_extent_z_mm=4.0,
                           width_mm=float(rng.uniform(0.8, 1.1)), length_mm=60.0)
        marker.streaked = True


def _write_ct(image, grid: ct.Grid, out_dir: Path, opts: SimulationOptions, seed: int, progress: Progress) -> dict:
    start = time.perf_counter()
    if opts.ct_format == "dicom":
        ct.write_dicom_series(image, out_dir / "ct", seed, progress=progress)
        name = "ct"
    else:
        with progress.step("simulate: write ct.nrrd"):
            ct.write_nrrd(image, out_dir / "ct.nrrd")
        name = "ct.nrrd"
    _remove_stale_cts(out_dir, keep=name)
    progress.message(f"[emreg] {name} written in {time.perf_counter() - start:.1f}s")
    return {"file": name, **grid.to_dict()}


def _remove_stale_cts(out_dir: Path, keep: str) -> None:
    """A case holds one CT: drop those an earlier simulation into the same folder left behind."""
    for name in (*CT_FILE_NAMES, CT_FOLDER_NAME):
        path = out_dir / name
        if name == keep or not path.exists():
            continue
        if path.is_dir():
            shutil.rmtree(path)
        else:
            path.unlink()


# --- tracking ---------------------------------------------------------------------------------


def _write_recording(recording, path: Path, orientation: str | None = None, probe_axis: str = "+x_in") -> None:
    """Write a recording (probe rows in the given convention), or remove a stale file when there is
    nothing to record."""
    if recording is None:
        path.unlink(missing_ok=True)
    else:
        write_tracking_csv(apply_probe_convention(recording, probe_axis), path, orientation=orientation)


def _frame_to_tracker(rng: np.random.Generator, size: np.ndarray, yaw_deg: float, offset: np.ndarray) -> np.ndarray:
    """The frame in the transmitter's field: tracker +Z points down, so Frame +Z (up) maps to Tracker -Z."""
    base = np.diag([1.0, -1.0, -1.0])
    yaw = axis_angle_to_rotation([0, 0, 1], np.radians(yaw_deg))
    rotation = random_rotation(rng, 4.0) @ yaw @ base
    centre_frame = np.array([0.0, 0.0, size[2] / 2])
    return pose(rotation, offset - rotation @ centre_frame)


def _calibration(seed: int, opts: SimulationOptions, phantom: Phantom, l_mm: float) -> dict:
    rng = _rng(seed, STREAM_CALIBRATION)
    frame_to_tracker = _frame_to_tracker(rng, phantom.geometry.size, rng.uniform(-180, 180),
                                         np.array([rng.uniform(280, 380), rng.uniform(-60, 60), rng.uniform(-40, 80)]))
    visits = []
    for m in phantom.markers:
        if not m.calibrated:
            continue
        rotation = m.marker_to_frame[:3, :3] @ probe_rotation_into([0.0, -1.0, 0.0], rng.uniform(0, 2 * np.pi))
        position = apply_transform(m.marker_to_frame, [0.0, l_mm, 0.0])
        label = m.label if opts.calibration_labels else ""
        if opts.tool_tip_mm is None:
            visits.append(Visit(pose(rotation, position), float(rng.uniform(1.0, 2.0)), label, m.label))
        else:  # the stylus's tip in the pinhole, the shaft along the hole's axis, pivoting
            visits.append(_tool_visit(rotation, position, opts, float(rng.uniform(2.0, 3.0)), label, m.label,
                                      opts.pivot_swing_deg))
    bumps: dict[int, np.ndarray] = {}
    current = frame_to_tracker
    if opts.n_bumps and len(visits) > 2:
        for i in sorted(rng.choice(np.arange(1, len(visits)), size=min(opts.n_bumps, len(visits) - 1),
                                   replace=False)):
            pivot = current[:3, 3] + rng.normal(0, 40.0, 3)
            rotation = random_rotation(rng, 4.0)
            shift = rng.normal(0, 1.0, 3)
            shift *= rng.uniform(3.0, 15.0) / np.linalg.norm(shift)
            delta = pose(rotation, pivot - rotation @ pivot + shift)
            current = delta @ current
            bumps[int(i)] = current
    noise = NoiseModel(bad_sample_rate=opts.bad_sample_rate).scaled(opts.tracker_noise_scale)
    centre = np.array([0.0, 0.0, phantom.geometry.size[2] / 2])
    start_time_s = round(float(rng.uniform(0, 5)), 2)
    distortion = _distortion(seed, opts, phantom, l_mm, frame_to_tracker, start_time_s)
    recording, dwells, body_poses = simulate_session(
        rng, visits, frame_to_tracker, phantom.reference_to_frame, centre, lift_mm=25.0, bump_before=bumps,
        hesitation_rate=opts.hesitation_rate, noise=noise, start_time_s=start_time_s,
        distortion=distortion["calibration"] if distortion else None)
    reference_to_tracker = [b @ phantom.reference_to_frame for b in body_poses]
    return {"recording": recording, "dwells": dwells, "reference_to_tracker": reference_to_tracker,
            "bumps": len(bumps), "distortion": distortion}


def _tool_visit(probe_rotation: np.ndarray, tip_position: np.ndarray, opts: SimulationOptions, duration_s: float,
                label: str, name: str, swing_deg: float) -> Visit:
    """A stylus touch: the sensor turned so that its shaft (sensor to tip) runs along ``probe_rotation``'s +X (the
    pinhole probe's way in), placed so that the tip (``opts.tool_tip_mm``) is at ``tip_position``."""
    tip_mm = np.asarray(opts.tool_tip_mm, dtype=float)
    rotation = probe_rotation @ shaft_rotation(tip_mm)
    return Visit(pose(rotation, np.asarray(tip_position) - rotation @ tip_mm), duration_s, label, name,
                 tip_mm=tip_mm, pivot_swing_deg=swing_deg)


def _checkpoint_visits(seed: int, opts: SimulationOptions, phantom: Phantom, l_mm: float, visits: list[Visit]) -> None:
    """Insert ``navigation_checkpoints`` unlabelled rests in marker pinholes (markers in the CT, at depth l, as at
    calibration), evenly among the target visits; their own random stream leaves the rest unchanged."""
    rng = _rng(seed, STREAM_CHECKPOINTS)
    markers = [m for m in phantom.markers if m.in_ct]
    count = opts.navigation_checkpoints
    chosen = rng.choice(len(markers), size=count, replace=len(markers) < count)
    where = np.linspace(0, len(visits), opts.navigation_checkpoints + 2)[1:-1].round().astype(int)
    for k, (i, at) in enumerate(zip(chosen, where, strict=True)):
        m = markers[int(i)]
        rotation = m.marker_to_frame[:3, :3] @ probe_rotation_into([0.0, -1.0, 0.0], rng.uniform(0, 2 * np.pi))
        position = apply_transform(m.marker_to_frame, [0.0, l_mm, 0.0])
        visits.insert(int(at) + k, Visit(pose(rotation, position), float(rng.uniform(1.0, 2.0)), "", m.label))


def _reference_slip(seed: int, opts: SimulationOptions) -> ReferenceSlip | None:
    """The slip of the reference sensor in its slot (random directions of the given sizes), or None."""
    if opts.reference_slip_mm <= 0 and opts.reference_slip_deg <= 0:
        return None
    rng = _rng(seed, STREAM_CHECKPOINTS + 1)
    shift = rng.normal(size=3)
    rotation = axis_angle_to_rotation(rng.normal(size=3), np.radians(opts.reference_slip_deg))
    return ReferenceSlip(opts.reference_slip_at, pose(rotation, shift / np.linalg.norm(shift) * opts.reference_slip_mm))


def _distortion(seed: int, opts: SimulationOptions, phantom: Phantom, l_mm: float, frame_to_tracker: np.ndarray,
                calibration_start_s: float) -> dict | None:
    """The steel rod of ``distortion_mm`` beside the frame as calibrated (None without one): the object in each
    recording it is in (``calibration`` / ``navigation``, None where absent) and its truth at the pinholes."""
    if opts.distortion_mm <= 0:
        return None
    calibrated = [m for m in phantom.markers if m.calibrated]
    pinholes = np.array([apply_transform(m.marker_to_frame, [0.0, l_mm, 0.0]) for m in calibrated])
    distortion = place_object(_rng(seed, STREAM_DISTORTION), pinholes, frame_to_tracker, phantom.reference_to_frame,
                              opts.distortion_mm)
    onset = opts.distortion_onset_s
    calibration = navigation = None
    if opts.distortion_during in ("calibration", "both"):
        calibration = distortion if onset is None else replace(distortion, onset_s=calibration_start_s + onset)
    if opts.distortion_during == "both":
        navigation = distortion
    truth = truth_at_points(distortion, [m.label for m in calibrated], pinholes, frame_to_tracker,
                            phantom.reference_to_frame)
    return {"calibration": calibration, "navigation": navigation, "object": distortion,
            "frame_to_tracker": frame_to_tracker, "pinholes": pinholes, "truth": truth}


def _navigation(seed: int, opts: SimulationOptions, phantom: Phantom, frame_to_image: np.ndarray,
                l_mm: float, distortion: dict | None = None) -> dict:
    rng = _rng(seed, STREAM_NAVIGATION)
    frame_to_tracker = _frame_to_tracker(rng, phantom.geometry.size, rng.uniform(-180, 180),
                                         np.array([rng.uniform(250, 420), rng.uniform(-120, 120),
                                                   rng.uniform(-80, 100)]))
    if distortion is not None:  # navigated where it was calibrated: the field the calibration measured
        frame_to_tracker = distortion["frame_to_tracker"]
    visits = []
    n = len(phantom.targets)
    for _round in range(opts.navigation_rounds):
        for t in range(n):
            rotation = probe_rotation_into(-phantom.target_normals[t], rng.uniform(0, 2 * np.pi), 25.0, rng)
            if opts.tool_tip_mm is None:
                visits.append(Visit(pose(rotation, phantom.targets[t]), float(rng.uniform(1.0, 2.0)), f"T{t + 1}",
                                    f"T{t + 1}", tremor_mm=0.08))
            else:
                visit = _tool_visit(rotation, phantom.targets[t], opts, float(rng.uniform(1.0, 2.0)), f"T{t + 1}",
                                    f"T{t + 1}", 0.0)
                visit.tremor_mm = 0.08
                visits.append(visit)
    if opts.navigation_checkpoints:
        _checkpoint_visits(seed, opts, phantom, l_mm, visits)
    targets_image = apply_transform(frame_to_image, phantom.targets) if n else np.zeros((0, 3))
    out: dict[str, Any] = {"targets_image": targets_image, "dwells": [], "reference_to_tracker": None,
                           "recording": None, "reference_slip": None}
    if not visits:
        return out
    noise = NoiseModel(bad_sample_rate=opts.bad_sample_rate).scaled(opts.tracker_noise_scale)
    centre = np.asarray(phantom.targets).mean(axis=0) if n else phantom.geometry.size * [0.0, 0.0, 0.5]
    slip = _reference_slip(seed, opts)
    start_time_s = round(float(rng.uniform(0, 5)), 2)
    field = None
    if distortion is not None:
        field = distortion["navigation"]
        if opts.distortion_during == "navigation":
            field = distortion["object"]
            if opts.distortion_onset_s is not None:
                field = replace(field, onset_s=start_time_s + opts.distortion_onset_s)
        out["distortion"] = field
    recording, dwells, body_poses = simulate_session(
        rng, visits, frame_to_tracker, phantom.reference_to_frame, centre, lift_mm=20.0, noise=noise,
        start_time_s=start_time_s, reference_slip=slip, distortion=field)
    out.update(recording=recording, dwells=dwells,
               reference_to_tracker=frame_to_tracker @ phantom.reference_to_frame,
               reference_slip=None if slip is None else _slip_truth(slip, phantom, l_mm, dwells))
    return out


def _slip_truth(slip: ReferenceSlip, phantom: Phantom, l_mm: float, dwells) -> dict:
    """Ground truth of the slip: when, how much, and the error it makes at each later rest in a pinhole
    (``|inv(S) p - p|`` for the pinhole ``p`` in the Reference frame: what the navigated probe is off by,
    before tracker noise and registration error)."""
    after_to_before = slip.reference_after_to_before
    before_to_after = invert_rigid(after_to_before)
    frame_to_reference = invert_rigid(phantom.reference_to_frame)
    pinholes = {m.label: apply_transform(frame_to_reference @ m.marker_to_frame, [0.0, l_mm, 0.0])
                for m in phantom.markers}
    errors = []
    for d in dwells:
        if d.name in pinholes:
            p = pinholes[d.name]
            moved = float(np.linalg.norm(apply_transform(before_to_after, p) - p)) if d.start_s >= slip.time_s else 0.0
            errors.append({"name": d.name, "start_s": round(d.start_s, 4), "end_s": round(d.end_s, 4),
                           "true_error_mm": round(moved, 4)})
    angle = float(np.degrees(np.arccos(np.clip((np.trace(after_to_before[:3, :3]) - 1) / 2, -1, 1))))
    return {"time_s": round(float(slip.time_s), 4), "translation_mm": float(np.linalg.norm(after_to_before[:3, 3])),
            "rotation_deg": angle, "ReferenceAfterToReferenceBefore": after_to_before, "checkpoints": errors}


def board_holes(edges_mm) -> np.ndarray:
    """Corner holes H1..H4 (4, 3) in the Board frame (z = 0 plane, centred) with the given edge lengths.

    L1 = H1-H2, L2 = H2-H3, L3 = H3-H4, L4 = H4-H1; the angle at H1 is a right angle.
    """
    l1, l2, l3, l4 = (float(v) for v in edges_mm)
    h1, h2, h4 = np.array([0.0, 0.0]), np.array([l1, 0.0]), np.array([0.0, l4])
    d = np.linalg.norm(h4 - h2)
    a = (l2**2 - l3**2 + d**2) / (2 * d)
    h = np.sqrt(max(l2**2 - a**2, 0.0))
    mid = h2 + a * (h4 - h2) / d
    perp = np.array([-(h4 - h2)[1], (h4 - h2)[0]]) / d
    candidates = [mid + h * perp, mid - h * perp]
    h3 = max(candidates, key=lambda c: c[0] + c[1])  # the convex quadrilateral
    holes = np.array([h1, h2, h3, h4])
    holes -= holes.mean(axis=0)
    return np.column_stack([holes, np.zeros(4)])


def _board(seed: int, opts: SimulationOptions, phantom: Phantom) -> dict:
    """Board phantom fixed near the frame; holes in the Reference frame; probe in H1..H4 each round."""
    rng = _rng(seed, STREAM_BOARD)
    board_rotation = random_rotation(rng, 20.0) @ np.diag([1.0, -1.0, -1.0])  # board normal roughly Reference -Z
    direction = rng.normal(size=3)
    direction /= np.linalg.norm(direction)
    board_to_reference = pose(board_rotation, direction * rng.uniform(120.0, 220.0))
    holes = apply_transform(board_to_reference, board_holes(opts.board_edges_mm))
    normal = board_to_reference[:3, 2]
    reference_to_tracker = _frame_to_tracker(rng, np.zeros(3), rng.uniform(-180, 180),
                                             np.array([rng.uniform(250, 400), rng.uniform(-100, 100),
                                                       rng.uniform(-60, 60)]))
    visits = []
    for _round in range(opts.board_rounds):
        for h in range(4):
            rotation = probe_rotation_into(-normal, rng.uniform(0, 2 * np.pi), 2.0, rng)
            duration = float(rng.uniform(0.7, 1.3))
            visits.append(Visit(pose(rotation, holes[h]), duration, f"H{h + 1}", f"H{h + 1}")
                          if opts.tool_tip_mm is None else
                          _tool_visit(rotation, holes[h], opts, duration, f"H{h + 1}", f"H{h + 1}", 0.0))
    noise = NoiseModel(bad_sample_rate=opts.bad_sample_rate).scaled(opts.tracker_noise_scale)
    recording, dwells = None, []
    if visits:
        recording, dwells, _ = simulate_session(
            rng, visits, reference_to_tracker, np.eye(4), holes.mean(axis=0), lift_mm=15.0, noise=noise,
            start_time_s=round(float(rng.uniform(0, 5)), 2))
    return {"recording": recording, "dwells": dwells, "holes_in_reference": holes,
            "reference_to_tracker": reference_to_tracker}


# --- case.toml and truth ----------------------------------------------------------------------


def _case_toml(seed: int, difficulty: str, opts: SimulationOptions, model: MarkerModel) -> str:
    marker = "\n".join(f"{k} = {v:g}" for k, v in model.to_dict().items())
    edges = ", ".join(f"{v:g}" for v in opts.board_edges_mm)
    tool = "" if opts.tool_tip_mm is None else '\n[tool]\ncalibration = "tool_calibration.json"\n'
    return (f"# EMReg simulated case: seed {seed}, difficulty {difficulty}\n\n"
            f"[sensors]\nreference = 1\nprobe = 2\n\n"
            f"[marker]\n{marker}\n\n"
            f"[board]\nedges_mm = [{edges}]\n" + tool)


def _write_tool(out_dir: Path, seed: int, opts: SimulationOptions) -> None:
    """A stylus case's ``tool_calibration.json`` (the true tip) and pivot recording ``pivot.csv``; removed
    (stale) for the pinhole probe."""
    if opts.tool_tip_mm is None:
        for name in ("tool_calibration.json", "TipToProbe.h5", "pivot.csv"):
            (out_dir / name).unlink(missing_ok=True)
        return
    tip_mm = np.asarray(opts.tool_tip_mm, dtype=float)
    write_tool_calibration(ToolCalibration(pose(None, tip_mm), "simulated (true tip)", None, "truth"), out_dir)
    noise = NoiseModel(bad_sample_rate=opts.bad_sample_rate).scaled(opts.tracker_noise_scale)
    recording, _ = simulate_pivot_recording(seed, tip_mm, max(opts.pivot_swing_deg, 30.0), noise=noise)
    write_tracking_csv(recording, out_dir / "pivot.csv")


def _dwell_list(dwells, reference_to_tracker=None) -> list[dict]:
    out = []
    for i, d in enumerate(dwells):
        item = {"name": d.name, "label": d.label, "start_s": round(d.start_s, 4), "end_s": round(d.end_s, 4)}
        if isinstance(reference_to_tracker, list):
            item["ReferenceToTracker"] = reference_to_tracker[i]
        out.append(item)
    return out


def _truth(seed: int, difficulty: str, opts: SimulationOptions, model: MarkerModel, phantom: Phantom,
           frame_to_image: np.ndarray, ct_written: dict, l_mm: float, calibration: dict, navigation: dict,
           board: dict) -> dict:
    reference_to_image = frame_to_image @ phantom.reference_to_frame
    frame_to_reference = invert_rigid(phantom.reference_to_frame)
    markers = []
    for m in phantom.markers:
        marker_to_image = frame_to_image @ m.marker_to_frame
        pinhole = apply_transform(frame_to_reference @ m.marker_to_frame, [0.0, l_mm, 0.0])
        markers.append({
            "label": m.label, "origin": marker_to_image[:3, 3], "axis": marker_to_image[:3, 1],
            "marker_to_image": marker_to_image, "in_ct": m.in_ct, "calibrated": m.calibrated,
            "streaked": m.streaked,
            "pinhole_in_reference": pinhole, "face": m.face,
        })
    decoys = [{"center": apply_transform(frame_to_image, d.centre), "kind": d.kind, "hu": d.hu,
               "resting_on": d.resting_on}
              for d in phantom.decoys]
    image = {k: ct_written[k] for k in ("size", "spacing", "origin", "direction")}
    return {
        "seed": int(seed), "difficulty": difficulty, "marker_model": model.to_dict(), "image": image,
        "sensor_offset_l_mm": float(l_mm), "ReferenceToImage": reference_to_image,
        "markers": markers, "decoys": decoys,
        "targets": [{"label": f"T{i + 1}", "position": p} for i, p in enumerate(navigation["targets_image"])],
        "board": {"edges_mm": list(opts.board_edges_mm), "holes_in_reference": board["holes_in_reference"],
                  "ReferenceToTracker": board["reference_to_tracker"],
                  "dwells": _dwell_list(board["dwells"])},
        "ct": {"file": ct_written["file"], "noise_hu": opts.noise_hu, "psf_fwhm_mm": opts.psf_fwhm_mm,
               "hu": {"air": -1000.0, "pom": 340.0, "pvc": 1100.0}},
        "frame": {"size_mm": list(opts.frame_size_mm), "FrameToImage": frame_to_image,
                  "ReferenceToFrame": phantom.reference_to_frame,
                  "bed": {"radius_mm": phantom.geometry.bed_radius, "axis_z_mm": phantom.geometry.bed_axis_z}},
        "calibration": {"labelled": opts.calibration_labels, "bumps": calibration["bumps"],
                        "probe_axis": opts.probe_axis,
                        "dwells": _dwell_list(calibration["dwells"], calibration["reference_to_tracker"])},
        "navigation": {"ReferenceToTracker": navigation["reference_to_tracker"],
                       "dwells": _dwell_list(navigation["dwells"]),
                       **({"reference_slip": navigation["reference_slip"]}
                          if navigation.get("reference_slip") else {})},
        "tool": None if opts.tool_tip_mm is None else {"tip_mm": list(opts.tool_tip_mm),
                                                       "pivot_swing_deg": opts.pivot_swing_deg},
        **({"distortion": _distortion_truth(opts, phantom, calibration, navigation)} if calibration["distortion"]
           else {}),
    }


def _distortion_truth(opts: SimulationOptions, phantom: Phantom, calibration: dict, navigation: dict) -> dict:
    """``truth.json`` ``distortion``: the object (Tracker frame), when it is in each recording, its errors at the
    calibrated pinholes (Reference frame, full strength) and at the targets, and its strength at every dwell."""
    distortion = calibration["distortion"]
    frame_to_tracker = distortion["frame_to_tracker"]

    def phase(field: FieldDistortion | None, dwells: list) -> dict | None:
        if field is None:
            return None
        return {"onset_s": field.onset_s if np.isfinite(field.onset_s) else None, "ramp_s": field.ramp_s,
                "dwells": [{"name": d.name, "start_s": round(d.start_s, 4), "end_s": round(d.end_s, 4),
                            "strength": round(float(field.strength((d.start_s + d.end_s) / 2)), 4)}
                           for d in dwells]}

    targets = {}
    if len(phantom.targets):
        raw, nonrigid = nonrigid_errors(distortion["object"], distortion["pinholes"], frame_to_tracker,
                                        phantom.reference_to_frame,
                                        at_body=np.asarray(phantom.targets))
        targets = {f"T{i + 1}": {"raw_mm": r.tolist(), "after_registration_mm": n.tolist(),
                                 "after_registration_norm_mm": float(np.linalg.norm(n))}
                   for i, (r, n) in enumerate(zip(raw, nonrigid, strict=True))}
    return {"size_mm": opts.distortion_mm, "during": opts.distortion_during,
            "object": distortion["object"].to_json(), "FrameToTracker": frame_to_tracker,
            "frame": "pinhole and target errors in the Reference frame (mm), at full strength",
            **distortion["truth"], "targets": targets,
            "calibration": phase(distortion["calibration"], calibration["dwells"]),
            "navigation": phase(navigation.get("distortion"), navigation["dwells"])}
