"""The verification report: ``OUT/report.html``, one self-contained page showing a run's evidence.

:func:`write_report` reads whatever a run left in OUT (spec formats): ``markers.json``,
``frame_calibration.json``, ``registration.json``, ``navigation.csv``, ``evaluation.json``,
``run.json``, and the CT of the case (from ``case_dir`` or ``run.json``'s ``"case"``). It
renders offscreen (pyvista, OpenCV) a 3D view of the frame with every fitted marker model
coloured by its registration residual, the reference sensor and the calibration points
mapped into image space; per-marker CT slices with the fitted outline; plots of the
residual per marker, FRE(l) with the chosen l, TRE per target; and tables (pairs,
calibration points, rejected candidates, TRE, board). A section whose inputs are missing
is left out with a note; warnings (outliers, unpaired points, refused steps) come first.

Images are embedded as base64 PNG (the page opens anywhere) and also written to
``OUT/report_figures/``. Every file is written atomically; the page holds no timestamps, so
the same inputs give the same bytes. :func:`write_reports_batch` renders many runs, in
parallel processes, with a progress bar.

Frames: positions in the tables are image space (CT LPS, mm) unless they say Reference.
"""

from __future__ import annotations

import csv
import html
import os
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from .errors import EMRegError
from .io.atomic import atomic_write_text, read_json
from .marker_model import MarkerModel
from .progress import QUIET, Progress
from .settings import Settings
from .transforms import apply_transform, fit_rigid, fre, make_transform, rotation_from_y_axis

if TYPE_CHECKING:
    import SimpleITK as sitk

REPORT_NAME = "report.html"
FIGURE_DIR = "report_figures"
INPUT_NAMES = ("markers.json", "frame_calibration.json", "registration.json", "navigation.csv", "evaluation.json",
               "run.json")

#: A pair whose residual exceeds this (mm), or 3x the median residual and 1 mm, is flagged as an outlier.
OUTLIER_RESIDUAL_MM = 2.0
#: FRE above this (mm) is flagged (the paper's mean FRE over 30 calibrations was 1.38 mm).
FRE_WARNING_MM = 2.0
#: A calibration dwell whose spread exceeds this (mm) is flagged (probe moved in the pinhole).
CALIBRATION_STD_WARNING_MM = 0.5
#: Samples of the FRE(l) curve over the pinhole range [a, b].
FRE_CURVE_SAMPLES = 151

FIGURE_NAMES = ("scene_oblique", "scene_top", "marker_slices", "residuals", "fre_curve", "tre_targets")


# --- inputs -----------------------------------------------------------------------------------


@dataclass
class ReportInputs:
    """Everything found for one report; None where absent. Positions in image space (LPS mm)."""

    out_dir: Path
    case_dir: Path | None = None
    run: dict | None = None
    markers: dict | None = None
    frame_calibration: dict | None = None
    registration: dict | None = None
    navigation_positions: np.ndarray | None = None
    navigation_labels: list[str] | None = None
    evaluation: dict | None = None
    image: sitk.Image | None = None
    ct_path: Path | None = None
    targets_labels: list[str] | None = None
    targets_positions: np.ndarray | None = None
    settings: Settings = field(default_factory=Settings)
    model: MarkerModel = field(default_factory=MarkerModel)
    notes: list[str] = field(default_factory=list)  # inputs that could not be read


def _read_optional_json(path: Path, what: str, notes: list[str]) -> dict | None:
    if not path.is_file():
        return None
    try:
        document = read_json(path, what)
    except EMRegError as exc:
        notes.append(str(exc))
        return None
    if not isinstance(document, dict):
        notes.append(f"{path}: not a {what} (expected a JSON object)")
        return None
    return document


def _validate_with_stage_reader(path: Path, module: str, reader: str, notes: list[str]) -> bool:
    """Check a stage output with its own module's reader when that module exists in this build."""
    import importlib

    try:
        read = getattr(importlib.import_module(f"EMRegModule.{module}"), reader)
    except (ImportError, AttributeError):
        return True
    try:
        read(path)
    except EMRegError as exc:
        notes.append(str(exc))
        return False
    return True


def read_navigation_csv(path: Path) -> tuple[np.ndarray, list[str]]:
    """Probe positions (N, 3, image LPS mm) and labels of an ``OUT/navigation.csv``."""
    positions: list[list[float]] = []
    labels: list[str] = []
    try:
        with path.open(newline="", encoding="utf-8") as f:
            reader = csv.DictReader(f)
            missing = {"x_mm", "y_mm", "z_mm"} - set(reader.fieldnames or [])
            if missing:
                raise EMRegError(f"{path}: navigation CSV lacks column(s) {', '.join(sorted(missing))}")
            for row in reader:
                positions.append([float(row["x_mm"]), float(row["y_mm"]), float(row["z_mm"])])
                labels.append((row.get("label") or "").strip())
    except (ValueError, TypeError):
        raise EMRegError(f"{path}: navigation CSV holds a non-numeric position") from None
    return np.asarray(positions, dtype=float).reshape(-1, 3), labels


def _resolve_case_dir(out_dir: Path, case_dir: Path | None, run: dict | None, notes: list[str]) -> Path | None:
    if case_dir is not None:
        case_dir = Path(case_dir)
        if not case_dir.is_dir():
            raise EMRegError(f"{case_dir}: case folder not found (give the folder of the CT with --case)")
        return case_dir
    recorded = (run or {}).get("case")
    if not recorded:
        return None
    for candidate in (Path(recorded), out_dir / recorded):
        if candidate.is_dir():
            return candidate
    notes.append(f"{out_dir / 'run.json'}: the recorded case folder {recorded} is not there any more; "
                 "give it with --case to see the CT")
    return None


