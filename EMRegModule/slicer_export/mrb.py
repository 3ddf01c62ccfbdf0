"""The scene bundle's zip (``.mrb``): 3D Slicer's scene folder, zipped by EMReg with the CT's voxels written in.

Slicer's own bundle writer gzips a CT on one thread (450 MB of voxels: 10-41 s) and copies the voxels to disk
twice. :func:`write_mrb` lets Slicer write the scene folder with one-voxel placeholders of the volumes, then
:func:`_zip_bundle` writes each volume's NRRD entry from the placeholder's header and the voxels: those of the CT's
own file (:class:`StoredVoxels`, copied as stored) or those in memory (:class:`_MemoryVoxels`, gzip-compressed by
ISA-L on the way).
"""

from __future__ import annotations

import os
import re
import shutil
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any
from urllib.parse import unquote

import numpy as np

from ..errors import EMRegError
from ..io.atomic import cannot_write
from ..io.zip_store import FileRegion, StoredZipWriter

try:  # a declared dependency, absent from 3D Slicer's own Python: then Slicer's own compressed writer
    from isal import igzip_threaded
except ImportError:  # pragma: no cover - depends on the installation
    igzip_threaded = None


def write_mrb(scene: Any, path: Path, stored: dict[str, StoredVoxels]) -> str:
    """Write ``scene`` (a ``vtkMRMLScene``) as a bundle (``.mrb``: the ``.mrml`` scene and its data files,
    zipped) with Slicer's writer (``vtkMRMLScene::WriteToMRB``), atomically: built in a private folder beside
    ``path``, then renamed onto it. Returns its sha256 (hex, computed as it was written).

    ``stored``: volume node id -> :class:`StoredVoxels`, for volume nodes made by
    :func:`~EMRegModule.slicer_export.nodes.show_stored_volume` (a one-voxel placeholder with the CT's geometry):
    their entries get the voxels of that file, copied as it stores them (no decoding, no re-compression)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    # Slicer's default storage nodes. Its single-threaded gzip of a CT is slow (450 MB of voxels: 10-41 s)
    # and its bundle writer copies the voxels to disk twice (the folder, then the zip). So each scalar
    # volume is saved by Slicer as a one-voxel placeholder of the same type and geometry, uncompressed,
    # and :func:`_zip_bundle` writes its NRRD entry from that header (true ``sizes``, ``encoding: gzip``)
    # and the node's voxels in memory, gzip-compressed by ISA-L on their way into the zip.
    volumes: dict[str, tuple[Any, Any]] = {}  # storage node id -> (volume node, its image data)
    sources: dict[str, Any] = {}  # storage node id -> where the entry's voxels come from
    fast_gzip = igzip_threaded is not None  # without it (3D Slicer's Python), Slicer's own compressed writer
    storables = scene.GetNodesByClass("vtkMRMLStorableNode")
    for node in (storables.GetItemAsObject(i) for i in range(storables.GetNumberOfItems())):
        if node.GetStorageNode() is None:
            node.AddDefaultStorageNode()
        storage = node.GetStorageNode()
        data = node.GetImageData() if node.IsA("vtkMRMLScalarVolumeNode") else None
        if node.GetID() in stored and storage is not None:
            if not storage.IsA("vtkMRMLVolumeArchetypeStorageNode"):
                raise EMRegError(f"{path}: 3D Slicer gave the volume {node.GetName()!r} an unexpected writer")
            volumes[storage.GetID()] = (node, data)  # already a placeholder: written as it is
            sources[storage.GetID()] = stored[node.GetID()]
        elif (fast_gzip and data is not None and data.GetPointData().GetScalars() is not None
                and storage is not None and storage.IsA("vtkMRMLVolumeArchetypeStorageNode")):
            volumes[storage.GetID()] = (node, data)
            sources[storage.GetID()] = _MemoryVoxels(data)
    work = Path(tempfile.mkdtemp(prefix=f".{path.stem}-", dir=path.parent)).resolve()
    try:
        # What ``vtkMRMLScene::WriteToMRB`` does (the scene and its data in a folder named as the bundle,
        # zipped: stored entries), with the zip made here.
        folder = work / path.stem
        staged = work / path.name
        folder.mkdir()
        for storage_id, (node, data) in volumes.items():
            scene.GetNodeByID(storage_id).UseCompressionOff()
            if not isinstance(sources[storage_id], StoredVoxels):
                node.SetAndObserveImageData(_placeholder_like(data))
        scene.SetRootDirectory(str(work))
        saved = scene.SaveSceneToSlicerDataBundleDirectory(str(folder))
        for node, data in volumes.values():
            node.SetAndObserveImageData(data)
        if not saved or not folder.is_dir():
            raise EMRegError(f"{path}: 3D Slicer's writer could not write the scene bundle "
                             "(disk full or no permission?)")
        digest = _zip_bundle(folder, staged, sources)
        os.replace(staged, path)
    except OSError as exc:  # a full disk, no permission: one line naming the bundle, as for every output
        raise cannot_write(path, exc) from None
    finally:
        for storage_id, (node, data) in volumes.items():  # the scene as it was (Slicer's default: compressed)
            if node.GetImageData() is not data:
                node.SetAndObserveImageData(data)
            scene.GetNodeByID(storage_id).UseCompressionOn()
        shutil.rmtree(work, ignore_errors=True)
    return digest


#: ISA-L's compression level for the CT in a bundle (0-3; 2: measured as small as Slicer's zlib level, ~10x faster).
BUNDLE_GZIP_LEVEL = 2
#: Bytes re-encoded at a time (bounded memory whatever the CT's size).
_CHUNK_BYTES = 16 << 20


def _placeholder_like(data: Any) -> Any:
    """A one-voxel ``vtkImageData`` of the scalar type and components of ``data`` (geometry is the node's)."""
    scalars = data.GetPointData().GetScalars()
    return _placeholder(scalars.GetDataType(), scalars.GetNumberOfComponents())


def placeholder_of(dtype: np.dtype) -> Any:
    """A one-voxel scalar ``vtkImageData`` of a numpy voxel type."""
    from vtkmodules.util import numpy_support

    return _placeholder(numpy_support.get_vtk_array_type(np.dtype(dtype)), 1)


def _placeholder(vtk_type: int, components: int) -> Any:
    from vtkmodules.vtkCommonDataModel import vtkImageData

    placeholder = vtkImageData()
    placeholder.SetDimensions(1, 1, 1)
    placeholder.AllocateScalars(vtk_type, components)
    placeholder.GetPointData().GetScalars().Fill(0)
    return placeholder


class _MemoryVoxels:
    """An entry's voxels from a ``vtkImageData`` in memory, gzip-compressed by ISA-L on their way into the zip."""

    encoding = "gzip"  # the bundle entry's

    def __init__(self, data: Any) -> None:
        self.data = data

    @property
    def dimensions(self) -> tuple[int, int, int]:
        return tuple(int(n) for n in self.data.GetDimensions())

    def write_gzip(self, sink: Any) -> None:
        from vtkmodules.util import numpy_support

        flat = memoryview(numpy_support.vtk_to_numpy(self.data.GetPointData().GetScalars())).cast("B")
        with _parallel_gzip(sink) as gzip:
            for start in range(0, flat.nbytes, _CHUNK_BYTES):
                gzip.write(flat[start:start + _CHUNK_BYTES])

    @property
    def nbytes(self) -> int:
        scalars = self.data.GetPointData().GetScalars()
        return scalars.GetNumberOfValues() * scalars.GetDataTypeSize()

    def zip_parts(self, scratch: Path) -> list[Any]:
        """The gzip stream of the voxels as parts of a zip entry (:mod:`EMRegModule.io.zip_store`): compressed
        into the file ``scratch`` first (an entry's CRC comes before its data)."""
        return _spooled(self, scratch)


@dataclass(frozen=True)
class StoredVoxels:
    """A CT's voxels as its NRRD file stores them (:func:`stored_voxels`): copied into a bundle as they are.

    ``path`` the file, ``offset`` where its data starts, ``encoding`` "gzip" or "raw" (the bundle's entry has
    the same: the gzip stream or the raw voxels are copied byte for byte, nothing is decoded or compressed
    again); ``geometry`` SimpleITK's reading of the header (size, spacing, origin, direction
    and pixel type as ``sitk.ReadImage`` gives them); ``dtype`` the voxel type (machine byte order).
    """

    path: Path
    offset: int
    encoding: str
    geometry: Any
    dtype: np.dtype

    @property
    def dimensions(self) -> tuple[int, int, int]:
        return tuple(int(n) for n in self.geometry.GetSize())

    @property
    def nbytes(self) -> int:
        return int(np.prod(self.dimensions)) * self.dtype.itemsize

    def zip_parts(self, scratch: Path) -> list[Any]:
        """The voxels as the file stores them, as the parts of a zip entry (:mod:`EMRegModule.io.zip_store`): its
        gzip stream, or its raw bytes (``scratch`` is not used)."""
        length = self.path.stat().st_size - self.offset
        if self.encoding == "gzip":
            return [FileRegion(self.path, self.offset, length)]
        if length < self.nbytes:
            raise EMRegError(f"{self.path}: the CT file is shorter than its header says")
        return [FileRegion(self.path, self.offset, self.nbytes)]


def _parallel_gzip(sink: Any) -> Any:
    """A writer of one gzip stream into ``sink``, compressed by ISA-L on every core (pigz's way: 1 MB blocks,
    each with the last 32 kB of the one before as its dictionary). The bytes do not depend on the number of
    threads, and the header has no time stamp: the same voxels give the same stream. ``sink`` stays open.

    One thread compressed a 0.5 mm full-frame CT (955 MB) at about 250 MB/s: 4-5 s of ``emreg report`` on a
    DICOM case, whose bundle compresses the CT from memory."""
    return igzip_threaded.open(sink, "wb", compresslevel=BUNDLE_GZIP_LEVEL, threads=max(1, os.cpu_count() or 1))


def _spooled(voxels: _MemoryVoxels, scratch: Path) -> list[Any]:
    """``voxels.write_gzip`` into the file ``scratch``, as the one part of a zip entry."""
    with scratch.open("wb") as sink:
        voxels.write_gzip(sink)
    return [FileRegion(scratch, 0, scratch.stat().st_size)]


def stored_voxels(path: str | os.PathLike[str] | None) -> StoredVoxels | None:
    """The CT file's voxels as a bundle can copy them (a plain NRRD: attached raw or gzip data in the
    machine's byte order, see :func:`EMRegModule.io.fast_read.stored_nrrd_voxels`), or None (then the
    bundle needs the CT in memory: DICOM, MetaImage, NIfTI, other NRRD layouts)."""
    if path is None:
        return None
    from ..io.fast_read import stored_nrrd_voxels

    found = stored_nrrd_voxels(Path(path))
    if found is None:
        return None
    geometry, dtype, offset, encoding = found
    if encoding == "raw" and igzip_threaded is None:
        return None
    return StoredVoxels(Path(path).resolve(), offset, encoding, geometry, dtype)


def _zip_bundle(folder: Path, target: Path, sources: dict[str, Any]) -> str:
    """Zip a scene-bundle folder (Slicer's ``.mrb`` layout: ``NAME/NAME.mrml``, ``NAME/Data/...``, stored
    entries) into ``target``; returns the sha256 of the archive (computed as it is written).

    ``sources``: storage node id -> the voxels (:class:`_MemoryVoxels` or :class:`StoredVoxels`) of
    the volumes Slicer saved as one-voxel raw NRRD placeholders (their files are found by the storage
    nodes' ``fileName`` in the ``.mrml``). Their entries are written from the placeholder's header
    (Slicer's fields and geometry) with ``sizes`` set to the volume's dimensions and the source's encoding,
    followed by its voxels: a plain NRRD CT file's own gzip stream or raw voxels copied as they are (a raw
    NRRD gives a raw entry: compressing 2.7 GB at 0.3 mm took ~12 s of CPU, the copy is the kernel's), or a
    gzip stream (as Slicer's own compressed writer makes) of the voxels in memory, compressed by ISA-L at
    :data:`BUNDLE_GZIP_LEVEL` a chunk of :data:`_CHUNK_BYTES` at a time into a scratch file beside ``target``.
    The ``.mrml`` says
    ``useCompression="1"`` again for the storage nodes, so that a scene saved again from Slicer stays
    compressed. The archive is written by :class:`~EMRegModule.io.zip_store.StoredZipWriter` (one forward
    pass, large files copied by the kernel, hashed on the way).
    """
    files_of: dict[Path, Any] = {}
    for scene_file in folder.glob("*.mrml"):
        scene = scene_file.read_text(encoding="utf-8")
        for storage_id, source in sources.items():
            found = re.search(rf'<\w+\s[^>]*\bid="{re.escape(storage_id)}"[^>]*\bfileName="([^"]*)"', scene)
            if found:  # relative to the scene's folder, URL-encoded
                files_of[(folder / unquote(found.group(1))).resolve()] = source
    written = set()
    scratch = target.with_name(f"{target.name}.voxels")
    try:
        with StoredZipWriter(target) as out:
            for current, dirs, files in os.walk(folder):
                dirs.sort()
                here = Path(current)
                status = here.stat()
                out.add_directory(here.relative_to(folder.parent).as_posix(), status.st_mtime, status.st_mode)
                for name in sorted(files):
                    path = here / name
                    arcname = path.relative_to(folder.parent).as_posix()
                    status = path.stat()
                    if name.endswith(".mrml"):
                        scene = path.read_text(encoding="utf-8")
                        for storage_id in sources:
                            scene = re.sub(rf'(<\w+\s[^>]*\bid="{re.escape(storage_id)}"[^>]*\buseCompression=")0"',
                                           r'\g<1>1"', scene)
                        out.add(arcname, [scene.encode("utf-8")], status.st_mtime)
                        continue
                    if path.resolve() not in files_of:
                        out.add(arcname, [path.read_bytes()], status.st_mtime, (status.st_mode & 0xFFFF) << 16)
                        continue
                    with path.open("rb") as placeholder:
                        header = _read_nrrd_header(placeholder)
                    if not (header.endswith(b"\n\n") and b"\nencoding: raw\n" in header
                            and b"\nsizes: 1 1 1\n" in header):
                        raise EMRegError(f"{arcname}: 3D Slicer wrote the volume in a form EMReg does not expect")
                    source = files_of[path.resolve()]
                    written.add(id(source))
                    sizes = " ".join(str(n) for n in source.dimensions).encode("ascii")
                    encoding = f"\nencoding: {source.encoding}\n".encode("ascii")
                    header = header.replace(b"\nencoding: raw\n", encoding, 1).replace(
                        b"\nsizes: 1 1 1\n", b"\nsizes: " + sizes + b"\n", 1)
                    out.add(arcname, [header, *source.zip_parts(scratch)], status.st_mtime)
                    scratch.unlink(missing_ok=True)
            digest = out.close()
    finally:
        scratch.unlink(missing_ok=True)
    if written != {id(source) for source in sources.values()}:  # a placeholder left as a volume: a wrong scene
        raise EMRegError("3D Slicer did not write every volume where its scene says")
    return digest


def _read_nrrd_header(entry: Any) -> bytes:
    """The header of an attached-data NRRD read from a binary stream, through its blank line (what was
    read, without that blank line, when the stream holds no such header)."""
    lines = []
    while True:
        line = entry.readline(1 << 16)
        lines.append(line)
        if not line.endswith(b"\n") or line in (b"\n", b"\r\n"):
            return b"".join(lines)


def bundle_needs_ct_image(ct_path: str | os.PathLike[str] | None) -> bool:
    """False when a bundle of a run on this CT copies the CT from its file (:func:`stored_voxels`), so that
    the CT need not be kept in memory for it."""
    return stored_voxels(ct_path) is None
