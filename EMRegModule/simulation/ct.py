"""CT synthesis: paint solids into a voxel grid, blur, add correlated noise and metal streaks.

Geometry: the grid is a SimpleITK-style image (origin, spacing, direction cosines, any of
them oblique, flipped or anisotropic); the solids live in the fiducial frame's CAD frame
("Frame") and reach the grid through ``FrameToImage`` (image = physical LPS space). Ground
truth is physical, so it does not depend on how voxels are indexed.

Method, in float32 throughout:

1. Painter's algorithm: air (-1000 HU), then each :class:`Layer` in turn,
   ``v <- v + f (HU - v)`` where ``f`` is the voxel's fill fraction (or ``v + f (HU + 1000)``
   for a layer that displaces air, see :class:`Layer`). Work is done in
   bricks of 16^3 voxels: a conservative SDF at brick centres skips bricks wholly outside
   and fills bricks wholly inside, so only bricks crossing a surface are evaluated voxel
   by voxel. Large smooth solids use an analytic partial-volume ramp
   ``f = clip(0.5 - sdf / w, 0, 1)`` (w = voxel size); small solids (markers, decoys,
   the metal sensor) are supersampled (n^3 points) in voxels near their surface.
2. White noise is added and the volume is blurred with a Gaussian point-spread function;
   the same kernel correlates the noise (as a reconstruction kernel does). The white-noise
   level is set so that the filtered noise has the requested standard deviation.
3. Streaks around metal (bright and dark lines through the metal in the axial planes of
   the scanner, i.e. planes of constant LPS z) are added, then values are clipped to
   [-1024, 3071] and rounded to int16.

:func:`paint_layers` is EMReg's one partial-volume painter: the test fixtures
(``Testing/Python/fixtures``) and the detection benchmark paint their small scenes with it too.
"""

from __future__ import annotations

import os
import shutil
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import SimpleITK as sitk
from scipy import ndimage

from ..io.atomic import atomic_path, cannot_write, itk_write_errors
from ..progress import QUIET, Progress
from .shapes import F32, Shape

AIR_HU = -1000.0
HU_MIN, HU_MAX = -1024, 3071
BRICK = 16


@dataclass
class Grid:
    """Voxel grid geometry: ``size`` (i, j, k), ``spacing`` (mm), ``origin`` (LPS mm), ``direction`` (3x3)."""

    size: tuple[int, int, int]
    spacing: np.ndarray
    origin: np.ndarray
    direction: np.ndarray

    @property
    def index_to_image(self) -> np.ndarray:
        """4x4 continuous index (i, j, k) -> LPS (mm)."""
        out = np.eye(4)
        out[:3, :3] = np.asarray(self.direction) * np.asarray(self.spacing)[None, :]
        out[:3, 3] = self.origin
        return out

    @property
    def shape_kji(self) -> tuple[int, int, int]:
        return (self.size[2], self.size[1], self.size[0])

    @property
    def n_voxels(self) -> int:
        return int(np.prod(self.size))

    def to_dict(self) -> dict:
        return {"size": [int(v) for v in self.size], "spacing": [float(v) for v in self.spacing],
                "origin": [float(v) for v in self.origin],
                "direction": [float(v) for v in np.asarray(self.direction).ravel()]}


def grid_around(points_image: np.ndarray, spacing: np.ndarray, direction: np.ndarray, margin_mm: float) -> Grid:
    """The smallest grid of given spacing and direction holding ``points_image`` (LPS) with a margin."""
    spacing = np.asarray(spacing, dtype=float)
    direction = np.asarray(direction, dtype=float)
    along = np.asarray(points_image, dtype=float) @ direction  # coordinates along the index axes (mm)
    lo = along.min(axis=0) - margin_mm
    hi = along.max(axis=0) + margin_mm
    size = np.ceil((hi - lo) / spacing).astype(int) + 1
    origin = direction @ lo
    return Grid(tuple(int(v) for v in size), spacing, origin, direction)