def load_report_inputs(out_dir: str | os.PathLike[str], case_dir: str | os.PathLike[str] | None = None,
                       read_image: bool = True, image=None) -> ReportInputs:
    """Gather what exists in OUT and the case folder. Unreadable files become notes, not errors.

    ``image`` (a ``SimpleITK.Image``) is the case's CT when the caller already holds it in memory
    (``emreg run``); otherwise the CT is read from the case folder when ``read_image``.

    Raises :class:`EMRegError` when OUT is missing or holds none of the run's outputs, or
    when an explicitly given ``case_dir`` does not exist.
    """
    out = Path(out_dir)
    if not out.is_dir():
        raise EMRegError(f"{out}: output folder not found")
    if not any((out / name).is_file() for name in INPUT_NAMES):
        raise EMRegError(f"{out}: nothing to report (none of {', '.join(INPUT_NAMES)}); run emreg run CASE --out "
                         f"{out} first")
    inputs = ReportInputs(out_dir=out)
    notes = inputs.notes
    inputs.run = _read_optional_json(out / "run.json", "run record", notes)
    for name, attribute, what, module, reader in (
        ("markers.json", "markers", "markers file", "detection", "read_detection"),
        ("frame_calibration.json", "frame_calibration", "frame calibration", "calibration",
         "read_frame_calibration"),
        ("registration.json", "registration", "registration file", "registration", "read_registration"),
        ("evaluation.json", "evaluation", "evaluation file", None, None),
    ):
        document = _read_optional_json(out / name, what, notes)
        if document is not None and module is not None \
                and not _validate_with_stage_reader(out / name, module, reader, notes):
            document = None
        setattr(inputs, attribute, document)
    if (out / "navigation.csv").is_file():
        try:
            inputs.navigation_positions, inputs.navigation_labels = read_navigation_csv(out / "navigation.csv")
        except EMRegError as exc:
            notes.append(str(exc))
    inputs.case_dir = _resolve_case_dir(out, Path(case_dir) if case_dir is not None else None, inputs.run, notes)
    if inputs.case_dir is not None:
        from .io.case import open_case

        try:
            case = open_case(inputs.case_dir)
        except EMRegError as exc:
            notes.append(str(exc))
            case = None
        if case is not None:
            inputs.settings = case.settings
            inputs.ct_path = case.ct
            if case.targets is not None:
                from .io.markups import read_markups

                try:
                    inputs.targets_labels, inputs.targets_positions = read_markups(case.targets)
                except EMRegError as exc:
                    notes.append(str(exc))
    inputs.model = inputs.settings.marker
    if image is not None:
        inputs.image = image
    elif read_image and inputs.ct_path is not None:
        from .io.image import read_ct

        try:
            inputs.image = read_ct(inputs.ct_path)
        except EMRegError as exc:
            notes.append(str(exc))
    return inputs


# --- derived quantities -----------------------------------------------------------------------


@dataclass
class MarkerRow:
    """One detected marker with its pairing (image space, LPS mm)."""

    id: str
    origin: np.ndarray
    axis: np.ndarray
    marker_to_image: np.ndarray
    volume_mm3: float | None
    fit_rms_mm: float | None
    calibration_label: str | None = None
    residual_mm: float | None = None


def marker_rows(markers: dict | None) -> list[MarkerRow]:
    """Detected markers of a ``markers.json`` document with ``MarkerToImage`` from origin and axis."""
    rows: list[MarkerRow] = []
    for entry in (markers or {}).get("markers", []):
        origin = np.asarray(entry["origin"], dtype=float)
        axis = np.asarray(entry["axis"], dtype=float)
        axis = axis / np.linalg.norm(axis)
        rows.append(MarkerRow(
            id=str(entry.get("id", f"I{len(rows) + 1:02d}")), origin=origin, axis=axis,
            marker_to_image=make_transform(rotation_from_y_axis(axis), origin),
            volume_mm3=_maybe_float(entry.get("volume_mm3")), fit_rms_mm=_maybe_float(entry.get("fit_rms_mm")),
        ))
    return rows


def _maybe_float(value: Any) -> float | None:
    try:
        number = float(value)
    except (TypeError, ValueError):
        return None
    return number if np.isfinite(number) else None


def calibration_points(frame_calibration: dict | None) -> dict[str, dict]:
    """Calibration points by label: position (Reference, mm) and the dwell figures."""
    points = {}
    for entry in (frame_calibration or {}).get("points", []):
        points[str(entry["label"])] = {
            "position": np.asarray(entry["position"], dtype=float),
            "direction": np.asarray(entry["direction"], dtype=float) if entry.get("direction") is not None
            else None,
            "samples": entry.get("samples"), "std_mm": _maybe_float(entry.get("std_mm")),
        }
    return points


def fre_curve(rows: Sequence[MarkerRow], points: dict[str, dict], l_range: tuple[float, float],
              samples: int = FRE_CURVE_SAMPLES) -> tuple[np.ndarray, np.ndarray] | None:
    """FRE(l) (paper Eq. 10) over the pinhole range for the paired markers; None with fewer than 3 pairs.

    For each l the sensor points ``origin + l * axis`` (image) are fitted rigidly to the paired
    calibration points (Reference) and the RMS residual is taken.
    """
    paired = [r for r in rows if r.calibration_label in points]
    if len(paired) < 3:
        return None
    reference_points = np.stack([points[r.calibration_label]["position"] for r in paired])
    origins = np.stack([r.origin for r in paired])
    axes = np.stack([r.axis for r in paired])
    l_values = np.linspace(l_range[0], l_range[1], samples)
    values = np.empty_like(l_values)
    for i, l_mm in enumerate(l_values):
        image_points = origins + l_mm * axes
        try:
            reference_to_image = fit_rigid(reference_points, image_points)
        except ValueError:
            return None
        values[i] = fre(reference_to_image, reference_points, image_points)
    return l_values, values


