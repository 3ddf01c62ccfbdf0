"""NIfTI-1 files (``.nii``, ``.nii.gz``, ``.hdr`` + ``.img``) whose two placements of the voxels (sform and
qform) disagree, refused before use.

A NIfTI-1 header can place the voxel grid twice: the ``sform`` (a 3x4 matrix, ``sform_code`` > 0) and the
``qform`` (a quaternion, pixdim and an offset, ``qform_code`` > 0), both from voxel index (i, j, k) to RAS
millimetres. Readers differ on which one counts when both are set: FSL and nibabel take the sform whenever
``sform_code`` > 0; ITK (hence SimpleITK, EMReg's reader, and 3D Slicer) takes the sform only when its
code is 1 (scanner) or the qform is unset, and only when the sform is a rotation times the voxel sizes,
otherwise the qform. When the two disagree, the markers would then be found where one convention puts them
and not the other: such a file is refused with one line that says what to do (make them agree).

Frames: NIfTI's RAS millimetres (the header); EMReg's LPS millimetres = diag(-1, -1, 1) RAS (SimpleITK's).
"""

from __future__ import annotations

import gzip
import os
import struct
from pathlib import Path

import numpy as np

from ..core.frames import LPS_TO_RAS_3X3
from ..errors import EMRegError

#: Largest distance (mm) between where the sform and SimpleITK's geometry put a corner voxel of the grid
#: that still counts as agreement (the float32 rounding of either is far below it; a voxel is >= 0.2 mm).
PLACEMENT_TOLERANCE_MM = 0.05

_UNIT_MM = {1: 1000.0, 2: 1.0, 3: 0.001}  # xyzt_units' space unit (metre, mm, micron) in mm, as ITK scales it


_NAMES = (".nii", ".nii.gz", ".hdr", ".hdr.gz", ".img", ".img.gz")


def is_nifti(path: str | os.PathLike[str]) -> bool:
    """True for a NIfTI-1 file name: ``.nii``, ``.nii.gz``, or either file of a ``.hdr`` / ``.img`` pair
    (also Analyze 7.5's names: such a header has no NIfTI magic and passes)."""
    return Path(path).name.lower().endswith(_NAMES)


def _header_file(path: Path) -> Path | None:
    """The file holding the 348-byte header: ``path`` itself, or the ``.hdr`` beside an ``.img``."""
    name = path.name.lower()
    for suffix in (".img", ".img.gz"):
        if name.endswith(suffix):
            stem = path.name[:-len(suffix)]
            return next((h for h in (path.with_name(stem + e) for e in (".hdr", ".hdr.gz", ".HDR")) if h.is_file()),
                        None)
    return path


def _head(path: Path, size: int) -> bytes | None:
    """The first ``size`` bytes of ``path`` (inflated when it is gzip), or None when it cannot be read."""
    try:
        with open(path, "rb") as stream:
            start = stream.read(2)
            stream.seek(0)
            return gzip.GzipFile(fileobj=stream).read(size) if start == b"\x1f\x8b" else stream.read(size)
    except (OSError, EOFError, gzip.BadGzipFile):
        return None


def check_nifti_magic(path: str | os.PathLike[str]) -> None:
    """Refuse a ``.nii`` / ``.nii.gz`` whose header is not NIfTI's: NIfTI-1 (``sizeof_hdr`` 348, magic ``n+1`` or
    ``ni1`` at byte 344) or NIfTI-2 (540, ``n+2`` or ``ni2`` at byte 4), in either byte order.

    ITK reads a single-file NIfTI whose magic is damaged as an Analyze 7.5 header: no qform nor sform, so the
    orientation and origin are dropped (identity direction, origin 0) and the markers come out hundreds of
    millimetres from where the file puts them. A ``.hdr`` / ``.img`` pair may be Analyze and is not checked.
    """
    path = Path(path)
    if not path.name.lower().endswith((".nii", ".nii.gz")):
        return
    head = _head(path, 348)
    if head is None:
        return  # unreadable: the read says why
    sizes = {struct.unpack_from(o + "i", head, 0)[0] for o in "<>"} if len(head) >= 4 else set()
    if 348 in sizes and len(head) >= 348 and head[344:348] in (b"n+1\0", b"ni1\0"):
        return
    if 540 in sizes and head[4:8] in (b"n+2\0", b"ni2\0"):
        return
    if 348 in sizes and len(head) < 348:
        raise EMRegError(f"{path}: cannot read CT (its NIfTI header is truncated: {len(head)} of 348 bytes)")
    if 348 in sizes:
        found = head[344:348]
        raise EMRegError(f"{path}: not a valid NIfTI file (its magic is {bytes(found)!r}, not 'n+1'): ITK would read "
                         "it as an Analyze 7.5 header and drop its orientation and origin; export the CT again")
    raise EMRegError(f"{path}: not a NIfTI file (no NIfTI-1 or NIfTI-2 header: the file is damaged or not NIfTI); "
                     "export the CT again")


