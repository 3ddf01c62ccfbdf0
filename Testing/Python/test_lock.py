"""The lock file: made from pyproject.toml as it is, satisfying its ranges, installed exactly, refused when stale."""

from __future__ import annotations

import importlib.util
import os
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest
from packaging.requirements import Requirement

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def lock():
    spec = importlib.util.spec_from_file_location("emreg_lock", ROOT / "scripts" / "lock.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules.setdefault("emreg_lock", module)
    spec.loader.exec_module(module)
    return module


def _declared_requirements() -> list[Requirement]:
    data = tomllib.loads((ROOT / "pyproject.toml").read_text())
    project = data["project"]
    declared = [*project["dependencies"], *data["build-system"]["requires"]]
    for extra in ("test", "aurora", "slicer", "studies", "docs", "robot", "lock"):
        declared += project["optional-dependencies"][extra]
    return [Requirement(text) for text in declared]


def test_the_committed_lock_was_made_from_pyproject_as_it_is(lock):
    assert lock.check() == 0


def test_every_declared_requirement_is_locked_at_a_version_its_range_allows(lock):
    pins = lock.pins()
    for requirement in _declared_requirements():
        name = lock._normalise(requirement.name)
        assert name in pins, f"{requirement} is not in requirements.lock"
        assert requirement.specifier.contains(pins[name], prereleases=True), (requirement, pins[name])


def test_every_locked_file_has_a_hash(lock):
    text = (ROOT / "requirements.lock").read_text()
    blocks = [block for block in text.split("\n") if lock._PIN.match(block)]
    assert len(blocks) == len(lock.pins()) > 50
    for name in lock.pins():
        assert "--hash=sha256:" in lock.requirement_block(name)


@pytest.mark.skipif(os.environ.get("EMREG_LATEST") == "1", reason="scripts/test --latest runs off the lock")
def test_the_environment_is_exactly_the_lock(lock):
    assert lock.diff() == []


@pytest.mark.parametrize("change", ["a new dependency", "a changed range", "a new extra's member"])
def test_a_pyproject_changed_without_relocking_is_refused_in_one_line(lock, tmp_path, change):
    text = (ROOT / "pyproject.toml").read_text()
    if change == "a new dependency":
        text = text.replace('"pydicom>=2.4",', '"pydicom>=2.4",\n    "requests>=2",')
    elif change == "a changed range":
        text = text.replace('"scipy>=1.11"', '"scipy>=1.12"')
    else:
        text = text.replace('"pytest>=8",', '"pytest>=8",\n    "hypothesis",')
    pyproject = tmp_path / "pyproject.toml"
    pyproject.write_text(text)
    assert pyproject.read_text() != (ROOT / "pyproject.toml").read_text()
    script = (f"import sys; sys.path.insert(0, {str(ROOT / 'scripts')!r}); import lock; from pathlib import Path; "
              f"sys.exit(lock.check(Path({str(pyproject)!r})))")
    result = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True)
    assert result.returncode == 1
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and "scripts/lock" in lines[0] and "out of date" in lines[0], result.stderr


def test_setup_stops_before_installing_when_the_lock_is_stale(tmp_path):
    """scripts/setup on a copy whose pyproject gained a dependency: exit 1, one line naming scripts/lock."""
    copy = tmp_path / "repo"
    (copy / "scripts").mkdir(parents=True)
    for name in ("setup", "lock.py"):
        (copy / "scripts" / name).write_bytes((ROOT / "scripts" / name).read_bytes())
    (copy / "scripts" / "setup").chmod(0o755)
    (copy / "requirements.lock").write_bytes((ROOT / "requirements.lock").read_bytes())
    text = (ROOT / "pyproject.toml").read_text().replace('"pydicom>=2.4",', '"pydicom>=2.4",\n    "requests>=2",')
    (copy / "pyproject.toml").write_text(text)
    env = {**os.environ, "PATH": os.environ.get("PATH", ""), "PYTHON": sys.executable}
    result = subprocess.run(["bash", str(copy / "scripts" / "setup")], capture_output=True, text=True, env=env,
                            timeout=600)
    assert result.returncode == 1
    assert not (copy / ".venv").exists()  # nothing installed
    lines = [line for line in result.stderr.splitlines() if line.strip()]
    assert lines[-1].startswith("requirements.lock is out of date") and "scripts/lock" in lines[-1], result.stderr
