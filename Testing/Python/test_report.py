"""The verification report: content, missing inputs, warnings, determinism, atomicity, batch, browser.

Most tests use a small sample run (fixtures.samples.write_sample_run: a painted CT,
spec-format outputs) so they do not depend on the detection pipeline; the end-to-end test runs
``emreg run`` on the simulated standard case when the simulator's fixture exists.
"""

from __future__ import annotations

import base64
import json
import re
import shutil
import subprocess
from html.parser import HTMLParser
from pathlib import Path

import cv2
import numpy as np
import pytest
from fixtures.samples import write_sample_run

from EMRegModule.cli.main import main
from EMRegModule.errors import EMRegError
from EMRegModule.names import REPORT_FIGURES
from EMRegModule.progress import Progress
from EMRegModule.report.batch import write_reports_batch
from EMRegModule.report.writer import write_report

CHROMIUM_CANDIDATES = ("/usr/bin/chromium", "/usr/bin/chromium-browser", "/usr/bin/google-chrome")
ALL_FIGURES = ("scene_oblique", "scene_top", "marker_slices", "residuals", "fre_curve", "tre_targets")


class _Images(HTMLParser):
    """Collects <img> sources, figure ids and any external reference of a page."""

    def __init__(self) -> None:
        super().__init__()
        self.sources: list[str] = []
        self.figure_ids: list[str] = []
        self.external: list[str] = []

    def handle_starttag(self, tag, attrs):
        attrs = dict(attrs)
        if tag == "img":
            self.sources.append(attrs.get("src", ""))
        if tag == "figure":
            self.figure_ids.append(attrs.get("id", ""))
        for key in ("src", "href"):
            value = attrs.get(key) or ""
            if value and not value.startswith(("data:", "#")):
                self.external.append(value)


def _parse(html_text: str) -> _Images:
    parser = _Images()
    parser.feed(html_text)
    return parser


@pytest.fixture(scope="module")
def sample_run(tmp_path_factory):
    """A small case and a run's outputs in OUT, with the report written once."""
    root = tmp_path_factory.mktemp("sample_run")
    truth = write_sample_run(root / "case", root / "out")
    path = write_report(root / "out")
    return root, truth, path


def _without_out_path(page: Path) -> str:
    """The page's text with its own output folder's path (shown in the summary) taken out."""
    return page.read_text(encoding="utf-8").replace(str(page.parent), "OUT")


def _copy_run(sample_run, tmp_path) -> Path:
    root, _, _ = sample_run
    out = tmp_path / "out"
    shutil.copytree(root / "out", out)
    return out


def test_report_shows_every_figure_and_table(sample_run):
    root, truth, path = sample_run
    assert path == root / "out" / "report.html"
    text = path.read_text(encoding="utf-8")
    page = _parse(text)
    assert page.external == []  # self-contained: nothing fetched from disk or network
    assert page.figure_ids == [f"fig-{name}" for name in
                               ("scene_oblique", "scene_top", "residuals", "fre_curve", "marker_slices", "tre_targets")]
    for source in page.sources:
        assert source.startswith("data:image/png;base64,")
        image = cv2.imdecode(np.frombuffer(base64.b64decode(source.split(",", 1)[1]), np.uint8), cv2.IMREAD_COLOR)
        assert image is not None and image.shape[0] > 100 and image.shape[1] > 300
    for name in ALL_FIGURES:
        png = root / "out" / REPORT_FIGURES / f"{name}.png"
        assert png.is_file() and png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
        assert base64.b64encode(png.read_bytes()).decode() in text  # the page embeds the very same file
    registration = json.loads((root / "out" / "registration.json").read_text(encoding="utf-8"))
    assert f"{registration['fre_mm']:.2f} mm" in text
    assert f"{registration['sensor_offset_l_mm']:.2f} mm" in text
    for heading in ("Summary", "Warnings", "Frame in 3D", "Registration", "Markers in the CT", "Frame calibration",
                    "Target registration error", "Board phantom"):
        assert f"<h2>{heading}</h2>" in text
    assert "1 detected marker(s) not paired: I05" in text  # the sample's fifth marker has no calibration point
    assert "Rejected candidates" in text and "905" in text
    assert "75.18" in text and "+0.18" in text  # board L1 mean and its error against case.toml's nominal 75 mm
    assert not re.search(r"20\d\d-\d\d-\d\d", text)  # no timestamps


