"""Small, fixed, fully deterministic sample scenes for the renderers and the report.

Used by the golden-image tests (``Testing/Python/test_golden_images.py``), by
``scripts/regenerate_baselines`` and by the report tests: a synthetic CT block with PVC
markers painted with partial volume, markers at fixed poses, a fixed ``ReferenceToImage``
and calibration points derived from it. Nothing here runs the detection or registration
pipeline, so the scenes stay fast and independent of those stages.

Frames: image space is LPS (mm); calibration points are in the Reference frame.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import SimpleITK as sitk

from ..marker_model import MarkerModel
from ..transforms import (
    apply_transform,
    axis_angle_to_rotation,
    fit_rigid,
    invert_rigid,
    make_transform,
    residuals,
    rotation_from_y_axis,
)

AIR_HU = -1000.0
FRAME_HU = 300.0  # polyoxymethylene frame body
PVC_HU = 1300.0
SENSOR_L_MM = 14.2


@dataclass
class SampleMarker:
    """A marker of a sample scene: label, origin (bottom-face centre) and unit axis (+Y), LPS mm."""

    label: str
    origin: np.ndarray
    axis: np.ndarray

    @property
    def marker_to_image(self) -> np.ndarray:
        return make_transform(rotation_from_y_axis(self.axis), self.origin)


def sample_markers(shift_mm: tuple[float, float, float] = (0.0, 0.0, 0.0), which: int | None = None
                   ) -> list[SampleMarker]:
    """Five markers standing on the top face (z = 0) of a block, slightly tilted, at fixed places.

    ``shift_mm`` moves marker number ``which`` (all when None): the perturbation of the tests.
    """
    layout = [("I01", (-22.0, -20.0), (0.10, 0.05)), ("I02", (21.0, -19.0), (-0.08, 0.12)),
              ("I03", (22.0, 21.0), (0.0, -0.15)), ("I04", (-21.0, 20.0), (0.14, 0.0)),
              ("I05", (0.0, 1.0), (-0.05, -0.06))]
    markers = []
    for i, (label, (x, y), (tx, ty)) in enumerate(layout):
        axis = np.array([tx, ty, 1.0])
        origin = np.array([x, y, 0.0])
        if which is None or which == i:
            origin = origin + np.asarray(shift_mm, dtype=float)
        markers.append(SampleMarker(label, origin, axis / np.linalg.norm(axis)))
    return markers


def sample_reference_to_image() -> np.ndarray:
    """A fixed ``ReferenceToImage``: the reference sensor sits in front of the block, turned 20 degrees."""
    rotation = axis_angle_to_rotation([0.2, 0.3, 1.0], np.radians(20.0))
    return make_transform(rotation, [0.0, -36.0, -6.0])


def empty_ct(size: tuple[int, int, int] = (120, 120, 60), spacing_mm: float = 0.6,
             origin: tuple[float, float, float] = (-36.0, -36.0, -12.0)) -> sitk.Image:
    """A CT geometry (int16, identity direction) filled with air."""
    image = sitk.Image(list(size), sitk.sitkInt16)
    image.SetSpacing([spacing_mm] * 3)
    image.SetOrigin(list(origin))
    return sitk.Add(image, int(AIR_HU))


def paint_sample_ct(markers: list[SampleMarker], model: MarkerModel | None = None,
                    size: tuple[int, int, int] = (120, 120, 60), spacing_mm: float = 0.6,
                    origin: tuple[float, float, float] = (-36.0, -36.0, -12.0), supersample: int = 3,
                    block: bool = True) -> sitk.Image:
    """A synthetic CT: a frame block (top face at z = 0) and the markers, with partial volume.

    Each voxel's marker fraction is the share of ``supersample**3`` sub-samples inside the
    marker solid (the pinhole included), so edges are smooth and a shift below a voxel shows.
    """
    model = model or MarkerModel()
    image = empty_ct(size, spacing_mm, origin)
    array = sitk.GetArrayFromImage(image).astype(np.float32)  # (k, j, i)
    spacing = np.full(3, spacing_mm)
    origin_arr = np.asarray(origin, dtype=float)
    if block:
        z = origin_arr[2] + np.arange(size[2]) * spacing_mm
        fraction = np.clip((0.0 - z) / spacing_mm + 0.5, 0.0, 1.0)  # block below z = 0, one-voxel ramp
        array += (FRAME_HU - AIR_HU) * fraction[:, None, None]
    offsets = (np.arange(supersample) + 0.5) / supersample - 0.5
    sub = np.stack(np.meshgrid(offsets, offsets, offsets, indexing="ij"), axis=-1).reshape(-1, 3)
    half_diagonal = 0.87 * spacing_mm
    radius = np.hypot(model.bottom_diameter_mm / 2, model.height_mm / 2) + 1.0
    for marker in markers:
        image_to_marker = invert_rigid(marker.marker_to_image)
        centre = marker.origin + marker.axis * model.height_mm / 2
        low = np.maximum(np.floor((centre - radius - origin_arr) / spacing).astype(int), 0)
        high = np.minimum(np.ceil((centre + radius - origin_arr) / spacing).astype(int) + 1, np.asarray(size))
        ii, jj, kk = np.meshgrid(*(np.arange(low[d], high[d]) for d in range(3)), indexing="ij")
        voxels = np.stack([ii, jj, kk], axis=-1).reshape(-1, 3)
        centres_marker = apply_transform(image_to_marker, voxels * spacing + origin_arr)
        distance = model.signed_distance(centres_marker)
        radial = np.hypot(centres_marker[:, 0], centres_marker[:, 2])
        near_hole = (radial < model.pinhole_diameter_mm / 2 + half_diagonal) \
            & (centres_marker[:, 1] > model.pinhole_bottom_mm - half_diagonal)
        fraction = (distance < 0).astype(float)
        edge = (np.abs(distance) < half_diagonal) | (near_hole & (distance < half_diagonal))
        fraction[near_hole & ~edge] = 0.0
        points = (voxels[edge][:, None, :] + sub[None, :, :]) * spacing + origin_arr
        inside = model.contains(apply_transform(image_to_marker, points.reshape(-1, 3))).reshape(-1, len(sub))
        fraction[edge] = inside.mean(axis=1)
        hit = fraction > 0
        k, j, i = voxels[hit, 2], voxels[hit, 1], voxels[hit, 0]
        array[k, j, i] = array[k, j, i] * (1 - fraction[hit]) + PVC_HU * fraction[hit]
    painted = sitk.GetImageFromArray(np.round(array).astype(np.int16))
    painted.CopyInformation(image)
    return painted


def sample_calibration_points(markers: list[SampleMarker], reference_to_image: np.ndarray,
                              l_mm: float = SENSOR_L_MM, noise_mm: float = 0.35, seed: int = 7) -> np.ndarray:
    """Calibration points (Reference frame) of the markers' sensor points, with fixed pseudo-random noise."""
    rng = np.random.default_rng(seed)
    image_points = np.stack([m.origin + l_mm * m.axis for m in markers])
    noise = rng.normal(scale=noise_mm / np.sqrt(3), size=image_points.shape)
    return apply_transform(invert_rigid(reference_to_image), image_points + noise)


