"""The scene bundle ``OUT/EMReg.mrb`` against 3D Slicer's own MRML on CT geometries where LPS/RAS and
index/physical conversions go wrong, each a small simulated case (1 mm voxels, 8 markers) whose CT is
stored again with the same physical content, run at the command line, the bundle then imported with
Slicer's reader (``vtkMRMLScene::ReadFromMRB``) and checked in RAS: the volume's voxels at the CT's
physical points (SimpleITK's reading, LPS -> RAS), the marker fiducials at the simulator's markers and on
the CT's bright marker voxels, the calibration points under ``ReferenceToImage`` at the residuals
``registration.json`` gives, targets and probe path as the case / ``navigation.csv`` hold them, and the
predicted-TRE map over the CT's physical extent.

Geometries swept (the standard case of test_slicer_module.py, a near-identity gzip NRRD, and its raw
NRRD / MetaImage copies are checked there): a left-handed grid (one axis flipped), a sagittally stored
CT (axes permuted, two flipped) in a NRRD written in RAS space, an oblique grid (30 degrees) as a DICOM
series, an oblique anisotropic (0.7 x 0.9 x 1.4 mm) grid as NIfTI with its origin 3 m away and targets
given in RAS. All of them agreed, with one note: 3D Slicer reads a left-handed volume with its k axis
(and voxels) reversed, so its IJK-to-RAS differs from SimpleITK's index-to-LPS while every voxel stays at
its physical point; the checks here compare voxels at physical points, not matrices.

Found:

- A bundle written from a run's outputs without the CT in memory (``write_run_bundle(OUT)``, the library
  call) on a DICOM folder of several series read the folder's default series, not the one the run had
  detected in (``--series`` / ``[ct] series``): the scene showed another reconstruction (here a thin slab,
  elsewhere a differently oriented CT) under markers placed in the chosen one. It now reads the series
  ``markers.json`` (else ``run.json``) names.
"""

from __future__ import annotations

import csv
import json
import shutil
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("slicer")

import SimpleITK as sitk  # noqa: E402
from conftest import SMALL_CASE_OPTIONS  # noqa: E402
from ct_files import write_nrrd  # noqa: E402

from EMRegModule.cli.main import main  # noqa: E402
from EMRegModule.simulation.case import simulate_case  # noqa: E402

SMALL = {**SMALL_CASE_OPTIONS, "board_rounds": 1}
RAS = np.array([-1.0, -1.0, 1.0])
FAR_MM = np.array([3000.0, -2000.0, 1500.0])


@pytest.fixture(scope="module")
def base_case(tmp_path_factory) -> Path:
    folder = tmp_path_factory.mktemp("bundle_sweep") / "base"
    simulate_case(folder, seed=6, spacing_mm=1.0, **SMALL)
    return folder


# --- the same physical content on another grid ---------------------------------------------------------


def _restored(image: sitk.Image, order: tuple[int, int, int], flips: tuple[bool, bool, bool]) -> sitk.Image:
    """``image`` stored with new index axis ``a`` = old axis ``order[a]``, reversed where ``flips[a]``:
    voxels moved, origin and direction changed so that every voxel keeps its physical (LPS) point."""
    voxels = sitk.GetArrayFromImage(image)  # (k, j, i)
    moved = np.transpose(voxels, [2 - o for o in order][::-1])
    for axis, flip in enumerate(flips):
        if flip:
            moved = np.flip(moved, axis=2 - axis)
    columns = np.asarray(image.GetDirection()).reshape(3, 3) * np.asarray(image.GetSpacing())
    steps = np.stack([columns[:, o] * (-1.0 if f else 1.0) for o, f in zip(order, flips, strict=True)], axis=1)
    first = [float(image.GetSize()[o] - 1) if f else 0.0 for o, f in sorted(zip(order, flips, strict=True))]
    result = sitk.GetImageFromArray(np.ascontiguousarray(moved))
    spacing = np.linalg.norm(steps, axis=0)
    result.SetSpacing(spacing.tolist())
    result.SetDirection((steps / spacing).ravel().tolist())
    result.SetOrigin(image.TransformContinuousIndexToPhysicalPoint(first))
    return result


def _rotation(axis, degrees: float) -> np.ndarray:
    u = np.asarray(axis, dtype=float) / np.linalg.norm(axis)
    k = np.array([[0.0, -u[2], u[1]], [u[2], 0.0, -u[0]], [-u[1], u[0], 0.0]])
    t = np.radians(degrees)
    return np.eye(3) + np.sin(t) * k + (1.0 - np.cos(t)) * k @ k


