"""The report page, one function per section, in :data:`SECTIONS` order; :func:`build_html` joins them.

A section whose inputs are missing says so in a note instead of disappearing. The page holds
no timestamps: the same inputs give the same bytes.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from ..core.ct import image_geometry
from .derived import finite_or_none, predicted_tre_by_target, tre_figures
from .figures import Figure, ReportData, read_checkpoints
from .html import CSS, DASH, esc, figure_html, note, num, table, vec
from .robot_section import robot_section

if TYPE_CHECKING:
    from ..core.evaluation import BoardEdge
    from ..core.registration import RegistrationResult


def _left_out(data: ReportData, part: str | None, absent: str) -> str:
    """Why a section has nothing to show, as the run's outputs say it: the part's "not evaluated" reason
    (``evaluation.json`` or ``run.json``), else the run's refusal or failure (``run.json`` ``status`` and
    ``message``: the steps after it were not made), else ``absent`` (what is missing and what it needs)."""
    run = data.inputs.run or {}
    evaluation = data.inputs.evaluation
    reasons = {**(run.get("not_evaluated") or {}), **(evaluation.not_evaluated if evaluation is not None else {})}
    if part is not None and reasons.get(part):
        return note(f"Not evaluated: {esc(reasons[part])}")
    status = run.get("status")
    if status in ("refused", "failed", "interrupted"):
        said = f": {run['message']}" if run.get("message") else ""
        return note(esc(f"Not shown: the run was {status}{said}; the steps after it were not made."))
    return note(absent)


def _figures(figures: dict[str, Figure], *names: str) -> str:
    return "".join(figure_html(figures[name]) for name in names if name in figures)


def summary_section(data: ReportData, figures: dict[str, Figure]) -> str:
    """Case, output folder, version, sensor ports, CT and the headline figures of every stage."""
    inputs, registration = data.inputs, data.inputs.registration
    rows = []
    if inputs.case_dir is not None:
        rows.append(("case folder", esc(inputs.case_dir)))
    rows.append(("output folder", esc(inputs.out_dir)))
    run = inputs.run or {}
    if run.get("emreg_version"):
        rows.append(("EMReg version", esc(run["emreg_version"])))
    if "reference_sensor" in run:
        rows.append(("sensor ports", f"reference {esc(run['reference_sensor'])}, probe {esc(run.get('probe_sensor'))}"))
    geometry = image_geometry(inputs.ct.image) if inputs.ct is not None else \
        (inputs.detection.image if inputs.detection is not None else None)
    if geometry:
        rows.append(("CT", f"{' x '.join(str(s) for s in geometry['size'])} voxels of "
                           f"{' x '.join(f'{s:.3g}' for s in geometry['spacing'])} mm"
                           + (f" ({esc(inputs.ct_path.name)})" if inputs.ct_path is not None else "")))
    series = inputs.detection.ct_series if inputs.detection is not None else None
    if series:
        others = series.get("others") or []
        rows.append(("CT series", esc(f"{series.get('series_number')} '{series.get('description', '')}' "
                                      f"({series.get('series_instance_uid')}), {series.get('slices')} slices "
                                      f"{series.get('slice_spacing_mm')} mm apart; {len(others)} other series "
                                      f"not used")))
    if inputs.detection is not None:
        rows.append(("markers detected", f"{len(data.rows)} ({len(inputs.detection.rejected)} candidates rejected)"))
    if inputs.frame_calibration is not None:
        rows.append(("pinholes calibrated", str(len(data.points))))
    if registration is not None:
        rows.append(("pairs", str(len(registration.pairs))))
        rows.append(("FRE", f"{num(registration.fre_mm)} mm"))
        model = inputs.model
        if registration.point_fit:
            block = registration.fiducials
            rows.append(("registered onto", esc(f"{len(block.get('points') or [])} fiducials ({block.get('format')}, "
                                                f"{Path(str(block.get('file', ''))).name}): rigid point fit, no "
                                                "sensor offset; no CT")))
        else:
            rows.append(("sensor offset l", f"{num(registration.sensor_offset_l_mm)} mm (pinhole range "
                                            f"{model.pinhole_bottom_mm:.1f} to {model.pinhole_top_mm:.1f} mm)"))
    if inputs.navigation_positions is not None:
        rows.append(("navigated probe samples", str(len(inputs.navigation_positions))))
    tre = tre_figures(inputs.evaluation)
    if tre:
        rows.append(("TRE", f"{num(tre.get('mean_mm'))} &plusmn; {num(tre.get('std_mm'))} mm"))
    return "<h2>Summary</h2>" + table(("item", "value"), rows, left_columns=2)


def warnings_section(data: ReportData, figures: dict[str, Figure]) -> str:
    """Refusals, warnings and notes, or a green box when there is nothing to worry about."""
    parts = ["<h2>Warnings</h2>"]
    if not any(w.kind in ("warning", "refused") for w in data.warnings):
        parts.append("<div class=\"ok\">No warnings.</div>")
    for w in data.warnings:
        css = {"refused": "refused", "warning": "warn"}.get(w.kind, "note")
        prefix = {"refused": "Refused: ", "warning": ""}.get(w.kind, "")
        parts.append(f"<div class=\"{css}\">{esc(prefix + w.text)}</div>")
    return "\n".join(parts)


def scene_section(data: ReportData, figures: dict[str, Figure]) -> str:
    """The frame in 3D from two directions."""
    if "scene_oblique" in figures:
        return "<h2>Frame in 3D</h2>\n" + _figures(figures, "scene_oblique", "scene_top")
    return "<h2>Frame in 3D</h2>\n" + note("Not shown: no markers.json (nor a registration placing the calibration "
                                            "points) in the output folder.")


def _pairs_table(data: ReportData) -> str:
    by_id = {r.id: r for r in data.rows}
    rows = []
    for pair in data.inputs.registration.pairs:
        marker = by_id.get(str(pair.get("image_marker")))
        point = data.points.get(str(pair.get("calibration_point")))
        samples = point.samples if point is not None and point.samples else None
        rows.append((esc(pair.get("image_marker")), esc(pair.get("calibration_point")), num(pair.get("residual_mm")),
                     "<b>yes</b>" if pair.get("outlier") else "", num(marker.volume_mm3 if marker else None, 0),
                     num(marker.fit_rms_mm if marker else None, 3), num(point.std_mm if point else None, 3),
                     esc(samples) if samples is not None else DASH))
    return "<h3>Pairs</h3>" + table(
        ("image marker", "calibration point", "residual (mm)", "outlier", "marker volume (mm³)", "fit RMS (mm)",
         "dwell spread (mm)", "samples"), rows, left_columns=2)


def registration_section(data: ReportData, figures: dict[str, Figure]) -> str:
    """Residuals, FRE(l), ReferenceToImage, the pairs, what stayed unpaired and the other figures."""
    registration = data.inputs.registration
    if registration is None:
        return "<h2>Registration</h2>\n" + _left_out(data, None, "Not shown: no registration.json in the output "
                                                                 "folder.")
    matrix = np.asarray(registration.reference_to_image, dtype=float)
    parts = ["<h2>Registration</h2>", _figures(figures, "residuals"), _figures(figures, "fre_curve"),
             _figures(figures, "distortion"),
             "<h3>ReferenceToImage</h3>" + table(("", "x", "y", "z", "t"),
                                                 [(f"row {i + 1}", *(f"{v:.4f}" for v in matrix[i]))
                                                  for i in range(4)]),
             _pairs_table(data)]
    unpaired = [("detected markers", ", ".join(map(str, registration.unpaired_image_markers))),
                ("calibration points", ", ".join(map(str, registration.unpaired_calibration_points)))]
    parts.append("<h3>Unpaired</h3>" + table(("kind", "labels"), [(k, esc(v) or "none") for k, v in unpaired],
                                             left_columns=2))
    extra = [(name, value) for name, value in (("sensor_offset_l_std_mm", registration.sensor_offset_l_std_mm),
                                               ("fle_mm", registration.fle_mm))
             if finite_or_none(value) is not None]
    if extra:
        parts.append("<h3>Other figures</h3>" + table(("name", "value"), [(esc(k), num(v, 3)) for k, v in extra]))
    return "\n".join(p for p in parts if p)


def markers_section(data: ReportData, figures: dict[str, Figure]) -> str:
    """Slices through each marker, the detected markers and the rejected candidates."""
    detection = data.inputs.detection
    registration = data.inputs.registration
    if detection is None and registration is not None and registration.point_fit:
        return fiducials_section(data)
    if detection is None:
        return "<h2>Markers in the CT</h2>\n" + note("Not shown: no markers.json in the output folder.")
    parts = ["<h2>Markers in the CT</h2>"]
    parts.append(_figures(figures, "marker_slices") if "marker_slices" in figures else
                 note("CT slices not shown: the CT was not found (give the case folder with --case)."))
    parts.append("<h3>Detected markers</h3>" + table(
        ("id", "origin (LPS mm)", "axis", "volume (mm³)", "fit RMS (mm)", "paired with", "residual (mm)"),
        [(esc(r.id), vec(r.origin), vec(r.axis, 3), num(r.volume_mm3, 0), num(r.fit_rms_mm, 3),
          esc(r.calibration_label) if r.calibration_label else DASH, num(r.residual_mm)) for r in data.rows]))
    if detection.rejected:
        parts.append("<h3>Rejected candidates</h3>" + table(
            ("centroid (LPS mm)", "volume (mm³)", "reason"),
            [(vec(c.centroid), num(c.volume_mm3, 0), esc(c.reason)) for c in detection.rejected], left_columns=(2,)))
    return "\n".join(parts)


def fiducials_section(data: ReportData) -> str:
    """The fiducials a point fit registered onto (no CT, nothing detected): each with its pair and residual."""
    block = data.inputs.registration.fiducials
    pairs = {str(p.get("image_marker")): p for p in data.inputs.registration.pairs}
    declared = block.get("declared") or {}
    rows = []
    for point in block.get("points") or []:
        pair = pairs.get(str(point.get("label")), {})
        rows.append((esc(point.get("label")), vec(np.asarray(point.get("position"), dtype=float)),
                     esc(pair.get("calibration_point")) if pair else DASH, num(pair.get("residual_mm"))))
    said = ", ".join(f"{k.replace('_', ' ')} {v}" for k, v in declared.items())
    return "\n".join([
        "<h2>Fiducials</h2>",
        note(esc(f"No CT: the calibration points were registered onto the fiducials of {block.get('file')} "
                 f"({block.get('format')}{'; ' + said if said else ''}) by a rigid point fit, with no sensor offset; "
                 "marker detection was skipped. Calibration points: "
                 f"{block.get('calibration_points', 'the touched points')}.")),
        table(("fiducial", f"position ({block.get('frame', 'LPS')} mm)", "paired with", "residual (mm)"), rows)])


def calibration_section(data: ReportData, figures: dict[str, Figure]) -> str:
    """The calibrated pinholes (Reference frame) with their dwell figures."""
    if not data.points:
        return "<h2>Frame calibration</h2>\n" + _left_out(data, None, "Not shown: no frame_calibration.json in the "
                                                                      "output folder.")
    rows = [(esc(label), vec(p.position), vec(p.direction, 3) if np.all(np.isfinite(p.direction)) else DASH,
             esc(p.samples) if p.samples else DASH, num(p.std_mm, 3)) for label, p in data.points.items()]
    tool = data.inputs.frame_calibration.tool if data.inputs.frame_calibration is not None else None
    if not tool:
        return "<h2>Frame calibration</h2>\n" + table(
            ("label", "position (Reference mm)", "direction", "samples", "spread (mm)"), rows)
    rows = [row + (esc(p.motion) if p.motion else DASH,) for row, p in zip(rows, data.points.values(), strict=True)]
    return "\n".join(["<h2>Frame calibration</h2>", tool_note(tool), table(
        ("label", "tip position (Reference mm)", "direction", "samples", "spread (mm)", "touch"), rows)])


def tool_note(tool: dict) -> str:
    """One paragraph on the tool whose tip made the calibration points (``frame_calibration.json``'s ``tool``)."""
    tip = np.asarray(tool.get("tip_mm") or [np.nan] * 3, dtype=float)
    text = (f"Tool: {esc(tool.get('name') or 'tracked tool')}, tip at {vec(tip)} mm in the sensor's frame "
            f"({num(float(np.linalg.norm(tip)), 1)} mm from it), from {esc(tool.get('source', ''))}")
    if tool.get("method"):
        text += f"; {esc(tool['method'])}"
    if tool.get("rms_mm") is not None:
        text += f", pivot residual {num(tool['rms_mm'], 2)} mm RMS"
    if tool.get("tip_std_mm") is not None:
        text += f", tip standard deviation {vec(tool['tip_std_mm'], 2)} mm"
    return note(text + ". Each point is the tip held still: pivot (the shaft swung about it) or rest.")


def tre_section(data: ReportData, figures: dict[str, Figure]) -> str:
    """Measured TRE per target and over all, beside the predicted end-to-end RMS TRE and its budget."""
    tre = tre_figures(data.inputs.evaluation)
    if not tre:
        return "<h2>Target registration error</h2>\n" + _left_out(
            data, "tre", "Not shown: no TRE in evaluation.json (needs navigation.csv and targets.mrk.json in the "
                         "case).")
    registration_only = predicted_tre_by_target(data.inputs)
    rows = [(esc(name), num(t.get("mean_mm")), num(t.get("std_mm")), esc(t.get("n", "")), num(t.get("rms_mm")),
             num(t.get("predicted_rms_mm")), num(registration_only.get(name)))
            for name, t in (tre.get("targets") or {}).items()]
    rows.append(("<b>all</b>", num(tre.get("mean_mm")), num(tre.get("std_mm")),
                 esc(tre.get("n", "")) if tre.get("n") is not None else "", num(tre.get("rms_mm")),
                 num(tre.get("predicted_rms_mm")),
                 num(np.sqrt(np.mean(np.square(list(registration_only.values()))))) if registration_only else DASH))
    return "\n".join(["<h2>Target registration error</h2>", _figures(figures, "tre_targets", "error_budget", "tre_map"),
                      table(("target", "mean (mm)", "std (mm)", "n", "RMS (mm)", "predicted RMS (mm)",
                             "registration's share (mm)"), rows),
                      note("Predicted: the end-to-end RMS TRE the error model predicts (registration, tracking at the "
                           "target, reference sensor, placement); the registration's share: its registration term "
                           "alone.")])


def checkpoints_section(data: ReportData, figures: dict[str, Figure]) -> str:
    """The checkpoints during navigation (``checkpoints.json``): the figure and one row per checkpoint."""
    if "checkpoints" not in figures:
        return ""

    document = read_checkpoints(data) or {}
    rows = [(esc(c["image_marker"]), num(c["start_s"], 2), num(c["end_s"], 2), num(c["error_mm"]),
             "passed" if c["ok"] else "<b>FAILED</b>") for c in document.get("checkpoints", [])]
    return "\n".join(["<h2>Checkpoints during navigation</h2>", _figures(figures, "checkpoints"),
                      table(("marker", "from (s)", "to (s)", "error (mm)", "verdict"), rows)])


def guidance_section(data: ReportData, figures: dict[str, Figure]) -> str:
    """The navigation to a plan (``navigation.json``): the plan, the tool, the predicted error at the target, the
    closest approach with its time, and the approach figures."""
    document = data.inputs.folder.guidance
    if document is None:
        return ""
    plan = document.get("plan") or {}
    prediction = document.get("predicted_at_target") or {}
    closest = document.get("closest_approach") or {}
    tool = document.get("tool") or {}

    def point(values: object) -> str:
        return DASH if not values else esc(", ".join(f"{float(v):.2f}" for v in values))  # type: ignore[union-attr]

    rows = [("Target (LPS, mm)", point(plan.get("target_mm"))), ("Entry (LPS, mm)", point(plan.get("entry_mm"))),
            ("planned length (mm)", num(plan.get("length_mm"))),
            ("plan file", esc(f"{plan.get('source', '')} ({plan.get('declared_coordinate_system', 'LPS')})")),
            ("tool", esc(f"{tool.get('source')}: tip at {point(tool.get('tip_mm'))} mm" if tool else
                         "none: the probe sensor is navigated")),
            ("predicted error at the target (RMS, mm)", num(prediction.get("rms_mm"))),
            ("predicted 95 % radius (mm)", num(prediction.get("radius_95_mm"))),
            ("closest approach (mm)", num(closest.get("target_distance_mm"))),
            ("at (s)", num(closest.get("time_s"), 2)),
            ("then: off the line (mm), angle (degrees), to go (mm)",
             f"{num(closest.get('lateral_mm'))}, {num(closest.get('angle_deg'))}, {num(closest.get('to_go_mm'))}")]
    return "\n".join(["<h2>Guidance to the plan</h2>", table(("item", "value"), rows, left_columns=2),
                      _figures(figures, "guidance_approach", "guidance_plan_view", "guidance_ct"),
                      note("The predicted error at the target: the error model's end-to-end RMS TRE there, the tool "
                           "file's calibration error and the sensor's orientation error over the tool's lever arm, in "
                           "quadrature; 95 %: the radius holding 95 % of an isotropic Gaussian error of that RMS.")])


def _board_row(i: int, name: str, edge: BoardEdge, nominal: list) -> tuple[str, ...]:
    reference = finite_or_none(edge.nominal_mm)
    if reference is None and i < len(nominal):
        reference = finite_or_none(nominal[i])
    mean = finite_or_none(edge.length.mean_mm)
    error = f"{mean - reference:+.2f}" if reference is not None and mean is not None else DASH
    if edge.abs_error_mean_mm is not None:
        absolute = f"{num(edge.abs_error_mean_mm)} &plusmn; {num(edge.abs_error_std_mm)}"
        relative = f"{num(edge.rel_error_mean_percent)}% &plusmn; {num(edge.rel_error_std_percent)}%"
    else:
        absolute = DASH
        relative = f"{100 * (mean - reference) / reference:+.2f}%" \
            if reference is not None and mean is not None and reference else DASH
    holes = DASH.join(esc(h) for h in edge.holes)
    return (esc(name), holes, num(mean), num(edge.length.std_mm), esc(edge.length.n), num(reference), error,
            absolute, relative)


def board_section(data: ReportData, figures: dict[str, Figure]) -> str:
    """The board phantom's edge lengths against their nominal lengths (paper Table 1)."""
    board = data.inputs.evaluation.board if data.inputs.evaluation is not None else None
    if board is None or not board.edges:
        return "<h2>Board phantom</h2>\n" + _left_out(
            data, "board", "Not shown: no board table in evaluation.json (needs board.csv in the case).")
    nominal = list(data.inputs.settings.board.edges_mm or [])
    rows = [_board_row(i, name, edge, nominal) for i, (name, edge) in enumerate(board.edges.items())]
    return "\n".join([
        "<h2>Board phantom</h2>",
        table(("edge", "holes", "mean length (mm)", "std (mm)", "n", "nominal (mm)", "mean - nominal (mm)",
               "absolute error (mm)", "relative error"), rows, left_columns=2),
        "<p class=\"muted\">Paper Table 1: absolute errors 0.16 to 0.21 mm against a Vernier caliper, all below "
        "1 mm.</p>"])


def run_log_section(data: ReportData, figures: dict[str, Figure]) -> str:
    """The run's summary lines, as ``emreg run`` printed them."""
    summary = (data.inputs.run or {}).get("summary")
    return "<h2>Run log</h2><pre>" + esc("\n".join(map(str, summary))) + "</pre>" if summary else ""


SECTIONS: tuple[Callable[[ReportData, dict[str, Figure]], str], ...] = (
    summary_section, warnings_section, scene_section, registration_section, markers_section, calibration_section,
    tre_section, checkpoints_section, guidance_section, robot_section, board_section, run_log_section)


def _image_space(registration: RegistrationResult | None) -> str:
    """What "image space" is in this report (HTML): the CT's, or (a point fit) the fiducials' frame."""
    if registration is not None and registration.point_fit:
        block = registration.fiducials
        return esc(f"Image space is the fiducials' frame ({block.get('frame', 'LPS')}, mm) of {block.get('file')}; "
                   "there is no CT.")
    return "Image space is the CT's LPS physical space (mm)."


def build_html(data: ReportData, figures: list[Figure]) -> str:
    """The report page (one string, deterministic for the same inputs)."""
    inputs = data.inputs
    case_name = inputs.case_dir.name if inputs.case_dir is not None else inputs.out_dir.name
    by_name = {f.name: f for f in figures}
    parts = [f"<!DOCTYPE html><html lang=\"en\"><head><meta charset=\"utf-8\">"
             f"<meta name=\"viewport\" content=\"width=device-width, initial-scale=1\">"
             f"<title>EMReg report: {esc(case_name)}</title><style>{CSS}</style></head><body><main>",
             f"<h1>EMReg verification report: {esc(case_name)}</h1>",
             f"<p class=\"muted\">{_image_space(inputs.registration)} ReferenceToImage maps points of the "
             "reference sensor (Model 800) frame into it.</p>"]
    parts += [text for section in SECTIONS if (text := section(data, by_name))]
    parts.append("</main></body></html>\n")
    return "\n".join(parts)
