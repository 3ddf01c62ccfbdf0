"""Defects a sweep of the verification report found (does the page say exactly what the outputs say, and never
more?), each checked on a small simulated case made here.

- ``emreg report --batch DIR`` checked every folder's outputs before rendering any: one folder mixing two runs'
  outputs stopped the whole batch (exit 2) and no good folder was reported. Each job now checks its own folder:
  the good folders are reported, the mixed one is named in the one-line error (exit 2, as a failed report).
- A section with nothing to show gave a cause of its own instead of the run's: an unreadable ``board.csv`` read
  "needs board.csv in the case" (the case has one), and every evaluation section of a run refused at the
  registration (exit 3) said the case lacked its recordings. The page now gives the reason the outputs record
  (``not_evaluated`` in ``evaluation.json``/``run.json``, or the run's refusal in ``run.json``). The TRE table's
  note also claimed the registration's share is "far smaller" whatever the numbers; it now says what the column is.
- A warning ``registration.json`` repeats from the calibration (rows of status MISSING in ``calibration.csv``)
  was shown twice on the page, as if there were two problems; and ``emreg run`` did not print the board
  recording's own warnings (rows left out, time segments) on stderr, though they were in ``evaluation.json`` and
  on the page. Each is now said once in both places.
- A marker left unpaired was two warnings: the registration's own ("CT marker(s) I02 paired with no calibration
  point ...") and the report's ("1 detected marker(s) not paired: I02"). The report now adds its line only for
  names the registration's warnings do not give.
- The FRE(l) plot's dot read "chosen l = 15.88 mm, FRE 0.33 mm" beside a registration of FRE 0.30 mm: the stored
  curve is sampled every 0.25 mm and near a sharp minimum the straight line between two samples passes above the
  FRE at the chosen l. The curve now goes through the registration's own point (l, FRE).
- A navigation recording the run could not use ("navigation not made: ...", on stderr and in ``run.json``'s
  ``not_evaluated``) was not on the page, which showed no navigated path and no sample count without saying why.
- The 3D view's caption named a reference sensor, calibration points, sensor points, targets and a probe path
  whatever the run had: a detection-only run's view "showed" all of them. The caption now names what the scene
  holds.
- A long label (a target's or a pinhole's, 300 characters) broke the figures: drawn vertically under the TRE bar
  chart it took the whole height (no bar left to see), under the error budget it ran over the neighbouring
  targets' labels, and in a marker's caption on the CT slices it ran into the next marker's caption and hid
  that marker's residual. Labels are now cut to their room with a visible "..." (the tables hold them whole).
- ``emreg report OUT`` read the CT ``run.json`` names without checking it was still the run's: a CT replaced
  since (here shifted by 10 voxels, same grid) was drawn under the markers found in the other, and the page said
  "No warnings". The report's own read of the CT now computes its sha256 in the same pass and refuses a CT whose
  sha256 differs from the recorded one (exit 2, one line; no page, no figures and no bundle left in OUT).

What held (checked here or by hand on the same cases): every number on the page equals its output file's, in
the same rounding; labels and paths (``<b>T1</b>``, ``T&1 "quoted"``, ``Zielpunkt ä``, folders with spaces and
``#``) are escaped, never injected; every warning ``emreg run`` printed and every "not evaluated" reason is on
the page; ``emreg report`` on one mixed folder refuses it (exit 2).
"""

from __future__ import annotations

import csv
import io
import json
import re
import shutil
from pathlib import Path

import numpy as np
import pytest

from EMRegModule.cli.main import main
from EMRegModule.rendering.error_views import error_budget_chart
from EMRegModule.rendering.plots import BAR, bar_chart

LONG = "L" + "x" * 298 + "Z"


def _page_text(out: Path) -> str:
    """The page's visible text, tags and figures left out, entities resolved, white space collapsed."""
    import html

    text = re.sub(r"<figure.*?</figure>|<style>.*?</style>", " ", (out / "report.html").read_text(encoding="utf-8"),
                  flags=re.S)
    return re.sub(r"\s+", " ", html.unescape(re.sub(r"<[^>]+>", " ", text)))


def _scene_caption(out: Path) -> str:
    """The caption of the page's 3D view (the page is UTF-8 whatever the locale)."""
    page = (out / "report.html").read_text(encoding="utf-8")
    return re.search(r"<b>3D view of the frame\.</b>([^<]*)", page).group(1)


def _warnings_text(out: Path) -> str:
    """The text of the page's Warnings section."""
    return _page_text(out).split(" Warnings ", 1)[1].split(" Frame in 3D ", 1)[0]


