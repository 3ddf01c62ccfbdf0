"""A second ``emreg report`` of a run reuses what did not change: the CT's products (``report_figures/ct_context.npz``)
and the 3D Slicer bundle; never when something they were made from changed, and never past the CT check.

Each test works on its own copy of the small case and of its run (``run.json``'s paths moved with it).
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import SimpleITK as sitk

from EMRegModule.cli.main import main
from EMRegModule.report.ct_memo import MEMO_NAME

FIGURES = "report_figures"


def _own_copy(small_case: Path, tmp_path: Path, out_name: str = "out") -> tuple[Path, Path]:
    """The small case and its run's outputs copied under ``tmp_path`` (the outputs into ``out_name``, e.g.
    ``batch/out`` for a folder of runs without the case in it), ``run.json`` naming the copies."""
    case, out = tmp_path / "case", tmp_path / out_name
    shutil.copytree(small_case, case)
    shutil.copytree(small_case.parent / "out", out)
    shutil.rmtree(out / "previous", ignore_errors=True)
    text = (out / "run.json").read_text(encoding="utf-8")
    (out / "run.json").write_text(text.replace(str(small_case.resolve()), str(case.resolve())), encoding="utf-8")
    return case, out


def _settings_with_iso_300(case: Path, tmp_path: Path) -> Path:
    """The case's settings with ``[report] iso_value = 300``: a report made with them says so under its 3D view."""
    settings = tmp_path / "other.toml"
    settings.write_text((case / "case.toml").read_text(encoding="utf-8") + "\n[report]\niso_value = 300.0\n",
                        encoding="utf-8")
    return settings


def _assert_made_with(out: Path, settings: Path) -> None:
    """The page was made with ``settings`` (from :func:`_settings_with_iso_300`) and its provenance names them."""
    from EMRegModule.settings import load_settings

    page = (out / "report.html").read_text(encoding="utf-8")
    assert "The grey surface is the CT at 300 (the [report] iso_value setting)" in page
    run = json.loads((out / "run.json").read_text(encoding="utf-8"))
    assert run["outputs"]["report.html"]["provenance"]["settings_sha256"] == load_settings(settings).digest()


def _figures(out: Path) -> dict[str, bytes]:
    return {p.name: p.read_bytes() for p in sorted((out / FIGURES).glob("*.png"))}


def _no_ct_read(monkeypatch: pytest.MonkeyPatch) -> None:
    """Fail any read of the CT's voxels (the products are to come from the kept file)."""
    def refuse(*args, **kwargs):
        raise AssertionError("the CT was read although its products were kept")

    monkeypatch.setattr("EMRegModule.io.ct_stream.start_streamed_read", refuse)
    monkeypatch.setattr("EMRegModule.io.image.open_ct", refuse)


def _report(out: Path, capsys: pytest.CaptureFixture) -> tuple[int, str, str]:
    code = main(["report", str(out), "--quiet"])
    captured = capsys.readouterr()
    return code, captured.out, captured.err


def test_a_second_report_uses_the_kept_ct_products_and_keeps_the_bundle(small_case, tmp_path, monkeypatch, capsys):
    case, out = _own_copy(small_case, tmp_path)
    assert (out / FIGURES / MEMO_NAME).is_file(), "the run's report keeps the CT products it made"
    before, bundle = _figures(out), (out / "EMReg.mrb").stat()
    listed = json.loads((out / "run.json").read_text(encoding="utf-8"))["outputs"]["EMReg.mrb"]
    _no_ct_read(monkeypatch)
    code, printed, err = _report(out, capsys)
    assert code == 0, err
    assert _figures(out) == before  # every figure byte for byte, the CT slices and the 3D view's surface too
    assert f"bundle: {out / 'EMReg.mrb'} (up to date: kept)" in printed
    assert (out / "EMReg.mrb").stat().st_mtime_ns == bundle.st_mtime_ns
    run = json.loads((out / "run.json").read_text(encoding="utf-8"))
    assert run["outputs"]["EMReg.mrb"] == listed
    assert (out / FIGURES / MEMO_NAME).is_file() and "report_figures" in run["outputs"]
    assert not (out / "previous" / "EMReg.mrb").exists()


def test_a_replaced_ct_is_refused_although_its_products_are_kept(small_case, tmp_path, capsys):
    case, out = _own_copy(small_case, tmp_path)
    image = sitk.ReadImage(str(case / "ct.nrrd"))
    image[5, 5, 5] = image[5, 5, 5] + 100  # one voxel: another scan for the sha256, the same geometry
    sitk.WriteImage(image, str(case / "ct.nrrd"), useCompression=True)
    code, _, err = _report(out, capsys)
    assert code == 2
    assert "not the CT this run used" in err and len(err.strip().splitlines()) == 1
    assert not (out / "report.html").exists()


