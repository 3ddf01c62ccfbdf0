"""The modules every command loads stay free of libraries only some stages use.

An import at the top of a core module runs in every command that touches it: scipy.stats and
scipy.optimize at the top of ``error_model`` (which ``registration`` imports) once added about a
second of CPU to ``emreg report`` and ``emreg run`` at 0.6 mm (bench_report: the report's CPU from
5.2 s to 6.2 s) for a check only the evaluation makes. pyvista (with matplotlib.pyplot) belongs to
the rendering, slicer-core to the bundle's own process, pydicom to DICOM folders. Timings live in
``scripts/bench_*``; this checks which modules are loaded, which does not depend on the machine.
"""

from __future__ import annotations

import json
import subprocess
import sys

#: Modules each command imports before it knows what it will do (command line, controller, stage modules).
CORE = ("EMRegModule.cli.main", "EMRegModule.pipeline.controller", "EMRegModule.core.detection.detect",
        "EMRegModule.core.registration", "EMRegModule.core.calibration", "EMRegModule.core.evaluation",
        "EMRegModule.core.navigation", "EMRegModule.report.writer", "EMRegModule.report.batch",
        "EMRegModule.slicer_export.bundle", "EMRegModule.slicer_export.run_scene", "EMRegModule.io.image")

#: Libraries none of them may load at import time.
HEAVY = ("scipy.stats", "scipy.optimize", "matplotlib", "pyvista", "slicer", "vtkmodules.vtkRenderingCore",
         "pydicom", "dask")


def _printed_by(script: str):
    """What ``script``, run by a fresh interpreter (nothing imported before it), prints last, as JSON."""
    result = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stderr
    return json.loads(result.stdout.strip().splitlines()[-1])


def test_core_modules_load_no_stage_specific_library():
    script = (
        "import importlib, json, sys\n"
        f"heavy = {HEAVY!r}\n"
        "loaded = {}\n"
        f"for name in {CORE!r}:\n"
        "    importlib.import_module(name)\n"
        "    loaded[name] = [h for h in heavy if h in sys.modules and h not in sum(loaded.values(), [])]\n"
        "print(json.dumps(loaded))\n"
    )
    loaded = _printed_by(script)
    assert set(loaded) == set(CORE)
    assert {name: found for name, found in loaded.items() if found} == {}


def test_the_parser_loads_no_command():
    """``emreg --help`` and the parsing of every command build the whole parser: it loads the argument declarations
    and the base modules only (no numpy, no pipeline, device or algorithm); a command's modules are imported when it
    runs (``cli/main.py``'s ``COMMANDS``)."""
    script = (
        "import json, sys\n"
        "from EMRegModule.cli.main import build_parser\n"
        "build_parser().parse_args(['robot-go', '--robot', 'franka://h', '--tracker', 'igtl://h', '--target', 't'])\n"
        "print(json.dumps(sorted(n for n in sys.modules if n.startswith('EMRegModule') or n == 'numpy')))\n"
    )
    loaded = _printed_by(script)
    assert loaded == ["EMRegModule", "EMRegModule.cli", "EMRegModule.cli.main", "EMRegModule.cli.options",
                      "EMRegModule.errors", "EMRegModule.interrupts", "EMRegModule.names"]
