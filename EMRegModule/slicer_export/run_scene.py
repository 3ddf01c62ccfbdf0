"""The scene of one run: what it shows (:class:`RunScene`, from a run's output files or from the Slicer Logic's
results) and its nodes on a scene (:func:`build_run_scene`). Image-space positions are LPS (mm) here and RAS in
the nodes; Reference-frame ones stay as they are, under the ``ReferenceToImage`` node.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ..core.frames import lps_to_ras_points
from ..core.registration import RegistrationResult
from ..errors import EMRegError
from ..io.case import run_ct_path
from ..io.image import read_ct
from ..io.markups import read_markups
from ..io.run_folder import RunFolder, read_manifest, read_run_folder, recorded_series_uid
from ..names import (
    CALIBRATION_NODE_NAME,
    FIDUCIALS_NODE_NAME,
    MARKERS_NODE_NAME,
    PATH_NODE_NAME,
    PINHOLES_NODE_NAME,
    PROBE_NODE_NAME,
    RESIDUALS_NODE_NAME,
    TARGETS_FILE,
    TARGETS_NODE_NAME,
    TIP_NODE_NAME,
    TRANSFORM_NODE_NAME,
    TRE_MAP_NODE_NAME,
    VOLUME_NODE_NAME,
)
from .mrb import StoredVoxels, stored_voxels
from .nodes import (
    show_curve,
    show_points,
    show_reference_to_image,
    show_residual_spheres,
    show_stored_volume,
    show_transform,
    show_tre_map,
    show_volume,
)
from .robot_scene import RobotScene, build_robot_scene, robot_scene_of

#: Most control points of the probe path curve (the recording is subsampled evenly).
MAX_PATH_POINTS = 1000


@dataclass
class RunScene:
    """What a run's scene shows, from its output files (all image-space positions LPS, mm)."""

    marker_ids: list[str] = field(default_factory=list)
    marker_origins: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    marker_axes: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    calibration_labels: list[str] = field(default_factory=list)
    calibration_points: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    registration: RegistrationResult | None = None
    target_labels: list[str] = field(default_factory=list)
    targets: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    path: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    probe_to_reference: np.ndarray | None = None
    tip_to_probe: np.ndarray | None = None  # a tool's tip (frame_calibration.json's "tool"), None: the pinhole probe
    tre_map_path: Path | None = None
    image: Any = None
    stored_ct: StoredVoxels | None = None  # the CT in its file, copied into a bundle without being read
    robot: RobotScene | None = None  # the robot's calibration, guide and plan (issue 39), None without them
    notes: list[str] = field(default_factory=list)


def run_scene_of(folder: RunFolder, targets: tuple[list[str], np.ndarray] | None = None,
                 probe_to_reference: np.ndarray | None = None) -> RunScene:
    """What a run's scene shows, from its outputs (read from OUT, or the Slicer Logic's results in memory):
    markers, calibration points (and a tool's ``TipToProbe``), the registration, the probe path, the
    predicted-TRE map, the robot's calibration, guide and plan; ``targets`` (labels, (N, 3) image LPS mm) and the
    last probe pose ``probe_to_reference`` (4x4, probe -> Reference) when known. Without the CT (:func:`collect_run`
    adds it)."""
    content = RunScene(probe_to_reference=probe_to_reference, registration=folder.registration,
                       tre_map_path=folder.tre_map_path, robot=robot_scene_of(folder))
    if folder.detection is not None:
        content.marker_ids = [m.id for m in folder.detection.markers]
        content.marker_origins = folder.detection.origins
        content.marker_axes = folder.detection.axes
    calibration = folder.frame_calibration
    if calibration is not None:
        tool = calibration.tool
        if tool is not None and tool.get("TipToProbe") is not None:
            content.tip_to_probe = np.asarray(tool["TipToProbe"], dtype=float).reshape(4, 4)
        content.calibration_labels = list(calibration.labels)
        content.calibration_points = calibration.positions
    if folder.navigation_positions is not None:
        content.path = folder.navigation_positions
    if targets is not None:
        content.target_labels, content.targets = list(targets[0]), np.asarray(targets[1], dtype=float)
    return content


