"""Defects a sweep of CT files as other tools write them found (a user's CT is often converted, not straight
from our simulator or the scanner's DICOM), each checked at the command line (``emreg detect``) on a small
simulated case made here, against the case's truth: every marker where the truth puts it, or a one-line
refusal (exit 2) naming the file; never markers in the wrong place. Files the fast reader takes are also
compared with ``sitk.ReadImage`` (geometry and every voxel).

- An NRRD whose ``endian`` is written in capitals (``endian: BIG``, ``Big``) was read little-endian by the fast
  reader while SimpleITK (teem, whose field values are case-insensitive) reads it big-endian: every voxel
  byte-swapped, "0 marker(s) found" (exit 3, blaming the detection thresholds). ``endian``, ``type`` and
  ``encoding`` values are now read in any case, as teem does.
- A MetaImage whose yes/no fields are written ``true``, ``t`` or ``1`` (MetaIO, hence SimpleITK, takes any value
  starting with T, t or 1) was misread by the fast reader: ``BinaryDataByteOrderMSB = true`` gave byte-swapped
  voxels (0 markers found, exit 3), and ``CompressedData = true`` (or ``1``) was taken as raw data and refused as
  "file is truncated" (by the fast reader for a ``.mha``, by the data-length check for a ``.mhd`` + ``.zraw``).
  Both now read the flags as MetaIO does.
- A NIfTI whose sform (code 2, aligned, or 3-5) and qform (code 1) disagree was read at the qform's place
  (ITK's rule) while FSL and nibabel use the sform: with the sform right, all 8 markers came out 30 mm from
  the truth without a word (a ``.hdr`` + ``.img`` pair likewise). Files whose sform places the voxels elsewhere
  than the geometry read (also a sheared sform, which ITK passes over for the qform) are now refused in one
  line that says how to make the two agree.

Already right, tested here: dcm2niix's NIfTI of the simulator's DICOM series (RAS sform/qform, rows
flipped, ``scl_inter`` -1024); NIfTI with ``scl_slope`` 0.5 or ``scl_inter`` -1024, with the qform only
(``sform_code`` 0), the sform only (``qform_code`` 0), or a scanner sform and a qform elsewhere (every
reader takes the sform); NRRD as 3D Slicer writes it (RAS or LPS space, negative space directions, big
endian, gzip or raw, attached or a detached ``.nhdr`` with ``.raw`` / ``.raw.gz``); MetaImage ``.mhd`` +
``.raw`` / ``.zraw`` with ``AnatomicalOrientation`` RAI or LPS and a ``TransformMatrix`` with a flip.
"""

from __future__ import annotations

import json
import re
import shutil
import struct
import subprocess
import zlib
from pathlib import Path

import numpy as np
import pytest
import SimpleITK as sitk
from ct_files import RAS_FROM_LPS, index_to_lps, write_nrrd
from scipy.spatial.transform import Rotation

from EMRegModule.cli.main import main
from EMRegModule.errors import EMRegError
from EMRegModule.io.ct_stream import start_streamed_read
from EMRegModule.io.fast_read import plain_storage, start_fast_read
from EMRegModule.io.image import read_ct

ORIGIN_TOLERANCE_MM = 0.3  # well under the 1 mm voxel


@pytest.fixture(scope="module")
def case(small_dicom_case) -> Path:
    """A small simulated case (1 mm voxels, 8 markers) whose CT is a DICOM series (``case/ct``): conftest's
    ``small_dicom_case``, read only."""
    return small_dicom_case


@pytest.fixture(scope="module")
def hu(case) -> sitk.Image:
    """The case's CT in HU (int16), LPS geometry: the image every variant below stores."""
    image = read_ct(case / "ct")  # int32 (the series' rescale could overflow int16); its HU fit int16
    values = sitk.GetArrayViewFromImage(image)
    assert -32768 <= values.min() and values.max() <= 32767
    return sitk.Cast(image, sitk.sitkInt16)


def _truth_origins(case: Path) -> np.ndarray:
    truth = json.loads((case / "truth.json").read_text())
    return np.array([m["origin"] for m in truth["markers"] if m["in_ct"]])


def _detect(ct: Path, case: Path, capsys) -> tuple[int, dict | None, str]:
    """``emreg detect CT``: the exit code, markers.json (None on failure) and stderr."""
    out = ct.parent / (ct.name.replace(".", "_") + "-out")
    capsys.readouterr()
    code = main(["detect", str(ct), "--settings", str(case / "case.toml"), "--out", str(out), "--quiet"])
    err = capsys.readouterr().err
    found = json.loads((out / "markers.json").read_text()) if code == 0 else None
    return code, found, err


