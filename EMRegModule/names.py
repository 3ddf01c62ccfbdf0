"""The one home of the names users and other tools see: the files of a case folder and of an output
folder (spec: FORMATS.md), 3D Slicer's node names, and the default tracker ports. Every module spells
these through the constants here, never as literals, so a rename is one edit.
"""

from __future__ import annotations

# --- case folder (inputs) ------------------------------------------------------------------------
CT_FILE_NAMES = ("ct.nrrd", "ct.nii.gz", "ct.nii", "ct.mha", "ct.mhd", "ct.nhdr")  # .nhdr: Slicer's detached NRRD
CT_FOLDER_NAME = "ct"  # a DICOM series
RECORDING_ROLES = ("calibration", "navigation", "board")
#: The file forms of a recording: EMReg's CSV, or a PLUS sequence metafile (.seq.mha ...).
RECORDING_SUFFIXES = (".csv", ".seq.mha", ".mha", ".seq.nrrd", ".igs.nrrd")
TARGETS_FILE = "targets.mrk.json"
SETTINGS_FILE = "case.toml"
CASE_FIDUCIALS_FILE = "fiducials.mrk.json"  # planned landmarks instead of a CT

#: Every name a case folder is read from (an output folder equal to the case must write none of them).
CASE_INPUT_NAMES = (CT_FOLDER_NAME, *CT_FILE_NAMES,
                    *(role + suffix for role in RECORDING_ROLES for suffix in RECORDING_SUFFIXES),
                    TARGETS_FILE, SETTINGS_FILE, CASE_FIDUCIALS_FILE)

# --- output folder ---------------------------------------------------------------------------------
RUN_JSON = "run.json"  # the manifest
PREVIOUS_FOLDER = "previous"  # where an earlier run's outputs are moved
MARKERS_JSON = "markers.json"
MARKERS_MRK_JSON = "markers.mrk.json"
FRAME_CALIBRATION_JSON = "frame_calibration.json"
TOOL_CALIBRATION_JSON = "tool_calibration.json"
TIP_TO_PROBE_H5 = "TipToProbe.h5"
REGISTRATION_JSON = "registration.json"
REFERENCE_TO_IMAGE_H5 = "ReferenceToImage.h5"
NAVIGATION_CSV = "navigation.csv"
CHECKPOINTS_JSON = "checkpoints.json"
NAVIGATION_JSON = "navigation.json"  # with a plan: the plan, the predicted error at the target, the closest approach
EVALUATION_JSON = "evaluation.json"
TRE_MAP_NRRD = "tre_map.nrrd"
REPORT_HTML = "report.html"
REPORT_FIGURES = "report_figures"
BUNDLE_MRB = "EMReg.mrb"
# the robot's outputs (issue 39): emreg handeye / robot-calibrate, robot-target, robot-go --out
ROBOT_CALIBRATION_JSON = "robot_calibration.json"
SENSOR_TO_FLANGE_H5 = "SensorToFlange.h5"
TRACKER_TO_BASE_H5 = "TrackerToBase.h5"
ROBOT_TARGET_JSON = "robot_target.json"
ROBOT_GO_JSON = "robot_go.json"

# --- 3D Slicer node names (the bundle's scene and the module's own nodes) ---------------------------
VOLUME_NODE_NAME = "EMReg CT"
MARKERS_NODE_NAME = "EMReg markers"
PINHOLES_NODE_NAME = "EMReg pinhole points"
CALIBRATION_NODE_NAME = "EMReg calibration points"
TARGETS_NODE_NAME = "EMReg targets"
PATH_NODE_NAME = "EMReg probe path"
RESIDUALS_NODE_NAME = "EMReg marker residuals"
TRANSFORM_NODE_NAME = "ReferenceToImage"
PROBE_NODE_NAME = "ProbeToReference"
TIP_NODE_NAME = "TipToProbe"
TRE_MAP_NODE_NAME = "EMReg predicted TRE (mm)"
FIDUCIALS_NODE_NAME = "EMReg fiducials"
CONNECTOR_NODE_NAME = "EMReg OpenIGTLink"
#: The robot's calibration (tracker and robot side frames: their matrices as they are, as in the ``.h5`` files).
SENSOR_TO_FLANGE_NODE_NAME = "SensorToFlange"
TRACKER_TO_BASE_NODE_NAME = "TrackerToBase"
#: The needle guide on its plan: its pose in RAS (the name ``emreg robot-go`` streams it under), its model under it
#: and the planned line (Entry -> Target, RAS).
GUIDE_NODE_NAME = "NeedleGuideToRAS"
GUIDE_MODEL_NODE_NAME = "EMReg needle guide"
ROBOT_PLAN_NODE_NAME = "EMReg robot plan"
#: The OpenIGTLink STRING of the guidance numbers (``emreg navigate --plan``): OpenIGTLinkIF makes it a text node
#: of this name, which the module's panel shows as it changes.
GUIDANCE_NAME = "Guidance"

# --- tracker ports ---------------------------------------------------------------------------------
#: trakSTAR / Aurora ports of the reference sensor and the probe when nothing says otherwise (``[sensors]``).
DEFAULT_REFERENCE_PORT = 1
DEFAULT_PROBE_PORT = 2
#: OpenIGTLink's registered port (the server's default, as in PLUS and Slicer's OpenIGTLinkIF).
DEFAULT_IGTL_PORT = 18944
#: The trakSTAR's line speed when nothing says otherwise (:data:`EMRegModule.devices.trakstar.protocol.DEFAULT_BAUD`).
DEFAULT_TRAKSTAR_BAUD = 115200

# --- live commands ---------------------------------------------------------------------------------
#: Default time (s) live navigation keeps trying to reopen a lost tracker before it gives up (``--reconnect``).
DEFAULT_RECONNECT_S = 30.0
#: Share of the expected samples (the frames a replay sent; else the measurement cycles the tracker's rate gives
#: over the recording's time) that the reference and the probe must each reach for ``emreg record`` to succeed.
#: A clean link delivers all of them (measured: 100 %); under the link alarm nothing is recorded, and a
#: recording missing more than half its samples is more gap than recording (dwells cut short, motion unseen):
#: exit 3, never a success.
MIN_RECORDED_SHARE = 0.5
