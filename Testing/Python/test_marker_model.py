"""The parametric marker model: dimensions, solid, surface and CAD mesh agree with each other."""

import numpy as np
import pytest
from vtkmodules.util.numpy_support import vtk_to_numpy
from vtkmodules.vtkFiltersCore import vtkFeatureEdges, vtkMassProperties

from EMRegModule.errors import EMRegError
from EMRegModule.marker_model import MarkerModel


def test_paper_dimensions_give_pinhole_span():
    model = MarkerModel()
    assert (model.pinhole_bottom_mm, model.pinhole_top_mm) == (11.0, 18.5)
    np.testing.assert_allclose(model.sensor_point(14.2), [0, 14.2, 0])


def test_volume_and_centroid_match_a_voxelisation():
    model = MarkerModel()
    step = 0.1
    axis = np.arange(-8.05, 8.1, step)
    ys = np.arange(0.05, 18.5, step)
    x, y, z = np.meshgrid(axis, ys, axis, indexing="ij")
    inside = model.contains(np.stack([x, y, z], axis=-1))
    assert inside.sum() * step**3 == pytest.approx(model.volume_mm3, rel=0.01)
    assert y[inside].mean() == pytest.approx(model.centroid_y_mm, abs=0.02)


def test_cad_mesh_is_closed_with_the_solid_volume():
    model = MarkerModel(bottom_diameter_mm=14, top_height_mm=8)
    surface = model.surface_polydata(resolution=128)
    edges = vtkFeatureEdges()
    edges.SetInputData(surface)
    edges.BoundaryEdgesOn()
    edges.NonManifoldEdgesOn()
    edges.FeatureEdgesOff()
    edges.ManifoldEdgesOff()
    edges.Update()
    assert edges.GetOutput().GetNumberOfCells() == 0
    mass = vtkMassProperties()
    mass.SetInputData(surface)
    mass.Update()
    hole = np.pi * (model.pinhole_diameter_mm / 2) ** 2 * model.pinhole_depth_mm
    assert mass.GetVolume() == pytest.approx(model.volume_mm3 + hole, rel=0.002)
    points = vtk_to_numpy(surface.GetPoints().GetData())
    assert np.abs(model.signed_distance(points)).max() < 1e-5
    np.testing.assert_allclose(surface.GetBounds(), [-7, 7, 0, model.height_mm, -7, 7], atol=1e-6)


def test_surface_points_lie_on_the_surface_and_cover_it():
    model = MarkerModel()
    points = model.surface_points(0.5)
    assert np.abs(model.signed_distance(points)).max() < 1e-6
    assert 2000 < len(points) < 8000
    assert points[:, 1].min() == 0 and points[:, 1].max() == pytest.approx(model.height_mm)


def test_settings_and_validation():
    model = MarkerModel.from_settings({"top_height_mm": 12, "pinhole_depth_mm": 8})
    assert model.pinhole_bottom_mm == pytest.approx(12.5)
    with pytest.raises(EMRegError, match="unknown key"):
        MarkerModel.from_settings({"height": 3})
    with pytest.raises(EMRegError, match="positive"):
        MarkerModel(top_diameter_mm=-1)
    with pytest.raises(EMRegError, match="wider"):
        MarkerModel(top_diameter_mm=20)
