"""The checks every CT reader applies before EMReg uses an image (one place for all readers).

- :func:`check_ct_path` and :func:`check_ct_file`, before any read: the path exists and is no symbolic-link
  loop; a ``.nii`` / ``.nii.gz`` carries NIfTI's magic (:func:`~.nifti_header.check_nifti_magic`: ITK reads a
  damaged one as Analyze 7.5 and drops the file's geometry).
- :func:`check_ct_geometry`: 3D, scalar, a supported pixel type, a non-degenerate size, a finite spacing
  within ``SPACING_RANGE_MM``, a finite origin within ``ORIGIN_LIMIT_MM``, and **orthonormal direction
  cosines**. A sheared direction matrix (non-orthogonal ``space directions`` / ``ImageOrientationPatient``
  columns) has no exact meaning for SimpleITK, which normalises the columns and keeps the shear: voxels
  would land up to millimetres away from where the scanner put them, so such images are refused
  (``ORTHONORMAL_TOLERANCE``).
- :func:`check_ct_voxels`: every voxel value finite. NaN or +-inf voxels (a NaN slab, sprinkled
  non-finite values) make the band-pass segmentation silently wrong; the image is refused with the
  number of non-finite voxels.
- :func:`check_ct_image` = both, for an image read in full (SimpleITK, a DICOM series, a volume
  handed over by 3D Slicer). The streaming fast path (:mod:`.fast_read`) checks the geometry before
  reading and counts non-finite voxels slice by slice as they arrive (:class:`NonFiniteCounter`).

The length of the voxel data against the header's ``sizes`` is checked by the readers themselves
(:func:`EMRegModule.io.ct_header.check_data_length`), since only they see the bytes.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from ..errors import EMRegError
from . import pixel_types

if TYPE_CHECKING:
    import SimpleITK as sitk

#: Largest |D^T D - I| entry accepted for the direction cosines D (about 0.006 degrees of shear:
#: 0.03 mm over a 300 mm field; DICOM direction cosines written with 6 digits stay well inside).
ORTHONORMAL_TOLERANCE = 1e-4

#: Voxel spacings (mm) a CT may have. Far wider than any scanner's (a CT in metres, 0.0005, still passes and
#: is named as such by detection), narrow enough that the geometry's arithmetic (voxel volumes, cross
#: products of the axes) stays finite and non-zero: a header's ``1e300`` or ``1e-300`` is refused here.
SPACING_RANGE_MM = (1e-6, 1e4)

#: Largest |coordinate| (mm) of a CT's origin: a kilometre, where a scanner's are within a metre or two.
ORIGIN_LIMIT_MM = 1e6


def check_ct_path(path: str | os.PathLike[str]) -> None:
    """Refuse a CT path that does not exist, naming a symbolic-link loop or a broken link as such."""
    path = Path(path)
    try:
        path.stat()
    except OSError as exc:
        if path.is_symlink():
            import errno

            what = "a symbolic-link loop" if exc.errno == errno.ELOOP else "a broken symbolic link"
            raise EMRegError(f"{path}: CT path is {what}; give the CT file or DICOM folder itself") from None
        raise EMRegError(f"{path}: CT not found") from None


def check_ct_file(path: str | os.PathLike[str]) -> None:
    """Refuse, before reading it, a CT file that SimpleITK would read wrongly: a ``.nii`` / ``.nii.gz`` without
    NIfTI's magic (read as Analyze 7.5, its orientation and origin lost), a NRRD whose header's spacing or origin
    is damaged (:func:`_check_nrrd_geometry`)."""
    from .nifti_header import check_nifti_magic

    check_nifti_magic(path)
    _check_nrrd_geometry(path)


def _check_nrrd_geometry(path: str | os.PathLike[str]) -> None:
    """Refuse a NRRD whose header gives a spacing (the lengths of its ``space directions``, or its ``spacings``) or
    a ``space origin`` no CT has: ITK reads a ``space directions`` vector of length 1e300 as spacing 1 along the
    identity direction, silently (a plausible, wrong geometry)."""
    import re

    from .ct_header import nrrd_header_fields

    fields = nrrd_header_fields(Path(path)) or {}
    vectors = [_numbers(text) for text in re.findall(r"\(([^)]*)\)", fields.get("space directions", ""))]
    spacing = [float(np.hypot.reduce(v)) if np.all(np.isfinite(v)) else float("nan") for v in vectors if v.size]
    spacing += [v for v in _numbers(fields.get("spacings", "")).tolist() if not np.isnan(v)]
    if spacing:
        _check_spacing(np.asarray(spacing), path)
    origin = re.findall(r"\(([^)]*)\)", fields.get("space origin", ""))
    if origin:
        _check_origin(_numbers(origin[0]), path)


def _numbers(text: str) -> np.ndarray:
    """The numbers of a NRRD field's text (``nan`` for a word that is none: NRRD's ``none`` / ``nan`` axes)."""
    values = []
    for word in text.replace(",", " ").split():
        try:
            values.append(float(word))
        except ValueError:
            values.append(float("nan"))
    return np.asarray(values, dtype=float)


def check_file_placement(geometry: sitk.Image, path: str | os.PathLike[str]) -> None:
    """Refuse a CT file whose header places its voxels where SimpleITK (EMReg's reader) and other tools disagree:
    a NIfTI whose sform and qform differ (:mod:`.nifti_header`), an NRRD not in millimetres. ``geometry``: the
    image, or its header reading."""
    from .nifti_header import check_nifti_placement, is_nifti

    if is_nifti(path):
        check_nifti_placement(geometry, path)
    _check_space_units(path)


def _check_space_units(path: str | os.PathLike[str]) -> None:
    """Refuse a NRRD whose ``space units`` are not millimetres: SimpleITK (EMReg's reader) and 3D Slicer ignore
    the field and read the numbers as mm, so a CT in cm would come out 10 times too small (its markers not
    found, or found at the wrong size) instead of being said wrong."""
    if not Path(path).name.lower().endswith((".nrrd", ".nhdr")):
        return  # no NRRD header (nrrd_header_fields reads none): a DICOM folder, another format
    import re

    from .ct_header import nrrd_header_fields

    units = (nrrd_header_fields(Path(path)) or {}).get("space units")
    named = [u.strip() for u in re.findall(r'"([^"]*)"', units or "")]
    if any(u.lower() not in ("", "mm") for u in named):
        raise EMRegError(f"{path}: CT space units {' '.join(named)}: EMReg reads CT geometry in millimetres (as "
                         "SimpleITK and 3D Slicer do, whatever the field says); save the CT with spacing and origin "
                         "in mm")


def check_ct_geometry(image: sitk.Image, source: str | os.PathLike[str] = "CT") -> None:
    """Refuse a CT EMReg cannot place exactly: not 3D, not scalar, degenerate, or sheared directions."""
    if image.GetDimension() != 3:
        raise EMRegError(f"{source}: CT must be a 3D volume, got a {image.GetDimension()}D image")
    if image.GetNumberOfComponentsPerPixel() != 1 or image.GetPixelID() not in pixel_types.SCALAR:
        raise EMRegError(
            f"{source}: CT must hold scalar intensities (HU), got pixel type {image.GetPixelIDTypeAsString()}"
        )
    if min(image.GetSize()) < 2:
        raise EMRegError(f"{source}: CT has a degenerate size {image.GetSize()}")
    _check_spacing(np.asarray(image.GetSpacing(), dtype=float), source)
    _check_origin(np.asarray(image.GetOrigin(), dtype=float), source)
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


def _check_spacing(spacing: np.ndarray, source: str | os.PathLike[str]) -> None:
    """Refuse voxel spacings (mm) that are not finite, not positive or outside :data:`SPACING_RANGE_MM`."""
    if not np.all(np.isfinite(spacing)) or np.min(spacing) <= 0:
        raise EMRegError(f"{source}: CT has a non-positive or non-finite spacing {tuple(spacing.tolist())}")
    low, high = SPACING_RANGE_MM
    if np.min(spacing) < low or np.max(spacing) > high:
        raise EMRegError(f"{source}: CT spacing {tuple(float(f'{v:.6g}') for v in spacing)} mm is outside "
                         f"{low:g}..{high:g} mm, no CT's voxel size: the header's spacing is damaged")


def _check_origin(origin: np.ndarray, source: str | os.PathLike[str]) -> None:
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


class NonFiniteCounter:
    """Counts NaN / +-inf values over chunks of voxels (a bounded temporary per chunk)."""

    def __init__(self) -> None:
        self.count = 0
        self.total = 0

    def add(self, voxels: np.ndarray) -> int:
        """Count the non-finite values of ``voxels`` (any shape); returns the count of this chunk."""
        flat = voxels.reshape(-1)
        found = 0
        step = 1 << 22
        for start in range(0, len(flat), step):
            found += int(flat.size and np.count_nonzero(~np.isfinite(flat[start:start + step])))
        self.count += found
        self.total += flat.size
        return found

    def check(self, source: str | os.PathLike[str]) -> None:
        """Raise the one-line refusal when any non-finite value was counted."""
        if self.count:
            raise EMRegError(
                f"{source}: CT holds {self.count} non-finite voxel value(s) (NaN or +-inf) of {self.total}; "
                "EMReg cannot segment markers in it: export the CT again or replace them (e.g. with the "
                "air value) explicitly"
            )


def check_ct_voxels(image: sitk.Image, source: str | os.PathLike[str] = "CT") -> None:
    """Refuse a CT holding NaN or +-inf voxels, naming how many (integer images cannot hold any)."""
    if image.GetPixelID() not in pixel_types.FLOATS:
        return
    import SimpleITK as sitk

    counter = NonFiniteCounter()
    counter.add(sitk.GetArrayViewFromImage(image))
    counter.check(source)


def check_ct_image(image: sitk.Image, source: str | os.PathLike[str] = "CT") -> None:
    """Every check of this module on an image read in full (geometry, then voxel values)."""
    check_ct_geometry(image, source)
    check_ct_voxels(image, source)
