"""EMReg: automatic patient-to-image registration for EM navigation, as a 3D Slicer scripted module.

Load it by adding this folder (``<repository>/EMRegModule/slicer``) to Slicer's additional
module paths (Edit > Application Settings > Modules), or build the extension (``CMakeLists.txt``: the
package ``EMRegModule/`` and ``Resources/`` then sit beside this file). The module puts the package's
folder on ``sys.path`` itself; the first time its panel or Logic is made in the Slicer application it
installs the Python packages that are missing with ``slicer.util.pip_install``, and says so in Slicer's
log and in its panel, which names any package still missing.

Layout (Slicer's scripted-module template): ``EMReg`` (module description), ``EMRegWidget``
(loads ``Resources/UI/EMReg.ui`` of the repository and only wires its buttons),
``EMRegLogic`` (the very controller the ``emreg`` command uses,
:class:`EMRegModule.pipeline.controller.EMRegController`, plus the MRML nodes that show its results)
and ``EMRegTest`` (drives the Logic end to end on a simulated case).

The Logic needs only MRML nodes and ``slicer.util``: inside Slicer they are the application's;
outside it (the tests) the ``slicer-core`` wheel provides them without Qt, and the scripted-module
bases Slicer's application would provide are replaced by minimal ones (see the imports). The nodes
are made by the package ``EMRegModule/slicer_export/``, which also writes the ``EMReg.mrb`` bundle of
``emreg run``; their names are ``EMRegModule/names.py``'s.
Supported: 3D Slicer 5.10 and later (Python 3.12; EMReg needs 3.11).

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
import shutil
import sys
import tempfile
from pathlib import Path

import slicer
from slicer.util import VTKObservationMixin

MODULE_DIR = Path(__file__).resolve().parent
# a clone: <repository>/EMRegModule/slicer/EMReg.py; the built extension: EMRegModule/ and Resources/ beside this file
REPOSITORY_ROOT = MODULE_DIR if (MODULE_DIR / "EMRegModule").is_dir() else MODULE_DIR.parents[1]
UI_FILE = REPOSITORY_ROOT / "Resources" / "UI" / "EMReg.ui"
ICON_FILE = REPOSITORY_ROOT / "Resources" / "Icons" / "EMReg.png"

if str(REPOSITORY_ROOT) not in sys.path:  # the names module is the repository's, read before anything else
    sys.path.insert(0, str(REPOSITORY_ROOT))
# Two base modules of plain Python (3.9 too, so that old Slicers load this file and say they are too old). The rest
# of the package is imported inside the functions that use it, once ensureEMRegImportable has checked the Python and
# installed the missing packages (scripts/architecture.py, DEFERRED_IN_MODULES).
from EMRegModule import names  # noqa: E402
from EMRegModule.errors import EMRegError  # noqa: E402

try:  # the 3D Slicer application (Qt)
    import qt
except ImportError:  # slicer-core (pip) or plain Python: MRML and slicer.util only; the Widget cannot run
    qt = None

try:
    from slicer.ScriptedLoadableModule import (
        ScriptedLoadableModule,
        ScriptedLoadableModuleLogic,
        ScriptedLoadableModuleTest,
        ScriptedLoadableModuleWidget,
    )
except ImportError:  # outside the Slicer application: the parts of Slicer's bases the Logic and the test use
    from EMRegModule.pipeline.slicer_bases import (
        ScriptedLoadableModule,
        ScriptedLoadableModuleLogic,
        ScriptedLoadableModuleTest,
        ScriptedLoadableModuleWidget,
    )


#: Python packages EMReg needs: import name -> (pip name, what needs it).
DEPENDENCIES = {
    "numpy": ("numpy", "everything"),
    "scipy": ("scipy", "detection, calibration, registration"),
    "SimpleITK": ("SimpleITK", "reading the CT and detection"),
    "pydicom": ("pydicom", "reading DICOM CT series"),
    "vtk": ("vtk", "marker models and detection"),
    "pyvista": ("pyvista", "the verification report"),
    "cv2": ("opencv-python-headless", "the verification report"),
    "pyigtl": ("pyigtl", "live navigation from the command line"),
    "serial": ("pyserial", "the robot panel's tracker on a serial line (trakSTAR, Aurora)"),
}
#: Without these the workflow cannot run at all; the others only disable one feature.
ESSENTIAL = ("python", "numpy", "scipy", "SimpleITK", "vtk")

#: EMReg's package needs Python 3.11 (tomllib, zip(strict=...)): 3D Slicer 5.10 and later (Python 3.12);
#: Slicer 5.8 and older ship Python 3.9. This file itself stays Python 3.9 so old Slicers can say so.
MINIMUM_PYTHON = (3, 11)
#: The packages this module installed into Slicer (``slicer.util.pip_install``), shown in its panel.
INSTALLED = []


def ensureEMRegImportable(install=False):
    """Put the repository root on ``sys.path``; return the missing dependencies (logged clearly).

    With ``install``, inside the 3D Slicer application (``slicer.app``), the missing packages are first installed
    with ``slicer.util.pip_install`` (once: then none is missing), which the log says and :data:`INSTALLED` keeps.
    Returns a list of ``(import name, pip name, what needs it)`` for every package that is absent.
    """
    if sys.version_info < MINIMUM_PYTHON:
        logging.error("EMReg needs 3D Slicer 5.10 or later (Python %d.%d or newer); this Slicer runs Python %d.%d",
                      *MINIMUM_PYTHON, *sys.version_info[:2])
        return [("python", "3D Slicer 5.10 or later", "everything")]
    root = str(REPOSITORY_ROOT)
    if root not in sys.path:
        sys.path.insert(0, root)
    missing = []
    for module, (pip_name, needed_by) in DEPENDENCIES.items():
        if importlib.util.find_spec(module) is None:
            missing.append((module, pip_name, needed_by))
    if install and missing and getattr(slicer, "app", None) is not None:
        requirements = " ".join(pip_name for _, pip_name, _ in missing)
        logging.warning("EMReg: installing the Python packages it needs into this Slicer (once, it may take a few "
                        "minutes): slicer.util.pip_install('%s')", requirements)
        try:
            slicer.util.pip_install(requirements)
        except Exception as error:  # offline, no permission...: what is still missing is named below
            logging.error("EMReg: installing %s failed: %s", requirements, error)
        importlib.invalidate_caches()
        INSTALLED.extend(m for m, _, _ in missing if importlib.util.find_spec(m) is not None)
        missing = [entry for entry in missing if importlib.util.find_spec(entry[0]) is None]
    if importlib.util.find_spec("EMRegModule") is None:
        logging.error("EMReg: the EMRegModule package was not found under %s; keep this module file inside the "
                      "EMReg repository (EMRegModule/slicer/EMReg.py)", root)
    for module, pip_name, needed_by in missing:
        level = logging.ERROR if module in ESSENTIAL else logging.WARNING
        logging.log(level, "EMReg: Python package '%s' is missing (needed for %s). Install it from Slicer's Python "
                           "console with: slicer.util.pip_install('%s')", module, needed_by, pip_name)
    return missing


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

        missing = ensureEMRegImportable(install=True)
        if any(module == "python" for module, _, _ in missing):
            self.ui.dependenciesLabel.text = (f"EMReg needs 3D Slicer 5.10 or later (Python "
                                              f"{MINIMUM_PYTHON[0]}.{MINIMUM_PYTHON[1]}+); this Slicer runs "
                                              f"Python {sys.version_info[0]}.{sys.version_info[1]}.")
        elif missing:
            self.ui.dependenciesLabel.text = "Missing Python packages: " + ", ".join(
                f"{module} (slicer.util.pip_install('{pip}'), for {needed})" for module, pip, needed in missing)
        else:
            self.ui.dependenciesLabel.text = "All Python packages found" + (
                f" (installed with slicer.util.pip_install: {', '.join(INSTALLED)})." if INSTALLED else ".")
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
        self.ui.toolPathLineEdit.connect("currentPathChanged(QString)", self.onToolChanged)
        self.ui.pivotButton.connect("clicked(bool)", self.onPivot)
        self.ui.fiducialsNodeComboBox.setMRMLScene(slicer.mrmlScene)
        self.ui.useFiducialsButton.connect("clicked(bool)", self.onUseFiducials)
        self.ui.planNodeComboBox.setMRMLScene(slicer.mrmlScene)
        self.ui.planNodeComboBox.connect("currentNodeChanged(vtkMRMLNode*)", self.onPlanChanged)
        self.setupRobotPanel()
        # the live guidance readout: OpenIGTLinkIF makes the Guidance STRING a text node and updates it as it arrives
        self.addObserver(slicer.mrmlScene, slicer.mrmlScene.NodeAddedEvent, self.onNodeAdded)
        self.onNodeAdded()
        self.updateGUIFromLogic()

    def cleanup(self):
        self.removeObservers()
        if self.logic is not None:
            self.logic.stopLiveNavigation()

    def onSceneStartClose(self, caller, event):
        logic = getattr(self, "logic", None)  # gone too while the panel is torn down with the scene it observes
        if logic is not None:
            logic.forgetNodes()
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
        self.ui.referenceSensorSpinBox.value = self.logic.controller.inputs.reference_sensor
        self.ui.probeSensorSpinBox.value = self.logic.controller.inputs.probe_sensor

    def onSensorsChanged(self, value=None):
        self.logic.setSensors(self.ui.referenceSensorSpinBox.value, self.ui.probeSensorSpinBox.value)
        self.updateGUIFromLogic()

    def onCalibrate(self):
        self._run("Frame calibration failed.", self.logic.calibrateFrame)

    def onToolChanged(self, path=None):
        self._run("Reading the tool failed.", self.logic.loadTool, self.ui.toolPathLineEdit.currentPath)

    def onPivot(self):
        self._run("Pivot calibration failed.", self.logic.pivotCalibrate,
                  self.ui.pivotRecordingPathLineEdit.currentPath)

    def onNodeAdded(self, caller=None, event=None):
        """Watch the guidance text node once it exists (made by OpenIGTLinkIF when the first STRING arrives)."""
        node = self.logic.guidanceNode()
        if node is not None and not self.hasObserver(node, node.TextModifiedEvent, self.onGuidanceModified):
            self.addObserver(node, node.TextModifiedEvent, self.onGuidanceModified)
            self.onGuidanceModified()

    def onGuidanceModified(self, caller=None, event=None):
        self.ui.guidanceLabel.text = self.logic.guidanceReadout()

    def onPlanChanged(self, node=None):
        self._run("Using the plan failed.", self.logic.setPlanFromMarkupsNode, self.ui.planNodeComboBox.currentNode())

    def onUseFiducials(self):
        self._run("Using the fiducials failed.", self._useFiducials)

    def _useFiducials(self):
        node = self.ui.fiducialsNodeComboBox.currentNode()
        if node is None:
            raise ValueError("choose a markups point list whose control points are the fiducials")
        self.logic.setFiducialsFromMarkupsNode(node)

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

    # --- the robot panel: its logic is EMRegModule.pipeline.robot_panel (the robot commands' own functions) ------

    def setupRobotPanel(self):
        from EMRegModule.pipeline.robot_panel import RobotPanelLogic

        self.robot = RobotPanelLogic(self.logic.controller.settings, slicer.mrmlScene)
        self.ui.robotCalibrateButton.connect("clicked(bool)", self.onRobotCalibrate)
        self.ui.robotTargetButton.connect("clicked(bool)", self.onRobotTarget)
        self.ui.robotGoButton.connect("clicked(bool)", self.onRobotGo)

    def _robotRun(self, errorMessage, function, *args):
        """A robot step with the case's settings, into the output folder; the panel says what it said."""
        self.robot.settings = self.logic.controller.settings
        try:
            self._run(errorMessage, function, *args)
        finally:
            self.ui.robotStatusLabel.text = self.robot.describe()

    def _robotFolder(self):
        return self.ui.outputDirectoryPathLineEdit.currentPath or self.logic.outputDirectory

    def onRobotCalibrate(self):
        self._robotRun("Robot calibration failed.", self.robot.calibrate, self.ui.robotPosesPathLineEdit.currentPath,
                       self.ui.flangeRecordingPathLineEdit.currentPath, self._robotFolder(),
                       self.ui.flangeSensorLineEdit.text.strip() or None)

    def onRobotTarget(self):
        folder = self._robotFolder()
        self._robotRun("Targeting the plan failed.", self.robot.target_plan,
                       Path(folder) / names.REGISTRATION_JSON if folder else None,
                       self.ui.robotReferenceLineEdit.text.strip(), self.ui.robotPlanPathLineEdit.currentPath,
                       self.ui.needleGuidePathLineEdit.currentPath, folder)

    def onRobotGo(self):
        self._robotRun("Moving the robot failed.", self.robot.go_to_target, self.ui.robotUrlLineEdit.text.strip(),
                       self.ui.robotTrackerUrlLineEdit.text.strip(), self._robotFolder(),
                       self.ui.robotExecuteCheckBox.checked is True)

    def updateGUIFromLogic(self):
        """Enable the buttons whose prerequisites exist and show the workflow state and figures."""
        if self.logic is None:
            return
        controller = self.logic.controller
        hasCase = self.logic.case is not None
        stages = controller.results.available(controller.inputs.image is not None,
                                              controller.inputs.calibration_recording is not None)  # the table's
        self.ui.calibrateButton.enabled = "calibrate" in stages
        self.ui.detectButton.enabled = "detect" in stages
        self.ui.registerButton.enabled = "register" in stages
        self.ui.navigateButton.enabled = "navigate" in stages and hasCase and self.logic.case.navigation is not None
        self.ui.reportButton.enabled = self.logic.outputDirectory is not None and "report" in stages
        self.ui.runAllButton.enabled = hasCase
        self.ui.connectButton.text = "Disconnect" if self.logic.connectorNode is not None else "Connect"
        self.ui.statusLabel.text = controller.results.describe()
        self.ui.resultsLabel.text = self.logic.resultsText()


