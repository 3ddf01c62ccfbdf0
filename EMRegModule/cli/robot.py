"""The robot commands (issue 39): ``emreg handeye`` and ``emreg robot-target`` (:mod:`EMRegModule.pipeline.robot`
does the work).

``emreg handeye --robot-poses ROBOT --tracker TRACKER [--sensor NAME|PORT] [--settings case.toml] --out OUT``
writes ``OUT/robot_calibration.json`` and ``OUT/SensorToFlange.h5``, ``OUT/TrackerToBase.h5``.

``emreg robot-target --registration R --robot-calibration C --reference REF --plan PLAN --tool GUIDE --out OUT``
writes ``OUT/robot_target.json``.

Exit 2 for bad input, 3 when the data do not allow a safe answer; nothing is written then.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from ..pipeline.robot import handeye_from_recordings, target_robot
from .args import out_folder, settings_of, warn


def cmd_handeye(args: argparse.Namespace) -> int:
    settings = settings_of(args)
    out = Path(out_folder(args.out) or args.out)
    written = handeye_from_recordings(args.robot_poses, args.tracker, args.sensor, settings, out)
    result, residuals = written.result, written.document["residuals"]
    warn("handeye", written.warnings)
    print(f"SensorToFlange and TrackerToBase from {len(result.used)} frames ({len(result.rejected)} left out); "
          f"time offset {result.time_offset_s:.4f} s; residual RMS {residuals['rotation_deg']['rms']:.3f}"
          f" deg, {residuals['translation_mm']['rms']:.3f} mm; predicted tool-point error "
          f"{result.tool_tip_rms_mm:.3f} mm RMS -> {written.path}")
    return 0


def cmd_robot_target(args: argparse.Namespace) -> int:
    settings = settings_of(args)
    out = Path(out_folder(args.out))
    written = target_robot(args.registration, args.robot_calibration, args.reference, args.reference_sensor,
                           args.plan, args.tool, settings, out)
    answer = written.answer
    print(f"FlangeToBase for the plan: guide exit on Entry, {answer.depth_mm:.1f} mm to the target; predicted error "
          f"at the target {answer.predicted_error_mm['total']:.2f} mm RMS -> {written.path}")
    return 0
