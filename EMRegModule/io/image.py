"""CT volume reading (NRRD / NIfTI / MHA / DICOM series) and image-geometry helpers.

Image space is the physical LPS space SimpleITK reports; origin, spacing and direction
cosines are kept as read.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import TYPE_CHECKING

from ..core.ct import check_ct_geometry
from ..errors import EMRegError
from .atomic import atomic_path, itk_write_errors
from .ct_checks import check_ct_file, check_ct_path, check_ct_voxels, check_file_placement
from .ct_handle import CTHandle
from .itk_messages import quiet_itk, read_failure
from .provenance import BackgroundHash, note_read_digest

if TYPE_CHECKING:  # SimpleITK is imported where an image is read or written: a DICOM series read into numpy
    import SimpleITK as sitk  # memory (emreg detect) needs none (its library takes 50 ms of CPU to load)


def read_ct(path: str | os.PathLike[str], series: str | int | None = None) -> sitk.Image:
    """Read a scalar 3D CT from a file or a DICOM folder (its best CT series, or ``series``: UID or number).

    Raises :class:`EMRegError` with a one-line message for a missing, empty, truncated
    or unreadable file, a non-scalar or non-3D image, or a folder without a usable CT series.
    """
    return open_ct(path, series).result()


def open_ct(path: str | os.PathLike[str], series: str | int | None = None, compact: bool = False,
            voxels_only: bool = False) -> CTHandle:
    """Start reading a CT as :func:`read_ct` does; the voxels may still be arriving when this returns.

    Plain NRRD, MetaImage and NIfTI files take the fast path of :mod:`.fast_read` (the same
    image as SimpleITK's, 1.2-1.4x faster on compressed scans), read slice by slice on a
    background thread; a DICOM folder is decoded slice by slice on a thread pool
    (:mod:`.dicom_series`, which also chooses the series: ``fill.series`` names it); anything
    else is read by SimpleITK before this returns: a :class:`~EMRegModule.io.ct_handle.CTHandle` in every case.
    The geometry is checked (:func:`~EMRegModule.core.ct.check_ct_geometry`) before returning; ``result()``
    raises the read's own errors. ``fill.sha256`` is the source's sha256 (provenance), computed from the bytes
    this read takes.
    ``compact``: a DICOM series whose headers call for int32 voxels is read as int16 (half the memory to fill)
    and ends with :class:`~EMRegModule.io.dicom_read.NarrowVoxelsError` if a slice does not fit it.
    ``voxels_only``: a DICOM series' integer voxels may come as ``fill.voxels`` (numpy, k, j, i, or for an
    uncompressed series a :class:`~EMRegModule.io.dicom_slices.DicomSliceStack` indexed like it, read from the
    files where it is indexed and hashed by a pass of its own) with ``fill.image`` only their geometry, for a
    caller that needs them only while it works on them (see ``open_dicom_series``).
    """
    path = Path(path)
    check_ct_path(path)
    try:
        if path.is_dir():
            from .dicom_read import open_dicom_series

            fill, _ = open_dicom_series(path, series, compact=compact, voxels_only=voxels_only)
        else:
            from .ct_header import check_data_length  # the file readers (ISA-L): not for a DICOM folder
            from .fast_read import start_fast_read

            if path.stat().st_size == 0:
                raise EMRegError(f"{path}: CT file is empty")
            check_ct_file(path)  # e.g. a damaged NIfTI magic, which ITK would read as Analyze (geometry lost)
            fill = start_fast_read(path)
            if fill is None:
                check_data_length(path)  # SimpleITK reads what the header asks for and ignores the rest
                digest = BackgroundHash(path)  # SimpleITK's read is a pass of its own: hash beside it
                fill = CTHandle.of_image(_read_with_simpleitk(path))
                fill.sha256 = digest
        if fill.sha256 is not None:
            note_read_digest(path, fill.sha256)  # the provenance's sha256 of the CT, from this read
        image = fill.image
    except RuntimeError as exc:
        raise EMRegError(f"{path}: cannot read CT ({read_failure(exc)})") from None
    try:
        check_ct_geometry(image, path)  # 3D first: the placement checks below assume it
        check_file_placement(image, path)  # e.g. a NIfTI's sform and qform that disagree: readers differ
        if fill.is_complete:
            check_ct_voxels(image, path)  # the voxel values of an image read in full
        # else: the fast path counts non-finite voxels as they arrive
    except EMRegError:
        fill.cancel()
        raise
    return fill


def _read_with_simpleitk(path: Path) -> sitk.Image:
    """``sitk.ReadImage``, ITK's own printing silenced; a failure is one line with the reason the reader gave."""
    import SimpleITK as sitk

    failure = None
    with quiet_itk(capture=True) as printed:
        try:
            return sitk.ReadImage(str(path))
        except RuntimeError as exc:
            failure = exc
    raise EMRegError(f"{path}: cannot read CT ({read_failure(failure, printed, path)})") from None


def write_image(image: sitk.Image, path: str | os.PathLike[str], compress: bool = True) -> None:
    """Write an image atomically (format by extension)."""
    import SimpleITK as sitk


    with atomic_path(path) as tmp, itk_write_errors():
        sitk.WriteImage(image, str(tmp), compress)