def _assert_markers_at_truth(ct: Path, case: Path, capsys) -> None:
    code, found, err = _detect(ct, case, capsys)
    assert code == 0, err
    truth = _truth_origins(case)
    origins = np.array([m["origin"] for m in found["markers"]]).reshape(-1, 3)
    assert len(origins) == len(truth), f"{ct.name}: {len(origins)} markers found, {len(truth)} in the CT"
    nearest = np.linalg.norm(truth[:, None] - origins[None], axis=2).min(axis=1)
    assert nearest.max() < ORIGIN_TOLERANCE_MM, f"{ct.name}: origins off by up to {nearest.max():.2f} mm"


def _assert_refused(ct: Path, case: Path, capsys, reason: str) -> None:
    code, _, err = _detect(ct, case, capsys)
    lines = err.strip().splitlines()
    assert code == 2, err
    assert len(lines) == 1 and ct.name in lines[0] and reason in lines[0], err


def _assert_fast_read_is_simpleitk(path: Path) -> None:
    """The fast reader, where it takes the file, gives SimpleITK's geometry and voxels."""
    if plain_storage(path) is None:
        return
    fast, reference = start_fast_read(path).result(), sitk.ReadImage(str(path))
    for name in ("GetSize", "GetPixelID", "GetSpacing", "GetOrigin", "GetDirection"):
        assert getattr(fast, name)() == getattr(reference, name)(), name
    np.testing.assert_array_equal(sitk.GetArrayViewFromImage(fast), sitk.GetArrayViewFromImage(reference))


# --- NRRD --------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("space, endian, encoding, name, data_file", [
    ("RAS", "big", "gzip", "slicer.nhdr", "slicer.raw.gz"),
    ("RAS", "big", "raw", "slicer_raw.nhdr", "slicer_raw.raw"),
    ("LPS", "little", "gzip", "slicer_lps.nrrd", None),
    ("RAS", "BIG", "raw", "capital_endian.nrrd", None),  # found: read little-endian by the fast reader
    ("LPS", "Big", "GZIP", "capital_gzip.nrrd", None),
])
def test_nrrd_as_slicer_writes_it(case, hu, tmp_path, capsys, space, endian, encoding, name, data_file):
    path = write_nrrd(tmp_path / name, hu, space, endian, encoding, data_file)
    _assert_fast_read_is_simpleitk(path)
    _assert_markers_at_truth(path, case, capsys)


def test_a_case_folder_whose_ct_is_a_detached_nrrd_header(case, hu, tmp_path, capsys):
    """``ct.nhdr`` + ``ct.raw.gz`` (3D Slicer's "detached header" NRRD) is the case's CT, as ``ct.nrrd`` is."""
    folder = tmp_path / "case"
    folder.mkdir()
    shutil.copy2(case / "case.toml", folder / "case.toml")
    write_nrrd(folder / "ct.nhdr", hu, "RAS", "little", "gzip", "ct.raw.gz")
    capsys.readouterr()
    assert main(["detect", str(folder), "--out", str(tmp_path / "out"), "--quiet"]) == 0, capsys.readouterr().err
    found = json.loads((tmp_path / "out" / "markers.json").read_text())
    truth = _truth_origins(case)
    origins = np.array([m["origin"] for m in found["markers"]]).reshape(-1, 3)
    assert len(origins) == len(truth)
    assert np.linalg.norm(truth[:, None] - origins[None], axis=2).min(axis=1).max() < ORIGIN_TOLERANCE_MM


@pytest.mark.parametrize("units, refused", [('"mm" "mm" "mm"', False), ('"cm" "cm" "cm"', True),
                                             ('"m" "m" "m"', True)])
def test_nrrd_space_units_other_than_mm_are_refused(case, hu, tmp_path, capsys, units, refused):
    """SimpleITK (and 3D Slicer) ignore ``space units`` and read the numbers as mm: a CT in cm would be a tenth of
    its size, its markers missed. Refused in one line; ``mm`` is what every reader assumes and is read."""
    path = write_nrrd(tmp_path / "units.nrrd", hu, "LPS", "little", "gzip")
    header, _, voxels = path.read_bytes().partition(b"\n\n")
    path.write_bytes(header + f"\nspace units: {units}".encode("ascii") + b"\n\n" + voxels)
    if refused:
        _assert_refused(path, case, capsys, f"space units {units.split()[0].strip(chr(34))}")
        with pytest.raises(EMRegError, match="space units"):
            start_streamed_read(path)
    else:
        _assert_markers_at_truth(path, case, capsys)


