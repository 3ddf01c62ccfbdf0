"""3D Slicer scenes of EMReg's results, built with Slicer's own MRML (``slicer`` package).

Inside 3D Slicer ``slicer`` is the application's; outside it, the optional ``slicer-core``
wheel (``pip install 'emreg[slicer]'``) provides the same MRML nodes, storage nodes, module
logics and ``slicer.util`` array helpers, without Qt. This module uses nothing else, so the
3D Slicer module's Logic (``EMRegModule/slicer/EMReg.py``) and the scene bundle
``OUT/EMReg.mrb`` written by ``emreg run`` / ``emreg report`` show the same nodes.

Frames: EMReg's image space is the CT's LPS space; Slicer's world is RAS. Points of image
space are flipped (x, y negated). ``ReferenceToImage`` becomes the linear transform node
``ReferenceToImage`` holding ``ReferenceToRAS = LPS_TO_RAS @ ReferenceToImage``; nodes in the
Reference frame (calibration points, the probe pose ``ProbeToReference``) are placed under it
with their coordinates unchanged, as PLUS and SlicerIGT do for tracker-side frames.
"""

from __future__ import annotations

import contextlib
import os
import shutil
import tempfile
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import EMRegError
from ..frames import LPS_TO_RAS, lps_to_ras_points
from ..outputs import signals_held, vtk_imports_uninterrupted
from .atomic import _cannot_write

#: File name of the scene bundle in an output folder.
BUNDLE_FILE = "EMReg.mrb"
#: How to get Slicer's MRML outside 3D Slicer.
INSTALL_HINT = "install the optional dependency with: pip install 'emreg[slicer]' (the slicer-core wheel)"


# Node names (the Slicer module's Logic and the bundle use the same ones).
VOLUME_NODE_NAME = "EMReg CT"
MARKERS_NODE_NAME = "EMReg markers"
PINHOLES_NODE_NAME = "EMReg pinhole points"
CALIBRATION_NODE_NAME = "EMReg calibration points"
TARGETS_NODE_NAME = "EMReg targets"
PATH_NODE_NAME = "EMReg probe path"
RESIDUALS_NODE_NAME = "EMReg marker residuals"
TRANSFORM_NODE_NAME = "ReferenceToImage"
PROBE_NODE_NAME = "ProbeToReference"
TIP_NODE_NAME = "TipToProbe"  # a tool's tip (frame_calibration.json's tool), under the probe pose when known
TRE_MAP_NODE_NAME = "EMReg predicted TRE (mm)"
FIDUCIALS_NODE_NAME = "EMReg fiducials"
#: The predicted-TRE map of a run (``emreg run`` writes it beside registration.json when it can).
TRE_MAP_FILE = "tre_map.nrrd"

#: Most control points of the probe path curve (the recording is subsampled evenly).
MAX_PATH_POINTS = 1000


def slicer_mrml_missing() -> str | None:
    """Why Slicer's MRML cannot be used here (``None`` when it can).

    The import is never cut by Ctrl-C / SIGTERM (held, then delivered: :func:`~EMRegModule.outputs.signals_held`):
    VTK's loader turned the interrupt into an ImportError (a false "not installed") or left a half-initialised
    extension module that crashed the process."""
    try:
        with signals_held():
            import slicer
    except ImportError as exc:
        return f"3D Slicer's MRML (the slicer-core wheel) is not installed ({exc}); {INSTALL_HINT}"
    if not hasattr(slicer, "vtkMRMLScene") or not hasattr(slicer, "vtkSlicerMarkupsLogic"):
        return f"the 'slicer' package found has no MRML classes; {INSTALL_HINT}"
    return None


