"""The 3D Slicer module (EMRegModule/slicer/EMReg.py) without 3D Slicer.

Slicer cannot run here, so the module is checked three ways:
- structure: its four classes and their Slicer bases, parsed from the source (ast); the folder
  Slicer scans holds only the module file; the icon;
- the .ui file: valid Qt Designer XML whose widgets include every ``self.ui.<name>`` the code uses,
  with custom widgets declared;
- behaviour: the Widget, Logic and Test code paths run against the real controller and a real
  simulated case, with small fakes of ``slicer``, ``qt``, ``ctk`` and ``sitkUtils`` that follow
  Slicer's API names (``AddNewNodeByClass``, ``AddControlPoint(vtkVector3d, label)``,
  ``updateTransformMatrixFromArray``...). ``vtk`` is the real one.

Inside Slicer, run the module's own self-test from the Python console:
``slicer.util.selectModule("EMReg"); slicer.selfTests["EMReg"]()`` (or the module's "Reload and Test").
"""

from __future__ import annotations

import ast
import contextlib
import importlib.util
import logging
import sys
import types
import unittest
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[2]
MODULE_DIR = ROOT / "EMRegModule" / "slicer"
MODULE_FILE = MODULE_DIR / "EMReg.py"
UI_FILE = ROOT / "Resources" / "UI" / "EMReg.ui"
ICON_FILE = ROOT / "Resources" / "Icons" / "EMReg.png"

EXPECTED_BASES = {
    "EMReg": ["ScriptedLoadableModule"],
    "EMRegWidget": ["ScriptedLoadableModuleWidget", "VTKObservationMixin"],
    "EMRegLogic": ["ScriptedLoadableModuleLogic"],
    "EMRegTest": ["ScriptedLoadableModuleTest"],
}


# --- structure ------------------------------------------------------------------------------------


def _tree() -> ast.Module:
    return ast.parse(MODULE_FILE.read_text(encoding="utf-8"))


def _ui_names_used() -> set[str]:
    """Every ``self.ui.<name>`` attribute in the module source."""
    names = set()
    for node in ast.walk(_tree()):
        if isinstance(node, ast.Attribute) and isinstance(node.value, ast.Attribute) and node.value.attr == "ui" \
                and isinstance(node.value.value, ast.Name) and node.value.value.id == "self":
            names.add(node.attr)
    return names


def test_module_defines_the_four_slicer_classes_with_their_bases():
    classes = {node.name: [ast.unparse(b) for b in node.bases] for node in _tree().body
               if isinstance(node, ast.ClassDef)}
    assert classes == EXPECTED_BASES
    imported = {alias.name for node in ast.walk(_tree()) if isinstance(node, ast.ImportFrom)
                and node.module == "slicer.ScriptedLoadableModule" for alias in node.names}
    assert {"ScriptedLoadableModule", "ScriptedLoadableModuleWidget", "ScriptedLoadableModuleLogic",
            "ScriptedLoadableModuleTest"} <= imported


def test_module_folder_holds_only_the_module_file():
    """Slicer loads every .py file of an additional module path as a module: only EMReg.py may be there."""
    assert sorted(p.name for p in MODULE_DIR.glob("*.py")) == ["EMReg.py"]


def test_module_source_runs_on_slicers_python_39():
    """Slicer 5.6 ships Python 3.9: 3.9 syntax only, and no zip(strict=) (a 3.10 keyword)."""
    tree = ast.parse(MODULE_FILE.read_text(encoding="utf-8"), feature_version=(3, 9))
    assert not any(isinstance(node, ast.keyword) and node.arg == "strict" for node in ast.walk(tree))


def test_ui_file_is_qt_designer_xml_with_every_widget_the_code_uses():
    root = ET.parse(UI_FILE).getroot()
    assert root.tag == "ui" and root.get("version") == "4.0"
    assert root.findtext("class") == "EMReg"
    top = root.find("widget")
    assert top.get("class") == "qMRMLWidget" and top.get("name") == "EMReg"
    widgets = list(top.iter("widget"))
    names = [w.get("name") for w in widgets]
    assert len(names) == len(set(names)), "widget names must be unique"
    classes = {w.get("class") for w in widgets}
    declared = {c.findtext("class") for c in root.find("customwidgets")}
    assert {c for c in classes if not c.startswith("Q")} <= declared  # ctk/qMRML widgets are declared
    used = _ui_names_used()
    assert used, "the widget should use widgets from the .ui file"
    assert used <= set(names), f"widgets missing from EMReg.ui: {sorted(used - set(names))}"
    for button in ("calibrateButton", "detectButton", "registerButton", "navigateButton", "reportButton"):
        assert button in used


