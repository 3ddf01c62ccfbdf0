"""Tracked tools: a sensor plus a tip, ``TipToProbe`` (4x4, mm: the tip frame into the probe sensor's frame).

PLUS calls it ``StylusTipToStylus`` (``<Transform From="StylusTip" To="Stylus">`` in a device-set file);
SlicerIGT's pivot calibration writes it as a linear transform. Without a tool EMReg uses the paper's pinhole
probe (the sensor on the pinhole axis at an unknown depth l); with one, every probe sample is turned into the
tip's pose (``TipToReference = ProbeToReference @ TipToProbe``), so the touched points are tip positions and
there is no unknown depth.

Tool files (:func:`read_tool`), by name:

- ``*.json``: EMReg's ``tool_calibration.json`` (``{"TipToProbe": 4x4, ...}``, :func:`write_tool_calibration`);
- ``*.h5``, ``*.tfm``, ``*.txt``: an ITK transform file as 3D Slicer saves a linear transform node named
  ``TipToProbe``. ITK stores the *resampling* transform (it maps points of the parent frame, Probe, into the
  child frame, Tip: the inverse of the node's "to parent" matrix) in LPS, and 3D Slicer converts it to RAS on
  reading: a file holding ``T`` is the node ``TipToProbe = F @ inv(T) @ F`` with ``F = diag(-1, -1, 1)``.
  Both frames are tracker-side frames, which Slicer (as PLUS and SlicerIGT) uses unchanged, so the node's
  matrix is ``TipToProbe`` itself; :func:`write_tip_to_probe_itk` writes ``T = F @ ProbeToTip @ F``;
- ``*.xml``: a PLUS device-set file: ``<CoordinateDefinitions><Transform From="<Name>Tip" To="<Name>"
  Matrix="..."/>``, ``<Name>`` the tool's transform name (``Stylus``: the recording's ``StylusToTracker``).

Pivot calibration (:func:`pivot_calibration`): the tip rests in a divot while the tool swings, so for every
sample ``R_i @ tip + p_i = pivot`` (``R_i``, ``p_i``: ``ProbeToReference``). The six unknowns (the tip in the
probe frame, the pivot point in the Reference frame) are solved by linear least squares over all samples, then
refitted without the outliers (samples whose residual exceeds three times the robust RMS residual, as PLUS's
``vtkIGSIOPivotCalibrationAlgo`` and scikit-surgerycalibration reject them) until the inliers stop changing.
The tip frame is oriented as PLUS orients it: +Z from the sensor's origin towards the tip (along the shaft), +X
the sensor's +X made perpendicular to it.
"""

from __future__ import annotations

import os
import xml.etree.ElementTree as ElementTree
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from .errors import EMRegError, NoSafeAnswerError
from .io.atomic import atomic_path, atomic_write_json, itk_write_errors, read_json
from .transforms import LPS_TO_RAS, invert_rigid

#: Names of ``emreg pivot``'s outputs.
TOOL_CALIBRATION_JSON = "tool_calibration.json"
TIP_TO_PROBE_ITK = "TipToProbe.h5"

#: A tool file's ``TipToProbe`` must be rigid within this (|R^T R - I|, |det R - 1|, last row).
RIGID_TOLERANCE = 1e-3

#: The shaft must swing over at least this cone (degrees, the largest angle between two shaft directions, 95th
#: percentile) for the tip to be pinned down along the shaft: at 0.25 mm of tracker noise per sample, 200
#: samples swung over 20 degrees put the tip within about 0.3 mm (``Testing/Python/test_tool.py``).
MIN_PIVOT_ROTATION_DEG = 20.0

#: A pivot fit whose inliers' RMS residual exceeds this (mm) did not pivot about one point (PLUS reports 0.3 to
#: 0.6 mm for hand-held pivots; a recording of touches at several places fits tens of millimetres).
MAX_PIVOT_RMS_MM = 1.5

#: Fewest samples of a pivot calibration.
MIN_PIVOT_SAMPLES = 10

#: Residuals above this many robust RMS residuals are outliers (PLUS: three standard deviations).
OUTLIER_FACTOR = 3.0

#: The outlier cut is never below this (mm): a perfect synthetic pivot keeps its samples.
MIN_OUTLIER_CUT_MM = 0.05


