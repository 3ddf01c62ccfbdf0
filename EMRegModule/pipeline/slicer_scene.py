"""What the 3D Slicer module (``EMRegModule/slicer/EMReg.py``) shows and checks besides the controller's steps:
the nodes of the Logic's results (:mod:`EMRegModule.slicer_export`, the same code as the scene bundle
``EMReg.mrb``), the markups nodes it reads (world RAS, kept in LPS), the OpenIGTLink connector of live
navigation, and the probe pose it shows (Reference frame, under ``ReferenceToImage``). Positions in mm."""

from __future__ import annotations

import numpy as np

from ..core.tracking import TrackingRecording, probe_in_reference
from ..slicer_export.nodes import connect_igtl_client, markups_points_lps, plan_from_markups_node, show_volume
from ..slicer_export.run_scene import build_run_scene, run_scene_of
from ..slicer_export.scene_check import scene_disagreements

__all__ = ["build_run_scene", "connect_igtl_client", "last_probe_to_reference", "markups_points_lps",
           "plan_from_markups_node", "run_scene_of", "scene_disagreements", "show_volume"]


def last_probe_to_reference(recording: TrackingRecording, reference_port: int, probe_port: int) -> np.ndarray:
    """The recording's last probe pose in the Reference frame (``ProbeToReference``, 4 x 4, mm), for the probe
    node that Slicer composes with ``ReferenceToImage``."""
    return probe_in_reference(recording, reference_port, probe_port).probe_to_reference[-1]
