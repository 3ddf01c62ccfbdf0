"""A plan and the guidance numbers (issue 38): the pure geometry, the plan file, and ``emreg navigate`` / ``emreg run``
with ``--plan`` as a user runs them on the small simulated case navigated with a needle (tip 118 mm along +x;
see :mod:`test_navigate_tool` for the case and the truth)."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from test_navigate_tool import (
    NEEDLE_TIP_MM,
    needle,  # noqa: F401 - the module fixture, shared
    needle_tip_to_probe,
    read_navigation,
    tip_positions,
    write_plus_device_set,
)

from EMRegModule.cli.main import main
from EMRegModule.core.guidance import RADIUS_95_PER_RMS, TOOL_ROTATION_SIGMA_DEG, Plan, guidance, shaft_in_tip
from EMRegModule.core.navigation import navigate_recording
from EMRegModule.core.plan import check_plan_in_image
from EMRegModule.core.transforms import make_transform, random_rotation
from EMRegModule.errors import EMRegError
from EMRegModule.io.navigation_csv import GUIDANCE_COLUMNS, NAVIGATION_HEADER
from EMRegModule.io.plan_markups import read_plan
from EMRegModule.io.recording import read_recording
from EMRegModule.io.registration_files import read_registration
from EMRegModule.pipeline.navigating import error_model
from EMRegModule.settings import Settings, load_settings

# --- the geometry -------------------------------------------------------------------------------------


def _perpendicular(u: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    v = np.cross(u, rng.normal(size=3))
    return v / np.linalg.norm(v)


def test_guidance_numbers_of_tips_placed_about_the_planned_line():
    """Tips placed at a known depth ``a`` before the target along u and ``b`` off the line: the numbers are those
    placements (to_go = a, lateral = |b|, distance = hypot(a, b)), negative to_go past the target."""
    rng = np.random.default_rng(5)
    target = np.array([10.0, -40.0, 120.0])
    u = rng.normal(size=3)
    u /= np.linalg.norm(u)
    plan = Plan(target, target - 80.0 * u)
    depth = rng.uniform(-30.0, 90.0, 50)
    off = rng.uniform(0.0, 12.0, 50)
    poses = np.tile(np.eye(4), (50, 1, 1))
    for k in range(50):
        poses[k, :3, 3] = target - depth[k] * u + off[k] * _perpendicular(u, rng)
    numbers = guidance(poses, plan)
    np.testing.assert_allclose(numbers.to_go_mm, depth, atol=1e-9)
    np.testing.assert_allclose(numbers.lateral_mm, off, atol=1e-9)
    np.testing.assert_allclose(numbers.target_distance_mm, np.hypot(depth, off), atol=1e-9)
    assert np.all(np.isnan(numbers.angle_deg))  # no tool axis given


def test_angle_is_the_shaft_against_the_plan_whatever_the_tip_frame():
    """A tool whose tip frame is turned against its sensor (a PLUS file's identity, a pivot's +Z along the shaft):
    the angle is the shaft's (sensor -> tip), tilted by a known angle from u."""
    rng = np.random.default_rng(9)
    tip_mm = np.array([118.0, 0.0, 0.0])
    u = np.array([0.0, 0.0, 1.0])
    plan = Plan(np.zeros(3), -50.0 * u)
    for tip_frame in (np.eye(3), random_rotation(rng)):
        tip_to_probe = make_transform(tip_frame, tip_mm)
        shaft = shaft_in_tip(tip_to_probe)
        for tilt_deg in (0.0, 7.5, 30.0, 120.0):
            tilt = np.radians(tilt_deg)
            # the sensor's +x (its shaft) tilted from u about y, spun about u
            spin = make_transform(_rotation_z(rng.uniform(0, 2 * np.pi)), [0, 0, 0])[:3, :3]
            probe_to_image = np.eye(4)
            probe_to_image[:3, :3] = spin @ np.array([[np.sin(tilt), 0, -np.cos(tilt)], [0, 1, 0],
                                                      [np.cos(tilt), 0, np.sin(tilt)]])
            tip_to_image = probe_to_image @ tip_to_probe
            assert guidance(tip_to_image, plan, shaft).angle_deg[0] == pytest.approx(tilt_deg, abs=1e-6)


