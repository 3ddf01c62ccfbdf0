"""The per-stage commands of a case: ``emreg detect``, ``calibrate``, ``pivot``, ``register``, ``navigate``,
``evaluate``: each reads its inputs, runs its stage of :mod:`EMRegModule.stages` through the controller and
saves it into OUT (the outputs of its own and of every later stage moved to ``OUT/previous/``).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from ..errors import EMRegError, NoSafeAnswerError
from ..io.case import find_ct, open_case, read_targets
from ..io.markers_json import markers_beside
from ..io.output_folder import refuse_out_over_inputs
from ..io.tool_files import write_tool_calibration
from ..names import REGISTRATION_JSON, TIP_TO_PROBE_H5, TOOL_CALIBRATION_JSON
from ..pipeline.inputs import case_recording, read_recording
from ..pipeline.pivot import pivot_tool
from ..pipeline.results import offset_summary
from .args import (
    controller_of,
    out_folder,
    output_folder,
    ports_given,
    settings_of,
    use_plan,
    use_tool,
    warn,
    with_series_of,
)
from .live import check_live_options, run_live_navigate


def cmd_detect(args: argparse.Namespace) -> int:
    out_folder(args.out)
    source = Path(args.ct)
    case_dir = source if source.is_dir() and find_ct(source) is not None else None
    ct_path = find_ct(source) if case_dir is not None else source
    controller = controller_of(args, with_series_of(settings_of(args, case_dir), args))
    folder = output_folder(args, "detect", [ct_path], case_dir)
    controller.recorder.note_inputs(ct=ct_path if ct_path.exists() else None)
    # detected on the slices read as the rest arrives; the CT is not kept (only the markers are written)
    result = controller.make("detect", folder=folder, ct=ct_path, keep_image=False)
    print(f"{len(result.markers)} markers detected, {len(result.rejected)} candidates rejected -> {args.out}")
    return 0


def cmd_calibrate(args: argparse.Namespace) -> int:
    out_folder(args.out)
    recording = Path(args.recording)
    controller = controller_of(args, settings_of(args))
    use_tool(args, controller)
    controller.give(calibration=recording)
    tool_file = [Path(args.tool)] if args.tool and args.tool != "auto" else []
    folder = output_folder(args, "calibrate", [recording] + tool_file)
    controller.recorder.note_inputs(calibration=recording)
    result = controller.make("calibrate", folder=folder)
    controller.recorder.warn(result.warnings)
    tool = controller.inputs.tool
    if tool is None:
        print(f"{len(result.points)} pinholes calibrated -> {args.out}")
    else:
        motions = [p.motion for p in result.points]
        solved = "" if result.solved_tool is None else (
            f"; tip solved from {tool.touches} pivoting touches: [{', '.join(f'{v:.2f}' for v in tool.tip_mm)}] mm "
            f"+/- [{', '.join(f'{v:.2f}' for v in tool.tip_std_mm)}], RMS {tool.rms_mm:.2f} mm")
        print(f"{len(result.points)} tip touches ({motions.count('pivot')} pivoting, {motions.count('rest')} "
              f"resting) with the tool of {tool.source}{solved} -> {args.out}")
    return 0


def cmd_pivot(args: argparse.Namespace) -> int:
    out_folder(args.out)
    recording_path = Path(args.recording)
    inputs = controller_of(args, settings_of(args)).inputs
    tool, warnings = pivot_tool(recording_path, inputs.settings, inputs.reference_sensor, inputs.probe_sensor)
    refuse_out_over_inputs(args.out, [recording_path], (TOOL_CALIBRATION_JSON, TIP_TO_PROBE_H5))
    write_tool_calibration(tool, args.out)
    warn("pivot", warnings + tool.warnings)
    tip = ", ".join(f"{v:.2f}" for v in tool.tip_mm)
    print(f"tip at [{tip}] mm in the probe frame ({np.linalg.norm(tool.tip_mm):.1f} mm from the sensor), RMS "
          f"{tool.rms_mm:.2f} mm over {tool.samples} of {tool.samples_total} samples, swing "
          f"{tool.rotation_range_deg:.0f} degrees -> {args.out}")
    return 0


def cmd_register(args: argparse.Namespace) -> int:
    out_folder(args.out)
    controller = controller_of(args, settings_of(args))
    inputs = [Path(p) for p in (args.markers, args.fiducials, args.calibration, args.targets) if p]
    if (args.markers is None) == (args.fiducials is None):
        raise EMRegError("register: give the image side once: --markers markers.json (CT markers) or --fiducials FILE "
                         "(.mrk.json, .fcsv, a PLUS device-set XML with landmarks, or markers.json)")
    folder = output_folder(args, "register", inputs)
    controller.adopt("detect", args.fiducials if args.fiducials is not None else args.markers)
    controller.adopt("calibrate", args.calibration)
    targets = None
    if args.targets:
        controller.recorder.note_inputs(targets=args.targets)
        targets = read_targets(args.targets)[1]
    try:
        result = controller.make("register", folder=folder, targets=targets)
    except NoSafeAnswerError:
        folder.remove_from("register")
        raise
    controller.recorder.warn(result.warnings)

    print(f"registered: FRE {result.fre_mm:.2f} mm, {offset_summary(result)}, {len(result.pairs)} pairs -> {args.out}")
    return 0


def cmd_navigate(args: argparse.Namespace) -> int:
    check_live_options(args)  # replay or live: a value out of range is refused before anything is made
    out_folder(args.out)
    if args.igtl_port is not None or not args.source.startswith("replay:"):
        return run_live_navigate(args)
    if not args.out:
        raise EMRegError("navigate: --out DIR is needed to write navigation.csv from a replay")

    recording_path = Path(args.source[len("replay:"):])
    controller = controller_of(args, settings_of(args))

    markers, note = markers_beside(args.registration)
    if markers is not None:  # the checkpoints need the markers' pinholes (before the registration: it is dropped)
        controller.adopt("detect", detection=markers)
    controller.adopt("register", args.registration)
    warn("navigate", [note] if note else [])
    warn("navigate", controller.use_ports(*ports_given(args, controller.settings), args.registration))
    use_tool(args, controller, solves=False)
    use_plan(args, controller)
    recording = read_recording(recording_path, controller.inputs)
    plan = controller.inputs.plan
    folder = output_folder(args, "navigate", [recording_path, Path(args.registration)]
                           + ([Path(plan.source)] if plan is not None else []))
    controller.recorder.note_inputs(navigation=recording_path)
    result = controller.make("navigate", recording=recording)
    controller.recorder.warn(recording.warnings)
    controller.save("navigate", folder)
    checkpoints = controller.results.checkpoints
    guided = "" if controller.results.guidance is None else f"; {controller.results.guidance.summary()}"
    print(f"{len(result)} probe samples mapped into image space; {checkpoints.summary()}{guided} -> {args.out}")
    return 0


def cmd_evaluate(args: argparse.Namespace) -> int:
    case = open_case(args.case, settings_of(args) if args.settings else None)
    out_folder(args.out)
    if case.navigation is None and case.board is None:
        raise EMRegError(f"{case.folder}: nothing to evaluate: no navigation recording (navigation.csv) and no "
                         "board recording (board.csv) in the case folder")
    if case.navigation is not None and case.targets is None and case.board is None:
        raise EMRegError(f"{case.folder}: nothing to evaluate: a navigation recording but no targets.mrk.json "
                         "(and no board.csv)")
    given = ports_given(args, case.settings)
    case.settings = case.settings.with_sensors(args.reference_sensor, args.probe_sensor)  # sequence files' ports
    controller = controller_of(args, case.settings)
    inputs = [p for p in (case.navigation, case.targets, case.board) if p is not None]
    folder = output_folder(args, "evaluate", [*inputs, Path(args.registration)], case.folder)

    markers, note = markers_beside(args.registration)
    if markers is not None:  # the pose status (checkpoints at the pinholes) as navigate gives it: INVALID left out
        controller.adopt("detect", detection=markers)
    controller.adopt("register", args.registration)
    warn("evaluate", ([note] if note else []) + controller.use_ports(*given, args.registration))
    inputs = controller.inputs
    case.settings = case.settings.with_sensors(inputs.reference_sensor, inputs.probe_sensor)
    controller.recorder.check_case_inputs(REGISTRATION_JSON, args.registration, case)
    controller.recorder.note_inputs(navigation=case.navigation, targets=case.targets, board=case.board)
    use_tool(args, controller, solves=False)

    inputs = controller.inputs
    result = controller.make("evaluate", folder=folder, navigation=case_recording(case, "navigation", inputs),
                             targets=case.read_targets(), board=case_recording(case, "board", inputs))
    controller.recorder.warn(result.warnings)
    print(f"evaluation -> {folder.path / 'evaluation.json'}")
    return 0