def test_products_kept_for_other_markers_are_not_used(small_case, tmp_path, capsys):
    """A kept file whose marker poses differ (by 1 micrometre) is ignored: the CT is read, the figures are the run's."""
    case, out = _own_copy(small_case, tmp_path)
    before = _figures(out)
    memo = out / FIGURES / MEMO_NAME
    with np.load(memo) as kept:
        arrays = {name: kept[name] for name in kept.files}
    arrays["marker_to_image"][0, 0, 3] += 1e-3
    with memo.open("wb") as file:
        np.savez(file, **arrays)
    code, _, err = _report(out, capsys)
    assert code == 0, err
    assert _figures(out) == before
    with np.load(out / FIGURES / MEMO_NAME) as kept:  # kept again, for the markers there are
        assert not np.array_equal(kept["marker_to_image"], arrays["marker_to_image"])


@pytest.mark.parametrize("change", ["targets", "bundle edited", "settings"])
def test_the_bundle_is_written_again_when_what_it_shows_changed(small_case, tmp_path, capsys, change):
    case, out = _own_copy(small_case, tmp_path)
    listed = json.loads((out / "run.json").read_text(encoding="utf-8"))["outputs"]["EMReg.mrb"]["sha256"]
    if change == "targets":
        targets = json.loads((case / "targets.mrk.json").read_text(encoding="utf-8"))
        targets["markups"][0]["controlPoints"][0]["label"] = "renamed"
        (case / "targets.mrk.json").write_text(json.dumps(targets), encoding="utf-8")
    elif change == "bundle edited":
        with (out / "EMReg.mrb").open("ab") as bundle:
            bundle.write(b"\0")
    else:
        with (case / "case.toml").open("a", encoding="utf-8") as settings:
            settings.write("\n[report]\niso_value = 300.0\n")
    code, printed, err = _report(out, capsys)
    assert code == 0, err
    assert "up to date" not in printed and f"bundle: {out / 'EMReg.mrb'}" in printed
    run = json.loads((out / "run.json").read_text(encoding="utf-8"))
    written = run["outputs"]["EMReg.mrb"]
    assert written["sha256"] != listed or change == "bundle edited"
    from EMRegModule.io.provenance import file_sha256

    assert file_sha256(out / "EMReg.mrb") == written["sha256"]
    assert written["provenance"]["inputs"]["ct"] == run["inputs"]["ct"]


def test_a_report_uses_the_settings_it_names(small_case, tmp_path, capsys):
    """``emreg report --settings FILE``: the figures are made with FILE's settings and the provenance names FILE
    (before, the figures used the case's ``case.toml`` whatever the provenance said)."""
    case, out = _own_copy(small_case, tmp_path)
    settings = _settings_with_iso_300(case, tmp_path)
    code = main(["report", str(out), "--settings", str(settings), "--quiet"])
    assert code == 0, capsys.readouterr().err
    _assert_made_with(out, settings)
    assert main(["report", str(out), "--quiet"]) == 0  # the case's settings again: Otsu's threshold, said so
    assert "(Otsu&#x27;s threshold between air and the frame and patient)" in (out / "report.html").read_text(
        encoding="utf-8")


def test_a_bundle_written_by_a_batch_is_kept_by_the_next_report(small_case, tmp_path, capsys):
    case, out = _own_copy(small_case, tmp_path, "batch/out")
    (out / "EMReg.mrb").unlink()
    assert main(["report", "--batch", str(out.parent), "--quiet"]) == 0, capsys.readouterr().err
    assert (out / "EMReg.mrb").is_file()
    code, printed, err = _report(out, capsys)
    assert code == 0, err
    assert f"bundle: {out / 'EMReg.mrb'} (up to date: kept)" in printed


@pytest.mark.parametrize("damage", ["truncated", "not a zip", "empty"])
def test_a_damaged_kept_file_is_read_past(small_case, tmp_path, capsys, damage):
    """A kept file cut short (a full disk, a copy interrupted) or replaced is ignored: the CT is read, the figures
    are the run's, and the products are kept again."""
    case, out = _own_copy(small_case, tmp_path)
    before = _figures(out)
    memo = out / FIGURES / MEMO_NAME
    data = memo.read_bytes()
    memo.write_bytes({"truncated": data[: len(data) // 2], "not a zip": b"PK\x03\x04" + b"x" * 100,
                      "empty": b""}[damage])
    code, _, err = _report(out, capsys)
    assert code == 0, err
    assert _figures(out) == before
    with np.load(out / FIGURES / MEMO_NAME) as kept:
        assert "binned" in kept.files


def test_batch_reports_use_the_settings_they_name(small_case, tmp_path, capsys):
    """``emreg report --batch DIR --settings FILE``: every page made with FILE, as each provenance says."""
    case, out = _own_copy(small_case, tmp_path, "batch/out")
    settings = _settings_with_iso_300(case, tmp_path)
    assert main(["report", "--batch", str(out.parent), "--settings", str(settings), "--quiet"]) == 0, \
        capsys.readouterr().err
    _assert_made_with(out, settings)
    (tmp_path / "broken.toml").write_text("[report\n", encoding="utf-8")
    assert main(["report", "--batch", str(out.parent), "--settings", str(tmp_path / "broken.toml"), "--quiet"]) == 2
    assert len(capsys.readouterr().err.strip().splitlines()) == 1
