"""DICOM exports as hospitals give them: several series, DICOMDIR, transfer syntaxes, rescales, broken files.

The series are written by SimpleITK's GDCM writer and re-encoded by GDCM's and dcmtk's own
tools (``gdcmconv``, ``dcmconv``; ``scripts/setup`` installs them); voxels are checked against
the values written and against ``SimpleITK.ImageSeriesReader``.
"""

from __future__ import annotations

import io
import json
import shutil
from pathlib import Path

import numpy as np
import pydicom
import pytest
import SimpleITK as sitk
from conftest import load_truth
from dicom_files import TRANSFER_SYNTAXES, convert, make_volume, tools_available, transfer_syntax_uid, uid, write_series

from EMRegModule.cli.main import main
from EMRegModule.errors import EMRegError
from EMRegModule.io.dicom_read import open_dicom_series
from EMRegModule.io.dicom_series import choose_series, scan_series
from EMRegModule.io.image import read_ct
from EMRegModule.io.markers_json import read_detection


def _voxels(image: sitk.Image) -> np.ndarray:
    return sitk.GetArrayFromImage(image)


def _series_reader(files: list[Path]) -> sitk.Image:
    reader = sitk.ImageSeriesReader()
    reader.SetFileNames([str(f) for f in files])
    return reader.Execute()


def _export(folder: Path) -> dict[str, str]:
    """A scanner export: a 0.8 mm volume, a 2.4 mm reconstruction, a scout, an MR series, junk; their UIDs."""
    volume = make_volume()
    write_series(volume, folder / "S1", uid(10), number=2, description="thin 0.8")
    thick = volume[:, :, ::3]
    write_series(thick, folder / "S2", uid(20), number=3, description="thick 2.4")
    write_series(volume[:, :, :3], folder / "SCOUT", uid(30), number=1, description="topogram",
                 image_type="ORIGINAL\\PRIMARY\\LOCALIZER")
    write_series(volume, folder / "MR", uid(40), number=4, description="t1", modality="MR")
    (folder / "README.txt").write_text("export of the CT scanner\n")
    return {"volume": uid(10), "thick": uid(20), "scout": uid(30), "mr": uid(40)}


def test_the_volume_best_for_detection_is_chosen_and_the_others_listed(tmp_path):
    uids = _export(tmp_path)
    fill, record = open_dicom_series(tmp_path)
    image = fill.result()
    assert record["series_instance_uid"] == uids["volume"]
    assert record["series_number"] == 2 and record["description"] == "thin 0.8"
    assert record["slice_spacing_mm"] == pytest.approx(0.8) and record["slices"] == 12
    others = {o["series_instance_uid"]: o for o in record["others"]}
    assert set(others) == {uids["thick"], uids["scout"], uids["mr"]}
    assert "not_used_because" not in others[uids["thick"]]  # a volume, just coarser
    assert "localizer" in others[uids["scout"]]["not_used_because"]
    assert "MR" in others[uids["mr"]]["not_used_because"]
    expected = make_volume()
    reference = _series_reader(sorted((tmp_path / "S1").glob("*.dcm")))
    np.testing.assert_array_equal(_voxels(image), _voxels(expected))
    np.testing.assert_array_equal(_voxels(image), _voxels(reference))
    np.testing.assert_allclose(image.GetOrigin(), reference.GetOrigin(), atol=1e-5)
    np.testing.assert_allclose(image.GetSpacing(), reference.GetSpacing(), atol=1e-6)
    np.testing.assert_allclose(image.GetDirection(), reference.GetDirection(), atol=1e-6)
    np.testing.assert_allclose(image.GetOrigin(), expected.GetOrigin(), atol=1e-5)


def test_a_series_is_forced_by_number_or_uid(tmp_path):
    uids = _export(tmp_path)
    fill, record = open_dicom_series(tmp_path, series="3")
    assert record["series_instance_uid"] == uids["thick"] and fill.result().GetSize()[2] == 4
    _, record = open_dicom_series(tmp_path, series=uids["thick"])
    assert record["slice_spacing_mm"] == pytest.approx(2.4)
    with pytest.raises(EMRegError, match="no DICOM series '9'.*available"):
        open_dicom_series(tmp_path, series="9")
    with pytest.raises(EMRegError, match="localizer"):
        open_dicom_series(tmp_path, series="1")


