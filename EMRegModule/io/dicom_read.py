"""Reading a DICOM CT series chosen by :mod:`.dicom_series`: its slices decoded in parallel into a
:class:`~EMRegModule.io.ct_handle.CTHandle`, announced in order as they are in, so that detection works on them
meanwhile.

Uncompressed 16-bit greyscale slices are read whole (one read, which also gives their sha256) and converted by
numpy straight into the volume; every other transfer syntax is decoded by GDCM through SimpleITK, a run of
consecutive slices per ``ImageSeriesReader`` call, the rescale slope/intercept of each slice applied. The volume is
allocated while the folder's headers are read (a SimpleITK image), or, for a caller that needs the voxels only
while it works on them, is fresh anonymous memory that only the slices' decoding touches; such a caller gets an
uncompressed 16-bit series as its files themselves, indexed where it looks (:mod:`.dicom_slices`), its folder hashed
beside. A multi-frame file is decoded whole by GDCM.

Frames: the voxels are numpy (k, j, i); the geometry (LPS mm) is the series' (:class:`.dicom_series.DicomSeries`),
as SimpleITK's ``ImageSeriesReader`` gives it.
"""

from __future__ import annotations

import hashlib
import os
import threading
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from ..core.pixel_types import FLOAT32, FLOATS, INT16, INT32, NAMES, NUMPY_NAMES, UINT16
from ..errors import EMRegError
from .ct_handle import CTGeometry, CTHandle, writable_bytes
from .dicom_pixels import (
    UNCOMPRESSED,
    NarrowVoxelsError,
    check_fits,
    check_pixel_data_length,
    native_16bit,
    rescaled_range,
    stored_dtype,
    stored_to_voxels,
)
from .dicom_series import DicomSeries, SliceHeader, choose_series, scan_series, series_record
from .dicom_slices import DicomSliceStack
from .itk_messages import quiet_itk
from .provenance import BackgroundHash, Digest, file_sha256, folder_members, folder_sha256
from .read_process import can_fork_reader, fork_reader

if TYPE_CHECKING:  # SimpleITK is imported where an image is made or GDCM decodes: an uncompressed series read
    import SimpleITK as sitk  # into numpy memory (emreg detect) needs none (its library takes 50 ms of CPU to load)

# The threads that run SimpleITK (the read, the early allocation) are no daemons. A daemon thread still inside
# SimpleITK (a volume being allocated, a slice decoded) when the interpreter exits, e.g. right after a one-line
# refusal, is ended by the interpreter from within that C++ code: the process then dies of SIGABRT ("FATAL:
# exception not rethrown") or SIGSEGV instead of exiting 2. The interpreter waits for threads that are no
# daemons before it exits; these end soon (an allocation within a second, a cancelled read at its next slice).