def _rotation_z(angle: float) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def test_a_target_alone_has_only_its_distance_and_a_tip_at_the_sensor_no_axis():
    numbers = guidance(make_transform(np.eye(3), [3.0, 4.0, 12.0]), Plan(np.zeros(3)), np.array([1.0, 0, 0]))
    assert numbers.target_distance_mm[0] == pytest.approx(13.0)
    assert all(np.isnan(getattr(numbers, name)[0]) for name in ("lateral_mm", "angle_deg", "to_go_mm"))
    assert shaft_in_tip(None) is None and shaft_in_tip(np.eye(4)) is None


# --- the plan file -----------------------------------------------------------------------------------


def write_plan(path: Path, points: list[tuple[str, np.ndarray]], kind: str = "Fiducial", system: str = "LPS") -> Path:
    """A Slicer markups file of ``kind`` with ``points`` (label, LPS mm), written in ``system`` (LPS or RAS)."""
    flip = np.array([-1.0, -1.0, 1.0]) if system == "RAS" else np.ones(3)
    path.write_text(json.dumps({"markups": [{
        "type": kind, "coordinateSystem": system, "coordinateUnits": "mm",
        "controlPoints": [{"id": str(k + 1), "label": label, "position": list(np.asarray(p, dtype=float) * flip),
                           "positionStatus": "defined"} for k, (label, p) in enumerate(points)]}]}))
    return path


ENTRY, TARGET = np.array([10.0, 20.0, 30.0]), np.array([12.0, 25.0, 90.0])


@pytest.mark.parametrize("system", ["LPS", "RAS"])
def test_a_slicer_line_is_entry_then_target_in_lps(tmp_path, system):
    plan = read_plan(write_plan(tmp_path / "plan.mrk.json", [("L-1", ENTRY), ("L-2", TARGET)], "Line", system))
    np.testing.assert_allclose(plan.entry_mm, ENTRY)
    np.testing.assert_allclose(plan.target_mm, TARGET)
    assert plan.coordinate_system == system


def test_labelled_points_are_taken_by_their_labels_in_any_order(tmp_path):
    plan = read_plan(write_plan(tmp_path / "p.mrk.json", [("other", ENTRY + 5), (" target", TARGET), ("Entry", ENTRY)]))
    np.testing.assert_allclose(plan.entry_mm, ENTRY)
    np.testing.assert_allclose(plan.target_mm, TARGET)
    line = read_plan(write_plan(tmp_path / "l.mrk.json", [("Target", TARGET), ("Entry", ENTRY)], "Line"))
    np.testing.assert_allclose(line.entry_mm, ENTRY)


def test_a_single_point_is_a_target_alone(tmp_path):
    plan = read_plan(write_plan(tmp_path / "p.mrk.json", [("T7", TARGET)], system="RAS"))
    np.testing.assert_allclose(plan.target_mm, TARGET)
    assert plan.entry_mm is None and plan.direction is None


@pytest.mark.parametrize(("points", "kind", "says"), [
    ([("Target", TARGET), ("target", ENTRY)], "Fiducial", "2 points are labelled 'Target'"),
    ([("Entry", ENTRY), ("Entry", TARGET), ("Target", TARGET + 9)], "Fiducial", "labelled 'Entry'"),
    ([("Entry", ENTRY), ("X", TARGET)], "Fiducial", "none labelled Target"),
    ([("A", ENTRY), ("B", TARGET)], "Fiducial", "none labelled Target"),
    ([], "Fiducial", "no defined control point"),
    ([("L-1", ENTRY), ("L-2", TARGET), ("L-3", TARGET + 1)], "Line", "3 defined control point"),
    ([("Entry", TARGET + 0.2), ("Target", TARGET)], "Line", "zero-length"),
    ([("Entry", TARGET), ("Target", TARGET)], "Fiducial", "zero-length"),
])
def test_a_plan_without_the_needed_points_is_refused_naming_the_file(tmp_path, points, kind, says):
    path = write_plan(tmp_path / "plan.mrk.json", points, kind)
    with pytest.raises(EMRegError, match=says) as refused:
        read_plan(path)
    assert str(path) in str(refused.value) and "\n" not in str(refused.value)