def _resampled(image: sitk.Image, direction: np.ndarray, spacing) -> sitk.Image:
    """``image`` resampled (linear) onto a grid of ``direction`` and ``spacing`` covering it."""
    size = np.asarray(image.GetSize())
    corners = np.array([image.TransformIndexToPhysicalPoint([int(v) for v in c]) for c in _corners(size)])
    along = corners @ direction
    low = along.min(axis=0)
    grid = sitk.Image([int(n) for n in np.ceil((along.max(axis=0) - low) / spacing) + 1], image.GetPixelID())
    grid.SetSpacing([float(s) for s in spacing])
    grid.SetDirection(direction.ravel().tolist())
    grid.SetOrigin((direction @ low).tolist())
    return sitk.Resample(image, grid, sitk.Transform(), sitk.sitkLinear, -1000.0)


def _corners(size) -> np.ndarray:
    return np.array([[i, j, k] for i in (0, size[0] - 1) for j in (0, size[1] - 1) for k in (0, size[2] - 1)],
                    dtype=float)


def _write_dicom_series(image: sitk.Image, folder: Path) -> None:
    """``image`` as DICOM series 1, beside series 2: a thin-slice slab (0.5 mm, a few slices) that a folder's
    default choice prefers (finest slices), so that the run must be told ``--series 1``."""
    import dicom_files

    dicom_files.write_series(image, folder, dicom_files.uid(61, 1), number=1, prefix="A")
    slab = sitk.Image([48, 40, 6], sitk.sitkInt16)
    slab.SetSpacing((0.5, 0.5, 0.5))
    slab.SetOrigin(image.GetOrigin())
    dicom_files.write_series(slab - 1000, folder, dicom_files.uid(61, 2), number=2, prefix="B")


def _targets_in_ras(path: Path, shift) -> None:
    document = json.loads(path.read_text())
    markup = document["markups"][0]
    assert markup["coordinateSystem"] == "LPS"
    markup["coordinateSystem"] = "RAS"
    for point in markup["controlPoints"]:
        point["position"] = ((np.asarray(point["position"]) + shift) * RAS).tolist()
    path.write_text(json.dumps(document))


GEOMETRIES = ("left-handed-nrrd", "sagittal-nrrd-ras", "oblique-dicom", "oblique-anisotropic-far-nifti")


def _make_case(base: Path, folder: Path, geometry: str) -> tuple[list[str], np.ndarray]:
    """A copy of ``base`` with its CT stored as ``geometry`` says; (extra ``emreg run`` arguments, the shift
    of the whole scene in LPS mm)."""
    shutil.copytree(base, folder, ignore=shutil.ignore_patterns("ct.nrrd"))
    ct = sitk.ReadImage(str(base / "ct.nrrd"))
    shift = np.zeros(3)
    if geometry == "left-handed-nrrd":
        sitk.WriteImage(_restored(ct, (0, 1, 2), (False, True, False)), str(folder / "ct.nrrd"), True)
    elif geometry == "sagittal-nrrd-ras":
        write_nrrd(folder / "ct.nrrd", _restored(ct, (1, 2, 0), (True, False, True)), "RAS", "little", "gzip")
    elif geometry == "oblique-dicom":
        _write_dicom_series(_resampled(ct, _rotation((1, 2, 3), 30.0), np.ones(3)), folder / "ct")
        return ["--series", "1"], shift
    else:
        shift = FAR_MM
        oblique = _resampled(ct, _rotation((3, 1, -2), 20.0), np.array([0.7, 0.9, 1.4]))
        oblique.SetOrigin((np.asarray(oblique.GetOrigin()) + shift).tolist())
        sitk.WriteImage(oblique, str(folder / "ct.nii.gz"))
        _targets_in_ras(folder / "targets.mrk.json", shift)
    return [], shift


@pytest.fixture(scope="module", params=GEOMETRIES)
def swept_run(request, base_case, tmp_path_factory) -> tuple[str, Path, Path, np.ndarray]:
    """(geometry, case folder, OUT, scene shift) of ``emreg run`` on the base case stored as ``geometry``."""
    root = tmp_path_factory.mktemp(request.param)
    case, out = root / "case", root / "out"
    arguments, shift = _make_case(base_case, case, request.param)
    assert main(["run", str(case), "--out", str(out), "--quiet", *arguments]) == 0
    return request.param, case, out, shift


# --- checks in RAS on the bundle as 3D Slicer imports it --------------------------------------------------


def _import_bundle(path: Path):
    from EMRegModule.slicer_export.mrml import SlicerScene

    mrml = SlicerScene()
    mrml.read_bundle(path)
    return mrml


