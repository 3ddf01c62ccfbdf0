"""The 3D Slicer module (EMRegModule/slicer/EMReg.py) on 3D Slicer's own MRML, without the application.

The ``slicer-core`` wheel (installed by scripts/setup) is 3D Slicer's MRML, storage nodes, module
logics and ``slicer.util`` without Qt. So:
- the Logic and the module's own self-test run on a real ``vtkMRMLScene`` (application, Markups,
  Transforms, Volumes and Sequences logics) and their nodes are checked numerically, through
  Slicer's transform hierarchy (``world=True``);
- every file EMReg writes for Slicer (``markers.mrk.json``, ``ReferenceToImage.h5``, ``EMReg.mrb``) is
  read back with Slicer's storage nodes / scene reader and compared with the JSON outputs;
- stand-ins remain only for what needs Qt and the application: the panel's widgets (built from the
  .ui file), ``slicer.ScriptedLoadableModule`` (Qt-based bases of the Module and Widget),
  ``slicer.util.loadUI`` / ``childWidgetVariables`` / ``tryWithErrorDisplay`` and ``qt`` (icon, URL);
- structure and source compatibility are checked from the source (ast).

Inside Slicer, run the module's own self-test from the Python console:
``slicer.util.selectModule("EMReg"); slicer.selfTests["EMReg"]()`` (or the module's "Reload and Test").
"""

from __future__ import annotations

import ast
import contextlib
import importlib.util
import logging
import os
import sys
import tempfile
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


# --- stand-ins for Qt only (names as in Slicer): the panel's widgets -------------------------------


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


class QCheckBox(FakeSignalWidget):
    signals = ("toggled(bool)",)

    def __init__(self, name, properties):
        super().__init__(name, properties)
        self.checked = properties.get("checked", False)


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


class qMRMLNodeComboBox(FakeSignalWidget):  # noqa: N801
    """A node selector: it lists the scene's nodes of ``nodeTypes`` once given the scene."""

    signals = ("currentNodeChanged(vtkMRMLNode*)",)

    def __init__(self, name, properties):
        super().__init__(name, properties)
        self.scene = None
        self._node = None

    def setMRMLScene(self, scene) -> None:
        self.scene = scene

    def currentNode(self):
        return self._node

    def setCurrentNode(self, node) -> None:
        assert self.scene is not None and (node is None or self.scene.IsNodePresent(node)), "a node of its scene"
        self._node = node
        self.emit("currentNodeChanged(vtkMRMLNode*)", node)


class qMRMLWidget(FakeSignalWidget):  # noqa: N801
    def __init__(self, name, properties):
        super().__init__(name, properties)
        self.scene = None

    def setMRMLScene(self, scene) -> None:
        self.scene = scene


WIDGET_CLASSES = {cls.__name__: cls for cls in (QPushButton, QSpinBox, QLabel, QCheckBox, QLineEdit, ctkPathLineEdit,
                                                ctkCollapsibleButton, qMRMLNodeComboBox, qMRMLWidget)}


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




# --- Slicer's MRML (slicer-core), with the Qt parts stood in ---------------------------------------


class FakeLayout:
    def __init__(self) -> None:
        self.widgets = []

    def addWidget(self, widget) -> None:
        self.widgets.append(widget)


class FakeScriptedLoadableModule:
    """Stand-in for Slicer's Qt-based module base: the parent is a qSlicerScriptedLoadableModule."""

    def __init__(self, parent) -> None:
        import slicer

        self.parent = parent
        self.moduleName = type(self).__name__
        parent.title = ""
        parent.categories = []
        parent.dependencies = []
        parent.contributors = []
        parent.helpText = ""
        parent.acknowledgementText = ""
        slicer.selfTests[self.moduleName] = self.runTest

    def runTest(self, msec=100, **kwargs) -> None:
        module = sys.modules[type(self).__module__]
        test = getattr(module, self.moduleName + "Test")()
        test.messageDelay = msec
        test.runTest(**kwargs)


class FakeScriptedLoadableModuleWidget:
    """Stand-in for Slicer's widget base (a Qt layout). ``made``: the panels made, for :meth:`SlicerHarness.close`."""

    made: list = []

    def __init__(self, parent=None) -> None:
        self.moduleName = type(self).__name__[: -len("Widget")]
        self.parent = parent or types.SimpleNamespace()
        self.layout = FakeLayout()
        FakeScriptedLoadableModuleWidget.made.append(self)

    def setup(self) -> None:
        pass


class FakeScriptedLoadableModuleLogic:
    def __init__(self, parent=None) -> None:
        self.moduleName = type(self).__name__[: -len("Logic")]


class FakeScriptedLoadableModuleTest(unittest.TestCase):
    def delayDisplay(self, message, requestedDelay=None, msec=None) -> None:
        logging.info("delayDisplay: %s", message)


class SlicerHarness:
    """A real MRML scene as ``slicer.mrmlScene`` (slicer-core); with ``application=True`` also stand-ins for
    the Qt parts of Slicer (``qt``, ``slicer.ScriptedLoadableModule``, the Qt helpers of ``slicer.util``)."""

    def __init__(self, monkeypatch, application: bool) -> None:
        import slicer
        import slicer.util

        from EMRegModule.slicer_export.mrml import SlicerScene

        self.mrml = SlicerScene()
        self.scene = self.mrml.scene
        self.errors: list[str] = []
        self.opened_urls: list[str] = []
        monkeypatch.setattr(slicer, "mrmlScene", self.scene, raising=False)
        monkeypatch.setattr(slicer, "selfTests", {}, raising=False)
        if application:
            qt = types.ModuleType("qt")
            qt.QIcon = lambda path: ("QIcon", path)
            qt.QUrl = types.SimpleNamespace(fromLocalFile=lambda path: f"file://{path}")
            qt.QDesktopServices = types.SimpleNamespace(openUrl=self.opened_urls.append)
            scripted = types.ModuleType("slicer.ScriptedLoadableModule")
            for cls in (FakeScriptedLoadableModule, FakeScriptedLoadableModuleWidget,
                        FakeScriptedLoadableModuleLogic, FakeScriptedLoadableModuleTest):
                setattr(scripted, cls.__name__[len("Fake"):], cls)
            monkeypatch.setitem(sys.modules, "qt", qt)
            monkeypatch.setitem(sys.modules, "slicer.ScriptedLoadableModule", scripted)
            monkeypatch.setattr(slicer.util, "loadUI", fake_load_ui)
            monkeypatch.setattr(slicer.util, "childWidgetVariables",
                                lambda widget: types.SimpleNamespace(**widget.children))
            monkeypatch.setattr(slicer.util, "tryWithErrorDisplay", self._try_with_error_display)
        else:  # plain Python with slicer-core: no qt, no ScriptedLoadableModule
            monkeypatch.setitem(sys.modules, "qt", None)
            monkeypatch.setitem(sys.modules, "slicer.ScriptedLoadableModule", None)
        monkeypatch.delitem(sys.modules, "EMReg", raising=False)
        monkeypatch.setattr(sys, "path", list(sys.path))  # the module inserts the repository root itself
        self.monkeypatch = monkeypatch

    @contextlib.contextmanager
    def _try_with_error_display(self, message=None, show=True, waitCursor=False):
        try:
            yield
        except Exception as exc:
            self.errors.append(f"{message} {exc}")
            raise

    def close(self) -> None:
        """What Slicer does when it closes: every panel made stops observing the scene (``cleanup``). Else the
        scene, collected later with the panel it is in a cycle with, calls the panel's handler while the collector
        takes the panel apart, in whatever test runs then (an AttributeError traceback on its stderr)."""
        for panel in FakeScriptedLoadableModuleWidget.made:
            if hasattr(panel, "cleanup"):
                panel.cleanup()
        FakeScriptedLoadableModuleWidget.made.clear()

    def load_module(self):
        spec = importlib.util.spec_from_file_location("EMReg", MODULE_FILE)
        module = importlib.util.module_from_spec(spec)
        self.monkeypatch.setitem(sys.modules, "EMReg", module)
        spec.loader.exec_module(module)
        return module