def nifti_sform_lps(path: str | os.PathLike[str]) -> tuple[np.ndarray, int, int] | None:
    """The sform of a NIfTI-1 file as a 4x4 voxel index (i, j, k) -> LPS mm matrix (the header's space unit
    turned into mm, as ITK does), with the sform and qform codes; ``None`` when the file has no sform
    (``sform_code`` 0) or is not a readable NIfTI-1 header."""
    header = _header_file(Path(path))
    if header is None:
        return None
    head = _head(header, 348)
    if head is None or len(head) < 348 or head[344:348] not in (b"n+1\0", b"ni1\0"):
        return None  # not NIfTI-1 (Analyze 7.5 keeps other fields where the sform would be)
    order = next((o for o in "<>" if struct.unpack_from(o + "i", head, 0)[0] == 348), None)
    if order is None:
        return None  # NIfTI-2 (no such ambiguity handled here) or not NIfTI
    qform_code, sform_code = struct.unpack_from(order + "2h", head, 252)
    if sform_code <= 0:
        return None
    index_to_ras = np.asarray(struct.unpack_from(order + "12f", head, 280), dtype=float).reshape(3, 4)
    index_to_lps = np.eye(4)
    index_to_lps[:3, :] = LPS_TO_RAS_3X3 @ index_to_ras * _UNIT_MM.get(head[123] & 0x07, 1.0)
    return index_to_lps, int(sform_code), int(qform_code)


def check_nifti_placement(image, path: str | os.PathLike[str]) -> None:
    """Refuse a NIfTI file whose sform places the voxels elsewhere than ``image`` (SimpleITK's reading of it).

    ``image``: anything answering ``GetSize``, ``GetSpacing``, ``GetOrigin``, ``GetDirection`` (an image or a
    header reading). Files without a sform, or whose sform SimpleITK used, pass.
    """
    sform = nifti_sform_lps(path)
    if sform is None or image.GetDimension() != 3:
        return  # no sform, or an image refused as not 3D anyway
    index_to_lps, sform_code, qform_code = sform
    direction = np.asarray(image.GetDirection(), dtype=float).reshape(3, 3)
    read = np.eye(4)
    read[:3, :3] = direction * np.asarray(image.GetSpacing(), dtype=float)[None, :]
    read[:3, 3] = image.GetOrigin()
    last = np.asarray(image.GetSize()[:3], dtype=float) - 1
    corners = np.array([[i, j, k, 1.0] for i in (0, last[0]) for j in (0, last[1]) for k in (0, last[2])]).T
    distance = float(np.max(np.linalg.norm((index_to_lps @ corners - read @ corners)[:3], axis=0)))
    if not np.isfinite(distance) or distance > PLACEMENT_TOLERANCE_MM:
        raise EMRegError(
            f"{path}: cannot read CT (its NIfTI sform (code {sform_code}) and qform (code {qform_code}) place the "
            f"voxels up to {distance:.3g} mm apart, and readers differ on which counts: ITK and 3D Slicer use the "
            "qform here, FSL and nibabel the sform; make them agree, e.g. with fslorient -copysform2qform or "
            "-copyqform2sform)"
        )