def registration_fre_curve(registration: dict) -> tuple[np.ndarray, np.ndarray] | None:
    """The FRE(l) curve the registration stored (``fre_curve``: ``l_mm``, ``fre_mm``), if any."""
    curve = registration.get("fre_curve") or {}
    try:
        l_values = np.asarray(curve.get("l_mm", []), dtype=float)
        values = np.asarray(curve.get("fre_mm", []), dtype=float)
    except (TypeError, ValueError, AttributeError):
        return None
    if l_values.ndim != 1 or l_values.shape != values.shape or len(l_values) < 2 or np.ptp(l_values) <= 0:
        return None
    return l_values, values


def predicted_tre_by_target(inputs: ReportInputs) -> dict[str, float]:
    """Fitzpatrick's predicted TRE (mm) per target label, from ``registration.json`` when it has one.

    The registration stores ``targets_image`` with ``predicted_tre_mm``; labels come from the
    case's ``targets.mrk.json`` (matched by position) or, without it, T1, T2, ... in order.
    """
    registration = inputs.registration or {}
    predicted, targets = registration.get("predicted_tre_mm"), registration.get("targets_image")
    if predicted is None or targets is None:
        return {}
    try:
        predicted = np.asarray(predicted, dtype=float).reshape(-1)
        targets = np.asarray(targets, dtype=float).reshape(-1, 3)
    except (TypeError, ValueError):
        return {}
    if len(predicted) != len(targets):
        return {}
    result = {}
    for i, (target, value) in enumerate(zip(targets, predicted, strict=True)):
        label = f"T{i + 1}"
        if inputs.targets_positions is not None and len(inputs.targets_positions):
            distance = np.linalg.norm(inputs.targets_positions - target, axis=1)
            k = int(np.argmin(distance))
            if distance[k] > 0.01:
                continue
            label = inputs.targets_labels[k]
        result[label] = float(value)
    return result


@dataclass
class ReportWarning:
    """One warning of the report: ``kind`` is "refused", "warning" or "note"."""

    kind: str
    text: str


def collect_warnings(inputs: ReportInputs, rows: list[MarkerRow], points: dict[str, dict],
                     curve: tuple[np.ndarray, np.ndarray] | None) -> list[ReportWarning]:
    """Refused steps, outliers, unpaired points and other things a reviewer must see first."""
    found: list[ReportWarning] = []
    summary = [str(line) for line in (inputs.run or {}).get("summary", [])]
    refused = [line for line in summary if ": refused:" in line]
    found.extend(ReportWarning("refused", line) for line in refused)
    found.extend(ReportWarning("warning", f"could not read: {note}") for note in inputs.notes)
    registration = inputs.registration
    if registration is None and inputs.markers is not None and inputs.frame_calibration is not None and not refused:
        found.append(ReportWarning("warning", "no registration.json although markers and a frame calibration exist: "
                                         "the registration step refused or was not run"))
    for document in (inputs.markers, inputs.frame_calibration, registration, inputs.evaluation):
        for text in (document or {}).get("warnings", []) or []:
            found.append(ReportWarning("warning", str(text)))
    if registration is not None:
        # A registration written by EMReg lists its own outliers and l warnings; check a bare spec file here.
        own_checks = "warnings" not in registration
        residuals = np.array([r.residual_mm for r in rows if r.residual_mm is not None], dtype=float)
        median = float(np.median(residuals)) if residuals.size else 0.0
        for r in rows if own_checks else []:
            if r.residual_mm is None:
                continue
            if r.residual_mm > OUTLIER_RESIDUAL_MM or (r.residual_mm > 1.0 and r.residual_mm > 3.0 * median):
                found.append(ReportWarning(
                    "warning", f"outlier: marker {r.id} (calibration point {r.calibration_label}) has a residual "
                               f"of {r.residual_mm:.2f} mm (median {median:.2f} mm)"))
        fre_mm = _maybe_float(registration.get("fre_mm"))
        if fre_mm is not None and fre_mm > FRE_WARNING_MM:
            found.append(ReportWarning("warning", f"FRE {fre_mm:.2f} mm is above {FRE_WARNING_MM:.1f} mm"))
        unpaired_image = registration.get("unpaired_image_markers") or []
        unpaired_calibration = registration.get("unpaired_calibration_points") or []
        if unpaired_image:
            found.append(ReportWarning("warning", f"{len(unpaired_image)} detected marker(s) not paired: "
                                                  + ", ".join(map(str, unpaired_image))))
        if unpaired_calibration:
            found.append(ReportWarning("warning", f"{len(unpaired_calibration)} calibration point(s) not paired: "
                                                  + ", ".join(map(str, unpaired_calibration))))
        l_mm = _maybe_float(registration.get("sensor_offset_l_mm"))
        a, b = inputs.model.pinhole_bottom_mm, inputs.model.pinhole_top_mm
        fixed = bool(registration.get("sensor_offset_fixed", False))
        if own_checks and not fixed and l_mm is not None and (l_mm <= a + 0.05 or l_mm >= b - 0.05):
            found.append(ReportWarning(
                "warning", f"the sensor offset l = {l_mm:.2f} mm sits at an end of the pinhole range "
                           f"[{a:.1f}, {b:.1f}] mm: check the marker model and that the probe reached the "
                           "pinhole's floor"))
        if curve is not None and l_mm is not None:
            l_values, values = curve
            l_best = float(l_values[int(np.argmin(values))])
            step = float(l_values[1] - l_values[0])
            if abs(l_best - l_mm) > 2 * step + 0.05:
                found.append(ReportWarning("warning", f"the FRE(l) curve of the reported pairs is lowest at l = "
                                                 f"{l_best:.2f} mm, not at the reported {l_mm:.2f} mm"))
    for label, point in points.items():
        if point["std_mm"] is not None and point["std_mm"] > CALIBRATION_STD_WARNING_MM:
            found.append(ReportWarning("warning", f"calibration point {label}: the probe moved during the dwell "
                                             f"(spread {point['std_mm']:.2f} mm)"))
    if inputs.image is not None and inputs.markers is not None and "image" in inputs.markers:
        from .io.image import image_geometry

        recorded = inputs.markers["image"]
        actual = image_geometry(inputs.image)
        if list(recorded.get("size", [])) != list(actual["size"]) or not np.allclose(
                recorded.get("spacing", actual["spacing"]), actual["spacing"], atol=1e-4):
            found.append(ReportWarning("warning", "the CT found for this report does not have the geometry recorded in "
                                             "markers.json: the slices may show another image"))
    if inputs.markers is not None and inputs.image is None:
        found.append(ReportWarning("note", "no CT available (give the case with --case): the CT slices and the CT "
                                      "surface are left out"))
    return found


