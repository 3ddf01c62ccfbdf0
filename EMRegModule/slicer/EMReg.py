"""EMReg: automatic patient-to-image registration for EM navigation, as a 3D Slicer scripted module.

Load it by adding this folder (``<repository>/EMRegModule/slicer``) to Slicer's additional
module paths (Edit > Application Settings > Modules); nothing needs to be pip-installed into
Slicer for the module to load. The module puts the repository root on ``sys.path`` itself
and names, in Slicer's log and in its panel, every Python package that is missing.

Layout (Slicer's scripted-module template): ``EMReg`` (module description), ``EMRegWidget``
(loads ``Resources/UI/EMReg.ui`` of the repository and only wires its buttons),
``EMRegLogic`` (the very controller the ``emreg`` command uses,
:class:`EMRegModule.controller.EMRegController`, plus the MRML nodes that show its results)
and ``EMRegTest`` (drives the Logic end to end on a simulated case).

Coordinates: EMReg works in the CT's LPS space, Slicer in RAS. Markers and targets are
converted point by point (x, y negated). ``ReferenceToImage`` becomes the linear transform
node ``ReferenceToImage`` whose matrix is ``LPS_TO_RAS @ ReferenceToImage``: a node placed
under it holds Reference-frame coordinates as they are (the calibration points node does),
the same convention as the live ``ProbeToImage`` stream (the probe frame unchanged, the
image side in RAS).
"""

import importlib.util
import logging
import os
import sys
from pathlib import Path

import qt
import slicer
import vtk
from slicer.ScriptedLoadableModule import (
    ScriptedLoadableModule,
    ScriptedLoadableModuleLogic,
    ScriptedLoadableModuleTest,
    ScriptedLoadableModuleWidget,
)
from slicer.util import VTKObservationMixin

MODULE_DIR = Path(__file__).resolve().parent
REPOSITORY_ROOT = MODULE_DIR.parents[1]
UI_FILE = REPOSITORY_ROOT / "Resources" / "UI" / "EMReg.ui"
ICON_FILE = REPOSITORY_ROOT / "Resources" / "Icons" / "EMReg.png"

#: Python packages EMReg needs: import name -> (pip name, what needs it).
DEPENDENCIES = {
    "numpy": ("numpy", "everything"),
    "scipy": ("scipy", "detection, calibration, registration"),
    "SimpleITK": ("SimpleITK", "reading the CT and detection"),
    "vtk": ("vtk", "marker models and detection"),
    "pyvista": ("pyvista", "the verification report"),
    "cv2": ("opencv-python-headless", "the verification report"),
    "pyigtl": ("pyigtl", "live navigation from the command line"),
}
#: Without these the workflow cannot run at all; the others only disable one feature.
ESSENTIAL = ("numpy", "scipy", "SimpleITK", "vtk")

LPS_TO_RAS_DIAGONAL = (-1.0, -1.0, 1.0)


def ensureEMRegImportable():
    """Put the repository root on ``sys.path``; return the missing dependencies (logged clearly).

    Returns a list of ``(import name, pip name, what needs it)`` for every package that is absent.
    """
    root = str(REPOSITORY_ROOT)
    if root not in sys.path:
        sys.path.insert(0, root)
    missing = []
    for module, (pip_name, needed_by) in DEPENDENCIES.items():
        if importlib.util.find_spec(module) is None:
            missing.append((module, pip_name, needed_by))
    if importlib.util.find_spec("EMRegModule") is None:
        logging.error("EMReg: the EMRegModule package was not found under %s; keep this module file inside the "
                      "EMReg repository (EMRegModule/slicer/EMReg.py)", root)
    for module, pip_name, needed_by in missing:
        level = logging.ERROR if module in ESSENTIAL else logging.WARNING
        logging.log(level, "EMReg: Python package '%s' is missing (needed for %s). Install it from Slicer's Python "
                           "console with: slicer.util.pip_install('%s')", module, needed_by, pip_name)
    return missing