def test_a_series_asked_for_a_ct_that_is_one_image_is_said_to_be_ignored(standard_case, tmp_path, capsys):
    assert main(["detect", str(standard_case), "--out", str(tmp_path / "out"), "--series", "3", "--quiet"]) == 0
    warning = [line for line in capsys.readouterr().err.splitlines() if "warning" in line]
    assert len(warning) == 1 and "'3' was asked for" in warning[0] and "one image, not a DICOM folder" in warning[0]


def test_equally_good_series_of_different_geometry_are_an_error_never_a_guess(tmp_path):
    volume = make_volume()
    write_series(volume, tmp_path / "A", uid(1), number=5, description="head")
    shifted = sitk.Image(volume)
    shifted.SetOrigin((0.0, 0.0, 50.0))
    write_series(shifted, tmp_path / "B", uid(2), number=6, description="neck")
    with pytest.raises(EMRegError, match="2 equally good CT series of different geometry") as info:
        open_dicom_series(tmp_path)
    assert "\n" not in str(info.value) and "series 5" in str(info.value) and "series 6" in str(info.value)
    # two kernels of one reconstruction (same geometry): either serves, the first by number is taken
    shutil.rmtree(tmp_path / "B")
    write_series(volume, tmp_path / "B", uid(3), number=7, description="bone kernel")
    assert choose_series(scan_series(tmp_path), tmp_path).uid == uid(1)


def test_cli_refuses_a_folder_without_ct_volume_in_one_line(tmp_path, capsys):
    volume = make_volume()
    write_series(volume[:, :, :2], tmp_path / "ct" / "a", uid(1), image_type="ORIGINAL\\PRIMARY\\LOCALIZER")
    write_series(volume, tmp_path / "ct" / "b", uid(2), modality="MR")
    assert main(["detect", str(tmp_path / "ct"), "--out", str(tmp_path / "out"), "--quiet"]) == 2
    err = capsys.readouterr().err.strip()
    assert "no CT volume among 2 DICOM series" in err and len(err.splitlines()) == 1
    assert not (tmp_path / "out" / "markers.json").exists()
    (tmp_path / "empty").mkdir()
    (tmp_path / "empty" / "notes.txt").write_text("nothing here")
    assert main(["detect", str(tmp_path / "empty"), "--out", str(tmp_path / "out"), "--quiet"]) == 2
    assert "no DICOM image series" in capsys.readouterr().err


@pytest.mark.parametrize("defect", ["gap", "duplicate", "tilt"])
def test_missing_duplicate_or_sheared_slices_are_refused_naming_the_files(tmp_path, defect):
    volume = make_volume(spacing=(0.5, 0.5, 1.0))
    direction = np.asarray(volume.GetDirection()).reshape(3, 3)
    positions = [np.asarray(volume.TransformIndexToPhysicalPoint((0, 0, k))) for k in range(12)]
    if defect == "tilt":  # a 15 degree gantry tilt: each slice slides along the column direction
        positions = [p + np.tan(np.radians(15)) * k * 1.0 * direction[:, 1] for k, p in enumerate(positions)]
    files = write_series(volume, tmp_path, uid(1), positions=positions)
    if defect == "gap":
        files[6].unlink()
    if defect == "duplicate":
        dataset = pydicom.dcmread(files[4])
        dataset.SOPInstanceUID = uid(1, 99)
        dataset.save_as(tmp_path / "copy.dcm")
    with pytest.raises(EMRegError) as info:
        read_ct(tmp_path)
    message = str(info.value)
    assert "\n" not in message
    if defect == "gap":
        assert "IM00006.dcm and IM00008.dcm" in message and "missing slice" in message
    elif defect == "duplicate":
        assert "duplicate slice position" in message and "IM00005.dcm" in message and "copy.dcm" in message
    else:
        assert "gantry tilt of 15.0 deg" in message


