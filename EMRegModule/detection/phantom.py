"""Small synthetic CT volumes for testing and benchmarking detection (not the case simulator).

Objects are painted with partial volume (sub-voxel supersampling of an inside test in the
object's own frame), then the volume is blurred with an isotropic Gaussian (physical mm) and
noise is added. Geometry (origin, spacing, direction) is honoured, so oblique and flipped
images come out right. ``EMRegModule.simulation`` makes whole realistic cases; this module
only serves unit tests and the large-volume benchmark.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np
import SimpleITK as sitk
from scipy import ndimage

from ..marker_model import MarkerModel
from ..transforms import apply_transform, invert_rigid, make_transform, rotation_from_y_axis

InsideFn = Callable[[np.ndarray], np.ndarray]

AIR_HU = -1000.0
POM_HU = 340.0
PVC_HU = 1200.0


@dataclass
class PaintedObject:
    """One object: an inside test in its own frame (mm), its local bounding box, its pose and HU."""

    inside: InsideFn
    bounds_local: tuple[np.ndarray, np.ndarray]
    object_to_image: np.ndarray
    hu: float
    kind: str = "object"
    info: dict = field(default_factory=dict)
    over: bool = False
    """False: the object displaces air (right for objects that touch but do not overlap, no
    dark film at contacts); True: painted over whatever lies beneath (nested objects)."""


def marker_object(model: MarkerModel, origin: Sequence[float], axis: Sequence[float], hu: float = PVC_HU,
                  spin_deg: float = 0.0) -> PaintedObject:
    """A marker whose bottom-face centre is ``origin`` and +Y is ``axis`` (image space, mm)."""
    rotation = rotation_from_y_axis(axis)
    spin = np.radians(spin_deg)
    c, s = np.cos(spin), np.sin(spin)
    rotation = rotation @ np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])
    r = model.bottom_diameter_mm / 2
    marker_to_image = make_transform(rotation, origin)
    return PaintedObject(model.contains, (np.array([-r, 0, -r]), np.array([r, model.height_mm, r])),
                         marker_to_image, hu, "marker", {"origin": np.asarray(origin, float),
                                                        "axis": rotation[:, 1].copy()})


def box_object(center: Sequence[float], half_size: Sequence[float], hu: float, rotation: np.ndarray | None = None,
               kind: str = "box") -> PaintedObject:
    """A box (half sizes in mm) centred at ``center``."""
    half = np.asarray(half_size, dtype=float)

    def inside(p: np.ndarray) -> np.ndarray:
        return np.all(np.abs(p) <= half, axis=-1)

    return PaintedObject(inside, (-half, half), make_transform(rotation, center), hu, kind,
                         {"center": np.asarray(center, float), "box_half": half})


def ellipsoid_object(center: Sequence[float], radii: Sequence[float], hu: float, rotation: np.ndarray | None = None,
                     kind: str = "sphere") -> PaintedObject:
    """An ellipsoid with semi-axes ``radii`` (mm)."""
    radii_arr = np.asarray(radii, dtype=float)

    def inside(p: np.ndarray) -> np.ndarray:
        return np.sum((p / radii_arr) ** 2, axis=-1) <= 1.0

    return PaintedObject(inside, (-radii_arr, radii_arr), make_transform(rotation, center), hu, kind,
                         {"center": np.asarray(center, float)})


def cylinder_object(center: Sequence[float], axis: Sequence[float], radius: float, length: float, hu: float,
                    kind: str = "rod") -> PaintedObject:
    """A solid cylinder (a rod) centred at ``center`` along ``axis``."""

    def inside(p: np.ndarray) -> np.ndarray:
        return (p[..., 0] ** 2 + p[..., 2] ** 2 <= radius**2) & (np.abs(p[..., 1]) <= length / 2)

    half = np.array([radius, length / 2, radius])
    return PaintedObject(inside, (-half, half), make_transform(rotation_from_y_axis(axis), center), hu, kind,
                         {"center": np.asarray(center, float)})


def make_image_geometry(size: Sequence[int], spacing: Sequence[float], origin: Sequence[float] = (0, 0, 0),
                        direction: np.ndarray | None = None) -> sitk.Image:
    """An empty int16 image carrying the geometry (used to map indices to LPS)."""
    image = sitk.Image([int(v) for v in size], sitk.sitkInt16)
    image.SetSpacing([float(v) for v in spacing])
    image.SetOrigin([float(v) for v in origin])
    if direction is not None:
        image.SetDirection([float(v) for v in np.asarray(direction, dtype=float).ravel()])
    return image


def index_to_image_of(image: sitk.Image) -> np.ndarray:
    direction = np.asarray(image.GetDirection(), dtype=float).reshape(3, 3)
    matrix = np.eye(4)
    matrix[:3, :3] = direction * np.asarray(image.GetSpacing(), dtype=float)[None, :]
    matrix[:3, 3] = image.GetOrigin()
    return matrix


def paint(volume_zyx: np.ndarray, index_to_image: np.ndarray, obj: PaintedObject, supersample: int = 7,
          offset_ijk: Sequence[int] = (0, 0, 0), background_hu: float = AIR_HU) -> None:
    """Composite one object into ``volume_zyx`` (float, numpy order z, y, x) with partial volume.

    ``offset_ijk`` is the image index of ``volume_zyx[0, 0, 0]`` (to paint into a sub-block).
    """
    lo, hi = obj.bounds_local
    corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    object_to_index = invert_rigid_affine(index_to_image) @ obj.object_to_image
    corners_index = apply_transform(object_to_index, corners)
    offset = np.asarray(offset_ijk, dtype=int)
    shape_ijk = np.array(volume_zyx.shape[::-1])
    start = np.maximum(np.floor(corners_index.min(axis=0)).astype(int) - 1 - offset, 0)
    stop = np.minimum(np.ceil(corners_index.max(axis=0)).astype(int) + 2 - offset, shape_ijk)
    if np.any(stop <= start):
        return
    ii, jj, kk = (np.arange(a, b) + o for a, b, o in zip(start, stop, offset, strict=True))
    index_to_object = invert_rigid(obj.object_to_image) @ index_to_image
    occupancy = _grid_aligned_box(obj, index_to_object, ii, jj, kk)
    if occupancy is None:
        occupancy = sampled_occupancy(obj, index_to_object, ii, jj, kk, supersample)
    block = volume_zyx[start[2]:stop[2], start[1]:stop[1], start[0]:stop[0]]
    if obj.over:
        block *= 1 - occupancy
        block += obj.hu * occupancy
    else:
        block += (obj.hu - background_hu) * occupancy


def _grid_aligned_box(obj: PaintedObject, index_to_object: np.ndarray, ii: np.ndarray, jj: np.ndarray,
                      kk: np.ndarray) -> np.ndarray | None:
    """Exact voxel fill fractions of a box whose faces are parallel to the voxel grid, else None."""
    half = obj.info.get("box_half")
    if half is None:
        return None
    linear = index_to_object[:3, :3]
    scale = np.abs(linear).max(axis=0)  # mm per index step along each index axis
    permutation = np.abs(linear).argmax(axis=0)  # which object axis each index axis runs along
    if sorted(permutation) != [0, 1, 2] or not np.allclose(np.abs(linear), np.abs(linear) * 0 + (
            np.eye(3)[permutation].T * scale), atol=1e-9):
        return None
    fractions = []
    for axis, indices in enumerate((ii, jj, kk)):
        along = linear[permutation[axis], axis] * indices + index_to_object[permutation[axis], 3]
        h, step = half[permutation[axis]], scale[axis]
        overlap = np.clip(np.minimum(along + step / 2, h) - np.maximum(along - step / 2, -h), 0, step) / step
        fractions.append(overlap.astype(np.float32))
    return fractions[2][:, None, None] * fractions[1][None, :, None] * fractions[0][None, None, :]


def sampled_occupancy(obj: PaintedObject, index_to_object: np.ndarray, ii: np.ndarray, jj: np.ndarray,
                       kk: np.ndarray, supersample: int) -> np.ndarray:
    grid = np.stack(np.meshgrid(kk, jj, ii, indexing="ij")[::-1], axis=-1).astype(float)
    centres = obj.inside(apply_transform(index_to_object, grid.reshape(-1, 3))).reshape(grid.shape[:3])
    occupancy = centres.astype(np.float32)
    # only voxels next to the surface need sub-voxel sampling (objects are thicker than a voxel)
    cube = np.ones((3, 3, 3), dtype=bool)
    edge = ndimage.binary_dilation(centres, cube) & ~ndimage.binary_erosion(centres, cube, border_value=1)
    where = np.argwhere(edge)
    if len(where):
        sub = (np.arange(supersample) + 0.5) / supersample - 0.5
        offsets = np.stack(np.meshgrid(sub, sub, sub, indexing="ij"), axis=-1).reshape(-1, 3)
        base = apply_transform(index_to_object, grid[where[:, 0], where[:, 1], where[:, 2]]).astype(np.float32)
        offsets_object = (offsets @ index_to_object[:3, :3].T).astype(np.float32)
        hits = np.zeros(len(where), dtype=np.float32)
        for chunk in np.array_split(offsets_object, max(1, len(offsets_object) // 25)):
            local = base[:, None, :] + chunk[None, :, :]
            hits += obj.inside(local.reshape(-1, 3)).reshape(len(where), -1).sum(axis=1)
        occupancy[where[:, 0], where[:, 1], where[:, 2]] = hits / len(offsets)
    return occupancy


def invert_rigid_affine(matrix: np.ndarray) -> np.ndarray:
    return np.linalg.inv(matrix)


def render(geometry: sitk.Image, objects: Sequence[PaintedObject], background_hu: float = AIR_HU,
           blur_mm: float = 0.4, noise_hu: float = 20.0, seed: int = 0, supersample: int = 7,
           pixel_type: int = sitk.sitkInt16) -> sitk.Image:
    """Paint ``objects`` in order into a volume with ``geometry``; blur (mm), add noise (HU), cast."""
    size = geometry.GetSize()
    volume = np.full(size[::-1], background_hu, dtype=np.float32)
    index_to_image = index_to_image_of(geometry)
    for obj in objects:
        paint(volume, index_to_image, obj, supersample, background_hu=background_hu)
    if blur_mm > 0:
        sigma = [blur_mm / s for s in geometry.GetSpacing()[::-1]]
        volume = ndimage.gaussian_filter(volume, sigma, mode="nearest")
    if noise_hu > 0:
        volume += np.random.default_rng(seed).normal(0.0, noise_hu, volume.shape).astype(np.float32)
    if pixel_type == sitk.sitkInt16:
        volume = np.clip(np.rint(volume), -32768, 32767).astype(np.int16)
    image = sitk.GetImageFromArray(volume)
    image.CopyInformation(geometry)
    return sitk.Cast(image, pixel_type) if image.GetPixelID() != pixel_type else image


def marker_truth(objects: Sequence[PaintedObject]) -> list[dict]:
    """Origins and axes (image space) of the markers among ``objects``."""
    return [{"origin": o.info["origin"], "axis": o.info["axis"], "marker_to_image": o.object_to_image}
            for o in objects if o.kind == "marker"]


def oblique_direction(seed: int = 1, flip: Sequence[int] = (1, 1, -1)) -> np.ndarray:
    """A random orthonormal direction matrix with column signs ``flip`` (det may be -1)."""
    rng = np.random.default_rng(seed)
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q = q @ np.diag(np.sign(np.diag(r)))
    if np.linalg.det(q) < 0:
        q[:, 0] *= -1
    return q @ np.diag(np.asarray(flip, dtype=float))


def center_of(geometry: sitk.Image) -> np.ndarray:
    """Physical centre of the image's voxel grid (mm)."""
    size = np.asarray(geometry.GetSize(), dtype=float)
    return np.asarray(geometry.TransformContinuousIndexToPhysicalPoint(list((size - 1) / 2)))