@pytest.mark.parametrize("header, data", [("ct.nhdr", "ct.raw.gz"), ("ct.mhd", "ct.raw"), ("ct.hdr", "ct.img")])
def test_the_sha256_of_a_detached_header_covers_its_voxels(hu, tmp_path, header, data):
    """Provenance: a CT whose voxels are in a file beside its header changes its sha256 when the voxels change
    (it covered the header's bytes only, so outputs made from the earlier voxels still passed as this CT's)."""
    from EMRegModule.io.provenance import file_sha256

    small = hu[:40, :30, :20]
    if header.endswith(".nhdr"):
        write_nrrd(tmp_path / header, small, "RAS", "little", "gzip", data)
    else:
        sitk.WriteImage(small, str(tmp_path / header))
    assert (tmp_path / data).is_file()
    before = file_sha256(tmp_path / header)
    assert before == file_sha256(tmp_path / header)
    changed = sitk.GetArrayFromImage(small)
    changed[5, 5, 5] += 100
    altered = sitk.GetImageFromArray(changed)
    altered.CopyInformation(small)
    if header.endswith(".nhdr"):
        write_nrrd(tmp_path / header, altered, "RAS", "little", "gzip", data)
    else:
        sitk.WriteImage(altered, str(tmp_path / header))
    assert file_sha256(tmp_path / header) != before


# --- MetaImage ---------------------------------------------------------------------------------------------


def _write_metaimage(path: Path, image: sitk.Image, orientation: str = "RAI", compressed: str | None = None,
                     msb: str | None = None, flip_i: bool = False, data_file: str | None = None) -> Path:
    """A MetaImage by hand: ``compressed`` / ``msb`` the text of CompressedData / BinaryDataByteOrderMSB
    (None: left out), ``flip_i`` stores the i axis reversed (a TransformMatrix with a flip), ``data_file``
    a detached ``.mhd`` whose voxels are in that file (``.raw`` or ``.zraw``)."""
    voxels = sitk.GetArrayFromImage(image)
    matrix = index_to_lps(image)
    if flip_i:
        voxels = voxels[:, :, ::-1]
        matrix = matrix @ np.array([[-1.0, 0, 0, image.GetSize()[0] - 1], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]])
    direction = matrix[:3, :3] / np.asarray(image.GetSpacing())[None, :]
    big = msb is not None and msb[:1] in "Tt1"
    payload = np.ascontiguousarray(voxels).astype(">i2" if big else "<i2").tobytes()
    header = ["ObjectType = Image", "NDims = 3", "BinaryData = True"]
    if msb is not None:
        header.append(f"BinaryDataByteOrderMSB = {msb}")
    if compressed is not None:
        header.append(f"CompressedData = {compressed}")
        if compressed[:1] in "Tt1":
            payload = zlib.compress(payload, 1)
            header.append(f"CompressedDataSize = {len(payload)}")  # without it SimpleITK garbles attached data
    header += ["TransformMatrix = " + " ".join(f"{v:.17g}" for v in direction.T.ravel()),
               "Offset = " + " ".join(f"{v:.17g}" for v in matrix[:3, 3]), "CenterOfRotation = 0 0 0",
               f"AnatomicalOrientation = {orientation}",
               "ElementSpacing = " + " ".join(f"{v:.17g}" for v in image.GetSpacing()),
               "DimSize = " + " ".join(map(str, image.GetSize())), "ElementType = MET_SHORT"]
    if data_file is None:
        path.write_bytes(("\n".join([*header, "ElementDataFile = LOCAL"]) + "\n").encode("ascii") + payload)
    else:
        (path.parent / data_file).write_bytes(payload)
        path.write_text("\n".join([*header, f"ElementDataFile = {data_file}"]) + "\n")
    return path


@pytest.mark.parametrize("name, options", [
    ("ct.mhd", {"orientation": "RAI", "data_file": "ct.raw"}),
    ("flipped.mhd", {"orientation": "LPS", "compressed": "True", "flip_i": True, "data_file": "flipped.zraw"}),
    ("msb_true.mha", {"msb": "true"}),  # found: byte-swapped by the fast reader
    ("compressed_1.mha", {"compressed": "1", "msb": "False"}),  # found: taken as raw, refused as too long
    ("compressed_true.mhd", {"compressed": "true", "data_file": "compressed_true.zraw"}),  # found: "truncated"
])
def test_metaimage_as_other_tools_write_it(case, hu, tmp_path, capsys, name, options):
    path = _write_metaimage(tmp_path / name, hu, **options)
    _assert_fast_read_is_simpleitk(path)
    _assert_markers_at_truth(path, case, capsys)


# --- NIfTI-1 ------------------------------------------------------------------------------------------------