def _relabelled(case: Path, target: Path, names: dict[str, str]) -> Path:
    """A copy of ``case`` whose target and pinhole labels (``names``: old -> new) are renamed everywhere."""
    shutil.copytree(case, target)
    for name in ("navigation.csv", "calibration.csv"):
        rows = list(csv.reader((case / name).read_text().splitlines()))
        written = io.StringIO()
        csv.writer(written, lineterminator="\n").writerows([rows[0]] + [[*r[:-1], names.get(r[-1], r[-1])]
                                                                         for r in rows[1:]])
        (target / name).write_text(written.getvalue(), encoding="utf-8")
    markups = json.loads((case / "targets.mrk.json").read_text())
    for point in markups["markups"][0]["controlPoints"]:
        point["label"] = names.get(point["label"], point["label"])
    (target / "targets.mrk.json").write_text(json.dumps(markups, ensure_ascii=False), encoding="utf-8")
    return target


def test_batch_reports_the_good_folders_and_names_a_mixed_one(small_case, labelled_run, tmp_path, capsys):
    """Two good run folders, one holding another run's registration.json, an empty folder."""
    out = small_case.parent / "out"
    batch = tmp_path / "batch"
    for name in ("good_a", "good_b", "mixed"):
        shutil.copytree(out, batch / name)
        (batch / name / "report.html").unlink()
    shutil.copy(labelled_run / "registration.json", batch / "mixed" / "registration.json")
    (batch / "empty").mkdir()
    capsys.readouterr()
    assert main(["report", "--batch", str(batch), "--jobs", "2", "--quiet"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "1 of 3 reports failed" in err and str(batch / "mixed") in err, err
    for name in ("good_a", "good_b"):
        assert "FRE" in _page_text(batch / name)
    assert not (batch / "mixed" / "report.html").exists() and not (batch / "empty" / "report.html").exists()


def test_batch_leaves_a_case_folder_beside_the_runs_alone(small_case, tmp_path, capsys):
    """A case folder kept beside its run (its navigation.csv is a tracking recording, named like the run's
    mapped probe path) is neither reported nor written into; asked for by name, there is nothing to report."""
    batch = tmp_path / "batch"
    shutil.copytree(small_case, batch / "case")
    shutil.copytree(small_case.parent / "out", batch / "out")
    (batch / "out" / "report.html").unlink()
    before = sorted(p.name for p in (batch / "case").iterdir())
    capsys.readouterr()
    assert main(["report", "--batch", str(batch), "--quiet"]) == 0, capsys.readouterr().err
    assert "1 reports written" in capsys.readouterr().out
    assert sorted(p.name for p in (batch / "case").iterdir()) == before
    assert "FRE" in _page_text(batch / "out")
    assert main(["report", str(batch / "case"), "--quiet"]) == 2
    assert "nothing to report" in capsys.readouterr().err


def test_an_unreadable_board_recording_is_named_as_the_boards_reason(small_case, tmp_path, capsys):
    case = tmp_path / "case"
    shutil.copytree(small_case, case)
    (case / "board.csv").write_text("garbage\n1,2\n")
    assert main(["run", str(case), "--out", str(tmp_path / "out"), "--quiet"]) == 0
    warned = [line for line in capsys.readouterr().err.splitlines() if "board not evaluated" in line]
    reason = json.loads((tmp_path / "out" / "run.json").read_text())["not_evaluated"]["board"]
    assert len(warned) == 1 and reason in warned[0]
    board = _page_text(tmp_path / "out").split("Board phantom", 1)[1]
    assert f"Not evaluated: {reason}" in board and "needs board.csv" not in board


def test_a_run_refused_at_registration_is_the_reason_its_later_sections_give(small_case, tmp_path, capsys):
    case = tmp_path / "case"
    shutil.copytree(small_case, case)
    with open(case / "case.toml", "a", encoding="utf-8") as settings:
        settings.write("\n[registration]\nmax_fre_mm = 0.05\n")
    out = tmp_path / "out"
    assert main(["run", str(case), "--out", str(out), "--quiet"]) == 3
    assert main(["report", str(out), "--quiet"]) == 0
    run = json.loads((out / "run.json").read_text())
    assert run["status"] == "refused"
    text = _page_text(out)
    assert f"Refused: {[line for line in run['summary'] if 'refused' in line][0]}" in text
    said = f"Not shown: the run was refused: {run['message']}"
    for section in ("Registration", "Target registration error", "Board phantom"):
        body = text.split(f" {section} ", 1)[1]
        assert body.lstrip().startswith(said), (section, body[:300])
    assert "needs navigation.csv" not in text and "needs board.csv" not in text


def test_every_warning_of_a_run_is_said_once_on_stderr_and_once_on_the_page(small_case, tmp_path, capsys):
    """Rows of status MISSING in the calibration and board recordings (every 7th moment)."""
    case = tmp_path / "case"
    shutil.copytree(small_case, case)
    for name in ("calibration.csv", "board.csv"):
        header, *rows = (small_case / name).read_text().splitlines()
        marked = [f"{row},{'MISSING' if (i // 2) % 7 == 3 else 'OK'}" for i, row in enumerate(rows)]
        (case / name).write_text("\n".join([f"{header},status", *marked]) + "\n")
    out = tmp_path / "out"
    capsys.readouterr()
    assert main(["run", str(case), "--out", str(out), "--quiet"]) == 0
    said = [re.sub(r"^emreg run: warning: ", "", line) for line in capsys.readouterr().err.splitlines()]
    assert any("board.csv" in line and "status other than OK" in line for line in said), said
    assert any("calibration.csv" in line and "status other than OK" in line for line in said), said
    warnings = _warnings_text(out)
    for line in said:
        assert warnings.count(re.sub(r"\s+", " ", line)) == 1, line


def test_an_unpaired_marker_is_one_warning(small_case, tmp_path, capsys):
    """The calibration recording cut before its last pinholes: a marker of the CT is left unpaired."""
    case = tmp_path / "case"
    shutil.copytree(small_case, case)
    header, *rows = (small_case / "calibration.csv").read_text().splitlines()
    (case / "calibration.csv").write_text("\n".join([header, *rows[: int(len(rows) * 0.87) // 2 * 2]]) + "\n")
    out = tmp_path / "out"
    assert main(["run", str(case), "--out", str(out), "--quiet"]) == 0
    unpaired = json.loads((out / "registration.json").read_text())["unpaired_image_markers"]
    assert unpaired
    warnings = _warnings_text(out)
    for name in unpaired:
        assert len(re.findall(rf"(?<![\w-]){name}(?![\w-])", warnings)) == 1, warnings


def test_a_navigation_recording_that_could_not_be_used_is_said_on_the_page(small_case, tmp_path, capsys):
    case = tmp_path / "case"
    shutil.copytree(small_case, case)
    (case / "navigation.csv").write_text("garbage\n")
    out = tmp_path / "out"
    capsys.readouterr()
    assert main(["run", str(case), "--out", str(out), "--quiet"]) == 0
    said = [re.sub(r"^emreg run: warning: ", "", line) for line in capsys.readouterr().err.splitlines()]
    assert any(line.startswith("navigation not made: ") for line in said), said
    warnings = _warnings_text(out)
    for line in said:
        assert warnings.count(re.sub(r"\s+", " ", line)) == 1, line
    caption = _scene_caption(out)
    assert "probe path" not in caption and "targets (red)" in caption


def test_the_3d_views_caption_names_only_what_a_detection_only_run_has(small_case, tmp_path):
    out = tmp_path / "out"
    assert main(["detect", str(small_case), "--out", str(out), "--quiet"]) == 0
    assert main(["report", str(out), "--quiet"]) == 0
    caption = _scene_caption(out)
    assert caption.strip().startswith("Fitted marker models (grey: no registration)"), caption
    for absent in ("residual", "reference sensor", "calibration points", "sensor points", "targets", "probe path"):
        assert absent not in caption, (absent, caption)


def test_the_fre_curves_dot_is_the_registrations_fre_at_its_l(small_case, monkeypatch):
    from EMRegModule.report import figures
    from EMRegModule.report.derived import calibration_points, marker_rows, report_fre_curve
    from EMRegModule.report.inputs import load_report_inputs

    inputs = load_report_inputs(small_case.parent / "out", read_image=False)
    rows, points = marker_rows(inputs.detection, inputs.registration), calibration_points(inputs.frame_calibration)
    curve, stored = report_fre_curve(inputs, rows, points)
    drawn = {}
    monkeypatch.setattr(figures, "line_chart", lambda x, y, *args, **kwargs: drawn.update(x=x, y=y, **kwargs)
                        or np.zeros((2, 2, 3), np.uint8))
    figures.render_fre_curve(figures.ReportData(inputs, rows, points, curve, stored))
    registration = inputs.registration
    said = float(np.interp(registration.sensor_offset_l_mm, drawn["x"], drawn["y"]))
    assert stored and said == pytest.approx(registration.fre_mm, abs=0.005)
    assert drawn["marker_label"].endswith(f"FRE {registration.fre_mm:.2f} mm"), drawn["marker_label"]


def test_the_tre_note_claims_nothing_the_numbers_do_not_say(small_case):
    text = _page_text(small_case.parent / "out")
    assert "far smaller" not in text and "registration's share: its registration term alone" in text


@pytest.fixture(scope="module")
def labelled_run(small_case, tmp_path_factory) -> Path:
    """The case with labels that are markup, entities, quotes, non-ASCII and 300 characters long, in a folder whose
    path holds a space and a ``#``; its run's output folder."""
    root = tmp_path_factory.mktemp("report_sweep_labels")
    names = {"T1": "<b>T1</b>", "T2": 'T&1 "quoted"', "T3": f"Zielpunkt ä {LONG}",
             "M01": "<script>alert(1)</script>", "M02": "M&2", "M04": "Zielpunkt ä", "M05": LONG}
    case = _relabelled(small_case, root / "label case #1", names)
    out = root / "label out #1"
    assert main(["run", str(case), "--out", str(out), "--quiet"]) == 0
    return out


def test_labels_and_paths_are_escaped_and_whole_on_the_page(labelled_run):
    page = (labelled_run / "report.html").read_text(encoding="utf-8")
    assert "<b>T1</b>" not in page and "<script>" not in page and 'T&1 "' not in page
    text = _page_text(labelled_run)
    calibration = json.loads((labelled_run / "frame_calibration.json").read_text())
    targets = json.loads((labelled_run / "evaluation.json").read_text())["tre"]["targets"]
    for label in [p["label"] for p in calibration["points"]] + list(targets):
        assert f" {label} " in text, label[:40]
    assert "label case #1" in text and "label out #1" in text


def _ink_columns(image: np.ndarray, rows: slice) -> np.ndarray:
    """Columns of ``image`` holding anything but white within ``rows``."""
    return np.flatnonzero((image[rows] < 250).any(axis=(0, 2)))


def test_a_long_label_leaves_the_bars_of_a_bar_chart_their_height():
    short = bar_chart(["T1", "T2", "T3"], [0.4, 0.35, 0.36], errors=[0.1, 0.02, 0.05])
    long = bar_chart(["T1", "T2", f"Zielpunkt {LONG}"], [0.4, 0.35, 0.36], errors=[0.1, 0.02, 0.05])
    bar_pixels = [int(np.all(chart == np.asarray(BAR, dtype=np.uint8), axis=2).sum()) for chart in (short, long)]
    assert bar_pixels[1] > 0.5 * bar_pixels[0], bar_pixels


def test_a_long_label_stays_under_its_own_target_in_the_error_budget():
    budget = {"registration": [0.15, 0.15, 0.15], "tracking": [0.27, 0.27, 0.27]}
    plain = error_budget_chart(["A", "", "B"], budget, [0.4, 0.35, 0.36])
    long = error_budget_chart(["A", LONG, "B"], budget, [0.4, 0.35, 0.36])
    label_rows = slice(plain.shape[0] - 26, plain.shape[0])
    changed = _ink_columns(np.abs(long.astype(int) - plain.astype(int)).astype(np.uint8) ^ 255, label_rows)
    left, right = 62, plain.shape[1] - 20
    slot = (right - left) / 3
    assert changed.size and changed.min() >= left + slot and changed.max() < left + 2 * slot, changed


def test_a_long_pinhole_label_keeps_the_residual_in_the_markers_caption(labelled_run):
    from EMRegModule.rendering.slices import VIEW_PX
    from EMRegModule.rendering.text import text_size
    from EMRegModule.report.derived import calibration_points, marker_rows
    from EMRegModule.report.figures import ReportData, _slice_markers
    from EMRegModule.report.inputs import load_report_inputs

    inputs = load_report_inputs(labelled_run, read_image=False)
    rows = marker_rows(inputs.detection, inputs.registration)
    captions = {m.label: m.caption for m in _slice_markers(ReportData(inputs, rows,
                                                                      calibration_points(inputs.frame_calibration)))}
    paired = next(r for r in rows if r.calibration_label == LONG)
    caption = captions[paired.id]
    assert caption.endswith(f"...  {paired.residual_mm:.2f} mm") and caption.startswith(f"{paired.id} -> Lxxx")
    assert text_size(caption, 0.42)[0] < 3 * VIEW_PX, caption  # within its tile: three views


def test_a_report_over_a_ct_replaced_since_the_run_is_refused(small_case, tmp_path, capsys):
    import SimpleITK as sitk

    case, out = tmp_path / "case", tmp_path / "out"
    shutil.copytree(small_case, case)
    assert main(["run", str(case), "--out", str(out), "--quiet"]) == 0
    ct = sitk.ReadImage(str(case / "ct.nrrd"))
    shifted = sitk.GetImageFromArray(np.roll(sitk.GetArrayFromImage(ct), 10, axis=2))  # another scan, same grid
    shifted.CopyInformation(ct)
    sitk.WriteImage(shifted, str(case / "ct.nrrd"), useCompression=True)
    capsys.readouterr()
    assert main(["report", str(out), "--quiet"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and str(case / "ct.nrrd") in err[0] and "not the CT this run used" in err[0], err
    assert not (out / "report.html").exists() and not (out / "report_figures").exists()
    assert not (out / "EMReg.mrb").exists()  # the bundle would hold the other scan too
