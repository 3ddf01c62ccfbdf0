"""The checks every CT reader applies before EMReg uses an image (one place for all readers).

- :func:`check_ct_path` and :func:`check_ct_file`, before any read: the path exists and is no symbolic-link
  loop; a ``.nii`` / ``.nii.gz`` carries NIfTI's magic (:func:`~.nifti_header.check_nifti_magic`: ITK reads a
  damaged one as Analyze 7.5 and drops the file's geometry).
- :func:`~EMRegModule.core.ct.check_ct_geometry` (in :mod:`EMRegModule.core.ct`, since detection applies it
  too to an image handed over): 3D, scalar, a finite, non-degenerate and orthonormal geometry.
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

import errno
import os
import re
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from ..core import pixel_types
from ..core.ct import check_ct_geometry, check_origin, check_spacing
from ..errors import EMRegError
from .nifti_header import check_nifti_magic, check_nifti_placement, is_nifti

if TYPE_CHECKING:
    import SimpleITK as sitk


def check_ct_path(path: str | os.PathLike[str]) -> None:
    """Refuse a CT path that does not exist, naming a symbolic-link loop or a broken link as such."""
    path = Path(path)
    try:
        path.stat()
    except OSError as exc:
        if path.is_symlink():
            what = "a symbolic-link loop" if exc.errno == errno.ELOOP else "a broken symbolic link"
            raise EMRegError(f"{path}: CT path is {what}; give the CT file or DICOM folder itself") from None
        raise EMRegError(f"{path}: CT not found") from None


def check_ct_file(path: str | os.PathLike[str]) -> None:
    """Refuse, before reading it, a CT file that SimpleITK would read wrongly: a ``.nii`` / ``.nii.gz`` without
    NIfTI's magic (read as Analyze 7.5, its orientation and origin lost), a NRRD whose header's spacing or origin
    is damaged (:func:`_check_nrrd_geometry`)."""
    check_nifti_magic(path)
    _check_nrrd_geometry(path)


def _check_nrrd_geometry(path: str | os.PathLike[str]) -> None:
    """Refuse a NRRD whose header gives a spacing (the lengths of its ``space directions``, or its ``spacings``) or
    a ``space origin`` no CT has: ITK reads a ``space directions`` vector of length 1e300 as spacing 1 along the
    identity direction, silently (a plausible, wrong geometry)."""
    from .ct_header import nrrd_header_fields

    fields = nrrd_header_fields(Path(path)) or {}
    vectors = [_numbers(text) for text in re.findall(r"\(([^)]*)\)", fields.get("space directions", ""))]
    spacing = [float(np.hypot.reduce(v)) if np.all(np.isfinite(v)) else float("nan") for v in vectors if v.size]
    spacing += [v for v in _numbers(fields.get("spacings", "")).tolist() if not np.isnan(v)]
    if spacing:
        check_spacing(np.asarray(spacing), path)
    origin = re.findall(r"\(([^)]*)\)", fields.get("space origin", ""))
    if origin:
        check_origin(_numbers(origin[0]), path)


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
    if is_nifti(path):
        check_nifti_placement(geometry, path)
    _check_space_units(path)


def _check_space_units(path: str | os.PathLike[str]) -> None:
    """Refuse a NRRD whose ``space units`` are not millimetres: SimpleITK (EMReg's reader) and 3D Slicer ignore
    the field and read the numbers as mm, so a CT in cm would come out 10 times too small (its markers not
    found, or found at the wrong size) instead of being said wrong."""
    if not Path(path).name.lower().endswith((".nrrd", ".nhdr")):
        return  # no NRRD header (nrrd_header_fields reads none): a DICOM folder, another format
    from .ct_header import nrrd_header_fields

    units = (nrrd_header_fields(Path(path)) or {}).get("space units")
    named = [u.strip() for u in re.findall(r'"([^"]*)"', units or "")]
    if any(u.lower() not in ("", "mm") for u in named):
        raise EMRegError(f"{path}: CT space units {' '.join(named)}: EMReg reads CT geometry in millimetres (as "
                         "SimpleITK and 3D Slicer do, whatever the field says); save the CT with spacing and origin "
                         "in mm")


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
