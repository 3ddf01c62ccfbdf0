"""The fiducial frame in 3D, rendered offscreen with pyvista: verification snapshot of a registration.

All geometry is in image space (CT physical LPS, mm). The scene shows a translucent
iso-surface of the CT for context, every detected marker's fitted CAD model coloured by
its registration residual (unpaired markers grey), the reference sensor (Model 800) with
its axes at ``ReferenceToImage``, the calibration points mapped into image space, and
optionally targets and the navigated probe path.

Rendering is deterministic: fixed window size, camera from fixed view directions, the
"light kit" lighting, no anti-aliasing, no timestamps.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from ..core.transforms import apply_transform
from ..interrupts import vtk_imports_uninterrupted
from ..marker_model import MarkerModel
from .colors import CALIBRATION, DEFAULT_COLORMAP, GREY, NAVIGATION, SENSOR, TARGET, colormap_table, residual_range
from .context import MAX_CONTEXT_VOXELS, binned_ct, context_surface

if TYPE_CHECKING:
    import SimpleITK as sitk

#: View directions in LPS (from the focal point towards the camera) and the screen's up vector.
VIEWS: dict[str, tuple[tuple[float, float, float], tuple[float, float, float]]] = {
    "oblique": ((0.55, -1.0, 0.75), (0.0, 0.0, 1.0)),  # from anterior-left-superior, superior up
    "top": ((0.0, 0.0, 1.0), (0.0, -1.0, 0.0)),  # from superior, anterior up
    "front": ((0.0, -1.0, 0.0), (0.0, 0.0, 1.0)),  # from anterior, superior up
    "side": ((1.0, 0.0, 0.0), (0.0, 0.0, 1.0)),  # from the left, superior up
}

#: trakSTAR Model 800 sensor housing (mm), long axis along the sensor's +X.
REFERENCE_SENSOR_SIZE_MM = (19.8, 7.9, 7.9)


@dataclass
class SceneMarker:
    """One detected marker: its label, ``MarkerToImage`` (4x4) and registration residual (None: unpaired)."""

    label: str
    marker_to_image: np.ndarray
    residual_mm: float | None = None


@dataclass
class Camera:
    """An explicit camera (LPS mm); ``view_angle_deg`` is the vertical field of view."""

    position: tuple[float, float, float]
    focal_point: tuple[float, float, float]
    view_up: tuple[float, float, float]
    view_angle_deg: float = 30.0


@dataclass
class FrameScene:
    """What to draw; every position in image space (LPS, mm)."""

    model: MarkerModel
    markers: list[SceneMarker] = field(default_factory=list)
    ct: sitk.Image | None = None
    iso_value: float | None = None
    context_surface: object | None = None  # a precomputed ``ct_context_surface`` (pyvista.PolyData)
    reference_to_image: np.ndarray | None = None
    calibration_points: np.ndarray | None = None
    sensor_points: np.ndarray | None = None
    sensor_points_name: str = "sensor points at the solved l"  # "fiducials" for a point fit (no CT)
    targets: np.ndarray | None = None
    target_labels: list[str] | None = None
    navigation_path: np.ndarray | None = None
    colormap: str = DEFAULT_COLORMAP
    residual_range: tuple[float, float] | None = None
    show_labels: bool = True
    show_scalar_bar: bool = True
    title: str | None = None


def prepare_offscreen() -> None:
    """Without a display, ask VTK for its EGL render window (no X server, no Xvfb needed).

    pyvista's first ``Plotter`` would then probe for a display (``xset``) and, finding none, make a throwaway
    render window and OpenGL context only to decide whether to warn that plotting may fail (``ALLOW_PLOTTING``
    skips that probe): EMReg renders offscreen, where a missing OpenGL fails at the first render anyway."""
    if not os.environ.get("DISPLAY") and not os.environ.get("WAYLAND_DISPLAY"):
        os.environ.setdefault("VTK_DEFAULT_OPENGL_WINDOW", "vtkEGLRenderWindow")
        os.environ.setdefault("ALLOW_PLOTTING", "true")


def marker_mesh(model: MarkerModel, marker_to_image: np.ndarray, resolution: int = 64):
    """The marker's CAD surface (``pyvista.PolyData``) placed in image space by ``MarkerToImage``."""
    import pyvista as pv

    mesh = pv.wrap(model.surface_polydata(resolution)).copy()
    mesh.points = apply_transform(marker_to_image, np.asarray(mesh.points, dtype=float))
    return mesh