# --- figures ----------------------------------------------------------------------------------


@dataclass
class Figure:
    """A rendered figure: file name stem, title, caption and PNG bytes."""

    name: str
    title: str
    caption: str
    png: bytes


def _scene_for(inputs: ReportInputs, rows: list[MarkerRow], points: dict[str, dict], context_surface):
    from .rendering.scene3d import FrameScene, SceneMarker

    registration = inputs.registration or {}
    reference_to_image = np.asarray(registration["ReferenceToImage"], dtype=float) \
        if "ReferenceToImage" in registration else None
    l_mm = _maybe_float(registration.get("sensor_offset_l_mm"))
    calibration_image = None
    if reference_to_image is not None and points:
        calibration_image = apply_transform(reference_to_image, np.stack([p["position"] for p in points.values()]))
    sensor_points = None
    if l_mm is not None:
        paired = [r for r in rows if r.residual_mm is not None]
        if paired:
            sensor_points = np.stack([r.origin + l_mm * r.axis for r in paired])
    navigation = inputs.navigation_positions
    if navigation is not None and len(navigation) > 2000:
        navigation = navigation[:: int(np.ceil(len(navigation) / 2000))]
    return FrameScene(
        model=inputs.model,
        markers=[SceneMarker(r.id, r.marker_to_image, r.residual_mm) for r in rows],
        context_surface=context_surface,
        reference_to_image=reference_to_image,
        calibration_points=calibration_image,
        sensor_points=sensor_points,
        targets=inputs.targets_positions,
        target_labels=inputs.targets_labels,
        navigation_path=navigation,
    )