class EMRegLogic(ScriptedLoadableModuleLogic):
    """The EMReg workflow for Slicer: the command line's controller plus MRML nodes showing its results.

    ``self.controller`` is an :class:`EMRegModule.pipeline.controller.EMRegController`; every step is one
    stage of its table (``make``), then the result is written to the output folder (the same files as
    ``emreg run``) and shown in the scene. Usable without the panel (Python console, tests) and
    without Qt: it needs only MRML nodes and ``slicer.util`` (3D Slicer's, or the slicer-core
    wheel's). The nodes are made by :mod:`EMRegModule.slicer_export`, the same code that writes
    the scene bundle ``EMReg.mrb`` of ``emreg run``, so both show the same nodes.

    ``scene``: the MRML scene to show the results in (default ``slicer.mrmlScene``).
    """

    # the node names of EMRegModule/names.py (the bundle's too)
    VOLUME_NODE_NAME = names.VOLUME_NODE_NAME
    MARKERS_NODE_NAME = names.MARKERS_NODE_NAME
    CALIBRATION_NODE_NAME = names.CALIBRATION_NODE_NAME
    TARGETS_NODE_NAME = names.TARGETS_NODE_NAME
    PATH_NODE_NAME = names.PATH_NODE_NAME
    TRANSFORM_NODE_NAME = names.TRANSFORM_NODE_NAME
    PROBE_NODE_NAME = names.PROBE_NODE_NAME
    CONNECTOR_NODE_NAME = names.CONNECTOR_NODE_NAME
    COMMAND = "EMReg (3D Slicer)"

    def __init__(self, settings=None, scene=None):
        ScriptedLoadableModuleLogic.__init__(self)
        ensureEMRegImportable(install=True)
        from EMRegModule.pipeline.controller import EMRegController

        self._scene = scene
        self.controller = EMRegController(settings, command=self.COMMAND)
        self.case = None
        self.outputDirectory = None
        self.reportPath = None
        self.evaluation = None
        self.probeToReference = None
        self.connectorNode = None
        self.nodes = {}

    @property
    def scene(self):
        return self._scene if self._scene is not None else slicer.mrmlScene

    # --- inputs -------------------------------------------------------------------------------------

    def loadCase(self, caseDirectory, outputDirectory=None):
        """Open a case folder (spec layout): read its settings, CT (or ``fiducials.mrk.json`` instead) and
        calibration recording; show the CT.

        ``outputDirectory`` receives the result files (default: ``<case>/emreg-output``).
        """
        from EMRegModule.io.case import open_case
        from EMRegModule.pipeline.controller import EMRegController
        from EMRegModule.pipeline.inputs import check_case_image_side

        if not caseDirectory:
            raise EMRegError("choose a case folder first")
        case = open_case(caseDirectory)
        check_case_image_side(case)
        self.controller = EMRegController.for_case(case, command=self.COMMAND)  # sensor ports from case.toml
        self.case = case
        self.outputDirectory = Path(outputDirectory) if outputDirectory else case.folder / "emreg-output"
        self.outputDirectory.mkdir(parents=True, exist_ok=True)
        self.reportPath = None
        self.evaluation = None
        self.probeToReference = None
        if case.ct is not None:
            self.controller.give(ct=case.ct)
        else:  # a fiducial case: registered onto its fiducials, nothing to detect
            self.controller.adopt("detect", case.fiducials)
        self.controller.recorder.note_inputs(ct=case.ct, calibration=case.calibration, navigation=case.navigation,
                                    targets=case.targets, board=case.board)  # provenance of the outputs
        if case.calibration is not None:
            self.controller.give(calibration=case.calibration)
        if case.ct is not None:
            self.showVolume()
        self.showResults()
        logging.info("EMReg: case %s loaded; %s", case.folder, self.controller.results.describe())
        return case

    def setFiducialsFromMarkupsNode(self, markupsNode):
        """Register onto the defined control points of a markups node (world RAS, as Slicer shows them; kept
        in LPS) instead of CT markers: a rigid point fit of the calibration points, no sensor offset. Checked as a
        fiducials file is (at least 3, unique labels, not on one line); drops the registration."""
        from EMRegModule.io.fiducials import Fiducials, check_fiducials
        from EMRegModule.pipeline.slicer_scene import markups_points_lps

        labels, positions = markups_points_lps(markupsNode)
        fiducials = Fiducials(labels, positions,
                              f"markups node {markupsNode.GetName()}", "3D Slicer markups node", "LPS",
                              {"coordinate_system": "RAS (world)", "units": "mm"})
        check_fiducials(fiducials)
        self.controller.adopt("detect", fiducials=fiducials)
        self.showResults()
        return fiducials

    def setPlanFromMarkupsNode(self, markupsNode):
        """The plan from a markups node (world RAS, kept in LPS): a line (Entry, Target), points labelled Entry and
        Target, or one target point (:mod:`EMRegModule.core.plan`); None: no plan. Each navigation then gets the
        guidance
        numbers (``navigation.csv``, ``navigation.json``) and the panel the closest approach and the predicted error."""
        from EMRegModule.pipeline.slicer_scene import plan_from_markups_node

        self.controller.give(plan=None if markupsNode is None else plan_from_markups_node(markupsNode))
        return self.controller.inputs.plan

    def setSensors(self, referenceSensor, probeSensor):
        """Sensor ports (1..4); a change drops the frame calibration and what follows."""
        self.controller.give(sensors=(int(referenceSensor), int(probeSensor)))
        self.showResults()

    # --- stages -------------------------------------------------------------------------------------

    def loadTool(self, path):
        """Use a tracked tool's tip (a tool file, or ``auto``; :mod:`EMRegModule.core.tool`); empty: the pinhole probe.
        The frame calibration is made again with it."""
        return self.controller.give(tool=path or None).tool

    def pivotCalibrate(self, recordingPath, outputDirectory=None):
        """``emreg pivot``: the tool's tip from a pivot recording, written as ``tool_calibration.json`` and
        ``TipToProbe.h5`` into ``outputDirectory`` (default: the output folder, else ``pivot/`` beside the
        recording), then used. Returns the :class:`~EMRegModule.core.tool.ToolCalibration`."""
        from EMRegModule.io.tool_files import write_tool_calibration
        from EMRegModule.pipeline.pivot import pivot_tool

        inputs = self.controller.inputs
        tool, _ = pivot_tool(recordingPath, inputs.settings, inputs.reference_sensor, inputs.probe_sensor)
        out = Path(outputDirectory or self.outputDirectory or Path(recordingPath).parent / "pivot")
        out.mkdir(parents=True, exist_ok=True)
        write_tool_calibration(tool, out)
        self.controller.give(tool=tool)
        return tool

    def calibrateFrame(self):
        """Frame calibration (one point per pinhole, Reference frame); writes ``frame_calibration.json``."""
        result = self.controller.make("calibrate")
        self.controller.save("calibrate", self._outputs("calibrate"))
        self.showResults()
        return result

    def detectMarkers(self):
        """Marker detection in the CT; writes ``markers.json`` and shows the markers (RAS)."""
        result = self.controller.make("detect")
        self.controller.save("detect", self._outputs("detect"))
        self.showResults()
        return result

    def register(self):
        """Pairing, sensor offset and ``ReferenceToImage``; writes ``registration.json`` and the .h5 file."""
        targets = None
        if self.case is not None and self.case.targets is not None:
            from EMRegModule.io.markups import read_markups

            targets = read_markups(self.case.targets)[1]
        result = self.controller.make("register", targets=targets)
        self.controller.save("register", self._outputs("register"))
        self.showResults()
        return result

    def navigateRecording(self):
        """Replay the case's navigation recording (paper Eq. 12); writes ``navigation.csv`` and
        ``evaluation.json``; shows the probe path and the last probe pose (``ProbeToReference``,
        under ``ReferenceToImage``)."""
        from EMRegModule.io.recording import read_recording

        if self.case is None or self.case.navigation is None:
            raise EMRegError("the case has no navigation.csv to replay")
        inputs = self.controller.inputs
        recording = read_recording(self.case.navigation, self.case.settings, inputs.reference_sensor,
                                   inputs.probe_sensor)
        result = self.controller.make("navigate", recording=recording)
        self.controller.save("navigate", self._outputs("navigate"))
        self._lastProbePose(recording)
        self.evaluate()
        self.showResults()
        return result

    def evaluate(self):
        """TRE at the targets and the board table when the case has the recordings; writes ``evaluation.json``.
        The same step as ``emreg run``'s: a part that cannot be made is "not evaluated" with its reason."""
        if self.case is None or (self.case.navigation is None and self.case.board is None):
            return None
        self.controller.make("evaluate", case=self.case, folder=self._outputs("evaluate"))
        self.evaluation = self.controller.results.evaluation
        return self.evaluation

    def writeReport(self):
        """The verification report ``report.html`` of the output folder (offscreen rendering)."""
        folder = self._outputs("report")
        self.controller.make("report", folder=folder, case_dir=self.case.folder if self.case else None)
        self.reportPath = folder.path / names.REPORT_HTML
        return self.reportPath

    def runAll(self):
        """Every step in order: the controller's run, the same as ``emreg run`` (output folder, ``run.json``,
        provenance); then the results are shown in the scene."""
        if self.case is None:
            raise EMRegError("load a case first")
        report = importlib.util.find_spec("pyvista") is not None and importlib.util.find_spec("cv2") is not None
        if not report:
            logging.warning("EMReg: the report needs pyvista and opencv-python-headless; skipped")
        summary = self.controller.run(self.case, self.outputDirectory, report=report)
        self.evaluation = self.controller.results.evaluation
        if self.controller.results.navigation is not None:
            self._lastProbePose(self.case.read_recording("navigation"))
        page = self.outputDirectory / names.REPORT_HTML
        self.reportPath = page if report and page.is_file() else None
        self.showResults()
        return summary

    def _lastProbePose(self, recording):
        """The last probe pose straight from the recording (Reference frame); Slicer composes it with
        ReferenceToRAS."""
        from EMRegModule.pipeline.slicer_scene import last_probe_to_reference

        inputs = self.controller.inputs
        self.probeToReference = last_probe_to_reference(recording, inputs.reference_sensor, inputs.probe_sensor)

    # --- live navigation ----------------------------------------------------------------------------

    def startLiveNavigation(self, host="localhost", port=names.DEFAULT_IGTL_PORT):
        """Connect OpenIGTLinkIF to an ``emreg navigate --igtl-port PORT`` server: ``ProbeToImage`` (RAS)
        arrives as a linear transform node. Needs the SlicerOpenIGTLink extension."""
        from EMRegModule.pipeline.slicer_scene import connect_igtl_client

        connector = connect_igtl_client(self.scene, host, port, self.CONNECTOR_NODE_NAME)
        self.connectorNode = connector
        logging.info("EMReg: OpenIGTLink client connected to %s:%s; ProbeToImage will appear as a transform node",
                     host, port)
        return connector

    def guidanceNode(self):
        """The text node of the live guidance numbers (``names.GUIDANCE_NAME``, the STRING ``emreg navigate --plan``
        sends, which OpenIGTLinkIF turns into a text node), or None before the first one arrived."""
        nodes = self.scene.GetNodesByClassByName("vtkMRMLTextNode", names.GUIDANCE_NAME)
        return nodes.GetItemAsObject(0) if nodes.GetNumberOfItems() else None

    def guidanceReadout(self):
        """The latest guidance numbers (tip to target, off the line, angle, depth to go, the predicted error at the
        target), as the navigation sent them; empty before any."""
        node = self.guidanceNode()
        return (node.GetText() or "") if node is not None else ""

    def stopLiveNavigation(self):
        if self.connectorNode is not None:
            self.connectorNode.Stop()
            self.scene.RemoveNode(self.connectorNode)
            self.connectorNode = None

    # --- MRML nodes ---------------------------------------------------------------------------------

    def forgetNodes(self):
        """Drop references to nodes (the scene is closing)."""
        self.nodes = {}
        self.connectorNode = None

    def _outputs(self, stage):
        """The output folder for one step: that step's earlier outputs and those of later steps move to
        ``previous/`` (stale once this step has a new result)."""
        from EMRegModule.io.output_folder import OutputFolder

        if self.outputDirectory is None:
            raise EMRegError("load a case (or set an output folder) first")
        folder = OutputFolder(self.outputDirectory, self.COMMAND)
        folder.start_stage(stage)
        return folder

    def showVolume(self):
        """The controller's CT as a scalar volume node (IJK-to-RAS from the image's LPS geometry)."""
        from EMRegModule.pipeline.slicer_scene import show_volume

        # A copy: in 3D Slicer a user may edit the volume in place; the controller's CT must not change.
        node = show_volume(self.scene, self.controller.inputs.image, self.VOLUME_NODE_NAME,
                                        node=self.nodes.get(self.VOLUME_NODE_NAME), copy_voxels=True)
        self.nodes[self.VOLUME_NODE_NAME] = node
        if hasattr(slicer, "app"):  # slice views exist only in the application
            slicer.util.setSliceViewerLayers(background=node, fit=True)
        return node

    def resultsContent(self):
        """What the scene shows, from the controller's results: the run's typed view
        (:class:`~EMRegModule.io.run_folder.RunFolder`, in memory) turned into a scene as the bundle's is."""
        from EMRegModule.io.markups import read_markups
        from EMRegModule.io.run_folder import RunFolder
        from EMRegModule.pipeline.slicer_scene import run_scene_of

        results = self.controller.results
        navigated = results.registration is not None and results.navigation is not None
        folder = RunFolder(self.outputDirectory, detection=results.detection,
                           frame_calibration=results.frame_calibration, registration=results.registration,
                           navigation_positions=results.navigation.position_mm if navigated else None)
        targets = read_markups(self.case.targets) if self.case is not None and self.case.targets is not None else None
        return run_scene_of(folder, targets, self.probeToReference if navigated else None)

    def showResults(self):
        """Show (or update) every result node: markers, calibration points under ``ReferenceToImage``,
        pinhole points, residual spheres, targets, probe path and pose; nodes of dropped results go."""
        from EMRegModule.pipeline.slicer_scene import build_run_scene

        return build_run_scene(self.scene, self.resultsContent(), self.nodes)

    def resultsText(self):
        """A few lines of figures for the panel (with a plan: the closest approach and the predicted error)."""
        from EMRegModule.pipeline.results import results_lines

        return "\n".join(results_lines(self.controller.results, self.evaluation, self.reportPath))