def _world_points(node) -> np.ndarray:
    import slicer.util

    return slicer.util.arrayFromMarkupsControlPoints(node, world=True)


def _labels(node) -> list[str]:
    return [node.GetNthControlPointLabel(i) for i in range(node.GetNumberOfControlPoints())]


def _ras(points_lps) -> np.ndarray:
    return np.asarray(points_lps, dtype=float).reshape(-1, 3) * np.array([-1.0, -1.0, 1.0])


def _navigation_csv(path: Path) -> np.ndarray:
    import csv

    with path.open(newline="") as handle:
        return np.array([[float(r["x_mm"]), float(r["y_mm"]), float(r["z_mm"])] for r in csv.DictReader(handle)])


def _check_volume_matches_ct(volume_node, ct_path: Path) -> None:
    """IJK-to-RAS and voxels of a volume node against the CT read by SimpleITK (LPS)."""
    import SimpleITK as sitk
    import slicer.util
    import vtk

    from EMRegModule.core.ct import index_to_physical_matrix
    from EMRegModule.io.image import read_ct

    image = read_ct(ct_path)
    matrix = vtk.vtkMatrix4x4()
    volume_node.GetIJKToRASMatrix(matrix)
    ijk_to_ras = slicer.util.arrayFromVTKMatrix(matrix)
    np.testing.assert_allclose(ijk_to_ras, np.diag([-1.0, -1.0, 1.0, 1.0]) @ index_to_physical_matrix(image),
                               atol=1e-6)
    voxels = slicer.util.arrayFromVolume(volume_node)
    assert voxels.shape == sitk.GetArrayViewFromImage(image).shape
    assert np.array_equal(voxels, sitk.GetArrayViewFromImage(image))


# --- the module's classes in (stood-in) Slicer -------------------------------------------------------


def test_module_description_icon_and_self_test_registration(slicer_app):
    module = slicer_app.load_module()
    parent = types.SimpleNamespace()
    description = module.EMReg(parent)
    import slicer

    assert parent.title == "EMReg" and parent.categories == ["IGT"]
    assert parent.icon == ("QIcon", str(ICON_FILE))
    assert "EMReg" in slicer.selfTests
    assert description.missingDependencies == []
    assert str(ROOT) in sys.path


def test_missing_dependency_is_named_in_the_log_and_the_panel(slicer_app, monkeypatch, caplog):
    module = slicer_app.load_module()
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


def test_first_load_in_slicer_installs_the_missing_packages_and_says_so(slicer_app, monkeypatch, caplog):
    """Inside the Slicer application (``slicer.app``), opening the panel pip-installs what is missing, once, with
    ``slicer.util.pip_install``; the log and the panel say so, and the workflow is enabled. Outside it (the other
    tests, slicer-core) nothing is installed."""
    import slicer
    import slicer.util

    module = slicer_app.load_module()
    absent = {"scipy", "pyvista"}
    real_find_spec = importlib.util.find_spec
    monkeypatch.setattr(module.importlib.util, "find_spec",
                        lambda name, *args: None if name in absent else real_find_spec(name, *args))
    installs = []

    def pip_install(requirements):
        installs.append(requirements)
        absent.clear()

    monkeypatch.setattr(slicer.util, "pip_install", pip_install)
    monkeypatch.setattr(slicer, "app", object(), raising=False)
    monkeypatch.setattr(module, "INSTALLED", [])
    with caplog.at_level(logging.WARNING):
        widget = module.EMRegWidget(parent=types.SimpleNamespace())
        widget.setup()
    assert installs == ["scipy pyvista"]
    assert "installing the Python packages" in caplog.text and "slicer.util.pip_install('scipy pyvista')" in caplog.text
    assert "installed with slicer.util.pip_install: scipy, pyvista" in widget.ui.dependenciesLabel.text
    assert widget.logic is not None and module.ensureEMRegImportable(install=True) == []
    assert installs == ["scipy pyvista"]  # nothing missing any more: not installed twice


def test_a_failed_install_names_what_is_still_missing(slicer_app, monkeypatch, caplog):
    import slicer
    import slicer.util

    module = slicer_app.load_module()
    real_find_spec = importlib.util.find_spec
    monkeypatch.setattr(module.importlib.util, "find_spec",
                        lambda name, *args: None if name == "scipy" else real_find_spec(name, *args))

    def offline(requirements):
        raise RuntimeError("no network")

    monkeypatch.setattr(slicer.util, "pip_install", offline)
    monkeypatch.setattr(slicer, "app", object(), raising=False)
    with caplog.at_level(logging.WARNING):
        missing = module.ensureEMRegImportable(install=True)
    assert [m[0] for m in missing] == ["scipy"]
    assert "installing scipy failed: no network" in caplog.text
    assert "slicer.util.pip_install('scipy')" in caplog.text


def test_the_built_extension_finds_the_package_and_resources_beside_the_module(tmp_path):
    """The extension's layout (``CMakeLists.txt``): EMReg.py with ``EMRegModule/`` and ``Resources/`` beside it."""
    import shutil

    (tmp_path / "EMRegModule").mkdir()
    shutil.copy(MODULE_FILE, tmp_path / "EMReg.py")
    source = (tmp_path / "EMReg.py").read_text(encoding="utf-8")
    namespace = {"__file__": str(tmp_path / "EMReg.py")}
    head = source[source.index("MODULE_DIR ="):source.index("if str(REPOSITORY_ROOT) not in sys.path")]
    exec("from pathlib import Path\n" + head, namespace)  # the layout lines only: no import of Slicer
    assert namespace["REPOSITORY_ROOT"] == tmp_path
    assert namespace["UI_FILE"] == tmp_path / "Resources" / "UI" / "EMReg.ui"


