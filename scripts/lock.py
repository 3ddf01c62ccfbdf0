"""The lock file: every Python distribution ``scripts/setup`` installs, at one version, with hashes.

``requirements.lock`` is a pip requirements file (``name==version --hash=sha256:...``) resolved by uv for
CPython 3.11 on Linux x86-64 from ``pyproject.toml``: the core dependencies, the extras setup installs, the
build backend (installed without build isolation, so the editable build uses locked tools too) and pip
itself. Its header records a digest of the declarations it was resolved from, so a ``pyproject.toml``
edited without re-locking is caught before anything is installed.

    python scripts/lock.py check          # exit 1, one line, when the lock does not match pyproject.toml
    python scripts/lock.py refresh        # re-resolve the lock from pyproject.toml, keeping the versions it pins
    python scripts/lock.py upgrade        # re-resolve the lock from pyproject.toml's ranges (newest allowed)
    python scripts/lock.py pins           # print "name==version" for every locked distribution
    python scripts/lock.py pip            # print pip's own locked requirement (with its hashes)
    python scripts/lock.py diff           # compare the installed distributions with the lock

Standard library only: ``check`` runs before the virtual environment holds anything.
"""

from __future__ import annotations

import hashlib
import json
import os
import re
import subprocess
import sys
import tempfile
import tomllib
from importlib import metadata
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
PYPROJECT = ROOT / "pyproject.toml"
LOCK = ROOT / "requirements.lock"
# The extras scripts/setup installs; the lock covers exactly these.
EXTRAS = ("test", "aurora", "slicer", "studies", "docs", "robot", "lock")
# Installed outside the resolution of pyproject's dependencies, but locked all the same.
TOOLING = ("pip",)
PYTHON_VERSION = "3.11"
PLATFORM = "x86_64-manylinux_2_28"
DIGEST_LINE = "# inputs-sha256: "
REFRESH_COMMAND = "scripts/lock"
_PIN = re.compile(r"^([A-Za-z0-9][A-Za-z0-9._-]*)==([^\s\\;]+)")


def _normalise(name: str) -> str:
    return re.sub(r"[-_.]+", "-", name).lower()


def inputs_digest(pyproject: Path = PYPROJECT) -> str:
    """sha256 of the declarations the lock is resolved from (order-insensitive, whitespace-insensitive)."""
    data = tomllib.loads(pyproject.read_text(encoding="utf-8"))
    project = data.get("project", {})
    extras = project.get("optional-dependencies", {})
    declared = {
        "requires-python": project.get("requires-python", ""),
        "build-system": sorted(data.get("build-system", {}).get("requires", [])),
        "dependencies": sorted(project.get("dependencies", [])),
        "extras": {name: sorted(extras.get(name, [])) for name in EXTRAS},
        "tooling": list(TOOLING),
        "target": [PYTHON_VERSION, PLATFORM],
    }
    canonical = json.dumps(declared, sort_keys=True, separators=(",", ":"))
    return hashlib.sha256(re.sub(r"\s+", "", canonical).encode()).hexdigest()


def recorded_digest(lock: Path = LOCK) -> str | None:
    """The digest the lock's header records, or None for a lock without one."""
    for line in lock.read_text(encoding="utf-8").splitlines():
        if line.startswith(DIGEST_LINE):
            return line[len(DIGEST_LINE):].strip()
    return None


def pins(lock: Path = LOCK) -> dict[str, str]:
    """{normalised name: version} of every distribution the lock pins."""
    found: dict[str, str] = {}
    for line in lock.read_text(encoding="utf-8").splitlines():
        match = _PIN.match(line)
        if match:
            found[_normalise(match.group(1))] = match.group(2)
    return found


def requirement_block(name: str, lock: Path = LOCK) -> str:
    """The lock's lines for one distribution: its pin and its hashes."""
    lines = lock.read_text(encoding="utf-8").splitlines()
    for index, line in enumerate(lines):
        match = _PIN.match(line)
        if match and _normalise(match.group(1)) == _normalise(name):
            block = [line]
            while block[-1].rstrip().endswith("\\") and index + len(block) < len(lines):
                block.append(lines[index + len(block)])
            return "\n".join(block).rstrip(" \\") + "\n"
    raise SystemExit(f"{lock.name} does not lock {name}")