@dataclass
class Layer:
    """One solid of uniform density.

    ``supersample`` 0 uses the analytic partial-volume ramp; n > 0 averages n^3 exact
    membership tests in each voxel near the surface. ``over`` True paints the solid over what
    lies beneath it (``v <- v + f (HU - v)``); False makes it displace air
    (``v <- v + f (HU - AIR)``), right for solids that touch without overlapping (no dark film of
    air at the contact).
    """

    name: str
    shape: Shape
    hu: float
    supersample: int = 0
    over: bool = True


def paint_layers(volume: np.ndarray, grid: Grid, image_to_frame: np.ndarray, layers: list[Layer],
                 progress: Progress | None = None) -> None:
    """Paint ``layers`` in order into ``volume`` (float32, indexed [k, j, i]) in place."""
    progress = progress or QUIET
    index_to_frame = np.asarray(image_to_frame, dtype=float) @ grid.index_to_image
    with progress.step("paint solids", total=len(layers)) as step:
        for layer in layers:
            _paint(volume, grid, index_to_frame, layer)
            step.advance()


def _paint(volume: np.ndarray, grid: Grid, index_to_frame: np.ndarray, layer: Layer) -> None:
    frame_to_index = np.linalg.inv(index_to_frame)
    lo, hi = layer.shape.bounds
    corners = np.array([[a, b, c] for a in (lo[0], hi[0]) for b in (lo[1], hi[1]) for c in (lo[2], hi[2])])
    idx = corners @ frame_to_index[:3, :3].T + frame_to_index[:3, 3]
    start = np.maximum(np.floor(idx.min(axis=0)).astype(int) - 1, 0)
    stop = np.minimum(np.ceil(idx.max(axis=0)).astype(int) + 2, np.asarray(grid.size))  # exclusive
    if np.any(stop <= start):
        return
    a = index_to_frame[:3, :3]
    b = index_to_frame[:3, 3]
    spacing = np.linalg.norm(a, axis=0)
    ramp = float(np.prod(spacing) ** (1 / 3))
    voxel_half_diag = 0.5 * float(np.linalg.norm(spacing))
    brick_half_diag = 0.5 * float(np.linalg.norm(spacing * (BRICK - 1)))
    margin = brick_half_diag + ramp + voxel_half_diag + 1e-3
    starts = [np.arange(start[d], stop[d], BRICK) for d in range(3)]
    centres = [np.minimum(s + (BRICK - 1) / 2, (np.minimum(s + BRICK, stop[d]) + s - 1) / 2)
               for d, s in enumerate(starts)]
    ci, cj, ck = np.meshgrid(*centres, indexing="ij")
    pts = np.stack([ci.ravel(), cj.ravel(), ck.ravel()], axis=1) @ a.T + b
    bound = layer.shape.bound(*(pts[:, d].astype(F32) for d in range(3))).reshape(ci.shape)
    hu = F32(layer.hu)
    for n0 in range(len(starts[0])):
        for n1 in range(len(starts[1])):
            for n2 in range(len(starts[2])):
                d = bound[n0, n1, n2]
                if d > margin:
                    continue
                i0, j0, k0 = starts[0][n0], starts[1][n1], starts[2][n2]
                i1, j1, k1 = min(i0 + BRICK, stop[0]), min(j0 + BRICK, stop[1]), min(k0 + BRICK, stop[2])
                view = volume[k0:k1, j0:j1, i0:i1]
                if d < -margin:
                    if layer.over:
                        view[...] = hu
                    else:
                        view += hu - F32(AIR_HU)
                    continue
                fraction = _brick_fraction(layer, a, b, (i0, i1), (j0, j1), (k0, k1), ramp, voxel_half_diag)
                if fraction is not None:
                    view += fraction * ((hu - view) if layer.over else (hu - F32(AIR_HU)))