def render_figures(inputs: ReportInputs, rows: list[MarkerRow], points: dict[str, dict],
                   curve: tuple[np.ndarray, np.ndarray] | None, progress: Progress = QUIET) -> list[Figure]:
    """Render every figure whose inputs exist, in report order."""
    from .rendering.colors import GREY, colorize, residual_range
    from .rendering.images import encode_png
    from .rendering.plots import bar_chart, line_chart

    registration = inputs.registration or {}
    evaluation = inputs.evaluation or {}
    tre = evaluation.get("tre") or {}
    planned = []
    if rows or (points and "ReferenceToImage" in registration):  # calibration points alone have no image place
        planned += ["scene_oblique", "scene_top"]
    if rows and inputs.image is not None:
        planned.append("marker_slices")
    if registration.get("pairs"):
        planned.append("residuals")
    if curve is not None:
        planned.append("fre_curve")
    if tre.get("targets"):
        planned.append("tre_targets")
    figures: list[Figure] = []
    with progress.step("rendering report", total=len(planned)) as step:
        if "scene_oblique" in planned:
            from .rendering.scene3d import ct_context_surface, render_frame_scene

            surface = None
            if inputs.image is not None:
                surface, _ = ct_context_surface(inputs.image, inputs.settings.report.iso_value)
            scene = _scene_for(inputs, rows, points, surface)
            caption = ("Fitted marker models coloured by registration residual (grey: unpaired), the reference "
                       "sensor with its axes (red X, green Y, blue Z), calibration points mapped into the CT "
                       "(magenta), sensor points at the solved l (yellow), targets (red) and the navigated probe "
                       "path (cyan)" + (", inside the CT surface." if surface is not None else "."))
            for view, title in (("oblique", "3D view of the frame"), ("top", "3D view from above")):
                image = render_frame_scene(scene, (960, 720), view=view)
                figures.append(Figure(f"scene_{view}", title, caption, encode_png(image)))
                step.advance()
        if "marker_slices" in planned:
            from .rendering.slices import SliceMarker, marker_slices_mosaic

            reference_to_image = np.asarray(registration["ReferenceToImage"], dtype=float) \
                if "ReferenceToImage" in registration else None
            l_mm = _maybe_float(registration.get("sensor_offset_l_mm"))
            slice_markers = []
            for r in rows:
                caption = r.id
                calibration_point = None
                if r.calibration_label is not None:
                    caption += f" -> {r.calibration_label}"
                    if r.residual_mm is not None:
                        caption += f"  {r.residual_mm:.2f} mm"
                    if reference_to_image is not None and r.calibration_label in points:
                        calibration_point = apply_transform(reference_to_image,
                                                            points[r.calibration_label]["position"])
                elif registration:
                    caption += "  (unpaired)"
                slice_markers.append(SliceMarker(
                    r.id, r.marker_to_image, caption, paired=r.calibration_label is not None or not registration,
                    sensor_point=(r.origin + l_mm * r.axis) if l_mm is not None else None,
                    calibration_point=calibration_point,
                ))
            mosaic = marker_slices_mosaic(inputs.image, slice_markers, inputs.model)
            figures.append(Figure(
                "marker_slices", "CT slices through each marker",
                "Per marker: two planes through the marker axis (XY, ZY) and a cross-section of its base (XZ), "
                "with the fitted model outline (green: paired, orange: unpaired), the sensor point at the solved "
                "l (yellow dot) and the calibration point mapped by ReferenceToImage (magenta cross). "
                "0.2 mm per pixel.", encode_png(mosaic)))
            step.advance()
        if "residuals" in planned:
            paired = [r for r in rows if r.residual_mm is not None]
            if not paired:  # pairs name markers this report does not know: plot from the pairs alone
                labels = [f"{p['image_marker']}" for p in registration["pairs"]]
                values = [float(p["residual_mm"]) for p in registration["pairs"]]
            else:
                labels = [r.id for r in paired]
                values = [float(r.residual_mm) for r in paired]
            low, high = residual_range(np.asarray(values))
            colors = [tuple(int(c) for c in colorize([v], low, high)[0]) for v in values]
            fre_mm = _maybe_float(registration.get("fre_mm"))
            lines = [(fre_mm, f"FRE {fre_mm:.2f} mm")] if fre_mm is not None else []
            chart = bar_chart(labels, values, title="Registration residual per marker", y_label="residual (mm)",
                              colors=colors or [GREY], reference_lines=lines)
            figures.append(Figure("residuals", "Residual per marker",
                                  "Distance between each calibration point mapped into the CT and its marker's "
                                  "sensor point at the solved l; the dashed line is the FRE (RMS).",
                                  encode_png(chart)))
            step.advance()
        if "fre_curve" in planned:
            l_values, values = curve
            l_mm = _maybe_float(registration.get("sensor_offset_l_mm"))
            label = ""
            if l_mm is not None:
                label = f"chosen l = {l_mm:.2f} mm, FRE {float(np.interp(l_mm, l_values, values)):.2f} mm"
            chart = line_chart(l_values, values, "FRE(l) over the pinhole range", "sensor offset l (mm)", "FRE (mm)",
                               marker_x=l_mm, marker_label=label)
            source = "as the registration computed it" if registration_fre_curve(registration) is not None \
                else "recomputed here from the reported pairs"
            figures.append(Figure("fre_curve", "FRE as a function of the sensor offset l",
                                  f"Paper Eq. 10, {source}: for each l in the pinhole range the rigid fit of the "
                                  "calibration points to the sensor points at l; the dot marks the l the "
                                  "registration chose.", encode_png(chart)))
            step.advance()
        if "tre_targets" in planned:
            targets = tre["targets"]
            labels = list(targets)
            means = [float(targets[t].get("mean_mm", np.nan)) for t in labels]
            stds = [float(targets[t].get("std_mm") or 0.0) for t in labels]
            lines = []
            if _maybe_float(tre.get("mean_mm")) is not None:
                lines.append((float(tre["mean_mm"]), f"mean {float(tre['mean_mm']):.2f} mm"))
            predicted = predicted_tre_by_target(inputs)
            overlay = [predicted.get(t, np.nan) for t in labels] if predicted else None
            chart = bar_chart(labels, means, errors=stds, title="Target registration error", y_label="TRE (mm)",
                              reference_lines=lines, overlay=overlay,
                              overlay_label="predicted from FLE (Fitzpatrick)" if overlay else "")
            figures.append(Figure("tre_targets", "TRE per target",
                                  "Mean and standard deviation over the dwells at each target"
                                  + (", with the RMS TRE predicted from the fiducial configuration and FLE (red)"
                                     if overlay else "")
                                  + " (paper: 1.38 +/- 0.32 mm over 6 targets x 15 placements).", encode_png(chart)))
            step.advance()
    return figures


# --- HTML -------------------------------------------------------------------------------------

_CSS = """
body{font-family:system-ui,-apple-system,'Segoe UI',Roboto,sans-serif;margin:0;background:#f4f5f7;color:#222}
main{max-width:1100px;margin:0 auto;padding:24px}
h1{font-size:24px;margin:0 0 4px} h2{font-size:19px;margin:28px 0 10px;border-bottom:1px solid #ccc;padding-bottom:4px}
h3{font-size:16px;margin:18px 0 6px}
table{border-collapse:collapse;margin:8px 0 12px;background:#fff;font-size:13px}
th,td{border:1px solid #d6d6d6;padding:4px 8px;text-align:right} th{background:#eceef2}
td.l,th.l{text-align:left}
figure{margin:10px 0 18px;background:#fff;padding:8px;border:1px solid #ddd}
figure img{max-width:100%;height:auto;display:block}
figcaption{font-size:13px;color:#444;margin-top:6px}
.warn{background:#fff5db;border-left:4px solid #e0a800;padding:6px 10px;margin:4px 0}
.refused{background:#fde2e1;border-left:4px solid #c62828;padding:6px 10px;margin:4px 0}
.note{background:#e8f1fb;border-left:4px solid #5b8def;padding:6px 10px;margin:4px 0}
.ok{background:#e5f5e8;border-left:4px solid #2e7d32;padding:6px 10px;margin:4px 0}
.muted{color:#666;font-size:13px}
"""


def _e(value: Any) -> str:
    return html.escape(str(value), quote=True)


def _num(value: Any, digits: int = 2) -> str:
    number = _maybe_float(value)
    return "&ndash;" if number is None else f"{number:.{digits}f}"


def _table(header: Sequence[str], rows: Sequence[Sequence[str]], left_columns: int | Sequence[int] = 1) -> str:
    """An HTML table; cells are already-escaped HTML; ``left_columns`` (count or indices) are left-aligned."""
    left = set(range(left_columns)) if isinstance(left_columns, int) else set(left_columns)
    head = "".join(f"<th class=\"l\">{_e(h)}</th>" if i in left else f"<th>{_e(h)}</th>"
                   for i, h in enumerate(header))
    body = "".join("<tr>" + "".join(f"<td class=\"l\">{c}</td>" if i in left else f"<td>{c}</td>"
                                    for i, c in enumerate(row)) + "</tr>" for row in rows)
    return f"<table><thead><tr>{head}</tr></thead><tbody>{body}</tbody></table>"