def test_a_plan_outside_the_ct_is_refused():
    """A CT whose index axes are turned (i runs along -y) and anisotropic: points placed at known continuous indices
    (``origin + direction @ (index * spacing)``) are inside up to half a voxel beyond the first and last centres."""
    geometry = {"size": [100, 80, 60], "spacing": [1.0, 1.0, 2.0], "origin": [-50.0, -40.0, 0.0],
                "direction": [0, 1, 0, -1, 0, 0, 0, 0, 1]}
    direction = np.array(geometry["direction"], dtype=float).reshape(3, 3)

    def at(index: tuple[float, float, float]) -> np.ndarray:
        return np.array(geometry["origin"]) + direction @ (np.array(index) * geometry["spacing"])

    check_plan_in_image(Plan(at((20, 30, 40)), at((99.4, -0.4, 59.4)), "p.mrk.json"), geometry)
    with pytest.raises(EMRegError, match="Entry .* outside"):
        check_plan_in_image(Plan(at((20, 30, 40)), at((-0.6, 10, 5)), "p.mrk.json"), geometry)
    with pytest.raises(EMRegError, match="Target .* outside"):
        check_plan_in_image(Plan(at((20, 30, 59.6)), None, "p.mrk.json"), geometry)


def test_navigation_plan_in_case_toml_leaves_the_settings_digest_of_files_without_it(tmp_path):
    """``[navigation] plan`` is a new key: settings that do not give it keep their JSON and digest (the provenance of
    every earlier output), those that do carry it."""
    assert "plan" not in Settings().to_json()["navigation"]
    (tmp_path / "case.toml").write_text('[navigation]\nplan = "plan.mrk.json"\n')
    given = load_settings(tmp_path / "case.toml")
    assert given.navigation.plan == "plan.mrk.json" and given.to_json()["navigation"]["plan"] == "plan.mrk.json"
    assert given.digest() != Settings().digest()


# --- emreg navigate --plan on a replay ----------------------------------------------------------------


def plan_at_target(path: Path, truth: dict, label: str = "T1", entry_offset: tuple = (0.0, 0.0, 40.0),
                   system: str = "RAS") -> Path:
    """A line plan ending at the case's target ``label``, its entry ``entry_offset`` (LPS mm) away."""
    target = next(np.array(t["position"]) for t in truth["targets"] if t["label"] == label)
    return write_plan(path, [("Entry", target + np.array(entry_offset)), ("Target", target)], "Line", system)


def _navigate(replay: dict, out: Path, *extra: str) -> int:
    """``emreg navigate`` of the needle's replay (the ``needle`` fixture) with the case's registration."""
    return main(["navigate", "--registration", str(replay["out"] / "registration.json"), "--source",
                 f"replay:{replay['recording']}", "--out", str(out), *extra])


