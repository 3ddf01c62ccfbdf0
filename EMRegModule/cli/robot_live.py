"""The robot commands that move a robot (issue 39, section 3): ``emreg robot-calibrate`` and ``emreg robot-go``
(:mod:`EMRegModule.pipeline.robot_session` does the work and says what it plans and measures).

``emreg robot-calibrate --robot URL --tracker URL --out OUT [--sensor PORT] [--execute]`` moves through calibration
poses it plans itself and writes ``OUT/robot_calibration.json``, the two ``.h5`` and the recordings.

``emreg robot-go --robot URL --tracker URL --target OUT/robot_target.json [--execute]`` moves the needle guide onto
the plan and corrects it with the EM tracker until it is within tolerance, streaming ``NeedleGuideToRAS`` over
OpenIGTLink (``--igtl-port``); ``--out`` writes ``robot_go.json``.

Without ``--execute`` nothing moves: both print the planned motion. A safety stop ends with exit 3 and the reason.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from ..pipeline.robot_session import robot_calibrate, robot_go
from .args import out_folder, settings_of


def cmd_robot_calibrate(args: argparse.Namespace) -> int:
    settings = settings_of(args)
    flange_port = args.sensor or settings.robot.flange_sensor
    out = Path(out_folder(args.out, create=args.execute))
    run = robot_calibrate(args.robot, args.tracker, flange_port, settings, out, args.execute, print)
    if run is None:
        return 0
    result, residuals = run.calibration.result, run.calibration.document["residuals"]
    print(f"robot-calibrate: SensorToFlange and TrackerToBase from {len(result.used)} frames over {run.poses} poses; "
          f"residual RMS {residuals['rotation_deg']['rms']:.3f} deg, "
          f"{residuals['translation_mm']['rms']:.3f} mm; predicted tool-point error "
          f"{result.tool_tip_rms_mm:.3f} mm RMS -> {run.calibration.path}")
    return 0


def cmd_robot_go(args: argparse.Namespace) -> int:
    settings = settings_of(args)
    flange_port = args.sensor or settings.robot.flange_sensor
    reference_port = args.reference_sensor or settings.sensors.reference
    out = out_folder(args.out, create=args.execute) if args.out else None
    went = robot_go(args.robot, args.tracker, args.target, flange_port, reference_port, settings, out, args.execute,
                    args.igtl_port, print)
    if went is None:
        return 0
    final = went.final
    print(f"robot-go: on the plan after {went.corrections} correction(s): exit {final['exit_mm']:.2f} mm, tip "
          f"{final['tip_mm']:.2f} mm, axis {final['angle_deg']:.2f} deg")
    return 0