def test_icon_is_a_png():
    import cv2

    icon = cv2.imread(str(ICON_FILE), cv2.IMREAD_UNCHANGED)
    assert icon is not None and icon.shape[:2] == (128, 128)


# --- fakes of Slicer's Python API (names as in Slicer) --------------------------------------------


class FakeSignalWidget:
    """A Qt widget with properties and ``connect(signal, slot)``; ``emit`` plays a user action."""

    signals: tuple[str, ...] = ()

    def __init__(self, name: str, properties: dict) -> None:
        self.objectName = name
        self.enabled = properties.get("enabled", True)
        self.text = properties.get("text", "")
        self.toolTip = properties.get("toolTip", "")
        self._slots: dict[str, list] = {}

    def connect(self, signal: str, slot) -> None:
        if signal not in self.signals:
            raise AttributeError(f"{type(self).__name__} {self.objectName} has no signal {signal}")
        self._slots.setdefault(signal, []).append(slot)

    def emit(self, signal: str, *args) -> None:
        """Call the connected slots as PythonQt does: with as many of the signal's arguments as they take."""
        import inspect

        for slot in self._slots.get(signal, []):
            parameters = [p for p in inspect.signature(slot).parameters.values()
                          if p.kind in (p.POSITIONAL_ONLY, p.POSITIONAL_OR_KEYWORD)]
            slot(*args[: len(parameters)])


class QPushButton(FakeSignalWidget):
    signals = ("clicked(bool)", "clicked()", "toggled(bool)")

    def click(self) -> None:
        assert self.enabled, f"{self.objectName} is disabled"
        self.emit("clicked(bool)", False)


class QSpinBox(FakeSignalWidget):
    signals = ("valueChanged(int)",)

    def __init__(self, name, properties):
        super().__init__(name, properties)
        self.value = int(properties.get("value", 0))
        self.minimum = int(properties.get("minimum", 0))
        self.maximum = int(properties.get("maximum", 99))

    def setValue(self, value: int) -> None:
        self.value = max(self.minimum, min(self.maximum, int(value)))
        self.emit("valueChanged(int)", self.value)


class QLabel(FakeSignalWidget):
    pass


class QLineEdit(FakeSignalWidget):
    signals = ("textChanged(QString)",)


class ctkPathLineEdit(FakeSignalWidget):  # noqa: N801 - Slicer's class name
    signals = ("currentPathChanged(QString)",)

    def __init__(self, name, properties):
        super().__init__(name, properties)
        self.currentPath = ""


class ctkCollapsibleButton(FakeSignalWidget):  # noqa: N801
    signals = ("contentsCollapsed(bool)",)

    def __init__(self, name, properties):
        super().__init__(name, properties)
        self.collapsed = properties.get("collapsed", False)


class qMRMLWidget(FakeSignalWidget):  # noqa: N801
    def __init__(self, name, properties):
        super().__init__(name, properties)
        self.scene = None

    def setMRMLScene(self, scene) -> None:
        self.scene = scene


WIDGET_CLASSES = {cls.__name__: cls for cls in (QPushButton, QSpinBox, QLabel, QLineEdit, ctkPathLineEdit,
                                                ctkCollapsibleButton, qMRMLWidget)}


def _ui_properties(element: ET.Element) -> dict:
    properties = {}
    for prop in element.findall("property"):
        value = prop[0]
        if value.tag == "bool":
            properties[prop.get("name")] = value.text == "true"
        elif value.tag == "number":
            properties[prop.get("name")] = int(value.text)
        elif value.tag == "string":
            properties[prop.get("name")] = value.text or ""
    return properties


def fake_load_ui(path: str):
    """``slicer.util.loadUI``: one fake widget per named widget of the .ui file (unknown classes fail)."""
    root = ET.parse(path).getroot().find("widget")
    children = {}
    for element in root.iter("widget"):
        cls = WIDGET_CLASSES[element.get("class")]  # KeyError: a widget class this fake does not know
        children[element.get("name")] = cls(element.get("name"), _ui_properties(element))
    top = children[root.get("name")]
    top.children = children
    return top


