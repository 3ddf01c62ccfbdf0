"""The voxels of an uncompressed DICOM series read from its files where they are looked at: no volume in memory.

A caller that only looks at parts of a CT (``emreg detect``: a strided sample of the whole, then marker-sized
regions at full resolution) needs no copy of all of it. :class:`DicomSliceStack` stands for the volume (numpy
order k, j, i, the series' slices in its order): indexing it with slices reads just the rows asked for from each
slice's file (one ``pread`` per slice, from the Pixel Data's offset that the header walk found) and returns them as
a numpy array, each slice's stored bits masked or sign-extended and its rescale applied exactly as a whole read
does (:func:`~.dicom_pixels.stored_to_voxels`). Filling a volume instead costs, for a 370 MB series,
0.3 s of CPU in page faults alone when the volume is memory a reading process shares, and the read's copy and
conversion of every voxel besides.

Only series whose every slice is a single 16-bit MONOCHROME2 image with native (uncompressed) Pixel Data of a
known offset and the exact length qualify (:meth:`DicomSliceStack.of`); anything else is read whole. A file cut
short is refused when the stack is made (as a whole read refuses it); one cut short afterwards (changed while the
command runs) is an :class:`~EMRegModule.errors.EMRegError` naming it where it is read. The stack is plain data
(paths, offsets, rescales): a forked process reads the same voxels.
"""

from __future__ import annotations

import os
import threading
from dataclasses import dataclass

import numpy as np

from ..errors import EMRegError
from .dicom_pixels import check_pixel_data_length, native_16bit, stored_dtype, stored_to_voxels
from .dicom_series import SliceHeader

_buffers = threading.local()


@dataclass(frozen=True)
class _SliceFile:
    header: SliceHeader
    offset: int  # the Pixel Data's first byte in the file
    stored: np.dtype  # the stored 16-bit values, in the file's byte order


class DicomSliceStack:
    """The volume (k, j, i) of an uncompressed 16-bit DICOM series in voxels of ``dtype``, read where indexed.

    ``stack[k0:k1, j0:j1, i0:i1]`` (steps, integers and fewer axes too) is a new numpy array of those voxels;
    ``shape``, ``dtype``, ``ndim`` and ``size`` are a numpy array's. Values beyond ``dtype`` in what is read raise
    :class:`~.dicom_pixels.NarrowVoxelsError`, as a whole read into ``dtype`` does.
    """

    def __init__(self, slices: list[_SliceFile], rows: int, columns: int, dtype: np.dtype) -> None:
        self._slices = slices
        self.shape = (len(slices), rows, columns)
        self.dtype = np.dtype(dtype)
        self.ndim = 3
        self.size = len(slices) * rows * columns

    @classmethod
    def of(cls, headers: list[SliceHeader], dtype: np.dtype) -> DicomSliceStack | None:
        """The stack of a series' slices (in order), or None unless every slice qualifies (module docstring).

        Each file is measured (``os.stat``): one whose Pixel Data is cut short is refused here
        (:func:`~.dicom_pixels.check_pixel_data_length`)."""
        if not headers or np.dtype(dtype).kind not in "iu":
            return None
        rows, columns = headers[0].rows, headers[0].columns
        slices = []
        for header in headers:
            if not _qualifies(header) or (header.rows, header.columns) != (rows, columns):
                return None
            try:
                size = os.stat(header.path).st_size
            except OSError as exc:
                raise EMRegError(f"{header.path}: cannot read ({exc.strerror})") from None
            check_pixel_data_length(header, size)
            slices.append(_SliceFile(header, header.pixel_data[0], stored_dtype(header)))
        return cls(slices, rows, columns, dtype)

    def __array__(self, dtype: np.dtype | None = None, copy: bool | None = None) -> np.ndarray:
        whole = self[:, :, :]
        return whole if dtype is None else whole.astype(dtype, copy=False)

    def __getitem__(self, key: object) -> np.ndarray:
        keys = key if isinstance(key, tuple) else (key,)
        if len(keys) > 3 or any(not isinstance(k, (slice, int, np.integer)) for k in keys):
            raise TypeError(f"a DICOM slice stack is indexed with up to three slices or integers, not {key!r}")
        keys = keys + (slice(None),) * (3 - len(keys))
        ranges, dropped = [], []
        for axis, (k, n) in enumerate(zip(keys, self.shape, strict=True)):
            if isinstance(k, slice):
                ranges.append(range(*k.indices(n)))
                continue
            index = int(k) + (n if int(k) < 0 else 0)
            if not 0 <= index < n:
                raise IndexError(f"index {int(k)} is out of bounds for axis {axis} with size {n}")
            ranges.append(range(index, index + 1))
            dropped.append(axis)
        out = np.empty(tuple(len(r) for r in ranges), dtype=self.dtype)
        if out.size:
            columns = ranges[2]
            columns = slice(columns.start, columns.stop if columns.stop >= 0 else None, columns.step)
            for n, k in enumerate(ranges[0]):
                self._read_into(self._slices[k], ranges[1], columns, out[n])
        return out.reshape(tuple(len(r) for axis, r in enumerate(ranges) if axis not in dropped))

    def _read_into(self, piece: _SliceFile, rows: range, columns: slice, out: np.ndarray) -> None:
        """Rows ``rows`` (not empty) and ``columns`` of one slice, read from its file and converted into ``out``."""
        first, last = min(rows[0], rows[-1]), max(rows[0], rows[-1])
        row_bytes = self.shape[2] * 2
        wanted = (last - first + 1) * row_bytes
        buffer = getattr(_buffers, "buffer", None)
        if buffer is None or len(buffer) < wanted:
            buffer = _buffers.buffer = bytearray(max(wanted, 1 << 20))
        view = memoryview(buffer)[:wanted]
        path = piece.header.path
        try:
            descriptor = os.open(path, os.O_RDONLY | getattr(os, "O_CLOEXEC", 0))
            try:
                filled, start = 0, piece.offset + first * row_bytes
                while filled < wanted:
                    count = os.preadv(descriptor, [view[filled:]], start + filled)
                    if not count:
                        raise EMRegError(f"{path}: DICOM pixel data is cut short (the file changed while it was "
                                         "read); export the series again")
                    filled += count
            finally:
                os.close(descriptor)
        except OSError as exc:
            raise EMRegError(f"{path}: cannot read ({exc.strerror})") from None
        span = np.frombuffer(buffer, dtype=piece.stored, count=wanted // 2).reshape(-1, self.shape[2])
        stored_to_voxels(span[rows[0] - first::rows.step, columns], piece.header, out)


def _qualifies(header: SliceHeader) -> bool:
    """Whether ``header``'s slice is one native 16-bit greyscale image whose Pixel Data offset and exact length
    are known."""
    if not native_16bit(header) or header.frame is not None or header.pixel_data is None:
        return False
    _, declared = header.pixel_data
    return declared == 2 * header.rows * header.columns
