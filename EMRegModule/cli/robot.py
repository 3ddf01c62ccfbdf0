"""The robot commands from files (issue 39): ``emreg handeye`` and ``emreg robot-target`` parse their arguments, call
:mod:`EMRegModule.pipeline.robot` (as the 3D Slicer module's robot panel does) and print.

``emreg handeye --robot-poses ROBOT --tracker TRACKER [--sensor NAME|PORT] [--settings case.toml] --out OUT``
writes ``OUT/robot_calibration.json``, ``OUT/SensorToFlange.h5`` and ``OUT/TrackerToBase.h5``.

``emreg robot-target --registration R --robot-calibration C --reference REF --plan PLAN --tool GUIDE --out OUT``
writes ``OUT/robot_target.json``.

Exit 2 for bad input, 3 when the data do not allow a safe answer; nothing is written then.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from ..names import ROBOT_TARGET_JSON
from ..pipeline.robot import calibrate_from_recordings, describe_calibration, target_from_files
from .args import out_folder, settings_of, warn


def cmd_handeye(args: argparse.Namespace) -> int:

    settings = settings_of(args)
    out = Path(out_folder(args.out) or args.out)
    result, document = calibrate_from_recordings(args.robot_poses, args.tracker, out, settings, args.sensor)
    warn("handeye", document["warnings"])
    print(describe_calibration(result, document, out))
    return 0


def cmd_robot_target(args: argparse.Namespace) -> int:

    settings = settings_of(args)
    out = Path(out_folder(args.out) or args.out)
    answer, _ = target_from_files(args.registration, args.robot_calibration, args.reference, args.plan, args.tool,
                                  out, settings, args.reference_sensor)
    print(f"FlangeToBase for the plan: guide exit on Entry, {answer.depth_mm:.1f} mm to the target; predicted error "
          f"at the target {answer.predicted_error_mm['total']:.2f} mm RMS -> {out / ROBOT_TARGET_JSON}")
    return 0

