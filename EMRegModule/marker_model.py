"""The parametric PVC marker: two coaxial cylinders with a pinhole for the probe sensor.

Marker frame (spec, paper S_m): origin at the centre of the bottom face, +Y along the
symmetry axis towards the pinhole opening. Default dimensions are the paper's: bottom
cylinder 16 mm diameter x 8.5 mm, top cylinder 6 mm x 10 mm, pinhole 1 mm diameter and
7.5 mm deep from the top, so the pinhole spans y = a..b = 11..18.5 mm. Another marker
design is a matter of numbers (``case.toml`` ``[marker]``), not code.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, fields
from typing import Any

import numpy as np

from .errors import EMRegError
from .tables import parse_table


@dataclass(frozen=True)
class MarkerModel:
    """Marker dimensions in millimetres (see module docstring for the frame)."""

    bottom_diameter_mm: float = 16.0
    bottom_height_mm: float = 8.5
    top_diameter_mm: float = 6.0
    top_height_mm: float = 10.0
    pinhole_diameter_mm: float = 1.0
    pinhole_depth_mm: float = 7.5

    def __post_init__(self) -> None:
        for f in fields(self):
            value = getattr(self, f.name)
            if not (isinstance(value, (int, float)) and np.isfinite(value) and value > 0):
                raise EMRegError(f"marker model: {f.name} must be a positive number of mm, got {value!r}")
        if self.top_diameter_mm > self.bottom_diameter_mm:
            raise EMRegError("marker model: the top cylinder must not be wider than the bottom one")
        if self.pinhole_depth_mm > self.top_height_mm + self.bottom_height_mm:
            raise EMRegError("marker model: the pinhole is deeper than the marker")
        if self.pinhole_diameter_mm >= self.top_diameter_mm:
            raise EMRegError("marker model: the pinhole must be narrower than the top cylinder")

    @classmethod
    def from_settings(cls, settings: dict[str, Any] | None) -> MarkerModel:
        """Build from a ``[marker]`` table (keys as the field names); unknown keys are an error."""
        return parse_table(cls, settings, "marker")

    def to_dict(self) -> dict[str, float]:
        return asdict(self)

    @property
    def height_mm(self) -> float:
        """Total height along +Y."""
        return self.bottom_height_mm + self.top_height_mm

    @property
    def pinhole_bottom_mm(self) -> float:
        """``a``: the lowest y the probe sensor's centre can reach (the pinhole's floor)."""
        return self.height_mm - self.pinhole_depth_mm

    @property
    def pinhole_top_mm(self) -> float:
        """``b``: the y of the pinhole's opening (the marker's top face)."""
        return self.height_mm

    @property
    def volume_mm3(self) -> float:
        """Solid PVC volume (cylinders less the pinhole)."""
        r_bottom = self.bottom_diameter_mm / 2
        r_top = self.top_diameter_mm / 2
        r_hole = self.pinhole_diameter_mm / 2
        return float(np.pi * (r_bottom**2 * self.bottom_height_mm + r_top**2 * self.top_height_mm
                              - r_hole**2 * self.pinhole_depth_mm))

    @property
    def centroid_y_mm(self) -> float:
        """y of the solid's centroid in the marker frame (it lies on the axis)."""
        r_bottom = self.bottom_diameter_mm / 2
        r_top = self.top_diameter_mm / 2
        r_hole = self.pinhole_diameter_mm / 2
        v_bottom = np.pi * r_bottom**2 * self.bottom_height_mm
        v_top = np.pi * r_top**2 * self.top_height_mm
        v_hole = np.pi * r_hole**2 * self.pinhole_depth_mm
        moment = (v_bottom * self.bottom_height_mm / 2
                  + v_top * (self.bottom_height_mm + self.top_height_mm / 2)
                  - v_hole * (self.height_mm - self.pinhole_depth_mm / 2))
        return float(moment / (v_bottom + v_top - v_hole))

    def sensor_point(self, l_mm: float) -> np.ndarray:
        """The probe sensor's position ``q_m = [0, l, 0]`` in the marker frame."""
        return np.array([0.0, float(l_mm), 0.0])

    def contains(self, points_marker: np.ndarray) -> np.ndarray:
        """Boolean mask: which points (N, 3, marker frame, mm) lie inside the solid PVC."""
        p = np.asarray(points_marker, dtype=float)
        radial2 = p[..., 0] ** 2 + p[..., 2] ** 2
        y = p[..., 1]
        in_bottom = (y >= 0) & (y <= self.bottom_height_mm) & (radial2 <= (self.bottom_diameter_mm / 2) ** 2)
        in_top = (y > self.bottom_height_mm) & (y <= self.height_mm) & (radial2 <= (self.top_diameter_mm / 2) ** 2)
        in_hole = (y > self.pinhole_bottom_mm) & (radial2 < (self.pinhole_diameter_mm / 2) ** 2)
        return (in_bottom | in_top) & ~in_hole

    def signed_distance(self, points_marker: np.ndarray) -> np.ndarray:
        """Approximate signed distance (mm, negative inside) to the outer surface (pinhole ignored).

        Exact for the union of two coaxial cylinders up to the usual union approximation
        (max/min of the parts): good enough for partial-volume sampling within a voxel.
        """
        p = np.asarray(points_marker, dtype=float)
        radial = np.sqrt(p[..., 0] ** 2 + p[..., 2] ** 2)
        y = p[..., 1]
        bottom = _cylinder_sdf(radial, y, self.bottom_diameter_mm / 2, 0.0, self.bottom_height_mm)
        top = _cylinder_sdf(radial, y, self.top_diameter_mm / 2, self.bottom_height_mm - 1e-6, self.height_mm)
        return np.minimum(bottom, top)

    def surface_points(self, spacing_mm: float = 0.5, include_pinhole: bool = False) -> np.ndarray:
        """Points sampled on the outer surface (N, 3, marker frame) about ``spacing_mm`` apart.

        Faces: bottom disc, bottom side, the annular shoulder, top side, top disc (with the
        pinhole opening left out). The pinhole walls are included only on request (CT cannot
        resolve a 1 mm hole well).
        """
        parts = []
        r_b, r_t, r_h = self.bottom_diameter_mm / 2, self.top_diameter_mm / 2, self.pinhole_diameter_mm / 2
        h_b, h = self.bottom_height_mm, self.height_mm
        parts.append(_disc(0.0, r_b, 0.0, spacing_mm))
        parts.append(_side(r_b, 0.0, h_b, spacing_mm))
        parts.append(_disc(r_t, r_b, h_b, spacing_mm))
        parts.append(_side(r_t, h_b, h, spacing_mm))
        parts.append(_disc(r_h, r_t, h, spacing_mm))
        if include_pinhole:
            parts.append(_side(r_h, self.pinhole_bottom_mm, h, spacing_mm))
            parts.append(_disc(0.0, r_h, self.pinhole_bottom_mm, spacing_mm))
        return np.concatenate(parts)

    def surface_polydata(self, resolution: int = 96):  # -> vtk.vtkPolyData
        """The closed outer CAD surface as triangulated ``vtkPolyData`` (marker frame, mm).

        A surface of revolution about +Y: the profile (radius, y) bottom centre -> bottom rim
        -> shoulder -> top rim -> top centre, swept in ``resolution`` steps; outward normals.
        """
        # VTK is imported here, not at the top: about 0.3 s (measured) that the commands using the model
        # without its surface (emreg register, evaluate, simulate, calibrate) should not pay at start-up.
        from vtkmodules.util.numpy_support import numpy_to_vtk, numpy_to_vtkIdTypeArray
        from vtkmodules.vtkCommonCore import vtkPoints
        from vtkmodules.vtkCommonDataModel import vtkCellArray, vtkPolyData
        from vtkmodules.vtkFiltersCore import vtkPolyDataNormals

        r_b, r_t = self.bottom_diameter_mm / 2, self.top_diameter_mm / 2
        h_b, h = self.bottom_height_mm, self.height_mm
        profile = [(0.0, 0.0), (r_b, 0.0), (r_b, h_b), (r_t, h_b), (r_t, h), (0.0, h)]
        angle = np.linspace(0.0, 2 * np.pi, resolution, endpoint=False)
        points: list[np.ndarray] = []
        ring_start: list[int] = []  # first point index of each profile vertex (apexes have one point)
        for radius, y in profile:
            ring_start.append(sum(len(p) for p in points))
            if radius == 0.0:
                points.append(np.array([[0.0, y, 0.0]]))
            else:
                points.append(np.column_stack([radius * np.cos(angle), np.full(resolution, y),
                                               -radius * np.sin(angle)]))
        triangles: list[tuple[int, int, int]] = []
        for k in range(len(profile) - 1):
            a0, b0 = ring_start[k], ring_start[k + 1]
            a_apex, b_apex = profile[k][0] == 0.0, profile[k + 1][0] == 0.0
            for i in range(resolution):
                j = (i + 1) % resolution
                if a_apex:
                    triangles.append((a0, b0 + i, b0 + j))
                elif b_apex:
                    triangles.append((a0 + i, b0, a0 + j))
                else:
                    triangles.append((a0 + i, b0 + i, b0 + j))
                    triangles.append((a0 + i, b0 + j, a0 + j))
        vtk_points = vtkPoints()
        vtk_points.SetData(numpy_to_vtk(np.concatenate(points), deep=True))
        offsets = np.arange(0, 3 * len(triangles) + 1, 3, dtype=np.int64)
        connectivity = np.asarray(triangles, dtype=np.int64).ravel()
        cells = vtkCellArray()
        cells.SetData(numpy_to_vtkIdTypeArray(offsets, deep=True), numpy_to_vtkIdTypeArray(connectivity, deep=True))
        surface = vtkPolyData()
        surface.SetPoints(vtk_points)
        surface.SetPolys(cells)
        normals = vtkPolyDataNormals()
        normals.SetInputData(surface)
        normals.ConsistencyOn()
        normals.AutoOrientNormalsOn()
        normals.SplittingOff()
        normals.Update()
        return normals.GetOutput()


