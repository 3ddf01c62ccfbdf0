"""The streamed CT read of the report (``EMRegModule.io.ct_stream``): the same voxels as ``read_ct``, the
same binned context and marker planes as from the whole image, slices handed back once used, and the
reader's errors kept."""

from __future__ import annotations

import numpy as np
import pytest
import SimpleITK as sitk

from EMRegModule.errors import EMRegError
from EMRegModule.io.ct_handle import CTHandle
from EMRegModule.io.ct_stream import start_streamed_read
from EMRegModule.io.image import read_ct
from EMRegModule.marker_model import MarkerModel
from EMRegModule.rendering.context import binned_ct
from EMRegModule.rendering.slices import SliceMarker, StreamingMarkerViews


def _ct(tmp_path, name: str, compress: bool = True, shape=(40, 30, 50)):
    rng = np.random.default_rng(3)
    image = sitk.GetImageFromArray(rng.integers(-1000, 3000, size=shape).astype(np.int16))
    image.SetSpacing((0.6, 0.5, 0.7))
    image.SetOrigin((5.0, -3.0, 12.0))
    image.SetDirection((0.0, 1.0, 0.0, -1.0, 0.0, 0.0, 0.0, 0.0, 1.0))
    path = tmp_path / name
    sitk.WriteImage(image, str(path), compress)
    return path, image


@pytest.mark.parametrize("name, compress", [("ct.nrrd", True), ("ct.nrrd", False), ("ct.mha", True),
                                            ("ct.nii.gz", True)])
def test_streamed_voxels_and_geometry_are_those_of_read_ct(tmp_path, name, compress):
    path, _ = _ct(tmp_path, name, compress)
    expected = read_ct(path)
    ct = start_streamed_read(path)
    assert isinstance(ct, CTHandle) and ct.voxels is ct.array
    assert ct.result() is None  # no image is kept
    assert np.array_equal(ct.array, sitk.GetArrayViewFromImage(expected))
    geometry = ct.image
    assert geometry.GetSize() == expected.GetSize() and geometry.GetPixelID() == expected.GetPixelID()
    assert np.allclose(geometry.GetSpacing(), expected.GetSpacing())
    assert np.allclose(geometry.GetOrigin(), expected.GetOrigin())
    assert np.allclose(geometry.GetDirection(), expected.GetDirection())


def test_binned_context_and_marker_planes_match_the_whole_image_while_slices_are_released(tmp_path):
    path, image = _ct(tmp_path, "ct.nrrd", shape=(90, 40, 60))
    marker_to_image = np.eye(4)
    marker_to_image[:3, 3] = image.TransformContinuousIndexToPhysicalPoint((30.0, 20.0, 45.0))
    markers = [SliceMarker("M1", marker_to_image)]
    model = MarkerModel()
    whole = binned_ct(image, max_voxels=5000)
    whole_views = StreamingMarkerViews(image, markers, model, view_px=24).views()

    ct = start_streamed_read(path)
    views = StreamingMarkerViews(ct.image, markers, model, view_px=24, array=ct.array)
    released = []

    def on_slices(read: int) -> None:
        views.sample_ready(read)
        stop = min(read - 4, views.first_needed_slice())
        ct.release_before(stop)
        released.append(stop)

    streamed = binned_ct(ct, max_voxels=5000, on_slices=on_slices)
    assert whole.factor == streamed.factor == 4
    assert np.array_equal(whole.values, streamed.values)
    assert np.allclose(whole.index_to_image, streamed.index_to_image)
    for plane, expected in zip(views.views()[0], whole_views[0], strict=True):
        assert np.array_equal(plane, expected, equal_nan=True)
    assert max(released) > 60  # most of the CT was handed back while it was read
    slice_bytes = ct.array[0].nbytes
    whole_pages = (max(released) * slice_bytes) // 4096 * 4096 // slice_bytes  # slices wholly released
    assert whole_pages > 0 and not ct.array[:whole_pages - 1].any()  # released pages read as zeros


def test_truncated_and_float_or_unusual_files(tmp_path):
    path, _ = _ct(tmp_path, "ct.nrrd", compress=False)
    data = path.read_bytes()
    path.write_bytes(data[:-1000])
    ct = start_streamed_read(path)
    with pytest.raises(EMRegError, match="truncated"):
        ct.result()
    floats = sitk.GetImageFromArray(np.zeros((4, 5, 6), dtype=np.float32))
    sitk.WriteImage(floats, str(tmp_path / "float.nrrd"), True)
    assert start_streamed_read(tmp_path / "float.nrrd") is None  # non-finite checks: the whole read
    assert start_streamed_read(tmp_path / "missing.nrrd") is None
    assert start_streamed_read(tmp_path) is None  # a folder (DICOM)