class SlicerScene:
    """A ``vtkMRMLScene`` with the module logics 3D Slicer's application registers for it.

    Application logic (colours), Markups, Transforms, Volumes and Sequences logics (their node
    classes, storage nodes and readers), and the remote-I/O logic that ``ReadFromMRB`` needs
    for its cache. ``scene`` is the ``vtkMRMLScene``; keep this object alive while using it.
    """

    def __init__(self) -> None:
        missing = slicer_mrml_missing()
        if missing:
            raise EMRegError(missing)
        import slicer

        self.scene = slicer.vtkMRMLScene()
        self.application_logic = slicer.vtkSlicerApplicationLogic()
        self.application_logic.SetMRMLScene(self.scene)
        colors = self.application_logic.GetColorLogic()
        colors.SetMRMLScene(self.scene)
        colors.AddDefaultColorNodes()
        self.logics: dict[str, Any] = {}
        for name, logic_class in (("Markups", slicer.vtkSlicerMarkupsLogic),
                                  ("Transforms", slicer.vtkSlicerTransformLogic),
                                  ("Volumes", slicer.vtkSlicerVolumesLogic),
                                  ("Sequences", slicer.vtkSlicerSequencesLogic)):
            logic = logic_class()
            logic.SetMRMLApplicationLogic(self.application_logic)
            logic.SetMRMLScene(self.scene)
            self.application_logic.SetModuleLogic(name, logic)
            self.logics[name] = logic
        self._cache = tempfile.TemporaryDirectory(prefix="emreg-mrml-cache-")
        self.remote_io = slicer.vtkMRMLRemoteIOLogic()
        self.remote_io.SetMRMLScene(self.scene)
        self.remote_io.SetMRMLApplicationLogic(self.application_logic)
        self.remote_io.GetCacheManager().SetRemoteCacheDirectory(self._cache.name)
        self.data_io = slicer.vtkDataIOManagerLogic()
        self.data_io.SetMRMLScene(self.scene)
        self.data_io.SetMRMLApplicationLogic(self.application_logic)
        self.data_io.SetAndObserveDataIOManager(self.remote_io.GetDataIOManager())
        self.remote_io.AddDataIOToScene()
        #: The sha256 (hex) of the bundle :meth:`write_bundle` wrote last.
        self.bundle_sha256: str | None = None

    def read_bundle(self, path: str | os.PathLike[str]) -> None:
        """Import a scene bundle (``.mrb``) with Slicer's reader (``vtkMRMLScene::ReadFromMRB``)."""
        path = Path(path)
        if not path.is_file():
            raise EMRegError(f"{path}: scene bundle not found")
        if not self.scene.ReadFromMRB(str(path.resolve())):
            raise EMRegError(f"{path}: 3D Slicer could not read this scene bundle")

    def write_bundle(self, path: str | os.PathLike[str], stored: dict[str, StoredVoxels] | None = None) -> Path:
        """Write the scene as a bundle (``.mrb``: the ``.mrml`` scene and its data files, zipped) with
        Slicer's writer (``vtkMRMLScene::WriteToMRB``), atomically: built in a private folder beside
        ``path``, then renamed onto it. Its sha256 is then :attr:`bundle_sha256` (computed as it was written).

        ``stored``: volume node id -> :class:`StoredVoxels`, for volume nodes made by
        :func:`show_stored_volume` (a one-voxel placeholder with the CT's geometry): their entries get
        the voxels of that file, copied as it stores them (no decoding, no re-compression)."""
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        stored = stored or {}
        # Slicer's default storage nodes. Its single-threaded gzip of a CT is slow (450 MB of voxels: 10-41 s)
        # and its bundle writer copies the voxels to disk twice (the folder, then the zip). So each scalar
        # volume is saved by Slicer as a one-voxel placeholder of the same type and geometry, uncompressed,
        # and :func:`_zip_bundle` writes its NRRD entry from that header (true ``sizes``, ``encoding: gzip``)
        # and the node's voxels in memory, gzip-compressed by ISA-L on their way into the zip.
        volumes: dict[str, tuple[Any, Any]] = {}  # storage node id -> (volume node, its image data)
        sources: dict[str, Any] = {}  # storage node id -> where the entry's voxels come from
        fast_gzip = _isal_available()  # without it (3D Slicer's Python), Slicer's own compressed writer
        for node in self.nodes("vtkMRMLStorableNode"):
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
                self.scene.GetNodeByID(storage_id).UseCompressionOff()
                if not isinstance(sources[storage_id], StoredVoxels):
                    node.SetAndObserveImageData(_placeholder_like(data))
            self.scene.SetRootDirectory(str(work))
            saved = self.scene.SaveSceneToSlicerDataBundleDirectory(str(folder))
            for node, data in volumes.values():
                node.SetAndObserveImageData(data)
            if not saved or not folder.is_dir():
                raise EMRegError(f"{path}: 3D Slicer's writer could not write the scene bundle "
                                 "(disk full or no permission?)")
            self.bundle_sha256 = _zip_bundle(folder, staged, sources)
            os.replace(staged, path)
        except OSError as exc:  # a full disk, no permission: one line naming the bundle, as for every output
            raise _cannot_write(path, exc) from None
        finally:
            for storage_id, (node, data) in volumes.items():  # the scene as it was (Slicer's default: compressed)
                if node.GetImageData() is not data:
                    node.SetAndObserveImageData(data)
                self.scene.GetNodeByID(storage_id).UseCompressionOn()
            shutil.rmtree(work, ignore_errors=True)
        return path

    def nodes(self, class_name: str = "vtkMRMLNode") -> list[Any]:
        """The scene's nodes of a class (all nodes by default)."""
        collection = self.scene.GetNodesByClass(class_name)
        return [collection.GetItemAsObject(i) for i in range(collection.GetNumberOfItems())]

    def node(self, name: str) -> Any:
        """The first node of that name; a missing node raises :class:`EMRegError`."""
        found = self.scene.GetFirstNodeByName(name)
        if found is None:
            raise EMRegError(f"the scene has no node named {name!r}")
        return found


#: ISA-L's compression level for the CT in a bundle (0-3; 2: measured as small as Slicer's zlib level, ~10x faster).
BUNDLE_GZIP_LEVEL = 2
#: Bytes re-encoded at a time (bounded memory whatever the CT's size).
_CHUNK_BYTES = 16 << 20


def _placeholder_like(data: Any) -> Any:
    """A one-voxel ``vtkImageData`` of the scalar type and components of ``data`` (geometry is the node's)."""
    scalars = data.GetPointData().GetScalars()
    return _placeholder(scalars.GetDataType(), scalars.GetNumberOfComponents())


def _placeholder_of(dtype: np.dtype) -> Any:
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
        from .zip_store import FileRegion

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
    from isal import igzip_threaded

    return igzip_threaded.open(sink, "wb", compresslevel=BUNDLE_GZIP_LEVEL, threads=max(1, os.cpu_count() or 1))


def _spooled(voxels: _MemoryVoxels, scratch: Path) -> list[Any]:
    """``voxels.write_gzip`` into the file ``scratch``, as the one part of a zip entry."""
    from .zip_store import FileRegion

    with scratch.open("wb") as sink:
        voxels.write_gzip(sink)
    return [FileRegion(scratch, 0, scratch.stat().st_size)]