def lpsToRas(point):
    """A point (3 numbers) from LPS to RAS (and back: the same flip)."""
    return [float(point[0]) * -1.0, float(point[1]) * -1.0, float(point[2])]


#
# EMReg
#


class EMReg(ScriptedLoadableModule):
    """Module description (title, category, help) for Slicer's module list."""

    def __init__(self, parent):
        ScriptedLoadableModule.__init__(self, parent)
        self.parent.title = "EMReg"
        self.parent.categories = ["IGT"]
        self.parent.dependencies = []
        self.parent.contributors = ["EMReg developers"]
        self.parent.helpText = (
            "Automatic patient-to-image registration for electromagnetic navigation (trakSTAR reference sensor in a "
            "fiducial frame with PVC markers, probe sensor put into each marker's pinhole, CT of the frame). Load a "
            "case folder, then calibrate the frame, detect the markers, pair and register, navigate and write the "
            "verification report. The same workflow runs on the command line as 'emreg run CASE --out OUT'."
        )
        self.parent.acknowledgementText = (
            "After Lin, Yang, Dai, Chen and Cai, 'Automatic registration method using EM sensors in the IoT "
            "operating room' (2020)."
        )
        if ICON_FILE.is_file():
            self.parent.icon = qt.QIcon(str(ICON_FILE))
        self.missingDependencies = ensureEMRegImportable()


#
# EMRegWidget
#


