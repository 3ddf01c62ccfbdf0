"""Defects a sweep of DICOM series as other scanners and PACS exports write them found, each checked
against GDCM's reading of the same files (``SimpleITK.ImageSeriesReader``) on series made here.

- A slice written with the 128-byte preamble but without its ``DICM`` marker (nor file meta), as some old
  exports write them, was taken for a file that is not DICOM and left out without a word: the last slice of
  a series read as a volume one slice shorter, no error (GDCM's series reader leaves it out too, and GDCM
  cannot read the file alone). Such a file is now named in a one-line error (exit 2).
- A MONOCHROME1 CT was read as GDCM reads it: with its stored values inverted before the rescale, so a
  simulated case's HU ran -3480 .. -1025 and ``emreg detect`` stopped with "0 marker(s) found ... check the
  [detection] thresholds" (exit 3). GDCM's HU being no HU, the series is now refused in one line naming the
  file (exit 2).
- A colour series (Samples per Pixel 3) was refused as "not greyscale" without naming a file; the message
  now names the file and its samples per pixel.

Variants that already gave GDCM's voxels and geometry, kept here so that they keep doing so: 12 stored
bits with garbage (overlay) in the high bits, signed and unsigned, little and big endian; unsigned pixels
with intercept -1024; slopes 0.5 / 2 and intercepts differing per slice; implicit VR, explicit big endian,
deflated; files named in reverse, Instance Numbers disagreeing with the positions, descending positions, a
negative Spacing Between Slices, Slice Thickness absent or different from the spacing; an orientation 1e-6
off orthonormal, oblique, FFS / HFP directions; Pixel Padding Value with values beyond it; 511 columns,
Rows != Columns; files without preamble (raw implicit or explicit datasets). On the simulator's DICOM
output, 12 stored bits with garbage high bits, big endian and shuffled file names give the 8 markers of
the truth. A series mixing two slice sizes is refused naming both files (GDCM refuses it too); a DICOMDIR
export with upper-case names in subfolders is covered by test_dicom_series.py.
"""

from __future__ import annotations

import io
import random
import shutil
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pydicom
import pytest
import SimpleITK as sitk
from conftest import load_truth
from dicom_files import convert, make_volume, tools_available, uid, write_series
from pydicom.dataelem import DataElement
from test_detection_cases import errors_against_truth

from EMRegModule.cli.main import main
from EMRegModule.errors import EMRegError
from EMRegModule.io.image import open_ct, read_ct
from EMRegModule.io.markers_json import read_detection

_TOOLS = tools_available()


def _gdcm(folder: Path) -> sitk.Image:
    """GDCM's reading of ``folder``'s series: its own file choice and order, its own geometry."""
    reader = sitk.ImageSeriesReader()
    reader.SetFileNames(sitk.ImageSeriesReader.GetGDCMSeriesFileNames(str(folder)))
    return reader.Execute()


def _assert_as_gdcm(folder: Path) -> None:
    """EMReg's voxels (exact and compact reads, and ``emreg detect``'s: the series indexed in its files where it
    can be, ``voxels_only``) and geometry are GDCM's."""
    expected, image = _gdcm(folder), read_ct(folder)
    values = sitk.GetArrayFromImage(image)
    np.testing.assert_array_equal(values.astype(float), sitk.GetArrayFromImage(expected).astype(float))
    np.testing.assert_array_equal(sitk.GetArrayFromImage(open_ct(folder, compact=True).result()), values)
    for_detection = open_ct(folder, compact=True, voxels_only=True)
    image_held = for_detection.result()  # float voxels (slopes) are held by an image
    voxels = sitk.GetArrayFromImage(image_held) if for_detection.voxels is None else for_detection.voxels
    np.testing.assert_array_equal(np.asarray(voxels), values)
    for name in ("GetOrigin", "GetSpacing", "GetDirection"):
        np.testing.assert_allclose(getattr(image, name)(), getattr(expected, name)(), atol=1e-5, err_msg=name)


def _series(folder: Path, pixel: int = sitk.sitkInt16, size=(33, 20, 6), image: sitk.Image | None = None,
            **options) -> list[Path]:
    image = image if image is not None else make_volume(size=size, pixel=pixel, seed=3)
    return write_series(image, folder, uid(99), **options)