def test_the_extension_description_agrees_with_the_cmake_files_and_the_module():
    """``EMReg.s4ext`` (the Extensions Index), the top-level ``CMakeLists.txt`` (the build and the Extension
    Manager) and the module say the same, and the module's CMakeLists names files that exist."""
    import re

    s4ext = {}
    for line in (ROOT / "EMReg.s4ext").read_text(encoding="utf-8").splitlines():
        if line.strip() and not line.startswith("#"):
            key, _, value = line.partition(" ")
            s4ext[key] = value.strip()
    cmake = (ROOT / "CMakeLists.txt").read_text(encoding="utf-8")
    meta = dict(re.findall(r'^set\(EXTENSION_(\w+) "([^"]*)"', cmake, re.M))
    url = re.search(r'^set\(EMReg_REPOSITORY_URL "([^"]+)"', cmake, re.M).group(1)
    assert re.search(r"^project\(EMReg\)$", cmake, re.M) and "add_subdirectory(EMRegModule/slicer)" in cmake
    assert s4ext["description"] == meta["DESCRIPTION"] and s4ext["category"] == meta["CATEGORY"] == "IGT"
    assert s4ext["homepage"] == url and s4ext["scmurl"] == url + ".git" and s4ext["build_subdirectory"] == "."
    assert s4ext["iconurl"] == meta["ICONURL"].replace("${EMReg_REPOSITORY_URL}", url)
    assert s4ext["depends"] == meta["DEPENDS"] == "NA"
    module_cmake = (MODULE_DIR / "CMakeLists.txt").read_text(encoding="utf-8")
    assert "slicerMacroBuildScriptedModule(" in module_cmake and "set(MODULE_NAME EMReg)" in module_cmake
    for resource in ("Resources/Icons/${MODULE_NAME}.png", "Resources/UI/${MODULE_NAME}.ui"):
        assert resource in module_cmake and (ROOT / resource.replace("${MODULE_NAME}", "EMReg")).is_file()


def test_old_slicer_python_is_refused_with_the_supported_versions(slicer_app, monkeypatch, caplog):
    module = slicer_app.load_module()
    monkeypatch.setattr(module.sys, "version_info", (3, 9, 10, "final", 0))
    with caplog.at_level(logging.ERROR):
        missing = module.ensureEMRegImportable()
    assert missing and missing[0][0] == "python"
    assert "3D Slicer 5.10 or later" in caplog.text and "Python 3.9" in caplog.text
    widget = module.EMRegWidget(parent=types.SimpleNamespace())
    widget.setup()
    assert "3D Slicer 5.10 or later" in widget.ui.dependenciesLabel.text and widget.logic is None


def test_widget_wires_the_buttons_to_the_logic_on_real_mrml(slicer_app, standard_case, tmp_path):
    module = slicer_app.load_module()
    widget = module.EMRegWidget(parent=types.SimpleNamespace())
    widget.setup()
    ui = widget.ui
    assert not ui.calibrateButton.enabled and not ui.detectButton.enabled and not ui.registerButton.enabled
    with pytest.raises(Exception, match="choose a case folder"):
        ui.loadCaseButton.click()
    assert slicer_app.errors and "Loading the case failed." in slicer_app.errors[-1]

    ui.caseDirectoryPathLineEdit.currentPath = str(standard_case)
    ui.outputDirectoryPathLineEdit.currentPath = str(tmp_path / "out")
    ui.loadCaseButton.click()
    assert widget.logic.controller.inputs.image is not None
    assert slicer_app.scene.GetFirstNodeByName("EMReg CT").IsA("vtkMRMLScalarVolumeNode")
    assert ui.calibrateButton.enabled and ui.detectButton.enabled and not ui.registerButton.enabled
    assert (ui.referenceSensorSpinBox.value, ui.probeSensorSpinBox.value) == (1, 2)  # from case.toml

    ui.calibrateButton.click()
    ui.detectButton.click()
    assert ui.registerButton.enabled
    ui.registerButton.click()
    assert "paired and registered" in ui.statusLabel.text and "FRE" in ui.resultsLabel.text
    assert slicer_app.scene.GetFirstNodeByName("ReferenceToImage") is not None

    ui.probeSensorSpinBox.setValue(3)  # a port change drops the calibration and the registration, and their nodes
    assert widget.logic.controller.inputs.probe_sensor == 3
    assert slicer_app.scene.GetFirstNodeByName("ReferenceToImage") is None
    assert slicer_app.scene.GetFirstNodeByName("EMReg calibration points") is None
    assert slicer_app.scene.GetFirstNodeByName("EMReg markers") is not None  # detection stands
    ui.probeSensorSpinBox.setValue(2)
    ui.calibrateButton.click()
    ui.registerButton.click()
    ui.navigateButton.click()
    assert "TRE" in ui.resultsLabel.text
    assert (tmp_path / "out" / "navigation.csv").is_file() and (tmp_path / "out" / "evaluation.json").is_file()
    assert ui.reportButton.enabled

    # live navigation needs the SlicerOpenIGTLink extension's connector node, which core Slicer has not
    with pytest.raises(Exception, match="SlicerOpenIGTLink extension"):
        ui.connectButton.click()
    assert widget.logic.connectorNode is None and ui.connectButton.text == "Connect"

    widget.onSceneStartClose(None, None)
    widget.cleanup()


# --- the Logic and the self-test on slicer-core's MRML, no Qt ----------------------------------------


def test_module_imports_without_qt_and_says_what_needs_the_application(slicer_core):
    module = slicer_core.load_module()
    assert module.qt is None
    logic = module.EMRegLogic()
    assert logic.moduleName == "EMReg" and logic.scene is slicer_core.scene
    with pytest.raises(RuntimeError, match="needs the 3D Slicer application"):
        module.EMRegWidget()
    with pytest.raises(RuntimeError, match="needs the 3D Slicer application"):
        module.EMReg(types.SimpleNamespace())


def test_self_test_runs_on_slicer_core_mrml(slicer_core, standard_case, tmp_path, monkeypatch):
    """The module's own ScriptedLoadableModuleTest (simulated standard case, real controller, real MRML)."""
    module = slicer_core.load_module()
    module.EMRegTest.caseDirectory = str(standard_case)
    # the temporary directory of this test alone: another test session on the machine (or its own self-test)
    # would otherwise add or remove EMRegTest-* folders in the shared one while this one looks
    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))
    temporary = Path(tempfile.gettempdir())
    before = set(temporary.glob("EMRegTest-*"))
    try:
        result = unittest.TextTestRunner(stream=open(os.devnull, "w"), verbosity=0).run(  # noqa: SIM115
            module.EMRegTest("test_EMReg_simulated_case"))
    finally:
        module.EMRegTest.caseDirectory = None
    assert result.wasSuccessful(), [str(e) for _, e in result.failures + result.errors]
    assert set(temporary.glob("EMRegTest-*")) == before, "the self-test left its output folder behind"
    names = {slicer_core.scene.GetNthNode(i).GetName() for i in range(slicer_core.scene.GetNumberOfNodes())}
    assert {"EMReg CT", "EMReg markers", "EMReg calibration points", "ReferenceToImage", "EMReg targets",
            "EMReg probe path", "ProbeToReference", "EMReg pinhole points", "EMReg marker residuals"} <= names