def _cylinder_sdf(radial: np.ndarray, y: np.ndarray, radius: float, y0: float, y1: float) -> np.ndarray:
    d_radial = radial - radius
    d_axial = np.maximum(y0 - y, y - y1)
    outside = np.sqrt(np.maximum(d_radial, 0) ** 2 + np.maximum(d_axial, 0) ** 2)
    inside = np.minimum(np.maximum(d_radial, d_axial), 0)
    return outside + inside


def _disc(r_inner: float, r_outer: float, y: float, spacing: float) -> np.ndarray:
    rings = max(1, int(np.ceil((r_outer - r_inner) / spacing)))
    out = []
    for radius in np.linspace(r_inner, r_outer, rings + 1):
        if radius <= 1e-9:
            out.append([[0.0, y, 0.0]])
            continue
        n = max(6, int(np.ceil(2 * np.pi * radius / spacing)))
        angle = np.linspace(0, 2 * np.pi, n, endpoint=False)
        out.append(np.column_stack([radius * np.cos(angle), np.full(n, y), radius * np.sin(angle)]))
    return np.concatenate(out)


def _side(radius: float, y0: float, y1: float, spacing: float) -> np.ndarray:
    n_around = max(6, int(np.ceil(2 * np.pi * radius / spacing)))
    n_along = max(2, int(np.ceil((y1 - y0) / spacing)) + 1)
    angle = np.linspace(0, 2 * np.pi, n_around, endpoint=False)
    ys = np.linspace(y0, y1, n_along)
    a, yy = np.meshgrid(angle, ys)
    return np.column_stack([radius * np.cos(a).ravel(), yy.ravel(), radius * np.sin(a).ravel()])