def _ijk_to_ras(volume_node) -> np.ndarray:
    import slicer.util
    import vtk

    matrix = vtk.vtkMatrix4x4()
    volume_node.GetIJKToRASMatrix(matrix)
    return slicer.util.arrayFromVTKMatrix(matrix)


def _check_volume_at_cts_physical_points(volume_node, ct: sitk.Image) -> None:
    """Corners within 1e-3 mm of the CT's corners (LPS -> RAS) and every sampled voxel holding the CT's voxel
    at its physical point. (Slicer may store the voxels in another index order: it reverses the k axis of a
    left-handed grid; what must agree is the content at each physical point.)"""
    import slicer.util

    from EMRegModule.core.ct import index_to_physical_matrix

    voxels = slicer.util.arrayFromVolume(volume_node)  # (k, j, i)
    ijk_to_ras = _ijk_to_ras(volume_node)
    corners_ras = (ijk_to_ras @ np.c_[_corners(voxels.shape[::-1]), np.ones(8)].T).T[:, :3]
    ct_corners_ras = np.array([ct.TransformContinuousIndexToPhysicalPoint(c.tolist()) for c in _corners(ct.GetSize())])
    ct_corners_ras *= RAS
    nearest = np.linalg.norm(corners_ras[:, None] - ct_corners_ras[None], axis=2).min(axis=1)
    assert nearest.max() < 1e-3, f"volume corners {nearest.max():.3g} mm off the CT's"
    to_ct_index = np.linalg.inv(index_to_physical_matrix(ct)) @ np.diag([-1.0, -1.0, 1.0, 1.0]) @ ijk_to_ras
    rng = np.random.default_rng(2)
    sampled = np.vstack([np.stack([rng.integers(0, n, 3000) for n in voxels.shape[::-1]], axis=1),
                         _corners(voxels.shape[::-1]).astype(int)])
    at = (to_ct_index @ np.c_[sampled, np.ones(len(sampled))].T).T[:, :3]
    index = np.round(at).astype(int)
    assert np.abs(at - index).max() < 1e-6
    assert np.all((index >= 0) & (index < np.asarray(ct.GetSize())))
    ct_voxels = sitk.GetArrayViewFromImage(ct)
    assert np.array_equal(voxels[sampled[:, 2], sampled[:, 1], sampled[:, 0]],
                          ct_voxels[index[:, 2], index[:, 1], index[:, 0]])


def _world(node) -> np.ndarray:
    import slicer.util

    return slicer.util.arrayFromMarkupsControlPoints(node, world=True)


def _labels(node) -> list[str]:
    return [node.GetNthControlPointLabel(i) for i in range(node.GetNumberOfControlPoints())]


def _read_ct(case: Path, out: Path) -> sitk.Image:
    from EMRegModule.io.image import read_ct

    series = json.loads((out / "markers.json").read_text()).get("ct_series")
    path = case / "ct" if (case / "ct").is_dir() else next(case.glob("ct.*"))
    return read_ct(path, series["series_instance_uid"] if series else None)