def add_streaks(volume_zyx: np.ndarray, index_to_image: np.ndarray, centre: Sequence[float],
                amplitude_hu: float = 400.0, n_streaks: int = 6, width_mm: float = 0.8, seed: int = 0) -> None:
    """Bright and dark lines through ``centre`` in planes of constant LPS z, fading with distance (metal)."""
    rng = np.random.default_rng(seed)
    kk, jj, ii = np.indices(volume_zyx.shape, dtype=np.float32)
    points = [index_to_image[r, 0] * ii + index_to_image[r, 1] * jj + index_to_image[r, 2] * kk
              + index_to_image[r, 3] - centre[r] for r in range(3)]
    radial = np.sqrt(points[0] ** 2 + points[1] ** 2)
    fade = 12.0 / (12.0 + radial) * np.exp(-np.maximum(np.abs(points[2]) - 6.0, 0) ** 2 / 4.5)
    for n, angle in enumerate(np.sort(rng.uniform(0, np.pi, n_streaks))):
        perp = points[0] * np.sin(angle) - points[1] * np.cos(angle)
        volume_zyx += ((-1) ** n * amplitude_hu * np.exp(-perp**2 / (2 * width_mm**2)) * fade).astype(np.float32)


@dataclass
class Scene:
    """A synthetic CT with its markers' truth and the other objects' kinds and centres."""

    image: sitk.Image
    markers: list[dict]
    others: list[dict]
    model: MarkerModel


