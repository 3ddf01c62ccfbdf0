"""The CT as the algorithms see it: its geometry, the checks of that geometry, and its slices as they arrive.

A CT's geometry is what SimpleITK's getters answer (:class:`ImageGeometry`): a ``SimpleITK.Image``, a header
reading, or :class:`~EMRegModule.io.ct_handle.CTGeometry` (the voxels still to come). Size (i, j, k) in voxels,
spacing in mm, origin in LPS mm, direction cosines (row-major 3 x 3, its columns the i, j, k axes in LPS).

- :func:`check_ct_geometry`: 3D, scalar, a supported pixel type (:mod:`.pixel_types`), a non-degenerate size, a
  finite spacing within ``SPACING_RANGE_MM``, a finite origin within ``ORIGIN_LIMIT_MM``, and **orthonormal
  direction cosines**. A sheared direction matrix (non-orthogonal ``space directions`` / ``ImageOrientationPatient``
  columns) has no exact meaning for SimpleITK, which normalises the columns and keeps the shear: voxels would land
  up to millimetres away from where the scanner put them, so such images are refused (``ORTHONORMAL_TOLERANCE``).
  Every CT reader applies it (:mod:`EMRegModule.io.ct_checks`), and so does detection on an image handed over.
- :func:`index_to_physical_matrix` and :func:`image_geometry`: the voxel index to LPS mm, and the geometry block of
  ``markers.json``.
- :class:`StreamedCT`: a CT whose slices arrive while it is read (what :mod:`EMRegModule.io.ct_handle` hands out),
  which detection follows slice block by slice block.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from typing import Any, Protocol, runtime_checkable

import numpy as np

from ..errors import EMRegError
from . import pixel_types

#: Largest |D^T D - I| entry accepted for the direction cosines D (about 0.006 degrees of shear:
#: 0.03 mm over a 300 mm field; DICOM direction cosines written with 6 digits stay well inside).
ORTHONORMAL_TOLERANCE = 1e-4

#: Voxel spacings (mm) a CT may have. Far wider than any scanner's (a CT in metres, 0.0005, still passes and
#: is named as such by detection), narrow enough that the geometry's arithmetic (voxel volumes, cross
#: products of the axes) stays finite and non-zero: a header's ``1e300`` or ``1e-300`` is refused here.
SPACING_RANGE_MM = (1e-6, 1e4)

#: Largest |coordinate| (mm) of a CT's origin: a kilometre, where a scanner's are within a metre or two.
ORIGIN_LIMIT_MM = 1e6


class ImageGeometry(Protocol):
    """A CT's geometry by SimpleITK's getters (``SimpleITK.Image`` has them, and so has a geometry without voxels)."""

    def GetSize(self) -> Sequence[int]: ...  # noqa: N802

    def GetSpacing(self) -> Sequence[float]: ...  # noqa: N802

    def GetOrigin(self) -> Sequence[float]: ...  # noqa: N802

    def GetDirection(self) -> Sequence[float]: ...  # noqa: N802

    def GetPixelID(self) -> int: ...  # noqa: N802

    def GetDimension(self) -> int: ...  # noqa: N802

    def GetNumberOfComponentsPerPixel(self) -> int: ...  # noqa: N802

    def GetPixelIDTypeAsString(self) -> str: ...  # noqa: N802


@runtime_checkable
class StreamedCT(Protocol):
    """A CT whose slices may still be arriving: ``image`` its geometry (or the image holding the voxels),
    ``array`` the voxels (numpy order k, j, i; slices ``0 .. n-1`` valid once ``wait_for_slices(n)`` returned),
    ``shared`` whether a process forked now sees the voxels as they are written."""

    @property
    def image(self) -> ImageGeometry: ...

    @property
    def array(self) -> np.ndarray | None: ...

    @property
    def shared(self) -> bool: ...

    def wait_for_slices(self, stop: int) -> None: ...


def check_ct_geometry(image: ImageGeometry, source: str | os.PathLike[str] = "CT") -> None:
    """Refuse a CT EMReg cannot place exactly: not 3D, not scalar, degenerate, or sheared directions."""
    if image.GetDimension() != 3:
        raise EMRegError(f"{source}: CT must be a 3D volume, got a {image.GetDimension()}D image")
    if image.GetNumberOfComponentsPerPixel() != 1 or image.GetPixelID() not in pixel_types.SCALAR:
        raise EMRegError(
            f"{source}: CT must hold scalar intensities (HU), got pixel type {image.GetPixelIDTypeAsString()}"
        )
    if min(image.GetSize()) < 2:
        raise EMRegError(f"{source}: CT has a degenerate size {image.GetSize()}")
    check_spacing(np.asarray(image.GetSpacing(), dtype=float), source)
    check_origin(np.asarray(image.GetOrigin(), dtype=float), source)
    direction = np.asarray(image.GetDirection(), dtype=float).reshape(3, 3)
    if not np.all(np.isfinite(direction)):
        raise EMRegError(f"{source}: CT has non-finite direction cosines")
    deviation = float(np.max(np.abs(direction.T @ direction - np.eye(3))))
    if deviation > ORTHONORMAL_TOLERANCE:
        angles = _axis_angles_deg(direction)
        raise EMRegError(
            f"{source}: CT direction cosines are not orthogonal (axes at {angles} degrees; sheared or "
            f"gantry-tilted geometry): resample it onto an orthogonal grid first (e.g. Slicer's "
            f"'Harden transform' / 'Resample Scalar Volume')"
        )


def check_spacing(spacing: np.ndarray, source: str | os.PathLike[str]) -> None:
    """Refuse voxel spacings (mm) that are not finite, not positive or outside :data:`SPACING_RANGE_MM`."""
    if not np.all(np.isfinite(spacing)) or np.min(spacing) <= 0:
        raise EMRegError(f"{source}: CT has a non-positive or non-finite spacing {tuple(spacing.tolist())}")
    low, high = SPACING_RANGE_MM
    if np.min(spacing) < low or np.max(spacing) > high:
        raise EMRegError(f"{source}: CT spacing {tuple(float(f'{v:.6g}') for v in spacing)} mm is outside "
                         f"{low:g}..{high:g} mm, no CT's voxel size: the header's spacing is damaged")


def check_origin(origin: np.ndarray, source: str | os.PathLike[str]) -> None:
    """Refuse an origin (LPS mm) that is not finite or lies beyond :data:`ORIGIN_LIMIT_MM`."""
    if not np.all(np.isfinite(origin)):
        raise EMRegError(f"{source}: CT has a non-finite origin {tuple(origin.tolist())}")
    if np.max(np.abs(origin)) > ORIGIN_LIMIT_MM:
        raise EMRegError(f"{source}: CT origin {tuple(float(f'{v:.6g}') for v in origin)} mm lies more "
                         f"than {ORIGIN_LIMIT_MM:g} mm from the scanner's origin: the header's origin is damaged")


def _axis_angles_deg(direction: np.ndarray) -> str:
    unit = direction / np.linalg.norm(direction, axis=0, keepdims=True)
    pairs = ((0, 1), (0, 2), (1, 2))
    return "/".join(f"{np.degrees(np.arccos(np.clip(unit[:, i] @ unit[:, j], -1, 1))):.2f}" for i, j in pairs)


def image_geometry(image: ImageGeometry) -> dict[str, Any]:
    """The geometry block of ``markers.json``: size, spacing, origin, direction (9 numbers)."""
    return {
        "size": list(image.GetSize()),
        "spacing": list(image.GetSpacing()),
        "origin": list(image.GetOrigin()),
        "direction": list(image.GetDirection()),
    }


def index_to_physical_matrix(image: ImageGeometry) -> np.ndarray:
    """4x4 ``IndexToImage``: continuous (i, j, k) index -> LPS physical point (mm)."""
    direction = np.asarray(image.GetDirection(), dtype=float).reshape(3, 3)
    spacing = np.asarray(image.GetSpacing(), dtype=float)
    index_to_image = np.eye(4)
    index_to_image[:3, :3] = direction * spacing[None, :]
    index_to_image[:3, 3] = image.GetOrigin()
    return index_to_image
