"""A CT read once, slice by slice, for work that needs each slice only for a while.

The report needs of the CT only a block-averaged copy (the 3D view's context surface) and small
planes around each marker, both made as the slices arrive. :func:`start_streamed_read` reads a
plain NRRD/MetaImage/NIfTI file (the layouts of :mod:`.fast_read`, integer voxels) on a thread into
an anonymous memory mapping that is only touched where voxels have arrived, and its user hands
slices back to the system (``madvise(MADV_DONTNEED)``) once it is done with them
(:meth:`StreamedCT.release_before`): the whole CT is never resident, so a report that reads its
own CT needs a fraction of the CT's bytes. The voxels are those of :func:`~EMRegModule.io.image.read_ct`
(the same inflater and checks: truncated, corrupt or over-long data is an error), and the file's
sha256 comes out of the same pass (``sha256``), so that the report can check it is the run's CT.

Frames: index space (k, j, i) of the CT; ``geometry`` gives its LPS physical space as SimpleITK does.
"""

from __future__ import annotations

import mmap
import threading
from pathlib import Path
from typing import Any

import numpy as np
import SimpleITK as sitk

from ..provenance import Digest
from . import fast_read
from .fast_read import VolumeFill


class CTGeometry:
    """A CT's header reading (``sitk.ImageFileReader`` after ``ReadImageInformation``) answering as an image
    does for its geometry: size, spacing, origin, direction, dimension and pixel type."""

    def __init__(self, info: sitk.ImageFileReader) -> None:
        self._info = info

    def __getattr__(self, name: str):
        return getattr(self._info, name)

    def GetNumberOfComponentsPerPixel(self) -> int:  # noqa: N802 - SimpleITK's name
        return self._info.GetNumberOfComponents()

    def GetPixelIDTypeAsString(self) -> str:  # noqa: N802 - SimpleITK's name
        return sitk.GetPixelIDValueAsString(self._info.GetPixelID())


class ReleasedCT:
    """A CT that was used and let go: its geometry (``image``: size, spacing, origin, direction, pixel type)
    answers as a :class:`VolumeFill` does; ``result()`` is None (no voxels are kept)."""

    is_complete = True

    def __init__(self, image: sitk.Image) -> None:
        self.image = FixedGeometry.of_image(image)

    def result(self) -> None:
        return None

    def read_error(self) -> None:
        return None

    def cancel(self) -> None:
        return None


#: The getters of a ``SimpleITK.Image`` that its geometry answers.
GEOMETRY_GETTERS = ("GetSize", "GetSpacing", "GetOrigin", "GetDirection", "GetPixelID", "GetDimension",
                    "GetNumberOfComponentsPerPixel", "GetPixelIDTypeAsString")


class FixedGeometry:
    """An image's geometry, without its voxels: ``values`` by getter name (:data:`GEOMETRY_GETTERS`)."""

    def __init__(self, values: dict[str, Any]) -> None:
        self.values = values

    @classmethod
    def of_image(cls, image: Any) -> FixedGeometry:
        return cls({name: getattr(image, name)() for name in GEOMETRY_GETTERS})

    def __getattr__(self, name: str):
        try:
            value = self.values[name]
        except KeyError:
            raise AttributeError(name) from None
        return lambda: value


#: Transparent huge pages (2 MB) are asked for the streamed CT only when one of its slices spans at least one
#: (slices are given back a few at a time). Streamed read with the report's slice-by-slice release, median of 4-5
#: alternated runs on 2 cores: 0.32 mm (2.2 MB slices) 8.9 -> 8.3 s with huge pages (kernel 2.6 -> 1.7 s);
#: 0.6 mm (0.63 MB slices) 1.37 -> 1.72 s (kernel 0.33 -> 0.62 s, and from 1.2 to 2.1 s run to run).
_HUGE_PAGE_BYTES = 2 << 20


class StreamedCT(VolumeFill):
    """A :class:`VolumeFill` whose ``image`` is the CT's geometry (SimpleITK's header reading: size,
    spacing, origin, direction) and whose voxels are ``array`` (k, j, i), valid for the slices read and
    not yet released. ``result()`` waits for the read and returns None: no image is kept."""

    def __init__(self, info: sitk.ImageFileReader, dtype: np.dtype) -> None:
        super().__init__(info.GetSize()[2])
        size = info.GetSize()
        self.dtype = dtype
        self.slice_bytes = int(size[0]) * int(size[1]) * dtype.itemsize
        # private: given-back pages are freed (in a shared mapping they would stay in memory)
        self._mapping = mmap.mmap(-1, max(1, self.slice_bytes * self.slice_count), flags=mmap.MAP_PRIVATE)
        if hasattr(mmap, "MADV_HUGEPAGE") and self.slice_bytes >= _HUGE_PAGE_BYTES:
            self._mapping.madvise(mmap.MADV_HUGEPAGE)  # see _HUGE_PAGE_BYTES
        self.bytes = np.frombuffer(self._mapping, dtype=np.uint8, count=self.slice_bytes * self.slice_count)
        self.array = self.bytes.view(dtype.newbyteorder("=")).reshape(self.slice_count, size[1], size[0])
        self._released = 0
        self.path: Path | None = None  # the file read
        self._image = CTGeometry(info)  # the geometry, known before any voxel
        self.is_complete = False
        self.sha256 = Digest()  # the file's, computed as it is read

    def release_before(self, stop: int) -> None:
        """Give slices ``0 .. stop-1`` back to the system (reading them afterwards gives zeros)."""
        start = self._released
        stop = min(stop, self._ready)
        first, last = (start * self.slice_bytes) // mmap.PAGESIZE, (stop * self.slice_bytes) // mmap.PAGESIZE
        if last > first:
            self._mapping.madvise(mmap.MADV_DONTNEED, first * mmap.PAGESIZE, (last - first) * mmap.PAGESIZE)
        self._released = max(start, stop)

    def result(self) -> None:
        super().result()
        return None


def start_streamed_read(path: str | Path) -> StreamedCT | None:
    """Start reading a CT file as :class:`StreamedCT`, or None when it is not a plain layout of integer voxels
    (then read it with :func:`~EMRegModule.io.image.open_ct`)."""
    path = Path(path)
    if not hasattr(mmap, "MADV_DONTNEED"):
        return None
    from .ct_checks import check_ct_file, check_ct_geometry, check_file_placement

    check_ct_file(path)
    plain = fast_read.plain_storage(path)
    if plain is None or plain[1].dtype.kind not in "iu":
        return None
    info, storage = plain
    check_ct_geometry(CTGeometry(info), path)  # 3D first: the placement check assumes it
    check_file_placement(CTGeometry(info), path)
    ct = StreamedCT(info, storage.dtype)
    ct.path = path.resolve()
    threading.Thread(target=fast_read.read_and_hash, args=(path, info, storage, ct.bytes, ct), name="emreg-ct-stream",
                     daemon=True).start()  # into the mapping, every byte hashed
    return ct
