"""Live guidance: the plan and the guidance numbers of each published tip pose, over OpenIGTLink in forms 3D Slicer
shows without custom code (OpenIGTLinkIF makes a transform node of a TRANSFORM, a markups point list of a POINT
message and a text node of a STRING).

Published (positions in Slicer's RAS world, as every TRANSFORM of live navigation; mm, degrees):

- TRANSFORM ``TrajectoryToImage``: the planned line's frame, origin at Entry, +Z towards Target (the line runs from 0
  to its length along +Z); ``TargetToImage`` (origin at the target) for a target alone. Sent at the start and once a
  second (a client that connects later gets it).
- POINT ``Plan``: the points ``Entry`` and ``Target``, with the same timing.
- STRING ``Guidance``: ``target 12.31 mm; lateral 1.02 mm; angle 4.4 deg; to go 11.80 mm; target 0.6 mm predicted
  (95 %: 1.0 mm)`` (``-`` where a number is undefined), for the newest published pose, at most
  :data:`GUIDANCE_INTERVAL_S` apart (a readout, not a stream: the tip's TRANSFORM carries every pose).

The numbers are :func:`EMRegModule.core.guidance.guidance`'s, computed per pose without building arrays
(:meth:`LiveGuide.numbers`: a few scalar products, microseconds on the tracker's thread).
"""

from __future__ import annotations

import math
import time

import numpy as np
from pyigtl.messages import PointMessage, StringMessage

from .. import names
from ..core.frames import LPS_TO_RAS
from ..core.guidance import Guidance, Plan, TargetPrediction

#: Device names of what :class:`LiveGuide` publishes.
TRAJECTORY_NAME = "TrajectoryToImage"
TARGET_NAME = "TargetToImage"
PLAN_POINTS_NAME = "Plan"
GUIDANCE_NAME = names.GUIDANCE_NAME

#: Least time (s) between two STRING ``Guidance`` messages (20 Hz: a readout a person reads).
GUIDANCE_INTERVAL_S = 0.05
#: Time (s) between two publications of the plan (TRANSFORM and POINT).
PLAN_INTERVAL_S = 1.0


