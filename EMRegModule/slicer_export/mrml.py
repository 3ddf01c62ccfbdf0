"""Slicer's MRML outside (or inside) 3D Slicer: whether it is there, and a scene with the module logics the
application registers for it (:class:`SlicerScene`)."""

from __future__ import annotations

import os
import tempfile
from pathlib import Path
from typing import Any

from ..errors import EMRegError
from ..interrupts import signals_held
from .mrb import StoredVoxels, write_mrb

#: How to get Slicer's MRML outside 3D Slicer.
INSTALL_HINT = "install the optional dependency with: pip install 'emreg[slicer]' (the slicer-core wheel)"


def slicer_mrml_missing() -> str | None:
    """Why Slicer's MRML cannot be used here (``None`` when it can).

    The import is never cut by Ctrl-C / SIGTERM (held, then delivered: :func:`~EMRegModule.interrupts.signals_held`):
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
        """Write the scene as a bundle (``.mrb``: the ``.mrml`` scene and its data files, zipped) atomically
        (:func:`~EMRegModule.slicer_export.mrb.write_mrb`); its sha256 is then :attr:`bundle_sha256`.

        ``stored``: volume node id -> :class:`~EMRegModule.slicer_export.mrb.StoredVoxels`, for volume nodes made
        by :func:`~EMRegModule.slicer_export.nodes.show_stored_volume`."""
        path = Path(path)
        self.bundle_sha256 = write_mrb(self.scene, path, stored or {})
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
