"""The simulator end to end: `emreg simulate` writes every file of the spec, deterministically per seed."""

from __future__ import annotations

import json

import numpy as np
import pytest
import SimpleITK as sitk
from conftest import CI_CASE_OPTIONS, load_truth

from EMRegModule.cli.main import main
from EMRegModule.core.transforms import apply_transform, invert_rigid, is_rigid, random_rotation
from EMRegModule.errors import EMRegError
from EMRegModule.io.case import open_case
from EMRegModule.io.image import read_ct
from EMRegModule.marker_model import MarkerModel
from EMRegModule.simulation.case import simulate_case
from EMRegModule.simulation.frame import FACE_NORMALS

SPEC_FILES = ("calibration.csv", "navigation.csv", "targets.mrk.json", "board.csv", "case.toml", "truth.json")
TINY = {"frame_size_mm": (160.0, 160.0, 100.0), "n_markers": 8, "navigation_rounds": 2, "board_rounds": 2,
        "n_targets": 3}


def test_cli_simulate_writes_every_file_of_the_spec(tmp_path, capsys):
    out = tmp_path / "case"
    assert main(["simulate", str(out), "--seed", "3", "--spacing", "1.5", "--quiet"]) == 0
    assert "simulated case written" in capsys.readouterr().out
    for name in (*SPEC_FILES, "ct.nrrd"):
        assert (out / name).is_file(), name
    case = open_case(out)
    assert case.ct == out / "ct.nrrd" and case.calibration and case.navigation and case.board and case.targets
    truth = load_truth(out)
    assert truth["seed"] == 3 and truth["difficulty"] == "standard"
    assert len(truth["markers"]) == 28 and all(m["in_ct"] and m["calibrated"] for m in truth["markers"])
    assert truth["image"]["spacing"] == pytest.approx([1.5, 1.5, 1.5])
    image = read_ct(out / "ct.nrrd")
    assert image.GetPixelID() == sitk.sitkInt16
    assert list(image.GetSize()) == truth["image"]["size"]
    assert np.allclose(image.GetOrigin(), truth["image"]["origin"]) and np.allclose(
        image.GetDirection(), truth["image"]["direction"])
    model = MarkerModel(**truth["marker_model"])
    assert model.pinhole_bottom_mm + 1 <= truth["sensor_offset_l_mm"] <= model.pinhole_top_mm - 1
    assert is_rigid(truth["ReferenceToImage"], 1e-9)
    assert not any(name.startswith(".") for name in (p.name for p in out.iterdir()))  # no temporaries left


def test_cli_simulate_hard_writes_a_dicom_folder(tmp_path):
    out = tmp_path / "hard"
    assert main(["simulate", str(out), "--difficulty", "hard", "--seed", "4", "--spacing", "1.6", "--quiet"]) == 0
    assert (out / "ct").is_dir() and not (out / "ct.nrrd").exists()
    assert all((out / name).is_file() for name in SPEC_FILES)
    truth = load_truth(out)
    assert truth["difficulty"] == "hard" and truth["ct"]["file"] == "ct"
    assert sum(not m["in_ct"] for m in truth["markers"]) == 2
    assert sum(not m["calibrated"] for m in truth["markers"]) == 1
    assert len(truth["decoys"]) == 6
    assert "qw" in (out / "board.csv").read_text().splitlines()[0]


def test_cli_simulate_bad_option_exits_2(tmp_path, capsys):
    with pytest.raises(SystemExit) as exit_info:
        main(["simulate", str(tmp_path / "x"), "--difficulty", "extreme"])
    assert exit_info.value.code == 2
    with pytest.raises(EMRegError, match="unknown option"):
        simulate_case(tmp_path / "y", n_markerz=3)
    with pytest.raises(EMRegError, match="n_markers"):
        simulate_case(tmp_path / "z", n_markers=2)
    assert not (tmp_path / "y").exists() or not any((tmp_path / "y").iterdir())


def test_same_seed_same_case_other_seed_other_layout(tmp_path):
    paths = [tmp_path / name for name in ("a", "b", "c")]
    for path, seed in zip(paths, (21, 21, 22), strict=True):
        simulate_case(path, seed=seed, spacing_mm=1.5, **TINY)
    a, b, c = paths
    for name in ("truth.json", "calibration.csv", "navigation.csv", "board.csv", "targets.mrk.json", "case.toml"):
        assert (a / name).read_bytes() == (b / name).read_bytes(), name
    ct_a = sitk.GetArrayFromImage(read_ct(a / "ct.nrrd"))
    assert np.array_equal(ct_a, sitk.GetArrayFromImage(read_ct(b / "ct.nrrd")))
    origins_a = np.array([m["origin"] for m in load_truth(a)["markers"]])
    origins_c = np.array([m["origin"] for m in load_truth(c)["markers"]])
    assert np.abs(origins_a - origins_c).max() > 5.0


