"""An uncompressed DICOM series indexed in its files (``EMRegModule.io.dicom_slices``, ``emreg detect``'s read): the
voxels SimpleITK's read gives, whatever the indexing; the folder's sha256; refusals of short files, and of values
beyond a compact read where they are read; the series it leaves to a whole read."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import SimpleITK as sitk
from dicom_files import convert, make_volume, tools_available, uid, write_series

from EMRegModule.errors import EMRegError
from EMRegModule.io.dicom_read import NarrowVoxelsError, open_dicom_series
from EMRegModule.io.dicom_series import choose_series, scan_series
from EMRegModule.io.dicom_slices import DicomSliceStack
from EMRegModule.io.image import read_ct
from EMRegModule.io.provenance import file_sha256

_KEYS = [
    (slice(None), slice(None), slice(None)),
    (slice(None, None, 2), slice(None, None, 3), slice(None, None, 4)),  # the coarse scan's sample
    (slice(2, 9), slice(5, 31), slice(7, 40)),  # a region
    (slice(8, 2, -2), slice(None, None, -1), slice(30, 3, -3)),
    (4,),
    (-1, 7),
    (slice(3, 5), -2, slice(None)),
    (slice(5, 5), slice(None), slice(None)),  # nothing
    (slice(None), slice(20, 10), slice(None)),
]


def _stack(folder):
    fill, _ = open_dicom_series(folder, compact=True, voxels_only=True)
    assert isinstance(fill.voxels, DicomSliceStack), "an uncompressed 16-bit series is indexed in its files"
    return fill


def _series(tmp_path, pixel=sitk.sitkUInt16, rescale=(1.0, -1024.0), bits_stored=16, seed=5):
    volume = make_volume(pixel=pixel, seed=seed)
    return write_series(volume, tmp_path / "series", uid(90, seed), rescale=[rescale] * 12, bits_stored=bits_stored)


@pytest.mark.parametrize(("pixel", "rescale", "bits_stored"), [
    (sitk.sitkUInt16, (1.0, -1024.0), 16),  # as scanners store it: int32 exactly, int16 for a compact read
    (sitk.sitkInt16, (1.0, 0.0), 12),  # signed 12-bit: the stored bits sign-extended
    (sitk.sitkUInt16, (1.0, -1024.0), 12),  # unsigned 12-bit: the bits above masked off
    (sitk.sitkUInt16, (2.0, -7.0), 12),  # a slope: integer voxels still (int16)
])
def test_a_stack_indexes_as_simpleitks_volume_does(tmp_path, pixel, rescale, bits_stored):
    folder = _series(tmp_path, pixel, rescale, bits_stored)[0].parent
    fill = _stack(folder)
    stack = fill.voxels
    whole = sitk.GetArrayFromImage(read_ct(folder))  # GDCM's decoding, rescaled
    assert stack.shape == whole.shape and stack.ndim == 3 and stack.size == whole.size
    for key in _KEYS:
        got = stack[key]
        assert isinstance(got, np.ndarray) and got.dtype == stack.dtype
        np.testing.assert_array_equal(got, whole[key].astype(stack.dtype), err_msg=str(key))
    np.testing.assert_array_equal(np.asarray(stack), whole)
    fill.result()
    assert fill.sha256.result() == file_sha256(folder)  # the folder's, as every other read gives it


def test_indexing_a_stack_otherwise_is_refused(tmp_path):
    stack = _stack(_series(tmp_path)[0].parent).voxels
    with pytest.raises(TypeError, match="up to three slices or integers"):
        stack[np.array([1, 2])]
    with pytest.raises(IndexError, match="out of bounds for axis 0"):
        stack[12]


def test_a_short_slice_is_refused_when_the_stack_is_made_naming_the_file(tmp_path):
    files = _series(tmp_path)
    files[7].write_bytes(files[7].read_bytes()[:-100])
    with pytest.raises(EMRegError, match="cut short") as raised:
        open_dicom_series(files[0].parent, compact=True, voxels_only=True)
    assert files[7].name in str(raised.value) and "\n" not in str(raised.value)


def test_a_file_cut_short_after_the_stack_was_made_is_refused_where_it_is_read(tmp_path):
    files = _series(tmp_path)
    stack = _stack(files[0].parent).voxels
    files[7].write_bytes(files[7].read_bytes()[:-100])
    stack[:6]  # the slices before it read as they are
    with pytest.raises(EMRegError, match="cut short") as raised:
        stack[7, 39]  # its last row, now partly gone
    assert files[7].name in str(raised.value)


def test_values_beyond_a_compact_stack_are_refused_where_they_are_read(tmp_path):
    volume = make_volume(pixel=sitk.sitkUInt16, seed=21)
    values = sitk.GetArrayFromImage(volume)
    values[5, 3, 4] = 40000  # 38976 HU: beyond int16
    changed = sitk.GetImageFromArray(values)
    changed.CopyInformation(volume)
    files = write_series(changed, tmp_path / "series", uid(91), rescale=[(1.0, -1024.0)] * 12, bits_stored=16)
    stack = _stack(files[0].parent).voxels
    assert stack.dtype == np.int16
    stack[:5]
    stack[5, 4:]
    with pytest.raises(NarrowVoxelsError, match=files[5].name):  # the controller then reads again as int32
        stack[5]
    exact, _ = open_dicom_series(files[0].parent, compact=False, voxels_only=True)
    assert exact.voxels.dtype == np.int32 and int(exact.voxels[5, 3, 4]) == 38976


def test_a_series_a_stack_cannot_index_is_left_to_a_whole_read(tmp_path):
    files = _series(tmp_path)
    headers = choose_series(scan_series(files[0].parent), files[0].parent, None).headers
    assert DicomSliceStack.of(headers, np.int16) is not None
    assert DicomSliceStack.of(headers, np.float32) is None  # float voxels: an image (check_ct_image)
    for change in ({"transfer_syntax": "1.2.840.10008.1.2.4.70"}, {"bits_allocated": 8}, {"frames": 2},
                   {"photometric": "MONOCHROME1"}, {"pixel_data": None}, {"pixel_data": (1000, None)},
                   {"rows": headers[3].rows + 1}):
        changed = [*headers[:3], dataclasses.replace(headers[3], **change), *headers[4:]]
        assert DicomSliceStack.of(changed, np.int16) is None, change


@pytest.mark.skipif(bool(tools_available()), reason=f"DICOM tools missing: {tools_available()} (scripts/setup)")
def test_a_compressed_series_is_read_whole_with_the_same_voxels(tmp_path):
    files = _series(tmp_path)
    convert(files, "jpeg-lossless")
    fill, _ = open_dicom_series(files[0].parent, compact=True, voxels_only=True)
    fill.result()
    assert isinstance(fill.voxels, np.ndarray)
    np.testing.assert_array_equal(fill.voxels, sitk.GetArrayFromImage(read_ct(files[0].parent)))
