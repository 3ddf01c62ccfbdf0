"""What a tool needs of the sensor it is on, checked before live navigation starts: a 5-DOF sensor (an Aurora
needle's or catheter's coil) measures its axis but not its roll, so only a tip on that axis has a known position.

Frames: ``TipToProbe`` (4x4, mm) maps the tip frame into the sensor's frame; a 5-DOF sensor's axis is its +X as EMReg
reports it (:data:`EMRegModule.devices.aurora.driver.FIVE_DOF_X_TO_NDI`), so the tip's offset from the axis is the
length of its (y, z) in the sensor frame.
"""

from __future__ import annotations

import math

from ..core.tool import ToolCalibration
from ..devices.source_base import SampleSource
from ..errors import EMRegError

#: A tip farther than this (mm) from a 5-DOF sensor's axis is refused: as the unmeasured roll turns, such a tip
#: moves on a circle of this radius (up to twice it from side to side; PLUS issue #286: 2-30 mm, unnoticed).
MAX_5DOF_OFF_AXIS_MM = 0.2


def check_tool_on_port(source: SampleSource, port: int, tool: ToolCalibration) -> None:
    """Refuse (:class:`EMRegError`, one line naming the offset) a tool whose tip is off the axis of the 5-DOF sensor
    on ``port``; a 6-DOF sensor, or one the source cannot tell, takes any tool."""
    if source.port_dof(port) != 5:
        return
    tip = tool.tip_mm
    off_axis = math.hypot(float(tip[1]), float(tip[2]))
    if off_axis > MAX_5DOF_OFF_AXIS_MM:
        where = ", ".join(f"{v:.2f}" for v in tip)
        raise EMRegError(f"{source.description}: port {port} holds a 5-DOF sensor (no roll), and the tool of "
                         f"{tool.source} puts its tip {off_axis:.2f} mm off the sensor's axis (tip [{where}] mm in "
                         "the sensor frame): its position would depend on the unmeasured roll; use a tip on the "
                         f"axis (within {MAX_5DOF_OFF_AXIS_MM:g} mm) or a 6-DOF sensor")