class FakeDisplayNode:
    def __init__(self) -> None:
        self.selectedColor = None

    def SetSelectedColor(self, r, g, b) -> None:
        self.selectedColor = (r, g, b)


class FakeNode:
    """A vtkMRMLNode: ID, name, parent transform."""

    def __init__(self, className: str, node_id: str, name: str) -> None:
        self.className = className
        self._id = node_id
        self._name = name
        self._transform_id = None
        self._display = FakeDisplayNode()

    def GetID(self):
        return self._id

    def GetName(self):
        return self._name

    def GetClassName(self):
        return self.className

    def GetDisplayNode(self):
        return self._display

    def SetAndObserveTransformNodeID(self, node_id) -> None:
        self._transform_id = node_id

    def GetTransformNodeID(self):
        return self._transform_id


class FakeMarkupsNode(FakeNode):
    def __init__(self, *args) -> None:
        super().__init__(*args)
        self.points: list[tuple[list[float], str]] = []
        self.locked = False

    def AddControlPoint(self, point, label: str = "") -> int:
        xyz = [point.GetX(), point.GetY(), point.GetZ()] if hasattr(point, "GetX") else [float(v) for v in point]
        self.points.append((xyz, label))
        return len(self.points) - 1

    def RemoveAllControlPoints(self) -> None:
        self.points = []

    def GetNumberOfControlPoints(self) -> int:
        return len(self.points)

    def GetNthControlPointPosition(self, index: int, out) -> None:
        out[:] = self.points[index][0]

    def GetNthControlPointLabel(self, index: int) -> str:
        return self.points[index][1]

    def SetLocked(self, locked) -> None:
        self.locked = bool(locked)


class FakeLinearTransformNode(FakeNode):
    def __init__(self, *args) -> None:
        super().__init__(*args)
        import vtk

        self.matrix = vtk.vtkMatrix4x4()

    def SetMatrixTransformToParent(self, matrix) -> None:
        self.matrix.DeepCopy(matrix)

    def GetMatrixTransformToParent(self, out) -> None:
        out.DeepCopy(self.matrix)


class FakeVolumeNode(FakeNode):
    image = None


class FakeConnectorNode(FakeNode):
    def __init__(self, *args) -> None:
        super().__init__(*args)
        self.client = None
        self.started = False

    def SetTypeClient(self, host: str, port: int) -> None:
        self.client = (host, port)

    def Start(self) -> int:
        self.started = True
        return 1

    def Stop(self) -> None:
        self.started = False


NODE_CLASSES = {
    "vtkMRMLMarkupsFiducialNode": FakeMarkupsNode,
    "vtkMRMLMarkupsCurveNode": FakeMarkupsNode,
    "vtkMRMLLinearTransformNode": FakeLinearTransformNode,
    "vtkMRMLScalarVolumeNode": FakeVolumeNode,
}


class FakeScene:
    """``slicer.mrmlScene``: AddNewNodeByClass, GetNodeByID, GetFirstNodeByName, RemoveNode, Clear."""

    StartCloseEvent = 66000

    def __init__(self, with_openigtlink: bool = True) -> None:
        self.nodes: list[FakeNode] = []
        self.count = 0
        self.with_openigtlink = with_openigtlink

    def AddNewNodeByClass(self, className: str, name: str = ""):
        classes = dict(NODE_CLASSES)
        if self.with_openigtlink:
            classes["vtkMRMLIGTLConnectorNode"] = FakeConnectorNode
        if className not in classes:
            raise ValueError(f"AddNewNodeByClass: unknown node class {className}")  # as Slicer does
        self.count += 1
        node = classes[className](className, f"{className}{self.count}", name or className)
        self.nodes.append(node)
        return node

    def GetNodeByID(self, node_id):
        return next((n for n in self.nodes if n.GetID() == node_id), None)

    def GetFirstNodeByName(self, name):
        return next((n for n in self.nodes if n.GetName() == name), None)

    def GetNodesByClass(self, className):
        return [n for n in self.nodes if n.className == className]

    def RemoveNode(self, node) -> None:
        self.nodes = [n for n in self.nodes if n is not node]

    def Clear(self, removeViews: int = 0) -> None:
        self.nodes = []