def test_bundle_shows_every_node_where_the_ct_and_the_outputs_put_it(swept_run):
    import slicer.util

    geometry, case, out, shift = swept_run
    ct = _read_ct(case, out)
    mrml = _import_bundle(out / "EMReg.mrb")
    volume = mrml.node("EMReg CT")
    _check_volume_at_cts_physical_points(volume, ct)

    # markers: at the simulator's markers, on the CT's bright (PVC) voxels of the volume as imported
    truth = json.loads((case / "truth.json").read_text())["markers"]
    truth_ras = (np.array([m["origin"] for m in truth]) + shift) * RAS
    markers = json.loads((out / "markers.json").read_text())["markers"]
    markers_node = mrml.node("EMReg markers")
    assert _labels(markers_node) == [m["id"] for m in markers] and len(markers) == SMALL["n_markers"]
    fiducials = _world(markers_node)
    assert np.linalg.norm(fiducials[:, None] - truth_ras[None], axis=2).min(axis=1).max() < 0.2
    voxels = slicer.util.arrayFromVolume(volume)
    ras_to_ijk = np.linalg.inv(_ijk_to_ras(volume))
    for marker, fiducial in zip(markers, fiducials, strict=True):
        inside = fiducial + 4.0 * np.asarray(marker["axis"]) * RAS  # 4 mm up the axis: inside the bottom cylinder
        i, j, k = np.round((ras_to_ijk @ [*inside, 1.0])[:3]).astype(int)
        assert voxels[k, j, i] > 600, f"{geometry}: marker {marker['id']} is not on bright voxels"

    # calibration points under ReferenceToImage: on the pinhole points at the residuals registration.json says
    registration = json.loads((out / "registration.json").read_text())
    transform = mrml.node("ReferenceToImage")
    np.testing.assert_allclose(slicer.util.arrayFromTransformMatrix(transform, toWorld=True),
                               np.diag([-1.0, -1.0, 1.0, 1.0]) @ registration["ReferenceToImage"], atol=1e-6)
    calibration = mrml.node("EMReg calibration points")
    assert calibration.GetTransformNodeID() == transform.GetID()
    landed = dict(zip(_labels(calibration), _world(calibration), strict=True))
    by_id = {m["id"]: m for m in markers}
    l_mm = registration["sensor_offset_l_mm"]
    assert len(registration["pairs"]) == SMALL["n_markers"]
    for pair in registration["pairs"]:
        marker = by_id[pair["image_marker"]]
        pinhole = (np.asarray(marker["origin"]) + l_mm * np.asarray(marker["axis"])) * RAS
        assert np.linalg.norm(landed[pair["calibration_point"]] - pinhole) == pytest.approx(pair["residual_mm"],
                                                                                            abs=1e-3)

    # targets and the probe path: where the case's targets (in the file's own coordinate system) and
    # navigation.csv (image space, LPS) put them
    markup = json.loads((case / "targets.mrk.json").read_text())["markups"][0]
    targets = np.array([p["position"] for p in markup["controlPoints"]])
    targets_ras = targets if markup["coordinateSystem"] == "RAS" else targets * RAS
    np.testing.assert_allclose(_world(mrml.node("EMReg targets")), targets_ras, atol=1e-6)
    evaluation = json.loads((out / "evaluation.json").read_text())
    assert evaluation["tre"]["mean_mm"] < 1.0  # the targets are where the probe went: the shift reached them too
    by_label = dict(zip(_labels(mrml.node("EMReg targets")), _world(mrml.node("EMReg targets")), strict=True))
    assert len(evaluation["tre"]["dwells"]) >= len(by_label)
    for dwell in evaluation["tre"]["dwells"]:  # each dwell's error: its distance to the target the scene shows
        assert np.linalg.norm(by_label[dwell["target"]] - np.asarray(dwell["position"]) * RAS) == pytest.approx(
            dwell["error_mm"], abs=1e-3)
    with (out / "navigation.csv").open(newline="") as handle:
        path_lps = np.array([[float(r["x_mm"]), float(r["y_mm"]), float(r["z_mm"])] for r in csv.DictReader(handle)])
    step = int(np.ceil(len(path_lps) / 1000))
    np.testing.assert_allclose(_world(mrml.node("EMReg probe path")), path_lps[::step] * RAS, atol=1e-6)

    # the predicted-TRE map: covers the CT's physical extent (within one of its steps beyond it)
    tre_map = mrml.node("EMReg predicted TRE (mm)")
    map_ijk_to_ras = _ijk_to_ras(tre_map)
    size = np.asarray(tre_map.GetImageData().GetDimensions())
    ct_corners = np.array([ct.TransformContinuousIndexToPhysicalPoint(c.tolist()) for c in _corners(ct.GetSize())])
    in_map = (np.linalg.inv(map_ijk_to_ras) @ np.c_[ct_corners * RAS, np.ones(8)].T).T[:, :3]
    assert np.all(in_map > -1e-6) and np.all(in_map < size - 1 + 1e-6)
    assert np.all(in_map.min(axis=0) < 1.0) and np.all(in_map.max(axis=0) > size - 2.0)


@pytest.mark.parametrize("swept_run", ["oblique-dicom"], indirect=True)
def test_bundle_written_from_the_outputs_shows_the_series_the_run_detected_in(swept_run, tmp_path):
    """``write_run_bundle(OUT)`` without the CT in memory reads it again: of a DICOM folder of several series,
    the one the run was told to use (``--series 1``), not the folder's default choice (series 2, thinner)."""
    from EMRegModule.slicer_export.bundle import write_run_bundle

    _, case, out, _ = swept_run
    copy = tmp_path / "out"
    shutil.copytree(out, copy, ignore=shutil.ignore_patterns("EMReg.mrb", "report*"))
    path, message, _ = write_run_bundle(copy)
    assert path == copy / "EMReg.mrb", message
    mrml = _import_bundle(path)
    _check_volume_at_cts_physical_points(mrml.node("EMReg CT"), _read_ct(case, out))
