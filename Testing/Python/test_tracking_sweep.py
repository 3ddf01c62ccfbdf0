"""Defects a sweep of tracking recordings found (the ways real operating-room files differ from the spec's
example), each checked at the command line on a small simulated case made here.

- A CSV whose rows are out of time order (sorted by another column, or shuffled) was read as thousands of
  clock resets: no probe row found its reference partner within a segment, and the run stopped with "no
  probe sample has a reference sample at the same time". Rows out of order are now read by their time
  stamps (with a warning) and give the answer the ordered file gives.
"""

from __future__ import annotations

import json
import random
import shutil
from pathlib import Path

import numpy as np
import pytest

from EMRegModule.cli import main
from EMRegModule.simulation import simulate_case

SMALL = {"frame_size_mm": (200.0, 200.0, 110.0), "n_markers": 8, "navigation_rounds": 2, "board_rounds": 3,
         "n_targets": 3}
RECORDINGS = ("calibration.csv", "navigation.csv", "board.csv")


@pytest.fixture(scope="module")
def small_case(tmp_path_factory) -> Path:
    """A small, coarse simulated case (1 mm voxels, 8 markers) and its run's output folder."""
    folder = tmp_path_factory.mktemp("tracking_sweep") / "case"
    simulate_case(folder, seed=6, spacing_mm=1.0, **SMALL)
    assert main(["run", str(folder), "--out", str(folder.parent / "out"), "--quiet"]) == 0
    return folder


def _json(path: Path) -> dict:
    return json.loads(path.read_text())


def _rewrite_rows(case: Path, target: Path, change) -> Path:
    """A copy of ``case`` whose recordings' data rows (header kept) are ``change(rows)``."""
    shutil.copytree(case, target)
    for name in RECORDINGS:
        header, *rows = (case / name).read_text().splitlines()
        (target / name).write_text("\n".join([header, *change(rows)]) + "\n")
    return target


def test_rows_out_of_time_order_give_the_ordered_files_answer(small_case, tmp_path, capsys):
    def shuffled(rows):
        rows = list(rows)
        random.Random(1).shuffle(rows)
        return rows

    case = _rewrite_rows(small_case, tmp_path / "case", shuffled)
    out = tmp_path / "out"
    capsys.readouterr()
    assert main(["run", str(case), "--out", str(out), "--quiet"]) == 0, capsys.readouterr().err
    err = capsys.readouterr().err
    assert "not in time order" in err and "clock reset" in err
    ordered = small_case.parent / "out"
    registration, expected = _json(out / "registration.json"), _json(ordered / "registration.json")
    assert np.allclose(registration["ReferenceToImage"], expected["ReferenceToImage"], atol=1e-9)
    assert registration["pairs"] == expected["pairs"]
    evaluation, expected = _json(out / "evaluation.json"), _json(ordered / "evaluation.json")
    assert evaluation["tre"]["mean_mm"] == pytest.approx(expected["tre"]["mean_mm"], abs=1e-9)
    assert evaluation["board"]["edges"] == expected["board"]["edges"]
    assert (out / "navigation.csv").read_text() == (ordered / "navigation.csv").read_text()