@dataclass
class ToolCalibration:
    """A tool: ``tip_to_probe`` (4x4, mm), where it came from, and (from a pivot calibration) how well it fits.

    ``name``: the tool's transform name (``Stylus`` for ``StylusToTracker``), None when the file does not say;
    ``pivot_point_mm``: the divot in the Reference frame (Tracker when the recording has no reference);
    ``rms_mm``: RMS distance of the inlier samples' tip from the pivot point; ``rotation_range_deg``: the
    shaft's swing (:data:`MIN_PIVOT_ROTATION_DEG`); ``samples``: inliers used of ``samples_total``."""

    tip_to_probe: np.ndarray
    source: str = ""
    name: str | None = None
    method: str = "file"
    pivot_point_mm: np.ndarray | None = None
    rms_mm: float | None = None
    rotation_range_deg: float | None = None
    samples: int | None = None
    samples_total: int | None = None
    pivot_frame: str | None = None
    warnings: list[str] = field(default_factory=list)

    @property
    def tip_mm(self) -> np.ndarray:
        """The tip in the probe sensor's frame (3,), mm."""
        return self.tip_to_probe[:3, 3].copy()

    def to_json(self) -> dict[str, Any]:
        """The ``tool_calibration.json`` document."""
        document: dict[str, Any] = {
            "TipToProbe": [[float(v) for v in row] for row in self.tip_to_probe],
            "tip_mm": [round(float(v), 4) for v in self.tip_mm],
            "method": self.method, "source": self.source,
        }
        if self.name:
            document["tool"] = self.name
        if self.pivot_point_mm is not None:
            document["pivot_point_mm"] = [round(float(v), 4) for v in self.pivot_point_mm]
            document["pivot_point_frame"] = self.pivot_frame or "Reference"
        for key in ("rms_mm", "rotation_range_deg"):
            value = getattr(self, key)
            if value is not None:
                document[key] = round(float(value), 4)
        if self.samples is not None:
            document["samples"] = int(self.samples)
            document["samples_total"] = int(self.samples_total or self.samples)
        if self.warnings:
            document["warnings"] = list(self.warnings)
        return document


# --- reading tool files ------------------------------------------------------------------------


def check_tip_to_probe(matrix: Any, where: str) -> np.ndarray:
    """``TipToProbe`` as a 4x4 float array, or :class:`EMRegError` (one line naming ``where``) when it is not
    a finite rigid transform within :data:`RIGID_TOLERANCE`."""
    try:
        matrix = np.asarray(matrix, dtype=float)
    except (TypeError, ValueError):
        raise EMRegError(f"{where}: TipToProbe is not a 4x4 matrix of numbers") from None
    if matrix.shape != (4, 4) or not np.all(np.isfinite(matrix)):
        raise EMRegError(f"{where}: TipToProbe must be a 4x4 matrix of finite numbers, got shape {matrix.shape}")
    rotation = matrix[:3, :3]
    orthogonality = float(np.max(np.abs(rotation.T @ rotation - np.eye(3))))
    determinant = float(np.linalg.det(rotation))
    last_row = float(np.max(np.abs(matrix[3] - [0, 0, 0, 1])))
    if orthogonality > RIGID_TOLERANCE or abs(determinant - 1.0) > RIGID_TOLERANCE or last_row > RIGID_TOLERANCE:
        raise EMRegError(f"{where}: TipToProbe is not a rigid transform (|R^T R - I| = {orthogonality:.2g}, "
                         f"det R = {determinant:.4g}, last row {matrix[3].tolist()}); a tool's tip transform must "
                         "be a rotation and a translation")
    return matrix


def read_tool(path: str | os.PathLike[str], name: str | None = None) -> ToolCalibration:
    """A tool from a file (module docstring), by its name: ``.json``, ``.h5`` / ``.tfm`` / ``.txt``, ``.xml``.

    ``name``: the tool's transform name (``[tool] name``), which picks the ``<Name>Tip`` transform of a PLUS
    device set. Raises :class:`EMRegError` (one line) for a missing or unreadable file, a non-rigid matrix,
    and a PLUS file without the tip transform."""
    path = Path(path)
    if not path.is_file():
        raise EMRegError(f"{path}: tool file not found")
    suffix = path.suffix.lower()
    if suffix == ".json":
        return _read_tool_json(path)
    if suffix in (".h5", ".hdf5", ".tfm", ".txt", ".mat"):
        return ToolCalibration(read_tip_to_probe_itk(path), str(path), None, "itk transform file")
    if suffix == ".xml":
        return _read_plus_device_set(path, name)
    raise EMRegError(f"{path}: not a tool file EMReg reads (tool_calibration.json, an ITK transform .h5/.tfm/.txt, "
                     "or a PLUS device-set .xml)")


