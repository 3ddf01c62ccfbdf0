"""Simulated cases: CT of the fiducial frame, trakSTAR recordings and their ground truth.

``simulate_case(out_dir, seed=0, difficulty="standard", spacing_mm=None, progress=None, **options)``
writes a case folder per the spec (``ct.nrrd`` or ``ct/``, ``calibration.csv``,
``navigation.csv``, ``targets.mrk.json``, ``board.csv``, ``case.toml``) plus ``truth.json``.
Options are the fields of :class:`SimulationOptions`.
"""

from .case import board_holes, load_truth, simulate_case, simulate_recordings
from .options import SimulationOptions, resolve_options

__all__ = ["SimulationOptions", "board_holes", "load_truth", "resolve_options", "simulate_case", "simulate_recordings"]
