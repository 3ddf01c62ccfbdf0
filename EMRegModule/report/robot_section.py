"""The report's robot section (issue 39): the hand-eye calibration (its residuals, the frames it used and left out,
the clock-offset fit), the flange pose for the plan and the guide-to-plan error ``emreg robot-go`` measured, in the
words of the people who use them. Shown when the output folder holds ``robot_calibration.json``,
``robot_target.json`` or ``robot_go.json``; absent otherwise."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from .figures import Figure, ReportData, robot_fit
from .html import DASH, esc, figure_html, note, num, table


def _stat(block: Mapping[str, Any], unit: str, digits: int = 3) -> str:
    return (f"RMS {num(block.get('rms'), digits)}, median {num(block.get('median'), digits)}, 95 % "
            f"{num(block.get('p95'), digits)}, largest {num(block.get('max'), digits)} {unit}")


def _point(values: Any) -> str:
    return esc(", ".join(f"{float(v):g}" for v in values or []))


def _calibration(data: ReportData, figures: dict[str, Figure]) -> list[str]:
    document = data.inputs.folder.robot_calibration
    residuals = document.get("residuals") or {}
    frames = document.get("frames") or {}
    clock = document.get("time_offset") or {}
    uncertainty = document.get("uncertainty") or {}
    motion = document.get("motion") or {}
    rotation, translation = residuals.get("rotation_deg") or {}, residuals.get("translation_mm") or {}
    rows = [
        ("frames used", esc(f"{frames.get('used', DASH)} ({frames.get('still', 0)} still, in {frames.get('dwells', 0)} "
                            "dwell(s))")),
        ("frames left out", esc(frames.get("rejected", DASH))),
        ("rotation residual", esc(_stat(rotation, "deg"))),
        ("translation residual", esc(_stat(translation, "mm"))),
        ("still noise per axis", f"{num(residuals.get('noise_rotation_deg'), 3)} deg, "
                                 f"{num(residuals.get('noise_position_mm'), 3)} mm"),
        ("clock offset time_offset_s", f"{num(document.get('time_offset_s'), 4)} s &plusmn; "
                                       f"{num(clock.get('std_s'), 4)} s (t_tracker = t_robot + time_offset_s)"),
        ("from the angular speeds alone", f"{num(clock.get('cross_correlation_s'), 4)} s, correlation "
                                          f"{num(clock.get('correlation'), 2)}"),
        ("flange rotation", f"up to {num(motion.get('rotation_range_deg'), 1)} deg, "
                            f"{num(motion.get('second_axis_rms_deg'), 1)} deg RMS about a second axis"),
        ("predicted error, tool point", f"{num(uncertainty.get('tool_tip_rms_mm'), 3)} mm RMS at "
                                        f"{_point(uncertainty.get('tool_tip_mm'))}"
                                        " mm in the sensor's frame"),
        ("predicted error, tracker point", f"{num(uncertainty.get('tracker_point_rms_mm'), 3)} mm RMS at "
                                           f"{_point(uncertainty.get('tracker_point_mm'))}"
                                           " mm in front of the field generator")]
    words = (f"The robot and the tracker agree on where the flange sensor is to {num(rotation.get('rms'), 2)} degrees "
             f"and {num(translation.get('rms'), 2)} mm (RMS over the {esc(frames.get('used', DASH))} samples used). "
             f"A needle guide 150 mm out on the flange is placed with a predicted error of "
             f"{num(uncertainty.get('tool_tip_rms_mm'), 2)} mm RMS from the calibration alone.")
    parts = ["<h3>Hand-eye calibration (SensorToFlange, TrackerToBase)</h3>", f"<p>{words}</p>",
             table(("item", "value"), rows, left_columns=2)]
    reasons = frames.get("rejected_by_reason") or {}
    if reasons:
        parts.append("<h4>Frames left out, by reason</h4>" + table(
            ("reason", "frames"), [(esc(reason), esc(count)) for reason, count in reasons.items()], left_columns=1))
    why = robot_fit(data)[1]
    if "robot_residuals" in figures:
        parts += [figure_html(figures["robot_residuals"]), figure_html(figures["robot_clock"])]
    elif why:
        parts.append(note(esc(f"Residual and clock-offset figures not drawn: {why}.")))
    return parts


def _target(document: Mapping[str, Any]) -> list[str]:
    predicted = document.get("predicted_error_mm") or {}
    rows = [("Entry (LPS, mm)", esc(", ".join(f"{float(v):.2f}" for v in document.get("entry_image_mm", [])))),
            ("Target (LPS, mm)", esc(", ".join(f"{float(v):.2f}" for v in document.get("target_image_mm", [])))),
            ("depth Entry to Target (mm)", num(document.get("depth_mm"), 1)),
            ("standoff before Entry (mm)", num(document.get("standoff_mm"), 1)),
            ("roll about the needle axis (deg)", num(document.get("roll_deg"), 1)),
            ("predicted error at the target (RMS, mm)", num(predicted.get("total"))),
            ("of which registration, hand-eye, guide (mm)",
             f"{num(predicted.get('registration'))}, {num(predicted.get('hand_eye'))}, {num(predicted.get('tool'))}")]
    return ["<h3>Flange pose for the plan (robot_target.json)</h3>",
            f"<p>The robot puts the needle guide's exit on Entry with its axis along Entry &rarr; Target; a needle "
            f"pushed {num(document.get('depth_mm'), 1)} mm through it is predicted to end within "
            f"{num(predicted.get('total'))} mm RMS of the Target.</p>", table(("item", "value"), rows, left_columns=2)]


def _go(document: Mapping[str, Any], figures: dict[str, Figure]) -> list[str]:
    final = document.get("final") or {}
    within = document.get("on_plan")
    verdict = (f"On the plan after {esc(document.get('corrections', DASH))} correction(s): the needle tip at the "
               f"planned depth lands {num(final.get('tip_mm'))} mm from the Target, the guide's axis is "
               f"{num(final.get('angle_deg'))} degrees off the planned line and its exit "
               f"{num(final.get('exit_mm'))} mm from Entry (tolerance {num(document.get('tolerance_mm'))} mm, "
               f"{num(document.get('tolerance_deg'))} degrees), measured with the EM tracker.")
    rows = [(esc("after the move" if int(m.get("step", 0)) == 0 else f"correction {int(m['step'])}"),
             num(m.get("tip_mm")), num(m.get("angle_deg")), num(m.get("exit_mm")), num(m.get("lateral_mm")))
            for m in document.get("measurements", [])]
    return ["<h3>Guide to plan (robot_go.json)</h3>",
            f"<div class=\"{'ok' if within else 'warn'}\">{verdict}</div>",
            table(("measured", "tip at planned depth to Target (mm)", "axis angle (deg)", "exit to Entry (mm)",
                   "exit off the line (mm)"), rows, left_columns=1),
            figure_html(figures["robot_go"]) if "robot_go" in figures else ""]


def robot_section(data: ReportData, figures: dict[str, Figure]) -> str:
    """The robot's outputs in the output folder (empty without any)."""
    folder = data.inputs.folder
    if not folder.has_robot:
        return ""
    parts = ["<h2>Robot</h2>"]
    if folder.robot_calibration is not None:
        parts += _calibration(data, figures)
    if folder.robot_target is not None:
        parts += _target(folder.robot_target)
    if folder.robot_go is not None:
        parts += _go(folder.robot_go, figures)
    return "\n".join(p for p in parts if p)
