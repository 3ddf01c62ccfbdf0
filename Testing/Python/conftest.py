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

``load_truth(case_dir)`` returns the case's ``truth.json`` as a dict.
"""

from __future__ import annotations

import signal
from pathlib import Path

import pytest
from versions import report_header

from EMRegModule.cli import main
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


@pytest.fixture(autouse=True)
def _signal_handlers_restored():
    """Every test starts with the SIGINT / SIGTERM handlers the session started with.

    Whatever a test leaves installed would otherwise meet later tests: pyigtl's server and client install
    handlers of their own in the thread that makes them and never put the previous ones back, and
    ``emreg`` commands run in-process install their SIGTERM handler. A test that sends itself SIGINT then met
    a stale handler and the run it interrupted ended 0 (a full CI run, not reproduced alone)."""
    saved = {signum: signal.getsignal(signum) for signum in (signal.SIGINT, signal.SIGTERM)}
    yield
    for signum, handler in saved.items():
        if handler is not None and signal.getsignal(signum) is not handler:
            signal.signal(signum, handler)


@pytest.fixture(scope="session")
def standard_case(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A CI-sized standard simulated case folder (see module docstring)."""
    folder = tmp_path_factory.mktemp("standard_case")
    simulate_case(folder, seed=STANDARD_SEED, difficulty="standard", **CI_CASE_OPTIONS)
    return folder


@pytest.fixture(scope="session")
def hard_case(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A CI-sized hard simulated case folder (see module docstring)."""
    folder = tmp_path_factory.mktemp("hard_case")
    simulate_case(folder, seed=HARD_SEED, difficulty="hard", **CI_CASE_OPTIONS)
    return folder


@pytest.fixture(scope="session")
def small_case(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The small case folder (see module docstring); its run's outputs are in ``small_case.parent / "out"``."""
    folder = tmp_path_factory.mktemp("small_case") / "case"
    simulate_case(folder, seed=6, spacing_mm=1.0, **SMALL_CASE_OPTIONS)
    assert main(["run", str(folder), "--out", str(folder.parent / "out"), "--quiet"]) == 0
    return folder