class FakeSlicer:
    """Installs fake ``slicer``, ``slicer.util``, ``slicer.ScriptedLoadableModule``, ``qt``, ``ctk``, ``sitkUtils``."""

    def __init__(self, monkeypatch, with_openigtlink: bool = True) -> None:
        self.scene = FakeScene(with_openigtlink)
        self.errors: list[str] = []
        self.opened_urls: list[str] = []
        self.layers = None
        slicer = types.ModuleType("slicer")
        slicer.mrmlScene = self.scene
        slicer.selfTests = {}
        util = types.ModuleType("slicer.util")
        util.loadUI = fake_load_ui
        util.childWidgetVariables = lambda widget: types.SimpleNamespace(**widget.children)
        util.tryWithErrorDisplay = self._try_with_error_display
        util.errorDisplay = lambda message, **kwargs: self.errors.append(message)
        util.delayDisplay = lambda message, msec=None: logging.info("delayDisplay: %s", message)
        util.setSliceViewerLayers = self._set_slice_viewer_layers
        util.updateTransformMatrixFromArray = _update_transform_matrix_from_array
        util.arrayFromTransformMatrix = _array_from_transform_matrix
        util.VTKObservationMixin = FakeVTKObservationMixin
        slicer.util = util
        scripted = types.ModuleType("slicer.ScriptedLoadableModule")
        for cls in (FakeScriptedLoadableModule, FakeScriptedLoadableModuleWidget, FakeScriptedLoadableModuleLogic,
                    FakeScriptedLoadableModuleTest):
            setattr(scripted, cls.__name__[len("Fake"):], cls)
        slicer.ScriptedLoadableModule = scripted
        qt = types.ModuleType("qt")
        qt.QIcon = lambda path: ("QIcon", path)
        qt.QUrl = types.SimpleNamespace(fromLocalFile=lambda path: f"file://{path}")
        qt.QDesktopServices = types.SimpleNamespace(openUrl=self.opened_urls.append)
        sitk_utils = types.ModuleType("sitkUtils")
        sitk_utils.PushVolumeToSlicer = self._push_volume
        for name, module in (("slicer", slicer), ("slicer.util", util), ("slicer.ScriptedLoadableModule", scripted),
                             ("qt", qt), ("ctk", types.ModuleType("ctk")), ("sitkUtils", sitk_utils)):
            monkeypatch.setitem(sys.modules, name, module)
        monkeypatch.delitem(sys.modules, "EMReg", raising=False)
        monkeypatch.setattr(sys, "path", list(sys.path))  # the module inserts the repository root itself
        self.monkeypatch = monkeypatch
        self.slicer = slicer

    @contextlib.contextmanager
    def _try_with_error_display(self, message=None, show=True, waitCursor=False):
        try:
            yield
        except Exception as exc:
            self.errors.append(f"{message} {exc}")
            raise

    def _set_slice_viewer_layers(self, background=None, fit=False, **kwargs):
        self.layers = (background, fit)

    def _push_volume(self, sitkimage, targetNode=None, name=None, className="vtkMRMLScalarVolumeNode"):
        node = targetNode or self.scene.AddNewNodeByClass(className, name)
        node.image = sitkimage
        return node

    def load_module(self):
        spec = importlib.util.spec_from_file_location("EMReg", MODULE_FILE)
        module = importlib.util.module_from_spec(spec)
        self.monkeypatch.setitem(sys.modules, "EMReg", module)
        spec.loader.exec_module(module)
        return module


def _update_transform_matrix_from_array(node, narray) -> None:
    import vtk

    matrix = vtk.vtkMatrix4x4()
    for i in range(4):
        for j in range(4):
            matrix.SetElement(i, j, float(narray[i][j]))
    node.SetMatrixTransformToParent(matrix)


def _array_from_transform_matrix(node, toWorld=False) -> np.ndarray:
    import vtk

    matrix = vtk.vtkMatrix4x4()
    node.GetMatrixTransformToParent(matrix)
    return np.array([[matrix.GetElement(i, j) for j in range(4)] for i in range(4)])


