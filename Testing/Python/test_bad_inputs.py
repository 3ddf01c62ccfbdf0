"""Bad inputs that must never give a plausible wrong answer (issue 11): every class is refused with
exit 2 and one line naming the input, through the ``emreg`` command where a user meets it.

Inputs are generated here, in the test run. Classes: CT geometry and voxel values, header sizes
against the data length, sensor ports, registration files, markups units, the fixed sensor
offset, recordings with time resets and gaps, output paths and odd recording paths, oversized
CSV fields and lines.
"""

from __future__ import annotations

import numpy as np
import pytest
import SimpleITK as sitk

from EMRegModule.cli import main


def _refused(capsys, argv, *needles, code=2):
    """Run ``emreg argv``; assert exit ``code``, one line on stderr containing every needle; the line."""
    result = main([str(a) for a in argv])
    err = capsys.readouterr().err.strip()
    assert result == code, err
    assert len(err.splitlines()) == 1, err
    assert "Traceback" not in err
    for needle in needles:
        assert needle in err, err
    return err


# --- CT -------------------------------------------------------------------------------------


def _ct(values=None, direction=None):
    array = np.full((12, 14, 16), -1000, np.float32) if values is None else values
    image = sitk.GetImageFromArray(array)
    image.SetSpacing((0.8, 0.8, 1.0))
    if direction is not None:
        image.SetDirection(direction)
    return image


@pytest.mark.parametrize("name", ["ct.nrrd", "ct.mha", "ct.nhdr"])  # NIfTI cannot store a shear
def test_sheared_direction_is_refused(tmp_path, capsys, name):
    sitk.WriteImage(_ct(direction=(1, 0.05, 0, 0, 1, 0, 0, 0, 1)), str(tmp_path / name))
    _refused(capsys, ["detect", tmp_path / name, "--out", tmp_path / "out", "--quiet"], "not orthogonal")
    assert not (tmp_path / "out" / "markers.json").exists()


def test_tiny_rounding_of_direction_cosines_is_accepted(tmp_path):
    angle = np.radians(1.5)
    rotation = np.array([[np.cos(angle), -np.sin(angle), 0], [np.sin(angle), np.cos(angle), 0], [0, 0, 1]])
    rounded = np.round(rotation, 6)  # DICOM writes direction cosines with about six digits
    sitk.WriteImage(_ct(direction=tuple(rounded.ravel())), str(tmp_path / "ct.nrrd"))
    from EMRegModule.io.image import read_ct

    assert read_ct(tmp_path / "ct.nrrd").GetSize() == (16, 14, 12)


@pytest.mark.parametrize("kind", ["nan slab", "-inf slab", "sprinkled nan/inf"])
@pytest.mark.parametrize("name,compress", [("ct.nrrd", True), ("ct.nrrd", False), ("ct.mha", True),
                                           ("ct.nii.gz", True), ("ct.nhdr", False)])
def test_non_finite_voxels_are_refused_with_their_count(tmp_path, capsys, kind, name, compress):
    values = np.full((12, 14, 16), -1000, np.float32)
    if kind == "nan slab":
        values[5] = np.nan
    elif kind == "-inf slab":
        values[:, 3] = -np.inf
    else:
        rng = np.random.default_rng(1)
        flat = values.reshape(-1)
        flat[rng.choice(flat.size, 40, replace=False)] = np.nan
        flat[rng.choice(flat.size, 7, replace=False)] = np.inf
    expected = int(np.count_nonzero(~np.isfinite(values)))
    sitk.WriteImage(_ct(values), str(tmp_path / name), compress)
    _refused(capsys, ["detect", tmp_path / name, "--out", tmp_path / "out", "--quiet"],
             f"{expected} non-finite voxel")


def test_non_finite_voxels_of_an_image_in_memory_are_refused():
    from EMRegModule.controller import EMRegController
    from EMRegModule.errors import EMRegError

    values = np.zeros((12, 14, 16), np.float64)
    values[0, 0, :3] = np.nan
    with pytest.raises(EMRegError, match="3 non-finite"):
        EMRegController().set_image(_ct(values))


def _write_with_sizes(path, compress, change):
    image = sitk.GetImageFromArray(np.zeros((10, 12, 14), np.int16))
    sitk.WriteImage(image, str(path), compress)
    if path.suffix == ".nhdr":
        header = path.read_text()
        path.write_text(header.replace("sizes: 14 12 10", f"sizes: 14 12 {10 + change}"))
        return
    raw = path.read_bytes()
    old = b"sizes: 14 12 10" if path.suffix == ".nrrd" else b"DimSize = 14 12 10"
    assert old in raw
    path.write_bytes(raw.replace(old, old[:-2] + str(10 + change).encode()))


@pytest.mark.parametrize("name,compress", [("ct.nrrd", False), ("ct.nrrd", True), ("ct.mha", False),
                                           ("ct.mha", True), ("ct.nhdr", False)])
@pytest.mark.parametrize("change,needle", [(-1, "more than its header"), (+1, "truncated")])
def test_header_sizes_must_match_the_data_length(tmp_path, capsys, name, compress, change, needle):
    _write_with_sizes(tmp_path / name, compress, change)
    _refused(capsys, ["detect", tmp_path / name, "--out", tmp_path / "out", "--quiet"], needle)


def test_sizes_check_also_holds_on_the_simpleitk_path(tmp_path, monkeypatch):
    """Without the fast path (no isal), the SimpleITK reader gets the same length check."""
    from EMRegModule.errors import EMRegError
    from EMRegModule.io import fast_read
    from EMRegModule.io.image import read_ct

    monkeypatch.setattr(fast_read, "igzip_lib", None)
    for compress in (False, True):
        _write_with_sizes(tmp_path / "ct.nrrd", compress, -2)
        with pytest.raises(EMRegError, match="more than its header"):
            read_ct(tmp_path / "ct.nrrd")
