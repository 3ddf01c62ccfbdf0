"""The CT handle: what every CT reader hands out and every user of a CT's voxels takes.

A reader returns a :class:`CTHandle` as soon as the CT's geometry is known, while its voxels still arrive on a
thread of the reader's: :func:`~EMRegModule.io.image.open_ct` (plain NRRD / MetaImage / NIfTI files through
:mod:`.fast_read`, a DICOM folder through :mod:`.dicom_series`, anything else through SimpleITK),
:func:`~EMRegModule.io.ct_stream.start_streamed_read` (the report's read, its slices given back as it goes), or
:meth:`CTHandle.of_image` (a CT already in memory). Detection, the report and the 3D Slicer bundle depend only
on this module. The handle answers four things:

- **geometry**: :class:`CTGeometry`, SimpleITK's reading of the header: size (i, j, k) in voxels, spacing in mm,
  origin in LPS mm, direction cosines (row-major 3 x 3, its columns the i, j, k axes in LPS), pixel type. It
  answers SimpleITK's getters, so the geometry checks and helpers that take an image take it too.
- **slices as they arrive**: :attr:`CTHandle.array` holds the voxels (numpy, index order k, j, i, native byte
  order); :meth:`CTHandle.wait_for_slices` returns once slices ``0 .. n-1`` (numpy axis 0, the image's k index)
  hold their final values; :meth:`CTHandle.result` waits for the whole read and raises its error.
- **sha256**: :attr:`CTHandle.sha256`, the source's sha256 (hex, for provenance) computed from the very bytes
  the read takes (:class:`~EMRegModule.io.provenance.Digest`); for voxels read from the files where they are looked
  at (:meth:`CTHandle.on_files`), by a pass of its own over the files beside that work.
- **release**: :meth:`CTHandle.release_before` gives slices back to the system (voxels in an anonymous
  mapping: :func:`anonymous_voxels`), :meth:`CTHandle.release` lets go of every voxel (the geometry stays),
  :meth:`CTHandle.cancel` stops the read.

The reader's side is :meth:`CTHandle.provide` (the voxels' home, allocated), :meth:`CTHandle.announce` (slices
in) and :meth:`CTHandle.finish` (the read's end, or its error).
"""

from __future__ import annotations

import ctypes
import mmap
import sys
import threading
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from ..errors import EMRegError
from .provenance import Digest

if TYPE_CHECKING:  # a handle of voxels in numpy memory (a DICOM series for emreg detect) needs no SimpleITK
    import SimpleITK as sitk

#: The getters of a ``SimpleITK.Image`` that a :class:`CTGeometry` answers (and the keys of its JSON form).
GEOMETRY_GETTERS = ("GetSize", "GetSpacing", "GetOrigin", "GetDirection", "GetPixelID", "GetDimension",
                    "GetNumberOfComponentsPerPixel", "GetPixelIDTypeAsString")

#: Transparent huge pages (2 MB) are asked for voxels in an anonymous mapping only when one of their slices
#: spans at least one (slices are given back a few at a time). Streamed read with the report's slice-by-slice
#: release, median of 4-5 alternated runs on 2 cores: 0.32 mm (2.2 MB slices) 8.9 -> 8.3 s with huge pages (kernel
#: 2.6 -> 1.7 s); 0.6 mm (0.63 MB slices) 1.37 -> 1.72 s (kernel 0.33 -> 0.62 s, and from 1.2 to 2.1 s run to run).
HUGE_PAGE_BYTES = 2 << 20