def write_sample_run(case_dir: Path, out_dir: Path, unpaired_marker: bool = True,
                     with_evaluation: bool = True) -> dict:
    """Write a small case folder and the outputs of a run on it, following the spec's formats.

    The case holds ``ct.nrrd``, ``targets.mrk.json`` and ``case.toml``; OUT holds
    ``run.json``, ``markers.json``, ``frame_calibration.json``, ``registration.json``
    (solved here by minimising FRE(l) over a grid), ``navigation.csv`` and
    ``evaluation.json``. With ``unpaired_marker`` the fifth marker has no calibration point.
    Returns a few truths (``reference_to_image``, ``l_mm``) for assertions.
    """
    from ..io.atomic import atomic_write_json, atomic_write_text
    from ..io.image import image_geometry, write_image
    from ..io.markups import write_markups

    model = MarkerModel()
    case_dir, out_dir = Path(case_dir), Path(out_dir)
    case_dir.mkdir(parents=True, exist_ok=True)
    out_dir.mkdir(parents=True, exist_ok=True)
    markers = sample_markers()
    image = paint_sample_ct(markers, model)
    write_image(image, case_dir / "ct.nrrd")
    reference_to_image = sample_reference_to_image()
    calibrated = markers[:4] if unpaired_marker else markers
    points = sample_calibration_points(calibrated, reference_to_image)
    labels = [f"M{i + 1:02d}" for i in range(len(calibrated))]
    targets = np.array([[-10.0, -8.0, 12.0], [12.0, 10.0, 14.0], [0.0, 20.0, 8.0]])
    write_markups(case_dir / "targets.mrk.json", ["T1", "T2", "T3"], targets, name="T")
    atomic_write_text(case_dir / "case.toml", "[sensors]\nreference = 1\nprobe = 2\n\n[board]\n"
                                              "edges_mm = [75.0, 60.0, 75.0, 60.0]\n")
    atomic_write_json(out_dir / "markers.json", {
        "coordinate_system": "LPS", "image": image_geometry(image),
        "markers": [{"id": m.label, "origin": m.origin, "axis": m.axis, "volume_mm3": round(model.volume_mm3, 1),
                     "fit_rms_mm": 0.1} for m in markers],
        "rejected": [{"centroid": [30.0, -30.0, 2.0], "volume_mm3": 905.0, "reason": "volume 905 mm3 is not a "
                      "marker's (1985 mm3)"}],
    })
    atomic_write_json(out_dir / "frame_calibration.json", {
        "reference_sensor": 1, "probe_sensor": 2,
        "points": [{"label": label, "position": p, "direction": [0.0, 0.0, 1.0], "samples": 80, "std_mm": 0.12}
                   for label, p in zip(labels, points, strict=True)],
    })
    l_grid = np.linspace(model.pinhole_bottom_mm, model.pinhole_top_mm, 751)
    best = None
    for l_mm in l_grid:
        image_points = np.stack([m.origin + l_mm * m.axis for m in calibrated])
        fit = fit_rigid(points, image_points)
        error = float(np.sqrt(np.mean(residuals(fit, points, image_points) ** 2)))
        if best is None or error < best[0]:
            best = (error, l_mm, fit, residuals(fit, points, image_points))
    fre_mm, l_mm, fit, pair_residuals = best
    atomic_write_json(out_dir / "registration.json", {
        "ReferenceToImage": fit, "sensor_offset_l_mm": l_mm, "fre_mm": fre_mm,
        "pairs": [{"image_marker": m.label, "calibration_point": label, "residual_mm": r}
                  for m, label, r in zip(calibrated, labels, pair_residuals, strict=True)],
        "unpaired_image_markers": [m.label for m in markers[len(calibrated):]],
        "unpaired_calibration_points": [],
    })
    rows = ["time_s,x_mm,y_mm,z_mm,label"]
    for n in range(30):
        t = n / 10.0
        target = targets[min(n // 10, 2)]
        p = target + 0.6 * np.array([np.cos(t), np.sin(t), 0.2])
        rows.append(f"{t:.3f},{p[0]:.3f},{p[1]:.3f},{p[2]:.3f},T{min(n // 10, 2) + 1}")
    atomic_write_text(out_dir / "navigation.csv", "\n".join(rows) + "\n")
    if with_evaluation:
        atomic_write_json(out_dir / "evaluation.json", {
            "tre": {"mean_mm": 1.21, "std_mm": 0.3, "targets": {
                "T1": {"mean_mm": 1.02, "std_mm": 0.21, "n": 15}, "T2": {"mean_mm": 1.44, "std_mm": 0.33, "n": 15},
                "T3": {"mean_mm": 1.17, "std_mm": 0.25, "n": 15}}},
            "board": {"edges": {"L1": {"mean_mm": 75.18, "std_mm": 0.2, "n": 60},
                                "L2": {"mean_mm": 60.21, "std_mm": 0.18, "n": 60},
                                "L3": {"mean_mm": 74.83, "std_mm": 0.22, "n": 60},
                                "L4": {"mean_mm": 60.12, "std_mm": 0.19, "n": 60}}},
        })
    (out_dir / "run.json").write_text(json.dumps({
        "case": str(case_dir.resolve()), "ct": str((case_dir / "ct.nrrd").resolve()), "emreg_version": "test",
        "reference_sensor": 1, "probe_sensor": 2,
        "summary": ["detect: 5 markers, 1 rejected", f"register: FRE {fre_mm:.2f} mm"]}, indent=2) + "\n",
        encoding="utf-8")
    return {"reference_to_image": reference_to_image, "l_mm": SENSOR_L_MM, "solved_l_mm": l_mm, "fre_mm": fre_mm}


# --- the golden-image scenes (Testing/Baseline) ------------------------------------------------

GOLDEN_WINDOW = (400, 300)
GOLDEN_RESIDUALS = (0.2, 0.6, 1.1, 1.6, None)


def golden_frame_scene(shift_mm: tuple[float, float, float] = (0.0, 0.0, 0.0), colormap: str = "viridis"):
    """The 3D golden scene: five markers (the first moved by ``shift_mm``), a coarse CT block, the
    reference sensor and four calibration points; returns ``(FrameScene, Camera)``."""
    from .scene3d import Camera, FrameScene, SceneMarker

    model = MarkerModel()
    markers = sample_markers(shift_mm, which=0)
    ct = paint_sample_ct(sample_markers(), model, size=(60, 60, 30), spacing_mm=1.2, origin=(-36.0, -36.0, -12.0))
    calibration = np.stack([m.origin + SENSOR_L_MM * m.axis for m in markers[:4]]) + 0.3
    scene = FrameScene(
        model=model,
        markers=[SceneMarker(m.label, m.marker_to_image, r) for m, r in zip(markers, GOLDEN_RESIDUALS, strict=True)],
        ct=ct, iso_value=-350.0, reference_to_image=sample_reference_to_image(), calibration_points=calibration,
        colormap=colormap, residual_range=(0.0, 2.0), show_labels=False,
    )
    camera = Camera(position=(60.0, -110.0, 95.0), focal_point=(0.0, 0.0, 8.0), view_up=(0.0, 0.0, 1.0))
    return scene, camera


def golden_frame_image(shift_mm: tuple[float, float, float] = (0.0, 0.0, 0.0), colormap: str = "viridis"
                       ) -> np.ndarray:
    """The rendered 3D golden scene (RGB, 400 x 300)."""
    from .scene3d import render_frame_scene

    scene, camera = golden_frame_scene(shift_mm, colormap)
    return render_frame_scene(scene, GOLDEN_WINDOW, camera=camera)


def golden_slices_image(ct_shift_mm: tuple[float, float, float] = (0.0, 0.0, 0.0)) -> np.ndarray:
    """The slice-mosaic golden image: two markers of a 0.5 mm CT (the first painted ``ct_shift_mm`` away
    from where its fitted model is drawn), fixed display window."""
    from .slices import SliceMarker, marker_slices_mosaic

    model = MarkerModel()
    fitted = sample_markers()[:2]
    ct = paint_sample_ct(sample_markers(ct_shift_mm, which=0)[:2], model, size=(136, 70, 45), spacing_mm=0.5,
                         origin=(-36.0, -32.0, -4.0))
    markers = [SliceMarker(m.label, m.marker_to_image, f"{m.label} -> M0{i + 1}", paired=i == 0,
                           sensor_point=m.origin + SENSOR_L_MM * m.axis,
                           calibration_point=m.origin + SENSOR_L_MM * m.axis + np.array([0.3, 0.2, 0.0]))
               for i, m in enumerate(fitted)]
    return marker_slices_mosaic(ct, markers, model, columns=2, view_px=100, mm_per_px=0.25, window=(-1000.0, 1500.0))


def golden_residual_bars_image(colormap: str = "viridis") -> np.ndarray:
    """The bar-chart golden image: residuals coloured by ``colormap`` (RGB, 400 x 300)."""
    from .colors import colorize
    from .plots import bar_chart

    values = np.array([0.2, 0.6, 1.1, 1.6, 0.9])
    colors = [tuple(int(c) for c in rgb) for rgb in colorize(values, 0.0, 2.0, colormap)]
    return bar_chart([f"I0{i}" for i in range(1, 6)], values, title="Residual per marker", y_label="residual (mm)",
                     colors=colors, reference_lines=[(1.0, "FRE 1.00 mm")], size=GOLDEN_WINDOW)


def golden_fre_curve_image(l_chosen_mm: float = 14.2) -> np.ndarray:
    """The line-chart golden image: an FRE(l) parabola-like curve with the chosen l (RGB, 400 x 300)."""
    from .plots import line_chart

    l_values = np.linspace(11.0, 18.5, 76)
    values = np.sqrt(0.8 ** 2 + 0.3 * (l_values - 14.2) ** 2)
    return line_chart(l_values, values, "FRE(l)", "sensor offset l (mm)", "FRE (mm)", marker_x=l_chosen_mm,
                      marker_label=f"l = {l_chosen_mm:.2f} mm", size=GOLDEN_WINDOW)


#: Baseline file name -> function rendering it (no arguments: the unperturbed scene).
GOLDEN_IMAGES = {
    "frame_scene.png": golden_frame_image,
    "marker_slices.png": golden_slices_image,
    "residual_bars.png": golden_residual_bars_image,
    "fre_curve.png": golden_fre_curve_image,
}
