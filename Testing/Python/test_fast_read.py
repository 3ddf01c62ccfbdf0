"""The fast CT reader gives exactly what SimpleITK gives, and falls back to it for anything unusual."""

import gzip
import hashlib
import zlib

import numpy as np
import pytest
import SimpleITK as sitk

from EMRegModule.core import transforms as tf
from EMRegModule.errors import EMRegError
from EMRegModule.io.fast_read import start_fast_read
from EMRegModule.io.image import read_ct
from EMRegModule.io.provenance import file_sha256

SIZE_IJK = (37, 29, 23)  # odd sizes: no axis can be swapped unnoticed


def read_fast(path) -> sitk.Image | None:
    """The image read on the fast path, or None when the fast path declines the file."""
    fill = start_fast_read(path)
    return None if fill is None else fill.result()


def _oblique_image(dtype: str, seed: int = 0) -> sitk.Image:
    rng = np.random.default_rng(seed)
    values = rng.normal(0, 800, size=SIZE_IJK[::-1])
    if np.dtype(dtype).kind == "u":
        values = np.abs(values)
    info = np.iinfo(dtype) if np.dtype(dtype).kind in "iu" else None
    array = np.clip(values, info.min, info.max).astype(dtype) if info else values.astype(dtype)
    image = sitk.GetImageFromArray(array)
    image.SetSpacing((0.55, 0.7, 1.25))
    image.SetOrigin((-120.5, 33.25, -402.0))
    image.SetDirection((tf.axis_angle_to_rotation([1, 2, 0.5], 0.4) @ np.diag([1, -1, -1])).ravel().tolist())
    return image


def _assert_same(fast: sitk.Image, reference: sitk.Image) -> None:
    assert fast.GetSize() == reference.GetSize()
    assert fast.GetPixelID() == reference.GetPixelID()
    assert fast.GetSpacing() == reference.GetSpacing()
    assert fast.GetOrigin() == reference.GetOrigin()
    assert fast.GetDirection() == reference.GetDirection()
    np.testing.assert_array_equal(sitk.GetArrayViewFromImage(fast), sitk.GetArrayViewFromImage(reference))


@pytest.mark.parametrize("name", ["ct.nrrd", "ct.mha", "ct.nii.gz", "ct.nii"])
@pytest.mark.parametrize("compress", [True, False])
@pytest.mark.parametrize("dtype", ["int16", "uint8", "uint16", "float32"])
def test_fast_read_equals_simpleitk(tmp_path, name, compress, dtype):
    path = tmp_path / name
    sitk.WriteImage(_oblique_image(dtype), str(path), compress)
    fill = start_fast_read(path)
    assert fill is not None, "the plain layout must take the fast path"
    _assert_same(fill.result(), sitk.ReadImage(str(path)))
    # the provenance's sha256 comes out of the same pass: the plain sha256 of the file's bytes
    assert fill.sha256.result() == hashlib.sha256(path.read_bytes()).hexdigest() == file_sha256(path)


def _hand_written_nrrd(path, array_zyx: np.ndarray, header_lines: list[str], encoding: str) -> None:
    payload = array_zyx.tobytes()
    if encoding == "gzip":
        payload = gzip.compress(payload, compresslevel=1)
    header = ["NRRD0004", "# written by the test", *header_lines, f"encoding: {encoding}", "", ""]
    path.write_bytes("\n".join(header).encode("ascii") + payload)


@pytest.mark.parametrize("encoding", ["raw", "gzip"])
def test_big_endian_right_anterior_superior_nrrd(tmp_path, encoding):
    """A header SimpleITK never writes: big-endian voxels in RAS space, with key/value pairs."""
    array = (np.arange(np.prod(SIZE_IJK[::-1])) - 3000).astype(">i2").reshape(SIZE_IJK[::-1])
    path = tmp_path / "ras.nrrd"
    _hand_written_nrrd(path, array, [
        "type: short", "dimension: 3", "space: right-anterior-superior", "sizes: " + " ".join(map(str, SIZE_IJK)),
        "space directions: (0,0.6,0) (-0.5,0,0) (0,0,1.5)", "kinds: domain domain domain", "endian: big",
        "space origin: (10.5,-20,30)", "scanner:=ct-01"], encoding)
    fill = start_fast_read(path)
    assert fill is not None
    fast = fill.result()
    assert fill.sha256.result() == hashlib.sha256(path.read_bytes()).hexdigest()  # hashed before the byte swap
    reference = sitk.ReadImage(str(path))
    _assert_same(fast, reference)
    assert reference.GetOrigin() == (-10.5, 20.0, 30.0)  # RAS -> LPS, as ITK reads it
    assert sitk.GetArrayViewFromImage(fast)[0, 0, 1] == -2999


