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

from .args import AddCommand, out_folder, settings_of, warn


def cmd_handeye(args: argparse.Namespace) -> int:
    from ..pipeline.robot import calibrate_from_recordings, describe_calibration

    settings = settings_of(args)
    out = Path(out_folder(args.out) or args.out)
    result, document = calibrate_from_recordings(args.robot_poses, args.tracker, out, settings, args.sensor)
    warn("handeye", document["warnings"])
    print(describe_calibration(result, document, out))
    return 0


def cmd_robot_target(args: argparse.Namespace) -> int:
    from ..names import ROBOT_TARGET_JSON
    from ..pipeline.robot import target_from_files

    settings = settings_of(args)
    out = Path(out_folder(args.out) or args.out)
    answer, _ = target_from_files(args.registration, args.robot_calibration, args.reference, args.plan, args.tool,
                                  out, settings, args.reference_sensor)
    print(f"FlangeToBase for the plan: guide exit on Entry, {answer.depth_mm:.1f} mm to the target; predicted error "
          f"at the target {answer.predicted_error_mm['total']:.2f} mm RMS -> {out / ROBOT_TARGET_JSON}")
    return 0


def add_parsers(add: AddCommand) -> None:
    """The subcommands of this module (``add``: :data:`~EMRegModule.cli.args.AddCommand`)."""
    p = add("handeye", cmd_handeye, "hand-eye (SensorToFlange) and robot-world (TrackerToBase) calibration with the "
            "EM tracker, from a robot's log and a tracker recording on two clocks")
    p.add_argument("--robot-poses", required=True, metavar="ROBOT",
                   help="the flange's poses in the robot base frame (FlangeToBase): a TUM trajectory file "
                        "(timestamp tx ty tz qx qy qz qw; s, m) or a PLUS sequence file ([handeye] flange_transform)")
    p.add_argument("--tracker", required=True, metavar="TRACKER",
                   help="the flange sensor's recording: a PLUS sequence file or EMReg tracking CSV")
    p.add_argument("--sensor", default=None, metavar="NAME|PORT",
                   help="the flange's sensor when TRACKER holds several: a transform name or a port")
    p.add_argument("--out", required=True, metavar="OUT", help="output folder (robot_calibration.json, .h5)")
    t = add("robot-target", cmd_robot_target, "the flange pose (FlangeToBase) that puts the needle guide on a "
            "trajectory planned in the CT")
    t.add_argument("--registration", required=True, metavar="R", help="registration.json (ReferenceToImage)")
    t.add_argument("--robot-calibration", required=True, metavar="C", help="robot_calibration.json (emreg handeye)")
    t.add_argument("--reference", required=True, metavar="REF",
                   help="the reference sensor now: a recording or a live source URL (trakstar:, aurora:, igtl:, "
                        "replay:), its samples averaged robustly")
    t.add_argument("--reference-sensor", type=int, default=None, metavar="PORT",
                   help="the reference sensor's port (default [sensors] reference)")
    t.add_argument("--plan", required=True, metavar="PLAN",
                   help="Slicer markups: a Line Entry -> Target, or points labelled Entry and Target")
    t.add_argument("--tool", required=True, metavar="GUIDE",
                   help="the needle guide on the flange sensor: a PLUS device set (From=NeedleGuide To=Sensor), an "
                        "ITK/Slicer transform or tool_calibration.json")
    t.add_argument("--out", required=True, metavar="OUT", help="output folder (robot_target.json)")
