"""What the workflow is given, once: the CT, the calibration recording, the tool, the sensor ports and the plan
(:class:`Inputs`, an immutable value: a new input gives a new one), and how each is read from its file.

Frames and units: the CT's image space is LPS (mm); a tool's ``TipToProbe`` maps its tip into the probe sensor's
frame (mm); a plan's points are image space (LPS, mm).
"""

from __future__ import annotations

import dataclasses
import os
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, NoReturn

import numpy as np

from .. import __version__
from ..core.plan import Plan, check_plan_in_image
from ..core.tool import ToolCalibration
from ..core.tracking import TrackingRecording
from ..errors import EMRegError
from ..io.case import Case
from ..io.ct_checks import check_ct_image
from ..io.image import open_ct
from ..io.plan_markups import read_plan
from ..io.recording import read_recording as read_recording_file
from ..io.tool_files import read_tool
from ..marker_model import MarkerModel
from ..progress import Progress
from ..settings import Settings
from .background import import_in_background

if TYPE_CHECKING:
    import SimpleITK as sitk

    from ..core.detection import DetectionResult


@dataclass(frozen=True)
class Inputs:
    """The inputs of the workflow (None: not given).

    - ``settings``: the checked ``case.toml`` (:class:`~EMRegModule.settings.Settings`); each stage reads its table.
    - ``reference_sensor``, ``probe_sensor``: the tracker ports (1..4).
    - ``image``: the CT in memory (``SimpleITK.Image``, LPS mm), ``image_source`` what it was read from and
      ``ct_series`` (a DICOM folder) the series used and the others.
    - ``calibration_recording``: the frame-calibration recording.
    - ``tool``: a tracked tool's tip (None: the paper's pinhole probe); ``tool_auto``: the tip is solved from the
      calibration recording's pivoting touches (``--tool auto``).
    - ``plan``: the planned trajectory guided to (None: no guidance numbers).
    """

    settings: Settings
    reference_sensor: int
    probe_sensor: int
    image: sitk.Image | None = None
    image_source: str | None = None
    ct_series: dict[str, Any] | None = None
    calibration_recording: TrackingRecording | None = None
    tool: ToolCalibration | None = None
    tool_auto: bool = False
    plan: Plan | None = None

    @classmethod
    def of(cls, settings: Settings) -> Inputs:
        """No input yet: the ports of ``settings``' ``[sensors]``."""
        return cls(settings, settings.sensors.reference, settings.sensors.probe)

    @property
    def marker_model(self) -> MarkerModel:
        return self.settings.marker

    @property
    def tip_to_probe(self) -> np.ndarray | None:
        """The tool's ``TipToProbe`` (4x4, mm), None for the pinhole probe."""
        return None if self.tool is None else self.tool.tip_to_probe

    def replace(self, **changes: Any) -> Inputs:
        return dataclasses.replace(self, **changes)


def with_ports(inputs: Inputs, reference_sensor: int | None, probe_sensor: int | None) -> Inputs:
    """``inputs`` with the ports changed where given, checked as ``[sensors]`` (1..4, two different ports)."""
    current = inputs.settings.with_sensors(inputs.reference_sensor, inputs.probe_sensor)
    sensors = current.with_sensors(reference_sensor, probe_sensor).sensors
    return inputs.replace(reference_sensor=sensors.reference, probe_sensor=sensors.probe)


def with_tool(inputs: Inputs, tool: str | os.PathLike[str] | ToolCalibration | None) -> Inputs:
    """``inputs`` with a tool: a tool file (``tool_calibration.json``, ITK transform, PLUS device set;
    :func:`EMRegModule.core.tool.read_tool`, named as ``[tool] name`` says when it does), ``auto`` (the tip solved
    when the frame is calibrated), a :class:`~EMRegModule.core.tool.ToolCalibration`, or None (the pinhole probe)."""
    if tool is None or isinstance(tool, ToolCalibration):
        return inputs.replace(tool=tool, tool_auto=False)
    if str(tool) == "auto":
        return inputs.replace(tool=None, tool_auto=True)
    return inputs.replace(tool=read_tool(tool, inputs.settings.tool.name), tool_auto=False)


def refuse_tool_auto(command: str) -> NoReturn:
    """``--tool auto`` where there is no calibration recording to solve the tip from: refused, one line."""
    raise EMRegError(f"{command}: --tool auto solves the tip from a calibration recording; give the "
                     "tool_calibration.json that emreg calibrate or emreg run wrote with it instead")


def with_plan(inputs: Inputs, plan: str | os.PathLike[str] | Plan | None,
              detection: DetectionResult | None) -> Inputs:
    """``inputs`` with a plan: a Slicer markups file (:func:`EMRegModule.core.plan.read_plan`: a Line Entry ->
    Target, points labelled Entry and Target, or one target point; LPS or RAS as the file declares), a
    :class:`~EMRegModule.core.plan.Plan`, or None (no plan); refused outside the CT of ``detection``."""
    plan = plan if plan is None or isinstance(plan, Plan) else read_plan(plan)
    check_plan_in_ct(plan, detection)
    return inputs.replace(plan=plan)