def _edit(files: list[Path], change: Callable[[int, pydicom.Dataset], None]) -> None:
    for k, path in enumerate(files):
        dataset = pydicom.dcmread(path)
        change(k, dataset)
        dataset.save_as(path)


def _overlay_bits(files: list[Path], seed: int = 1) -> None:
    """Random garbage in the 4 high bits of every 16-bit value (BitsStored 12: overlays, as old scanners)."""
    rng = np.random.default_rng(seed)

    def change(k: int, dataset: pydicom.Dataset) -> None:
        stored = np.frombuffer(dataset.PixelData, dtype="<u2")
        noise = rng.integers(0, 16, stored.shape).astype(np.uint16) << 12
        dataset.PixelData = ((stored & 0x0FFF) | noise).tobytes()

    _edit(files, change)


def _rename(files: list[Path], order: list[Path]) -> None:
    """File ``files[i]``'s contents moved to the name ``order[i]``."""
    moved = [path.rename(path.with_suffix(".moving")) for path in files]
    for source, target in zip(moved, order, strict=True):
        source.rename(target)


def _raw_dataset(path: Path, implicit: bool = True) -> bytes:
    """``path``'s dataset without preamble, marker or file meta (as old exports write it)."""
    dataset = pydicom.dcmread(path)
    del dataset.file_meta
    buffer = io.BytesIO()
    pydicom.dcmwrite(buffer, dataset, implicit_vr=implicit, little_endian=True, enforce_file_format=False)
    return buffer.getvalue()


def _directed(direction: list[float]) -> sitk.Image:
    image = make_volume(size=(33, 20, 6), seed=3)
    image.SetDirection(direction)
    return image


def _descending() -> list[float]:
    """make_volume's direction with the slice axis reversed (slice positions descending along the normal)."""
    direction = np.asarray(make_volume(size=(2, 2, 2)).GetDirection()).reshape(3, 3)
    direction[:, 2] *= -1
    return direction.ravel().tolist()


def _oblique() -> list[float]:
    from scipy.spatial.transform import Rotation

    return Rotation.from_euler("xyz", [20, -15, 35], degrees=True).as_matrix().ravel().tolist()


def _padding(k: int, dataset: pydicom.Dataset) -> None:
    dataset[0x00280120] = DataElement(0x00280120, "SS", -2000)
    stored = np.frombuffer(dataset.PixelData, dtype="<i2").copy()
    stored[:50], stored[50:60] = -2000, -3000  # padding, and values beyond it
    dataset.PixelData = stored.tobytes()


def _orientation_round_off(k: int, dataset: pydicom.Dataset) -> None:
    values = [float(v) for v in dataset.ImageOrientationPatient]
    values[0] += 1e-6
    values[4] -= 1e-6
    dataset.ImageOrientationPatient = [f"{v:.10g}" for v in values]


def _no_preamble(files: list[Path], implicit: bool) -> None:
    for path in files:
        path.write_bytes(_raw_dataset(path, implicit))