def open_dicom_series(folder: str | os.PathLike[str], series: str | int | None = None,
                      workers: int | None = None, compact: bool = False,
                      voxels_only: bool = False) -> tuple[CTHandle, dict[str, Any]]:
    """Start reading the chosen CT series of ``folder``; its handle and its ``ct_series`` record.

    Slices are decoded on ``workers`` threads (default: the CPU count, at most 8) and announced
    in order (``wait_for_slices``). A slice GDCM cannot decode, or whose size disagrees with its
    header, ends the read with an :class:`EMRegError` naming the file. ``handle.sha256`` is the
    folder's sha256 (:func:`~EMRegModule.io.provenance.file_sha256`), made from each slice's bytes
    as they are read for decoding (the first ones, read while the volume is allocated, are hashed then).

    ``compact``: voxels of :func:`compact_voxel_type` (int16 where the headers allow values beyond
    it but the CT's own values, as CTs' do, fit), half the memory to fill; a slice holding a value
    beyond it ends the read with :class:`NarrowVoxelsError` (read again without ``compact``).

    ``voxels_only``: for a caller that needs the voxels only while it works on them (``emreg detect``): an
    uncompressed 16-bit series is not read into memory at all but indexed where it is looked at
    (:class:`~.dicom_slices.DicomSliceStack`, ``handle.voxels``), while its folder is hashed beside the caller's
    work (by a process of its own where this one may fork, else on threads); other integer voxels go into
    anonymous memory (:meth:`CTHandle.in_anonymous_memory`: ``handle.voxels``, k, j, i;
    ``handle.image`` is only the geometry and ``result()`` None): SimpleITK fills a new image with zeros before a
    slice can be decoded into it (a pass over the whole volume, on one core, that the decoding waits for), where
    these voxels are fresh memory that only the slices' decoding touches, page by page on the workers. Where this
    process may fork (:func:`~.read_process.can_fork_reader`: the command, alone on its thread), the slices are read
    by a process of its own into memory shared with this one, so that the caller's work meanwhile (the detection
    stage's import) does not hold up the read's threads.
    """
    folder = Path(folder)
    early = None if voxels_only else _EarlyImage(compact)
    all_series = scan_series(folder, early.start if early is not None else None)
    chosen = choose_series(all_series, folder, series)
    record = series_record(chosen, all_series, folder)
    if chosen.multiframe:
        digest = BackgroundHash(folder)
        handle = CTHandle.of_image(_read_multiframe(chosen))
        handle.sha256 = digest
    else:
        pixel_type = (compact_voxel_type if compact else voxel_type)(chosen.headers)
        in_memory = voxels_only and pixel_type not in FLOATS  # float32 voxels go into an image (check_ct_image)
        in_process = in_memory and can_fork_reader()
        workers = workers or max(1, min(8, os.cpu_count() or 1))
        stack = DicomSliceStack.of(chosen.headers, NUMPY_NAMES[pixel_type]) if in_memory else None
        if stack is not None:
            handle = CTHandle.on_files(_series_geometry(chosen, pixel_type), stack, shared=in_process)
        elif in_memory:
            handle = CTHandle.in_anonymous_memory(_series_geometry(chosen, pixel_type),
                                                  np.dtype(NUMPY_NAMES[pixel_type]), shared=in_process)
        else:
            handle = CTHandle(len(chosen.headers))
        handle.sha256 = Digest()
        if stack is not None:  # only the folder's sha256 is left to make (then the read ends)
            _start_beside(handle, lambda side: _hash_folder(side, folder, workers), folder, in_process,
                          "emreg-dicom-hash", holds_voxels=False)
        else:
            _start_beside(handle, lambda side: _decode_series(chosen, side, pixel_type, workers, folder, early),
                          folder, in_process, "emreg-dicom-read", error_types=(NarrowVoxelsError,))
    handle.series = record
    return handle, record


def _start_beside(handle: CTHandle, run: Callable[[CTHandle], None], folder: Path, in_process: bool, name: str,
                  **process_options: Any) -> None:
    """Start ``run(handle)`` (reading or hashing the series): in a process of its own where ``in_process`` (not
    sharing the caller's interpreter lock, see :mod:`.read_process`; ``process_options`` are
    :func:`~.read_process.fork_reader`'s), else, or when the system refuses a process, on a thread named
    ``name``."""
    if in_process:
        try:
            fork_reader(handle, run, folder, **process_options)
            return
        except OSError:  # the system refuses a process: a thread
            pass
    threading.Thread(target=run, args=(handle,), name=name).start()  # no daemon: see above


def _hash_folder(handle: CTHandle, folder: Path, workers: int) -> None:
    """Make ``handle``'s sha256 (the folder's, :func:`~EMRegModule.io.provenance.file_sha256`), then end its read."""
    with ThreadPoolExecutor(max_workers=workers, thread_name_prefix="emreg-dicom-hash") as pool:
        _finish_digest(handle, folder, {}, pool)
    handle.finish()