def with_ct(inputs: Inputs, ct: str | os.PathLike[str] | sitk.Image, progress: Progress) -> Inputs:
    """``inputs`` with a CT: a file or DICOM folder read now (``[ct] series``), or a SimpleITK image in memory (a
    Slicer volume node converted); checked (geometry, voxel values: NaN / inf refused)."""
    if not isinstance(ct, str | os.PathLike):
        return inputs.replace(image=checked_image(ct), image_source="CT", ct_series=None)
    with progress.step("reading CT"):
        fill = open_ct(ct, series_choice(inputs.settings))
        import_in_background("EMRegModule.core.detection.detect")  # while the CT is read: detection follows
        image = fill.result()
    return inputs.replace(image=checked_image(image, str(ct)), image_source=str(ct), ct_series=fill.series)


def check_plan_in_ct(plan: Plan | None, detection: DetectionResult | None, ct_name: str = "the CT") -> None:
    """Refuse a plan outside the extent of the CT the markers were detected in (nothing to check without a plan
    or without detected markers: a registration onto fiducials has no CT)."""
    if plan is None or detection is None or not getattr(detection, "image", None):
        return
    check_plan_in_image(plan, detection.image, ct_name)


def check_plan_for_case(plan: Plan | None, case: Case) -> None:
    """A plan needs a registration: refused (one line) for a case without a calibration recording."""
    if plan is not None and case.calibration is None:
        raise EMRegError(f"{plan.source}: a plan needs a registration, and {case.folder} has no calibration "
                         "recording (calibration.csv or calibration.seq.mha) to register with; add it or leave "
                         "the plan out")


def checked_image(image: sitk.Image, source: str = "CT") -> sitk.Image:
    """A CT in memory (e.g. a Slicer volume node converted to SimpleITK), its geometry and voxel values checked
    (NaN / inf refused)."""
    check_ct_image(image, source)
    return image


def read_recording(path: str | os.PathLike[str], inputs: Inputs) -> TrackingRecording:
    """A tracking recording with the inputs' ports and transform names (a tool's name is its transform's:
    ``Stylus`` reads ``StylusToTracker`` unless ``[sensors] probe_transform`` says otherwise)."""
    settings, tool = inputs.settings, inputs.tool
    named_by_tool = tool is not None and tool.name and settings.sensors.probe_transform is None
    if named_by_tool:
        settings = dataclasses.replace(settings, sensors=dataclasses.replace(
            settings.sensors, probe_transform=f"{tool.name}ToTracker"))
    try:
        return read_recording_file(path, settings, inputs.reference_sensor, inputs.probe_sensor)
    except EMRegError as exc:
        if named_by_tool and f"{tool.name}ToTrackerTransform" in str(exc):
            raise EMRegError(f"{exc} (the tool file {tool.source} names the tool {tool.name})") from None
        raise


def case_recording(case: Case, role: str, inputs: Inputs) -> TrackingRecording | None:
    """A case's recording ``role`` (``navigation``, ``board``); with a tool, read with its transform name."""
    if inputs.tool is None:
        return case.read_recording(role)
    path = getattr(case, role)
    return None if path is None else read_recording(path, inputs)


def series_choice(settings: Settings) -> str | None:
    """``[ct] series`` (a Series Instance UID or a series number) forcing the DICOM series, or None."""
    value = settings.ct.series
    return None if value is None else str(value)


def series_unused(settings: Settings, path: str | os.PathLike[str]) -> list[str]:
    """A series forced (``--series``, ``[ct] series``) for a CT that is one image, not a DICOM folder, is said
    to be ignored rather than silently ignored."""
    if series_choice(settings) is not None and not Path(path).is_dir():
        return [f"the series {series_choice(settings)!r} was asked for, but {path} is one image, not a DICOM "
                "folder: it is read as it is"]
    return []


def check_case_image_side(case: Case) -> None:
    """A case registers onto its CT's markers or onto ``fiducials.mrk.json``: refused (one line) with neither
    or both."""
    if case.ct is None and case.fiducials is None:
        raise EMRegError(f"{case.folder}: no CT found (ct.nrrd, ct.nii.gz, ct.mha or a ct/ DICOM folder) and no "
                         "fiducials.mrk.json")
    if case.ct is not None and case.fiducials is not None:
        raise EMRegError(f"{case.folder}: holds both a CT ({case.ct.name}) and fiducials.mrk.json: register onto one "
                         "of them; move the other out of the case folder")


def case_files(case: Case) -> dict[str, Path | None]:
    """The input files of a case by role (``ct``, ``calibration``...), as provenance names them."""
    return {"ct": case.ct, "calibration": case.calibration, "navigation": case.navigation,
            "targets": case.targets, "board": case.board, "fiducials": case.fiducials}


def run_record(inputs: Inputs, case: Case, summary: list[str]) -> dict[str, Any]:
    """What ``run.json`` records of an ``emreg run`` before its outputs: the case, its CT (or fiducials), the
    version, the ports, the settings; ``summary`` (filled as the stages run)."""
    settings = inputs.settings
    return {"case": str(case.folder.resolve()), "ct": str(case.ct.resolve()) if case.ct is not None else None,
            **({"fiducials": str(case.fiducials.resolve())} if case.ct is None else {}),
            "emreg_version": __version__,
            "reference_sensor": inputs.reference_sensor, "probe_sensor": inputs.probe_sensor,
            "summary": summary, "not_evaluated": {}, "settings_file": settings.source,
            "settings_sha256": settings.digest(), "settings": settings.to_json()}