VARIANTS: dict[str, Callable[[Path], None]] = {
    "12 bits signed, overlay bits": lambda f: _overlay_bits(_series(f, bits_stored=12)),
    "12 bits unsigned, overlay bits": lambda f: _overlay_bits(_series(f, sitk.sitkUInt16, bits_stored=12)),
    "unsigned, intercept -1024": lambda f: _edit(_series(f, sitk.sitkUInt16),
                                                 lambda k, d: setattr(d, "RescaleIntercept", "-1024")),
    "slopes and intercepts per slice": lambda f: _series(
        f, rescale=[(0.5, -3.0), (2.0, 5.0), (1.0, -1024.0), (0.5, 0.25), (2.0, 0.0), (1.0, 1.0)]),
    "integer intercepts per slice": lambda f: _series(
        f, rescale=[(1, -1024), (1, -1000), (1, 0), (1, -1024), (1, 3), (1, -1024)]),
    "explicit VR little endian": lambda f: _edit(_series(f), lambda k, d: setattr(
        d.file_meta, "TransferSyntaxUID", pydicom.uid.ExplicitVRLittleEndian)),
    "files named in reverse": lambda f: (lambda files: _rename(files, files[::-1]))(_series(f)),
    "instance numbers disagree": lambda f: _edit(_series(f), lambda k, d: setattr(
        d, "InstanceNumber", str(6 - k if k % 2 else 100 + k))),
    "descending positions": lambda f: _series(f, image=_directed(_descending())),
    "negative spacing between slices": lambda f: _edit(_series(f), lambda k, d: setattr(
        d, "SpacingBetweenSlices", "-0.8")),
    "no slice thickness": lambda f: _edit(_series(f), lambda k, d: delattr(d, "SliceThickness")),
    "thickness not the spacing": lambda f: _edit(_series(f), lambda k, d: (
        setattr(d, "SliceThickness", "2.0"), setattr(d, "SpacingBetweenSlices", "0.8"))),
    "orientation 1e-6 off": lambda f: _edit(_series(f), _orientation_round_off),
    "oblique": lambda f: _series(f, image=_directed(_oblique())),
    "FFS": lambda f: _edit(_series(f, image=_directed([-1, 0, 0, 0, 1, 0, 0, 0, -1])),
                           lambda k, d: setattr(d, "PatientPosition", "FFS")),
    "HFP": lambda f: _edit(_series(f, image=_directed([-1, 0, 0, 0, -1, 0, 0, 0, 1])),
                           lambda k, d: setattr(d, "PatientPosition", "HFP")),
    "pixel padding value": lambda f: _edit(_series(f), _padding),
    "511 columns": lambda f: _series(f, size=(511, 4, 4)),
    "rows != columns": lambda f: _series(f, size=(17, 40, 5)),
    "no preamble, implicit": lambda f: _no_preamble(_series(f), implicit=True),
    "no preamble, explicit": lambda f: _no_preamble(_series(f), implicit=False),
}
TOOL_VARIANTS: dict[str, Callable[[Path], None]] = {
    "big endian": lambda f: convert(_series(f), "big-endian"),
    "big endian, 12 bits signed, overlay bits": lambda f: convert(
        (lambda files: (_overlay_bits(files), files)[1])(_series(f, bits_stored=12)), "big-endian"),
    "deflated": lambda f: convert(_series(f), "deflate"),
}


@pytest.mark.parametrize("variant", sorted(VARIANTS))
def test_vendor_variants_give_gdcms_voxels_and_geometry(tmp_path, variant):
    VARIANTS[variant](tmp_path)
    _assert_as_gdcm(tmp_path)


@pytest.mark.skipif(bool(_TOOLS), reason=f"DICOM tools missing: {_TOOLS} (scripts/setup)")
@pytest.mark.parametrize("variant", sorted(TOOL_VARIANTS))
def test_re_encoded_variants_give_gdcms_voxels_and_geometry(tmp_path, variant):
    TOOL_VARIANTS[variant](tmp_path)
    _assert_as_gdcm(tmp_path)