def scene(spacing: Sequence[float] = (0.6, 0.6, 0.6), direction: np.ndarray | None = None, noise_hu: float = 20.0,
          blur_mm: float = 0.45, seed: int = 0, pvc_hu: float = PVC_HU, decoys: bool = True,
          metal: bool = True, cut_marker: bool = True, model: MarkerModel | None = None) -> Scene:
    """A 100 x 100 x 66 mm test scene in a box-aligned frame (any direction cosines).

    A POM plate (340 HU) with two markers standing on it and one lying on its side on it
    (plastic on one side, air on the other), three markers tilted at random in air; with
    ``decoys`` a PVC sphere of a marker's volume, a PVC rod, a bone (cortex 1900 HU, marrow
    300 HU) and a small PVC cube; with ``metal`` a metal block (3071 HU) with streaks and a PVC
    cube beside it; with ``cut_marker`` a marker half outside the image.
    """
    model = model or MarkerModel()
    size = [int(round(extent / s)) for extent, s in zip((100.0, 100.0, 66.0), spacing, strict=True)]
    geometry = make_image_geometry(size, spacing, direction=direction)
    centre = center_of(geometry)
    frame = np.asarray(geometry.GetDirection(), dtype=float).reshape(3, 3)
    ex, ey, ez = frame[:, 0], frame[:, 1], frame[:, 2]

    def at(x: float, y: float, z: float) -> np.ndarray:
        return centre + x * ex + y * ey + z * ez

    rng = np.random.default_rng(seed)
    plate_top = -20.0
    objects = [box_object(at(0, 0, plate_top - 6), (60, 60, 6), POM_HU, rotation=frame, kind="pom")]
    objects.append(marker_object(model, at(-30, -25, plate_top), ez, pvc_hu))
    objects.append(marker_object(model, at(0, -25, plate_top), ez, pvc_hu, spin_deg=30))
    lying = ex * np.cos(0.3) + ey * np.sin(0.3)
    objects.append(marker_object(model, at(25, -25, plate_top + model.bottom_diameter_mm / 2) - lying * 9,
                                 lying, pvc_hu))
    for x, y in ((-25, 8), (5, 10), (30, 12)):
        axis = rng.normal(size=3)
        axis /= np.linalg.norm(axis)
        objects.append(marker_object(model, at(x, y, 4) - axis * model.centroid_y_mm, axis, pvc_hu))
    if decoys:
        radius = (3 * model.volume_mm3 / (4 * np.pi)) ** (1 / 3)
        objects.append(ellipsoid_object(at(-32, 34, 5), (radius,) * 3, pvc_hu, kind="sphere"))
        objects.append(cylinder_object(at(0, 36, 5), ex + 0.3 * ez, 3.0, 30.0, pvc_hu, kind="rod"))
        objects.append(ellipsoid_object(at(32, 34, 5), (10, 7, 7), 1900.0, kind="bone"))
        objects.append(ellipsoid_object(at(32, 34, 5), (8.5, 5.5, 5.5), 300.0, kind="marrow"))
        objects[-1].over = True
        objects.append(box_object(at(-8, -2, 22), (4, 4, 4), pvc_hu, kind="small cube"))
    if metal:
        objects.append(box_object(at(28, 0, 24), (4, 4, 10), 3071.0, kind="metal"))
        objects.append(box_object(at(28, 14, 24), (6, 6, 6), pvc_hu, kind="cube by metal"))
    if cut_marker:
        objects.append(marker_object(model, at(-54, -30, 20), ex, pvc_hu))
        objects[-1].kind = "cut marker"
    geometry_to_paint = geometry
    volume = np.full(size[::-1], AIR_HU, dtype=np.float32)
    index_to_image = index_to_image_of(geometry_to_paint)
    for obj in objects:
        paint(volume, index_to_image, obj)
    if blur_mm > 0:
        volume = ndimage.gaussian_filter(volume, [blur_mm / s for s in spacing[::-1]], mode="nearest")
    if noise_hu > 0:
        volume += np.random.default_rng(seed + 1).normal(0.0, noise_hu, volume.shape).astype(np.float32)
    if metal:
        add_streaks(volume, index_to_image, at(28, 0, 24), seed=seed)
    image = sitk.GetImageFromArray(np.clip(np.rint(volume), -1024, 3071).astype(np.int16))
    image.CopyInformation(geometry)
    markers = marker_truth([o for o in objects if o.kind == "marker"])
    others = [{"kind": o.kind, "center": apply_transform(o.object_to_image, np.zeros(3))}
              for o in objects if o.kind not in ("marker", "pom", "marrow")]
    return Scene(image, markers, others, model)