def test_logic_end_to_end_on_a_real_mrml_scene(slicer_core, standard_case, tmp_path):
    """Every node the Logic makes, read back from Slicer's MRML and compared with EMReg's own outputs."""
    import json

    import slicer.util

    module = slicer_core.load_module()
    scene = slicer_core.scene
    logic = module.EMRegLogic()
    out = tmp_path / "out"
    logic.loadCase(str(standard_case), str(out))
    _check_volume_matches_ct(scene.GetFirstNodeByName("EMReg CT"), standard_case / "ct.nrrd")
    targets = json.loads((standard_case / "targets.mrk.json").read_text())
    assert targets["markups"][0]["coordinateSystem"] == "LPS"
    target_points = targets["markups"][0]["controlPoints"]
    target_node = scene.GetFirstNodeByName("EMReg targets")
    assert _labels(target_node) == [p["label"] for p in target_points]
    np.testing.assert_allclose(_world_points(target_node), _ras([p["position"] for p in target_points]), atol=1e-9)

    logic.calibrateFrame()
    logic.detectMarkers()
    logic.register()
    logic.navigateRecording()
    markers = json.loads((out / "markers.json").read_text())["markers"]
    registration = json.loads((out / "registration.json").read_text())
    calibration = json.loads((out / "frame_calibration.json").read_text())["points"]

    markers_node = scene.GetFirstNodeByName("EMReg markers")
    assert _labels(markers_node) == [m["id"] for m in markers]
    np.testing.assert_allclose(_world_points(markers_node), _ras([m["origin"] for m in markers]), atol=1e-4)
    pairs = {p["image_marker"]: p for p in registration["pairs"]}
    for index, marker in enumerate(markers):
        description = markers_node.GetNthControlPointDescription(index)
        if marker["id"] in pairs:
            assert f"calibration point {pairs[marker['id']]['calibration_point']}" in description
        else:
            assert "unpaired" in description

    transform = scene.GetFirstNodeByName("ReferenceToImage")
    reference_to_ras = slicer.util.arrayFromTransformMatrix(transform, toWorld=True)
    np.testing.assert_allclose(reference_to_ras, np.diag([-1.0, -1.0, 1.0, 1.0]) @ registration["ReferenceToImage"],
                               atol=1e-9)
    # calibration points (Reference frame) under ReferenceToImage land on their markers' pinhole points
    calibration_node = scene.GetFirstNodeByName("EMReg calibration points")
    assert calibration_node.GetTransformNodeID() == transform.GetID()
    np.testing.assert_allclose(slicer.util.arrayFromMarkupsControlPoints(calibration_node),
                               [p["position"] for p in calibration], atol=1e-9)  # stored as they are
    landed = dict(zip(_labels(calibration_node), _world_points(calibration_node), strict=True))
    by_id = {m["id"]: m for m in markers}
    l_mm = registration["sensor_offset_l_mm"]
    assert len(pairs) >= 10
    for marker_id, pair in pairs.items():
        marker = by_id[marker_id]
        pinhole_ras = _ras(np.add(marker["origin"], l_mm * np.asarray(marker["axis"])))[0]
        distance = np.linalg.norm(landed[pair["calibration_point"]] - pinhole_ras)
        assert distance == pytest.approx(pair["residual_mm"], abs=1e-4)
        assert distance < 1.0

    # the navigated probe pose (ProbeToReference from the recording) under ReferenceToImage lands where
    # navigation.csv says, and so does a point placed at the probe's origin under it
    navigation = _navigation_csv(out / "navigation.csv")
    probe = scene.GetFirstNodeByName("ProbeToReference")
    assert probe.GetTransformNodeID() == transform.GetID()
    np.testing.assert_allclose(slicer.util.arrayFromTransformMatrix(probe, toWorld=True)[:3, 3],
                               _ras(navigation[-1])[0], atol=1e-3)  # navigation.csv holds 4 decimals
    tip = scene.AddNewNodeByClass("vtkMRMLMarkupsFiducialNode", "probe origin")
    tip.AddControlPoint(0.0, 0.0, 0.0)
    tip.SetAndObserveTransformNodeID(probe.GetID())
    np.testing.assert_allclose(_world_points(tip)[0], _ras(navigation[-1])[0], atol=1e-3)
    path = scene.GetFirstNodeByName("EMReg probe path")
    assert path.IsA("vtkMRMLMarkupsCurveNode") and 2 <= path.GetNumberOfControlPoints() <= 1000
    np.testing.assert_allclose(_world_points(path)[0], _ras(navigation[0])[0], atol=1e-3)


def test_files_for_slicer_read_by_slicers_storage_nodes(slicer_core, run_output):
    """markers.mrk.json and ReferenceToImage.h5 of ``emreg run`` as Slicer's own readers see them."""
    import json

    import slicer
    import slicer.util

    _, out = run_output
    scene = slicer_core.scene
    markers = json.loads((out / "markers.json").read_text())["markers"]
    node = scene.AddNewNodeByClass("vtkMRMLMarkupsFiducialNode", "read")
    storage = scene.AddNewNodeByClass("vtkMRMLMarkupsJsonStorageNode")
    storage.SetFileName(str(out / "markers.mrk.json"))
    assert storage.ReadData(node) == 1
    assert _labels(node) == [m["id"] for m in markers]
    np.testing.assert_allclose(_world_points(node), _ras([m["origin"] for m in markers]), atol=1e-4)

    registration = json.loads((out / "registration.json").read_text())
    transform = scene.AddNewNodeByClass("vtkMRMLLinearTransformNode", "read")
    storage = scene.AddNewNodeByClass("vtkMRMLTransformStorageNode")
    storage.SetFileName(str(out / "ReferenceToImage.h5"))
    assert storage.ReadData(transform) == 1
    assert transform.IsLinear()
    np.testing.assert_allclose(slicer.util.arrayFromTransformMatrix(transform),
                               np.diag([-1.0, -1.0, 1.0, 1.0]) @ registration["ReferenceToImage"], atol=1e-6)


@pytest.mark.parametrize("name", ["ReferenceToImage.h5", "t.tfm", "t.txt"])
def test_itk_transform_files_load_in_slicer_as_reference_to_ras(slicer_core, tmp_path, name):
    """Each ITK transform format EMReg writes, read by Slicer's transform storage node: the node's matrix
    is ReferenceToRAS, and a Reference-frame point under it lands where ReferenceToImage puts it (RAS)."""
    import slicer.util
    from scipy.spatial.transform import Rotation

    from EMRegModule.io.itk_transform import write_slicer_linear_transform

    reference_to_image = np.eye(4)
    reference_to_image[:3, :3] = Rotation.from_euler("zyx", [31.0, -12.0, 74.0], degrees=True).as_matrix()
    reference_to_image[:3, 3] = [-41.5, 12.25, 160.0]
    write_slicer_linear_transform(tmp_path / name, reference_to_image)
    scene = slicer_core.scene
    transform = scene.AddNewNodeByClass("vtkMRMLLinearTransformNode", "read")
    storage = scene.AddNewNodeByClass("vtkMRMLTransformStorageNode")
    storage.SetFileName(str(tmp_path / name))
    assert storage.ReadData(transform) == 1
    np.testing.assert_allclose(slicer.util.arrayFromTransformMatrix(transform),
                               np.diag([-1.0, -1.0, 1.0, 1.0]) @ reference_to_image, atol=1e-9)
    point = scene.AddNewNodeByClass("vtkMRMLMarkupsFiducialNode", "p")
    point.AddControlPoint(10.0, -20.0, 30.0)
    point.SetAndObserveTransformNodeID(transform.GetID())
    expected = reference_to_image @ [10.0, -20.0, 30.0, 1.0]
    np.testing.assert_allclose(_world_points(point)[0], _ras(expected[:3])[0], atol=1e-9)


def test_live_navigation_without_openigtlinkif_says_what_to_install(slicer_core):
    module = slicer_core.load_module()
    logic = module.EMRegLogic()
    from EMRegModule.errors import EMRegError

    with pytest.raises(EMRegError, match="SlicerOpenIGTLink extension"):
        logic.startLiveNavigation("localhost", 18944)


# --- the scene bundle OUT/EMReg.mrb, imported with Slicer's reader ----------------------------------