def check(pyproject: Path = PYPROJECT, lock: Path = LOCK) -> int:
    """0 when the lock was resolved from pyproject.toml as it is now; else one line naming the fix."""
    if not lock.is_file():
        print(f"{lock.name} is missing: run {REFRESH_COMMAND} to make it from pyproject.toml", file=sys.stderr)
        return 1
    if recorded_digest(lock) != inputs_digest(pyproject):
        print(
            f"{lock.name} is out of date with pyproject.toml's dependencies: run {REFRESH_COMMAND} to refresh it",
            file=sys.stderr,
        )
        return 1
    return 0


def _uv() -> list[str]:
    """A uv to resolve with: the locked one in .venv, else one installed into a throw-away environment."""
    venv_uv = ROOT / ".venv" / "bin" / "uv"
    if venv_uv.is_file():
        return [str(venv_uv)]
    tool = Path(tempfile.mkdtemp(prefix="emreg-uv-"))
    subprocess.run([sys.executable, "-m", "venv", str(tool)], check=True)
    subprocess.run([str(tool / "bin" / "python"), "-m", "pip", "install", "-q", "uv"], check=True)
    return [str(tool / "bin" / "uv")]


def refresh(upgrade: bool = False) -> int:
    """Resolve pyproject.toml into requirements.lock (hashes of every file). The versions the lock pins already
    are kept wherever the declarations still allow them (uv prefers the pins of the file it writes), so adding
    one dependency does not move every other; ``upgrade`` resolves the newest versions the ranges allow."""
    data = tomllib.loads(PYPROJECT.read_text(encoding="utf-8"))
    with tempfile.TemporaryDirectory() as tmp:
        extra_inputs = Path(tmp) / "build-and-tooling.in"
        extra_inputs.write_text("\n".join([*data["build-system"]["requires"], *TOOLING]) + "\n")
        resolved = Path(tmp) / "requirements.lock"
        if LOCK.is_file() and not upgrade:
            resolved.write_text(LOCK.read_text(encoding="utf-8"), encoding="utf-8")
        command = [
            *_uv(), "pip", "compile", str(PYPROJECT), str(extra_inputs),
            *[arg for extra in EXTRAS for arg in ("--extra", extra)],
            "--generate-hashes", "--python-version", PYTHON_VERSION, "--python-platform", PLATFORM,
            "--no-header", "--quiet", "--output-file", str(resolved), *(["--upgrade"] if upgrade else []),
        ]
        subprocess.run(command, check=True, cwd=ROOT, env={**os.environ, "UV_NO_CONFIG": "1"})
        body = resolved.read_text(encoding="utf-8").replace(tmp + "/", "").replace(str(ROOT) + "/", "")
    header = (
        "# EMReg's lock: every distribution scripts/setup installs, for CPython "
        f"{PYTHON_VERSION} on Linux x86-64.\n"
        f"# Made by `{REFRESH_COMMAND}` (uv pip compile --generate-hashes) from pyproject.toml; do not edit.\n"
        f"# Extras: {', '.join(EXTRAS)}; plus the build backend and pip.\n"
        f"{DIGEST_LINE}{inputs_digest()}\n"
    )
    LOCK.write_text(header + body, encoding="utf-8")
    print(f"{LOCK.name}: {len(pins())} distributions locked")
    return 0


def installed() -> dict[str, str]:
    """{normalised name: version} of the distributions in the running interpreter's environment."""
    return {_normalise(dist.metadata["Name"]): dist.version for dist in metadata.distributions()}


def diff(ignore: tuple[str, ...] = ("emreg",)) -> list[str]:
    """One line per distribution whose installed version differs from the lock (or is not locked)."""
    locked, have = pins(), installed()
    lines = []
    for name in sorted(set(locked) | set(have)):
        if name in ignore or locked.get(name) == have.get(name):
            continue
        lines.append(f"{name}: lock {locked.get(name, '-')}, installed {have.get(name, '-')}")
    return lines


def main(argv: list[str]) -> int:
    command = argv[0] if argv else "check"
    if command == "check":
        return check()
    if command in ("refresh", "upgrade"):
        return refresh(upgrade=command == "upgrade")
    if command == "pins":
        print("\n".join(f"{name}=={version}" for name, version in sorted(pins().items())))
        return 0
    if command == "pip":
        sys.stdout.write(requirement_block("pip"))
        return 0
    if command == "diff":
        lines = diff()
        print("\n".join(lines) if lines else "installed distributions equal the lock")
        return 1 if lines else 0
    print(f"unknown command {command!r}: check, refresh, pins, pip or diff", file=sys.stderr)
    return 2


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