def _figure_html(figure: Figure) -> str:
    from .rendering.images import png_data_uri

    return (f"<figure id=\"fig-{_e(figure.name)}\"><img src=\"{png_data_uri(figure.png)}\" alt=\"{_e(figure.title)}\">"
            f"<figcaption><b>{_e(figure.title)}.</b> {_e(figure.caption)}</figcaption></figure>")


def _vec(v: np.ndarray, digits: int = 2) -> str:
    return ", ".join(f"{x:.{digits}f}" for x in np.asarray(v, dtype=float))


def build_html(inputs: ReportInputs, rows: list[MarkerRow], points: dict[str, dict], figures: list[Figure],
               warnings: list[ReportWarning]) -> str:
    """The report page (one string, deterministic for the same inputs)."""
    figure = {f.name: f for f in figures}
    registration = inputs.registration or {}
    evaluation = inputs.evaluation or {}
    case_name = inputs.case_dir.name if inputs.case_dir is not None else inputs.out_dir.name
    parts = [f"<!DOCTYPE html><html lang=\"en\"><head><meta charset=\"utf-8\">"
             f"<meta name=\"viewport\" content=\"width=device-width, initial-scale=1\">"
             f"<title>EMReg report: {_e(case_name)}</title><style>{_CSS}</style></head><body><main>",
             f"<h1>EMReg verification report: {_e(case_name)}</h1>",
             "<p class=\"muted\">Image space is the CT's LPS physical space (mm). ReferenceToImage maps points of the "
             "reference sensor (Model 800) frame into it.</p>"]

    # Summary
    summary_rows = []
    if inputs.case_dir is not None:
        summary_rows.append(("case folder", _e(inputs.case_dir)))
    summary_rows.append(("output folder", _e(inputs.out_dir)))
    if inputs.run and inputs.run.get("emreg_version"):
        summary_rows.append(("EMReg version", _e(inputs.run["emreg_version"])))
    if inputs.run and "reference_sensor" in inputs.run:
        summary_rows.append(("sensor ports", f"reference {_e(inputs.run['reference_sensor'])}, probe "
                                             f"{_e(inputs.run.get('probe_sensor'))}"))
    image_info = (inputs.markers or {}).get("image")
    if inputs.image is not None:
        from .io.image import image_geometry

        image_info = image_geometry(inputs.image)
    if image_info:
        summary_rows.append(("CT", f"{' x '.join(str(s) for s in image_info['size'])} voxels of "
                                   f"{' x '.join(f'{s:.3g}' for s in image_info['spacing'])} mm"
                                   + (f" ({_e(inputs.ct_path.name)})" if inputs.ct_path is not None else "")))
    if inputs.markers is not None:
        summary_rows.append(("markers detected", f"{len(rows)} ({len(inputs.markers.get('rejected', []))} "
                                                 "candidates rejected)"))
    if inputs.frame_calibration is not None:
        summary_rows.append(("pinholes calibrated", str(len(points))))
    if registration:
        summary_rows.append(("pairs", str(len(registration.get("pairs", [])))))
        summary_rows.append(("FRE", f"{_num(registration.get('fre_mm'))} mm"))
        summary_rows.append(("sensor offset l", f"{_num(registration.get('sensor_offset_l_mm'))} mm "
                                                f"(pinhole range {inputs.model.pinhole_bottom_mm:.1f} to "
                                                f"{inputs.model.pinhole_top_mm:.1f} mm)"))
    if inputs.navigation_positions is not None:
        summary_rows.append(("navigated probe samples", str(len(inputs.navigation_positions))))
    tre = evaluation.get("tre")
    if tre:
        summary_rows.append(("TRE", f"{_num(tre.get('mean_mm'))} &plusmn; {_num(tre.get('std_mm'))} mm"))
    parts.append("<h2>Summary</h2>" + _table(("item", "value"), summary_rows, left_columns=2))

    # Warnings
    parts.append("<h2>Warnings</h2>")
    if not any(w.kind in ("warning", "refused") for w in warnings):
        parts.append("<div class=\"ok\">No warnings.</div>")
    for w in warnings:
        css = {"refused": "refused", "warning": "warn"}.get(w.kind, "note")
        prefix = {"refused": "Refused: ", "warning": ""}.get(w.kind, "")
        parts.append(f"<div class=\"{css}\">{_e(prefix + w.text)}</div>")

    # 3D
    parts.append("<h2>Frame in 3D</h2>")
    if "scene_oblique" in figure:
        parts.append(_figure_html(figure["scene_oblique"]) + _figure_html(figure["scene_top"]))
    else:
        parts.append("<div class=\"note\">Not shown: no markers.json (nor a registration placing the calibration "
                     "points) in the output folder.</div>")

    # Registration
    parts.append("<h2>Registration</h2>")
    if registration:
        if "residuals" in figure:
            parts.append(_figure_html(figure["residuals"]))
        if "fre_curve" in figure:
            parts.append(_figure_html(figure["fre_curve"]))
        matrix = np.asarray(registration.get("ReferenceToImage", np.eye(4)), dtype=float)
        parts.append("<h3>ReferenceToImage</h3>" + _table(
            ("", "x", "y", "z", "t"), [(f"row {i + 1}", *(f"{v:.4f}" for v in matrix[i])) for i in range(4)]))
        by_id = {r.id: r for r in rows}
        pair_rows = []
        for pair in registration.get("pairs", []):
            marker = by_id.get(str(pair.get("image_marker")))
            point = points.get(str(pair.get("calibration_point")), {})
            pair_rows.append((_e(pair.get("image_marker")), _e(pair.get("calibration_point")),
                              _num(pair.get("residual_mm")), "<b>yes</b>" if pair.get("outlier") else "",
                              _num(marker.volume_mm3 if marker else None, 0),
                              _num(marker.fit_rms_mm if marker else None, 3),
                              _num(point.get("std_mm"), 3), _e(point.get("samples", "")) or "&ndash;"))
        parts.append("<h3>Pairs</h3>" + _table(
            ("image marker", "calibration point", "residual (mm)", "outlier", "marker volume (mm³)", "fit RMS (mm)",
             "dwell spread (mm)", "samples"), pair_rows, left_columns=2))
        unpaired = [("detected markers", ", ".join(map(str, registration.get("unpaired_image_markers") or []))),
                    ("calibration points", ", ".join(map(str, registration.get("unpaired_calibration_points") or [])))]
        parts.append("<h3>Unpaired</h3>" + _table(("kind", "labels"),
                                                  [(k, _e(v) or "none") for k, v in unpaired], left_columns=2))
        extra = {k: v for k, v in registration.items()
                 if k not in ("ReferenceToImage", "sensor_offset_l_mm", "fre_mm", "pairs", "unpaired_image_markers",
                              "unpaired_calibration_points", "warnings")
                 and not isinstance(v, bool) and _maybe_float(v) is not None}
        if extra:
            parts.append("<h3>Other figures</h3>" + _table(("name", "value"),
                                                            [(_e(k), _num(v, 3)) for k, v in extra.items()]))
    else:
        parts.append("<div class=\"note\">Not shown: no registration.json in the output folder.</div>")

    # Markers in the CT
    parts.append("<h2>Markers in the CT</h2>")
    if inputs.markers is not None:
        if "marker_slices" in figure:
            parts.append(_figure_html(figure["marker_slices"]))
        else:
            parts.append("<div class=\"note\">CT slices not shown: the CT was not found (give the case folder with "
                         "--case).</div>")
        parts.append("<h3>Detected markers</h3>" + _table(
            ("id", "origin (LPS mm)", "axis", "volume (mm³)", "fit RMS (mm)", "paired with", "residual (mm)"),
            [(_e(r.id), _vec(r.origin), _vec(r.axis, 3), _num(r.volume_mm3, 0), _num(r.fit_rms_mm, 3),
              _e(r.calibration_label) if r.calibration_label else "&ndash;", _num(r.residual_mm))
             for r in rows]))
        rejected = inputs.markers.get("rejected", [])
        if rejected:
            parts.append("<h3>Rejected candidates</h3>" + _table(
                ("centroid (LPS mm)", "volume (mm³)", "reason"),
                [(_vec(entry.get("centroid", [np.nan] * 3)), _num(entry.get("volume_mm3"), 0),
                  _e(entry.get("reason", ""))) for entry in rejected], left_columns=(2,)))
    else:
        parts.append("<div class=\"note\">Not shown: no markers.json in the output folder.</div>")

    # Frame calibration
    parts.append("<h2>Frame calibration</h2>")
    if points:
        parts.append(_table(("label", "position (Reference mm)", "direction", "samples", "spread (mm)"),
                            [(_e(label), _vec(p["position"]),
                              _vec(p["direction"], 3) if p["direction"] is not None else "&ndash;",
                              _e(p["samples"]) if p["samples"] is not None else "&ndash;", _num(p["std_mm"], 3))
                             for label, p in points.items()]))
    else:
        parts.append("<div class=\"note\">Not shown: no frame_calibration.json in the output folder.</div>")

    # Evaluation
    parts.append("<h2>Target registration error</h2>")
    if tre:
        if "tre_targets" in figure:
            parts.append(_figure_html(figure["tre_targets"]))
        predicted = predicted_tre_by_target(inputs)
        target_rows = [(_e(name), _num(t.get("mean_mm")), _num(t.get("std_mm")), _e(t.get("n", "")),
                        _num(predicted.get(name)))
                       for name, t in (tre.get("targets") or {}).items()]
        target_rows.append(("<b>all</b>", _num(tre.get("mean_mm")), _num(tre.get("std_mm")),
                            _e(tre.get("n", "")) if tre.get("n") is not None else "",
                            _num(np.sqrt(np.mean(np.square(list(predicted.values()))))) if predicted else
                            "&ndash;"))
        parts.append(_table(("target", "mean (mm)", "std (mm)", "n", "predicted RMS (mm)"), target_rows))
    else:
        parts.append("<div class=\"note\">Not shown: no TRE in evaluation.json (needs navigation.csv and "
                     "targets.mrk.json in the case).</div>")

    parts.append("<h2>Board phantom</h2>")
    board = evaluation.get("board")
    if board and board.get("edges"):
        nominal = list(inputs.settings.board.edges_mm or [])
        board_rows = []
        for i, (name, edge) in enumerate(board["edges"].items()):
            reference = _maybe_float(edge.get("nominal_mm", edge.get("reference_mm")))
            if reference is None and i < len(nominal):
                reference = _maybe_float(nominal[i])
            mean = _maybe_float(edge.get("mean_mm"))
            error = f"{mean - reference:+.2f}" if reference is not None and mean is not None else "&ndash;"
            if "abs_error_mean_mm" in edge:
                absolute = f"{_num(edge.get('abs_error_mean_mm'))} &plusmn; {_num(edge.get('abs_error_std_mm'))}"
                relative = (f"{_num(edge.get('rel_error_mean_percent'))}% &plusmn; "
                            f"{_num(edge.get('rel_error_std_percent'))}%")
            else:
                absolute = "&ndash;"
                relative = f"{100 * (mean - reference) / reference:+.2f}%" \
                    if reference is not None and mean is not None and reference else "&ndash;"
            holes = "&ndash;".join(_e(h) for h in edge.get("holes", []))
            board_rows.append((_e(name), holes, _num(mean), _num(edge.get("std_mm")), _e(edge.get("n", "")),
                               _num(reference), error, absolute, relative))
        parts.append(_table(("edge", "holes", "mean length (mm)", "std (mm)", "n", "nominal (mm)",
                             "mean - nominal (mm)", "absolute error (mm)", "relative error"), board_rows,
                            left_columns=2))
        parts.append("<p class=\"muted\">Paper Table 1: absolute errors 0.16 to 0.21 mm against a Vernier caliper, "
                     "all below 1 mm.</p>")
    else:
        parts.append("<div class=\"note\">Not shown: no board table in evaluation.json (needs board.csv in the "
                     "case).</div>")

    if inputs.run and inputs.run.get("summary"):
        parts.append("<h2>Run log</h2><pre>" + _e("\n".join(map(str, inputs.run["summary"]))) + "</pre>")
    parts.append("</main></body></html>\n")
    return "\n".join(parts)