def test_spacing_does_not_change_layout_or_recordings(tmp_path):
    simulate_case(tmp_path / "coarse", seed=5, spacing_mm=1.5, **TINY)
    simulate_case(tmp_path / "fine", seed=5, spacing_mm=(1.0, 1.1, 1.3), **TINY)
    coarse, fine = load_truth(tmp_path / "coarse"), load_truth(tmp_path / "fine")
    assert fine["image"]["spacing"] == pytest.approx([1.0, 1.1, 1.3])
    assert json.dumps(coarse["markers"]) == json.dumps(fine["markers"])
    for name in ("calibration.csv", "board.csv"):
        assert (tmp_path / "coarse" / name).read_bytes() == (tmp_path / "fine" / name).read_bytes()


def test_layout_is_on_the_faces_irregular_and_spread(standard_case):
    truth = load_truth(standard_case)
    model = MarkerModel(**truth["marker_model"])
    image_to_frame = invert_rigid(truth["frame"]["FrameToImage"])
    size = np.asarray(truth["frame"]["size_mm"])
    assert len(truth["markers"]) == CI_CASE_OPTIONS["n_markers"]
    assert [m["label"] for m in truth["markers"]] == [f"M{i:02d}" for i in range(1, 17)]
    faces = set()
    origins = []
    for m in truth["markers"]:
        origin = apply_transform(image_to_frame, m["origin"])
        axis = image_to_frame[:3, :3] @ np.asarray(m["axis"])
        normal = FACE_NORMALS[m["face"]]
        assert np.allclose(axis, normal, atol=1e-9)
        faces.add(m["face"])
        # the bottom cylinder fills the slot: the marker's shoulder is flush with the face
        shoulder = origin + model.bottom_height_mm * normal
        face_level = {"top": size[2], "+x": size[0] / 2, "-x": size[0] / 2, "+y": size[1] / 2, "-y": size[1] / 2}
        coordinate = shoulder[2] if m["face"] == "top" else abs(shoulder @ np.abs(normal))
        assert coordinate == pytest.approx(face_level[m["face"]], abs=1e-9)
        marker_to_image = np.asarray(m["marker_to_image"])
        assert is_rigid(marker_to_image, 1e-9) and np.allclose(marker_to_image[:3, 1], m["axis"])
        origins.append(m["origin"])
    assert faces == set(FACE_NORMALS)
    origins = np.asarray(origins)
    distances = np.linalg.norm(origins[:, None] - origins[None], axis=2)
    assert np.min(distances + np.eye(len(origins)) * 1e3) >= model.bottom_diameter_mm + 8.0 - 1e-9
    profiles = np.sort(distances, axis=1)
    difference = np.abs(profiles[:, None] - profiles[None]).max(axis=2) + np.eye(len(origins)) * 1e3
    assert difference.min() > 2.0  # each marker is told apart by its distances to the others


def test_left_handed_nrrd_keeps_physical_truth_and_replaces_stale_ct(tmp_path):
    out = tmp_path / "case"
    simulate_case(out, seed=8, difficulty="hard", spacing_mm=1.5, **TINY)
    assert (out / "ct").is_dir()
    direction = (random_rotation(np.random.default_rng(1), 35.0) @ np.diag([1.0, 1.0, -1.0])).ravel()
    truth = simulate_case(out, seed=8, difficulty="hard", spacing_mm=(0.9, 1.0, 1.2), ct_format="nrrd",
                          direction=direction, noise_hu=10.0, **TINY)
    assert (out / "ct.nrrd").is_file() and not (out / "ct").exists()
    image = read_ct(out / "ct.nrrd")
    assert np.allclose(image.GetDirection(), direction) and np.linalg.det(direction.reshape(3, 3)) < 0
    array = sitk.GetArrayViewFromImage(image)
    for marker in truth["markers"]:
        inside = apply_transform(marker["marker_to_image"], [0.0, 4.0, 0.0])
        above = apply_transform(marker["marker_to_image"], [0.0, 22.0, 0.0])
        values = []
        for point in (inside, above):
            i, j, k = np.round(image.TransformPhysicalPointToContinuousIndex(point.tolist())).astype(int)
            values.append(array[k, j, i])
        assert (values[0] > 900) == marker["in_ct"] and values[1] < -800, (marker["label"], values)