@dataclass(frozen=True)
class CTGeometry:
    """A CT's geometry without its voxels, as SimpleITK's getters give it: ``size`` (i, j, k) voxels, ``spacing``
    (mm), ``origin`` (LPS mm), ``direction`` (9 numbers, row-major, columns the i, j, k axes in LPS), the pixel type
    (``pixel_id``, a ``sitk.sitk*`` value, and its name), dimension and components per voxel."""

    size: tuple[int, ...]
    spacing: tuple[float, ...]
    origin: tuple[float, ...]
    direction: tuple[float, ...]
    pixel_id: int
    dimension: int
    components: int
    pixel_type: str

    @classmethod
    def of(cls, source: sitk.Image | sitk.ImageFileReader | CTGeometry) -> CTGeometry:
        """The geometry of an image, of a header reading (``ImageFileReader`` after ``ReadImageInformation``) or
        another geometry."""
        if isinstance(source, CTGeometry):
            return source
        sitk = sys.modules.get("SimpleITK")  # whoever made ``source`` imported it
        if sitk is not None and isinstance(source, sitk.ImageFileReader):
            return cls(source.GetSize(), source.GetSpacing(), source.GetOrigin(), source.GetDirection(),
                       source.GetPixelID(), source.GetDimension(), source.GetNumberOfComponents(),
                       sitk.GetPixelIDValueAsString(source.GetPixelID()))
        return cls.from_getters({name: getattr(source, name)() for name in GEOMETRY_GETTERS})

    @classmethod
    def from_getters(cls, values: dict[str, object]) -> CTGeometry:
        """The geometry from the getters' values by name (:meth:`getters`; lists are taken as tuples)."""
        value = [tuple(v) if isinstance(v, list) else v for v in (values[name] for name in GEOMETRY_GETTERS)]
        return cls(*value)

    def getters(self) -> dict[str, object]:
        """The getters' values by name (:data:`GEOMETRY_GETTERS`, in that order): the JSON form."""
        return dict(zip(GEOMETRY_GETTERS, (self.size, self.spacing, self.origin, self.direction, self.pixel_id,
                                           self.dimension, self.components, self.pixel_type), strict=True))

    def with_size(self, size: tuple[int, ...]) -> CTGeometry:
        return replace(self, size=tuple(int(n) for n in size))

    # SimpleITK's names, so that what takes an image's geometry takes this
    def GetSize(self) -> tuple[int, ...]:  # noqa: N802
        return self.size

    def GetSpacing(self) -> tuple[float, ...]:  # noqa: N802
        return self.spacing

    def GetOrigin(self) -> tuple[float, ...]:  # noqa: N802
        return self.origin

    def GetDirection(self) -> tuple[float, ...]:  # noqa: N802
        return self.direction

    def GetPixelID(self) -> int:  # noqa: N802
        return self.pixel_id

    def GetDimension(self) -> int:  # noqa: N802
        return self.dimension

    def GetNumberOfComponentsPerPixel(self) -> int:  # noqa: N802
        return self.components

    def GetPixelIDTypeAsString(self) -> str:  # noqa: N802
        return self.pixel_type


def anonymous_voxels(size: tuple[int, ...], dtype: np.dtype, shared: bool = False) -> tuple[mmap.mmap, np.ndarray]:
    """Fresh anonymous memory for a volume of ``size`` (i, j, k) voxels of ``dtype``, and its (k, j, i) array of
    native byte order: each page is faulted in (zeroed by the kernel) only when written, and pages given back
    (``madvise(MADV_DONTNEED)``) are freed (the mapping is private). Huge pages only for slices of at least
    :data:`HUGE_PAGE_BYTES`. ``shared``: a mapping that a child process forked afterwards writes into and this
    one sees (pages are given back with ``MADV_REMOVE``)."""
    dtype = np.dtype(dtype)
    slice_bytes = int(size[0]) * int(size[1]) * dtype.itemsize
    mapping = mmap.mmap(-1, max(1, slice_bytes * int(size[2])), flags=mmap.MAP_SHARED if shared else mmap.MAP_PRIVATE)
    if not shared and hasattr(mmap, "MADV_HUGEPAGE") and slice_bytes >= HUGE_PAGE_BYTES:
        mapping.madvise(mmap.MADV_HUGEPAGE)
    array = np.frombuffer(mapping, dtype=dtype.newbyteorder("="), count=int(np.prod(size)))
    return mapping, array.reshape(tuple(int(n) for n in size[::-1]))


def writable_bytes(image: sitk.Image) -> np.ndarray:
    """The voxel buffer of a freshly made (unshared) ``image`` as a writable flat uint8 array: a reader fills a
    SimpleITK image through it.

    SimpleITK only hands out read-only views; the buffer itself is the image's own, so it is
    written through its address. The returned array must not outlive ``image``.
    """
    import SimpleITK as sitk

    view = sitk.GetArrayViewFromImage(image)  # also makes the buffer unique to this image
    address = view.__array_interface__["data"][0]
    return np.frombuffer((ctypes.c_char * view.nbytes).from_address(address), dtype=np.uint8)