def ct_context_surface(image: sitk.Image, iso_value: float | None = None, max_voxels: int = MAX_CONTEXT_VOXELS):
    """Iso-surface (``pyvista.PolyData``, LPS mm) of a CT binned to at most ``max_voxels`` voxels.

    Thin sheets (metal streaks) and small disconnected pieces are left out
    (:func:`EMRegModule.rendering.context.context_surface`); ``iso_value`` defaults to Otsu's
    threshold (air versus everything else). Oblique and flipped CTs come out right (physical
    space). Returns ``(surface, iso_value)``.
    """
    shown = context_surface(binned_ct(image, max_voxels), iso_value)
    return shown.surface, shown.iso_value


def _lookup_table(colormap: str, clim: tuple[float, float]):
    import pyvista as pv

    table = colormap_table(colormap)
    values = np.hstack([table, np.full((256, 1), 255, dtype=np.uint8)])
    lut = pv.LookupTable(values=values)
    lut.scalar_range = clim
    return lut


def _scene_bounds(meshes: list, points: list[np.ndarray]) -> np.ndarray:
    lows, highs = [], []
    for mesh in meshes:
        if mesh.n_points:
            b = np.asarray(mesh.bounds).reshape(3, 2)
            lows.append(b[:, 0])
            highs.append(b[:, 1])
    for p in points:
        if p is not None and len(p):
            lows.append(np.min(p, axis=0))
            highs.append(np.max(p, axis=0))
    if not lows:
        return np.array([-50.0, 50.0, -50.0, 50.0, -50.0, 50.0])
    low, high = np.min(lows, axis=0), np.max(highs, axis=0)
    return np.column_stack([low, high]).ravel()


def render_frame_scene(
    scene: FrameScene, window_size: tuple[int, int] = (960, 720), view: str = "oblique",
    camera: Camera | None = None, focus: str = "markers",
) -> np.ndarray:
    """Render the scene offscreen; returns an RGB ``uint8`` image (height, width, 3).

    ``view`` picks a direction from :data:`VIEWS`; the camera then frames the markers
    (``focus="markers"``) or everything (``focus="all"``). ``camera`` overrides both.
    """
    return render_frame_views(scene, window_size, (view,), camera, focus)[0]


def render_frame_views(
    scene: FrameScene, window_size: tuple[int, int] = (960, 720), views: tuple[str, ...] = ("oblique",),
    camera: Camera | None = None, focus: str = "markers",
) -> list[np.ndarray]:
    """Render the scene once per view of ``views`` (RGB ``uint8`` images), building it only once."""
    renderer = FrameSceneRenderer(scene, window_size, focus)
    try:
        return renderer.screenshots(views, camera)
    finally:
        renderer.close()


class FrameSceneRenderer:
    """An offscreen plotter holding a built scene: build it early, add the CT surface late, then take views.

    Building the scene and drawing it once (:meth:`warm_up`: OpenGL context, shaders, marker
    meshes) can happen while the CT is still being read; :meth:`set_context_surface` then adds
    the surface made from it, and :meth:`screenshots` renders the views. The images are those
    of :func:`render_frame_views` on the finished scene.
    """

    def __init__(self, scene: FrameScene, window_size: tuple[int, int] = (960, 720), focus: str = "markers") -> None:
        vtk_imports_uninterrupted()  # the Plotter loads VTK's rendering modules
        import pyvista as pv

        prepare_offscreen()
        self.scene = scene
        self.window_size = window_size
        self.focus = focus
        self.plotter = pv.Plotter(off_screen=True, window_size=list(window_size), lighting="light kit")
        try:
            self.plotter.disable_anti_aliasing()
            self.plotter.set_background("white")
            self.meshes_for_bounds, self.points_for_bounds = _add_scene(self.plotter, scene, window_size, focus)
        except BaseException:
            self.plotter.close()
            raise

    def warm_up(self) -> None:
        """Draw once (discarded) so that the views later cost only their own rendering."""
        _frame_camera(self.plotter, _scene_bounds(self.meshes_for_bounds, self.points_for_bounds), "oblique")
        self.plotter.screenshot(return_img=False)  # pyvista draws the first frame only through a screenshot

    def set_context_surface(self, surface) -> None:
        """Add the CT context surface (``pyvista.PolyData``, LPS mm; None or empty: nothing)."""
        if _add_context_surface(self.plotter, surface) and self.focus == "all":
            self.meshes_for_bounds.append(surface)

    def screenshots(self, views: tuple[str, ...], camera: Camera | None = None) -> list[np.ndarray]:
        """One RGB ``uint8`` image per view of :data:`VIEWS` (or one with the explicit ``camera``)."""
        unknown = [view for view in views if view not in VIEWS]
        if unknown:
            raise ValueError(f"unknown view {unknown[0]!r}; known: {', '.join(VIEWS)}")
        images = []
        for view in views:
            if camera is not None:
                _set_camera(self.plotter, camera)
            else:
                _frame_camera(self.plotter, _scene_bounds(self.meshes_for_bounds, self.points_for_bounds), view)
            self.plotter.render()  # a screenshot after the first one shows the last frame drawn, not the new camera
            image = self.plotter.screenshot(return_img=True)
            images.append(np.ascontiguousarray(np.asarray(image)[:, :, :3], dtype=np.uint8))
        return images

    def close(self) -> None:
        self.plotter.close()