def stored_voxels(path: str | os.PathLike[str] | None) -> StoredVoxels | None:
    """The CT file's voxels as a bundle can copy them (a plain NRRD: attached raw or gzip data in the
    machine's byte order, see :func:`EMRegModule.io.fast_read.stored_nrrd_voxels`), or None (then the
    bundle needs the CT in memory: DICOM, MetaImage, NIfTI, other NRRD layouts)."""
    if path is None:
        return None
    from .fast_read import stored_nrrd_voxels

    found = stored_nrrd_voxels(Path(path))
    if found is None:
        return None
    geometry, dtype, offset, encoding = found
    if encoding == "raw" and not _isal_available():
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
    import re
    from urllib.parse import unquote

    from .zip_store import StoredZipWriter

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


def _isal_available() -> bool:
    try:
        from isal import isal_zlib  # noqa: F401
    except ImportError:
        return False
    return True


def _read_nrrd_header(entry: Any) -> bytes:
    """The header of an attached-data NRRD read from a binary stream, through its blank line (what was
    read, without that blank line, when the stream holds no such header)."""
    lines = []
    while True:
        line = entry.readline(1 << 16)
        lines.append(line)
        if not line.endswith(b"\n") or line in (b"\n", b"\r\n"):
            return b"".join(lines)


# --- nodes (usable on Slicer's application scene and on a SlicerScene's) -----------------------------


def _named_node(scene: Any, class_name: str, name: str, existing: Any = None) -> Any:
    if existing is not None and scene.GetNodeByID(existing.GetID()) is existing:
        return existing
    return scene.AddNewNodeByClass(class_name, name)


def vtk_matrix(matrix: Any) -> Any:
    """A ``vtkMatrix4x4`` holding a 4x4 array (what ``slicer.util.vtkMatrixFromArray`` makes; made here from
    ``vtkmodules`` so that writing a scene does not import the whole ``vtk`` package, 0.25 s)."""
    from vtkmodules.vtkCommonMath import vtkMatrix4x4

    values = np.asarray(matrix, dtype=float)
    if values.shape != (4, 4):
        raise EMRegError(f"a 4x4 matrix was expected, not {values.shape}")
    result = vtkMatrix4x4()
    result.DeepCopy([float(v) for v in values.ravel()])
    return result


def image_ijk_to_ras(image: Any) -> np.ndarray:
    """IJK-to-RAS 4x4 of a SimpleITK image (its index-to-LPS matrix, flipped to RAS)."""
    spacing = np.asarray(image.GetSpacing(), dtype=float)
    direction = np.asarray(image.GetDirection(), dtype=float).reshape(3, 3)
    ijk_to_lps = np.eye(4)
    ijk_to_lps[:3, :3] = direction * spacing
    ijk_to_lps[:3, 3] = image.GetOrigin()
    return LPS_TO_RAS @ ijk_to_lps


def show_volume(scene: Any, image: Any, name: str = VOLUME_NODE_NAME, node: Any = None,
                copy_voxels: bool = False) -> Any:
    """A SimpleITK scalar image as a scalar volume node (IJK-to-RAS from the image).

    By default the node's ``vtkImageData`` scalars wrap the image's voxel buffer without copying it
    (``numpy_support.numpy_to_vtk(deep=False)`` on ``sitk.GetArrayViewFromImage``); the image is kept
    alive by the VTK array for as long as the node holds it, and the voxels must not be changed through
    either while both are in use. ``copy_voxels`` gives the node its own copy instead (a scene where a
    user may edit the volume in place, as in 3D Slicer's application).
    """
    import SimpleITK as sitk
    import slicer.util

    if image.GetNumberOfComponentsPerPixel() != 1 or image.GetDimension() != 3:
        raise EMRegError("the CT must be a 3D scalar image to show it in 3D Slicer")
    node = _named_node(scene, "vtkMRMLScalarVolumeNode", name, node)
    node.SetIJKToRASMatrix(vtk_matrix(image_ijk_to_ras(image)))
    _ct_display(node)  # before the voxels: a display node made after them computes their histogram
    if copy_voxels:
        slicer.util.updateVolumeFromArray(node, sitk.GetArrayViewFromImage(image))
    else:
        node.SetAndObserveImageData(_image_data_sharing_voxels(image))
    return node


def _ct_display(node: Any) -> None:
    """The volume's display node with a fixed CT window (soft tissue to PVC and bone).

    Made while the node holds no voxels (or a placeholder): a display node created over a whole CT
    would first compute its automatic window from the CT's histogram (seconds for a full-frame scan)
    only to be overridden here."""
    node.CreateDefaultDisplayNodes()
    display = node.GetDisplayNode()
    if display is not None:
        display.AutoWindowLevelOff()
        display.SetWindowLevel(2000.0, 300.0)


def show_stored_volume(scene: Any, stored: StoredVoxels, name: str = VOLUME_NODE_NAME, node: Any = None) -> Any:
    """A scalar volume node for a CT kept in its file (:class:`StoredVoxels`), without its voxels in memory.

    The node has the CT's IJK-to-RAS and a one-voxel placeholder of its pixel type; pass
    ``{node.GetID(): stored}`` to :meth:`SlicerScene.write_bundle`, which writes the file's voxels
    into the bundle (3D Slicer then loads the whole CT from it)."""
    node = _named_node(scene, "vtkMRMLScalarVolumeNode", name, node)
    node.SetIJKToRASMatrix(vtk_matrix(image_ijk_to_ras(stored.geometry)))
    _ct_display(node)
    node.SetAndObserveImageData(_placeholder_of(stored.dtype))
    return node