def test_navigate_with_a_plan_writes_each_rows_guidance_from_its_own_tip(needle, tmp_path, capsys):  # noqa: F811
    """Every row's columns are those of its own tip and the plan (recomputed here from the row), the angle that of
    the needle's shaft (the registration's sensor pose, sensor -> tip); against the simulated truth (the true
    ReferenceToImage on the same samples) each number is off by at most the tip's own error (triangle
    inequality), which stays within the registration's error."""
    truth = needle["truth"]
    plan_file = plan_at_target(tmp_path / "plan.mrk.json", truth)
    tool = write_plus_device_set(tmp_path / "needle.xml", needle_tip_to_probe(), error_mm=0.4)
    assert _navigate(needle, tmp_path / "nav", "--tool", str(tool), "--plan", str(plan_file)) == 0
    printed = capsys.readouterr().out
    header, rows = read_navigation(tmp_path / "nav" / "navigation.csv")
    assert header == NAVIGATION_HEADER.split(",") + list(GUIDANCE_COLUMNS)
    _, tip, ok = tip_positions(rows)
    plan = read_plan(plan_file)
    u = plan.direction
    to_target = plan.target_mm - tip
    columns = {name: np.array([float(r[name]) for r in rows]) for name in GUIDANCE_COLUMNS}
    np.testing.assert_allclose(columns["target_distance_mm"], np.linalg.norm(to_target, axis=1), atol=2e-4)
    np.testing.assert_allclose(columns["to_go_mm"], to_target @ u, atol=2e-4)
    np.testing.assert_allclose(columns["lateral_mm"], np.linalg.norm(np.cross(to_target, u), axis=1), atol=2e-4)
    registration = read_registration(needle["out"] / "registration.json")
    recording = read_recording(needle["recording"])
    sensor = navigate_recording(recording, registration.reference_to_image, 1, 2)
    shaft = sensor.probe_to_image[:, :3, 0]  # the needle's tip is on its sensor's +x
    np.testing.assert_allclose(columns["angle_deg"], np.degrees(np.arccos(np.clip(shaft @ u, -1, 1))), atol=1e-3)
    # against the truth
    true_tip = navigate_recording(recording, np.array(truth["ReferenceToImage"]), 1, 2,
                                  needle_tip_to_probe()).position_mm
    tip_error = np.linalg.norm(tip - true_tip, axis=1)
    true_to_target = plan.target_mm - true_tip
    assert np.all(np.abs(columns["target_distance_mm"] - np.linalg.norm(true_to_target, axis=1))
                  <= tip_error + 2e-4)
    assert np.all(np.abs(columns["to_go_mm"] - true_to_target @ u) <= tip_error + 2e-4)
    predicted = np.sqrt(error_model(registration, Settings()).budget(tip[ok]).registration_ms)
    assert np.all(tip_error[ok] < 3.0 * predicted)
    # navigation.json: the predicted error at the target, with the tool's Error, and the closest approach
    document = json.loads((tmp_path / "nav" / "navigation.json").read_text())
    at_target = float(error_model(registration, Settings()).budget(plan.target_mm[None]).rms_mm[0])
    prediction = document["predicted_at_target"]
    lever = np.sqrt(2) * NEEDLE_TIP_MM[0] * np.radians(TOOL_ROTATION_SIGMA_DEG)
    assert prediction["rms_mm"] == pytest.approx(np.sqrt(at_target**2 + 0.4**2 + lever**2), abs=1e-3)
    assert prediction["tool_rms_mm"] == 0.4 and prediction["lever_rms_mm"] == pytest.approx(lever, abs=1e-3)
    assert prediction["radius_95_mm"] == pytest.approx(RADIUS_95_PER_RMS * prediction["rms_mm"], abs=1e-3)
    assert f"target {prediction['rms_mm']:.1f} mm predicted (95 %: {prediction['radius_95_mm']:.1f} mm)" in printed
    closest = document["closest_approach"]
    best = int(np.argmin(np.where(ok, columns["target_distance_mm"], np.inf)))
    assert closest["target_distance_mm"] == pytest.approx(columns["target_distance_mm"][best], abs=1e-3)
    assert closest["time_s"] == pytest.approx(float(rows[best]["time_s"]), abs=1e-3)
    assert document["plan"]["declared_coordinate_system"] == "RAS"
    assert document["tool"]["tip_mm"] == list(NEEDLE_TIP_MM)


def test_the_error_at_the_target_measured_at_its_dwells_against_the_prediction(needle, tmp_path):  # noqa: F811
    """A plan on each target in turn; at every dwell on it the median tip's distance to it is the error measured at
    the target. Their RMS over the 6 dwells is the predicted RMS within sampling (0.6x to 1.4x): the simulated
    needle's tip is exact (its file says Error 0), so the prediction is the error model's at the target plus the
    sensor's orientation error over the 118 mm lever arm, without which it would be about half what is measured."""
    truth = needle["truth"]
    tool = write_plus_device_set(tmp_path / "needle.xml", needle_tip_to_probe(), error_mm=0.0)
    measured, predicted = [], []
    for label in ("T1", "T2", "T3"):
        plan_file = plan_at_target(tmp_path / f"{label}.mrk.json", truth, label)
        out = tmp_path / label
        assert _navigate(needle, out, "--quiet", "--tool", str(tool), "--plan", str(plan_file)) == 0
        _, rows = read_navigation(out / "navigation.csv")
        time_s, _, ok = tip_positions(rows)
        distance = np.array([float(r["target_distance_mm"]) for r in rows])
        at_target = [np.median(distance[(time_s >= d["start_s"]) & (time_s <= d["end_s"]) & ok])
                     for d in needle["dwells"] if d["name"] == label]
        prediction = json.loads((out / "navigation.json").read_text())["predicted_at_target"]
        measured += at_target
        predicted += [prediction["rms_mm"]] * len(at_target)
    ratio = np.sqrt(np.mean(np.square(measured))) / np.sqrt(np.mean(np.square(predicted)))
    assert 0.6 <= ratio <= 1.4, (measured, predicted, ratio)  # measured here: 0.94 mm RMS, predicted 0.85 mm


