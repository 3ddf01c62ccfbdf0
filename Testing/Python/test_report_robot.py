"""The robot in the report and in EMReg.mrb (issue 39, section 4): a run folder holding ``emreg handeye``'s
``robot_calibration.json`` (from a KinHEC recording with a clock offset and wrong poses), ``emreg robot-target``'s
``robot_target.json`` and a robot-go result.

- the report's robot section: the hand-eye residuals per sample (used against left out, with the reasons), the
  clock-offset fit with its valley at the chosen ``time_offset_s``, the flange pose for the plan and the final
  guide-to-plan error, drawn offscreen as the other figures;
- without the recordings the calibration names (moved, or not the same bytes) the figures are left out, saying why;
- the bundle carries ``SensorToFlange``, ``TrackerToBase``, the guide on its plan and the planned line, as Slicer
  reads them (:func:`~EMRegModule.slicer_export.scene_check.robot_disagreements`).
"""

from __future__ import annotations

import json
import shutil
import sys
from pathlib import Path

import numpy as np
import pytest

from EMRegModule.cli.main import main
from EMRegModule.io.run_folder import read_run_folder
from EMRegModule.names import BUNDLE_MRB, REPORT_FIGURES, REPORT_HTML, ROBOT_GO_JSON
from EMRegModule.report.inputs import load_report_inputs
from EMRegModule.report.robot_inputs import load_robot_fit

sys.path.insert(0, str(Path(__file__).parent))
from handeye_sequences import kinhec_case, write_targeting_inputs  # noqa: E402

#: A robot-go result as ``emreg robot-go --out`` writes it (every measurement, mm and degrees).
GO = {"on_plan": True, "corrections": 2, "tolerance_mm": 0.5, "tolerance_deg": 0.5,
      "predicted_error_mm": {"total": 0.4},
      "measurements": [{"step": 0, "exit_mm": 2.31, "lateral_mm": 2.1, "angle_deg": 1.42, "tip_mm": 3.87},
                       {"step": 1, "exit_mm": 0.61, "lateral_mm": 0.5, "angle_deg": 0.38, "tip_mm": 0.72},
                       {"step": 2, "exit_mm": 0.18, "lateral_mm": 0.12, "angle_deg": 0.09, "tip_mm": 0.23}]}


@pytest.fixture(scope="module")
def robot_run(tmp_path_factory):
    """One output folder with the calibration, the target and a robot-go result; the recordings beside it."""
    folder = tmp_path_factory.mktemp("robot-run")
    case = kinhec_case("panda", "joint_sinusoid", seed=11, outlier_fraction=0.04)
    robot, tracker = case.write_recordings(folder)
    out = folder / "out"
    assert main(["handeye", "--robot-poses", str(robot), "--tracker", str(tracker), "--sensor", "3", "--out",
                 str(out), "--quiet"]) == 0
    write_targeting_inputs(folder)
    assert main(["robot-target", "--registration", str(folder / "reg" / "registration.json"), "--robot-calibration",
                 str(out / "robot_calibration.json"), "--reference", str(folder / "reference.csv"), "--plan",
                 str(folder / "plan.mrk.json"), "--tool", str(folder / "guide.json"), "--out", str(out),
                 "--quiet"]) == 0
    (out / ROBOT_GO_JSON).write_text(json.dumps({**GO, "final": GO["measurements"][-1]}))
    return folder, out, case


def test_the_report_shows_the_robot(robot_run, capsys):
    folder, out, case = robot_run
    report = folder / "report"
    shutil.copytree(out, report)
    assert main(["report", str(report), "--quiet"]) == 0, capsys.readouterr().err
    page = (report / REPORT_HTML).read_text()
    for name in ("robot_residuals", "robot_clock", "robot_go"):
        assert (report / REPORT_FIGURES / f"{name}.png").stat().st_size > 5000, name
        assert f'id="fig-{name}"' in page
    document = json.loads((out / "robot_calibration.json").read_text())
    assert "<h2>Robot</h2>" in page and f"{document['time_offset_s']:.4f} s" in page
    for reason in document["frames"]["rejected_by_reason"]:
        assert reason.replace("'", "&#x27;") in page
    assert "lands 0.23 mm from the Target" in page and "0.09 degrees off the planned line" in page
    target = json.loads((out / "robot_target.json").read_text())
    assert f"{target['predicted_error_mm']['total']:.2f}" in page