def _write_nifti(path: Path, image: sitk.Image, slope: float = 1.0, intercept: float = 0.0, sform_code: int = 1,
                 qform_code: int = 1, qform_shift_mm: float = 0.0) -> Path:
    """A NIfTI-1 file (348-byte header by hand) of ``image``'s HU stored as int16 ``(HU - intercept) / slope``;
    sform and qform both the image's geometry (RAS), the qform moved ``qform_shift_mm`` along R when asked."""
    index_to_ras = RAS_FROM_LPS @ index_to_lps(image)[:3, :]
    spacing = np.asarray(image.GetSpacing())
    rotation = index_to_ras[:3, :3] / spacing[None, :]
    qfac = 1.0 if np.linalg.det(rotation) > 0 else -1.0
    x, y, z, w = Rotation.from_matrix(rotation @ np.diag([1.0, 1.0, qfac])).as_quat()
    b, c, d = (x, y, z) if w >= 0 else (-x, -y, -z)
    header = bytearray(348)
    struct.pack_into("<i", header, 0, 348)
    struct.pack_into("<8h", header, 40, 3, *image.GetSize(), 1, 1, 1, 1)
    struct.pack_into("<2h", header, 70, 4, 16)  # int16
    struct.pack_into("<8f", header, 76, qfac, *spacing, 0, 0, 0, 0)
    struct.pack_into("<3f", header, 108, 352.0, slope, intercept)
    header[123] = 2 | 8  # mm, s
    struct.pack_into("<2h", header, 252, qform_code, sform_code)
    struct.pack_into("<6f", header, 256, b, c, d, *(index_to_ras[:, 3] + [qform_shift_mm, 0.0, 0.0]))
    struct.pack_into("<12f", header, 280, *index_to_ras.ravel())
    header[344:348] = b"n+1\0"
    stored = np.rint((sitk.GetArrayViewFromImage(image) - intercept) / slope).astype("<i2")
    path.write_bytes(bytes(header) + b"\0" * 4 + stored.tobytes())
    return path


@pytest.mark.parametrize("name, options", [
    ("slope.nii", {"slope": 0.5}),
    ("intercept.nii", {"intercept": -1024.0}),
    ("qform_only.nii", {"sform_code": 0}),
    ("sform_only.nii", {"qform_code": 0}),
    ("scanner_sform.nii", {"sform_code": 1, "qform_shift_mm": 30.0}),  # every reader takes the scanner sform
])
def test_nifti_scaling_and_transforms(case, hu, tmp_path, capsys, name, options):
    path = _write_nifti(tmp_path / name, hu, **options)
    _assert_fast_read_is_simpleitk(path)
    _assert_markers_at_truth(path, case, capsys)


def test_nifti_whose_aligned_sform_and_qform_disagree_is_refused(case, hu, tmp_path, capsys):
    """Found: ITK read the qform (30 mm off), FSL and nibabel read the (right) sform; now refused."""
    path = _write_nifti(tmp_path / "aligned_sform.nii", hu, sform_code=2, qform_code=1, qform_shift_mm=30.0)
    reason = "sform (code 2) and qform (code 1) place the voxels up to 30 mm apart"
    _assert_refused(path, case, capsys, reason)
    with pytest.raises(EMRegError, match=re.escape(reason)):  # the report's streamed read refuses it too
        start_streamed_read(path)
    # the same header as a .hdr + .img pair (magic "ni1"), read by SimpleITK, named by either file
    data = path.read_bytes()
    header = bytearray(data[:348])
    header[108:112], header[344:348] = struct.pack("<f", 0.0), b"ni1\0"
    (tmp_path / "pair.hdr").write_bytes(bytes(header))
    (tmp_path / "pair.img").write_bytes(data[352:])
    for name in ("pair.hdr", "pair.img"):
        with pytest.raises(EMRegError, match=re.escape(reason)):
            read_ct(tmp_path / name)


def test_dcm2niix_nifti_of_the_dicom_series(case, tmp_path, capsys):
    """dcm2niix (Chris Rorden's converter) on the simulator's DICOM series: RAS sform/qform, rows stored
    flipped, the series' rescale intercept kept as ``scl_inter``."""
    if shutil.which("dcm2niix") is None:
        pytest.skip("dcm2niix is not installed (scripts/setup installs the Debian package dcm2niix)")
    subprocess.run(["dcm2niix", "-z", "y", "-f", "converted", "-o", str(tmp_path), str(case / "ct")],
                   check=True, capture_output=True)
    path = tmp_path / "converted.nii.gz"
    _assert_fast_read_is_simpleitk(path)
    _assert_markers_at_truth(path, case, capsys)
