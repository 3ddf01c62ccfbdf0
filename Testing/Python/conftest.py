"""Shared pytest fixtures: CI-sized simulated cases, generated once per test session.

``standard_case`` and ``hard_case`` are paths of case folders (spec layout plus
``truth.json``) written by :func:`EMRegModule.simulation.simulate_case` into temporary
folders. They keep the frame's character at a smaller size so that they are cheap:
a 220 x 220 x 140 mm frame with 16 markers (the full frame is 350 x 350 x 200 mm with 28).

- standard (seed 11): ``ct.nrrd``, 0.6 mm isotropic (474 x 361 x 452 voxels), grid
  oblique by under 2 degrees, 20 HU noise, labelled calibration recording; about 7 s.
- hard (seed 12): ``ct/`` DICOM series of 349 slices, 0.5 x 0.5 x 0.8 mm (542 x 423 x 349
  voxels), oblique and flipped grid, 35 HU noise, 6 decoys (2 on the patient), 2 calibrated
  markers absent from the CT, 1 CT marker not calibrated, an unlabelled calibration
  recording in which the frame is bumped twice, board.csv with quaternions; about 8 s.

Both have the patient, the couch, the reference sensor with streaks, navigation (6 targets
x 15 dwells) and the board (60 rounds).

``small_case`` (seed 6): a small, coarse case (1 mm voxels, a 200 x 200 x 110 mm frame with 8 markers, 3
targets, 2 navigation and 3 board rounds) with its ``emreg run`` done into ``small_case.parent / "out"``; the
sweeps of tracking recordings and of the report derive their variants from it and compare with that run
(read only); about 4 s.

``standard_run``: ``emreg run`` of the standard case (its OUT folder and the summary it printed), read only.

``small_dicom_case``: the small case's simulation with its CT as a DICOM series (``ct/``), read only.

Each is made once per test run: under pytest-xdist the workers share it (see :func:`_made_once`).

``load_truth(case_dir)`` returns the case's ``truth.json`` as a dict.
"""

from __future__ import annotations

import faulthandler
import fcntl
import io
import locale
import os
import shutil
import signal
import sys
from collections.abc import Callable
from contextlib import redirect_stdout
from pathlib import Path
from typing import NamedTuple

import pytest
from versions import report_header

from EMRegModule.cli.main import main
from EMRegModule.simulation.case import load_truth, simulate_case

#: Options of the CI-sized cases (shared so tests can state what they rely on).
CI_CASE_OPTIONS = {"frame_size_mm": (220.0, 220.0, 140.0), "n_markers": 16}
STANDARD_SEED = 11
HARD_SEED = 12
#: Options of the small case (``small_case``, 1 mm voxels).
SMALL_CASE_OPTIONS = {"frame_size_mm": (200.0, 200.0, 110.0), "n_markers": 8, "navigation_rounds": 2,
                      "board_rounds": 3, "n_targets": 3}

__all__ = ["CI_CASE_OPTIONS", "load_truth"]


def pytest_report_header(config) -> list[str]:
    """The versions results depend on (Python distributions, DICOM tools, the lock), so a failure carries them."""
    return report_header()


#: SIGINT / SIGTERM as a Python process started in the foreground of a terminal has them, which is how users run
#: ``emreg``: Ctrl-C raises KeyboardInterrupt, SIGTERM ends the process.
_FOREGROUND_HANDLERS = {signal.SIGINT: signal.default_int_handler, signal.SIGTERM: signal.SIG_DFL}


class _ProcessState(NamedTuple):
    """What one test could change for every later test of its worker: the working directory, the environment
    variables, the C locale, faulthandler, and the SIGINT / SIGTERM handlers."""

    cwd: str
    environment: dict[str, str]
    locale: str
    faulthandler: bool
    handlers: dict[int, object]

    @classmethod
    def now(cls) -> _ProcessState:
        return cls(os.getcwd(), dict(os.environ), locale.setlocale(locale.LC_ALL), faulthandler.is_enabled(),
                   {signum: signal.getsignal(signum) for signum in _FOREGROUND_HANDLERS})

    def restore(self) -> None:
        if os.getcwd() != self.cwd:
            os.chdir(self.cwd)
        if dict(os.environ) != self.environment:
            os.environ.clear()
            os.environ.update(self.environment)
        if locale.setlocale(locale.LC_ALL) != self.locale:
            locale.setlocale(locale.LC_ALL, self.locale)
        if faulthandler.is_enabled() != self.faulthandler:
            faulthandler.enable(sys.__stderr__) if self.faulthandler else faulthandler.disable()
        for signum, handler in self.handlers.items():
            if handler is not None:
                signal.signal(signum, handler)


@pytest.fixture(scope="session", autouse=True)
def _session_process_state() -> _ProcessState:
    """The process's state as the session began, before any other fixture (autouse, widest scope)."""
    return _ProcessState.now()