class _EarlyImage:
    """The volume allocated on a thread while the rest of the folder's headers are read.

    Allocating (and so zeroing) a CT of a few hundred MB takes about as long as reading all the
    headers; it does not hold the GIL. The size is guessed from the first image read and the
    files beside it (a folder holding one series: the usual case); the image is used only when
    the chosen series has exactly that size and voxel type, and dropped otherwise.
    """

    _MAX_SLICES = 4096

    def __init__(self, compact: bool = False) -> None:
        self._thread: threading.Thread | None = None
        self._image: sitk.Image | None = None
        self._voxel_type = compact_voxel_type if compact else voxel_type

    def start(self, header: SliceHeader, count: int) -> None:
        if header.frames != 1 or header.samples != 1 or not 3 <= count <= self._MAX_SLICES \
                or header.modality.upper() != "CT" or header.rows < 1 or header.columns < 1:
            return
        size, pixel = [header.columns, header.rows, count], self._voxel_type([header])
        import SimpleITK as sitk

        def allocate() -> None:
            self._image = sitk.Image(size, pixel)

        self._thread = threading.Thread(target=allocate, name="emreg-dicom-allocate")  # no daemon (see above)
        self._thread.start()

    def allocating(self) -> bool:
        """Whether the early image is still being allocated."""
        return self._thread is not None and self._thread.is_alive()

    def take(self, series: DicomSeries) -> sitk.Image | None:
        """The early image if it fits ``series`` (size, voxel type), else None (it is let go)."""
        if self._thread is None:
            return None
        self._thread.join()
        image, self._image = self._image, None
        if image is None or series.multiframe or series.size is None or tuple(image.GetSize()) != series.size \
                or image.GetPixelID() != self._voxel_type(series.headers):
            return None
        return image


def _read_multiframe(series: DicomSeries) -> sitk.Image:
    """A multi-frame file's volume: GDCM's pixels, frames in the order along the normal, the functional groups'
    geometry (:func:`_multiframe_geometry`); GDCM's own image for a file without functional groups."""
    import SimpleITK as sitk

    path = series.headers[0].path
    check_pixel_data_length(series.headers[0], path.stat().st_size)
    if not series.frames:
        return _read_one(path)
    decoded = _read_one(path, voxel_type(series.frames))
    values = sitk.GetArrayViewFromImage(decoded)
    order = [f.frame for f in series.frames]
    image = sitk.GetImageFromArray(values[order] if order != sorted(order) else values)
    image.SetSpacing(series.spacing)
    image.SetOrigin(series.origin)
    image.SetDirection(series.direction)
    return image


def _read_one(path: Path, pixel: int | None = None) -> sitk.Image:
    import SimpleITK as sitk

    reader = sitk.ImageFileReader()
    reader.SetImageIO("GDCMImageIO")
    reader.SetFileName(str(path))
    if pixel is not None:
        reader.SetOutputPixelType(pixel)
    try:
        with quiet_itk():
            return reader.Execute()
    except RuntimeError as exc:
        lines = [line.strip() for line in str(exc).splitlines() if line.strip()]
        detail = lines[-1][:160] if lines else "unreadable"
        raise EMRegError(f"{path}: cannot decode the DICOM image ({detail})") from None


def _integral(header: SliceHeader) -> bool:
    return float(header.slope).is_integer() and float(header.intercept).is_integer()


def voxel_type(headers: list[SliceHeader]) -> int:
    """The SimpleITK pixel type holding every slice's rescaled values exactly (int16 if it can)."""
    ranges = [rescaled_range(h) for h in headers]
    low, high = min(r[0] for r in ranges), max(r[1] for r in ranges)
    if all(_integral(h) for h in headers):
        for pixel in (INT16, UINT16, INT32):
            info = np.iinfo(NUMPY_NAMES[pixel])
            if info.min <= low and high <= info.max:
                return pixel
    return FLOAT32


def compact_voxel_type(headers: list[SliceHeader]) -> int:
    """int16 where :func:`voxel_type` is int32 only because the stored bits could hold more than CT values do.

    Scanners often store 16 bits with an intercept of -1024 (unsigned: -1024 .. 64511 HU; signed:
    -33792 .. 31743), which takes int32 to hold exactly, while the CT's values (air -1000, bone a
    few thousand, metal often clipped at 3071 or at most some 30000 HU) fit int16. A compact read
    checks every slice (:class:`NarrowVoxelsError` when one does not fit).
    """
    exact = voxel_type(headers)
    if exact == INT32 and all(h.bits_allocated == 16 for h in headers):
        return INT16
    return exact


