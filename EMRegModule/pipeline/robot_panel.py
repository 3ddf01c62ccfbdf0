"""The 3D Slicer module's robot panel without its widgets (issue 39): calibrate, target, go.

Each step calls what its command calls, into the same output folder (the run's, so that the report and
``EMReg.mrb`` pick the files up): :func:`~EMRegModule.pipeline.robot.calibrate_from_recordings` (``emreg handeye``),
:func:`~EMRegModule.pipeline.robot.target_from_files` (``emreg robot-target``) and
:func:`~EMRegModule.pipeline.robot_live.robot_go` (``emreg robot-go``), then shows the robot's nodes
(:mod:`EMRegModule.slicer_export.robot_scene`: ``SensorToFlange``, ``TrackerToBase``, the needle guide on its plan and
the planned line) on the scene given.

Go is a dry run (it says the planned motion, nothing moves) unless ``execute`` is exactly ``True``: the panel's
"Move the robot" check box, the ``--execute`` of the command line. No Qt here: the panel's buttons (``EMReg.py``)
call these methods; the tests call them too.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

from ..errors import EMRegError
from ..io.run_folder import RunFolder
from ..names import DEFAULT_IGTL_PORT, ROBOT_CALIBRATION_JSON, ROBOT_TARGET_JSON
from ..settings import Settings, load_settings
from ..slicer_export.robot_scene import build_robot_scene, robot_scene_of
from .robot import calibrate_from_recordings, describe_calibration, target_from_files
from .robot_live import robot_go


class RobotPanelLogic:
    """The robot panel's state and steps. ``settings``: the case's (default: EMReg's defaults); ``scene``: the MRML
    scene to show the robot's nodes on (None: none shown). ``messages``: what the steps said (the planned motion of
    a dry run, the measurements of a move), newest last; ``calibration``, ``target``, ``go``: the documents written
    (``robot_calibration.json``, ``robot_target.json``, robot-go's result), None before."""

    def __init__(self, settings: Settings | None = None, scene: Any = None) -> None:
        self.settings = settings if settings is not None else load_settings(None)
        self.scene = scene
        self.nodes: dict[str, Any] = {}
        self.messages: list[str] = []
        self.calibration: dict[str, Any] | None = None
        self.target: dict[str, Any] | None = None
        self.go: dict[str, Any] | None = None

    @staticmethod
    def _folder(output_folder: str | os.PathLike[str] | None) -> Path:
        if not output_folder:
            raise EMRegError("choose an output folder first (the robot's files go beside the run's)")
        folder = Path(output_folder)
        folder.mkdir(parents=True, exist_ok=True)
        return folder

    def calibrate(self, robot_poses: str, tracker_recording: str, output_folder: str | os.PathLike[str],
                  sensor: str | int | None = None) -> dict[str, Any]:
        """``emreg handeye``: ``SensorToFlange`` and ``TrackerToBase`` from the robot's log and the flange sensor's
        recording, written as ``robot_calibration.json`` (and the ``.h5``) into the output folder and shown."""
        if not robot_poses or not tracker_recording:
            raise EMRegError("choose the robot's log (TUM or PLUS) and the flange sensor's recording")
        out = self._folder(output_folder)
        result, self.calibration = calibrate_from_recordings(robot_poses, tracker_recording, out, self.settings,
                                                             sensor or None)
        self.messages.append(describe_calibration(result, self.calibration, out))
        self.show()
        return self.calibration

    def target_plan(self, registration: str | os.PathLike[str], reference: str, plan: str, guide: str,
                   output_folder: str | os.PathLike[str], robot_calibration: str | os.PathLike[str] | None = None,
                   reference_sensor: int | None = None) -> dict[str, Any]:
        """``emreg robot-target``: the flange pose that puts the guide on the plan, from the registration, the
        robot calibration (default: the output folder's ``robot_calibration.json``), the reference sensor now (a
        recording or a live URL), the plan and the guide; written as ``robot_target.json`` and shown (the guide
        on the plan, the planned line)."""
        out = self._folder(output_folder)
        calibration = Path(robot_calibration) if robot_calibration else out / ROBOT_CALIBRATION_JSON
        if not calibration.is_file():
            raise EMRegError(f"{calibration}: no robot calibration; calibrate first")
        for value, what in ((registration, "the registration (registration.json)"), (reference, "the reference"),
                            (plan, "the plan"), (guide, "the needle guide")):
            if not value:
                raise EMRegError(f"choose {what} first")
        answer, self.target = target_from_files(registration, calibration, reference, plan, guide, out, self.settings,
                                                reference_sensor)
        self.messages.append(f"FlangeToBase for the plan: guide exit on Entry, {answer.depth_mm:.1f} mm to the "
                             f"target; predicted error at the target {answer.predicted_error_mm['total']:.2f} mm RMS")
        self.show()
        return self.target

    def go_to_target(self, robot_url: str, tracker_url: str, output_folder: str | os.PathLike[str],
                   execute: bool = False, sensor: int | None = None, reference_sensor: int | None = None,
                   igtl_port: int | None = DEFAULT_IGTL_PORT) -> dict[str, Any] | None:
        """``emreg robot-go`` on the output folder's ``robot_target.json``: a dry run (the planned motion in
        :attr:`messages`, nothing moves, None returned) unless ``execute`` is ``True``; then the guide is moved,
        measured and corrected, and the result is written as ``robot_go.json`` and returned."""
        if not robot_url or not tracker_url:
            raise EMRegError("give the robot's URL (franka://HOST) and the tracker's (trakstar:, aurora:, igtl:)")
        out = self._folder(output_folder)
        if not (out / ROBOT_TARGET_JSON).is_file():
            raise EMRegError(f"{out / ROBOT_TARGET_JSON}: no target; target the plan first")
        moving = execute is True
        self.go = robot_go(robot_url, tracker_url, out / ROBOT_TARGET_JSON, self.settings, sensor, reference_sensor,
                           igtl_port, out, moving, self.messages.append)
        return self.go

    def show(self) -> dict[str, Any]:
        """The robot's nodes on the scene (none without a scene): the calibration and, with a target, the needle guide
        on its plan and the planned line."""
        content = robot_scene_of(RunFolder(None, robot_calibration=self.calibration, robot_target=self.target))
        if self.scene is None or content is None:
            return {}
        return build_robot_scene(self.scene, content, self.nodes)

    def describe(self) -> str:
        """The panel's status: the last messages (a dry run's planned motion among them)."""
        return "\n".join(self.messages[-8:])