@pytest.fixture(scope="module")
def run_output(standard_run):
    """``emreg run`` on the standard case (its summary lines and OUT): conftest's, made once, read only."""
    return standard_run.stdout, standard_run.out


def _import_bundle(path: Path):
    from EMRegModule.slicer_export.mrml import SlicerScene

    mrml = SlicerScene()
    mrml.read_bundle(path)
    return mrml


def test_run_writes_a_bundle_that_slicer_imports_matching_the_outputs(run_output, standard_case):
    import json
    import zipfile

    import slicer.util

    summary, out = run_output
    bundle = out / "EMReg.mrb"
    assert f"bundle: {bundle}" in summary
    with zipfile.ZipFile(bundle) as archive:  # a Slicer bundle: one folder with the .mrml scene and Data/
        names = archive.namelist()
    assert "EMReg/EMReg.mrml" in names and any(n.startswith("EMReg/Data/") and n.endswith(".h5") for n in names)
    mrml = _import_bundle(bundle)

    _check_volume_matches_ct(mrml.node("EMReg CT"), standard_case / "ct.nrrd")

    registration = json.loads((out / "registration.json").read_text())
    transform = mrml.node("ReferenceToImage")
    assert transform.GetTransformNodeID() is None
    np.testing.assert_allclose(slicer.util.arrayFromTransformMatrix(transform, toWorld=True),
                               np.diag([-1.0, -1.0, 1.0, 1.0]) @ registration["ReferenceToImage"], atol=1e-4)

    markers = json.loads((out / "markers.json").read_text())["markers"]
    markers_node = mrml.node("EMReg markers")
    assert _labels(markers_node) == [m["id"] for m in markers]
    np.testing.assert_allclose(_world_points(markers_node), _ras([m["origin"] for m in markers]), atol=1e-4)
    pairs = {p["image_marker"]: p for p in registration["pairs"]}
    for index, marker in enumerate(markers):
        text = markers_node.GetNthControlPointDescription(index)
        if marker["id"] in pairs:
            assert f"calibration point {pairs[marker['id']]['calibration_point']}" in text
            assert f"residual {pairs[marker['id']]['residual_mm']:.2f} mm" in text
        else:
            assert "unpaired" in text

    calibration_node = mrml.node("EMReg calibration points")
    assert calibration_node.GetTransformNodeID() == transform.GetID()
    landed = dict(zip(_labels(calibration_node), _world_points(calibration_node), strict=True))
    by_id = {m["id"]: m for m in markers}
    l_mm = registration["sensor_offset_l_mm"]
    pinholes = mrml.node("EMReg pinhole points")
    pinholes_ras = dict(zip(_labels(pinholes), _world_points(pinholes), strict=True))
    assert sorted(pinholes_ras) == sorted(pairs)
    for marker_id, pair in pairs.items():
        pinhole = _ras(np.add(by_id[marker_id]["origin"], l_mm * np.asarray(by_id[marker_id]["axis"])))[0]
        np.testing.assert_allclose(pinholes_ras[marker_id], pinhole, atol=1e-4)
        assert np.linalg.norm(landed[pair["calibration_point"]] - pinhole) == pytest.approx(pair["residual_mm"],
                                                                                          abs=1e-4)

    residuals = mrml.node("EMReg marker residuals")
    values = residuals.GetPolyData().GetPointData().GetArray("residual_mm")
    assert values is not None and values.GetRange()[1] == pytest.approx(max(p["residual_mm"] for p in pairs.values()),
                                                                         abs=1e-4)
    assert residuals.GetDisplayNode().GetScalarVisibility()
    assert residuals.GetDisplayNode().GetColorNode().GetName() == "ReverseRainbow"

    targets = json.loads((standard_case / "targets.mrk.json").read_text())["markups"][0]["controlPoints"]
    targets_node = mrml.node("EMReg targets")
    assert _labels(targets_node) == [t["label"] for t in targets]
    np.testing.assert_allclose(_world_points(targets_node), _ras([t["position"] for t in targets]), atol=1e-4)

    navigation = _navigation_csv(out / "navigation.csv")
    path = _world_points(mrml.node("EMReg probe path"))
    step = int(np.ceil(len(navigation) / 1000))
    np.testing.assert_allclose(path, _ras(navigation[::step]), atol=1e-4)


def test_bundle_volume_is_gzip_nrrd_holding_the_cts_voxels(run_output, standard_case):
    """The CT in the bundle is an attached gzip NRRD (Slicer's header; the case's ct.nrrd is a gzip NRRD, so
    its gzip stream is copied as it is, byte for byte): ``encoding: gzip``, the CT's sizes, its inflated
    bytes are the CT's voxels, and the scene keeps Slicer's default (compressed) for a re-save. (Slicer's
    import of the same bundle is checked above.)"""
    import gzip
    import re
    import zipfile

    import SimpleITK as sitk

    from EMRegModule.io.image import read_ct

    _, out = run_output
    with zipfile.ZipFile(out / "EMReg.mrb") as archive:
        entry = archive.getinfo("EMReg/Data/EMReg CT.nrrd")
        data = archive.read(entry)
        scene = archive.read("EMReg/EMReg.mrml").decode("utf-8")
    header, _, body = data.partition(b"\n\n")
    fields = dict(line.split(": ", 1) for line in header.decode("ascii").splitlines()[1:] if ": " in line)
    assert fields["encoding"] == "gzip" and fields["type"] == "short" and fields["endian"] == "little"
    image = read_ct(standard_case / "ct.nrrd")
    ct = sitk.GetArrayViewFromImage(image)  # a view: ``image`` must stay alive while it is used
    assert fields["sizes"].split() == [str(n) for n in ct.shape[::-1]]
    assert body[:2] == b"\x1f\x8b"  # a gzip stream
    voxels = np.frombuffer(gzip.decompress(body), dtype="<i2")
    assert np.array_equal(voxels, ct.astype("<i2").reshape(-1))
    assert len(body) < 0.8 * ct.nbytes  # compressed, not merely wrapped
    stored = (standard_case / "ct.nrrd").read_bytes()
    assert body == stored[stored.index(b"\n\n") + 2:]  # the case's own gzip stream: nothing compressed again
    storage = re.search(r'<VolumeArchetypeStorage\s[^>]*fileName="[^"]*EMReg%20CT\.nrrd"[^>]*>', scene) or \
        re.search(r'<VolumeArchetypeStorage\s[^>]*fileName="[^"]*EMReg CT\.nrrd"[^>]*>', scene)
    assert storage is not None and 'useCompression="1"' in storage.group(0)


