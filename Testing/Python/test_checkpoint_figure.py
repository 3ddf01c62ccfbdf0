"""The report's checkpoint figure (issue 27): the error at each checkpoint over the navigation's time, with the
limit. Checked on its pixels (where the dots lie against the limit line) and in a report of a run whose
navigation had a slipped reference."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import cv2
import numpy as np
from conftest import SMALL_CASE_OPTIONS

from EMRegModule.cli.main import main
from EMRegModule.rendering.checkpoint_chart import checkpoint_chart
from EMRegModule.rendering.plots import HIGHLIGHT, LINE
from EMRegModule.simulation.case import simulate_recordings


def _blobs(image: np.ndarray, color: tuple[int, int, int], min_area: int = 40) -> list[tuple[float, float]]:
    """Centroids (x, y) of the filled dots of ``color`` (components of at least ``min_area`` pixels that are
    about as tall as wide: not the dashed line)."""
    mask = np.all(np.abs(image.astype(int) - color) <= 12, axis=2).astype(np.uint8)
    count, _, stats, centroids = cv2.connectedComponentsWithStats(mask)
    return [tuple(centroids[i]) for i in range(1, count)
            if stats[i, cv2.CC_STAT_AREA] >= min_area
            and 0.6 <= stats[i, cv2.CC_STAT_WIDTH] / stats[i, cv2.CC_STAT_HEIGHT] <= 1.6]


def test_checkpoint_chart_puts_passed_dots_below_the_limit_and_failed_ones_above():
    image = checkpoint_chart([5.0, 12.0, 20.0], [0.3, 0.6, 2.2], [True, True, False], 1.5, jumps_s=[16.0])
    red = np.all(np.abs(image.astype(int) - HIGHLIGHT) <= 30, axis=2)  # the line is anti-aliased
    limit_row = int(np.argmax(red.sum(axis=1)))  # the dashed limit line: the row with the most red
    passed, failed = sorted(_blobs(image, LINE)), _blobs(image, HIGHLIGHT)  # passed: in x order
    assert len(passed) == 2 and len(failed) == 1
    assert all(y > limit_row for _, y in passed) and failed[0][1] < limit_row
    assert passed[0][0] < passed[1][0] < failed[0][0]  # in time order, left to right
    assert passed[0][1] > passed[1][1]  # 0.3 mm lies lower than 0.6 mm


def test_report_shows_the_checkpoints_of_a_navigation(small_case: Path, tmp_path: Path):
    """``emreg run`` on the small case whose navigation rests in four pinholes and whose reference slips 2 mm."""
    case = tmp_path / "case"
    shutil.copytree(small_case, case)
    simulate_recordings(tmp_path / "slip", seed=6, navigation_checkpoints=4, reference_slip_mm=2.0,
                        **SMALL_CASE_OPTIONS)
    shutil.copy(tmp_path / "slip" / "navigation.csv", case / "navigation.csv")
    out = tmp_path / "out"
    assert main(["run", str(case), "--out", str(out), "--quiet"]) == 0
    checkpoints = json.loads((out / "checkpoints.json").read_text())["checkpoints"]
    html = (out / "report.html").read_text(encoding="utf-8")
    assert "Checkpoints during navigation" in html and html.count("FAILED") == sum(not c["ok"] for c in checkpoints)
    image = cv2.imread(str(out / "report_figures" / "checkpoints.png"))[:, :, ::-1]
    assert len(_blobs(image, LINE)) + len(_blobs(image, HIGHLIGHT)) == len(checkpoints) == 4