# --- entry points -----------------------------------------------------------------------------


def _pair_rows(inputs: ReportInputs) -> list[MarkerRow]:
    rows = marker_rows(inputs.markers)
    by_id = {r.id: r for r in rows}
    for pair in (inputs.registration or {}).get("pairs", []):
        row = by_id.get(str(pair.get("image_marker")))
        if row is not None:
            row.calibration_label = str(pair.get("calibration_point"))
            row.residual_mm = _maybe_float(pair.get("residual_mm"))
    return rows


def write_report(out_dir: str | os.PathLike[str], case_dir: str | os.PathLike[str] | None = None,
                 progress: Progress | None = None, image=None) -> Path:
    """Render ``OUT/report.html`` (and ``OUT/report_figures/*.png``) from what the run left in OUT.

    ``case_dir`` is the case folder (for the CT and targets); by default the one recorded in
    ``OUT/run.json``. ``image``: the case's CT already in memory (``SimpleITK.Image``), which spares
    reading it again. Returns the path of the page. Raises :class:`EMRegError` when OUT holds
    nothing to report.
    """
    progress = progress or QUIET
    inputs = load_report_inputs(out_dir, case_dir, image=image)
    try:
        rows = _pair_rows(inputs)
        points = calibration_points(inputs.frame_calibration)
    except (KeyError, TypeError, ValueError, ZeroDivisionError) as exc:
        raise EMRegError(f"{inputs.out_dir}: an output file does not follow the spec ({exc!s:.120})") from None
    curve = None
    if inputs.registration is not None:
        curve = registration_fre_curve(inputs.registration) or \
            fre_curve(rows, points, (inputs.model.pinhole_bottom_mm, inputs.model.pinhole_top_mm))
    warnings = collect_warnings(inputs, rows, points, curve)
    figures = render_figures(inputs, rows, points, curve, progress)
    from .io.atomic import atomic_write_bytes

    figure_dir = inputs.out_dir / FIGURE_DIR
    for figure in figures:
        atomic_write_bytes(figure_dir / f"{figure.name}.png", figure.png)
    produced = {f.name for f in figures}
    for name in FIGURE_NAMES:  # figures of an earlier run that this one did not produce are stale
        if name not in produced:
            (figure_dir / f"{name}.png").unlink(missing_ok=True)
    path = inputs.out_dir / REPORT_NAME
    atomic_write_text(path, build_html(inputs, rows, points, figures, warnings))
    return path


