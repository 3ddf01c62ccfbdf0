"""The Slicer module's robot panel (issue 39, section 4) on Slicer's own MRML with the Qt parts stood in, as
``test_slicer_module.py`` tests the module: its buttons call what ``emreg handeye``, ``emreg robot-target`` and
``emreg robot-go`` call (:mod:`EMRegModule.pipeline.robot_panel`), into the run's output folder, and show the
calibration, the needle guide on its plan and the planned line; Go never moves without the "Move the robot" box.
A dry run against the robot's protocol simulator is in ``test_robot_drive.py``.
"""

from __future__ import annotations

import json
import shutil
import sys
import types
from pathlib import Path

import numpy as np
import pytest

from EMRegModule.io.run_folder import RunFolder
from EMRegModule.pipeline import robot_panel
from EMRegModule.slicer_export.robot_scene import robot_scene_of
from EMRegModule.slicer_export.scene_check import robot_disagreements

sys.path.insert(0, str(Path(__file__).parent))
from handeye_sequences import kinhec_case, tip_error_mm, write_targeting_inputs  # noqa: E402


@pytest.fixture(scope="module")
def recordings(tmp_path_factory):
    """A KinHEC recording (robot log, flange sensor on port 3 beside a reference) and the targeting inputs."""
    folder = tmp_path_factory.mktemp("panel")
    case = kinhec_case("panda", "joint_sinusoid", seed=11, outlier_fraction=0.04)
    case.write_recordings(folder)
    return folder, case, write_targeting_inputs(folder)


def _panel(slicer_app, out: Path):
    module = slicer_app.load_module()
    widget = module.EMRegWidget(parent=types.SimpleNamespace())
    widget.setup()
    widget.ui.outputDirectoryPathLineEdit.currentPath = str(out)
    return widget, widget.ui


def test_the_panel_calibrates_targets_and_shows_the_guide_on_the_plan(slicer_app, recordings, tmp_path):
    folder, case, truth = recordings
    out = tmp_path / "out"
    widget, ui = _panel(slicer_app, out)
    with pytest.raises(Exception, match="robot's log"):
        ui.robotCalibrateButton.click()
    assert "Robot calibration failed." in slicer_app.errors[-1]
    ui.robotPosesPathLineEdit.currentPath = str(folder / "robot.tum")
    ui.flangeRecordingPathLineEdit.currentPath = str(folder / "tracker.csv")
    ui.flangeSensorLineEdit.text = "3"
    ui.robotCalibrateButton.click()
    calibration = json.loads((out / "robot_calibration.json").read_text())
    assert tip_error_mm(np.array(calibration["SensorToFlange"]), case.sensor_to_flange) <= 0.25  # solved, not read
    assert (out / "SensorToFlange.h5").is_file() and "SensorToFlange and TrackerToBase from" in ui.robotStatusLabel.text
    shown = robot_scene_of(RunFolder(None, robot_calibration=calibration))
    assert robot_disagreements(slicer_app.scene, shown) == []

    shutil.copy(folder / "reg" / "registration.json", out / "registration.json")  # the run's registration
    ui.robotReferenceLineEdit.text = str(folder / "reference.csv")
    ui.robotPlanPathLineEdit.currentPath = str(folder / "plan.mrk.json")
    ui.needleGuidePathLineEdit.currentPath = str(folder / "guide.json")
    ui.robotTargetButton.click()
    target = json.loads((out / "robot_target.json").read_text())
    # the flange pose with the TRUE hand-eye and robot-world transforms puts the guide's exit on Entry
    guide_to_base = np.array(target["FlangeToBase"]) @ case.sensor_to_flange @ truth["guide_to_sensor"]
    image_to_base = case.tracker_to_base @ truth["reference_to_tracker"] @ np.linalg.inv(truth["reference_to_image"])
    exit_image = (np.linalg.inv(image_to_base) @ guide_to_base)[:3, 3]
    assert np.linalg.norm(exit_image - truth["entry"]) <= 3.0 * target["predicted_error_mm"]["total"]
    assert "predicted error at the target" in ui.robotStatusLabel.text
    shown = robot_scene_of(RunFolder(None, robot_calibration=calibration, robot_target=target))
    assert robot_disagreements(slicer_app.scene, shown) == []
    assert slicer_app.scene.GetFirstNodeByName("EMReg robot plan").GetNumberOfControlPoints() == 2
    widget.cleanup()


def test_go_moves_the_robot_only_with_the_execute_box_checked(slicer_app, tmp_path, monkeypatch):
    calls = []

    def robot_go(robot_url, tracker_url, target, settings, sensor, reference_sensor, igtl_port, out, execute, say):
        calls.append((robot_url, tracker_url, Path(target).name, execute))
        say("robot-go: dry run, nothing moved" if not execute else "robot-go: on the plan")

    monkeypatch.setattr(robot_panel, "robot_go", robot_go)
    out = tmp_path / "out"
    widget, ui = _panel(slicer_app, out)
    ui.robotUrlLineEdit.text = "franka://172.16.0.2"
    ui.robotTrackerUrlLineEdit.text = "trakstar:///dev/ttyUSB0"
    with pytest.raises(Exception, match="target the plan first"):
        ui.robotGoButton.click()
    assert calls == []
    out.mkdir(exist_ok=True)
    (out / "robot_target.json").write_text("{}")
    assert not ui.robotExecuteCheckBox.checked  # the panel opens on a dry run
    ui.robotGoButton.click()
    assert calls[-1] == ("franka://172.16.0.2", "trakstar:///dev/ttyUSB0", "robot_target.json", False)
    assert "dry run" in ui.robotStatusLabel.text
    ui.robotExecuteCheckBox.checked = True
    ui.robotGoButton.click()
    assert calls[-1][3] is True
    for not_explicit in ("yes", 1, None):  # only True moves
        widget.robot.go_to_target("franka://172.16.0.2", "trakstar:///dev/ttyUSB0", out, execute=not_explicit)
        assert calls[-1][3] is False
    widget.cleanup()