def _brick_fraction(layer: Layer, a: np.ndarray, b: np.ndarray, irange, jrange, krange, ramp: float,
                    voxel_half_diag: float) -> np.ndarray | None:
    ii = np.arange(*irange, dtype=F32)
    jj = np.arange(*jrange, dtype=F32)
    kk = np.arange(*krange, dtype=F32)
    a32 = a.astype(F32)
    coords = []
    for r in range(3):
        coords.append((F32(b[r]) + a32[r, 0] * ii)[None, None, :] + (a32[r, 1] * jj)[None, :, None]
                      + (a32[r, 2] * kk)[:, None, None])
    d = layer.shape.sdf(*coords)
    if layer.supersample <= 0:
        fraction = np.clip(F32(0.5) - d / F32(ramp), 0, 1)
        return fraction if np.any(fraction > 0) else None
    fraction = (d <= 0).astype(F32)
    near = np.abs(d) < voxel_half_diag * 1.05
    if np.any(near):
        fraction[near] = _supersample(layer, a, b, np.nonzero(near), (irange[0], jrange[0], krange[0]))
    return fraction if np.any(fraction > 0) else None


def _supersample(layer: Layer, a: np.ndarray, b: np.ndarray, near_kji, offset_ijk) -> np.ndarray:
    n = layer.supersample
    sub = (np.arange(n, dtype=F32) + F32(0.5)) / F32(n) - F32(0.5)
    si, sj, sk = np.meshgrid(sub, sub, sub, indexing="ij")
    sub_ijk = np.stack([si.ravel(), sj.ravel(), sk.ravel()], axis=1)  # (n^3, 3)
    k, j, i = near_kji
    centre = np.stack([i + offset_ijk[0], j + offset_ijk[1], k + offset_ijk[2]], axis=1).astype(F32)
    samples = centre[:, None, :] + sub_ijk[None, :, :]  # (m, n^3, 3)
    a32 = a.astype(F32)
    frame = samples @ a32.T + b.astype(F32)
    inside = layer.shape.inside(frame[..., 0], frame[..., 1], frame[..., 2])
    return inside.mean(axis=1, dtype=F32)


# --- point-spread function, noise, metal ---------------------------------------------------


def _kernel_energy(sigma_voxels: float, truncate: float = 4.0) -> float:
    """Sum of squared weights of scipy's discrete Gaussian kernel (noise variance gain)."""
    if sigma_voxels <= 1e-6:
        return 1.0
    radius = int(truncate * sigma_voxels + 0.5)
    x = np.arange(-radius, radius + 1)
    w = np.exp(-0.5 * (x / sigma_voxels) ** 2)
    w /= w.sum()
    return float(np.sum(w**2))


def psf_sigma_mm(spacing: np.ndarray, fwhm_mm: float) -> np.ndarray:
    """Gaussian PSF sigma per index axis (mm): ``fwhm_mm`` in-plane, at least the slice profile along k."""
    sigma = np.full(3, fwhm_mm / 2.3548)
    sigma[2] = max(sigma[2], float(spacing[2]) / 2.3548)
    return sigma


def blur_and_noise(volume: np.ndarray, grid: Grid, fwhm_mm: float, noise_hu: float,
                   rng: np.random.Generator) -> None:
    """Add white noise and blur in place with the PSF; the blurred noise has std ``noise_hu``."""
    sigma_vox = psf_sigma_mm(grid.spacing, fwhm_mm) / np.asarray(grid.spacing)
    gain = np.sqrt(np.prod([_kernel_energy(s) for s in sigma_vox]))
    white = F32(noise_hu / gain)
    for k0 in range(0, volume.shape[0], 8):  # slabs keep the temporary small
        slab = volume[k0:k0 + 8]
        slab += rng.standard_normal(slab.shape, dtype=F32) * white
    # volume is [k, j, i]; sigma per array axis
    ndimage.gaussian_filter(volume, sigma=(sigma_vox[2], sigma_vox[1], sigma_vox[0]), output=volume,
                            mode="nearest", truncate=4.0)