def _read_tool_json(path: Path) -> ToolCalibration:
    document = read_json(path, "tool calibration JSON")
    if not isinstance(document, dict) or "TipToProbe" not in document:
        raise EMRegError(f"{path}: not a tool calibration (no TipToProbe key)")
    matrix = check_tip_to_probe(document["TipToProbe"], str(path))
    name = document.get("tool")
    return ToolCalibration(matrix, str(path), str(name) if name else None, str(document.get("method", "file")),
                           rms_mm=_optional_float(document.get("rms_mm")))


def _optional_float(value: Any) -> float | None:
    try:
        return None if value is None else float(value)
    except (TypeError, ValueError):
        return None


def read_tip_to_probe_itk(path: str | os.PathLike[str]) -> np.ndarray:
    """``TipToProbe`` (4x4, mm) from an ITK transform file as 3D Slicer writes a ``TipToProbe`` node
    (``F @ inv(T) @ F`` of the stored ``T``; module docstring)."""
    import SimpleITK as sitk

    try:
        transform = sitk.ReadTransform(str(path))
    except RuntimeError:
        raise EMRegError(f"{path}: not a readable ITK transform file") from None
    stored = _itk_matrix(transform, str(path))
    return check_tip_to_probe(LPS_TO_RAS @ np.linalg.inv(stored) @ LPS_TO_RAS, str(path))


def _itk_matrix(transform: Any, where: str) -> np.ndarray:
    """The 4x4 of a 3D linear ITK transform (a composite holding one linear transform is unwrapped)."""
    import SimpleITK as sitk

    if transform.GetDimension() != 3:
        raise EMRegError(f"{where}: expected a 3D transform")
    try:
        affine = sitk.AffineTransform(transform)
    except (RuntimeError, TypeError):
        try:
            composite = sitk.CompositeTransform(transform)
            if composite.GetNumberOfTransforms() != 1:
                raise EMRegError(f"{where}: holds {composite.GetNumberOfTransforms()} transforms; a tool file holds "
                                 "one linear transform")
            affine = sitk.AffineTransform(composite.GetNthTransform(0))
        except (RuntimeError, TypeError):
            raise EMRegError(f"{where}: not a linear transform (a tool's TipToProbe is rigid)") from None
    matrix = np.eye(4)
    matrix[:3, :3] = np.asarray(affine.GetMatrix()).reshape(3, 3)
    center = np.asarray(affine.GetCenter())
    matrix[:3, 3] = np.asarray(affine.GetTranslation()) + center - matrix[:3, :3] @ center
    return matrix


def write_tip_to_probe_itk(path: str | os.PathLike[str], tip_to_probe: np.ndarray) -> None:
    """Write ``TipToProbe`` as an ITK transform file that 3D Slicer loads as the node ``TipToProbe``
    (``T = F @ ProbeToTip @ F``; module docstring), atomically."""
    import SimpleITK as sitk

    stored = LPS_TO_RAS @ invert_rigid(tip_to_probe) @ LPS_TO_RAS
    transform = sitk.AffineTransform(3)
    transform.SetMatrix(stored[:3, :3].ravel().tolist())
    transform.SetTranslation(stored[:3, 3].tolist())
    with atomic_path(path) as tmp, itk_write_errors():
        sitk.WriteTransform(transform, str(tmp))


def _read_plus_device_set(path: Path, name: str | None) -> ToolCalibration:
    """The ``<Name>Tip`` -> ``<Name>`` transform of a PLUS device set's ``CoordinateDefinitions``."""
    try:
        root = ElementTree.parse(path).getroot()
    except (ElementTree.ParseError, OSError, UnicodeDecodeError) as exc:
        raise EMRegError(f"{path}: not a readable XML file ({exc!s:.80})") from None
    tips = {}
    for element in root.iter("Transform"):
        source, target = element.get("From", ""), element.get("To", "")
        if source.endswith("Tip") and source[:-3] == target and target:
            tips[target] = element
    if name is not None:
        wanted = name[:-len("ToTracker")] if name.endswith("ToTracker") else name
        if wanted not in tips:
            found = ", ".join(f'From="{t}Tip" To="{t}"' for t in tips) or "none"
            raise EMRegError(f'{path}: no tip transform <Transform From="{wanted}Tip" To="{wanted}"> in '
                             f"CoordinateDefinitions (tip transforms found: {found})")
        chosen = wanted
    elif len(tips) == 1:
        chosen = next(iter(tips))
    elif not tips:
        raise EMRegError(f'{path}: no tool tip transform in CoordinateDefinitions (a <Transform From="<Name>Tip" '
                         'To="<Name>" Matrix="..."/>, e.g. From="StylusTip" To="Stylus")')
    else:
        raise EMRegError(f"{path}: several tool tip transforms ({', '.join(tips)}); name the tool with "
                         "[tool] name in case.toml")
    text = tips[chosen].get("Matrix", "")
    try:
        numbers = [float(v) for v in text.split()]
    except ValueError:
        raise EMRegError(f'{path}: the Matrix of From="{chosen}Tip" To="{chosen}" holds a non-number') from None
    if len(numbers) != 16:
        raise EMRegError(f'{path}: the Matrix of From="{chosen}Tip" To="{chosen}" has {len(numbers)} numbers, 16 '
                         "expected (4x4, row-major)")
    matrix = check_tip_to_probe(np.reshape(numbers, (4, 4)), f'{path} (From="{chosen}Tip" To="{chosen}")')
    error = _optional_float(tips[chosen].get("Error"))
    return ToolCalibration(matrix, str(path), chosen, "PLUS device set", rms_mm=error)