def has_report_inputs(folder: str | os.PathLike[str]) -> bool:
    """True when a folder holds at least one output of a run (something to report)."""
    folder = Path(folder)
    return folder.is_dir() and any((folder / name).is_file() for name in INPUT_NAMES)


def _batch_worker(folder: str) -> tuple[str, str | None, str | None]:
    try:
        return folder, str(write_report(Path(folder))), None
    except EMRegError as exc:
        return folder, None, str(exc)
    except Exception as exc:  # noqa: BLE001 - one broken folder must not stop the batch; reported below
        return folder, None, f"{type(exc).__name__}: {exc}"


def write_reports_batch(folders: Sequence[str | os.PathLike[str]], jobs: int = 1,
                        progress: Progress | None = None) -> list[Path]:
    """Render a report in every output folder, ``jobs`` processes at a time, with a progress bar.

    Folders without any run output are skipped (with a message). Each report finds its CT
    through its ``run.json``. Returns the written pages in the order of ``folders``; when a
    folder fails the others are still rendered, then :class:`EMRegError` lists the failures.
    """
    progress = progress or QUIET
    if jobs < 1:
        raise EMRegError(f"report --jobs must be at least 1, got {jobs}")
    selected = []
    for folder in folders:
        if has_report_inputs(folder):
            selected.append(str(folder))
        else:
            progress.message(f"[emreg] report: skipping {folder} (no run outputs in it)")
    results: dict[str, tuple[str | None, str | None]] = {}
    with progress.step("reports", total=len(selected)) as step:
        if jobs == 1 or len(selected) <= 1:
            for folder in selected:
                _, path, error = _batch_worker(folder)
                results[folder] = (path, error)
                step.advance()
        else:
            import multiprocessing
            from concurrent.futures import ProcessPoolExecutor, as_completed

            context = multiprocessing.get_context("spawn")  # VTK/EGL state must not be forked
            with ProcessPoolExecutor(max_workers=min(jobs, len(selected)), mp_context=context) as pool:
                futures = [pool.submit(_batch_worker, folder) for folder in selected]
                for future in as_completed(futures):
                    folder, path, error = future.result()
                    results[folder] = (path, error)
                    step.advance()
    failures = [f"{folder}: {error}" for folder in selected for path, error in [results[folder]] if error]
    if failures:
        raise EMRegError(f"{len(failures)} of {len(selected)} reports failed: " + "; ".join(failures))
    return [Path(results[folder][0]) for folder in selected]