def _image_data_sharing_voxels(image: Any) -> Any:
    """A ``vtkImageData`` (origin 0, spacing 1: Slicer keeps the geometry in IJK-to-RAS) whose scalars
    are the SimpleITK image's own voxel buffer, not a copy."""
    import SimpleITK as sitk
    from vtkmodules.util import numpy_support
    from vtkmodules.vtkCommonDataModel import vtkImageData

    voxels = sitk.GetArrayViewFromImage(image).reshape(-1)  # (k, j, i) C order = VTK's point order
    scalars = numpy_support.numpy_to_vtk(voxels, deep=False)  # keeps ``voxels`` alive, not the image
    # SimpleITK's view does not own its buffer: the image must live as long as the VTK array. A Python
    # attribute of a VTK object lives as long as its C++ object (VTK keeps the wrapper's dict), as
    # numpy_support's own ``_numpy_reference`` does.
    scalars._emreg_image = image
    scalars.SetName("ImageScalars")
    data = vtkImageData()
    data.SetDimensions(*(int(n) for n in image.GetSize()))
    data.GetPointData().SetScalars(scalars)
    return data


def show_points(scene: Any, name: str, labels: Sequence[str], positions: Any, color: Sequence[float],
                descriptions: Sequence[str] | None = None, node: Any = None,
                parent_transform: Any = None) -> Any:
    """A locked markups point list; ``positions`` (N, 3) in the node's own coordinates (RAS, or the
    parent transform's frame when ``parent_transform`` is given)."""
    from vtkmodules.vtkCommonDataModel import vtkVector3d

    node = _named_node(scene, "vtkMRMLMarkupsFiducialNode", name, node)
    node.RemoveAllControlPoints()
    positions = np.asarray(positions, dtype=float).reshape(-1, 3)
    texts = list(descriptions) if descriptions is not None else [""] * len(positions)
    if not (len(labels) == len(positions) == len(texts)):
        raise EMRegError(f"{name}: {len(labels)} labels, {len(positions)} positions, {len(texts)} descriptions")
    for label, position, text in zip(labels, positions, texts):  # noqa: B905 - lengths checked (Python 3.9 in old Slicer)
        index = node.AddControlPoint(vtkVector3d(*(float(v) for v in position)), str(label))
        if text:
            node.SetNthControlPointDescription(index, str(text))
    node.SetLocked(True)
    node.CreateDefaultDisplayNodes()
    display = node.GetDisplayNode()
    if display is not None:
        display.SetSelectedColor(*color)
        display.SetColor(*color)
    node.SetAndObserveTransformNodeID(parent_transform.GetID() if parent_transform is not None else None)
    return node


def show_curve(scene: Any, name: str, positions_ras: Any, color: Sequence[float] = (1.0, 0.8, 0.0),
               node: Any = None) -> Any:
    """A locked markups curve through ``positions_ras`` (N, 3), without labels."""
    import slicer.util

    node = _named_node(scene, "vtkMRMLMarkupsCurveNode", name, node)
    points = np.asarray(positions_ras, dtype=float).reshape(-1, 3)
    slicer.util.updateMarkupsControlPointsFromArray(node, points)
    for index in range(node.GetNumberOfControlPoints()):
        node.SetNthControlPointLabel(index, "")
    node.SetLocked(True)
    node.CreateDefaultDisplayNodes()
    display = node.GetDisplayNode()
    if display is not None:
        display.SetSelectedColor(*color)
        display.SetColor(*color)
        display.SetPointLabelsVisibility(False)
    return node


def show_transform(scene: Any, name: str, to_parent: Any, parent: Any = None, node: Any = None) -> Any:
    """A linear transform node with matrix ``to_parent`` (4x4), under ``parent`` (or the world)."""
    matrix = vtk_matrix(to_parent)
    node = _named_node(scene, "vtkMRMLLinearTransformNode", name, node)
    node.SetMatrixTransformToParent(matrix)
    node.SetAndObserveTransformNodeID(parent.GetID() if parent is not None else None)
    return node


def show_reference_to_image(scene: Any, reference_to_image: Any, node: Any = None) -> Any:
    """``ReferenceToImage`` (LPS) as the transform node ``ReferenceToImage`` = ReferenceToRAS."""
    return show_transform(scene, TRANSFORM_NODE_NAME, LPS_TO_RAS @ np.asarray(reference_to_image, dtype=float),
                          node=node)


def show_residual_spheres(scene: Any, centres_ras: Any, residuals_mm: Sequence[float], radius_mm: float = 4.0,
                          name: str = RESIDUALS_NODE_NAME, node: Any = None) -> Any:
    """A model of one sphere per paired marker, coloured by its registration residual (mm) with
    Slicer's built-in ``ReverseRainbow`` table (blue at 0 mm to red at the largest residual)."""
    from vtkmodules.util import numpy_support
    from vtkmodules.vtkFiltersCore import vtkAppendPolyData, vtkAssignAttribute
    from vtkmodules.vtkFiltersSources import vtkSphereSource

    append = vtkAppendPolyData()
    for centre, residual in zip(np.asarray(centres_ras, dtype=float).reshape(-1, 3), residuals_mm):  # noqa: B905
        sphere = vtkSphereSource()
        sphere.SetCenter(*centre)
        sphere.SetRadius(radius_mm)
        sphere.SetThetaResolution(16)
        sphere.SetPhiResolution(12)
        sphere.Update()
        polydata = sphere.GetOutput()
        values = numpy_support.numpy_to_vtk(np.full(polydata.GetNumberOfPoints(), float(residual)), deep=True)
        values.SetName("residual_mm")
        polydata.GetPointData().AddArray(values)
        append.AddInputData(polydata)
    append.Update()
    node = _named_node(scene, "vtkMRMLModelNode", name, node)
    node.SetAndObservePolyData(append.GetOutput())
    node.CreateDefaultDisplayNodes()
    display = node.GetDisplayNode()
    if display is not None:
        display.SetActiveScalar("residual_mm", vtkAssignAttribute.POINT_DATA)
        colors = scene.GetFirstNodeByName("ReverseRainbow")
        if colors is not None:
            display.SetAndObserveColorNodeID(colors.GetID())
        high = max([float(r) for r in residuals_mm] + [1e-3])
        display.SetScalarRangeFlag(display.UseManualScalarRange)
        display.SetScalarRange(0.0, high)
        display.SetScalarVisibility(True)
        display.SetOpacity(0.6)
    return node