def collect_run(out_dir: str | os.PathLike[str], case_dir: str | os.PathLike[str] | None = None,
                image: Any = None) -> RunScene:
    """Read a run's outputs (:func:`~EMRegModule.io.run_folder.read_run_folder`: an unreadable file raises
    :class:`EMRegError`), the case's targets and its CT: when the CT that ``run.json`` names (per-stage
    outputs: the case's, :func:`~EMRegModule.io.case.run_ct_path`) is a plain NRRD (:func:`stored_voxels`)
    and ``image``, if given, has its grid, the file's stored voxels (a bundle copies them, nothing is read
    into memory); otherwise ``image``, else the CT read (of a DICOM folder, the series the markers were
    detected in, as ``markers.json`` / ``run.json`` name it, not the folder's default choice: the run may
    have forced another with ``--series``)."""

    out = Path(out_dir)
    run = read_manifest(out) or {}
    if case_dir is None and run.get("case"):
        case_dir = run["case"]
    folder = read_run_folder(out, run, tolerant=False)
    targets = None
    if case_dir is not None and (Path(case_dir) / TARGETS_FILE).is_file():

        targets = read_markups(Path(case_dir) / TARGETS_FILE)
    content = run_scene_of(folder, targets)
    content.image = image
    series = recorded_series_uid(run)
    if folder.detection is not None:  # the series whose space the markers are in
        series = recorded_series_uid({"ct_series": folder.detection.ct_series}) or series
    ct = run_ct_path(run, case_dir)
    stored = stored_voxels(ct) if ct and Path(ct).is_file() else None
    if stored is not None and (image is None or _same_grid(stored.geometry, image)):
        content.stored_ct, content.image = stored, None
    elif content.image is None:
        content.image = _read_ct(ct, series, bool(run.get("fiducials")), content.notes)
    return content


def _read_ct(ct: str | None, series: str | None, fiducial_case: bool, notes: list[str]) -> Any:
    """The run's CT read whole (None, with a note, when there is none or it cannot be read)."""
    if ct and Path(ct).exists():

        try:
            return read_ct(ct, series)
        except EMRegError as exc:
            notes.append(f"CT not included ({exc})")
    elif not ct and fiducial_case:
        notes.append("no CT: a fiducial case (the fiducials are in the scene)")
    else:
        notes.append("CT not included (run.json names no CT that exists)")
    return None


def _same_grid(geometry: Any, image: Any) -> bool:
    """True when a header reading (``sitk.ImageFileReader``) and an image have the same size, pixel type
    and physical grid."""
    return (tuple(geometry.GetSize()) == tuple(image.GetSize()) and geometry.GetPixelID() == image.GetPixelID()
            and np.allclose(geometry.GetSpacing(), image.GetSpacing(), rtol=0, atol=1e-9)
            and np.allclose(geometry.GetOrigin(), image.GetOrigin(), rtol=0, atol=1e-9)
            and np.allclose(geometry.GetDirection(), image.GetDirection(), rtol=0, atol=1e-12))


def _pair_descriptions(content: RunScene) -> tuple[list[str], dict[str, tuple[str, float]]]:
    """Per marker: its pairing in words; and marker id -> (calibration label, residual)."""
    pairs: dict[str, tuple[str, float]] = {}
    if content.registration is not None:
        for pair in content.registration.pairs:
            pairs[str(pair["image_marker"])] = (str(pair["calibration_point"]), float(pair["residual_mm"]))
    texts = []
    for marker_id in content.marker_ids:
        if marker_id in pairs:
            label, residual = pairs[marker_id]
            texts.append(f"paired with calibration point {label}; residual {residual:.2f} mm")
        elif content.registration is not None:
            texts.append("unpaired (no calibration point matches it)")
        else:
            texts.append("not registered")
    return texts, pairs