_PIXEL_DATA_TAG = {"<": b"\xe0\x7f\x10\x00", ">": b"\x7f\xe0\x00\x10"}
_CHUNK_SLICES = 8  # compressed slices decoded by one ImageSeriesReader call
_buffers = threading.local()


def _file_bytes(path: Path, hashed: bool = True) -> tuple[memoryview, bytes | None]:
    """The whole file in this thread's reusable buffer, and its sha256 (one read, no allocation per slice; None
    unless ``hashed``).

    Read with the operating system's calls themselves (open, fstat, one read asking one byte more than the file
    holds, close): each call lets go of the GIL and must take it back, which costs up to a switch interval (5 ms)
    while the detection stage's import holds it, so a slice is read with as few as it takes."""
    try:
        descriptor = os.open(path, os.O_RDONLY | getattr(os, "O_CLOEXEC", 0))
    except OSError as exc:
        raise EMRegError(f"{path}: cannot read ({exc.strerror})") from None
    try:
        size = os.fstat(descriptor).st_size
        buffer = getattr(_buffers, "buffer", None)
        if buffer is None or len(buffer) <= size:
            buffer = _buffers.buffer = bytearray(max(size + 1, 1 << 20))
        view = memoryview(buffer)[:size + 1]
        filled = 0
        while filled <= size:
            count = os.readv(descriptor, [view[filled:]])
            if not count:
                break  # the end, before the size fstat gave
            filled += count
            if filled == size:
                break  # all of it: a read asked for one byte more stops short only at a regular file's end
        if filled > size:
            raise EMRegError(f"{path}: the file grew while it was read")
    except OSError as exc:
        raise EMRegError(f"{path}: cannot read ({exc.strerror})") from None
    finally:
        os.close(descriptor)
    view = view[:filled]
    return view, hashlib.sha256(view).digest() if hashed else None


def _read_uncompressed(header: SliceHeader, data: memoryview, out: np.ndarray) -> bool:
    """Decode an uncompressed 16-bit slice from its file's bytes into ``out`` (HU after its rescale); False if
    not that simple; :class:`NarrowVoxelsError` when its values do not fit ``out``'s type.

    Taken only when the file ends with its Pixel Data element (checked from its tag) holding
    exactly rows x columns 16-bit values of a MONOCHROME2 image; the stored bits are masked
    (unsigned) or sign-extended (signed) as DICOM defines, then the slice's own slope and
    intercept applied. Anything else is decoded by GDCM. The tests compare both with
    ``SimpleITK.ImageSeriesReader``.
    """
    if not native_16bit(header):
        return False
    order = UNCOMPRESSED[header.transfer_syntax]
    count = header.rows * header.columns
    explicit = header.transfer_syntax != "1.2.840.10008.1.2"
    start = len(data) - 2 * count
    element = bytes(data[start - (12 if explicit else 8):start]) if start >= 12 else b""
    if len(element) < 8:
        return False
    length = int.from_bytes(element[-4:], "little" if order == "<" else "big")
    if element[:4] != _PIXEL_DATA_TAG[order] or length != 2 * count \
            or (explicit and element[4:6] not in (b"OW", b"OB")):
        return False
    stored = np.frombuffer(data, dtype=stored_dtype(header), count=count, offset=start)
    stored_to_voxels(stored.reshape(header.rows, header.columns), header, out)
    return True


def _slice_tasks(headers: list[SliceHeader]) -> list[tuple[int, int]]:
    """Runs of slices decoded by one task: one uncompressed slice, or up to ``_CHUNK_SLICES`` compressed ones."""
    tasks: list[tuple[int, int]] = []
    k = 0
    while k < len(headers):
        stop = k + 1
        if not native_16bit(headers[k]):
            while stop < len(headers) and stop - k < _CHUNK_SLICES and not native_16bit(headers[stop]):
                stop += 1
        tasks.append((k, stop))
        k = stop
    return tasks