@pytest.mark.parametrize("name, compress", [("ct.nrrd", True), ("ct.nrrd", False), ("ct.mha", True)])
def test_bundle_volume_from_the_file_or_from_memory_loads_in_slicer_with_the_cts_voxels(slicer_core, tmp_path,
                                                                                         name, compress):
    """A gzip NRRD's stream is copied, a raw NRRD's voxels too, as a raw entry (neither is read into memory: the
    node holds a one-voxel placeholder; neither is compressed again), any other CT is compressed from memory;
    Slicer's reader imports each bundle with the CT's geometry and voxels."""
    import zipfile

    import SimpleITK as sitk
    import slicer.util

    from EMRegModule.slicer_export.mrb import stored_voxels
    from EMRegModule.slicer_export.mrml import SlicerScene
    from EMRegModule.slicer_export.nodes import show_stored_volume, show_volume

    rng = np.random.default_rng(7)
    image = sitk.GetImageFromArray(rng.integers(-1000, 3000, size=(7, 9, 11)).astype(np.int16))
    image.SetSpacing((0.5, 0.6, 0.7))
    image.SetOrigin((10.0, -20.0, 30.0))
    image.SetDirection((0.0, 1.0, 0.0, -1.0, 0.0, 0.0, 0.0, 0.0, 1.0))
    ct = tmp_path / name
    sitk.WriteImage(image, str(ct), compress)
    stored = stored_voxels(ct)
    mrml = SlicerScene()
    if name.endswith(".nrrd"):
        assert stored is not None and stored.encoding == ("gzip" if compress else "raw")
        node = show_stored_volume(mrml.scene, stored)
        assert node.GetImageData().GetDimensions() == (1, 1, 1)  # the CT is not in memory
        mrml.write_bundle(tmp_path / "EMReg.mrb", {node.GetID(): stored})
    else:
        assert stored is None  # not a plain NRRD: the bundle compresses the CT from memory
        show_volume(mrml.scene, image)
        mrml.write_bundle(tmp_path / "EMReg.mrb")
    imported = SlicerScene()
    imported.read_bundle(tmp_path / "EMReg.mrb")
    volume = imported.node("EMReg CT")
    _check_volume_matches_ct(volume, ct)
    assert np.array_equal(slicer.util.arrayFromVolume(volume), sitk.GetArrayViewFromImage(image))
    assert volume.GetDisplayNode().GetWindow() == pytest.approx(2000.0)
    with zipfile.ZipFile(tmp_path / "EMReg.mrb") as archive:
        header, _, body = archive.read("EMReg/Data/EMReg CT.nrrd").partition(b"\n\n")
    encoding = "raw" if name.endswith(".nrrd") and not compress else "gzip"
    assert f"\nencoding: {encoding}\n" in header.decode("ascii") + "\n"
    if stored is not None:  # the file's own bytes
        assert body == ct.read_bytes()[stored.offset:]


def test_stored_voxels_only_for_plain_nrrd_in_the_machines_byte_order(tmp_path):
    """A big-endian NRRD, detached data or an .nhdr are read into memory for the bundle, never copied."""
    from EMRegModule.slicer_export.mrb import stored_voxels

    header = "NRRD0004\ntype: short\ndimension: 3\nsizes: 2 2 2\nencoding: raw\nendian: {}\n\n"
    little, big = tmp_path / "little.nrrd", tmp_path / "big.nrrd"
    little.write_bytes(header.format("little").encode() + bytes(16))
    big.write_bytes(header.format("big").encode() + bytes(16))
    assert stored_voxels(little) is not None and stored_voxels(little).offset == len(header.format("little"))
    assert stored_voxels(big) is None
    assert stored_voxels(tmp_path / "missing.nrrd") is None and stored_voxels(None) is None


def test_volume_node_shares_the_images_voxels_and_keeps_the_image_alive(slicer_core):
    import gc

    import SimpleITK as sitk
    import slicer.util

    from EMRegModule.slicer_export.mrml import SlicerScene
    from EMRegModule.slicer_export.nodes import show_volume

    voxels = np.arange(4 * 5 * 6, dtype=np.int16).reshape(4, 5, 6)
    image = sitk.GetImageFromArray(voxels)
    image.SetSpacing((0.5, 0.6, 0.7))
    image.SetOrigin((10.0, -20.0, 30.0))
    mrml = SlicerScene()
    node = show_volume(mrml.scene, image)
    assert np.shares_memory(slicer.util.arrayFromVolume(node), sitk.GetArrayViewFromImage(image))  # no copy
    del image
    gc.collect()
    sitk.GetImageFromArray(np.full((4, 5, 6), -1, dtype=np.int16))  # reuse freed memory, were it freed
    assert np.array_equal(slicer.util.arrayFromVolume(node), voxels)
    copied = show_volume(mrml.scene, sitk.GetImageFromArray(voxels), name="copy", copy_voxels=True)
    assert np.array_equal(slicer.util.arrayFromVolume(copied), voxels)


def test_report_batch_writes_one_bundle_per_case_and_an_unwritable_one_breaks_nothing(run_output, tmp_path, capsys):
    import hashlib
    import json
    import shutil

    import slicer.util

    from EMRegModule.cli.main import main

    _, out = run_output
    batch = tmp_path / "batch"
    for name in ("a", "b"):
        shutil.copytree(out, batch / name, ignore=shutil.ignore_patterns("EMReg.mrb", "report.html"))
    (batch / "b" / "EMReg.mrb").mkdir()  # cannot be replaced by a file: the bundle cannot be written
    assert main(["report", "--batch", str(batch), "--quiet"]) == 0
    captured = capsys.readouterr()
    assert f"bundle: {batch / 'a' / 'EMReg.mrb'}" in captured.out
    assert "emreg bundle: warning: no EMReg.mrb written" in captured.err and str(batch / "b") in captured.err
    for name in ("a", "b"):
        assert (batch / name / "report.html").is_file()
        assert json.loads((batch / name / "registration.json").read_text()) == json.loads(
            (out / "registration.json").read_text())
    assert (batch / "b" / "EMReg.mrb").is_dir() and not any(p.name.startswith(".EMReg") for p in
                                                             (batch / "b").iterdir())
    mrml = _import_bundle(batch / "a" / "EMReg.mrb")
    registration = json.loads((out / "registration.json").read_text())
    np.testing.assert_allclose(slicer.util.arrayFromTransformMatrix(mrml.node("ReferenceToImage")),
                               np.diag([-1.0, -1.0, 1.0, 1.0]) @ registration["ReferenceToImage"], atol=1e-4)
    recorded_a = json.loads((batch / "a" / "run.json").read_text())["outputs"]
    recorded_b = json.loads((batch / "b" / "run.json").read_text())["outputs"]
    assert recorded_a["EMReg.mrb"]["sha256"] == hashlib.sha256((batch / "a" / "EMReg.mrb").read_bytes()).hexdigest()
    assert recorded_a["EMReg.mrb"]["provenance"]["made_by"] == "emreg report --batch"
    assert "report.html" in recorded_a and "report.html" in recorded_b and "EMReg.mrb" not in recorded_b


def test_report_batch_with_a_failing_case_still_records_and_prints_the_others_bundles(run_output, tmp_path, capsys):
    import json
    import shutil

    from EMRegModule.cli.main import main

    _, out = run_output
    batch = tmp_path / "batch"
    for name in ("good", "bad"):
        shutil.copytree(out, batch / name, ignore=shutil.ignore_patterns("EMReg.mrb", "report.html"))
    (batch / "bad" / "report.html").mkdir()  # the page cannot be written there: this case fails
    assert main(["report", "--batch", str(batch), "--quiet"]) == 2
    captured = capsys.readouterr()
    assert f"bundle: {batch / 'good' / 'EMReg.mrb'}" in captured.out
    assert "1 of 2 reports failed" in captured.err and str(batch / "bad") in captured.err
    recorded = json.loads((batch / "good" / "run.json").read_text())["outputs"]
    assert "EMReg.mrb" in recorded and "report.html" in recorded
    assert not (batch / "bad" / "EMReg.mrb").exists()