class EMRegWidget(ScriptedLoadableModuleWidget, VTKObservationMixin):
    """The panel: loads ``Resources/UI/EMReg.ui`` and wires its buttons to the Logic; no work here."""

    def __init__(self, parent=None):
        ScriptedLoadableModuleWidget.__init__(self, parent)
        VTKObservationMixin.__init__(self)
        self.logic = None
        self.ui = None

    def setup(self):
        ScriptedLoadableModuleWidget.setup(self)
        uiWidget = slicer.util.loadUI(str(UI_FILE))
        self.layout.addWidget(uiWidget)
        self.ui = slicer.util.childWidgetVariables(uiWidget)
        uiWidget.setMRMLScene(slicer.mrmlScene)

        missing = ensureEMRegImportable()
        if missing:
            self.ui.dependenciesLabel.text = "Missing Python packages: " + ", ".join(
                f"{module} (slicer.util.pip_install('{pip}'), for {needed})" for module, pip, needed in missing)
        else:
            self.ui.dependenciesLabel.text = "All Python packages found."
        if any(module in ESSENTIAL for module, _, _ in missing):
            self.ui.workflowCollapsibleButton.enabled = False
            self.ui.statusLabel.text = "EMReg cannot run: see the missing packages below and Slicer's log."
            return

        self.logic = EMRegLogic()
        self.addObserver(slicer.mrmlScene, slicer.mrmlScene.StartCloseEvent, self.onSceneStartClose)

        self.ui.loadCaseButton.connect("clicked(bool)", self.onLoadCase)
        self.ui.referenceSensorSpinBox.connect("valueChanged(int)", self.onSensorsChanged)
        self.ui.probeSensorSpinBox.connect("valueChanged(int)", self.onSensorsChanged)
        self.ui.calibrateButton.connect("clicked(bool)", self.onCalibrate)
        self.ui.detectButton.connect("clicked(bool)", self.onDetect)
        self.ui.registerButton.connect("clicked(bool)", self.onRegister)
        self.ui.navigateButton.connect("clicked(bool)", self.onNavigate)
        self.ui.reportButton.connect("clicked(bool)", self.onReport)
        self.ui.runAllButton.connect("clicked(bool)", self.onRunAll)
        self.ui.connectButton.connect("clicked(bool)", self.onConnectLive)
        self.updateGUIFromLogic()

    def cleanup(self):
        self.removeObservers()
        if self.logic is not None:
            self.logic.stopLiveNavigation()

    def onSceneStartClose(self, caller, event):
        if self.logic is not None:
            self.logic.forgetNodes()
        self.updateGUIFromLogic()

    # --- buttons: each one calls the Logic and refreshes the panel ---------------------------------

    def _run(self, errorMessage, function, *args):
        """Call the Logic; an error is shown to the user (and logged), and the panel is refreshed either way."""
        try:
            with slicer.util.tryWithErrorDisplay(errorMessage, waitCursor=True):
                function(*args)
        finally:
            self.updateGUIFromLogic()

    def onLoadCase(self):
        output = self.ui.outputDirectoryPathLineEdit.currentPath or None
        self._run("Loading the case failed.", self.logic.loadCase, self.ui.caseDirectoryPathLineEdit.currentPath,
                  output)
        # the case's ports (case.toml [sensors]) show in the panel; changing them afterwards re-runs calibration
        self.ui.referenceSensorSpinBox.value = self.logic.controller.reference_sensor
        self.ui.probeSensorSpinBox.value = self.logic.controller.probe_sensor

    def onSensorsChanged(self, value=None):
        self.logic.setSensors(self.ui.referenceSensorSpinBox.value, self.ui.probeSensorSpinBox.value)
        self.updateGUIFromLogic()

    def onCalibrate(self):
        self._run("Frame calibration failed.", self.logic.calibrateFrame)

    def onDetect(self):
        self._run("Marker detection failed.", self.logic.detectMarkers)

    def onRegister(self):
        self._run("Registration failed.", self.logic.register)

    def onNavigate(self):
        self._run("Navigation replay failed.", self.logic.navigateRecording)

    def onReport(self):
        self._run("Writing the report failed.", self.logic.writeReport)
        if self.logic.reportPath is not None:
            qt.QDesktopServices.openUrl(qt.QUrl.fromLocalFile(str(self.logic.reportPath)))

    def onRunAll(self):
        self._run("The workflow stopped.", self.logic.runAll)

    def onConnectLive(self):
        if self.logic.connectorNode is not None:
            self._run("Stopping live navigation failed.", self.logic.stopLiveNavigation)
        else:
            self._run("Live navigation failed.", self.logic.startLiveNavigation, self.ui.igtlHostLineEdit.text,
                      self.ui.igtlPortSpinBox.value)

    def updateGUIFromLogic(self):
        """Enable the buttons whose prerequisites exist and show the workflow state and figures."""
        if self.logic is None:
            return
        controller = self.logic.controller
        hasCase = self.logic.case is not None
        self.ui.calibrateButton.enabled = controller.calibration_recording is not None
        self.ui.detectButton.enabled = controller.image is not None
        self.ui.registerButton.enabled = controller.detection is not None and controller.frame_calibration is not None
        self.ui.navigateButton.enabled = controller.registration is not None and hasCase \
            and self.logic.case.navigation is not None
        self.ui.reportButton.enabled = self.logic.outputDirectory is not None and (
            controller.detection is not None or controller.frame_calibration is not None)
        self.ui.runAllButton.enabled = hasCase
        self.ui.connectButton.text = "Disconnect" if self.logic.connectorNode is not None else "Connect"
        self.ui.statusLabel.text = controller.describe()
        self.ui.resultsLabel.text = self.logic.resultsText()


#
# EMRegLogic
#