def test_a_target_only_plan_leaves_lateral_angle_and_to_go_empty(needle, tmp_path):  # noqa: F811
    target = np.array(needle["truth"]["targets"][1]["position"])
    plan_file = write_plan(tmp_path / "t.mrk.json", [("T2", target)])
    tool = write_plus_device_set(tmp_path / "needle.xml", needle_tip_to_probe())
    assert _navigate(needle, tmp_path / "nav", "--quiet", "--tool", str(tool), "--plan", str(plan_file)) == 0
    _, rows = read_navigation(tmp_path / "nav" / "navigation.csv")
    assert all(r["lateral_mm"] == r["angle_deg"] == r["to_go_mm"] == "" for r in rows)
    _, tip, _ = tip_positions(rows)
    np.testing.assert_allclose([float(r["target_distance_mm"]) for r in rows], np.linalg.norm(tip - target, axis=1),
                               atol=2e-4)


def test_a_plan_without_a_tool_navigates_the_sensor_with_no_angle(needle, tmp_path):  # noqa: F811
    plan_file = plan_at_target(tmp_path / "plan.mrk.json", needle["truth"])
    assert _navigate(needle, tmp_path / "nav", "--quiet", "--plan", str(plan_file)) == 0
    header, rows = read_navigation(tmp_path / "nav" / "navigation.csv")
    assert header[-4:] == list(GUIDANCE_COLUMNS)
    assert all(r["angle_deg"] == "" and r["lateral_mm"] != "" for r in rows)
    assert json.loads((tmp_path / "nav" / "navigation.json").read_text())["tool"] is None


@pytest.mark.parametrize(("make", "says"), [
    (lambda folder, truth: plan_at_target(folder / "p.mrk.json", truth, entry_offset=(0.0, 0.0, 400.0)),
     "Entry .* outside"),
    (lambda folder, truth: write_plan(folder / "p.mrk.json", [("Target", [0, 0, 0]), ("Target", [1, 1, 1])]),
     "labelled 'Target'"),
    (lambda folder, truth: plan_at_target(folder / "p.mrk.json", truth, entry_offset=(0.0, 0.0, 0.0)),
     "zero-length"),
])
def test_a_bad_plan_exits_2_with_one_line_and_writes_nothing(needle, tmp_path, capsys, make, says):  # noqa: F811
    plan_file = make(tmp_path, needle["truth"])
    code = _navigate(needle, tmp_path / "nav", "--quiet", "--plan", str(plan_file))
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and str(plan_file) in err[0], err
    import re

    assert re.search(says, err[0])
    assert not (tmp_path / "nav" / "navigation.csv").exists() and not (tmp_path / "nav" / "navigation.json").exists()


# --- emreg run --plan and [navigation] plan -------------------------------------------------------------