def add_metal_streaks(volume: np.ndarray, grid: Grid, centre_image: np.ndarray, half_extent_z_mm: float,
                      rng: np.random.Generator, radius_mm: float = 110.0, n_streaks: int = 9,
                      amplitude_hu: float = 700.0) -> None:
    """Bright and dark streaks through a metal object in the scanner's axial planes (constant LPS z).

    Each streak is a line through ``centre_image`` at a random angle, alternating in sign,
    fading as ``r0 / (r0 + r)`` with distance and vanishing at ``radius_mm``; the streaks
    exist in the slices the metal crosses (LPS z within ``half_extent_z_mm`` of the centre,
    with a soft edge).
    """
    centre = np.asarray(centre_image, dtype=float)
    z_reach = half_extent_z_mm + 4.0
    box = np.array([[centre[0] + sx * radius_mm, centre[1] + sy * radius_mm, centre[2] + sz * z_reach]
                    for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)])
    image_to_index = np.linalg.inv(grid.index_to_image)
    idx = box @ image_to_index[:3, :3].T + image_to_index[:3, 3]
    start = np.maximum(np.floor(idx.min(axis=0)).astype(int), 0)
    stop = np.minimum(np.ceil(idx.max(axis=0)).astype(int) + 1, np.asarray(grid.size))
    if np.any(stop <= start):
        return
    angles = np.sort(rng.uniform(0, np.pi, n_streaks))
    signs = np.where(np.arange(n_streaks) % 2 == 0, 1.0, -1.0)
    amplitudes = signs * amplitude_hu * rng.uniform(0.5, 1.0, n_streaks)
    widths = rng.uniform(0.5, 1.1, n_streaks)
    a = grid.index_to_image[:3, :3].astype(F32)
    b = (grid.index_to_image[:3, 3] - centre).astype(F32)
    r0 = F32(16.0)
    for k0 in range(start[2], stop[2], 4):
        k1 = min(k0 + 4, stop[2])
        ii = np.arange(start[0], stop[0], dtype=F32)
        jj = np.arange(start[1], stop[1], dtype=F32)
        kk = np.arange(k0, k1, dtype=F32)
        rel = [(b[r] + a[r, 0] * ii)[None, None, :] + (a[r, 1] * jj)[None, :, None] + (a[r, 2] * kk)[:, None, None]
               for r in range(3)]
        dz = np.maximum(np.abs(rel[2]) - F32(half_extent_z_mm), 0)
        weight_z = np.exp(-(dz * dz) / F32(2 * 1.5**2))
        radial = np.sqrt(rel[0] ** 2 + rel[1] ** 2)
        window = np.clip(1 - (radial / F32(radius_mm)) ** 2, 0, 1) ** 2 * r0 / (r0 + radial)
        streaks = np.zeros_like(radial)
        for angle, amp, width in zip(angles, amplitudes, widths, strict=True):
            perp = rel[0] * F32(np.sin(angle)) - rel[1] * F32(np.cos(angle))
            streaks += F32(amp) * np.exp(-(perp * perp) / F32(2 * width**2))
        volume[k0:k1, start[1]:stop[1], start[0]:stop[0]] += streaks * window * weight_z


