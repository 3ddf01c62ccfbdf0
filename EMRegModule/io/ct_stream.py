"""A CT read once, slice by slice, for work that needs each slice only for a while.

The report needs of the CT only a block-averaged copy (the 3D view's context surface) and small
planes around each marker, both made as the slices arrive. :func:`start_streamed_read` reads a
plain NRRD/MetaImage/NIfTI file (the layouts of :mod:`.fast_read`, integer voxels) on a thread into
an anonymous memory mapping that is only touched where voxels have arrived, and its user hands
slices back to the system once it is done with them (:meth:`~EMRegModule.io.ct_handle.CTHandle.release_before`):
the whole CT is never resident, so a report that reads its own CT needs a fraction of the CT's bytes. The voxels
are those of :func:`~EMRegModule.io.image.read_ct` (the same inflater and checks: truncated, corrupt or over-long
data is an error), and the file's sha256 comes out of the same pass (``sha256``), so that the report can check it
is the run's CT.

Frames: index space (k, j, i) of the CT (``array``); ``geometry`` gives its LPS physical space as SimpleITK does.
"""

from __future__ import annotations

import mmap
import threading
from pathlib import Path

from . import fast_read
from .ct_checks import check_ct_file, check_ct_geometry, check_file_placement
from .ct_handle import CTGeometry, CTHandle
from .provenance import Digest


def start_streamed_read(path: str | Path) -> CTHandle | None:
    """Start reading a CT file into anonymous memory (:meth:`CTHandle.in_anonymous_memory`: ``result()`` is None,
    the voxels are ``array``), or None when it is not a plain layout of integer voxels (then read it with
    :func:`~EMRegModule.io.image.open_ct`)."""
    path = Path(path)
    if not hasattr(mmap, "MADV_DONTNEED"):
        return None
    check_ct_file(path)
    plain = fast_read.plain_storage(path)
    if plain is None or plain[1].dtype.kind not in "iu":
        return None
    info, storage = plain
    geometry = CTGeometry.of(info)
    check_ct_geometry(geometry, path)  # 3D first: the placement check assumes it
    check_file_placement(geometry, path)
    ct = CTHandle.in_anonymous_memory(geometry, storage.dtype)
    ct.path = path.resolve()
    ct.sha256 = Digest()  # the file's, computed as it is read
    voxel_bytes = ct.array.reshape(-1).view("uint8")
    threading.Thread(target=fast_read.read_and_hash, args=(path, info, storage, voxel_bytes, ct),
                     name="emreg-ct-stream", daemon=True).start()  # into the mapping, every byte hashed
    return ct