def test_slices_show_the_fitted_outline_on_the_ct(sample_run):
    root, _, _ = sample_run
    mosaic = cv2.imread(str(root / "out" / REPORT_FIGURES / "marker_slices.png"))[:, :, ::-1]
    green = np.all(np.abs(mosaic.astype(int) - (40, 200, 80)) < 40, axis=2)
    orange = np.all(np.abs(mosaic.astype(int) - (255, 140, 0)) < 40, axis=2)
    bright = mosaic.min(axis=2) > 200  # PVC in the CT window
    assert green.sum() > 500 and orange.sum() > 100  # paired and unpaired outlines
    assert bright.sum() > 10000


def test_report_is_deterministic(sample_run, tmp_path):
    root, _, first = sample_run
    out = _copy_run(sample_run, tmp_path)
    second = write_report(out, case_dir=root / "case")
    assert _without_out_path(second) == _without_out_path(first)
    for name in ALL_FIGURES:
        figure = REPORT_FIGURES + f"/{name}.png"
        assert (out / figure).read_bytes() == (root / "out" / figure).read_bytes()


def test_missing_inputs_leave_sections_out_with_a_note(tmp_path, sample_run):
    root, _, _ = sample_run
    out = tmp_path / "out"
    out.mkdir()
    shutil.copy(root / "out" / "markers.json", out / "markers.json")
    path = write_report(out)
    text = path.read_text(encoding="utf-8")
    assert "Not shown: no registration.json" in text
    assert "Not shown: no frame_calibration.json" in text
    assert "the CT was not found" in text and "no CT available" in text
    assert "fig-scene_oblique" in text and "fig-marker_slices" not in text and "fig-residuals" not in text
    assert sorted(p.name for p in (out / REPORT_FIGURES).iterdir()) == ["scene_oblique.png", "scene_top.png"]


def test_calibration_alone_gives_tables_but_no_empty_scene(tmp_path, sample_run):
    root, _, _ = sample_run
    out = tmp_path / "out"
    out.mkdir()
    shutil.copy(root / "out" / "frame_calibration.json", out / "frame_calibration.json")
    text = write_report(out).read_text(encoding="utf-8")
    assert "<img" not in text and "Not shown: no markers.json" in text
    assert "M04" in text  # the calibration table


def test_refusal_and_stale_figures(tmp_path, sample_run):
    """A refused registration (run.json) is shown first; figures of an earlier run are removed."""
    out = _copy_run(sample_run, tmp_path)
    (out / "registration.json").unlink()
    (out / "evaluation.json").unlink()
    run = json.loads((out / "run.json").read_text(encoding="utf-8"))
    run["summary"].append("register: refused: the pairing is ambiguous (two hypotheses explain 5 markers)")
    (out / "run.json").write_text(json.dumps(run), encoding="utf-8")
    text = write_report(out).read_text(encoding="utf-8")
    assert "Refused: register: refused: the pairing is ambiguous" in text
    assert text.index("Refused:") < text.index("Frame in 3D")
    figures = out / REPORT_FIGURES
    assert not (figures / "residuals.png").exists() and not (figures / "fre_curve.png").exists()
    assert (out / REPORT_FIGURES / "marker_slices.png").is_file()


def test_warnings_for_outliers_and_an_offset_off_the_fre_minimum(tmp_path, sample_run):
    out = _copy_run(sample_run, tmp_path)
    registration = json.loads((out / "registration.json").read_text(encoding="utf-8"))
    registration["pairs"][1]["residual_mm"] = 3.1
    registration["sensor_offset_l_mm"] = 17.0
    (out / "registration.json").write_text(json.dumps(registration), encoding="utf-8")
    text = write_report(out).read_text(encoding="utf-8")
    assert "outlier: marker I02 (calibration point M02) has a residual of 3.10 mm" in text
    assert re.search(r"lowest at l = 13\.5\d mm, not at the reported 17\.00 mm", text)


def test_unreadable_input_is_a_warning_not_a_crash(tmp_path, sample_run):
    out = _copy_run(sample_run, tmp_path)
    (out / "frame_calibration.json").write_text("{not json")
    text = write_report(out).read_text(encoding="utf-8")
    assert "could not read" in text and "frame_calibration.json" in text