def add_dark_streak(volume: np.ndarray, grid: Grid, point_image: np.ndarray, angle_rad: float, amplitude_hu: float,
                    half_extent_z_mm: float, width_mm: float = 1.0, length_mm: float = 60.0) -> None:
    """One streak through ``point_image`` in the axial planes (constant LPS z), at ``angle_rad`` from +x.

    Gaussian across the line (``width_mm`` sigma), ``amplitude_hu`` on it (negative: dark),
    fading to nothing ``length_mm / 2`` along the line from the point and outside the slices
    within ``half_extent_z_mm`` of it (soft edge, 0.5 mm).
    """
    centre = np.asarray(point_image, dtype=float)
    reach = np.array([length_mm / 2, length_mm / 2, half_extent_z_mm + 2.0])
    corners = np.array([[centre[0] + sx * reach[0], centre[1] + sy * reach[1], centre[2] + sz * reach[2]]
                        for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)])
    image_to_index = np.linalg.inv(grid.index_to_image)
    idx = corners @ image_to_index[:3, :3].T + image_to_index[:3, 3]
    start = np.maximum(np.floor(idx.min(axis=0)).astype(int), 0)
    stop = np.minimum(np.ceil(idx.max(axis=0)).astype(int) + 1, np.asarray(grid.size))
    if np.any(stop <= start):
        return
    ii, jj, kk = (np.arange(a, b, dtype=F32) for a, b in zip(start, stop, strict=True))
    a = grid.index_to_image[:3, :3].astype(F32)
    b = (grid.index_to_image[:3, 3] - centre).astype(F32)
    rel = [(b[r] + a[r, 0] * ii)[None, None, :] + (a[r, 1] * jj)[None, :, None] + (a[r, 2] * kk)[:, None, None]
           for r in range(3)]
    along = rel[0] * F32(np.cos(angle_rad)) + rel[1] * F32(np.sin(angle_rad))
    across = -rel[0] * F32(np.sin(angle_rad)) + rel[1] * F32(np.cos(angle_rad))
    dz = np.maximum(np.abs(rel[2]) - F32(half_extent_z_mm), 0)
    weight = np.exp(-(dz * dz) / F32(2 * 0.5**2)) * np.clip(1 - (2 * along / F32(length_mm)) ** 2, 0, 1)
    volume[start[2]:stop[2], start[1]:stop[1], start[0]:stop[0]] += \
        F32(amplitude_hu) * np.exp(-(across * across) / F32(2 * width_mm**2)) * weight


def to_int16(volume: np.ndarray) -> np.ndarray:
    """Clip to [-1024, 3071] and round to int16, slab by slab (no full-size temporary)."""
    out = np.empty(volume.shape, dtype=np.int16)
    for k0 in range(0, volume.shape[0], 16):
        slab = np.clip(volume[k0:k0 + 16], HU_MIN, HU_MAX)
        out[k0:k0 + 16] = np.rint(slab)
    return out


def to_sitk(array_kji: np.ndarray, grid: Grid) -> sitk.Image:
    image = sitk.GetImageFromArray(array_kji, isVector=False)
    image.SetSpacing([float(v) for v in grid.spacing])
    image.SetOrigin([float(v) for v in grid.origin])
    image.SetDirection([float(v) for v in np.asarray(grid.direction).ravel()])
    return image


def flip_to_right_handed(array_kji: np.ndarray, grid: Grid) -> tuple[np.ndarray, Grid]:
    """Same physical image, k axis reversed if the direction is left-handed (what a DICOM reader returns)."""
    if np.linalg.det(grid.direction) > 0:
        return array_kji, grid
    direction = np.array(grid.direction, dtype=float)
    origin = grid.index_to_image @ np.array([0, 0, grid.size[2] - 1, 1.0])
    direction[:, 2] *= -1
    return array_kji[::-1], Grid(grid.size, grid.spacing, origin[:3], direction)


# --- writing -----------------------------------------------------------------------------------


def write_nrrd(image: sitk.Image, path: Path) -> None:
    """Write a compressed NRRD atomically (fast zlib level)."""
    with atomic_path(path) as tmp, itk_write_errors():
        sitk.WriteImage(image, str(tmp), True, 1)