def show_tre_map(scene: Any, path: str | os.PathLike[str], name: str = TRE_MAP_NODE_NAME, node: Any = None) -> Any:
    """The predicted-TRE map (a scalar NRRD in LPS, mm) read by Slicer's volume storage node, shown with the
    ``ReverseRainbow`` colours from 0 mm to its largest value."""
    import slicer

    node = _named_node(scene, "vtkMRMLScalarVolumeNode", name, node)
    storage = slicer.vtkMRMLVolumeArchetypeStorageNode()
    storage.SetFileName(str(path))
    storage.SetSingleFile(True)
    if not storage.ReadData(node):
        raise EMRegError(f"{path}: 3D Slicer could not read this volume")
    node.CreateDefaultDisplayNodes()
    display = node.GetDisplayNode()
    if display is not None:
        colors = scene.GetFirstNodeByName("ReverseRainbow")
        if colors is not None:
            display.SetAndObserveColorNodeID(colors.GetID())
        high = float(node.GetImageData().GetScalarRange()[1])
        display.AutoWindowLevelOff()
        display.SetWindowLevelMinMax(0.0, max(high, 1e-3))
    return node


# --- the scene of one run -------------------------------------------------------------------------


@dataclass
class RunScene:
    """What a run's scene shows, from its output files (all image-space positions LPS, mm)."""

    marker_ids: list[str] = field(default_factory=list)
    marker_origins: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    marker_axes: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    calibration_labels: list[str] = field(default_factory=list)
    calibration_points: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    registration: dict[str, Any] | None = None
    target_labels: list[str] = field(default_factory=list)
    targets: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    path: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    probe_to_reference: np.ndarray | None = None
    tip_to_probe: np.ndarray | None = None  # a tool's tip (frame_calibration.json's "tool"), None: the pinhole probe
    tre_map_path: Path | None = None
    image: Any = None
    stored_ct: StoredVoxels | None = None  # the CT in its file, copied into a bundle without being read
    notes: list[str] = field(default_factory=list)


def collect_run(out_dir: str | os.PathLike[str], case_dir: str | os.PathLike[str] | None = None,
                image: Any = None) -> RunScene:
    """Read a run's outputs (``markers.json``, ``frame_calibration.json``, ``registration.json``,
    ``navigation.csv``), the case's targets and its CT: when the CT that ``run.json`` names (per-stage
    outputs: the case's, :func:`~EMRegModule.io.case.run_ct_path`) is a plain NRRD (:func:`stored_voxels`)
    and ``image``, if given, has its grid, the file's stored voxels (a bundle copies them, nothing is read
    into memory); otherwise ``image``, else the CT read (of a DICOM folder, the series the markers were
    detected in, as ``markers.json`` / ``run.json`` name it, not the folder's default choice: the run may
    have forced another with ``--series``)."""
    from ..outputs import recorded_series_uid
    from .atomic import read_json

    out = Path(out_dir)
    run = read_json(out / "run.json", "run record") if (out / "run.json").is_file() else {}
    if case_dir is None and run.get("case"):
        case_dir = run["case"]
    content = RunScene(image=image)
    series = recorded_series_uid(run)
    if (out / "markers.json").is_file():
        detected = read_json(out / "markers.json", "markers JSON")
        series = recorded_series_uid(detected) or series  # the series whose space the markers are in
        markers = detected.get("markers", [])
        content.marker_ids = [str(m["id"]) for m in markers]
        content.marker_origins = np.array([m["origin"] for m in markers], dtype=float).reshape(-1, 3)
        content.marker_axes = np.array([m["axis"] for m in markers], dtype=float).reshape(-1, 3)
    if (out / "frame_calibration.json").is_file():
        document = read_json(out / "frame_calibration.json", "frame calibration JSON")
        tool = document.get("tool") if isinstance(document.get("tool"), dict) else None
        if tool is not None and tool.get("TipToProbe") is not None:
            content.tip_to_probe = np.asarray(tool["TipToProbe"], dtype=float).reshape(4, 4)
        points = document.get("points", [])
        content.calibration_labels = [str(p["label"]) for p in points]
        content.calibration_points = np.array([p["position"] for p in points], dtype=float).reshape(-1, 3)
    if (out / "registration.json").is_file():
        content.registration = read_json(out / "registration.json", "registration JSON")
    if (out / "navigation.csv").is_file():
        from .navigation_csv import read_navigation_csv

        content.path = read_navigation_csv(out / "navigation.csv")[0]
    if (out / TRE_MAP_FILE).is_file():
        content.tre_map_path = out / TRE_MAP_FILE
    if case_dir is not None:
        targets = Path(case_dir) / "targets.mrk.json"
        if targets.is_file():
            from .markups import read_markups

            labels, positions = read_markups(targets)
            content.target_labels, content.targets = list(labels), np.asarray(positions, dtype=float)
    from .case import run_ct_path

    ct = run_ct_path(run, case_dir)
    stored = stored_voxels(ct) if ct and Path(ct).is_file() else None
    if stored is not None and (image is None or _same_grid(stored.geometry, image)):
        content.stored_ct, content.image = stored, None
    elif content.image is None:
        if ct and Path(ct).exists():
            from .image import read_ct

            try:
                content.image = read_ct(ct, series)
            except EMRegError as exc:
                content.notes.append(f"CT not included ({exc})")
        elif not ct and run.get("fiducials"):
            content.notes.append("no CT: a fiducial case (the fiducials are in the scene)")
        else:
            content.notes.append("CT not included (run.json names no CT that exists)")
    return content


