"""What the test results depend on, for the header of every test session (and so of every failure report).

The Python distributions are read from their installed metadata (nothing is imported); the DICOM tools
print their own versions. The last line says whether the environment is exactly ``requirements.lock``.
"""

from __future__ import annotations

import importlib.util
import re
import shutil
import subprocess
import sys
from importlib import metadata
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
#: Distributions whose versions move results: numerics, image I/O, rendering, Slicer's MRML.
DISTRIBUTIONS = ("numpy", "scipy", "SimpleITK", "vtk", "pyvista", "opencv-python-headless", "slicer-core",
                 "pydicom", "isal")
#: Command-line tools the DICOM tests call, with the argument that makes each print its version.
TOOLS = (("gdcmconv", "--version"), ("dcmdump", "--version"), ("dcm2niix", "--version"))


def distribution_versions() -> list[str]:
    """``name version`` for each of :data:`DISTRIBUTIONS` (``name -`` when it is not installed)."""
    found = []
    for name in DISTRIBUTIONS:
        try:
            found.append(f"{name} {metadata.version(name)}")
        except metadata.PackageNotFoundError:
            found.append(f"{name} -")
    return found


def tool_versions() -> list[str]:
    """``tool version`` for each of :data:`TOOLS` (``tool -`` when it is not on the PATH)."""
    found = []
    for tool, flag in TOOLS:
        if shutil.which(tool) is None:
            found.append(f"{tool} -")
            continue
        try:
            printed = subprocess.run([tool, flag], capture_output=True, text=True, timeout=10)
        except (OSError, subprocess.SubprocessError):
            found.append(f"{tool} ?")
            continue
        match = re.search(r"v?(\d+\.\d+(?:\.\d+)*)", printed.stdout + printed.stderr)
        found.append(f"{tool} {match.group(1) if match else '?'}")
    return found


def lock_state() -> str:
    """Whether the installed distributions are exactly ``requirements.lock``'s, and if not, how many differ."""
    spec = importlib.util.spec_from_file_location("emreg_lock", ROOT / "scripts" / "lock.py")
    if spec is None or spec.loader is None or not (ROOT / "requirements.lock").is_file():
        return "no requirements.lock"
    lock = importlib.util.module_from_spec(spec)
    sys.modules.setdefault("emreg_lock", lock)
    spec.loader.exec_module(lock)
    differences = lock.diff()
    if not differences:
        return "installed = requirements.lock"
    return f"{len(differences)} distributions differ from requirements.lock: " + "; ".join(differences[:12])


def report_header() -> list[str]:
    """The lines pytest prints under its own header."""
    return [
        "versions: " + ", ".join(distribution_versions()),
        "tools: " + ", ".join(tool_versions()),
        "lock: " + lock_state(),
    ]
