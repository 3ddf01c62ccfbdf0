"""File I/O: tracking CSV, markups, ITK transform files, CT reading, atomic writes, case folders."""

import json

import numpy as np
import pytest
import SimpleITK as sitk

from EMRegModule.core import transforms as tf
from EMRegModule.core.ct import image_geometry, index_to_physical_matrix
from EMRegModule.core.frames import LPS_TO_RAS
from EMRegModule.core.tracking import TrackingRecording, probe_in_reference
from EMRegModule.errors import EMRegError
from EMRegModule.io.atomic import atomic_path, atomic_write_json
from EMRegModule.io.case import open_case
from EMRegModule.io.image import read_ct
from EMRegModule.io.itk_transform import read_slicer_linear_transform, write_slicer_linear_transform
from EMRegModule.io.markups import read_markups, write_markups
from EMRegModule.io.tracking_csv import format_tracking_csv, parse_tracking_csv, read_tracking_csv, write_tracking_csv

HEADER = "time_s,sensor,x_mm,y_mm,z_mm,azimuth_deg,elevation_deg,roll_deg,quality,label\n"


def _recording(n=20, seed=0):
    rng = np.random.default_rng(seed)
    angles = rng.uniform([-170, -80, -170], [170, 80, 170], size=(n, 3))
    return TrackingRecording(
        time_s=np.repeat(np.arange(n // 2) / 80.0, 2), sensor=np.tile([1, 2], n // 2),
        position_mm=rng.uniform(-300, 300, size=(n, 3)), rotation=tf.angles_to_rotation(*angles.T),
        quality=np.where(rng.random(n) < 0.2, np.nan, rng.integers(0, 5, n)),
        label=np.array(["M01" if i % 3 else "" for i in range(n)], dtype=object),
    )


@pytest.mark.parametrize("orientation", ["angles", "quaternion"])
def test_tracking_csv_round_trip(tmp_path, orientation):
    recording = _recording()
    path = tmp_path / "rec.csv"
    write_tracking_csv(recording, path, orientation)
    back = read_tracking_csv(path)
    assert back.orientation_format == orientation
    np.testing.assert_allclose(back.time_s, recording.time_s, atol=1e-4)
    np.testing.assert_array_equal(back.sensor, recording.sensor)
    np.testing.assert_allclose(back.position_mm, recording.position_mm, atol=1e-4)
    np.testing.assert_allclose(back.rotation, recording.rotation, atol=1e-5)
    np.testing.assert_array_equal(np.isnan(back.quality), np.isnan(recording.quality))
    assert list(back.label) == list(recording.label)


def test_tracking_csv_without_labels_and_quality():
    text = "time_s,sensor,x_mm,y_mm,z_mm,azimuth_deg,elevation_deg,roll_deg\n0,1,1,2,3,0,0,0\n0,2,4,5,6,90,0,0\n"
    recording = parse_tracking_csv(text)
    assert len(recording) == 2 and list(recording.label) == ["", ""]
    assert np.all(np.isnan(recording.quality))


@pytest.mark.parametrize(
    "text, message",
    [
        ("", "empty"),
        (HEADER, "no samples"),
        ("time_s,sensor,x_mm,y_mm\n0,1,2,3\n", "lacks column"),
        (HEADER + "0,1,1,2,3,0,0,abc,0,\n", "line 2"),
        (HEADER + "0,1,1,2,3,0,0,0,0,\n0,2,1,2\n", "line 3"),
        (HEADER + "0,1.5,1,2,3,0,0,0,0,\n", "port"),
        (HEADER + "0,1,nan,2,3,0,0,0,0,\n", "non-finite"),
        # a blank line and a left-out row still count: the error names the file's own line
        (HEADER + "0,1,1,2,3,0,0,0,0,\n\n0.1,1,nan,2,3,0,0,0,0,\n", "line 4 holds a non-finite"),
        ("time_s,sensor,x_mm,y_mm,z_mm,azimuth_deg,elevation_deg,roll_deg,status\n0,1,,,,,,,MISSING\n"
         "0.1,1,nan,2,3,0,0,0,OK\n", "line 3 holds a non-finite"),
    ],
)
def test_malformed_tracking_csv_is_one_clear_error(text, message):
    with pytest.raises(EMRegError, match=message) as info:
        parse_tracking_csv(text, source="bad.csv")
    assert "\n" not in str(info.value) and "bad.csv" in str(info.value)


def test_missing_recording_names_file(tmp_path):
    with pytest.raises(EMRegError, match="not found"):
        read_tracking_csv(tmp_path / "absent.csv")


def test_probe_in_reference_is_invariant_to_moving_the_frame():
    """Eq. 3-5: moving reference and probe together (a bumped frame) changes nothing."""
    rng = np.random.default_rng(3)
    probe_to_reference = tf.make_transform(tf.random_rotation(rng), [10, 20, 30])
    rows = []
    for k in range(6):
        reference_to_tracker = tf.make_transform(tf.random_rotation(rng), rng.normal(size=3) * 100)
        probe_to_tracker = reference_to_tracker @ probe_to_reference
        rows.append((k / 80, 1, reference_to_tracker))
        rows.append((k / 80 + 0.0004, 2, probe_to_tracker))
    recording = TrackingRecording(
        time_s=[r[0] for r in rows], sensor=[r[1] for r in rows], position_mm=[r[2][:3, 3] for r in rows],
        rotation=[r[2][:3, :3] for r in rows], quality=np.zeros(len(rows)), label=[""] * len(rows),
    )
    result = probe_in_reference(recording, 1, 2, check_ports=False)  # the probe is fixed to the reference here
    assert len(result) == 6
    np.testing.assert_allclose(result.probe_to_reference, np.broadcast_to(probe_to_reference, (6, 4, 4)), atol=1e-9)
    with pytest.raises(EMRegError, match="port 3"):
        probe_in_reference(recording, 1, 3)


def test_markups_round_trip_and_ras_input(tmp_path):
    positions = np.array([[1.5, -2, 3], [10, 20, -30]])
    write_markups(tmp_path / "m.mrk.json", ["I01", "I02"], positions)
    document = json.loads((tmp_path / "m.mrk.json").read_text())
    assert document["markups"][0]["coordinateSystem"] == "LPS"
    labels, back = read_markups(tmp_path / "m.mrk.json")
    assert labels == ["I01", "I02"]
    np.testing.assert_allclose(back, positions)
    document["markups"][0]["coordinateSystem"] = "RAS"
    (tmp_path / "ras.mrk.json").write_text(json.dumps(document))
    np.testing.assert_allclose(read_markups(tmp_path / "ras.mrk.json")[1], positions * [-1, -1, 1])
    (tmp_path / "bad.mrk.json").write_text("{not json")
    with pytest.raises(EMRegError, match="bad.mrk.json"):
        read_markups(tmp_path / "bad.mrk.json")


@pytest.mark.parametrize("name", ["ReferenceToImage.h5", "t.tfm"])
def test_itk_transform_round_trip_and_how_slicer_loads_it(tmp_path, name):
    rng = np.random.default_rng(9)
    reference_to_image = tf.make_transform(tf.random_rotation(rng), [5, -7, 120])
    path = tmp_path / name
    write_slicer_linear_transform(path, reference_to_image)
    np.testing.assert_allclose(read_slicer_linear_transform(path), reference_to_image, atol=1e-9)
    # The file holds ITK's resampling direction: image (LPS) -> Reference, x and y negated.
    stored = sitk.ReadTransform(str(path))
    point_reference = np.array([1.0, 2.0, 3.0])
    point_image = tf.apply_transform(reference_to_image, point_reference)
    np.testing.assert_allclose(stored.TransformPoint(point_image.tolist()), point_reference * [-1, -1, 1], atol=1e-9)
    # 3D Slicer converts an ITK file T into the node's "to parent" F @ inv(T) @ F (LPS<->RAS on
    # both sides): that must be ReferenceToRAS, which maps raw Reference coordinates into RAS.
    matrix = np.eye(4)
    matrix[:3, :3] = np.reshape(sitk.AffineTransform(stored).GetMatrix(), (3, 3))
    matrix[:3, 3] = sitk.AffineTransform(stored).GetTranslation()
    to_parent_ras = LPS_TO_RAS @ np.linalg.inv(matrix) @ LPS_TO_RAS
    np.testing.assert_allclose(to_parent_ras, LPS_TO_RAS @ reference_to_image, atol=1e-9)


def _volume(size=(12, 10, 8)):
    image = sitk.GetImageFromArray(np.arange(np.prod(size), dtype=np.int16).reshape(size[::-1]))
    image.SetSpacing((0.5, 0.7, 1.1))
    image.SetOrigin((10, -20, 30))
    direction = tf.axis_angle_to_rotation([1, 1, 0], 0.3) @ np.diag([1, -1, -1])
    image.SetDirection(direction.ravel().tolist())
    return image


@pytest.mark.parametrize("name", ["ct.nrrd", "ct.nii.gz", "ct.mha"])
def test_read_ct_keeps_geometry(tmp_path, name):
    image = _volume()
    sitk.WriteImage(image, str(tmp_path / name))
    back = read_ct(tmp_path / name)
    geometry = image_geometry(back)
    np.testing.assert_allclose(geometry["spacing"], image.GetSpacing(), atol=1e-6)
    np.testing.assert_allclose(geometry["origin"], image.GetOrigin(), atol=1e-5)
    np.testing.assert_allclose(geometry["direction"], image.GetDirection(), atol=1e-6)
    index_to_image = index_to_physical_matrix(back)
    index = (3.5, 2.25, 6.0)
    np.testing.assert_allclose(
        tf.apply_transform(index_to_image, index), back.TransformContinuousIndexToPhysicalPoint(index), atol=1e-9
    )


def test_read_ct_dicom_series(tmp_path):
    image = sitk.Cast(_volume((16, 12, 6)), sitk.sitkInt16)
    image.SetDirection(tf.axis_angle_to_rotation([0, 0, 1], 0.2).ravel().tolist())
    folder = tmp_path / "ct"
    folder.mkdir()
    writer = sitk.ImageFileWriter()
    writer.KeepOriginalImageUIDOn()
    direction = image.GetDirection()
    for k in range(image.GetDepth()):
        slice_k = image[:, :, k]
        slice_k.SetMetaData("0020|000e", "1.2.826.0.1.3680043.2.1125.1.1")
        slice_k.SetMetaData("0020|0013", str(k + 1))
        slice_k.SetMetaData("0020|0032", "\\".join(map(str, image.TransformIndexToPhysicalPoint((0, 0, k)))))
        slice_k.SetMetaData("0020|0037", "\\".join(map(str, direction[0:7:3] + direction[1:8:3])))
        slice_k.SetMetaData("0018|0050", str(image.GetSpacing()[2]))
        slice_k.SetMetaData("0008|0060", "CT")
        writer.SetFileName(str(folder / f"slice{k:03d}.dcm"))
        writer.Execute(slice_k)
    back = read_ct(folder)
    assert back.GetSize() == image.GetSize()
    np.testing.assert_allclose(back.GetOrigin(), image.GetOrigin(), atol=1e-3)
    np.testing.assert_allclose(back.GetDirection(), image.GetDirection(), atol=1e-4)
    np.testing.assert_array_equal(sitk.GetArrayFromImage(back), sitk.GetArrayFromImage(image))
    assert open_case(tmp_path).ct == folder


def test_bad_ct_inputs_give_one_line_errors(tmp_path):
    (tmp_path / "empty.nrrd").write_bytes(b"")
    flat = sitk.Image(10, 10, sitk.sitkInt16)
    sitk.WriteImage(flat, str(tmp_path / "flat.nrrd"))
    vector = sitk.Image([6, 6, 6], sitk.sitkVectorFloat32, 3)
    sitk.WriteImage(vector, str(tmp_path / "vector.nrrd"))
    sitk.WriteImage(_volume((40, 40, 40)), str(tmp_path / "whole.mha"))
    data = (tmp_path / "whole.mha").read_bytes()
    (tmp_path / "truncated.mha").write_bytes(data[: len(data) // 2])
    (tmp_path / "text.nrrd").write_text("hello")
    for name, message in [("empty.nrrd", "empty"), ("flat.nrrd", "3D"), ("vector.nrrd", "scalar"),
                          ("truncated.mha", "cannot read"), ("text.nrrd", "cannot read"), ("absent.nrrd", "not found")]:
        with pytest.raises(EMRegError, match=message) as info:
            read_ct(tmp_path / name)
        assert "\n" not in str(info.value) and name in str(info.value)


def test_atomic_write_keeps_old_file_on_failure(tmp_path):
    target = tmp_path / "out.json"
    atomic_write_json(target, {"good": np.float64(1.5), "arr": np.arange(3)})
    assert json.loads(target.read_text()) == {"good": 1.5, "arr": [0, 1, 2]}
    with pytest.raises(RuntimeError):
        with atomic_path(target) as tmp:
            tmp.write_text("half")
            raise RuntimeError("interrupted")
    assert json.loads(target.read_text())["good"] == 1.5
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out.json"]


def test_case_folder_discovery_and_settings(tmp_path):
    (tmp_path / "calibration.csv").write_text(HEADER)
    (tmp_path / "case.toml").write_text("[sensors]\nreference = 3\nprobe = 4\n[board]\nedges_mm = [75.3, 60.4, 75.3]\n")
    case = open_case(tmp_path)
    assert case.ct is None and case.calibration == tmp_path / "calibration.csv" and case.board is None
    assert (case.reference_sensor, case.probe_sensor) == (3, 4)
    assert case.settings.board.edges_mm == (75.3, 60.4, 75.3)
    (tmp_path / "case.toml").write_text("[sensors\nreference = 3\n")
    with pytest.raises(EMRegError, match="malformed TOML"):
        open_case(tmp_path)
    (tmp_path / "case.toml").write_text("[sensors]\nreference = 'one'\n")
    with pytest.raises(EMRegError, match=r"\[sensors\] reference must be a whole number, got 'one'"):
        open_case(tmp_path)
    (tmp_path / "case.toml").write_text("[sensors]\nreference = 0\n")
    with pytest.raises(EMRegError, match="port number"):
        open_case(tmp_path)


def test_format_is_stable_text():
    text = format_tracking_csv(_recording(4))
    assert text.splitlines()[0] == HEADER.strip()
    assert len(text.splitlines()) == 5


def test_atomic_files_get_the_usual_permissions(tmp_path):
    import os

    atomic_write_json(tmp_path / "a.json", {})
    mask = os.umask(0)
    os.umask(mask)
    assert (tmp_path / "a.json").stat().st_mode & 0o777 == 0o666 & ~mask


def test_pixel_types_are_simpleitks_own():
    """EMReg names SimpleITK's voxel types without loading SimpleITK where it needs no image (core.pixel_types):
    the same values and names as SimpleITK's."""
    from EMRegModule.core import pixel_types

    for name in ("Int8", "UInt8", "Int16", "UInt16", "Int32", "UInt32", "Int64", "UInt64", "Float32", "Float64"):
        value = getattr(pixel_types, name.upper())
        assert value == getattr(sitk, f"sitk{name}")
        assert pixel_types.NAMES[value] == sitk.GetPixelIDValueAsString(value)
    assert pixel_types.FLOATS == {sitk.sitkFloat32, sitk.sitkFloat64}
    for value, name in pixel_types.NUMPY_NAMES.items():  # the numpy type an image of each type holds
        assert sitk.GetImageFromArray(np.zeros((2, 2, 2), dtype=name)).GetPixelID() == value
        assert pixel_types.BY_NUMPY_NAME[name] == value
