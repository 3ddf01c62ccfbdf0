"""Live ``emreg navigate`` with a tool and a plan: the tool file and the plan read and checked before the tracker is
opened, the tip's device name, and what is said at the end (``OUT/navigation.json``, the summary line).

Frames and units: image space (the CT's LPS, mm), ``TipToProbe`` (mm). Heavy modules are imported by the functions
(every command builds the live parsers).
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import TYPE_CHECKING

from ..errors import EMRegError

if TYPE_CHECKING:
    from ..core.registration import RegistrationResult
    from ..core.tool import ToolCalibration
    from ..live.guide import LiveGuide


def _settings_path(settings, name: str) -> Path:
    """A file a settings file names, relative to that file's folder."""
    path = Path(name)
    if not path.is_absolute() and settings.source:
        path = Path(settings.source).parent / path
    return path


def live_tool_and_guide(args: argparse.Namespace, registration: RegistrationResult
                        ) -> tuple[ToolCalibration | None, LiveGuide | None]:
    """The tool (``--tool``, else ``[tool] calibration``) and the guide of the plan (``--plan``, else ``[navigation]
    plan``) of live navigation, each None when not given. Refused (one line): ``--tool auto`` (nothing to solve it
    from live), an unreadable tool or plan file, a plan outside the CT of the markers beside the registration."""
    from ..settings import load_settings

    settings = load_settings(getattr(args, "settings", None), required=True)
    tool = None
    tool_file = getattr(args, "tool", None) or settings.tool.calibration
    if tool_file == "auto":
        raise EMRegError("navigate: --tool auto solves the tip from a calibration recording; give the "
                         "tool_calibration.json that emreg calibrate or emreg run wrote with it instead")
    if tool_file:
        from ..core.tool import read_tool

        tool = read_tool(tool_file if getattr(args, "tool", None) else _settings_path(settings, tool_file),
                         settings.tool.name)
        if settings.tool.name:
            tool.name = settings.tool.name
    plan_file = getattr(args, "plan", None) or settings.navigation.plan
    if not plan_file:
        return tool, None
    from ..core.checkpoints import markers_beside
    from ..core.guidance import predicted_at, shaft_in_tip
    from ..core.plan import check_plan_in_image, read_plan
    from ..live.guide import LiveGuide
    from ..pipeline.navigating import error_model

    plan = read_plan(plan_file if getattr(args, "plan", None) else _settings_path(settings, plan_file))
    markers, _ = markers_beside(args.registration)
    if markers is not None and getattr(markers, "image", None):
        check_plan_in_image(plan, markers.image)
    model = error_model(registration, settings)
    prediction = None if model is None else predicted_at(model, plan.target_mm, tool)
    return tool, LiveGuide(plan, None if tool is None else shaft_in_tip(tool.tip_to_probe), prediction)


def tip_device_name(tool: ToolCalibration | None) -> str:
    """The TRANSFORM's device name: ``ProbeToImage`` without a tool, ``<Name>TipToImage`` for a tool its file names
    (``StylusTipToImage``), else ``TipToImage``."""
    if tool is None:
        return "ProbeToImage"
    return f"{tool.name}TipToImage" if tool.name else "TipToImage"


def live_guidance_summary(guide: LiveGuide) -> str:
    """The closest approach and the predicted error at the target, in one line."""
    closest = ("no OK pose to approach the target" if guide.closest is None else
               f"closest {guide.closest[1]:.2f} mm from the target at {guide.closest[0]:.2f} s")
    return closest if guide.prediction is None else f"{closest}; {guide.prediction.summary()}"


def write_live_guidance(out: Path, guide: LiveGuide, tool: ToolCalibration | None, frames: int) -> None:
    """``OUT/navigation.json`` of live navigation with a plan (as the replay writes it), atomically."""
    from ..core.guidance import GuidanceReport
    from ..io.atomic import atomic_write_json
    from ..live.guide import closest_numbers
    from ..names import NAVIGATION_JSON
    from ..pipeline.navigating import tool_summary

    numbers = closest_numbers(guide)
    closest = None if numbers is None else {name: float(getattr(numbers, name)[0]) for name in
                                            ("target_distance_mm", "lateral_mm", "angle_deg", "to_go_mm")}
    report = GuidanceReport(guide.plan, guide.prediction, None, None if guide.closest is None else guide.closest[0],
                            None if guide.closest is None else guide.closest[2], closest, frames, tool_summary(tool))
    atomic_write_json(out / NAVIGATION_JSON, report.to_json())
