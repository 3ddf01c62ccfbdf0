"""End to end: ``emreg run`` on the simulated standard and hard cases, checked against truth.json.

The run goes through the real marker detector, the frame calibration (labelled recording in
the standard case; unlabelled with the frame bumped in the hard one), automatic pairing (the
hard case has calibrated markers absent from the CT, a CT marker never calibrated and decoys),
the sensor offset, registration, navigation and evaluation. Accuracy asserted (issue 4):
pairing 100 % correct and complete, |l - l_true| < 0.3 mm, TRE within 1.2x (+0.1 mm) of an
ideal registration (true marker poses, true pairing, true l, same tracking data), board
edges within 0.2 mm of the truth.
"""

from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np
import pytest
from conftest import load_truth

from EMRegModule.cli.main import main
from EMRegModule.core.evaluation import evaluate
from EMRegModule.core.transforms import fit_rigid
from EMRegModule.io.case import open_case
from EMRegModule.io.itk_transform import read_slicer_linear_transform

SPEC_OUTPUTS = ("markers.json", "markers.mrk.json", "frame_calibration.json", "registration.json",
                "ReferenceToImage.h5", "navigation.csv", "evaluation.json")


def _run(case: Path, out: Path) -> tuple[Path, Path, dict]:
    assert main(["run", str(case), "--out", str(out), "--quiet"]) == 0
    return case, out, load_truth(case)


@pytest.fixture(scope="module")
def standard_case_run(standard_case, standard_run):
    """The session's ``emreg run`` of the standard case (conftest's ``standard_run``: made once, read only)."""
    return standard_case, standard_run.out, load_truth(standard_case)


@pytest.fixture(scope="module")
def hard_case_run(hard_case, tmp_path_factory):
    return _run(hard_case, tmp_path_factory.mktemp("run_hard"))


@pytest.fixture(params=["standard", "hard"])
def run(request):
    return request.getfixturevalue(f"{request.param}_case_run")


def _load(out: Path, name: str) -> dict:
    return json.loads((out / name).read_text())


def _nearest(label_positions: dict[str, np.ndarray], point, limit_mm: float = 2.0) -> str | None:
    labels = list(label_positions)
    distance = np.linalg.norm(np.asarray([label_positions[k] for k in labels]) - np.asarray(point), axis=1)
    k = int(np.argmin(distance))
    return labels[k] if distance[k] < limit_mm else None


def _truth_names(out: Path, truth: dict) -> tuple[dict[str, str | None], dict[str, str | None]]:
    """Truth marker label of every detected marker (by origin) and calibration point (by pinhole)."""
    origins = {m["label"]: np.asarray(m["origin"]) for m in truth["markers"] if m["in_ct"]}
    pinholes = {m["label"]: np.asarray(m["pinhole_in_reference"]) for m in truth["markers"] if m["calibrated"]}
    image = {m["id"]: _nearest(origins, m["origin"]) for m in _load(out, "markers.json")["markers"]}
    calibration = {p["label"]: _nearest(pinholes, p["position"])
                   for p in _load(out, "frame_calibration.json")["points"]}
    return image, calibration


def test_run_writes_every_output_of_the_spec(run):
    case, out, truth = run
    for name in SPEC_OUTPUTS:
        assert (out / name).is_file(), name
    registration = _load(out, "registration.json")
    np.testing.assert_allclose(read_slicer_linear_transform(out / "ReferenceToImage.h5"),
                               registration["ReferenceToImage"], atol=1e-9)
    with (out / "navigation.csv").open() as f:
        rows = list(csv.reader(f))
    assert rows[0][:5] == ["time_s", "x_mm", "y_mm", "z_mm", "label"] and len(rows) > 1000
    assert rows[0][5:] == ["status"] and {row[5] for row in rows[1:]} <= {"OK", "INVALID"}  # added after the spec's
    evaluation = _load(out, "evaluation.json")
    assert set(evaluation["tre"]["targets"]) == {t["label"] for t in truth["targets"]}
    assert list(evaluation["board"]["edges"]) == ["L1", "L2", "L3", "L4"]


def test_calibration_finds_every_pinhole(run):
    case, out, truth = run
    _, calibration = _truth_names(out, truth)
    calibrated = {m["label"] for m in truth["markers"] if m["calibrated"]}
    found = {name for name in calibration.values() if name is not None}
    assert found == calibrated
    # Every calibrated pinhole once (stray still periods, if any, match no pinhole and stay unpaired).
    assert sorted(n for n in calibration.values() if n) == sorted(calibrated)
    document = _load(out, "frame_calibration.json")
    if truth["calibration"]["labelled"]:
        assert all(p["label"] == calibration[p["label"]] for p in document["points"])
    else:
        assert all(p["label"].startswith("P") for p in document["points"])


def test_pairing_is_correct_and_complete(run):
    case, out, truth = run
    image, calibration = _truth_names(out, truth)
    registration = _load(out, "registration.json")
    for pair in registration["pairs"]:
        assert image[pair["image_marker"]] is not None
        assert image[pair["image_marker"]] == calibration[pair["calibration_point"]], pair
    pairable = set(image.values()) & set(calibration.values()) - {None}
    assert len(registration["pairs"]) == len(pairable)


def test_sensor_offset_is_found(run):
    case, out, truth = run
    registration = _load(out, "registration.json")
    assert abs(registration["sensor_offset_l_mm"] - truth["sensor_offset_l_mm"]) < 0.3
    assert registration["sensor_offset_l_std_mm"] < 0.3
    assert registration["fre_mm"] < 1.0