def _add_context_surface(plotter, surface) -> bool:
    """Add the CT surface; not drawn here (pyvista draws a frame per mesh added after the first one): the views
    that follow draw it."""
    if surface is None or not surface.n_points:
        return False
    plotter.add_mesh(surface, color=(0.93, 0.91, 0.86), opacity=0.22, smooth_shading=False, name="ct_surface",
                     render=False)
    return True


def _add_scene(plotter, scene: FrameScene, window_size: tuple[int, int], focus: str) -> tuple[list, list]:
    """Every actor of the scene; returns the meshes and point sets the camera should frame."""
    meshes_for_bounds: list = []
    points_for_bounds: list[np.ndarray] = []
    surface = scene.context_surface
    if surface is None and scene.ct is not None:
        surface, _ = ct_context_surface(scene.ct, scene.iso_value)
    if _add_context_surface(plotter, surface) and focus == "all":
        meshes_for_bounds.append(surface)
    meshes_for_bounds += _add_markers(plotter, scene, window_size)
    if scene.reference_to_image is not None:
        _add_reference_sensor(plotter, np.asarray(scene.reference_to_image, dtype=float))
        points_for_bounds.append(np.asarray(scene.reference_to_image, dtype=float)[None, :3, 3])
    points_for_bounds += _add_points(plotter, scene)
    if scene.show_labels:
        _add_labels(plotter, scene)
    if scene.title:
        plotter.add_text(scene.title, position="upper_left", font_size=10, color="black", name="title")
    return meshes_for_bounds, points_for_bounds


def _add_markers(plotter, scene: FrameScene, window_size: tuple[int, int]) -> list:
    """The marker models coloured by residual (grey: unpaired) and the residual colour bar."""
    residuals = np.array([m.residual_mm for m in scene.markers if m.residual_mm is not None], dtype=float)
    clim = scene.residual_range or residual_range(residuals)
    lut = _lookup_table(scene.colormap, clim)
    scalar_mapper = None
    meshes = []
    for i, marker in enumerate(scene.markers):
        mesh = marker_mesh(scene.model, marker.marker_to_image)
        meshes.append(mesh)
        if marker.residual_mm is None:
            plotter.add_mesh(mesh, color=np.asarray(GREY) / 255.0, smooth_shading=True, split_sharp_edges=True,
                             name=f"marker_{i}")
        else:
            mesh.point_data["residual_mm"] = np.full(mesh.n_points, float(marker.residual_mm))
            actor = plotter.add_mesh(mesh, scalars="residual_mm", cmap=lut, clim=clim, smooth_shading=True,
                                     split_sharp_edges=True, show_scalar_bar=False, name=f"marker_{i}")
            scalar_mapper = actor.mapper
    if scalar_mapper is not None and scene.show_scalar_bar:
        steps = int(round((clim[1] - clim[0]) / 0.5))
        n_labels = steps + 1 if steps <= 6 else 5
        font_scale = min(1.0, window_size[0] / 960.0)
        plotter.add_scalar_bar(title="residual (mm)", mapper=scalar_mapper, n_labels=n_labels, fmt="%.1f",
                               color="black", vertical=True, position_x=0.84, position_y=0.25, width=0.07,
                               height=0.5, title_font_size=max(9, int(round(14 * font_scale))),
                               label_font_size=max(8, int(round(12 * font_scale))))
    return meshes