def test_big_endian_compressed_metaimage(tmp_path):
    array = (np.arange(np.prod(SIZE_IJK[::-1])) % 4000 - 1000).astype(">i2").reshape(SIZE_IJK[::-1])
    payload = zlib.compress(array.tobytes())
    header = ["ObjectType = Image", "NDims = 3", "BinaryData = True", "BinaryDataByteOrderMSB = True",
              "CompressedData = True", f"CompressedDataSize = {len(payload)}",
              "TransformMatrix = 0 1 0 -1 0 0 0 0 1", "Offset = 1 2 3", "ElementSpacing = 0.5 0.6 0.7",
              "DimSize = " + " ".join(map(str, SIZE_IJK)), "ElementType = MET_SHORT", "ElementDataFile = LOCAL"]
    path = tmp_path / "msb.mha"
    path.write_bytes(("\n".join(header) + "\n").encode("ascii") + payload)
    fast = read_fast(path)
    assert fast is not None
    _assert_same(fast, sitk.ReadImage(str(path)))


def test_unusual_files_fall_back_to_simpleitk(tmp_path):
    image = _oblique_image("int16")
    # a NIfTI with an intensity slope: SimpleITK rescales, so the fast path must not take it
    nifti = tmp_path / "scaled.nii"
    sitk.WriteImage(image, str(nifti))
    data = bytearray(nifti.read_bytes())
    data[112:116] = np.float32(2.0).tobytes()
    nifti.write_bytes(bytes(data))
    # detached data: a .nhdr-style "data file" field inside a .nrrd
    raw = tmp_path / "voxels.raw"
    raw.write_bytes(sitk.GetArrayViewFromImage(image).astype("<i2").tobytes())
    detached = tmp_path / "detached.nrrd"
    detached.write_text("\n".join([
        "NRRD0004", "type: short", "dimension: 3", "space: left-posterior-superior",
        "sizes: " + " ".join(map(str, SIZE_IJK)), "space directions: (0.5,0,0) (0,0.5,0) (0,0,0.5)",
        "endian: little", "encoding: raw", "data file: voxels.raw", ""]))
    # a DICOM-like 2D file and a vector image
    vector = tmp_path / "vector.nrrd"
    sitk.WriteImage(sitk.Image([6, 6, 6], sitk.sitkVectorFloat32, 3), str(vector))
    for path in (nifti, detached, vector):
        assert read_fast(path) is None, path.name
    scaled = read_ct(nifti)  # read by SimpleITK, rescaled as SimpleITK does
    _assert_same(scaled, sitk.ReadImage(str(nifti)))
    _assert_same(read_ct(detached), sitk.ReadImage(str(detached)))


@pytest.mark.parametrize("name", ["ct.nrrd", "ct.nii.gz", "ct.mha", "raw.nrrd"])
def test_truncated_or_corrupt_voxels_give_one_line_errors(tmp_path, name):
    whole = tmp_path / ("whole_" + name)
    sitk.WriteImage(_oblique_image("int16"), str(whole), not name.startswith("raw"))
    data = whole.read_bytes()
    truncated = tmp_path / ("truncated_" + name)
    truncated.write_bytes(data[: int(len(data) * 0.7)])
    with pytest.raises(EMRegError, match="cannot read CT") as info:
        read_ct(truncated)
    assert "\n" not in str(info.value) and truncated.name in str(info.value)
    if name.startswith("raw"):
        return
    corrupt = tmp_path / ("corrupt_" + name)
    middle = len(data) // 2
    corrupt.write_bytes(data[:middle] + bytes(b ^ 0x5A for b in data[middle:middle + 64]) + data[middle + 64:])
    with pytest.raises(EMRegError, match="cannot read CT") as info:
        read_ct(corrupt)
    assert "\n" not in str(info.value) and corrupt.name in str(info.value)