def write_dicom_series(image: sitk.Image, folder: Path, seed: int, description: str = "EMReg simulated CT",
                       progress: Progress | None = None) -> None:
    """Write a 3D int16 image as a CT DICOM series (one file per k slice) into ``folder`` atomically.

    The image's direction must be right-handed (DICOM's slice normal is row x column).
    Tags: Image Position / Orientation (Patient), Pixel Spacing, Slice Thickness, Spacing
    Between Slices, Rescale Intercept / Slope (pixels stored as HU + 1024, intercept -1024),
    one Study and Series Instance UID. The folder appears complete or not at all.
    """
    progress = progress or QUIET
    direction = np.asarray(image.GetDirection()).reshape(3, 3)
    if np.linalg.det(direction) < 0:
        raise ValueError("DICOM series need a right-handed direction; flip the slice axis first")
    folder = Path(folder)
    try:
        folder.parent.mkdir(parents=True, exist_ok=True)
        tmp = Path(tempfile.mkdtemp(prefix=f".{folder.name}-", dir=folder.parent))
    except OSError as exc:
        raise cannot_write(folder, exc) from None
    try:
        with itk_write_errors():  # a full disk: one line naming the folder, not GDCM's RuntimeError
            _write_slices(image, tmp, seed, description, progress)
        old = None
        if folder.exists():
            old = Path(tempfile.mkdtemp(prefix=f".{folder.name}-old-", dir=folder.parent))
            os.replace(folder, old / folder.name)
        os.replace(tmp, folder)
        if old is not None:
            shutil.rmtree(old, ignore_errors=True)
    except OSError as exc:
        shutil.rmtree(tmp, ignore_errors=True)
        raise cannot_write(folder, exc) from None
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise


def _uid(seed: int, kind: int) -> str:
    return f"1.2.826.0.1.3680043.8.498.{int(time.time())}.{seed % 100000}.{kind}"


def _write_slices(image: sitk.Image, folder: Path, seed: int, description: str, progress: Progress) -> None:
    direction = np.asarray(image.GetDirection()).reshape(3, 3)
    spacing = image.GetSpacing()
    stored = sitk.Cast(image, sitk.sitkInt16)  # the writer stores HU + 1024 (intercept -1024)
    study_uid, series_uid, frame_uid = _uid(seed, 1), _uid(seed, 2), _uid(seed, 3)
    date, clock = time.strftime("%Y%m%d"), time.strftime("%H%M%S")
    iop = "\\".join(f"{v:.10g}" for v in (*direction[:, 0], *direction[:, 1]))
    common = {
        "0008|0008": "DERIVED\\SECONDARY\\AXIAL", "0008|0016": "1.2.840.10008.5.1.4.1.1.2",
        "0008|0020": date, "0008|0021": date, "0008|0030": clock, "0008|0031": clock,
        "0008|0060": "CT", "0008|0070": "EMReg simulator", "0008|103e": description,
        "0010|0010": "EMReg^Phantom", "0010|0020": f"EMREG-SIM-{seed}", "0018|0050": f"{spacing[2]:.6g}",
        "0018|0088": f"{spacing[2]:.6g}", "0018|0060": "120", "0020|000d": study_uid, "0020|000e": series_uid,
        "0020|0052": frame_uid, "0020|0011": "1", "0020|0037": iop, "0028|1052": "-1024", "0028|1053": "1",
        "0028|1054": "HU", "0028|1050": "40", "0028|1051": "400",
    }
    writer = sitk.ImageFileWriter()
    writer.KeepOriginalImageUIDOn()
    n = image.GetSize()[2]
    with progress.step("write DICOM series", total=n) as step:
        for k in range(n):
            slice_k = stored[:, :, k]
            for tag, value in common.items():
                slice_k.SetMetaData(tag, value)
            position = image.TransformIndexToPhysicalPoint((0, 0, k))
            slice_k.SetMetaData("0020|0032", "\\".join(f"{v:.6f}" for v in position))
            slice_k.SetMetaData("0020|0013", str(k + 1))
            slice_k.SetMetaData("0020|1041", f"{float(np.dot(position, direction[:, 2])):.6f}")
            slice_k.SetMetaData("0008|0018", f"{series_uid}.{k + 1}")
            writer.SetFileName(str(folder / f"CT{k + 1:05d}.dcm"))
            writer.Execute(slice_k)
            step.advance()