def _series_geometry(series: DicomSeries, pixel_type: int) -> CTGeometry:
    """The geometry of ``series``' volume of ``pixel_type`` voxels as the image SimpleITK would hold them gives it,
    without the image (nor SimpleITK): ITK keeps the spacing, origin and direction it is given, number for number
    (the tests compare both)."""
    return CTGeometry(tuple(int(n) for n in series.size), tuple(float(v) for v in series.spacing),
                      tuple(float(v) for v in series.origin), tuple(float(v) for v in series.direction), pixel_type,
                      3, 1, NAMES[pixel_type])


def _decode_series(series: DicomSeries, handle: CTHandle, pixel_type: int, workers: int, folder: Path,
                   early: _EarlyImage | None = None) -> None:
    """The reading thread: allocate the volume of ``pixel_type`` voxels (or take the ``early`` image) unless the
    handle holds its voxels already, decode slices on a pool, announce the in-order prefix, then the sha256.

    Uncompressed slices are read whole (one read, which also gives their sha256) and converted by
    numpy; compressed ones are decoded by GDCM, a run of consecutive slices per
    ``SimpleITK.ImageSeriesReader`` call (one header parse per file fewer than ``ImageFileReader``,
    and SimpleITK releases the GIL, so the workers decode in parallel).
    """
    digests: dict[str, bytes] = {}
    names = {h.path: _relative(h.path, folder) for h in series.headers}
    pool = ThreadPoolExecutor(max_workers=workers, thread_name_prefix="emreg-dicom-decode")
    try:
        if early is not None:
            _hash_while_allocating(series.headers, early, pool, workers, names, digests)
        voxels = handle.voxels if handle.provided else _allocate(series, handle, pixel_type, early)
        expected = (series.size[1], series.size[0])
        pixel = voxel_type(series.headers)  # GDCM's output, checked where it is narrowed to the image's type

        def decode(start: int, stop: int) -> None:
            if handle.cancelled:
                return
            headers = series.headers[start:stop]
            direct = False
            for k, header in enumerate(headers, start):
                hashed = names[header.path] not in digests
                data, digest = _file_bytes(header.path, hashed)
                if hashed:
                    digests[names[header.path]] = digest
                check_pixel_data_length(header, len(data), data)
                if stop - start == 1:
                    direct = _read_uncompressed(header, data, voxels[k])
            if not direct:
                _decode_gdcm(headers, voxels[start:stop], expected, pixel)

        with pool:
            tasks = _slice_tasks(series.headers)
            futures = [pool.submit(decode, start, stop) for start, stop in tasks]
            try:
                for k, ((_, stop), future) in enumerate(zip(tasks, futures, strict=True)):
                    future.result()
                    if handle.cancelled:
                        raise EMRegError(f"{series.headers[0].path.parent}: reading the CT was cancelled")
                    if k + 1 == len(futures) or not futures[k + 1].done():
                        # the slices in order so far, told once before waiting for the next: a reader waiting
                        # for slices is woken (and takes the GIL) once per run of them, not once per slice
                        handle.announce(stop)
            except BaseException:
                for future in futures:
                    future.cancel()
                raise
            _finish_digest(handle, folder, digests, pool)
    except BaseException as exc:  # handed to the waiting thread
        pool.shutdown(cancel_futures=True)
        if not handle.sha256.done():
            handle.sha256.fail(exc)
        handle.finish(exc)
    else:
        handle.finish()


def _allocate(series: DicomSeries, handle: CTHandle, pixel_type: int, early: _EarlyImage | None) -> np.ndarray:
    """The SimpleITK image of ``series``' volume (the ``early`` one if it fits), provided to ``handle``; its
    voxels (k, j, i) as a writable array."""
    import SimpleITK as sitk

    image = early.take(series) if early is not None else None  # allocated while the headers were read
    if image is None:
        image = sitk.Image(list(series.size), pixel_type)
    image.SetSpacing(series.spacing)
    image.SetOrigin(series.origin)
    image.SetDirection(series.direction)
    raw = writable_bytes(image)
    handle.provide(image=image)
    view = handle.array
    return raw.view(view.dtype).reshape(view.shape)