def test_without_slicer_core_the_report_succeeds_and_says_why_no_bundle(run_output, tmp_path, monkeypatch, capsys):
    import shutil

    from EMRegModule.cli.main import main

    _, out = run_output
    copy = tmp_path / "out"
    shutil.copytree(out, copy, ignore=shutil.ignore_patterns("report.html"))
    assert (copy / "EMReg.mrb").is_file()  # an earlier bundle: gone once it cannot be renewed
    monkeypatch.setitem(sys.modules, "slicer", None)  # import slicer -> ImportError, as without the wheel
    assert main(["report", str(copy), "--quiet"]) == 0
    captured = capsys.readouterr()
    assert "no EMReg.mrb written" in captured.err and "pip install 'emreg[slicer]'" in captured.err
    assert (copy / "report.html").is_file() and not (copy / "EMReg.mrb").exists()


def test_report_writes_the_bundle_in_a_process_of_its_own_recorded_in_run_json(run_output, tmp_path, capsys):
    """``emreg report`` on a run whose CT is a gzip NRRD writes EMReg.mrb in a separate process while the
    report renders (slicer-core is never imported by the report's process); the bundle imports in Slicer
    with the CT's voxels, and run.json lists it with its true sha256."""
    import hashlib
    import json
    import shutil
    import subprocess

    _, out = run_output
    copy = tmp_path / "out"
    shutil.copytree(out, copy, ignore=shutil.ignore_patterns("report.html", "EMReg.mrb"))
    probe = ("import sys; from EMRegModule.cli.main import main; code = main(['report', sys.argv[1], '--quiet']); "
             "print('slicer imported:', 'slicer' in sys.modules); sys.exit(code)")
    done = subprocess.run([sys.executable, "-c", probe, str(copy)], capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr
    assert f"bundle: {copy / 'EMReg.mrb'}" in done.stdout and "slicer imported: False" in done.stdout
    recorded = json.loads((copy / "run.json").read_text())["outputs"]["EMReg.mrb"]
    assert recorded["sha256"] == hashlib.sha256((copy / "EMReg.mrb").read_bytes()).hexdigest()
    assert recorded["provenance"]["made_by"] == "emreg report"
    assert not any(p.name.startswith(".EMReg") for p in copy.iterdir())
    mrml = _import_bundle(copy / "EMReg.mrb")
    _check_volume_matches_ct(mrml.node("EMReg CT"), Path(json.loads((copy / "run.json").read_text())["ct"]))


def test_a_cold_report_of_per_stage_outputs_streams_the_case_ct_and_copies_it_into_the_bundle(small_case, tmp_path):
    """``emreg report OUT --case CASE`` over the outputs of the per-stage commands (their ``run.json`` names no CT)
    takes the case's CT as ``emreg run``'s report does: the CT is streamed and the bundle is written by a process of
    its own (slicer-core never imported by the report), with the case's gzip stream copied as it is (not the CT held
    whole and compressed again after the report); it imports in Slicer with the CT's voxels."""
    import json
    import subprocess
    import zipfile

    from EMRegModule.cli.main import main

    out = tmp_path / "out"
    for command in (["detect", str(small_case), "--out", str(out)],
                    ["calibrate", str(small_case / "calibration.csv"), "--out", str(out)],
                    ["register", "--markers", str(out / "markers.json"), "--calibration",
                     str(out / "frame_calibration.json"), "--out", str(out)]):
        assert main([*command, "--quiet"]) == 0
    assert "ct" not in json.loads((out / "run.json").read_text())
    probe = ("import sys; from EMRegModule.cli.main import main; "
             "code = main(['report', sys.argv[1], '--case', sys.argv[2], '--quiet']); "
             "print('slicer imported:', 'slicer' in sys.modules); sys.exit(code)")
    done = subprocess.run([sys.executable, "-c", probe, str(out), str(small_case)], capture_output=True, text=True,
                          timeout=600)
    assert done.returncode == 0, done.stderr
    assert f"bundle: {out / 'EMReg.mrb'}" in done.stdout and "slicer imported: False" in done.stdout
    with zipfile.ZipFile(out / "EMReg.mrb") as archive:
        body = archive.read("EMReg/Data/EMReg CT.nrrd").partition(b"\n\n")[2]
    stored = (small_case / "ct.nrrd").read_bytes()
    assert body == stored[stored.index(b"\n\n") + 2:]
    _check_volume_matches_ct(_import_bundle(out / "EMReg.mrb").node("EMReg CT"), small_case / "ct.nrrd")


# --- source compatibility with 3D Slicer's Python ---------------------------------------------------

#: Standard-library modules removed in Python 3.12 and 3.13 (3D Slicer 5.10 runs 3.12; later releases newer).
REMOVED_STDLIB = {"distutils", "imp", "asynchat", "asyncore", "smtpd", "aifc", "audioop", "cgi", "cgitb", "chunk",
                  "crypt", "imghdr", "mailcap", "msilib", "nis", "nntplib", "ossaudiodev", "pipes", "sndhdr", "spwd",
                  "sunau", "telnetlib", "uu", "xdrlib", "lib2to3"}
#: Provided by 3D Slicer itself (its Python packages and modules).
SLICER_PROVIDED = {"slicer", "qt", "ctk", "vtk", "vtkmodules", "numpy", "SimpleITK", "sitkUtils"}
#: Outside packages the module's code reaches but does without: isal (zlib instead), franky (the robot's driver,
#: the optional extra robot: the panel's Go refuses with one line naming "pip install 'emreg[robot]'").
OPTIONAL_WITH_FALLBACK = {"isal", "franky"}


def _module_file(name: str) -> Path | None:
    parts = name.split(".")
    if parts[0] != "EMRegModule":
        return None
    base = ROOT.joinpath(*parts)
    for candidate in (base.with_suffix(".py"), base / "__init__.py"):
        if candidate.is_file():
            return candidate
    return None


def _imports(path: Path) -> set[str]:
    """Absolute names of every module a file imports (top level and inside functions)."""
    package = ".".join(path.relative_to(ROOT).parent.parts)  # the package the file belongs to
    names = set()
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.Import):
            names.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")[: len(package.split(".")) - node.level + 1]
                module = ".".join(base + ([node.module] if node.module else []))
            else:
                module = node.module
            names.add(module)
            names.update(f"{module}.{alias.name}" for alias in node.names)  # submodules imported by name
    return names


def _modules_the_slicer_module_loads() -> tuple[set[Path], set[str]]:
    """Every EMRegModule file reachable from EMReg.py through its imports, and the outside top-level names."""
    files, outside, queue = set(), set(), [MODULE_FILE]
    while queue:
        path = queue.pop()
        if path in files:
            continue
        files.add(path)
        for name in _imports(path):
            if name.split(".")[0] == "EMRegModule":
                target = _module_file(name)
                if target is not None:
                    queue.append(target)
                parent = _module_file(name.rsplit(".", 1)[0]) if "." in name else None
                if parent is not None:  # "from .pkg import x" runs pkg/__init__.py
                    queue.append(parent)
            else:
                outside.add(name.split(".")[0])
    return files, outside