@pytest.fixture(autouse=True)
def _process_state_restored(_session_process_state: _ProcessState):
    """Every test starts with SIGINT / SIGTERM as a foreground process has them; after it, the process's state is
    put back as the session began (:class:`_ProcessState`), whatever the test, a fixture of a wider scope or a
    library left behind, so that no test's result depends on which tests ran before it in the same worker (the
    suite runs in a random order: pytest-randomly).

    - Signals: a pytest started in the background of a non-interactive shell (``scripts/test &``, a CI harness,
      ``nohup``) inherits SIGINT ignored and Python keeps it ignored, so a test that sends itself SIGINT saw
      nothing happen (issue 35's three failures); pyigtl's server and client install handlers of their own that
      they never put back.
    - Locale: SimpleITK's GDCM writer leaves every category at "C" (Python's default text encoding then turned
      ASCII for every later test in the worker); tests write DICOM fixtures with it directly.
    The product keeps these itself where it touches them (``emreg`` commands called in-process put their signal
    handlers back, its DICOM writes keep the locale, a study's local Dask cluster keeps the environment: tested in
    test_process_state.py and test_studies.py)."""
    for signum, handler in _FOREGROUND_HANDLERS.items():
        signal.signal(signum, handler)
    yield
    _session_process_state.restore()


def _made_once(tmp_path_factory: pytest.TempPathFactory, name: str, make: Callable[[Path], None]) -> Path:
    """The folder ``name``, filled by ``make(folder)`` once for the whole test run.

    In one process that is a fresh temporary folder per session, as ``tmp_path_factory.mktemp`` gives. Under
    pytest-xdist each worker is a session of its own: the workers of one run share the folder instead, in the
    run's temporary folder (the parent of each worker's own). The first worker that needs it makes it while
    holding a lock; the others wait for it rather than making it again, and a folder left half-made by a
    worker that failed is made again from scratch. Whatever uses it must only read it, as in one process."""
    if os.environ.get("PYTEST_XDIST_WORKER") is None:
        folder = tmp_path_factory.mktemp(name)
        make(folder)
        return folder
    shared = tmp_path_factory.getbasetemp().parent  # the run's, holding the workers' basetemps popen-gw0, ...
    folder, done = shared / name, shared / f"{name}.done"
    with open(shared / f"{name}.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)  # released when the file closes, or when a crashed worker's process ends
        if not done.exists():
            shutil.rmtree(folder, ignore_errors=True)
            folder.mkdir()
            make(folder)
            done.touch()
    return folder


@pytest.fixture(scope="session")
def standard_case(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A CI-sized standard simulated case folder (see module docstring)."""
    return _made_once(tmp_path_factory, "standard_case", lambda folder: simulate_case(
        folder, seed=STANDARD_SEED, difficulty="standard", **CI_CASE_OPTIONS))


@pytest.fixture(scope="session")
def hard_case(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A CI-sized hard simulated case folder (see module docstring)."""
    return _made_once(tmp_path_factory, "hard_case", lambda folder: simulate_case(
        folder, seed=HARD_SEED, difficulty="hard", **CI_CASE_OPTIONS))


def _small_case_and_its_run(folder: Path) -> None:
    simulate_case(folder / "case", seed=6, spacing_mm=1.0, **SMALL_CASE_OPTIONS)
    assert main(["run", str(folder / "case"), "--out", str(folder / "out"), "--quiet"]) == 0


@pytest.fixture(scope="session")
def small_case(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The small case folder (see module docstring); its run's outputs are in ``small_case.parent / "out"``."""
    return _made_once(tmp_path_factory, "small_case", _small_case_and_its_run) / "case"


@pytest.fixture(scope="session")
def small_dicom_case(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The small case's simulation (seed 6, 1 mm voxels, 8 markers) with its CT a DICOM series (``ct/``)."""
    return _made_once(tmp_path_factory, "small_dicom_case", lambda folder: simulate_case(
        folder / "case", seed=6, spacing_mm=1.0, ct_format="dicom", **SMALL_CASE_OPTIONS)) / "case"


class StandardRun(NamedTuple):
    """``emreg run STANDARD_CASE --out OUT --quiet``: its OUT folder and what it printed (the summary)."""

    out: Path
    stdout: str


def _standard_run(standard_case: Path) -> Callable[[Path], None]:
    def make(folder: Path) -> None:
        printed = io.StringIO()
        with redirect_stdout(printed):
            assert main(["run", str(standard_case), "--out", str(folder / "out"), "--quiet"]) == 0
        (folder / "stdout.txt").write_text(printed.getvalue(), encoding="utf-8")

    return make


@pytest.fixture(scope="session")
def standard_run(standard_case: Path, tmp_path_factory: pytest.TempPathFactory) -> StandardRun:
    """``emreg run`` of the standard case, made once for the modules that read its outputs (read only)."""
    folder = _made_once(tmp_path_factory, "standard_run", _standard_run(standard_case))
    return StandardRun(folder / "out", (folder / "stdout.txt").read_text(encoding="utf-8"))


@pytest.fixture
def slicer_app(monkeypatch):
    """Slicer's MRML plus stand-ins for its Qt parts (for the Module and the Widget): ``test_slicer_module``'s
    ``SlicerHarness``, closed after the test (its panels stop observing the scene, as Slicer's ``cleanup`` does)."""
    from test_slicer_module import SlicerHarness

    harness = SlicerHarness(monkeypatch, application=True)
    yield harness
    harness.close()


@pytest.fixture
def slicer_core(monkeypatch):
    """Slicer's MRML only, as the slicer-core wheel gives it: no Qt, no ScriptedLoadableModule (closed after)."""
    from test_slicer_module import SlicerHarness

    harness = SlicerHarness(monkeypatch, application=False)
    yield harness
    harness.close()
