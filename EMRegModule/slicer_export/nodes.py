"""One MRML node per kind of EMReg result, on any scene (3D Slicer's application scene or a
:class:`~EMRegModule.slicer_export.mrml.SlicerScene`'s): the CT, point lists, curves, transforms, residual spheres
and the predicted-TRE map. Positions are given in the node's own coordinates (RAS unless under a transform);
the CT's geometry is converted from LPS here (:func:`image_ijk_to_ras`).
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from typing import Any

import numpy as np

from ..core.frames import LPS_TO_RAS
from ..core.plan import plan_from_points
from ..errors import EMRegError
from ..names import CONNECTOR_NODE_NAME, RESIDUALS_NODE_NAME, TRANSFORM_NODE_NAME, TRE_MAP_NODE_NAME, VOLUME_NODE_NAME
from .mrb import StoredVoxels, placeholder_of


def _named_node(scene: Any, class_name: str, name: str, existing: Any = None) -> Any:
    if existing is not None and scene.GetNodeByID(existing.GetID()) is existing:
        return existing
    return scene.AddNewNodeByClass(class_name, name)


def _model_node(scene: Any, name: str, polydata: Any, existing: Any = None) -> tuple[Any, Any]:
    """The model node ``name`` (``existing`` when still in the scene) showing ``polydata``, with its default display
    node; returns the node and that display node (None when Slicer made none)."""
    node = _named_node(scene, "vtkMRMLModelNode", name, existing)
    node.SetAndObservePolyData(polydata)
    node.CreateDefaultDisplayNodes()
    return node, node.GetDisplayNode()


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
    node.SetAndObserveImageData(placeholder_of(stored.dtype))
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
    _lock_and_colour(node, color)
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
    display = _lock_and_colour(node, color)
    if display is not None:
        display.SetPointLabelsVisibility(False)
    return node


def show_line(scene: Any, name: str, labels: Sequence[str], positions_ras: Any, color: Sequence[float],
              node: Any = None) -> Any:
    """A locked markups line between two points (RAS, mm; e.g. a plan's Entry and Target), labelled."""
    from vtkmodules.vtkCommonDataModel import vtkVector3d

    points = np.asarray(positions_ras, dtype=float).reshape(-1, 3)
    if len(points) != 2 or len(labels) != 2:
        raise EMRegError(f"{name}: a line needs two points and two labels, not {len(points)} and {len(labels)}")
    node = _named_node(scene, "vtkMRMLMarkupsLineNode", name, node)
    node.RemoveAllControlPoints()
    for label, point in zip(labels, points):  # noqa: B905 - lengths checked (Python 3.9 in old Slicer)
        node.AddControlPoint(vtkVector3d(*(float(v) for v in point)), str(label))
    _lock_and_colour(node, color)
    return node


def show_guide_model(scene: Any, name: str, parent: Any, depth_mm: float, body_mm: float = 40.0,
                     node: Any = None) -> Any:
    """A needle guide in its own frame (origin at its exit, +z the needle's direction), under ``parent`` (its pose):
    a tube ``body_mm`` long behind the exit (radius 4 mm) and the needle's axis ahead of it to ``depth_mm`` (a thin
    tube, radius 0.5 mm), so that the axis ends where a needle pushed to the planned depth would."""
    from vtkmodules.vtkFiltersCore import vtkAppendPolyData, vtkTubeFilter
    from vtkmodules.vtkFiltersSources import vtkLineSource

    append = vtkAppendPolyData()
    for start, end, radius in (((0.0, 0.0, -body_mm), (0.0, 0.0, 0.0), 4.0),
                               ((0.0, 0.0, 0.0), (0.0, 0.0, max(float(depth_mm), 1.0)), 0.5)):
        line = vtkLineSource()
        line.SetPoint1(*start)
        line.SetPoint2(*end)
        tube = vtkTubeFilter()
        tube.SetInputConnection(line.GetOutputPort())
        tube.SetRadius(radius)
        tube.SetNumberOfSides(24)
        tube.CappingOn()
        tube.Update()
        append.AddInputData(tube.GetOutput())
    append.Update()
    node, display = _model_node(scene, name, append.GetOutput(), node)
    if display is not None:
        display.SetColor(0.1, 0.8, 0.9)
    node.SetAndObserveTransformNodeID(parent.GetID() if parent is not None else None)
    return node


def _lock_and_colour(node: Any, color: Sequence[float]) -> Any:
    """Lock a markups node against edits and colour its points (selected or not); its display node (or None)."""
    node.SetLocked(True)
    node.CreateDefaultDisplayNodes()
    display = node.GetDisplayNode()
    if display is not None:
        display.SetSelectedColor(*color)
        display.SetColor(*color)
    return display


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
    node, display = _model_node(scene, name, append.GetOutput(), node)
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


def markups_points_lps(node: Any) -> tuple[list[str], np.ndarray]:
    """The defined control points of a markups node: labels (``F-<n>`` for an unnamed n-th point) and world
    positions (RAS, as Slicer shows them, through the transform hierarchy) in LPS, (N, 3) mm."""
    labels, positions = [], []
    for i in range(node.GetNumberOfControlPoints()):
        if node.GetNthControlPointPositionStatus(i) != node.PositionDefined:
            continue
        ras = [0.0, 0.0, 0.0]
        node.GetNthControlPointPositionWorld(i, ras)
        labels.append(node.GetNthControlPointLabel(i) or f"F-{i + 1}")
        positions.append([-ras[0], -ras[1], ras[2]])
    return labels, np.asarray(positions, dtype=float).reshape(-1, 3)


def plan_from_markups_node(node: Any) -> Any:
    """The :class:`~EMRegModule.core.guidance.Plan` (LPS mm) of a markups node as
    :func:`EMRegModule.io.plan_markups.read_plan` reads a
    file: a line node's two points (Entry, Target), else points labelled Entry and Target, or a single point."""

    labels, positions = markups_points_lps(node)
    is_line = node.IsA("vtkMRMLMarkupsLineNode")
    line = list(zip(labels, positions, strict=True)) if is_line else None
    return plan_from_points(labels, positions, line, f"markups node {node.GetName()}", "RAS (world)")


def connect_igtl_client(scene: Any, host: str, port: int, name: str = CONNECTOR_NODE_NAME) -> Any:
    """An OpenIGTLinkIF connector node connected as a client to ``host:port`` (an ``emreg navigate --igtl-port``
    server); :class:`EMRegError` without the SlicerOpenIGTLink extension or when nothing answers there."""
    try:
        connector = scene.AddNewNodeByClass("vtkMRMLIGTLConnectorNode", name)
    except Exception:  # noqa: BLE001 - Slicer raises a plain error for an unknown node class
        connector = None
    if connector is None:
        raise EMRegError("OpenIGTLinkIF is not available: install the SlicerOpenIGTLink extension "
                         "(Extensions Manager) for live navigation")
    connector.SetTypeClient(str(host), int(port))
    if connector.Start() != 1:
        scene.RemoveNode(connector)
        raise EMRegError(f"cannot connect to OpenIGTLink at {host}:{port}: start 'emreg navigate --igtl-port "
                         f"{port}' first")
    return connector