def _same_grid(geometry: Any, image: Any) -> bool:
    """True when a header reading (``sitk.ImageFileReader``) and an image have the same size, pixel type
    and physical grid."""
    return (tuple(geometry.GetSize()) == tuple(image.GetSize()) and geometry.GetPixelID() == image.GetPixelID()
            and np.allclose(geometry.GetSpacing(), image.GetSpacing(), rtol=0, atol=1e-9)
            and np.allclose(geometry.GetOrigin(), image.GetOrigin(), rtol=0, atol=1e-9)
            and np.allclose(geometry.GetDirection(), image.GetDirection(), rtol=0, atol=1e-12))


def bundle_needs_ct_image(ct_path: str | os.PathLike[str] | None) -> bool:
    """False when a bundle of a run on this CT copies the CT from its file (:func:`stored_voxels`), so that
    the CT need not be kept in memory for it."""
    return stored_voxels(ct_path) is None


def _pair_descriptions(content: RunScene) -> tuple[list[str], dict[str, tuple[str, float]]]:
    """Per marker: its pairing in words; and marker id -> (calibration label, residual)."""
    pairs: dict[str, tuple[str, float]] = {}
    if content.registration is not None:
        for pair in content.registration.get("pairs", []):
            pairs[str(pair["image_marker"])] = (str(pair["calibration_point"]), float(pair["residual_mm"]))
    texts = []
    for marker_id in content.marker_ids:
        if marker_id in pairs:
            label, residual = pairs[marker_id]
            texts.append(f"paired with calibration point {label}; residual {residual:.2f} mm")
        elif content.registration is not None:
            texts.append("unpaired (no calibration point matches it)")
        else:
            texts.append("not registered")
    return texts, pairs


def build_run_scene(scene: Any, content: RunScene, nodes: dict[str, Any] | None = None) -> dict[str, Any]:
    """Add a run's nodes to ``scene`` (a ``vtkMRMLScene``); returns them by name.

    CT volume; markers (origins, RAS; label = marker id, description = pairing and residual);
    ``ReferenceToImage`` (ReferenceToRAS) with the calibration points under it (Reference frame)
    and, when known, the probe pose ``ProbeToReference`` under it too, and a tool's ``TipToProbe`` under
    that (``TipToProbe`` alone without a probe pose); the pinhole points the
    calibration points are fitted to (``origin + l * axis``, RAS); spheres at them coloured by
    residual; targets; the probe path (curve, RAS); the predicted-TRE map when the run wrote one.

    ``nodes`` (name -> node) are reused and updated in place; those the content no longer has
    (e.g. the registration after a new CT) are removed from the scene, except the volume.
    """
    nodes = nodes if nodes is not None else {}
    built: dict[str, Any] = {}

    def keep(name: str, node: Any) -> Any:
        built[name] = nodes[name] = node
        return node

    if content.stored_ct is not None:
        keep(VOLUME_NODE_NAME, show_stored_volume(scene, content.stored_ct, node=nodes.get(VOLUME_NODE_NAME)))
    elif content.image is not None:
        keep(VOLUME_NODE_NAME, show_volume(scene, content.image, node=nodes.get(VOLUME_NODE_NAME)))
    texts, pairs = _pair_descriptions(content)
    if content.marker_ids:
        keep(MARKERS_NODE_NAME, show_points(scene, MARKERS_NODE_NAME, content.marker_ids,
                                            lps_to_ras_points(content.marker_origins), (0.2, 0.8, 0.3), texts,
                                            node=nodes.get(MARKERS_NODE_NAME)))
    transform = None
    if content.registration is not None:
        transform = keep(TRANSFORM_NODE_NAME, show_reference_to_image(
            scene, content.registration["ReferenceToImage"], node=nodes.get(TRANSFORM_NODE_NAME)))
        l_mm = float(content.registration["sensor_offset_l_mm"])
        index = {marker_id: k for k, marker_id in enumerate(content.marker_ids)}
        paired = [m for m in pairs if m in index]
        if paired:
            rows = [index[m] for m in paired]
            pinholes = lps_to_ras_points(content.marker_origins[rows] + l_mm * content.marker_axes[rows])
            keep(PINHOLES_NODE_NAME, show_points(
                scene, PINHOLES_NODE_NAME, paired, pinholes, (0.1, 0.6, 1.0),
                [f"pinhole point at l = {l_mm:.2f} mm of marker {m}; calibration point {pairs[m][0]}"
                 for m in paired], node=nodes.get(PINHOLES_NODE_NAME)))
            keep(RESIDUALS_NODE_NAME, show_residual_spheres(scene, pinholes, [pairs[m][1] for m in paired],
                                                            node=nodes.get(RESIDUALS_NODE_NAME)))
        fiducials = content.registration.get("fiducials")
        if isinstance(fiducials, dict) and fiducials.get("points"):  # a point fit: what the points were fitted onto
            _show_fiducials(scene, fiducials, pairs, keep, nodes)
        if content.probe_to_reference is not None:
            keep(PROBE_NODE_NAME, show_transform(scene, PROBE_NODE_NAME, content.probe_to_reference, transform,
                                                 node=nodes.get(PROBE_NODE_NAME)))
    if content.tip_to_probe is not None:  # tracker-side frames: the matrix as it is (as SlicerIGT's pivot writes it)
        keep(TIP_NODE_NAME, show_transform(scene, TIP_NODE_NAME, content.tip_to_probe, built.get(PROBE_NODE_NAME),
                                           node=nodes.get(TIP_NODE_NAME)))
    if content.calibration_labels:
        keep(CALIBRATION_NODE_NAME, show_points(scene, CALIBRATION_NODE_NAME, content.calibration_labels,
                                                content.calibration_points, (0.9, 0.2, 0.9),
                                                node=nodes.get(CALIBRATION_NODE_NAME), parent_transform=transform))
    if content.target_labels:
        keep(TARGETS_NODE_NAME, show_points(scene, TARGETS_NODE_NAME, content.target_labels,
                                            lps_to_ras_points(content.targets), (0.9, 0.1, 0.1),
                                            node=nodes.get(TARGETS_NODE_NAME)))
    if content.tre_map_path is not None:
        keep(TRE_MAP_NODE_NAME, show_tre_map(scene, content.tre_map_path, node=nodes.get(TRE_MAP_NODE_NAME)))
    if len(content.path):
        step = max(1, int(np.ceil(len(content.path) / MAX_PATH_POINTS)))
        keep(PATH_NODE_NAME, show_curve(scene, PATH_NODE_NAME, lps_to_ras_points(content.path[::step]),
                                        node=nodes.get(PATH_NODE_NAME)))
    for name in [n for n in nodes if n not in built and n != VOLUME_NODE_NAME]:
        stale = nodes.pop(name)
        if stale is not None and scene.GetNodeByID(stale.GetID()) is stale:
            scene.RemoveNode(stale)
    return built