def test_interrupted_report_keeps_the_previous_page(tmp_path, sample_run, monkeypatch):
    out = _copy_run(sample_run, tmp_path)
    before = (out / "report.html").read_bytes()

    def broken(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr("EMRegModule.report.writer.build_html", broken)
    with pytest.raises(KeyboardInterrupt):
        write_report(out)
    assert (out / "report.html").read_bytes() == before
    assert not [p for p in out.rglob(".*") if p.is_file()]  # no temporary file left behind


def test_nothing_to_report_is_exit_2(tmp_path, capsys):
    (tmp_path / "empty").mkdir()
    with pytest.raises(EMRegError, match="nothing to report"):
        write_report(tmp_path / "empty")
    assert main(["report", str(tmp_path / "empty")]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "nothing to report" in err
    assert main(["report", str(tmp_path / "nowhere")]) == 2
    assert main(["report", str(tmp_path / "empty"), "--case", str(tmp_path / "no-case")]) == 2


def test_cli_report_and_batch_with_progress(tmp_path, sample_run, capsys):
    root, _, _ = sample_run
    batch = tmp_path / "batch"
    for name in ("run_a", "run_b"):
        shutil.copytree(root / "out", batch / name)
        (batch / name / "report.html").unlink()
    (batch / "not_a_run").mkdir()
    assert main(["report", str(batch / "run_a"), "--quiet"]) == 0
    assert (batch / "run_a" / "report.html").is_file()
    (batch / "run_a" / "report.html").unlink()
    assert main(["report", "--batch", str(batch), "--jobs", "2"]) == 0
    captured = capsys.readouterr()
    assert "[emreg] reports" in captured.err and "skipping" in captured.err and "not_a_run" in captured.err
    for name in ("run_a", "run_b"):
        assert _without_out_path(batch / name / "report.html") == _without_out_path(root / "out" / "report.html")


def test_batch_reports_a_broken_folder_after_rendering_the_others(tmp_path, sample_run):
    root, _, _ = sample_run
    good, bad = tmp_path / "good", tmp_path / "bad"
    shutil.copytree(root / "out", good)
    shutil.copytree(root / "out", bad)
    (good / "report.html").unlink()
    (bad / "report.html").unlink()
    (bad / "report.html").mkdir()  # the page cannot be written there
    with pytest.raises(EMRegError, match=r"1 of 2 reports failed: .*bad: .*bad/report\.html: cannot write \(Is a "
                                         r"directory\)"):
        write_reports_batch([good, bad], jobs=1, progress=Progress(enabled=False))
    assert (good / "report.html").is_file()


# --- a real browser ------------------------------------------------------------------------------

_PROBE = """<script>
window.__emregErrors = [];
window.addEventListener('error', function (e) {
  var t = e.target;
  window.__emregErrors.push(t && t.tagName ? 'failed to load ' + t.tagName : String(e.message));
}, true);
window.addEventListener('load', function () {
  // Runs inside the load event, before --dump-dom serialises the page: every <img> has settled by now.
  var images = Array.prototype.slice.call(document.images);
  var pre = document.createElement('pre');
  pre.id = 'emreg-check';
  pre.textContent = JSON.stringify({errors: window.__emregErrors, title: document.title,
    images: images.map(function (img) {
      return {alt: img.alt, width: img.naturalWidth, height: img.naturalHeight,
              decoded: img.complete && img.naturalWidth > 0};
    })});
  document.body.appendChild(pre);
});
</script>"""


def _chromium() -> str | None:
    return next((c for c in CHROMIUM_CANDIDATES if Path(c).is_file()), shutil.which("chromium"))


def _load_in_chromium(page: Path, tmp_path: Path) -> dict:
    """Open a copy of ``page`` (with a probe script) in headless chromium; the probe's findings."""
    chromium = _chromium()
    probe_page = tmp_path / "probe.html"
    probe_page.write_text(page.read_text(encoding="utf-8").replace("<head>", "<head>" + _PROBE, 1), encoding="utf-8")
    result = subprocess.run(
        [chromium, "--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
         "--disable-background-networking", "--disable-component-update", "--disable-sync",
         f"--user-data-dir={tmp_path / 'chromium-profile'}", "--virtual-time-budget=10000", "--dump-dom",
         probe_page.as_uri()],
        capture_output=True, text=True, encoding="utf-8", errors="replace", timeout=120,
    )
    match = re.search(r'<pre id="emreg-check">(.*?)</pre>', result.stdout, re.S)
    assert match, f"chromium did not run the page's probe (exit {result.returncode}): {result.stderr[-500:]}"
    import html

    return json.loads(html.unescape(match.group(1)))


@pytest.mark.skipif(_chromium() is None, reason="chromium is not installed (scripts/setup installs Debian's chromium)")
def test_report_loads_in_headless_chromium_with_every_image_decoded(sample_run, tmp_path):
    _, _, path = sample_run
    found = _load_in_chromium(path, tmp_path)
    assert found["errors"] == []
    assert found["title"].startswith("EMReg report")
    assert len(found["images"]) == len(ALL_FIGURES)
    for image in found["images"]:
        assert image["decoded"] and image["width"] > 300 and image["height"] > 100, image


@pytest.mark.skipif(_chromium() is None, reason="chromium is not installed (scripts/setup installs Debian's chromium)")
def test_browser_check_catches_a_broken_image(sample_run, tmp_path):
    """The browser probe can fail: a page whose image data is corrupt is reported as such."""
    _, _, path = sample_run
    text = path.read_text(encoding="utf-8")
    broken = re.sub(r'src="data:image/png;base64,[^"]{0,40}', 'src="data:image/png;base64,AAAA', text, count=1)
    page = tmp_path / "broken.html"
    page.write_text(broken, encoding="utf-8")
    found = _load_in_chromium(page, tmp_path)
    assert found["images"][0]["decoded"] is False and found["images"][0]["width"] == 0
    assert any("IMG" in e for e in found["errors"])


# --- end to end --------------------------------------------------------------------------------


def test_emreg_run_writes_the_report_with_all_figures(request, tmp_path):
    """What a user does: ``emreg run CASE --out OUT`` on the simulated standard case."""
    try:
        case = request.getfixturevalue("standard_case")
    except pytest.FixtureLookupError:
        pytest.skip("the simulator's standard_case fixture is not available yet")
    out = tmp_path / "out"
    assert main(["run", str(case), "--out", str(out), "--quiet"]) == 0
    text = (out / "report.html").read_text(encoding="utf-8")
    page = _parse(text)
    assert page.external == []
    for name in ("scene_oblique", "scene_top", "marker_slices", "residuals", "fre_curve"):
        assert f"fig-{name}" in text, name
    registration = json.loads((out / "registration.json").read_text(encoding="utf-8"))
    assert f"{registration['fre_mm']:.2f} mm" in text
    if (out / "evaluation.json").is_file():
        evaluation = json.loads((out / "evaluation.json").read_text(encoding="utf-8"))
        if "tre" in evaluation:
            assert "fig-tre_targets" in text
        if "board" in evaluation:
            assert "absolute error (mm)" in text


@pytest.mark.parametrize("how", ["given", "handed", "streamed"])
def test_the_ct_given_handed_over_or_streamed_gives_the_same_page_and_figures(sample_run, tmp_path, how):
    """The report from a CT in memory (``emreg run``), from one handed over to be let go once used, and from
    one it streams itself: the same page and the same figures, byte for byte, as from a CT read whole."""
    from EMRegModule.io.ct_handle import CTHandle
    from EMRegModule.io.image import read_ct
    from EMRegModule.report.writer import write_report_keeping_ct

    root, _, _ = sample_run
    out = _copy_run(sample_run, tmp_path)
    for figure in (out / REPORT_FIGURES).iterdir():
        figure.unlink()
    image = read_ct(root / "case" / "ct.nrrd")
    if how == "given":
        page, kept = write_report_keeping_ct(out, image=image)
        assert kept is image
    elif how == "handed":
        handed = CTHandle.of_image(image)
        del image
        page, kept = write_report_keeping_ct(out, image=handed, keep_ct=False)
        assert kept is None and handed.result() is None and handed.array is None  # the report let it go
        assert handed.geometry.GetSize() == handed.image.GetSize()  # its geometry stays
    else:
        page, kept = write_report_keeping_ct(out, keep_ct=False)
        assert kept is None
    assert _without_out_path(page) == _without_out_path(root / "out" / "report.html")
    for figure in (root / "out" / REPORT_FIGURES).iterdir():
        assert (out / REPORT_FIGURES / figure.name).read_bytes() == figure.read_bytes(), figure.name


def test_an_early_ct_read_is_used_only_when_it_is_the_reports_ct(sample_run, tmp_path):
    """``emreg report`` starts streaming run.json's CT before the report's libraries load; the report uses that
    read only for its own CT (a read of another file is cancelled and the right CT read): same page either way."""
    import SimpleITK as sitk

    from EMRegModule.io.ct_stream import start_streamed_read
    from EMRegModule.report.writer import write_report_keeping_ct

    root, _, _ = sample_run
    other = tmp_path / "other.nrrd"
    image = sitk.ReadImage(str(root / "case" / "ct.nrrd"))
    sitk.WriteImage(image * 0, str(other), True)  # the same grid, other voxels
    for early in (start_streamed_read(root / "case" / "ct.nrrd"), start_streamed_read(other)):
        out = _copy_run(sample_run, tmp_path / early.path.stem)
        page, kept = write_report_keeping_ct(out, image=early, keep_ct=False)
        assert kept is None
        assert _without_out_path(page) == _without_out_path(root / "out" / "report.html")
        for figure in (root / "out" / REPORT_FIGURES).iterdir():
            assert (out / REPORT_FIGURES / figure.name).read_bytes() == figure.read_bytes(), figure.name