class CTHandle:
    """A CT being read, read, or let go (module docstring): its geometry, its slices as they arrive, the source's
    sha256, and the release of its voxels.

    ``image`` is the SimpleITK image holding the voxels when one does, else the geometry; ``voxels`` the voxels
    when no SimpleITK image holds them (a DICOM series read ``voxels_only``, a streamed file), else None;
    ``series`` the DICOM series read and the others (:mod:`.dicom_series`), ``path`` the source,
    ``memo`` what a consumer kept of these voxels earlier (the report's products) when the handle has none.
    An error of the read is raised by whichever of ``image``, ``array``, ``wait_for_slices`` or ``result`` waits.
    """

    def __init__(self, slice_count: int, geometry: CTGeometry | None = None) -> None:
        self.slice_count = slice_count
        self._geometry = geometry
        self._image: sitk.Image | None = None
        self._array: np.ndarray | None = None
        self._mapping: mmap.mmap | None = None
        self._shared = False
        self._provided = False
        self._ready = 0
        self._released = 0
        self._error: BaseException | None = None
        self._finished = False
        self._cancelled = False
        self._condition = threading.Condition()
        self.is_complete = False  # True when the voxels were all there before the handle was made
        self.sha256: Digest | None = None
        self.series: dict | None = None
        self.path: Path | None = None
        self.memo: object | None = None
        self.on_cancel: Callable[[], None] | None = None  # the reader's own way to stop (a reading process's)

    # --- making one -------------------------------------------------------------------------------

    @classmethod
    def of_image(cls, image: sitk.Image) -> CTHandle:
        """A CT read in full already (a SimpleITK image)."""
        size = image.GetSize()
        handle = cls(size[2] if len(size) > 2 else 1)  # a 2D image is refused by the geometry check
        handle.provide(image=image)
        handle._ready, handle._finished, handle.is_complete = handle.slice_count, True, True
        return handle

    @classmethod
    def in_anonymous_memory(cls, geometry: CTGeometry, dtype: np.dtype, shared: bool = False) -> CTHandle:
        """A CT whose voxels (of ``dtype``) are to be read into :func:`anonymous_voxels` (``shared``: by a child
        process), slices given back with :meth:`release_before`; ``result()`` is None (no SimpleITK image holds
        them)."""
        handle = cls(geometry.size[2], geometry)
        mapping, array = anonymous_voxels(geometry.size, dtype, shared)
        handle._mapping, handle._shared = mapping, shared
        handle.provide(array=array)
        return handle

    @classmethod
    def on_files(cls, geometry: CTGeometry, voxels: object, shared: bool = False) -> CTHandle:
        """A CT whose voxels are read from its files where they are looked at (``voxels``: a
        :class:`~EMRegModule.io.dicom_slices.DicomSliceStack`, indexed like a numpy array of them, k, j, i): every
        slice is there at once; the read ends (:meth:`finish`) once the source's sha256 is made. ``result()`` is
        None. ``shared``: a process forked later reads the same voxels, and may be forked (the caller's process has
        no thread of its own, :func:`~.read_process.can_fork_reader`)."""
        handle = cls(geometry.size[2], geometry)
        handle.provide(array=voxels)
        handle._shared = shared
        handle._ready = handle.slice_count
        return handle

    @classmethod
    def without_voxels(cls, geometry: CTGeometry, sha256: Digest | None = None) -> CTHandle:
        """A CT known by its geometry (and sha256) alone: ``array`` and ``result()`` are None."""
        handle = cls(geometry.size[2] if len(geometry.size) > 2 else 1, geometry)
        handle.sha256 = sha256
        handle._provided = handle._finished = handle.is_complete = True
        handle._ready = handle._released = handle.slice_count
        return handle

    # --- the reader's side ------------------------------------------------------------------------

    def provide(self, image: sitk.Image | None = None, array: np.ndarray | None = None,
                geometry: CTGeometry | None = None) -> None:
        """The voxels' home, allocated: a SimpleITK ``image`` (``array`` defaults to its voxels) or an ``array``
        (k, j, i) with ``geometry`` (default: the handle's)."""
        if array is None and image is not None:
            import SimpleITK as sitk

            array = sitk.GetArrayViewFromImage(image)
        with self._condition:
            self._image = image
            self._array = array
            if geometry is not None:
                self._geometry = geometry
            elif image is not None:
                self._geometry = CTGeometry.of(image)
            self._provided = True
            self._condition.notify_all()

    def announce(self, slices: int) -> None:
        """Slices ``0 .. slices-1`` hold their final values."""
        with self._condition:
            self._ready = slices
            self._condition.notify_all()

    def finish(self, error: BaseException | None = None) -> None:
        """The read is over (``error``: how it failed)."""
        with self._condition:
            self._error = error
            self._finished = True
            self._condition.notify_all()

    @property
    def provided(self) -> bool:
        """Whether the voxels' home is allocated (:meth:`provide`)."""
        return self._provided

    @property
    def shared(self) -> bool:
        """Whether a forked process sees the voxels as they are written (memory a reading process fills, or voxels
        read from the files where they are looked at: :meth:`on_files`)."""
        return self._shared

    @property
    def cancelled(self) -> bool:
        """Whether the user asked the read to stop (:meth:`cancel`)."""
        return self._cancelled

    # --- the consumer's side ----------------------------------------------------------------------

    @property
    def geometry(self) -> CTGeometry:
        """The CT's geometry (known before any voxel arrives)."""
        self._wait_provided()
        return self._geometry

    @property
    def image(self) -> sitk.Image | CTGeometry:
        """The SimpleITK image holding the voxels (which may still be arriving), or the geometry when none does."""
        self._wait_provided()
        return self._image if self._image is not None else self._geometry

    @property
    def array(self) -> np.ndarray | None:
        """The voxels (k, j, i), valid for the slices announced and not released; None once let go."""
        self._wait_provided()
        return self._array

    @property
    def voxels(self) -> np.ndarray | None:
        """The voxels (k, j, i) when no SimpleITK image holds them, else None."""
        self._wait_provided()
        return self._array if self._image is None else None

    def wait_for_slices(self, stop: int) -> None:
        """Block until slices ``0 .. stop-1`` are read (``stop`` is clipped to the slice count)."""
        stop = min(stop, self.slice_count)
        with self._condition:
            self._condition.wait_for(lambda: self._ready >= stop or self._finished)
            self._raise_error()

    def result(self) -> sitk.Image | None:
        """Wait for the whole read (its checksum verified); the SimpleITK image holding the voxels, or None when
        none does (voxels in an array, or let go)."""
        with self._condition:
            self._condition.wait_for(lambda: self._finished)
            self._raise_error()
            return self._image

    def read_error(self) -> BaseException | None:
        """Wait for the read to end; its own error (not a cancellation), or ``None``."""
        with self._condition:
            self._condition.wait_for(lambda: self._finished)
            error = self._error
        return None if isinstance(error, CancelledReadError) else error

    def cancel(self) -> None:
        """Stop reading (the voxels are then incomplete and must not be used)."""
        self._cancelled = True
        if self.on_cancel is not None:
            self.on_cancel()

    def release_before(self, stop: int) -> None:
        """Give slices ``0 .. stop-1`` back to the system when the voxels are in anonymous memory (reading them
        afterwards gives zeros); nothing otherwise."""
        if self._mapping is None or self._array is None:
            return
        start, stop = self._released, min(stop, self._ready)
        slice_bytes = self._array[0].nbytes if self.slice_count else 0
        first, last = (start * slice_bytes) // mmap.PAGESIZE, (stop * slice_bytes) // mmap.PAGESIZE
        if last > first:
            advice = mmap.MADV_REMOVE if self._shared else mmap.MADV_DONTNEED  # shared pages: freed only so
            self._mapping.madvise(advice, first * mmap.PAGESIZE, (last - first) * mmap.PAGESIZE)
        self._released = max(start, stop)

    def release(self) -> None:
        """Let go of every voxel (once read, or cancelled): ``array`` and ``result()`` are None afterwards, the
        geometry and sha256 stay."""
        with self._condition:
            self._image = self._array = None
            self._provided = True

    def _wait_provided(self) -> None:
        with self._condition:
            self._condition.wait_for(lambda: self._provided or self._finished)
            self._raise_error()

    def _raise_error(self) -> None:
        if self._error is not None:
            raise self._error


class CancelledReadError(EMRegError):
    """What a read ends with when its user cancelled it (detection failed first): not the read's own error."""