def build_run_scene(scene: Any, content: RunScene, nodes: dict[str, Any] | None = None) -> dict[str, Any]:
    """Add a run's nodes to ``scene`` (a ``vtkMRMLScene``); returns them by name.

    CT volume; markers (origins, RAS; label = marker id, description = pairing and residual);
    ``ReferenceToImage`` (ReferenceToRAS) with the calibration points under it (Reference frame)
    and, when known, the probe pose ``ProbeToReference`` under it too, and a tool's ``TipToProbe`` under
    that (``TipToProbe`` alone without a probe pose); the pinhole points the
    calibration points are fitted to (``origin + l * axis``, RAS); spheres at them coloured by
    residual; targets; the probe path (curve, RAS); the predicted-TRE map when the run wrote one; the robot's
    ``SensorToFlange``, ``TrackerToBase``, needle guide and plan (:mod:`.robot_scene`) when the folder has them.

    ``nodes`` (name -> node) are reused and updated in place; those the content no longer has
    (e.g. the registration after a new CT) are removed from the scene, except the volume.
    """
    nodes = nodes if nodes is not None else {}
    built: dict[str, Any] = {}

    def keep(name: str, node: Any) -> Any:
        built[name] = nodes[name] = node
        return node

    if content.stored_ct is not None:
        keep(VOLUME_NODE_NAME, show_stored_volume(scene, content.stored_ct, node=nodes.get(VOLUME_NODE_NAME)))
    elif content.image is not None:
        keep(VOLUME_NODE_NAME, show_volume(scene, content.image, node=nodes.get(VOLUME_NODE_NAME)))
    texts, pairs = _pair_descriptions(content)
    if content.marker_ids:
        keep(MARKERS_NODE_NAME, show_points(scene, MARKERS_NODE_NAME, content.marker_ids,
                                            lps_to_ras_points(content.marker_origins), (0.2, 0.8, 0.3), texts,
                                            node=nodes.get(MARKERS_NODE_NAME)))
    transform = None
    if content.registration is not None:
        transform = keep(TRANSFORM_NODE_NAME, show_reference_to_image(
            scene, content.registration.reference_to_image, node=nodes.get(TRANSFORM_NODE_NAME)))
        l_mm = float(content.registration.sensor_offset_l_mm)
        index = {marker_id: k for k, marker_id in enumerate(content.marker_ids)}
        paired = [m for m in pairs if m in index]
        if paired:
            rows = [index[m] for m in paired]
            pinholes = lps_to_ras_points(content.marker_origins[rows] + l_mm * content.marker_axes[rows])
            keep(PINHOLES_NODE_NAME, show_points(
                scene, PINHOLES_NODE_NAME, paired, pinholes, (0.1, 0.6, 1.0),
                [f"pinhole point at l = {l_mm:.2f} mm of marker {m}; calibration point {pairs[m][0]}"
                 for m in paired], node=nodes.get(PINHOLES_NODE_NAME)))
            keep(RESIDUALS_NODE_NAME, show_residual_spheres(scene, pinholes, [pairs[m][1] for m in paired],
                                                            node=nodes.get(RESIDUALS_NODE_NAME)))
        fiducials = content.registration.fiducials
        if isinstance(fiducials, dict) and fiducials.get("points"):  # a point fit: what the points were fitted onto
            _show_fiducials(scene, fiducials, pairs, keep, nodes)
        if content.probe_to_reference is not None:
            keep(PROBE_NODE_NAME, show_transform(scene, PROBE_NODE_NAME, content.probe_to_reference, transform,
                                                 node=nodes.get(PROBE_NODE_NAME)))
    if content.tip_to_probe is not None:  # tracker-side frames: the matrix as it is (as SlicerIGT's pivot writes it)
        keep(TIP_NODE_NAME, show_transform(scene, TIP_NODE_NAME, content.tip_to_probe, built.get(PROBE_NODE_NAME),
                                           node=nodes.get(TIP_NODE_NAME)))
    if content.calibration_labels:
        keep(CALIBRATION_NODE_NAME, show_points(scene, CALIBRATION_NODE_NAME, content.calibration_labels,
                                                content.calibration_points, (0.9, 0.2, 0.9),
                                                node=nodes.get(CALIBRATION_NODE_NAME), parent_transform=transform))
    if content.target_labels:
        keep(TARGETS_NODE_NAME, show_points(scene, TARGETS_NODE_NAME, content.target_labels,
                                            lps_to_ras_points(content.targets), (0.9, 0.1, 0.1),
                                            node=nodes.get(TARGETS_NODE_NAME)))
    if content.tre_map_path is not None:
        keep(TRE_MAP_NODE_NAME, show_tre_map(scene, content.tre_map_path, node=nodes.get(TRE_MAP_NODE_NAME)))
    if len(content.path):
        step = max(1, int(np.ceil(len(content.path) / MAX_PATH_POINTS)))
        keep(PATH_NODE_NAME, show_curve(scene, PATH_NODE_NAME, lps_to_ras_points(content.path[::step]),
                                        node=nodes.get(PATH_NODE_NAME)))
    if content.robot is not None:
        built.update(build_robot_scene(scene, content.robot, nodes))
    for name in [n for n in nodes if n not in built and n != VOLUME_NODE_NAME]:
        stale = nodes.pop(name)
        if stale is not None and scene.GetNodeByID(stale.GetID()) is stale:
            scene.RemoveNode(stale)
    return built


def _show_fiducials(scene: Any, fiducials: dict[str, Any], pairs: dict[str, tuple[str, float]], keep: Any,
                    nodes: dict[str, Any]) -> None:
    """The fiducials of a point fit (``registration.json`` ``fiducials``: image space, LPS) as a point list (RAS),
    each described by its pair, with residual spheres at the paired ones."""
    labels = [str(p["label"]) for p in fiducials["points"]]
    positions = lps_to_ras_points(np.array([p["position"] for p in fiducials["points"]], dtype=float).reshape(-1, 3))
    texts = [f"fiducial of {Path(str(fiducials.get('file', ''))).name}; " + (
        f"paired with calibration point {pairs[m][0]}; residual {pairs[m][1]:.2f} mm" if m in pairs else "unpaired")
        for m in labels]
    keep(FIDUCIALS_NODE_NAME, show_points(scene, FIDUCIALS_NODE_NAME, labels, positions, (0.1, 0.6, 1.0), texts,
                                          node=nodes.get(FIDUCIALS_NODE_NAME)))
    paired = [k for k, m in enumerate(labels) if m in pairs]
    if paired:
        keep(RESIDUALS_NODE_NAME, show_residual_spheres(scene, positions[paired], [pairs[labels[k]][1] for k in paired],
                                                        node=nodes.get(RESIDUALS_NODE_NAME)))