def _hash_while_allocating(headers: list[SliceHeader], early: _EarlyImage, pool: ThreadPoolExecutor, workers: int,
                           names: dict[Path, str | None], digests: dict[str | None, bytes]) -> None:
    """While the early volume is being allocated (zeroed, which keeps one core busy without the GIL), hash the
    first slices' files on the pool into ``digests``: the decoding, which waits for the volume, then reads them
    without hashing them (the slices' sha256 is the largest share of an uncompressed series' CPU)."""
    k, width = 0, max(1, workers - 1)  # a core is zeroing the volume
    while k < len(headers) and early.allocating():
        batch = headers[k:k + width]
        for header, digest in zip(batch, pool.map(lambda h: _file_bytes(h.path)[1], batch), strict=True):
            digests[names[header.path]] = digest
        k += len(batch)


def _decode_gdcm(headers: list[SliceHeader], out: np.ndarray, expected: tuple[int, int], pixel: int) -> None:
    """Decode consecutive slices with GDCM as ``pixel`` into ``out`` (one ImageSeriesReader call; file by file on
    an error, to name the file); :class:`NarrowVoxelsError` when a slice's values do not fit ``out``'s type."""
    import SimpleITK as sitk

    if len(headers) > 1:
        reader = sitk.ImageSeriesReader()
        reader.SetImageIO("GDCMImageIO")
        reader.SetFileNames([str(h.path) for h in headers])
        reader.SetOutputPixelType(pixel)
        reader.SetNumberOfThreads(1)  # the pool's workers are the parallelism
        try:
            with quiet_itk():
                chunk = reader.Execute()
        except RuntimeError:
            chunk = None  # one of the files is bad: decoded one by one below, which names it
        if chunk is not None and chunk.GetNumberOfComponentsPerPixel() == 1:
            values = sitk.GetArrayViewFromImage(chunk)
            if values.shape == (len(headers), *expected):
                for header, slice_values in zip(headers, values, strict=True):
                    check_fits(slice_values, header, out.dtype, stored=False)
                np.copyto(out, values, casting="unsafe")
                return
    for k, header in enumerate(headers):
        slice_image = _read_one(header.path, pixel)
        values = sitk.GetArrayViewFromImage(slice_image)
        values = values.reshape(values.shape[-2:]) if values.ndim == 3 and values.shape[0] == 1 else values
        if values.shape != expected or slice_image.GetNumberOfComponentsPerPixel() != 1:
            raise EMRegError(f"{header.path}: the decoded image ({values.shape[-1]}x{values.shape[-2]}) disagrees "
                             f"with its header ({expected[1]}x{expected[0]})")
        check_fits(values, header, out.dtype, stored=False)
        np.copyto(out[k], values, casting="unsafe")


def _relative(path: Path, folder: Path) -> str | None:
    try:
        return path.relative_to(folder).as_posix()
    except ValueError:
        return None


def _finish_digest(handle: CTHandle, folder: Path, digests: dict[str, bytes], pool: ThreadPoolExecutor) -> None:
    """``handle.sha256``: the folder's, from the slices' sha256 and those of its other files (hashed on ``pool``)."""
    try:
        members = folder_members(folder)
        others = [(name, path) for name, path in members if name not in digests]
        hashes = pool.map(lambda item: bytes.fromhex(file_sha256(item[1])), others)
        hashed = dict(zip([name for name, _ in others], hashes, strict=True))
        covered = {name: digests[name] for name, _ in members if name in digests}
        handle.sha256.set(folder_sha256({**covered, **hashed}))
    except Exception as exc:  # noqa: BLE001 - the CT is read; its provenance hash is asked again later
        handle.sha256.fail(exc)