def trajectory_to_image(plan: Plan) -> np.ndarray:
    """``TrajectoryToImage`` (4x4, image LPS mm): origin at Entry, +Z along Entry -> Target; for a target alone, the
    identity rotation at the target."""
    pose = np.eye(4)
    if plan.entry_mm is None:
        pose[:3, 3] = plan.target_mm
        return pose
    z = plan.direction
    helper = np.array([1.0, 0.0, 0.0]) if abs(z[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    x = np.cross(helper, z)
    x /= np.linalg.norm(x)
    pose[:3, :3] = np.column_stack([x, np.cross(z, x), z])
    pose[:3, 3] = plan.entry_mm
    return pose


class LiveGuide:
    """The guidance of live navigation against ``plan`` (image LPS mm); ``shaft_tip``: the tool's axis in its tip
    frame (:func:`EMRegModule.core.guidance.shaft_in_tip`; None: no angle); ``prediction``: the predicted error at the
    target, said in every ``Guidance`` STRING. Keeps the closest approach of the OK poses it was given."""

    def __init__(self, plan: Plan, shaft_tip: np.ndarray | None = None,
                 prediction: TargetPrediction | None = None) -> None:
        self.plan = plan
        self.shaft_tip = None if shaft_tip is None else np.asarray(shaft_tip, dtype=float)
        self.prediction = prediction
        self._target = np.asarray(plan.target_mm, dtype=float)
        self._u = plan.direction
        self._plan_sent_s = -math.inf
        self._guidance_sent_s = -math.inf
        self.closest: tuple[float, float, np.ndarray, tuple[float, float, float, float]] | None = None

    def numbers(self, tip_to_image: np.ndarray) -> tuple[float, float, float, float]:
        """(target_distance_mm, lateral_mm, angle_deg, to_go_mm) of one tip pose (4x4, image LPS mm); NaN where
        undefined (module :mod:`EMRegModule.core.guidance`)."""
        to_target = self._target - tip_to_image[:3, 3]
        distance = math.sqrt(float(to_target @ to_target))
        if self._u is None:
            return distance, math.nan, math.nan, math.nan
        to_go = float(to_target @ self._u)
        lateral = math.sqrt(max(distance * distance - to_go * to_go, 0.0))
        angle = math.nan
        if self.shaft_tip is not None:
            axis = tip_to_image[:3, :3] @ self.shaft_tip
            cosine = float(axis @ self._u) / math.sqrt(float(axis @ axis))
            angle = math.degrees(math.acos(min(1.0, max(-1.0, cosine))))
        return distance, lateral, angle, to_go

    def observe(self, time_s: float, tip_mm: np.ndarray, numbers: tuple[float, float, float, float]) -> None:
        """Keep the closest approach to the target (a published OK pose at ``time_s``, its tip in image LPS mm)."""
        if self.closest is None or numbers[0] < self.closest[1]:
            self.closest = (time_s, numbers[0], np.array(tip_mm, dtype=float), numbers)

    def text(self, numbers: tuple[float, float, float, float]) -> str:
        """The ``Guidance`` STRING of one pose's numbers."""
        def show(value: float, unit: str) -> str:
            return "-" if value != value else f"{value:.2f} {unit}"

        distance, lateral, angle, to_go = numbers
        text = (f"target {show(distance, 'mm')}; lateral {show(lateral, 'mm')}; angle {show(angle, 'deg')}; "
                f"to go {show(to_go, 'mm')}")
        return text if self.prediction is None else f"{text}; {self.prediction.summary()}"

    def publish(self, server, numbers: tuple[float, float, float, float], now_s: float | None = None) -> None:
        """Send the ``Guidance`` STRING of ``numbers`` unless one went out less than :data:`GUIDANCE_INTERVAL_S`
        ago (the plan is kept published by the navigator's tick, not on each pose: :meth:`keep_plan_published`)."""
        now_s = time.monotonic() if now_s is None else now_s
        if now_s - self._guidance_sent_s >= GUIDANCE_INTERVAL_S:
            self._guidance_sent_s = now_s
            server.send(StringMessage(self.text(numbers), device_name=GUIDANCE_NAME))

    def keep_plan_published(self, server, now_s: float | None = None) -> None:
        """Send the plan (TRANSFORM ``TrajectoryToImage`` / ``TargetToImage`` and POINT ``Plan``, RAS) if it was
        not sent in the last :data:`PLAN_INTERVAL_S`."""
        now_s = time.monotonic() if now_s is None else now_s
        if server is None or now_s - self._plan_sent_s < PLAN_INTERVAL_S:
            return
        self._plan_sent_s = now_s
        name = TRAJECTORY_NAME if self.plan.has_line else TARGET_NAME
        server.send_transform(name, LPS_TO_RAS @ trajectory_to_image(self.plan), time.time())
        points = [("Target", self._target)] if self.plan.entry_mm is None else [
            ("Entry", np.asarray(self.plan.entry_mm, dtype=float)), ("Target", self._target)]
        ras = np.array([LPS_TO_RAS[:3, :3] @ p for _, p in points], dtype=np.float32)
        server.send(PointMessage(positions=ras, names=[n for n, _ in points], device_name=PLAN_POINTS_NAME,
                                 rgba_colors=[[255, 255, 0, 255]] * len(points), diameters=[2.0] * len(points),
                                 groups=["Plan"] * len(points), owners=[""] * len(points)))


def closest_numbers(guide: LiveGuide) -> Guidance | None:
    """The closest approach's numbers as a one-sample :class:`~EMRegModule.core.guidance.Guidance` (None before any)."""
    if guide.closest is None:
        return None
    return Guidance(*(np.array([v]) for v in guide.closest[3]))