def write_tool_calibration(tool: ToolCalibration, out: str | os.PathLike[str]) -> tuple[Path, Path]:
    """Write ``OUT/tool_calibration.json`` and ``OUT/TipToProbe.h5`` (for 3D Slicer), each atomically."""
    out = Path(out)
    json_path, itk_path = out / TOOL_CALIBRATION_JSON, out / TIP_TO_PROBE_ITK
    atomic_write_json(json_path, tool.to_json())
    write_tip_to_probe_itk(itk_path, tool.tip_to_probe)
    return json_path, itk_path


def tip_poses(sensor_to_frame: np.ndarray, tip_to_probe: np.ndarray) -> np.ndarray:
    """``TipToFrame`` (N, 4, 4) of a tool from its sensor's poses ``ProbeToFrame`` (N, 4, 4) in any frame."""
    return np.asarray(sensor_to_frame, dtype=float) @ np.asarray(tip_to_probe, dtype=float)


# --- pivot calibration -------------------------------------------------------------------------


@dataclass
class PivotFit:
    """A pivot fit: ``tip_mm`` (3,) in the probe frame, ``pivot_mm`` (3,) in the samples' frame, the
    ``inliers`` mask (N,), the per-sample ``residual_mm`` (N,) and the RMS of the inliers' residuals."""

    tip_mm: np.ndarray
    pivot_mm: np.ndarray
    inliers: np.ndarray
    residual_mm: np.ndarray
    rms_mm: float