def test_everything_the_slicer_module_imports_runs_on_slicers_python():
    """EMReg needs Python 3.11 (tomllib, zip(strict=...)): 3D Slicer 5.10 or later (Python 3.12). Every file
    the module loads parses as 3.11, uses no standard module removed in 3.12/3.13, and every outside package
    is either shipped with Slicer or named by the module when missing (with its pip name)."""
    module = ast.parse(MODULE_FILE.read_text(encoding="utf-8"))
    declared = next(ast.literal_eval(node.value) for node in module.body if isinstance(node, ast.Assign)
                    and any(getattr(t, "id", "") == "DEPENDENCIES" for t in node.targets))
    minimum = next(ast.literal_eval(node.value) for node in module.body if isinstance(node, ast.Assign)
                   and any(getattr(t, "id", "") == "MINIMUM_PYTHON" for t in node.targets))
    assert minimum == (3, 11)
    files, outside = _modules_the_slicer_module_loads()
    assert len(files) > 30  # the controller, every stage, io, rendering, report...
    for path in files:
        ast.parse(path.read_text(encoding="utf-8"), feature_version=minimum)
    assert not outside & REMOVED_STDLIB
    third_party = {name for name in outside if name not in sys.stdlib_module_names} - SLICER_PROVIDED
    assert third_party <= set(declared) | OPTIONAL_WITH_FALLBACK, third_party - set(declared)


class FakeConnectorNode:
    """Stand-in for vtkMRMLIGTLConnectorNode of the SlicerOpenIGTLink extension (C++, not in slicer-core):
    the calls the Logic makes (``SetTypeClient``, ``Start`` returning 1 on success, ``Stop``)."""

    def __init__(self, name: str, starts: bool) -> None:
        self.name, self.starts, self.client, self.started = name, starts, None, False

    def GetID(self) -> str:
        return f"vtkMRMLIGTLConnectorNode_{self.name}"

    def SetTypeClient(self, host: str, port: int) -> None:
        self.client = (host, port)

    def Start(self) -> int:
        self.started = self.starts
        return 1 if self.starts else 0

    def Stop(self) -> None:
        self.started = False


class SceneWithOpenIGTLink:
    """The real MRML scene, which also knows the extension's connector node class (a stand-in)."""

    def __init__(self, scene, starts: bool = True) -> None:
        self._scene, self.starts, self.connectors = scene, starts, []

    def __getattr__(self, name):
        return getattr(self._scene, name)

    def AddNewNodeByClass(self, className, name=""):
        if className == "vtkMRMLIGTLConnectorNode":
            self.connectors.append(FakeConnectorNode(name, self.starts))
            return self.connectors[-1]
        return self._scene.AddNewNodeByClass(className, name)

    def RemoveNode(self, node) -> None:
        if isinstance(node, FakeConnectorNode):
            self.connectors.remove(node)
        else:
            self._scene.RemoveNode(node)


def test_live_navigation_connects_and_disconnects_openigtlinkif(slicer_core):
    from EMRegModule.errors import EMRegError

    module = slicer_core.load_module()
    scene = SceneWithOpenIGTLink(slicer_core.scene)
    logic = module.EMRegLogic(scene=scene)
    connector = logic.startLiveNavigation("navigation-pc", 18945)
    assert connector.client == ("navigation-pc", 18945) and connector.started and scene.connectors == [connector]
    assert connector.name == "EMReg OpenIGTLink"
    logic.stopLiveNavigation()
    assert not connector.started and scene.connectors == [] and logic.connectorNode is None

    refusing = module.EMRegLogic(scene=SceneWithOpenIGTLink(slicer_core.scene, starts=False))
    with pytest.raises(EMRegError, match="cannot connect to OpenIGTLink at localhost:18944"):
        refusing.startLiveNavigation()
    assert refusing.connectorNode is None and refusing.scene.connectors == []


def test_bundle_shows_the_predicted_tre_map_as_slicer_reads_it(run_output, tmp_path):
    """A run's ``tre_map.nrrd`` (float32, the CT's LPS origin and directions, coarse spacing) goes into the
    bundle as a volume; imported, its IJK-to-RAS and values match the file as SimpleITK reads it."""
    import json
    import shutil

    import SimpleITK as sitk
    import slicer.util
    import vtk

    from EMRegModule.core.ct import index_to_physical_matrix
    from EMRegModule.slicer_export.bundle import write_run_bundle

    _, out = run_output
    copy = tmp_path / "out"
    shutil.copytree(out, copy, ignore=shutil.ignore_patterns("EMReg.mrb", "report*"))
    if not (copy / "tre_map.nrrd").is_file():  # written by emreg run when the error model is available
        geometry = json.loads((copy / "markers.json").read_text())["image"]
        values = np.random.default_rng(5).uniform(0.3, 1.5, size=(17, 23, 29)).astype(np.float32)  # z, y, x
        tre_map = sitk.GetImageFromArray(values)
        tre_map.SetOrigin(geometry["origin"])
        tre_map.SetSpacing((4.5, 4.5, 4.5))
        tre_map.SetDirection(geometry["direction"])
        sitk.WriteImage(tre_map, str(copy / "tre_map.nrrd"))
    expected = sitk.ReadImage(str(copy / "tre_map.nrrd"))
    path, message, _ = write_run_bundle(copy)
    assert path == copy / "EMReg.mrb", message
    mrml = _import_bundle(path)  # keep the scene alive while its nodes are used
    node = mrml.node("EMReg predicted TRE (mm)")
    matrix = vtk.vtkMatrix4x4()
    node.GetIJKToRASMatrix(matrix)
    np.testing.assert_allclose(slicer.util.arrayFromVTKMatrix(matrix),
                               np.diag([-1.0, -1.0, 1.0, 1.0]) @ index_to_physical_matrix(expected), atol=1e-6)
    assert np.array_equal(slicer.util.arrayFromVolume(node), sitk.GetArrayViewFromImage(expected))
    assert node.GetDisplayNode().GetColorNode().GetName() == "ReverseRainbow"


def test_logic_pivot_calibrates_and_loads_a_tool(slicer_core, tmp_path):
    """The panel's tool row: a pivot recording calibrated into tool_calibration.json + TipToProbe.h5 and used; a
    PLUS device set's stylus tip; an empty path back to the pinhole probe."""
    from EMRegModule.io.sequence_metafile import write_sequence_metafile
    from EMRegModule.simulation.stylus import simulate_pivot_recording
    from EMRegModule.simulation.tracking import NoiseModel

    module = slicer_core.load_module()
    logic = module.EMRegLogic()
    recording, truth = simulate_pivot_recording(2, swing_deg=40.0, noise=NoiseModel(probe_dwell_deg=0.0))
    write_sequence_metafile(recording, tmp_path / "pivot.seq.mha")
    tool = logic.pivotCalibrate(str(tmp_path / "pivot.seq.mha"), str(tmp_path / "tool"))
    assert np.linalg.norm(tool.tip_mm - truth["tip_mm"]) < 0.5
    assert (tmp_path / "tool" / "tool_calibration.json").is_file() and (tmp_path / "tool" / "TipToProbe.h5").is_file()
    assert logic.controller.inputs.tool is tool
    device_set = Path(__file__).resolve().parents[1] / "Data" / "PlusLibData" / \
        "PlusDeviceSet_fCal_Sim_RecordPhantomLandmarks.xml"
    assert logic.loadTool(str(device_set)).name == "Stylus" and logic.controller.inputs.tool.name == "Stylus"
    logic.loadTool("")
    assert logic.controller.inputs.tool is None