def test_emreg_run_with_a_plan_in_case_toml_and_on_the_command_line(small_case, tmp_path, capsys):
    """A user's run: ``[navigation] plan`` in case.toml gives the guidance columns, navigation.json and the summary
    line; ``--plan`` on the command line wins over it; the run's other outputs stay."""
    case = tmp_path / "case"
    shutil.copytree(small_case, case)
    truth = json.loads((case / "truth.json").read_text())
    plan_at_target(case / "plan.mrk.json", truth, "T2")
    (case / "case.toml").write_text((case / "case.toml").read_text() + '\n[navigation]\nplan = "plan.mrk.json"\n')
    assert main(["run", str(case), "--out", str(tmp_path / "out")]) == 0
    printed = capsys.readouterr().out
    assert "closest" in printed and "mm predicted (95 %:" in printed
    header, _ = read_navigation(tmp_path / "out" / "navigation.csv")
    assert header[-4:] == list(GUIDANCE_COLUMNS)
    document = json.loads((tmp_path / "out" / "navigation.json").read_text())
    np.testing.assert_allclose(document["plan"]["target_mm"], truth["targets"][1]["position"], atol=1e-3)
    run = json.loads((tmp_path / "out" / "run.json").read_text())
    assert "navigation.json" in run["outputs"] and "plan" in run["inputs"]
    html = (tmp_path / "out" / "report.html").read_text(encoding="utf-8")  # the report's guidance section
    section = html[html.index("<h2>Guidance to the plan</h2>"):]
    section = section[:section.index("<h2>", 5)]
    closest = document["closest_approach"]
    assert f"<td class=\"l\">{closest['target_distance_mm']:.2f}</td>" in section
    assert f"<td class=\"l\">{closest['time_s']:.2f}</td>" in section
    assert 'id="fig-guidance_approach"' in section and 'id="fig-guidance_plan_view"' in section
    assert 'id="fig-guidance_ct"' in section  # the planned line in two CT planes
    other = plan_at_target(tmp_path / "other.mrk.json", truth, "T3")
    assert main(["run", str(case), "--out", str(tmp_path / "out2"), "--plan", str(other), "--quiet"]) == 0
    document = json.loads((tmp_path / "out2" / "navigation.json").read_text())
    np.testing.assert_allclose(document["plan"]["target_mm"], truth["targets"][2]["position"], atol=1e-3)