def _solve_pivot(rotation: np.ndarray, position: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Least squares of ``R_i @ tip - pivot = -p_i`` over the samples (a (3N, 6) system)."""
    n = len(rotation)
    system = np.zeros((3 * n, 6))
    system[:, :3] = rotation.reshape(3 * n, 3)
    system[:, 3:] = -np.tile(np.eye(3), (n, 1))
    solution = np.linalg.lstsq(system, -position.reshape(3 * n), rcond=None)[0]
    return solution[:3], solution[3:]


def fit_pivot(probe_to_frame: np.ndarray, max_iterations: int = 10) -> PivotFit:
    """Tip (probe frame) and pivot point (the poses' frame) from sensor poses ``ProbeToFrame`` (N, 4, 4, mm):
    algebraic least squares, then refits without the outliers (module docstring)."""
    poses = np.asarray(probe_to_frame, dtype=float)
    rotation, position = poses[:, :3, :3], poses[:, :3, 3]
    inliers = np.ones(len(poses), dtype=bool)
    for _ in range(max_iterations):
        tip, pivot = _solve_pivot(rotation[inliers], position[inliers])
        residual = np.linalg.norm(np.einsum("nij,j->ni", rotation, tip) + position - pivot, axis=1)
        # robust RMS of a 3D residual: the median of a chi-3 distance is about 1.538 sigma, the RMS sqrt(3) sigma
        robust_rms = float(np.median(residual[inliers])) * np.sqrt(3.0) / 1.5382
        cut = max(OUTLIER_FACTOR * robust_rms, MIN_OUTLIER_CUT_MM)
        new_inliers = residual <= cut
        if np.count_nonzero(new_inliers) < max(MIN_PIVOT_SAMPLES, len(poses) // 2):
            break  # never reject most of the samples: the fit stays with the previous inliers
        if np.array_equal(new_inliers, inliers):
            break
        inliers = new_inliers
    tip, pivot = _solve_pivot(rotation[inliers], position[inliers])
    residual = np.linalg.norm(np.einsum("nij,j->ni", rotation, tip) + position - pivot, axis=1)
    rms = float(np.sqrt(np.mean(residual[inliers] ** 2)))
    return PivotFit(tip, pivot, inliers, residual, rms)


def shaft_swing_deg(rotation: np.ndarray, tip_mm: np.ndarray) -> float:
    """How far the shaft swung (degrees): the 95th percentile of the angle between a sample's shaft direction
    (``R_i @ tip``, the sensor-to-tip line in the poses' frame) and the mean direction, doubled (a cone's full
    angle). Zero when the tip is at the sensor's origin (no shaft)."""
    length = float(np.linalg.norm(tip_mm))
    if length < 1e-6:
        return 0.0
    directions = np.einsum("nij,j->ni", np.asarray(rotation, dtype=float), np.asarray(tip_mm) / length)
    mean = directions.mean(axis=0)
    mean /= max(float(np.linalg.norm(mean)), 1e-12)
    angles = np.degrees(np.arccos(np.clip(directions @ mean, -1.0, 1.0)))
    return float(2.0 * np.percentile(angles, 95))


def tip_frame_rotation(tip_mm: np.ndarray) -> np.ndarray:
    """The tip frame's axes in the probe frame (3x3, columns X, Y, Z), as PLUS orients a pivot-calibrated tip:
    +Z along the shaft (from the sensor's origin towards the tip), +X the sensor's +X made perpendicular to it
    (its +Y when the shaft lies along +X), +Y = Z x X."""
    z_axis = np.asarray(tip_mm, dtype=float)
    length = float(np.linalg.norm(z_axis))
    if length < 1e-9:
        return np.eye(3)
    z_axis = z_axis / length
    seed = np.array([1.0, 0.0, 0.0]) if abs(z_axis[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    x_axis = seed - (seed @ z_axis) * z_axis
    x_axis /= np.linalg.norm(x_axis)
    return np.column_stack([x_axis, np.cross(z_axis, x_axis), z_axis])


def pivot_calibration(probe_to_frame: np.ndarray, source: str = "recording", frame: str = "Reference",
                      name: str | None = None, min_rotation_deg: float = MIN_PIVOT_ROTATION_DEG) -> ToolCalibration:
    """Pivot calibration from sensor poses ``ProbeToFrame`` (N, 4, 4, mm) taken while the tip rests in one divot.

    ``frame``: the poses' frame (``Reference``; ``Tracker`` when the recording has no reference), where the
    pivot point is given. Raises :class:`NoSafeAnswerError` (exit 3) when the shaft swung less than
    ``min_rotation_deg`` (saying how much it swung and how much is needed), the tip did not stay at one point
    (:data:`MAX_PIVOT_RMS_MM`) or there are too few samples."""
    poses = np.asarray(probe_to_frame, dtype=float).reshape(-1, 4, 4)
    finite = np.all(np.isfinite(poses.reshape(len(poses), -1)), axis=1)
    poses = poses[finite]
    if len(poses) < MIN_PIVOT_SAMPLES:
        raise NoSafeAnswerError(f"{source}: {len(poses)} samples with a full pose; a pivot calibration needs at "
                                f"least {MIN_PIVOT_SAMPLES}")
    rotation = poses[:, :3, :3]
    fit = fit_pivot(poses)
    swing = shaft_swing_deg(rotation[fit.inliers], fit.tip_mm)
    if swing < min_rotation_deg:
        raise NoSafeAnswerError(
            f"{source}: the tool swung only {swing:.1f} degrees about its tip; a pivot calibration needs at least "
            f"{min_rotation_deg:g} degrees of swing to pin the tip down (rest the tip in a divot and swing the "
            "shaft in a cone, 20-30 degrees each way)")
    if fit.rms_mm > MAX_PIVOT_RMS_MM:
        raise NoSafeAnswerError(
            f"{source}: the tip did not stay at one point: the pivot fit leaves {fit.rms_mm:.1f} mm RMS (at most "
            f"{MAX_PIVOT_RMS_MM:g} mm); record one divot per pivot recording, the tip resting in it throughout")
    tip_to_probe = np.eye(4)
    tip_to_probe[:3, :3] = tip_frame_rotation(fit.tip_mm)
    tip_to_probe[:3, 3] = fit.tip_mm
    warnings = []
    dropped = len(poses) - int(np.count_nonzero(fit.inliers))
    if dropped:
        warnings.append(f"{source}: {dropped} of {len(poses)} samples left out of the pivot fit as outliers "
                        f"(residual above {OUTLIER_FACTOR:g} x the robust RMS)")
    return ToolCalibration(tip_to_probe, source, name, "pivot: least squares, then refit without outliers "
                           f"(> {OUTLIER_FACTOR:g} x robust RMS residual)", fit.pivot_mm, fit.rms_mm, swing,
                           int(np.count_nonzero(fit.inliers)), len(poses), frame, warnings)