def _add_points(plotter, scene: FrameScene) -> list[np.ndarray]:
    """Calibration points, sensor points and targets as spheres, and the navigated path as a line."""
    import pyvista as pv

    shown = []
    for points, color, radius, name in (
        (scene.calibration_points, CALIBRATION, 0.9, "calibration_points"),
        (scene.sensor_points, SENSOR, 0.6, "sensor_points"),
        (scene.targets, TARGET, 1.5, "targets"),
    ):
        if points is not None and len(points):
            points = np.asarray(points, dtype=float).reshape(-1, 3)
            glyphs = pv.PolyData(points).glyph(geom=pv.Sphere(radius=radius, theta_resolution=16,
                                                              phi_resolution=16), scale=False, orient=False)
            plotter.add_mesh(glyphs, color=np.asarray(color) / 255.0, smooth_shading=True, name=name)
            shown.append(points)
    if scene.navigation_path is not None and len(scene.navigation_path) > 1:
        path = np.asarray(scene.navigation_path, dtype=float).reshape(-1, 3)
        plotter.add_mesh(pv.lines_from_points(path), color=np.asarray(NAVIGATION) / 255.0, line_width=2,
                         name="navigation")
    return shown


def _add_labels(plotter, scene: FrameScene) -> None:
    label_points, labels = [], []
    for marker in scene.markers:
        label_points.append(apply_transform(marker.marker_to_image, [0.0, scene.model.height_mm + 2.0, 0.0]))
        labels.append(marker.label)
    if scene.targets is not None and scene.target_labels:
        label_points.extend(np.asarray(scene.targets, dtype=float).reshape(-1, 3))
        labels.extend(scene.target_labels)
    if labels:
        plotter.add_point_labels(np.asarray(label_points), labels, font_size=11, bold=False, text_color="black",
                                 shape_color="white", shape_opacity=0.7, show_points=False, always_visible=True,
                                 margin=2, name="labels")


def _set_camera(plotter, camera: Camera) -> None:
    plotter.camera.position = camera.position
    plotter.camera.focal_point = camera.focal_point
    plotter.camera.up = camera.view_up
    plotter.camera.view_angle = camera.view_angle_deg
    plotter.renderer.ResetCameraClippingRange()


def _frame_camera(plotter, bounds: np.ndarray, view: str) -> None:
    """Look from the ``view`` direction at the centre of ``bounds`` and fit them in the window."""
    direction, up = VIEWS[view]
    direction = np.asarray(direction, dtype=float) / np.linalg.norm(direction)
    centre = bounds.reshape(3, 2).mean(axis=1)
    plotter.camera.focal_point = tuple(centre)
    plotter.camera.position = tuple(centre + direction * 1000.0)
    plotter.camera.up = up
    plotter.camera.view_angle = 30.0
    plotter.renderer.ResetCamera(*bounds)
    plotter.camera.zoom(1.15)
    plotter.renderer.ResetCameraClippingRange()


def _add_reference_sensor(plotter, reference_to_image: np.ndarray) -> None:
    import pyvista as pv

    length, width, height = REFERENCE_SENSOR_SIZE_MM
    box = pv.Box(bounds=(-length / 2, length / 2, -width / 2, width / 2, -height / 2, height / 2))
    box.points = apply_transform(reference_to_image, np.asarray(box.points, dtype=float))
    plotter.add_mesh(box, color=(0.25, 0.25, 0.3), name="reference_sensor")
    origin = reference_to_image[:3, 3]
    for axis, color in zip(range(3), ((0.85, 0.1, 0.1), (0.1, 0.7, 0.1), (0.1, 0.2, 0.9)), strict=True):
        direction = reference_to_image[:3, axis]
        arrow = pv.Arrow(start=origin, direction=direction, scale=18.0, tip_length=0.25, tip_radius=0.08,
                         shaft_radius=0.03)
        plotter.add_mesh(arrow, color=color, name=f"reference_axis_{axis}")