def test_the_clock_offset_fit_has_its_valley_at_the_chosen_offset(robot_run):
    """The residual of the samples used is smallest at the offset the calibration chose (within one step of the
    scan) and grows on both sides; the samples it left out are the file's, and every injected glitch is among them;
    the used samples' residuals are those robot_calibration.json reports."""
    _, out, case = robot_run
    fit, why = load_robot_fit(load_report_inputs(out, read_image=False))
    assert why is None
    step = fit.offsets_s[1] - fit.offsets_s[0]
    best = int(np.nanargmin(fit.offset_residual_mm))
    assert abs(fit.offsets_s[best] - fit.time_offset_s) <= step
    assert fit.offset_residual_mm[0] > 5 * fit.offset_residual_mm[best] < fit.offset_residual_mm[-1] / 5
    document = json.loads((out / "robot_calibration.json").read_text())
    assert np.count_nonzero(fit.rejected) == document["frames"]["rejected"]
    assert set(np.nonzero(case.outlier)[0]) <= set(np.nonzero(fit.rejected)[0])
    used = ~fit.rejected & np.isfinite(fit.translation_mm)
    rms = float(np.sqrt(np.mean(fit.translation_mm[used] ** 2)))
    assert rms == pytest.approx(document["residuals"]["translation_mm"]["rms"], rel=0.02)


def test_without_the_recordings_the_figures_are_left_out_saying_why(robot_run, tmp_path, capsys):
    folder, out, _ = robot_run
    moved = tmp_path / "out"
    shutil.copytree(out, moved)
    tracker = folder / "tracker.csv"
    kept = tracker.read_bytes()
    try:
        tracker.write_bytes(kept + b"\n")  # not the bytes the calibration used
        assert main(["report", str(moved), "--quiet"]) == 0, capsys.readouterr().err
    finally:
        tracker.write_bytes(kept)
    page = (moved / REPORT_HTML).read_text()
    assert not (moved / REPORT_FIGURES / "robot_clock.png").exists()
    assert "figures not drawn" in page and "is not the tracker recording the calibration used" in page
    assert (moved / REPORT_FIGURES / "robot_go.png").exists()


def test_the_bundle_carries_the_calibration_and_the_guide_on_its_plan(robot_run, slicer_core, tmp_path):
    import slicer.util

    from EMRegModule.slicer_export.bundle import write_run_bundle
    from EMRegModule.slicer_export.mrml import SlicerScene
    from EMRegModule.slicer_export.robot_scene import robot_scene_of
    from EMRegModule.slicer_export.scene_check import robot_disagreements

    _, out, _ = robot_run
    folder = tmp_path / "out"
    shutil.copytree(out, folder)
    path, message, sha256 = write_run_bundle(folder)
    assert path == folder / BUNDLE_MRB and sha256, message
    scene = SlicerScene()
    scene.read_bundle(path)
    content = robot_scene_of(read_run_folder(folder, None))
    assert robot_disagreements(scene.scene, content) == []
    model = scene.node("EMReg needle guide")
    assert model.GetPolyData().GetNumberOfPoints() > 0
    # the check sees a wrong calibration, and a guide moved off its plan in the scene
    content.tracker_to_base = content.tracker_to_base.copy()
    content.tracker_to_base[0, 3] += 0.5
    guide = scene.node("NeedleGuideToRAS")
    moved = slicer.util.arrayFromTransformMatrix(guide)
    moved[:3, 3] += [0.0, 0.3, 0.0]
    guide.SetMatrixTransformToParent(slicer.util.vtkMatrixFromArray(moved))
    found = robot_disagreements(scene.scene, content)
    assert any("TrackerToBase" in f for f in found) and any("from Target" in f for f in found)