def test_tre_is_close_to_the_ideal_registration(run):
    case, out, truth = run
    _, calibration = _truth_names(out, truth)
    markers = {m["label"]: m for m in truth["markers"]}
    points = {p["label"]: np.asarray(p["position"]) for p in _load(out, "frame_calibration.json")["points"]}
    l_true = truth["sensor_offset_l_mm"]
    pairs = [(points[label], np.asarray(markers[name]["origin"]) + l_true * np.asarray(markers[name]["axis"]))
             for label, name in calibration.items() if name is not None and markers[name]["in_ct"]]
    ideal = fit_rigid(np.array([p for p, _ in pairs]), np.array([q for _, q in pairs]))
    folder = open_case(case)
    ideal_tre = evaluate(ideal, 1, 2, folder.settings.evaluation, navigation=folder.read_recording("navigation"),
                         targets=folder.read_targets()).to_json()["tre"]["mean_mm"]
    tre = _load(out, "evaluation.json")["tre"]
    assert tre["n"] == len(truth["navigation"]["dwells"])
    assert tre["mean_mm"] <= 1.2 * ideal_tre + 0.1, (tre["mean_mm"], ideal_tre)
    predicted = _load(out, "registration.json")["predicted_registration_tre_mm"]
    assert len(predicted) == len(truth["targets"]) and max(predicted) < 1.0


def test_board_edges_match_the_truth(run):
    case, out, truth = run
    edges = _load(out, "evaluation.json")["board"]["edges"]
    for k, name in enumerate(("L1", "L2", "L3", "L4")):
        assert abs(edges[name]["mean_mm"] - truth["board"]["edges_mm"][k]) < 0.2
        assert edges[name]["n"] == len(truth["board"]["dwells"]) // 4


def test_predicted_end_to_end_tre_matches_the_measured_one(run):
    """Issue 15's goal on each CI case: predicted RMS TRE within 0.8-1.25x of the measured one overall
    and within 0.65-1.5x per target; the registration's own prediction alone falls far short."""
    case, out, truth = run
    tre = _load(out, "evaluation.json")["tre"]
    ratio = tre["predicted_rms_mm"] / tre["rms_mm"]
    assert 0.8 <= ratio <= 1.25, ratio
    per_target = {label: t["predicted_rms_mm"] / t["rms_mm"] for label, t in tre["targets"].items()}
    assert len(per_target) == len(truth["targets"])
    assert all(0.65 <= r <= 1.5 for r in per_target.values()), per_target
    registration_only = np.sqrt(np.mean(np.square(_load(out, "registration.json")["predicted_registration_tre_mm"])))
    assert registration_only < 0.5 * tre["rms_mm"]
    for target in tre["targets"].values():
        budget = target["budget_rms_mm"]
        assert np.sqrt(sum(v**2 for v in budget.values())) == pytest.approx(target["predicted_rms_mm"], abs=2e-4)
    # the report shows the budget and the map, and the predicted values beside the measured ones
    assert (out / "report_figures" / "error_budget.png").stat().st_size > 0
    assert (out / "report_figures" / "tre_map.png").stat().st_size > 0
    page = (out / "report.html").read_text(encoding="utf-8")
    assert f"{tre['predicted_rms_mm']:.2f}" in page and "Error budget per target" in page


def test_tre_map_covers_the_ct_and_agrees_with_the_targets_predictions(run):
    """``tre_map.nrrd``: float32 mm in the CT's LPS space; its value at each target is the target's
    predicted RMS TRE (within 10 %, the grid being coarse)."""
    import SimpleITK as sitk
    from scipy.ndimage import map_coordinates

    case, out, truth = run
    tre_map = sitk.ReadImage(str(out / "tre_map.nrrd"))
    assert tre_map.GetPixelID() == sitk.sitkFloat32
    image = _load(out, "markers.json")["image"]
    assert np.allclose(tre_map.GetDirection(), image["direction"]) and np.allclose(tre_map.GetOrigin(), image["origin"])
    far_corner = np.asarray(image["origin"]) + np.reshape(image["direction"], (3, 3)) @ (
        (np.asarray(image["size"]) - 1) * np.asarray(image["spacing"]))
    assert np.all(np.asarray(tre_map.TransformPhysicalPointToContinuousIndex(far_corner.tolist()))
                  <= np.asarray(tre_map.GetSize()) - 1 + 1e-6)
    values = sitk.GetArrayFromImage(tre_map)  # (k, j, i)
    assert np.all(np.isfinite(values)) and values.min() > 0
    targets = _load(out, "evaluation.json")["tre"]["targets"]
    labels = [t["label"] for t in truth["targets"]]
    for label, position in zip(labels, (t["position"] for t in truth["targets"]), strict=True):
        index = tre_map.TransformPhysicalPointToContinuousIndex([float(v) for v in position])
        at_target = map_coordinates(values, [[index[2]], [index[1]], [index[0]]], order=1)[0]
        assert at_target == pytest.approx(targets[label]["predicted_rms_mm"], rel=0.10)


def test_run_names_the_dicom_series_it_used(hard_case_run):
    """The hard case's CT is a DICOM folder: run.json and markers.json name the series (issue 13)."""
    hard_case, out, _ = hard_case_run
    used = _load(out, "run.json")["ct_series"]
    assert used == _load(out, "markers.json")["ct_series"]
    assert used["modality"] == "CT" and used["others"] == []
    assert used["slices"] == _load(out, "markers.json")["image"]["size"][2] == len(list((hard_case / "ct").iterdir()))
    assert used["slice_spacing_mm"] == pytest.approx(0.8, abs=1e-3) and used["series_instance_uid"]
    assert used["series_instance_uid"] in (out / "report.html").read_text(encoding="utf-8")  # named in the summary