def test_emreg_run_refuses_a_plan_outside_the_ct_before_writing_any_output(small_case, tmp_path, capsys):
    case = tmp_path / "case"
    shutil.copytree(small_case, case)
    truth = json.loads((case / "truth.json").read_text())
    plan_file = plan_at_target(tmp_path / "far.mrk.json", truth, entry_offset=(500.0, 0.0, 0.0))
    code = main(["run", str(case), "--out", str(tmp_path / "out"), "--plan", str(plan_file), "--quiet"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and "outside" in err[0]
    assert not (tmp_path / "out" / "markers.json").exists()


def test_emreg_run_refuses_a_plan_with_nothing_to_register(small_case, tmp_path, capsys):
    case = tmp_path / "case"
    shutil.copytree(small_case, case)
    (case / "calibration.csv").unlink()
    plan_file = plan_at_target(tmp_path / "plan.mrk.json", json.loads((case / "truth.json").read_text()))
    code = main(["run", str(case), "--out", str(tmp_path / "out"), "--plan", str(plan_file), "--quiet"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and "needs a registration" in err[0]
    assert not (tmp_path / "out" / "markers.json").exists()


# --- the 3D Slicer module's plan selector ----------------------------------------------------------------


def test_slicer_panel_plan_selector_gives_the_guidance_of_a_markups_line(slicer_app, small_case, tmp_path):
    """In the module's panel (Slicer's MRML, Qt stand-ins): a markups line (world RAS) chosen as the plan; the replay
    writes the guidance columns and navigation.json with the line's points in LPS, and the panel shows the closest
    approach and the predicted error. A point list with two points labelled Target is refused with the panel's
    error (the plan stays as it was)."""
    import types

    from vtkmodules.vtkCommonDataModel import vtkVector3d

    module = slicer_app.load_module()
    widget = module.EMRegWidget(parent=types.SimpleNamespace())
    widget.setup()
    ui = widget.ui
    ui.caseDirectoryPathLineEdit.currentPath = str(small_case)
    ui.outputDirectoryPathLineEdit.currentPath = str(tmp_path / "out")
    ui.loadCaseButton.click()
    ui.calibrateButton.click()
    ui.detectButton.click()
    ui.registerButton.click()
    truth = json.loads((small_case / "truth.json").read_text())
    target = np.array(truth["targets"][0]["position"])
    entry = target + np.array([0.0, 0.0, 40.0])
    line = slicer_app.scene.AddNewNodeByClass("vtkMRMLMarkupsLineNode", "trajectory")
    for label, lps in (("L-1", entry), ("L-2", target)):
        line.AddControlPoint(vtkVector3d(-lps[0], -lps[1], lps[2]), label)  # RAS, as Slicer places it
    ui.planNodeComboBox.setCurrentNode(line)
    np.testing.assert_allclose(widget.logic.controller.inputs.plan.target_mm, target, atol=1e-6)
    ui.navigateButton.click()
    header, _ = read_navigation(tmp_path / "out" / "navigation.csv")
    assert header[-4:] == list(GUIDANCE_COLUMNS)
    document = json.loads((tmp_path / "out" / "navigation.json").read_text())
    np.testing.assert_allclose(document["plan"]["entry_mm"], entry, atol=1e-3)
    assert "guidance: closest" in ui.resultsLabel.text and "mm predicted (95 %:" in ui.resultsLabel.text

    points = slicer_app.scene.AddNewNodeByClass("vtkMRMLMarkupsFiducialNode", "two targets")
    for lps in (target, entry):
        points.AddControlPoint(vtkVector3d(-lps[0], -lps[1], lps[2]), "Target")
    with pytest.raises(Exception, match="labelled 'Target'"):
        ui.planNodeComboBox.setCurrentNode(points)
    assert slicer_app.errors and "Using the plan failed." in slicer_app.errors[-1]
    np.testing.assert_allclose(widget.logic.controller.inputs.plan.entry_mm, entry, atol=1e-6)
    widget.cleanup()


def test_slicer_panel_shows_the_live_guidance_as_it_arrives(slicer_app):
    """Live, ``emreg navigate --plan --igtl-port`` sends the numbers as the STRING ``Guidance``, which OpenIGTLinkIF
    keeps in a text node of that name (played here: slicer-core has no OpenIGTLinkIF): the panel's readout shows
    each new text as it arrives, whether the node appears after the panel or was there before it."""
    import types

    module = slicer_app.load_module()
    widget = module.EMRegWidget(parent=types.SimpleNamespace())
    widget.setup()
    assert widget.ui.guidanceLabel.text == ""
    slicer_app.scene.AddNewNodeByClass("vtkMRMLScalarVolumeNode", "Guidance")  # not a text node: not the readout
    assert widget.ui.guidanceLabel.text == ""
    node = slicer_app.scene.AddNewNodeByClass("vtkMRMLTextNode", "Guidance")
    for text in ("target 12.31 mm; lateral 1.02 mm; angle 4.40 deg; to go 11.80 mm",
                 "target 3.05 mm; lateral 0.41 mm; angle 1.20 deg; to go 2.97 mm; target 0.9 mm predicted (95 %: "
                 "1.6 mm)"):
        node.SetText(text)
        assert widget.ui.guidanceLabel.text == text
    widget.cleanup()

    later = module.EMRegWidget(parent=types.SimpleNamespace())  # a panel made while the navigation runs
    later.setup()
    assert later.ui.guidanceLabel.text.startswith("target 3.05 mm")
    node.SetText("target 0.52 mm; lateral 0.10 mm; angle 0.90 deg; to go 0.50 mm")
    assert later.ui.guidanceLabel.text.startswith("target 0.52 mm")
    later.cleanup()


def test_navigate_takes_the_plan_of_a_settings_file_relative_to_it(needle, tmp_path):  # noqa: F811
    """``[navigation] plan`` of ``--settings FILE`` (a path relative to that file's folder) as ``--plan`` would give it;
    ``--plan`` on the command line wins over it."""
    settings = tmp_path / "settings" / "case.toml"
    settings.parent.mkdir()
    plan_at_target(settings.parent / "plan.mrk.json", needle["truth"], "T2")
    settings.write_text('[navigation]\nplan = "plan.mrk.json"\n')
    assert _navigate(needle, tmp_path / "nav", "--quiet", "--settings", str(settings)) == 0
    document = json.loads((tmp_path / "nav" / "navigation.json").read_text())
    np.testing.assert_allclose(document["plan"]["target_mm"], needle["truth"]["targets"][1]["position"], atol=1e-3)
    other = plan_at_target(tmp_path / "T3.mrk.json", needle["truth"], "T3")
    assert _navigate(needle, tmp_path / "nav3", "--quiet", "--settings", str(settings), "--plan", str(other)) == 0
    document = json.loads((tmp_path / "nav3" / "navigation.json").read_text())
    np.testing.assert_allclose(document["plan"]["target_mm"], needle["truth"]["targets"][2]["position"], atol=1e-3)