def _show_fiducials(scene: Any, fiducials: dict[str, Any], pairs: dict[str, tuple[str, float]], keep: Any,
                    nodes: dict[str, Any]) -> None:
    """The fiducials of a point fit (``registration.json`` ``fiducials``: image space, LPS) as a point list (RAS),
    each described by its pair, with residual spheres at the paired ones."""
    labels = [str(p["label"]) for p in fiducials["points"]]
    positions = lps_to_ras_points(np.array([p["position"] for p in fiducials["points"]], dtype=float).reshape(-1, 3))
    texts = [f"fiducial of {Path(str(fiducials.get('file', ''))).name}; " + (
        f"paired with calibration point {pairs[m][0]}; residual {pairs[m][1]:.2f} mm" if m in pairs else "unpaired")
        for m in labels]
    keep(FIDUCIALS_NODE_NAME, show_points(scene, FIDUCIALS_NODE_NAME, labels, positions, (0.1, 0.6, 1.0), texts,
                                          node=nodes.get(FIDUCIALS_NODE_NAME)))
    paired = [k for k, m in enumerate(labels) if m in pairs]
    if paired:
        keep(RESIDUALS_NODE_NAME, show_residual_spheres(scene, positions[paired], [pairs[labels[k]][1] for k in paired],
                                                        node=nodes.get(RESIDUALS_NODE_NAME)))


def write_run_bundle(out_dir: str | os.PathLike[str], case_dir: str | os.PathLike[str] | None = None,
                     image: Any = None) -> tuple[Path | None, str]:
    """Write ``OUT/EMReg.mrb`` from a run's outputs; returns ``(path, message)``.

    Never raises for a bundle that cannot be made (Slicer's MRML missing, unreadable outputs,
    disk full, no permission): ``path`` is then ``None`` and ``message`` says why; the run's
    other outputs are untouched and a previous bundle is removed only when this one replaces it.
    """
    return write_run_bundle_hashed(out_dir, case_dir, image)[:2]


def write_run_bundle_hashed(out_dir: str | os.PathLike[str], case_dir: str | os.PathLike[str] | None = None,
                            image: Any = None, may_write: Callable[[], bool] | None = None
                            ) -> tuple[Path | None, str, str | None]:
    """:func:`write_run_bundle`, and the sha256 of the bundle written (None without one), computed as it was
    written (for ``run.json``: the bundle is not read again).

    ``may_write``: asked (once) before anything in OUT is written or removed; False: nothing is, and the
    message says the bundle was not wanted (a bundle process started ahead of its command's checks)."""
    out = Path(out_dir)
    allowed: list[bool] = []

    def allowed_to_write() -> bool:
        if not allowed:
            allowed.append(may_write is None or may_write())
        return allowed[0]

    unwanted = None, f"no {BUNDLE_FILE} written: not wanted any more", None

    def no_bundle(reason: str) -> tuple[None, str, None]:
        if allowed_to_write():
            _remove_stale_bundle(out)
            return None, f"no {BUNDLE_FILE} written: {reason}", None
        return unwanted

    vtk_imports_uninterrupted()  # the scene's nodes and writers load VTK modules
    missing = slicer_mrml_missing()
    if missing:
        return no_bundle(missing)
    try:
        content = collect_run(out, case_dir, image)
        if not content.marker_ids and not content.calibration_labels:
            return no_bundle(f"no markers or calibration in {out}")
        with signals_held():  # the modules its logics and nodes load: never cut, the signal acts once they are
            holder = SlicerScene()
            built = build_run_scene(holder.scene, content)
        stored = {built[VOLUME_NODE_NAME].GetID(): content.stored_ct} if content.stored_ct is not None else {}
        if not allowed_to_write():
            return unwanted
        path = holder.write_bundle(out / BUNDLE_FILE, stored)
    except (EMRegError, OSError, KeyError, ValueError, TypeError) as exc:
        return no_bundle(str(exc))
    notes = f" ({'; '.join(content.notes)})" if content.notes else ""
    return path, f"{path}{notes}", holder.bundle_sha256