def _refused(folder: Path, out: Path, capsys) -> str:
    """``emreg detect``'s one-line error on ``folder`` (exit 2, nothing written)."""
    assert main(["detect", str(folder), "--out", str(out), "--quiet"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1, err
    assert not (out / "markers.json").exists()
    return err


def test_a_slice_with_a_preamble_but_no_dicm_marker_is_named_not_left_out(tmp_path, capsys):
    files = _series(tmp_path / "ct")
    files[-1].write_bytes(b"\0" * 128 + _raw_dataset(files[-1]))  # the last slice: leaving it out is silent
    assert len(sitk.ImageSeriesReader.GetGDCMSeriesFileNames(str(tmp_path / "ct"))) == len(files) - 1
    with pytest.raises(EMRegError, match="no 'DICM' marker") as info:
        read_ct(tmp_path / "ct")
    assert str(files[-1]) in str(info.value)
    assert files[-1].name in _refused(tmp_path / "ct", tmp_path / "out", capsys)


def test_a_file_that_is_no_dicom_after_128_bytes_is_still_ignored(tmp_path):
    files = _series(tmp_path)
    (tmp_path / "notes.bin").write_bytes(bytes(range(256)) * 4)
    (tmp_path / "README.txt").write_text("x" * 300)
    assert sitk.GetArrayFromImage(read_ct(tmp_path)).shape[0] == len(files)


def test_monochrome1_is_refused_naming_the_file_not_read_inverted(tmp_path, capsys):
    files = _series(tmp_path / "ct")
    _edit(files[2:3], lambda k, d: setattr(d, "PhotometricInterpretation", "MONOCHROME1"))
    with pytest.raises(EMRegError, match="MONOCHROME1") as info:
        read_ct(tmp_path / "ct")
    assert files[2].name in str(info.value)
    assert files[2].name in _refused(tmp_path / "ct", tmp_path / "out", capsys)


def test_a_colour_series_is_refused_naming_the_file(tmp_path, capsys):
    files = _series(tmp_path / "ct")

    def colour(k: int, dataset: pydicom.Dataset) -> None:
        grey = np.frombuffer(dataset.PixelData, dtype="<i2").astype(np.uint8)
        dataset.SamplesPerPixel, dataset.PhotometricInterpretation, dataset.PlanarConfiguration = 3, "RGB", 0
        dataset.BitsAllocated, dataset.BitsStored, dataset.HighBit, dataset.PixelRepresentation = 8, 8, 7, 0
        dataset.PixelData = np.repeat(grey, 3).tobytes()

    _edit(files, colour)
    err = _refused(tmp_path / "ct", tmp_path / "out", capsys)
    assert files[0].name in err and "3 samples per pixel" in err, err


def test_a_series_mixing_two_slice_sizes_is_refused_naming_both_files(tmp_path, capsys):
    files = _series(tmp_path / "ct")
    other = _series(tmp_path / "other", size=(33, 22, 6))
    dataset = pydicom.dcmread(other[2])
    dataset.SOPInstanceUID = f"{dataset.SOPInstanceUID}.9"
    dataset.save_as(files[2])
    err = _refused(tmp_path / "ct", tmp_path / "out", capsys)
    assert "different sizes" in err and files[0].name in err and files[2].name in err, err


@pytest.fixture(scope="module")
def dicom_case(small_dicom_case) -> Path:
    """A small simulated case (1 mm voxels, 8 markers) whose CT is the simulator's DICOM series: conftest's
    ``small_dicom_case``, read only (the tests copy it before changing its files)."""
    return small_dicom_case


def _unsigned_overlay_bits(files: list[Path]) -> None:
    """The simulator's stored values (HU + 1024, 0 .. 4095 here) as 12 unsigned bits under random high bits."""
    def unsigned(k: int, dataset: pydicom.Dataset) -> None:
        assert int(np.frombuffer(dataset.PixelData, dtype="<i2").min()) >= 0
        dataset.PixelRepresentation, dataset.BitsStored, dataset.HighBit = 0, 12, 11

    _edit(files, unsigned)
    _overlay_bits(files, seed=2)


@pytest.mark.skipif(bool(_TOOLS), reason=f"DICOM tools missing: {_TOOLS} (scripts/setup)")
def test_the_markers_of_a_re_encoded_shuffled_12_bit_export_are_the_truth(dicom_case, tmp_path):
    case = tmp_path / "case"
    shutil.copytree(dicom_case, case)
    files = sorted((case / "ct").iterdir())
    _unsigned_overlay_bits(files)
    convert(files, "big-endian")
    order = list(files)
    random.Random(1).shuffle(order)
    _rename(files, order)
    assert main(["detect", str(case), "--out", str(tmp_path / "out"), "--quiet"]) == 0
    origin_errors, _, false, missed = errors_against_truth(read_detection(tmp_path / "out"), load_truth(case))
    assert not false and not missed and len(origin_errors) == 8
    assert float(np.max(origin_errors)) < 0.5


def test_a_monochrome1_export_is_refused_not_searched_for_markers_in_inverted_values(dicom_case, tmp_path, capsys):
    case = tmp_path / "case"
    shutil.copytree(dicom_case, case)
    files = sorted((case / "ct").iterdir())
    _edit(files, lambda k, d: setattr(d, "PhotometricInterpretation", "MONOCHROME1"))
    err = _refused(case, tmp_path / "out", capsys)
    assert "MONOCHROME1" in err and files[0].name in err, err