class FakeVTKObservationMixin:
    def __init__(self) -> None:
        self.Observations = []

    def addObserver(self, obj, event, method, group="none", priority=0.0) -> None:
        self.Observations.append((obj, event, method))

    def removeObservers(self, method=None) -> None:
        self.Observations = []


class FakeLayout:
    def __init__(self) -> None:
        self.widgets = []

    def addWidget(self, widget) -> None:
        self.widgets.append(widget)


class FakeScriptedLoadableModule:
    def __init__(self, parent) -> None:
        self.parent = parent
        self.moduleName = type(self).__name__
        parent.title = ""
        parent.categories = []
        parent.dependencies = []
        parent.contributors = []
        parent.helpText = ""
        parent.acknowledgementText = ""
        sys.modules["slicer"].selfTests[self.moduleName] = self.runTest

    def runTest(self, msec=100, **kwargs) -> None:
        module = sys.modules[type(self).__module__]
        test = getattr(module, self.moduleName + "Test")()
        test.messageDelay = msec
        test.runTest(**kwargs)


class FakeScriptedLoadableModuleWidget:
    def __init__(self, parent=None) -> None:
        self.moduleName = type(self).__name__[: -len("Widget")]
        self.parent = parent or types.SimpleNamespace()
        self.layout = FakeLayout()

    def setup(self) -> None:
        pass


class FakeScriptedLoadableModuleLogic:
    def __init__(self, parent=None) -> None:
        self.moduleName = type(self).__name__[: -len("Logic")]


class FakeScriptedLoadableModuleTest(unittest.TestCase):
    def __init__(self, *args, **kwargs) -> None:
        super().__init__(*args, **kwargs)

    def delayDisplay(self, message, requestedDelay=None, msec=None) -> None:
        sys.modules["slicer"].util.delayDisplay(message, msec)


# --- behaviour -------------------------------------------------------------------------------------


@pytest.fixture
def fake_slicer(monkeypatch):
    return FakeSlicer(monkeypatch)


def test_module_description_icon_and_self_test_registration(fake_slicer):
    module = fake_slicer.load_module()
    parent = types.SimpleNamespace()
    description = module.EMReg(parent)
    assert parent.title == "EMReg" and parent.categories == ["IGT"]
    assert parent.icon == ("QIcon", str(ICON_FILE))
    assert "EMReg" in fake_slicer.slicer.selfTests
    assert description.missingDependencies == []
    assert str(ROOT) in sys.path


def test_missing_dependency_is_named_in_the_log_and_the_panel(fake_slicer, monkeypatch, caplog):
    module = fake_slicer.load_module()
    real_find_spec = importlib.util.find_spec
    monkeypatch.setattr(module.importlib.util, "find_spec",
                        lambda name, *args: None if name in ("scipy", "pyvista") else real_find_spec(name, *args))
    with caplog.at_level(logging.WARNING):
        missing = module.ensureEMRegImportable()
    assert [m[0] for m in missing] == ["scipy", "pyvista"]
    assert "Python package 'scipy' is missing" in caplog.text and "slicer.util.pip_install('scipy')" in caplog.text
    assert any(r.levelno == logging.ERROR and "scipy" in r.getMessage() for r in caplog.records)
    widget = module.EMRegWidget(parent=types.SimpleNamespace())
    widget.setup()
    assert "scipy" in widget.ui.dependenciesLabel.text and "pyvista" in widget.ui.dependenciesLabel.text
    assert widget.ui.workflowCollapsibleButton.enabled is False and widget.logic is None


def test_self_test_runs_the_logic_end_to_end(fake_slicer, standard_case):
    """The module's own ScriptedLoadableModuleTest, on the simulated standard case, through the real controller."""
    module = fake_slicer.load_module()
    module.EMRegTest.caseDirectory = str(standard_case)
    try:
        module.EMReg(types.SimpleNamespace())
        fake_slicer.slicer.selfTests["EMReg"]()
    finally:
        module.EMRegTest.caseDirectory = None
    scene = fake_slicer.scene
    names = {n.GetName() for n in scene.nodes}
    assert {"EMReg CT", "EMReg markers", "EMReg calibration points", "ReferenceToImage", "EMReg targets",
            "EMReg probe path"} <= names
    calibration = scene.GetFirstNodeByName("EMReg calibration points")
    transform = scene.GetFirstNodeByName("ReferenceToImage")
    assert calibration.GetTransformNodeID() == transform.GetID()  # Reference coordinates under ReferenceToImage