class BundleProcess:
    """:func:`write_run_bundle` in a process of its own, started by :func:`start_bundle_process` so that it goes
    on while this one renders the report; :meth:`result` waits for it.

    The child imports slicer-core (not this process), writes ``OUT/EMReg.mrb`` atomically and hashes it as it
    writes it (sha256, for ``run.json``). Interrupting this process interrupts the child (no temporary left behind).

    ``held``: the child reads the outputs and builds the scene but writes nothing into OUT until
    :meth:`release` (its command has checked OUT and moved the stale bundle aside); a child never released (its
    command failed, or :meth:`cancel`) writes nothing. So the bundle's imports can start with the command,
    on a core its own start-up leaves idle.
    """

    def __init__(self, out_dir: Path, case_dir: Path | None, held: bool = False) -> None:
        import subprocess
        import sys

        package_root = str(Path(__file__).resolve().parents[2])  # the EMRegModule this process runs
        env = {**os.environ, "PYTHONPATH": os.pathsep.join(p for p in (package_root, os.environ.get("PYTHONPATH"))
                                                            if p)}
        command = [sys.executable, "-c", "from EMRegModule.io.slicer_scene import _bundle_child; _bundle_child()",
                   str(out_dir), str(case_dir) if case_dir is not None else "", "held" if held else ""]
        self.held = held
        self.process = subprocess.Popen(command, stdin=subprocess.PIPE if held else subprocess.DEVNULL,
                                        stdout=subprocess.PIPE, stderr=subprocess.PIPE, env=env)

    def release(self) -> None:
        """Let a held child write the bundle into OUT (nothing for a child not held)."""
        if self.held and self.process.stdin is not None and not self.process.stdin.closed:
            with contextlib.suppress(OSError):  # a child that died already: result() says why
                self.process.stdin.write(_GO)
                self.process.stdin.flush()  # (closed by result(), which must find it open)

    def result(self) -> tuple[Path | None, str, str | None]:
        """``(path, message, sha256 of the bundle)`` as :func:`write_run_bundle` gives them (path None: no
        bundle, and the message says why)."""
        import json

        try:
            stdout, stderr = self.process.communicate()
        except BaseException:
            self.cancel()
            raise
        try:
            answer = json.loads(stdout.decode("utf-8").strip().splitlines()[-1])
            path = Path(answer["path"]) if answer.get("path") else None
            return path, str(answer["message"]), answer.get("sha256")
        except (ValueError, IndexError, KeyError, TypeError):
            detail = stderr.decode("utf-8", "replace").strip().splitlines()
            return None, f"no {BUNDLE_FILE} written: its writer failed ({(detail or ['no output'])[-1][:200]})", None

    def cancel(self) -> None:
        """Interrupt the child (it removes its temporary files) and wait for it."""
        import signal
        import subprocess

        if self.process.stdin is not None and not self.process.stdin.closed:  # never released: it may not write
            with contextlib.suppress(OSError):
                self.process.stdin.close()
        if self.process.poll() is None:
            self.process.send_signal(signal.SIGINT)
            try:
                self.process.wait(timeout=30)
            except subprocess.TimeoutExpired:
                self.process.kill()
                self.process.wait()


def start_bundle_process(out_dir: str | os.PathLike[str], case_dir: str | os.PathLike[str] | None = None,
                         held: bool = False) -> BundleProcess | None:
    """Start writing ``OUT/EMReg.mrb`` in a separate process when it needs nothing from this one: Slicer's MRML
    is there and the run's CT is a file the bundle copies (:func:`stored_voxels`). None otherwise (write it
    with :func:`write_run_bundle`, with the CT in memory if needed). ``held``: see :class:`BundleProcess`."""
    import importlib.util

    from .atomic import read_json

    out = Path(out_dir)
    try:  # not imported here: slicer-core's libraries stay out of this process
        if importlib.util.find_spec("slicer") is None:
            return None
    except (ImportError, ValueError):
        return None
    try:
        from .case import run_ct_path

        ct = run_ct_path(read_json(out / "run.json", "run record"), case_dir)
    except (EMRegError, OSError, AttributeError):
        return None
    if not isinstance(ct, str) or bundle_needs_ct_image(ct):
        return None
    return BundleProcess(out, Path(case_dir) if case_dir is not None else None, held)


#: What a held bundle process waits for on its standard input before it writes into OUT.
_GO = b"go\n"


def _bundle_child() -> None:
    """The bundle process: ``write_run_bundle(OUT, CASE)``, then one JSON line: path, message, sha256.
    Held (third argument ``held``): nothing is written into OUT before ``go`` arrives on standard input."""
    import json
    import sys

    out, case = sys.argv[1], sys.argv[2] or None
    held = len(sys.argv) > 3 and sys.argv[3] == "held"
    with contextlib.suppress(OSError, AttributeError):
        os.nice(5)  # the report's CT read, which the report waits for, goes first on a busy machine

    def released() -> bool:
        return sys.stdin.buffer.readline() == _GO  # end of input (the command ended or gave up): no

    try:
        path, message, sha = write_run_bundle_hashed(out, case, may_write=released if held else None)
    except KeyboardInterrupt:
        sys.exit(130)
    except EMRegError as exc:
        path, message, sha = None, f"no {BUNDLE_FILE} written: {exc}", None
    print(json.dumps({"path": str(path) if path is not None else None, "message": message, "sha256": sha}))


def _remove_stale_bundle(out: Path) -> None:
    """A bundle of an earlier run beside this run's outputs would mislead: remove it (if it is a file)."""
    with contextlib.suppress(OSError):
        (out / BUNDLE_FILE).unlink()