def test_rescale_per_slice_and_unsigned_pixels_give_the_stored_hu(tmp_path):
    stored = make_volume(pixel=sitk.sitkUInt16, seed=3)  # 0 .. 3000 stored, unsigned, 12 bits
    rescale = [(1.0, -1024.0) if k % 2 else (2.0, -2048.0) for k in range(stored.GetSize()[2])]
    files = write_series(stored, tmp_path, uid(5), rescale=rescale, bits_stored=12)
    image = read_ct(tmp_path)
    values = _voxels(stored).astype(float)
    slopes, intercepts = (np.array(v)[:, None, None] for v in zip(*rescale, strict=True))
    np.testing.assert_array_equal(_voxels(image), values * slopes + intercepts)
    assert image.GetPixelID() == sitk.sitkInt16  # -2048 .. 6142 fits: integral rescales need no float copy
    np.testing.assert_array_equal(_voxels(image), _voxels(_series_reader(files)).astype(float))
    fractional = [(0.5, -1000.5)] * len(files)
    for path, (slope, intercept) in zip(files, fractional, strict=True):
        dataset = pydicom.dcmread(path)
        dataset.RescaleSlope, dataset.RescaleIntercept = str(slope), str(intercept)
        dataset.save_as(path)
    image = read_ct(tmp_path)
    assert image.GetPixelID() == sitk.sitkFloat32
    np.testing.assert_allclose(_voxels(image), values * 0.5 - 1000.5, atol=1e-3)


def test_dicomdir_export_is_read_and_a_missing_file_named(tmp_path):
    from pydicom.fileset import FileSet

    source = tmp_path / "source"
    files = write_series(make_volume(), source, uid(7), number=2)
    write_series(make_volume()[:, :, :2], source, uid(8), number=1, prefix="SC",
                 image_type="ORIGINAL\\PRIMARY\\LOCALIZER")
    fileset = FileSet()
    for path in sorted(source.glob("*.dcm")):
        fileset.add(pydicom.dcmread(path))
    export = tmp_path / "export"
    fileset.write(export)  # DICOMDIR + files named by pydicom (no extensions, in subfolders)
    assert (export / "DICOMDIR").is_file()
    image = read_ct(export)
    np.testing.assert_array_equal(_voxels(image), _voxels(_series_reader(files)))
    victim = next(p for p in sorted(export.rglob("*")) if p.is_file() and p.name != "DICOMDIR")
    victim.unlink()
    with pytest.raises(EMRegError, match="DICOMDIR: refers to a missing file") as info:
        read_ct(export)
    assert victim.name in str(info.value)


