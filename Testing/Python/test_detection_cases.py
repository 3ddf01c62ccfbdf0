"""``emreg detect`` on the simulator's cases, checked against their ground truth, and on bad inputs.

Accuracy required (issue 3): standard case (0.6 mm, 20 HU noise) every marker found, none
false, origin error median < 0.15 mm and max < 0.4 mm, axis error median < 0.5 deg and
max < 2 deg; hard case (0.5 x 0.5 x 0.8 mm, oblique flipped grid, 35 HU, decoys) the same
recall, no false marker, origin median < 0.25 mm.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import SimpleITK as sitk
from conftest import CI_CASE_OPTIONS, load_truth
from fixtures import phantom as ph

from EMRegModule.cli.main import main
from EMRegModule.core.detection import DetectionResult
from EMRegModule.core.transforms import angle_between_deg
from EMRegModule.io.markers_json import read_detection
from EMRegModule.io.markups import read_markups
from EMRegModule.simulation.case import simulate_case


def run_detect(case: Path, out: Path, capsys) -> tuple[int, str, str]:
    code = main(["detect", str(case), "--out", str(out), "--quiet"])
    captured = capsys.readouterr()
    return code, captured.out, captured.err


def errors_against_truth(result: DetectionResult, truth: dict) -> tuple[np.ndarray, np.ndarray, list, list]:
    """Origin (mm) and axis (deg) errors of matched markers, false detections, missed truth labels."""
    present = [m for m in truth["markers"] if m["in_ct"]]
    origins = np.array([m["origin"] for m in present])
    origin_errors, axis_errors, false, matched = [], [], [], set()
    for marker in result.markers:
        distances = np.linalg.norm(origins - marker.origin, axis=1)
        j = int(np.argmin(distances))
        if distances[j] > 2.0 or j in matched:
            false.append(marker.id)
            continue
        matched.add(j)
        origin_errors.append(distances[j])
        axis_errors.append(float(angle_between_deg(marker.axis, present[j]["axis"])))
    missed = [m["label"] for j, m in enumerate(present) if j not in matched]
    return np.array(origin_errors), np.array(axis_errors), false, missed


@pytest.fixture(scope="module")
def standard_detection(standard_case, tmp_path_factory):
    out = tmp_path_factory.mktemp("detect_standard")
    assert main(["detect", str(standard_case), "--out", str(out), "--quiet"]) == 0
    return out


@pytest.fixture(scope="module")
def hard_detection(hard_case, tmp_path_factory):
    out = tmp_path_factory.mktemp("detect_hard")
    assert main(["detect", str(hard_case), "--out", str(out), "--quiet"]) == 0
    return out


def test_standard_case_accuracy(standard_case, standard_detection):
    truth = load_truth(standard_case)
    result = read_detection(standard_detection / "markers.json")
    origin_errors, axis_errors, false, missed = errors_against_truth(result, truth)
    assert not false and not missed
    assert np.median(origin_errors) < 0.15 and origin_errors.max() < 0.4, origin_errors
    assert np.median(axis_errors) < 0.5 and axis_errors.max() < 2.0, axis_errors
    assert all(m.fit_rms_mm < 0.2 for m in result.markers)


def test_hard_case_accuracy_and_decoys(hard_case, hard_detection):
    truth = load_truth(hard_case)
    result = read_detection(hard_detection / "markers.json")
    origin_errors, axis_errors, false, missed = errors_against_truth(result, truth)
    assert not false and not missed
    assert np.median(origin_errors) < 0.25 and origin_errors.max() < 0.6, origin_errors
    assert np.median(axis_errors) < 1.0, axis_errors
    # every decoy of PVC density is accounted for among the rejected candidates
    centroids = np.array([r.centroid for r in result.rejected]).reshape(-1, 3)
    for decoy in truth["decoys"]:
        assert np.min(np.linalg.norm(centroids - decoy["center"], axis=1)) < 8.0, decoy["kind"]


SMALL_MARKER = {"bottom_diameter_mm": 10.0, "bottom_height_mm": 6.0, "top_diameter_mm": 4.0, "top_height_mm": 7.0,
                "pinhole_diameter_mm": 1.0, "pinhole_depth_mm": 5.0}
THIN_TOP_MARKER = {"bottom_diameter_mm": 14.0, "bottom_height_mm": 8.0, "top_diameter_mm": 4.0, "top_height_mm": 9.0,
                   "pinhole_diameter_mm": 1.0, "pinhole_depth_mm": 6.0}


@pytest.mark.parametrize(("spacing", "seed", "options"), [
    ((0.8, 0.8, 3.0), 31, {}), ((1.25, 1.25, 1.25), 35, {}), (1.5, 52, {"noise_hu": 25.0}),
    (0.6, 41, {"marker": SMALL_MARKER}), (1.0, 42, {"marker": SMALL_MARKER}),
    (1.25, 23, {"marker": THIN_TOP_MARKER})])
def test_coarse_voxels_and_small_markers_keep_every_marker(spacing, seed, options, tmp_path, capsys):
    """Voxels coarse against the marker blur its narrow top: every marker is still found, none false.

    Before, these scans lost markers: the shape sieve took the blurred spreads for another
    shape, and where the skew axis pointed across or backwards the fit failed, or fitted the
    marker upside down about as well as the right way up (seed 52 at 1.5 mm: RMS 0.096 mm
    upside down, 0.109 mm right; only the brightness inside the fitted solid tells them apart).
    A 4 mm top at 1.25 mm voxels (seed 23) was turned over while the brightness was averaged over
    the whole solid: only the top tells the two poses apart.
    """
    case = tmp_path / "case"
    simulate_case(case, seed=seed, spacing_mm=spacing, patient=False, **options, **CI_CASE_OPTIONS)
    code, _, _ = run_detect(case, tmp_path / "out", capsys)
    assert code == 0
    result = read_detection(tmp_path / "out")
    origin_errors, axis_errors, false, missed = errors_against_truth(result, load_truth(case))
    assert not false and not missed, (false, missed)
    assert np.median(origin_errors) < 0.3 and origin_errors.max() < 1.0, origin_errors
    assert np.median(axis_errors) < 1.0, axis_errors


def test_detect_writes_both_files_per_spec(standard_case, standard_detection):
    document = json.loads((standard_detection / "markers.json").read_text())
    assert document["coordinate_system"] == "LPS"
    image = sitk.ReadImage(str(standard_case / "ct.nrrd"))
    assert document["image"]["size"] == list(image.GetSize())
    np.testing.assert_allclose(document["image"]["direction"], image.GetDirection())
    for i, marker in enumerate(document["markers"], start=1):
        assert marker["id"] == f"I{i:02d}"
        assert len(marker["origin"]) == 3 and abs(np.linalg.norm(marker["axis"]) - 1) < 1e-9
        assert marker["volume_mm3"] > 0 and marker["fit_rms_mm"] >= 0
    labels, positions = read_markups(standard_detection / "markers.mrk.json")
    assert labels == [m["id"] for m in document["markers"]]
    np.testing.assert_allclose(positions, [m["origin"] for m in document["markers"]], atol=1e-6)


def test_detect_accepts_a_ct_file_and_settings(tmp_path, capsys):
    scene = ph.scene(decoys=False, metal=False, cut_marker=False)
    ct = tmp_path / "scan.mha"
    sitk.WriteImage(scene.image, str(ct))
    settings = tmp_path / "case.toml"
    settings.write_text("[detection]\nmin_markers = 7\n")
    out = tmp_path / "out"
    code = main(["detect", str(ct), "--out", str(out), "--quiet", "--settings", str(settings)])
    err = capsys.readouterr().err
    assert code == 3 and "6 marker(s) found in the CT, at least 7 needed" in err and len(err.strip().splitlines()) == 1
    assert not (out / "markers.json").exists()
    settings.write_text("[detection]\nlow_hue = 500\n")
    code = main(["detect", str(ct), "--out", str(out), "--quiet", "--settings", str(settings)])
    err = capsys.readouterr().err
    assert code == 2 and "low_hue" in err and len(err.strip().splitlines()) == 1
    settings.write_text("[detection]\nmin_markers = 6\n")
    code = main(["detect", str(ct), "--out", str(out), "--settings", str(settings)])
    captured = capsys.readouterr()
    assert code == 0 and "6 markers detected" in captured.out
    assert len(read_detection(out).markers) == 6


def _bad_inputs(folder: Path, standard_case: Path) -> dict[str, Path]:
    folder.mkdir(parents=True, exist_ok=True)
    empty = folder / "empty.nrrd"
    empty.write_bytes(b"")
    flat = folder / "flat.nrrd"
    sitk.WriteImage(sitk.Image([32, 32], sitk.sitkInt16), str(flat))
    vector = folder / "vector.nrrd"
    sitk.WriteImage(sitk.Image([16, 16, 16], sitk.sitkVectorFloat32, 3), str(vector))
    truncated = folder / "truncated.nrrd"
    full = folder / "full.nrrd"
    sitk.WriteImage(sitk.Image([64, 64, 64], sitk.sitkInt16) - 1000, str(full), False)
    truncated.write_bytes(full.read_bytes()[: full.stat().st_size // 2])
    garbage = folder / "garbage.mha"
    garbage.write_bytes(b"not an image at all\n" * 10)
    return {"empty": empty, "2D": flat, "vector": vector, "truncated": truncated, "garbage": garbage,
            "missing": folder / "absent.nrrd"}


@pytest.mark.parametrize("kind", ["empty", "2D", "vector", "truncated", "garbage", "missing"])
def test_bad_ct_gives_exit_2_and_one_line(kind, standard_case, tmp_path, capsys):
    path = _bad_inputs(tmp_path / "inputs", standard_case)[kind]
    out = tmp_path / "out"
    code, _, err = run_detect(path, out, capsys)
    assert code == 2
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("emreg detect: error:") and path.name in lines[0]
    assert "Traceback" not in err
    assert not (out / "markers.json").exists()


def test_ct_without_markers_gives_exit_3(tmp_path, capsys):
    image = sitk.Image([80, 80, 60], sitk.sitkInt16) + 340  # a block of POM and nothing else
    image.SetSpacing([0.6, 0.6, 0.6])
    sitk.WriteImage(image, str(tmp_path / "ct.nrrd"))
    code, _, err = run_detect(tmp_path, tmp_path / "out", capsys)
    assert code == 3 and "0 marker(s) found" in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "out" / "markers.json").exists()


@pytest.mark.parametrize("name", ["ct.nii.gz", "ct.mha"])
def test_nifti_and_mha_cases_give_the_same_markers(name, tmp_path, capsys):
    """NIfTI stores RAS on disk; SimpleITK hands back LPS: markers must land at the same LPS points."""
    direction = ph.oblique_direction(seed=7, flip=(1, 1, 1))
    scene = ph.scene(spacing=(0.6, 0.7, 0.8), direction=direction, decoys=False, metal=False, cut_marker=False,
                     seed=9)
    case = tmp_path / "case"
    case.mkdir()
    sitk.WriteImage(scene.image, str(case / name))
    code, out, _ = run_detect(case, tmp_path / "out", capsys)
    assert code == 0
    result = read_detection(tmp_path / "out")
    truth = {"markers": [{"label": str(i), "origin": list(t["origin"]), "axis": list(t["axis"]), "in_ct": True}
                         for i, t in enumerate(scene.markers)]}
    origin_errors, axis_errors, false, missed = errors_against_truth(result, truth)
    assert not false and not missed
    assert origin_errors.max() < 0.2 and axis_errors.max() < 1.0