def test_widget_wires_the_buttons_to_the_controller(fake_slicer, standard_case, tmp_path):
    from EMRegModule.simulation import load_truth
    from EMRegModule.transforms import LPS_TO_RAS, apply_transform

    module = fake_slicer.load_module()
    widget = module.EMRegWidget(parent=types.SimpleNamespace())
    widget.setup()
    ui = widget.ui
    assert not ui.calibrateButton.enabled and not ui.detectButton.enabled and not ui.registerButton.enabled
    with pytest.raises(Exception, match="choose a case folder"):
        ui.loadCaseButton.click()
    assert fake_slicer.errors and "Loading the case failed." in fake_slicer.errors[-1]

    ui.caseDirectoryPathLineEdit.currentPath = str(standard_case)
    ui.outputDirectoryPathLineEdit.currentPath = str(tmp_path / "out")
    ui.loadCaseButton.click()
    assert widget.logic.controller.image is not None
    assert fake_slicer.layers[0] is fake_slicer.scene.GetFirstNodeByName("EMReg CT")
    assert ui.calibrateButton.enabled and ui.detectButton.enabled and not ui.registerButton.enabled
    assert (ui.referenceSensorSpinBox.value, ui.probeSensorSpinBox.value) == (1, 2)  # from case.toml

    ui.probeSensorSpinBox.setValue(3)  # a port change drops the calibration, like in the controller
    assert widget.logic.controller.probe_sensor == 3
    ui.probeSensorSpinBox.setValue(2)

    ui.calibrateButton.click()
    ui.detectButton.click()
    assert ui.registerButton.enabled
    ui.registerButton.click()
    controller = widget.logic.controller
    assert "paired and registered" in ui.statusLabel.text and "FRE" in ui.resultsLabel.text

    # MRML content: markers in RAS, ReferenceToImage as LPS_TO_RAS @ ReferenceToImage
    markers = fake_slicer.scene.GetFirstNodeByName("EMReg markers")
    assert markers.GetNumberOfControlPoints() == len(controller.detection.markers)
    for (xyz, label), marker in zip(markers.points, controller.detection.markers, strict=True):
        assert label == marker.id
        assert np.allclose(xyz, marker.origin * np.array([-1.0, -1.0, 1.0]))
    matrix = _array_from_transform_matrix(fake_slicer.scene.GetFirstNodeByName("ReferenceToImage"))
    assert np.allclose(matrix, LPS_TO_RAS @ controller.reference_to_image)
    # a calibration point (Reference frame) under the transform lands on its marker's sensor point (RAS)
    truth = load_truth(standard_case)
    calibration = fake_slicer.scene.GetFirstNodeByName("EMReg calibration points")
    point_ras = apply_transform(matrix, calibration.points[0][0])
    true_point = apply_transform(np.asarray(truth["ReferenceToImage"]), calibration.points[0][0])
    assert np.linalg.norm(point_ras - true_point * np.array([-1.0, -1.0, 1.0])) < 1.0

    ui.navigateButton.click()
    assert "TRE" in ui.resultsLabel.text
    assert (tmp_path / "out" / "navigation.csv").is_file() and (tmp_path / "out" / "evaluation.json").is_file()
    assert ui.reportButton.enabled

    ui.connectButton.click()  # live navigation: an OpenIGTLinkIF client to emreg navigate --igtl-port
    connector = widget.logic.connectorNode
    assert connector.client == ("localhost", 18944) and connector.started and ui.connectButton.text == "Disconnect"
    ui.connectButton.click()
    assert widget.logic.connectorNode is None and not connector.started

    widget.onSceneStartClose(None, None)
    widget.cleanup()


def test_live_navigation_without_openigtlinkif_says_what_to_install(monkeypatch):
    fake = FakeSlicer(monkeypatch, with_openigtlink=False)
    module = fake.load_module()
    logic = module.EMRegLogic()
    from EMRegModule.errors import EMRegError

    with pytest.raises(EMRegError, match="SlicerOpenIGTLink extension"):
        logic.startLiveNavigation("localhost", 18944)