class EMRegLogic(ScriptedLoadableModuleLogic):
    """The EMReg workflow for Slicer: the command line's controller plus MRML nodes showing its results.

    ``self.controller`` is an :class:`EMRegModule.controller.EMRegController`; every step is one
    of its methods, then the result is written to the output folder (the same files as
    ``emreg run``) and shown in the scene. Usable without the panel (Python console, tests).
    """

    VOLUME_NODE_NAME = "EMReg CT"
    MARKERS_NODE_NAME = "EMReg markers"
    CALIBRATION_NODE_NAME = "EMReg calibration points"
    TARGETS_NODE_NAME = "EMReg targets"
    PATH_NODE_NAME = "EMReg probe path"
    TRANSFORM_NODE_NAME = "ReferenceToImage"
    CONNECTOR_NODE_NAME = "EMReg OpenIGTLink"

    def __init__(self, settings=None):
        ScriptedLoadableModuleLogic.__init__(self)
        ensureEMRegImportable()
        from EMRegModule.controller import EMRegController

        self.controller = EMRegController(settings)
        self.case = None
        self.outputDirectory = None
        self.reportPath = None
        self.evaluation = None
        self.connectorNode = None
        self.nodes = {}

    # --- inputs -------------------------------------------------------------------------------------

    def loadCase(self, caseDirectory, outputDirectory=None):
        """Open a case folder (spec layout): read its settings, CT and calibration recording; show the CT.

        ``outputDirectory`` receives the result files (default: ``<case>/emreg-output``).
        """
        from EMRegModule.controller import EMRegController
        from EMRegModule.errors import EMRegError
        from EMRegModule.io.case import open_case

        if not caseDirectory:
            raise EMRegError("choose a case folder first")
        case = open_case(caseDirectory)
        if case.ct is None:
            raise EMRegError(f"{case.folder}: no CT found (ct.nrrd, ct.nii.gz, ct.mha or a ct/ DICOM folder)")
        self.controller = EMRegController.for_case(case)  # sensor ports from case.toml (default 1 and 2)
        self.case = case
        self.outputDirectory = Path(outputDirectory) if outputDirectory else case.folder / "emreg-output"
        self.outputDirectory.mkdir(parents=True, exist_ok=True)
        self.reportPath = None
        self.evaluation = None
        self.controller.load_ct(case.ct)
        if case.calibration is not None:
            self.controller.load_calibration_recording(case.calibration)
        self.showVolume()
        if case.targets is not None:
            from EMRegModule.io.markups import read_markups

            labels, positions = read_markups(case.targets)
            self.showPoints(self.TARGETS_NODE_NAME, labels, positions, color=(0.9, 0.1, 0.1))
        logging.info("EMReg: case %s loaded; %s", case.folder, self.controller.describe())
        return case

    def setSensors(self, referenceSensor, probeSensor):
        """Sensor ports (1..4); a change drops the frame calibration and what follows."""
        self.controller.set_sensors(int(referenceSensor), int(probeSensor))

    # --- stages -------------------------------------------------------------------------------------

    def calibrateFrame(self):
        """Frame calibration (one point per pinhole, Reference frame); writes ``frame_calibration.json``."""
        from EMRegModule.calibration import write_frame_calibration

        result = self.controller.calibrate_frame()
        write_frame_calibration(result, self._output("frame_calibration.json"))
        self.showPoints(self.CALIBRATION_NODE_NAME, result.labels, result.positions, color=(0.9, 0.2, 0.9),
                        lps=False)
        return result

    def detectMarkers(self):
        """Marker detection in the CT; writes ``markers.json`` and shows the markers (RAS)."""
        from EMRegModule.detection import write_detection

        result = self.controller.detect_markers()
        write_detection(result, self.outputDirectory or self._output(""))
        self.showPoints(self.MARKERS_NODE_NAME, [m.id for m in result.markers],
                        [m.origin for m in result.markers], color=(0.2, 0.8, 0.3))
        return result

    def register(self):
        """Pairing, sensor offset and ``ReferenceToImage``; writes ``registration.json`` and the .h5 file."""
        from EMRegModule.registration import write_registration

        targets = None
        if self.case is not None and self.case.targets is not None:
            from EMRegModule.io.markups import read_markups

            targets = read_markups(self.case.targets)[1]
        result = self.controller.register(targets)
        write_registration(result, self.outputDirectory or self._output(""))
        self.showReferenceToImage(result.reference_to_image)
        return result

    def navigateRecording(self):
        """Replay the case's navigation recording (paper Eq. 12); writes ``navigation.csv`` and
        ``evaluation.json``; shows the probe path."""
        from EMRegModule.errors import EMRegError
        from EMRegModule.io.recording import read_recording
        from EMRegModule.navigation import write_navigation_csv

        if self.case is None or self.case.navigation is None:
            raise EMRegError("the case has no navigation.csv to replay")
        result = self.controller.navigate_recording(read_recording(self.case.navigation, self.case.settings))
        write_navigation_csv(result, self._output("navigation.csv"))
        positions = result.position_mm
        step = max(1, len(positions) // 500)
        self.showPath(positions[::step])
        self.evaluate()
        return result

    def evaluate(self):
        """TRE at the targets and the board table when the case has the recordings; writes ``evaluation.json``."""
        from EMRegModule.evaluation import evaluate_case, write_evaluation

        if self.case is None or (self.case.navigation is None and self.case.board is None):
            return None
        self.evaluation = evaluate_case(self.case, self.controller.reference_to_image,
                                        self.controller.reference_sensor, self.controller.probe_sensor)
        write_evaluation(self.evaluation, self._output("evaluation.json"))
        return self.evaluation

    def writeReport(self):
        """The verification report ``report.html`` of the output folder (offscreen rendering)."""
        from EMRegModule.report import write_report

        self.reportPath = write_report(self.outputDirectory, case_dir=self.case.folder if self.case else None)
        return self.reportPath

    def runAll(self):
        """Every available step in order, as ``emreg run`` does."""
        if self.controller.calibration_recording is not None:
            self.calibrateFrame()
        self.detectMarkers()
        if self.controller.frame_calibration is not None:
            self.register()
            if self.case is not None and self.case.navigation is not None:
                self.navigateRecording()
            else:
                self.evaluate()
        if importlib.util.find_spec("pyvista") is not None and importlib.util.find_spec("cv2") is not None:
            self.writeReport()
        else:
            logging.warning("EMReg: the report needs pyvista and opencv-python-headless; skipped")

    # --- live navigation ----------------------------------------------------------------------------

    def startLiveNavigation(self, host="localhost", port=18944):
        """Connect OpenIGTLinkIF to an ``emreg navigate --igtl-port PORT`` server: ``ProbeToImage`` (RAS)
        arrives as a linear transform node. Needs the SlicerOpenIGTLink extension."""
        from EMRegModule.errors import EMRegError

        try:
            connector = slicer.mrmlScene.AddNewNodeByClass("vtkMRMLIGTLConnectorNode", self.CONNECTOR_NODE_NAME)
        except Exception:  # noqa: BLE001 - Slicer raises a plain error for an unknown node class
            connector = None
        if connector is None:
            raise EMRegError("OpenIGTLinkIF is not available: install the SlicerOpenIGTLink extension "
                             "(Extensions Manager) for live navigation")
        connector.SetTypeClient(str(host), int(port))
        if connector.Start() != 1:
            slicer.mrmlScene.RemoveNode(connector)
            raise EMRegError(f"cannot connect to OpenIGTLink at {host}:{port}: start 'emreg navigate --igtl-port "
                             f"{port}' first")
        self.connectorNode = connector
        logging.info("EMReg: OpenIGTLink client connected to %s:%s; ProbeToImage will appear as a transform node",
                     host, port)
        return connector

    def stopLiveNavigation(self):
        if self.connectorNode is not None:
            self.connectorNode.Stop()
            slicer.mrmlScene.RemoveNode(self.connectorNode)
            self.connectorNode = None

    # --- MRML nodes ---------------------------------------------------------------------------------

    def forgetNodes(self):
        """Drop references to nodes (the scene is closing)."""
        self.nodes = {}
        self.connectorNode = None

    def _node(self, className, name):
        node = self.nodes.get(name)
        if node is None or slicer.mrmlScene.GetNodeByID(node.GetID()) is None:
            node = slicer.mrmlScene.AddNewNodeByClass(className, name)
            self.nodes[name] = node
        return node

    def _output(self, name):
        from EMRegModule.errors import EMRegError

        if self.outputDirectory is None:
            raise EMRegError("load a case (or set an output folder) first")
        self.outputDirectory.mkdir(parents=True, exist_ok=True)
        return self.outputDirectory / name

    def showVolume(self):
        """The controller's CT as a scalar volume node (sitkUtils converts LPS to RAS)."""
        import sitkUtils

        node = self.nodes.get(self.VOLUME_NODE_NAME)
        node = sitkUtils.PushVolumeToSlicer(self.controller.image, targetNode=node, name=self.VOLUME_NODE_NAME)
        self.nodes[self.VOLUME_NODE_NAME] = node
        slicer.util.setSliceViewerLayers(background=node, fit=True)
        return node

    def showPoints(self, name, labels, positions, color=(1.0, 1.0, 0.0), lps=True):
        """A markups point list; ``positions`` (N, 3) LPS image space (``lps=True``) or Reference frame
        (placed under the ``ReferenceToImage`` transform node)."""
        node = self._node("vtkMRMLMarkupsFiducialNode", name)
        node.RemoveAllControlPoints()
        for label, position in zip(labels, positions):  # noqa: B905 - Slicer 5.6 ships Python 3.9 (no strict=)
            point = lpsToRas(position) if lps else [float(v) for v in position]
            node.AddControlPoint(vtk.vtkVector3d(*point), str(label))
        node.SetLocked(True)
        display = node.GetDisplayNode()
        if display is not None:
            display.SetSelectedColor(*color)
        if not lps:
            transform = self.nodes.get(self.TRANSFORM_NODE_NAME)
            node.SetAndObserveTransformNodeID(transform.GetID() if transform is not None else None)
        return node

    def showPath(self, positionsLps):
        """The navigated probe path (image space) as a markups curve."""
        node = self._node("vtkMRMLMarkupsCurveNode", self.PATH_NODE_NAME)
        node.RemoveAllControlPoints()
        for position in positionsLps:
            node.AddControlPoint(vtk.vtkVector3d(*lpsToRas(position)), "")
        node.SetLocked(True)
        return node

    def showReferenceToImage(self, referenceToImage):
        """``ReferenceToImage`` as a linear transform node, matrix ``LPS_TO_RAS @ ReferenceToImage``;
        the calibration points node goes under it."""
        import numpy as np

        referenceToRas = np.diag([*LPS_TO_RAS_DIAGONAL, 1.0]) @ np.asarray(referenceToImage, dtype=float)
        node = self._node("vtkMRMLLinearTransformNode", self.TRANSFORM_NODE_NAME)
        slicer.util.updateTransformMatrixFromArray(node, referenceToRas)
        calibration = self.nodes.get(self.CALIBRATION_NODE_NAME)
        if calibration is not None:
            calibration.SetAndObserveTransformNodeID(node.GetID())
        return node

    def resultsText(self):
        """A few lines of figures for the panel."""
        lines = []
        registration = self.controller.registration
        if registration is not None:
            lines.append(f"FRE {registration.fre_mm:.2f} mm over {len(registration.pairs)} pairs; "
                         f"sensor offset l = {registration.sensor_offset_l_mm:.2f} mm")
            if registration.unpaired_image_markers or registration.unpaired_calibration_points:
                lines.append(f"unpaired: {len(registration.unpaired_image_markers)} markers, "
                             f"{len(registration.unpaired_calibration_points)} calibration points")
        tre = (self.evaluation or {}).get("tre")
        if tre:
            lines.append(f"TRE {tre['mean_mm']:.2f} +/- {tre['std_mm']:.2f} mm")
        if self.reportPath is not None:
            lines.append(f"report: {self.reportPath}")
        return "\n".join(lines)


#
# EMRegTest
#


class EMRegTest(ScriptedLoadableModuleTest):
    """End-to-end self-test: simulate a small case, run the Logic through every step, check the result
    against the simulator's ground truth and the MRML nodes it made.

    Set ``EMREG_TEST_CASE`` (environment) or ``EMRegTest.caseDirectory`` to reuse a case folder.
    """

    caseDirectory = None

    def setUp(self):
        slicer.mrmlScene.Clear()

    def runTest(self):
        self.setUp()
        self.test_EMReg_simulated_case()

    def _case(self):
        import tempfile

        folder = self.caseDirectory or os.environ.get("EMREG_TEST_CASE")
        if folder:
            return Path(folder)
        from EMRegModule.simulation import simulate_case

        folder = Path(tempfile.mkdtemp(prefix="EMRegTest-")) / "case"
        self.delayDisplay("Simulating a small case")
        simulate_case(folder, seed=11, difficulty="standard", frame_size_mm=(220.0, 220.0, 140.0), n_markers=16)
        return folder

    def test_EMReg_simulated_case(self):
        import tempfile

        import numpy as np

        from EMRegModule.simulation import load_truth
        from EMRegModule.transforms import apply_transform

        self.delayDisplay("Starting the EMReg test")
        case = self._case()
        truth = load_truth(case)
        logic = EMRegLogic()
        output = Path(tempfile.mkdtemp(prefix="EMRegTest-out-"))
        logic.loadCase(str(case), str(output))
        self.assertIsNotNone(slicer.mrmlScene.GetFirstNodeByName(EMRegLogic.VOLUME_NODE_NAME))

        self.delayDisplay("Calibrating, detecting, registering")
        logic.calibrateFrame()
        detection = logic.detectMarkers()
        registration = logic.register()
        self.assertGreaterEqual(len(registration.pairs), 6)
        self.assertLess(registration.fre_mm, 1.0)

        # ReferenceToImage against the truth, at the markers (mm)
        true_reference_to_image = np.asarray(truth["ReferenceToImage"], dtype=float)
        markers = np.array([m.origin for m in detection.markers])
        error = apply_transform(registration.reference_to_image, apply_transform(
            np.linalg.inv(true_reference_to_image), markers)) - markers
        self.assertLess(float(np.max(np.linalg.norm(error, axis=1))), 1.0)

        # MRML: markers in RAS, the transform node in RAS
        markersNode = slicer.mrmlScene.GetFirstNodeByName(EMRegLogic.MARKERS_NODE_NAME)
        self.assertEqual(markersNode.GetNumberOfControlPoints(), len(detection.markers))
        first = [0.0, 0.0, 0.0]
        markersNode.GetNthControlPointPosition(0, first)
        self.assertTrue(np.allclose(first, lpsToRas(detection.markers[0].origin), atol=1e-6))
        transformNode = slicer.mrmlScene.GetFirstNodeByName(EMRegLogic.TRANSFORM_NODE_NAME)
        matrix = slicer.util.arrayFromTransformMatrix(transformNode)
        expected = np.diag([-1.0, -1.0, 1.0, 1.0]) @ registration.reference_to_image
        self.assertTrue(np.allclose(matrix, expected, atol=1e-9))

        self.delayDisplay("Navigating and writing the report")
        if logic.case.navigation is not None:
            navigation = logic.navigateRecording()
            self.assertGreater(len(navigation), 0)
            if logic.evaluation and "tre" in logic.evaluation:
                self.assertLess(logic.evaluation["tre"]["mean_mm"], 2.0)
        report = logic.writeReport()
        self.assertTrue(Path(report).is_file())
        for name in ("markers.json", "frame_calibration.json", "registration.json", "ReferenceToImage.h5"):
            self.assertTrue((output / name).is_file(), name)
        self.delayDisplay("Test passed")