class EMRegTest(ScriptedLoadableModuleTest):
    """End-to-end self-test: simulate a small case, run the Logic through every step, check the result
    against the simulator's ground truth and the MRML nodes it made (positions read back from MRML in
    world coordinates, i.e. through the transform hierarchy).

    Set ``EMREG_TEST_CASE`` (environment) or ``EMRegTest.caseDirectory`` to reuse a case folder.
    """

    caseDirectory = None

    def setUp(self):
        slicer.mrmlScene.Clear()

    def runTest(self):
        self.setUp()
        self.test_EMReg_simulated_case()

    def _case(self):
        folder = self.caseDirectory or os.environ.get("EMREG_TEST_CASE")
        if folder:
            return Path(folder)
        from EMRegModule.pipeline.sample_case import simulate_sample_case

        folder = Path(tempfile.mkdtemp(prefix="EMRegTest-")) / "case"
        self._temporary.append(folder.parent)
        self.delayDisplay("Simulating a small case")
        simulate_sample_case(folder, seed=11)
        return folder

    def test_EMReg_simulated_case(self):
        """Runs in folders of its own under the temporary directory, removed afterwards (passed or not)."""
        self._temporary = []
        try:
            self._simulated_case()
        finally:
            for folder in self._temporary:
                shutil.rmtree(folder, ignore_errors=True)

    def _simulated_case(self):
        from EMRegModule.pipeline.sample_case import load_truth, reference_to_image_error_mm
        from EMRegModule.pipeline.slicer_scene import scene_disagreements

        self.delayDisplay("Starting the EMReg test")
        case = self._case()
        truth = load_truth(case)
        logic = EMRegLogic()
        output = Path(tempfile.mkdtemp(prefix="EMRegTest-out-"))
        self._temporary.append(output)
        logic.loadCase(str(case), str(output))
        self.assertIsNotNone(slicer.mrmlScene.GetFirstNodeByName(EMRegLogic.VOLUME_NODE_NAME))

        self.delayDisplay("Calibrating, detecting, registering")
        logic.calibrateFrame()
        detection = logic.detectMarkers()
        registration = logic.register()
        self.assertGreaterEqual(len(registration.pairs), 6)
        self.assertLess(registration.fre_mm, 1.0)

        # ReferenceToImage against the truth, at the markers (mm)
        self.assertLess(reference_to_image_error_mm(registration.reference_to_image, truth,
                                                    [m.origin for m in detection.markers]), 1.0)

        # MRML (world coordinates): markers, ReferenceToRAS, calibration points on their pinhole points
        self.assertEqual(scene_disagreements(slicer.mrmlScene, detection, registration), [])

        self.delayDisplay("Navigating and writing the report")
        if logic.case.navigation is not None:
            navigation = logic.navigateRecording()
            self.assertGreater(len(navigation), 0)
            if logic.evaluation is not None and logic.evaluation.tre is not None:
                self.assertLess(logic.evaluation.tre.mean_mm, 2.0)
            # the last probe pose, under ReferenceToImage, lands where navigation says (RAS)
            self.assertEqual(scene_disagreements(slicer.mrmlScene, detection, registration,
                                                 navigation.position_mm[-1]), [])
        report = logic.writeReport()
        self.assertTrue(Path(report).is_file())
        for name in (names.MARKERS_JSON, names.FRAME_CALIBRATION_JSON, names.REGISTRATION_JSON,
                     names.REFERENCE_TO_IMAGE_H5):
            self.assertTrue((output / name).is_file(), name)
        self.delayDisplay("Test passed")