def test_one_unreadable_slice_is_named_and_nothing_is_written(tmp_path, capsys):
    files = write_series(make_volume(), tmp_path / "ct", uid(9))
    data = files[5].read_bytes()
    files[5].write_bytes(data[: len(data) - 1500])  # pixel data cut short
    assert main(["detect", str(tmp_path / "ct"), "--out", str(tmp_path / "out"), "--quiet"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and files[5].name in err, err
    assert not (tmp_path / "out" / "markers.json").exists()


@pytest.mark.skipif(bool(tools_available()), reason=f"DICOM tools missing: {tools_available()} (scripts/setup)")
@pytest.mark.parametrize("syntax", sorted(TRANSFER_SYNTAXES))
def test_every_transfer_syntax_hospitals_use(tmp_path, syntax):
    volume = make_volume(seed=4, smooth=True)
    files = write_series(volume, tmp_path, uid(11))
    plain_uid = transfer_syntax_uid(files[0])
    convert(files, syntax)
    assert transfer_syntax_uid(files[0]) != plain_uid  # the tool really re-encoded the files
    image = read_ct(tmp_path)
    expected = _voxels(volume)
    _, lossless = TRANSFER_SYNTAXES[syntax]
    if lossless:
        np.testing.assert_array_equal(_voxels(image), expected)
    else:
        error = np.abs(_voxels(image).astype(float) - expected)
        assert 0 < error.mean() < 0.01 * np.ptp(expected), (error.mean(), np.ptp(expected))  # lossy, close
    np.testing.assert_array_equal(_voxels(image), _voxels(_series_reader(files)))


@pytest.fixture(scope="module")
def hard_export(hard_case, tmp_path_factory):
    """The hard case's series in a scanner-like export beside a thick reconstruction and a scout."""
    export = tmp_path_factory.mktemp("hard_export")
    shutil.copytree(hard_case / "ct", export / "DICOM" / "SER001")
    thin = read_ct(hard_case / "ct")
    write_series(sitk.Cast(thin[:, :, ::4], sitk.sitkInt16), export / "DICOM" / "SER002", uid(21), number=3,
                 description="thick 3.2 mm")
    write_series(sitk.Cast(thin[:, :, 100:103], sitk.sitkInt16), export / "DICOM" / "SER000", uid(22), number=1,
                 description="topogram", image_type="ORIGINAL\\PRIMARY\\LOCALIZER")
    return export


def test_detect_on_a_multi_series_export_uses_the_thin_volume_and_says_so(hard_case, hard_export, tmp_path):
    from test_detection_cases import errors_against_truth

    assert main(["detect", str(hard_export), "--out", str(tmp_path), "--quiet"]) == 0
    document = json.loads((tmp_path / "markers.json").read_text())
    series_uid = pydicom.dcmread(next((hard_case / "ct").iterdir()), stop_before_pixels=True).SeriesInstanceUID
    assert document["ct_series"]["series_instance_uid"] == series_uid
    assert document["ct_series"]["slice_spacing_mm"] == pytest.approx(0.8, abs=1e-3)
    assert {o["series_instance_uid"] for o in document["ct_series"]["others"]} == {uid(21), uid(22)}
    origin_errors, _, false, missed = errors_against_truth(read_detection(tmp_path), load_truth(hard_case))
    assert not false and not missed and np.median(origin_errors) < 0.25


@pytest.mark.parametrize("signed", [True, False])
def test_uncompressed_slices_are_read_directly_and_match_gdcm(tmp_path, monkeypatch, signed):
    """Uncompressed slices skip GDCM (read straight into the volume); the voxels are GDCM's."""
    from EMRegModule.io import dicom_read

    pixel = sitk.sitkInt16 if signed else sitk.sitkUInt16
    files = write_series(make_volume(pixel=pixel, seed=6), tmp_path, uid(12), bits_stored=12,
                         rescale=[(1.0, -1024.0 if not signed else 0.0), (2.0, -7.0)] * 6)
    direct: list[bool] = []
    original = dicom_read._read_uncompressed

    def spied(header, data, out) -> bool:
        direct.append(original(header, data, out))
        return direct[-1]

    monkeypatch.setattr(dicom_read, "_read_uncompressed", spied)
    image = read_ct(tmp_path)
    assert direct == [True] * len(files)
    np.testing.assert_array_equal(_voxels(image), _voxels(_series_reader(files)).astype(float))
    monkeypatch.setattr(dicom_read, "_read_uncompressed", lambda h, data, out: False)  # GDCM for every slice
    np.testing.assert_array_equal(_voxels(read_ct(tmp_path)), _voxels(image))


def test_detection_while_decoding_gives_the_markers_of_the_whole_image(hard_case, hard_export):
    """Detection on slices as they are decoded (thread pool) equals detection on the image read whole."""
    from EMRegModule.core.detection import detect_markers
    from EMRegModule.pipeline.controller import EMRegController

    streamed = EMRegController().make("detect", ct=hard_export)
    whole = detect_markers(read_ct(hard_case / "ct"))
    assert len(streamed.markers) == len(whole.markers) > 0
    np.testing.assert_array_equal(streamed.origins, whole.origins)
    np.testing.assert_array_equal(streamed.axes, whole.axes)


def test_emreg_detect_reads_the_series_without_an_image_with_the_same_markers(hard_case, tmp_path, monkeypatch):
    """``emreg detect`` needs the voxels only while it detects: an uncompressed series is indexed in its files
    (``voxels_only``: no SimpleITK image of the volume, which SimpleITK fills with zeros before the first slice, nor
    any copy of it), with the same voxels and geometry as the image, and the same markers as a detection that keeps
    the image."""
    from EMRegModule.io import dicom_read
    from EMRegModule.io.markers_json import write_detection
    from EMRegModule.pipeline.controller import EMRegController

    kept = EMRegController()
    whole = kept.make("detect", ct=hard_case / "ct")
    image = kept.inputs.image
    fill, _ = open_dicom_series(hard_case / "ct", compact=True, voxels_only=True)
    assert fill.result() is None  # no SimpleITK image holds the voxels
    geometry = fill.geometry
    np.testing.assert_array_equal(fill.voxels, _voxels(image))
    for getter in ("GetSize", "GetSpacing", "GetOrigin", "GetDirection", "GetPixelID", "GetPixelIDTypeAsString",
                   "GetDimension", "GetNumberOfComponentsPerPixel"):
        assert getattr(geometry, getter)() == getattr(image, getter)()  # SimpleITK's numbers, without SimpleITK
    filled = []
    writable = dicom_read.writable_bytes
    monkeypatch.setattr(dicom_read, "writable_bytes", lambda image: filled.append(image) or writable(image))
    assert main(["detect", str(hard_case / "ct"), "--out", str(tmp_path), "--quiet"]) == 0
    assert not filled  # no SimpleITK image was filled
    write_detection(whole, tmp_path / "kept")
    documents = [json.loads((folder / "markers.json").read_text()) for folder in (tmp_path, tmp_path / "kept")]
    for document in documents:
        document.pop("provenance", None)
    assert documents[0] == documents[1] and documents[0]["markers"]


def test_emreg_detect_on_an_uncompressed_series_does_not_load_simpleitk(hard_case, tmp_path):
    """Nothing of an uncompressed series' read into fresh memory, nor detection on it, needs SimpleITK: its 270 MB
    library (50 ms of CPU to load, before the first slice is decoded) stays unloaded, and the markers are the ones
    of a read through it (above)."""
    import os
    import subprocess
    import sys

    script = ("import sys\n"
              "from EMRegModule.cli.main import main\n"
              f"code = main(['detect', {str(hard_case / 'ct')!r}, '--out', {str(tmp_path)!r}, '--quiet'])\n"
              "print(code, 'SimpleITK' in sys.modules)\n")
    result = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=300,
                            env=dict(os.environ))
    assert result.returncode == 0, result.stderr
    assert result.stdout.split()[-2:] == ["0", "False"]


@pytest.mark.skipif(bool(tools_available()), reason=f"DICOM tools missing: {tools_available()} (scripts/setup)")
def test_quick_header_reader_agrees_with_pydicom_on_every_syntax(tmp_path, monkeypatch):
    """The quick header walk gives pydicom's values; files it does not handle go to pydicom."""
    from EMRegModule.io import dicom_header, dicom_series

    volume = make_volume(seed=8)
    quick_used = 0
    for syntax in ["plain", *sorted(TRANSFER_SYNTAXES)]:
        folder = tmp_path / syntax
        files = write_series(volume[:, :, :3], folder, uid(13), number=4, description="dé scription",
                             rescale=[(2.0, -5.0)] * 3, bits_stored=12)
        if syntax != "plain":
            convert(files, syntax)
        for path in files:
            quick_used += dicom_header.quick_header(path) is not None
            fast = dicom_series.read_header(path)
            with monkeypatch.context() as patch:
                patch.setattr(dicom_series, "quick_header", lambda p: None)
                slow = dicom_series.read_header(path)
            for name in ("series_uid", "series_number", "description", "modality", "image_type", "sop_class",
                         "transfer_syntax", "pixel_spacing", "rows", "columns", "frames", "slope", "intercept",
                         "bits_stored", "signed", "samples", "instance", "bits_allocated", "photometric"):
                assert getattr(fast, name) == getattr(slow, name), (syntax, name)
            np.testing.assert_allclose(fast.position, slow.position)
            np.testing.assert_allclose(fast.orientation, slow.orientation)
    assert quick_used >= 3 * 6  # plain and the little-endian compressed syntaxes take the quick walk


def test_the_folder_sha256_comes_from_the_read_and_equals_a_pass_of_its_own(tmp_path):
    """The provenance's sha256 of a DICOM folder is made from the bytes each slice is decoded from, plus the
    folder's other files (another series, a README): the same value as ``file_sha256`` of the folder."""
    import hashlib

    from EMRegModule.io.provenance import file_sha256, folder_sha256

    _export(tmp_path)
    convert(sorted((tmp_path / "S2").iterdir()), "jpeg-lossless")  # chunks decoded by GDCM
    (tmp_path / ".hidden").write_bytes(b"part of the folder too")
    fill, _ = open_dicom_series(tmp_path)
    fill.result()
    expected = {p.relative_to(tmp_path).as_posix(): hashlib.sha256(p.read_bytes()).digest()
                for p in tmp_path.rglob("*") if p.is_file()}
    assert fill.sha256.result() == folder_sha256(expected) == file_sha256(tmp_path)
    fill, _ = open_dicom_series(tmp_path, series=uid(20))  # the compressed series read
    fill.result()
    assert fill.sha256.result() == file_sha256(tmp_path)
    (tmp_path / "README.txt").write_text("changed")
    assert file_sha256(tmp_path) != folder_sha256(expected)


def test_slices_hashed_while_the_volume_is_allocated_are_not_hashed_again_and_the_sha256_holds(tmp_path,
                                                                                                 monkeypatch):
    """The first slices are hashed while the volume is zeroed (here: for three rounds of the pool); their
    decoding reads them without hashing them again, and the folder's sha256 and the voxels are those of a plain
    read."""
    from EMRegModule.io import dicom_read
    from EMRegModule.io.provenance import file_sha256

    _export(tmp_path)
    rounds = iter([True, True, True])
    monkeypatch.setattr(dicom_read._EarlyImage, "allocating", lambda self: next(rounds, False))
    hashed: list[bool] = []
    file_bytes = dicom_read._file_bytes

    def counted(path, hashed_here=True):
        hashed.append(hashed_here)
        return file_bytes(path, hashed_here)

    monkeypatch.setattr(dicom_read, "_file_bytes", counted)
    fill, _ = open_dicom_series(tmp_path, workers=2)
    image = fill.result()
    assert hashed.count(True) == image.GetSize()[2] and hashed.count(False) == 3  # three rounds of one slice each
    assert fill.sha256.result() == file_sha256(tmp_path)
    np.testing.assert_array_equal(_voxels(image), _voxels(_series_reader(sorted((tmp_path / "S1").glob("*.dcm")))))


def test_enhanced_multiframe_ct_is_chosen_and_placed_from_its_functional_groups(tmp_path):
    """An Enhanced CT file (frames stored top down) beside a thick classic series: it is the volume used,
    its frames ordered along the normal, its geometry that of the same volume exported slice by slice."""
    from dicom_files import write_enhanced_ct

    volume = make_volume(seed=12)
    count = volume.GetSize()[2]
    write_enhanced_ct(volume, tmp_path / "EN" / "ENHANCED.dcm", uid(50), frame_order=range(count - 1, -1, -1))
    write_series(volume[:, :, ::3], tmp_path / "THICK", uid(51), number=3, description="thick")
    classic = write_series(volume, tmp_path.parent / f"{tmp_path.name}-classic" / "S", uid(52))
    chosen = choose_series(scan_series(tmp_path), tmp_path)
    assert chosen.uid == uid(50) and chosen.multiframe and chosen.size == volume.GetSize()
    image = read_ct(tmp_path)
    reference = _series_reader(classic)  # the classic export of the same volume, as SimpleITK reads it
    np.testing.assert_allclose(image.GetOrigin(), reference.GetOrigin(), atol=1e-5)
    np.testing.assert_allclose(image.GetSpacing(), reference.GetSpacing(), atol=1e-5)
    np.testing.assert_allclose(image.GetDirection(), reference.GetDirection(), atol=1e-6)
    np.testing.assert_array_equal(_voxels(image), _voxels(volume).astype(np.int32) - 1024)
    np.testing.assert_array_equal(_voxels(image), _voxels(reference) - 1024)


def test_enhanced_ct_with_a_missing_frame_or_unreadable_pixels_is_refused_in_one_line(tmp_path, capsys):
    from dicom_files import write_enhanced_ct

    volume = make_volume(seed=13)
    positions = [volume.TransformIndexToPhysicalPoint((0, 0, k + (k >= 6))) for k in range(volume.GetSize()[2])]
    write_enhanced_ct(volume, tmp_path / "gap" / "EN.dcm", uid(53), positions=positions)  # frame 7 is one too far
    assert main(["detect", str(tmp_path / "gap"), "--out", str(tmp_path / "out"), "--quiet"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "EN.dcm frame 6" in err and "EN.dcm frame 7" in err, err
    path = write_enhanced_ct(volume, tmp_path / "cut" / "EN.dcm", uid(54))
    data = path.read_bytes()
    path.write_bytes(data[: len(data) - 3000])  # pixel data cut short: GDCM cannot decode it
    assert main(["detect", str(tmp_path / "cut"), "--out", str(tmp_path / "out"), "--quiet"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "EN.dcm" in err, err
    assert not (tmp_path / "out" / "markers.json").exists()


def test_the_volume_allocated_while_headers_are_read_is_used_only_when_it_fits(tmp_path, monkeypatch):
    from EMRegModule.io import dicom_read

    taken: list[bool] = []
    original = dicom_read._EarlyImage.take

    def spied(self, series):
        image = original(self, series)
        taken.append(image is not None)
        return image

    monkeypatch.setattr(dicom_read._EarlyImage, "take", spied)
    volume = make_volume(seed=14)
    files = write_series(volume, tmp_path / "one", uid(60))
    np.testing.assert_array_equal(_voxels(read_ct(tmp_path / "one")), _voxels(_series_reader(files)))
    write_series(volume[:, :, ::3], tmp_path / "two" / "A", uid(61), description="thick")  # read first: 4 slices
    thin = write_series(volume, tmp_path / "two" / "B", uid(62), description="thin")
    np.testing.assert_array_equal(_voxels(read_ct(tmp_path / "two")), _voxels(_series_reader(thin)))
    assert taken == [True, False]


@pytest.mark.skipif(bool(tools_available()), reason=f"DICOM tools missing: {tools_available()} (scripts/setup)")
def test_compressed_runs_of_slices_keep_each_slices_own_rescale(tmp_path):
    """GDCM decodes compressed slices a run at a time: each slice keeps its own slope and intercept, as
    GDCM gives them file by file; one bad file in a run is still the one named."""
    files = write_series(make_volume(seed=15, size=(48, 40, 19)), tmp_path, uid(16), bits_stored=12,
                         rescale=[(1.0, -1024.0), (2.0, -7.0), (1.0, 5.0)] * 6 + [(3.0, 1.0)])
    convert(files, "jpeg-lossless")
    one_by_one = np.stack([_voxels(sitk.ReadImage(str(f), imageIO="GDCMImageIO")) for f in files])
    np.testing.assert_array_equal(_voxels(read_ct(tmp_path)), one_by_one.reshape(len(files), 40, 48))
    data = files[10].read_bytes()
    files[10].write_bytes(data[: len(data) // 2])  # inside the second run of eight
    with pytest.raises(EMRegError) as info:
        read_ct(tmp_path)
    assert files[10].name in str(info.value) and "\n" not in str(info.value)


@pytest.mark.parametrize("syntax", ["uncompressed", "jpeg-lossless"])
def test_a_compact_read_holds_int16_and_a_slice_beyond_it_is_read_again_exactly(tmp_path, syntax):
    """16 stored bits with intercept -1024 take int32 to hold what the headers allow; detection reads such a
    series as int16 (the CT's own values fit), and reads it again as int32 when one slice does not fit."""
    from EMRegModule.errors import NoSafeAnswerError
    from EMRegModule.io.dicom_read import NarrowVoxelsError
    from EMRegModule.pipeline.controller import EMRegController
    from EMRegModule.progress import Progress

    if syntax != "uncompressed" and tools_available():
        pytest.skip(f"DICOM tools missing: {tools_available()} (scripts/setup)")
    stored = make_volume(pixel=sitk.sitkUInt16, seed=16)  # 0 .. 3000 stored, all 16 bits in the header
    files = write_series(stored, tmp_path / "fits", uid(70), rescale=[(1.0, -1024.0)] * 12, bits_stored=16)
    if syntax != "uncompressed":
        convert(files, syntax)
    exact = _voxels(_series_reader(files))
    assert exact.dtype == np.int32  # what SimpleITK gives: -1024 .. 64511 HU needs int32
    fill, _ = open_dicom_series(tmp_path / "fits", compact=True)
    compact = fill.result()
    assert compact.GetPixelID() == sitk.sitkInt16
    np.testing.assert_array_equal(_voxels(compact), exact)
    assert read_ct(tmp_path / "fits").GetPixelID() == sitk.sitkInt32  # a plain read keeps the exact type

    values = _voxels(stored)
    values[7, 5, 6] = 40000  # 38976 HU: beyond int16, in the middle of the series
    beyond = sitk.GetImageFromArray(values)
    beyond.CopyInformation(stored)
    files = write_series(beyond, tmp_path / "beyond", uid(71), rescale=[(1.0, -1024.0)] * 12, bits_stored=16)
    if syntax != "uncompressed":
        convert(files, syntax)
    fill, _ = open_dicom_series(tmp_path / "beyond", compact=True)
    with pytest.raises(NarrowVoxelsError) as info:
        fill.result()
    assert files[7].name in str(info.value)
    log = io.StringIO()
    controller = EMRegController(progress=Progress(log))
    with pytest.raises(NoSafeAnswerError):  # no marker in this volume: the answer of the whole, exact image
        controller.make("detect", ct=tmp_path / "beyond")
    assert "reading the CT again with int32 voxels" in log.getvalue()
    image = read_ct(tmp_path / "beyond")
    assert image.GetPixelID() == sitk.sitkInt32 and int(_voxels(image).max()) == 38976


def _unsigned_copy(hard_case: Path, folder: Path, series_uid: str, beyond_int16: bool) -> Path:
    """The hard case with its CT stored the way many scanners store it: unsigned 16 bits, intercept -1024
    (SimpleITK reads it as int32); ``beyond_int16``: one voxel far from the frame at 40000 stored (38976 HU)."""
    shutil.copytree(hard_case, folder, ignore=shutil.ignore_patterns("ct"))
    hu = read_ct(hard_case / "ct")
    stored = np.clip(_voxels(hu).astype(np.int32) + 1024, 0, 65535).astype(np.uint16)
    if beyond_int16:
        stored[len(stored) // 2, 0, 0] = 40000
    image = sitk.GetImageFromArray(stored)
    image.CopyInformation(hu)
    write_series(image, folder / "ct", series_uid, rescale=[(1.0, -1024.0)] * len(stored), bits_stored=16)
    return folder


@pytest.mark.parametrize("beyond_int16", [False, True])
def test_report_reads_a_dicom_ct_compact_and_again_exactly_when_a_value_does_not_fit(hard_case, tmp_path,
                                                                                      beyond_int16):
    """``emreg report`` reads a 16-bit DICOM CT with an intercept as int16, like the detection (half the memory
    of SimpleITK's int32), and reads it again as int32 when a slice does not fit: its figures are those the run
    drew from the CT it held, byte for byte."""
    from EMRegModule.report.figures import ReportData, prepare_ct_products
    from EMRegModule.report.inputs import load_report_inputs

    case = _unsigned_copy(hard_case, tmp_path / "case", uid(80 + beyond_int16), beyond_int16)
    written = read_ct(case / "ct")  # read once (80 million voxels): its type and its largest value are checked
    written_pixel_id, written_max = written.GetPixelID(), int(_voxels(written).max())
    del written
    assert written_pixel_id == sitk.sitkInt32  # what the headers call for
    out = tmp_path / "out"
    assert main(["run", str(case), "--out", str(out), "--quiet"]) == 0
    figures = {p.name: p.read_bytes() for p in (out / "report_figures").glob("*.png")}
    assert {"scene_oblique.png", "marker_slices.png"} <= set(figures)
    assert main(["report", str(out), "--quiet"]) == 0
    assert {p.name: p.read_bytes() for p in (out / "report_figures").glob("*.png")} == figures

    inputs = load_report_inputs(out)
    assert inputs.ct.image.GetPixelID() == sitk.sitkInt16  # the compact read, before any slice is in
    data = ReportData(inputs, rows=[], points={})
    prepare_ct_products(data)
    image = inputs.image
    assert image.GetPixelID() == (sitk.sitkInt32 if beyond_int16 else sitk.sitkInt16)
    assert int(_voxels(image).max()) == (38976 if beyond_int16 else written_max)
