"""Simulated cases: CT of the fiducial frame, trakSTAR recordings and their ground truth.

:func:`EMRegModule.simulation.case.simulate_case` ``(out_dir, seed=0, difficulty="standard", spacing_mm=None,
progress=None, **options)`` writes a case folder per the spec (``ct.nrrd`` or ``ct/``, ``calibration.csv``,
``navigation.csv``, ``targets.mrk.json``, ``board.csv``, ``case.toml``) plus ``truth.json``. Options are the
fields of :class:`EMRegModule.simulation.options.SimulationOptions`. The package re-exports nothing: import
from the module that holds a name.
"""
