"""CT and image inputs of the bad-input matrix (issue 28): each refused with exit 2 and one line naming the
input and what is wrong, no traceback, no plausible wrong answer, and nothing ITK prints of its own.

Classes: a NIfTI whose magic is damaged (ITK reads it as Analyze 7.5 and drops its geometry), a 2-D NIfTI,
a header spacing of 1e300 (or an origin as far), a symbolic-link loop as the CT, a DICOM slice whose pixel
data is 100 bytes short, ITK / MetaIO chatter before EMReg's line (a truncated MetaImage header), and
SIGABRT / SIGSEGV at exit after a correct DICOM refusal (threads still inside SimpleITK at teardown).
"""

from __future__ import annotations

import gzip
import os
import subprocess
import sys
import threading
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np
import pytest
import SimpleITK as sitk
from dicom_files import convert, make_volume, tools_available, uid, write_series
from test_bad_inputs import _refused

from EMRegModule.errors import EMRegError

EMREG = [sys.executable, "-m", "EMRegModule"]


def _detect(ct: Path, tmp_path: Path) -> list:
    return ["detect", ct, "--out", tmp_path / "out", "--quiet"]


def _nifti(tmp_path: Path, name: str = "ct.nii") -> Path:
    path = tmp_path / name
    sitk.WriteImage(make_volume(), str(path))
    return path


# --- NIfTI ----------------------------------------------------------------------------------------


@pytest.mark.parametrize("name", ["ct.nii", "ct.nii.gz"])
def test_a_nifti_with_a_damaged_magic_is_refused_not_read_as_analyze(tmp_path, capfd, name):
    good = _nifti(tmp_path, "good.nii")
    header = bytearray(good.read_bytes())
    assert header[344:348] == b"n+1\0"
    header[344:348] = b"xx1\0"
    damaged = tmp_path / name
    damaged.write_bytes(gzip.compress(bytes(header)) if name.endswith(".gz") else bytes(header))
    # what ITK makes of it: an Analyze header, the oblique direction and the origin gone
    analyze = sitk.ReadImage(str(damaged))
    assert analyze.GetDirection() != make_volume().GetDirection()
    capfd.readouterr()
    err = _refused(capfd, _detect(damaged, tmp_path), name, "magic")
    assert "Analyze" in err
    assert not (tmp_path / "out" / "markers.json").exists()


def test_the_report_reader_refuses_a_damaged_nifti_magic_too(tmp_path):
    from EMRegModule.io.ct_stream import start_streamed_read

    path = _nifti(tmp_path)
    data = bytearray(path.read_bytes())
    data[344:348] = b"\0\0\0\0"
    path.write_bytes(bytes(data))
    with pytest.raises(EMRegError, match="magic"):
        start_streamed_read(path)


def test_a_file_named_nifti_without_any_nifti_header_is_refused(tmp_path, capfd):
    path = tmp_path / "ct.nii"
    path.write_bytes(b"\0" * 400)
    _refused(capfd, _detect(path, tmp_path), "ct.nii", "not a NIfTI file")
    path.write_bytes(_nifti(tmp_path, "good.nii").read_bytes()[:200])
    _refused(capfd, _detect(path, tmp_path), "ct.nii", "header is truncated: 200 of 348 bytes")


@pytest.mark.parametrize("name", ["ct.nii", "ct.nii.gz"])
def test_a_2d_nifti_is_one_line(tmp_path, capsys, name):
    sitk.WriteImage(make_volume()[:, :, 3], str(tmp_path / name))
    _refused(capsys, _detect(tmp_path / name, tmp_path), name, "3D volume", "2D")


# --- header geometry ----------------------------------------------------------------------------


def _mha_with(tmp_path: Path, key: str, value: str) -> Path:
    """A MetaImage of the test volume whose header field ``key`` is replaced by ``value``."""
    source = tmp_path / "source.mha"
    sitk.WriteImage(make_volume(), str(source))
    lines = source.read_bytes().split(b"\n")
    index = next(i for i, line in enumerate(lines) if line.startswith(key.encode()))
    lines[index] = f"{key} = {value}".encode()
    path = tmp_path / "ct.mha"
    path.write_bytes(b"\n".join(lines))
    return path


@pytest.mark.parametrize(("key", "value", "needle"), [
    ("ElementSpacing", "1e300 0.6 0.8", "spacing"),
    ("ElementSpacing", "1e-300 0.6 0.8", "spacing"),
    ("Offset", "1e300 30.5 -101.25", "origin"),
])
def test_an_absurd_spacing_or_origin_in_the_header_is_one_line(tmp_path, capfd, key, value, needle):
    path = _mha_with(tmp_path, key, value)
    err = _refused(capfd, _detect(path, tmp_path), "ct.mha", needle, "damaged")
    assert "Warning" not in err


def _nrrd_with(tmp_path: Path, key: str, value: str) -> Path:
    """A NRRD of the test volume whose header field ``key`` is replaced by ``value``."""
    source = tmp_path / "source.nrrd"
    sitk.WriteImage(make_volume(), str(source))
    data = source.read_bytes()
    end = data.index(b"\n\n") + 2
    lines = data[:end].split(b"\n")
    index = next(i for i, line in enumerate(lines) if line.startswith(f"{key}:".encode()))
    lines[index] = f"{key}: {value}".encode()
    path = tmp_path / "ct.nrrd"
    path.write_bytes(b"\n".join(lines) + data[end:])
    return path


@pytest.mark.parametrize(("key", "value", "needle"), [
    ("space directions", "(1e300,0,0) (0,0.6,0) (0,0,0.8)", "spacing"),
    ("space directions", "(1e-300,0,0) (0,0.6,0) (0,0,0.8)", "spacing"),
    ("space origin", "(1e300,30.5,-101.25)", "origin"),
])
def test_an_absurd_spacing_or_origin_in_a_nrrd_header_is_refused_before_itk_reads_it(tmp_path, capfd, key, value,
                                                                                    needle):
    """ITK reads a NRRD ``space directions`` vector of length 1e300 as spacing 1 along the identity direction,
    without a word: a plausible, wrong geometry. The header's own numbers are checked first."""
    path = _nrrd_with(tmp_path, key, value)
    err = _refused(capfd, _detect(path, tmp_path), "ct.nrrd", needle, "damaged")
    assert "Warning" not in err


def test_a_scanner_sized_spacing_and_origin_pass_the_geometry_check():
    from EMRegModule.core.ct import check_ct_geometry

    image = make_volume()
    image.SetSpacing((0.0005, 0.0005, 0.0008))  # a CT in metres: passed on, and named as such by detection
    image.SetOrigin((-250.0, -400.0, 1800.0))
    check_ct_geometry(image, "ct")


# --- paths --------------------------------------------------------------------------------------


def test_a_symlink_loop_as_the_ct_is_named(tmp_path, capsys):
    (tmp_path / "a.nrrd").symlink_to(tmp_path / "b.nrrd")
    (tmp_path / "b.nrrd").symlink_to(tmp_path / "a.nrrd")
    _refused(capsys, _detect(tmp_path / "a.nrrd", tmp_path), "a.nrrd", "symbolic-link loop")


def test_a_symlink_loop_as_the_ct_of_a_case_folder_is_named(tmp_path, capsys):
    case = tmp_path / "case"
    case.mkdir()
    (case / "ct.nrrd").symlink_to(case / "ct.nrrd")
    for command in (["detect", case, "--out", tmp_path / "out"], ["run", case, "--out", tmp_path / "out"]):
        _refused(capsys, [*command, "--quiet"], "ct.nrrd", "symbolic-link loop")


# --- DICOM pixel data ---------------------------------------------------------------------------


@pytest.mark.parametrize("syntax", ["plain", "big-endian", "deflate"])  # the last two: headers read by pydicom
def test_a_dicom_slice_whose_pixel_data_is_100_bytes_short_is_refused(tmp_path, capsys, syntax):
    import pydicom

    files = write_series(make_volume(), tmp_path / "ct", uid(91))
    if syntax != "plain":
        if tools_available():
            pytest.skip(f"DICOM tools missing: {tools_available()} (scripts/setup)")
        convert(files, syntax)
    dataset = pydicom.dcmread(files[5])
    dataset.PixelData = dataset.PixelData[:-100]  # a consistent file, its image 100 bytes short
    dataset.save_as(files[5])
    _refused(capsys, _detect(tmp_path / "ct", tmp_path), files[5].name, "cut short")
    if syntax == "plain":
        files[5].write_bytes(files[5].read_bytes() + b"\0" * 100)  # the length declared short, the bytes there
        _refused(capsys, _detect(tmp_path / "ct", tmp_path), files[5].name, "cut short")
    assert not (tmp_path / "out" / "markers.json").exists()


def test_a_dicom_file_cut_100_bytes_short_is_refused(tmp_path, capsys):
    files = write_series(make_volume(), tmp_path / "ct", uid(92))
    files[7].write_bytes(files[7].read_bytes()[:-100])
    _refused(capsys, _detect(tmp_path / "ct", tmp_path), files[7].name)


def test_a_whole_dicom_slice_passes_the_pixel_data_check(tmp_path):
    from EMRegModule.io.dicom_read import check_pixel_data_length
    from EMRegModule.io.dicom_series import read_header

    files = write_series(make_volume(), tmp_path / "ct", uid(93))
    header = read_header(files[0])
    assert header.pixel_data is not None  # the quick header walk found it
    check_pixel_data_length(header, files[0].stat().st_size)
    with pytest.raises(EMRegError, match="cut short"):
        check_pixel_data_length(header, files[0].stat().st_size - 1)


# --- what ITK prints ----------------------------------------------------------------------------


def test_a_truncated_metaimage_header_is_emregs_line_alone_and_true(tmp_path):
    source = tmp_path / "source.mha"
    sitk.WriteImage(make_volume(), str(source))
    path = tmp_path / "ct.mha"
    path.write_bytes(source.read_bytes()[:150])  # the header cut before DimSize
    result = subprocess.run([*EMREG, "detect", str(path), "--out", str(tmp_path / "out"), "--quiet"],
                            capture_output=True, text=True, timeout=300)
    assert result.returncode == 2, result.stderr
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1, result.stderr  # before: 12 lines of MetaIO, then EMReg's
    assert "ct.mha" in lines[0] and "DimSize" in lines[0], lines[0]
    assert "No such file" not in lines[0]


def test_the_batch_memory_estimate_reads_a_truncated_header_silently(tmp_path, capfd):
    import json

    from EMRegModule.report.batch import ct_bytes_of_run

    source = tmp_path / "source.mha"
    sitk.WriteImage(make_volume(), str(source))
    (tmp_path / "ct.mha").write_bytes(source.read_bytes()[:150])
    (tmp_path / "run.json").write_text(json.dumps({"ct": str(tmp_path / "ct.mha")}))
    capfd.readouterr()
    assert ct_bytes_of_run(tmp_path) == 0.0  # unknown: the report reading the CT says what is wrong
    assert capfd.readouterr().err == ""


def test_an_analyze_pair_is_read_without_itks_deprecation_warning(tmp_path, capfd):
    from EMRegModule.io.image import read_ct

    volume = sitk.GetImageFromArray(np.zeros((4, 5, 6), np.int16))
    sitk.WriteImage(volume, str(tmp_path / "ct.hdr"))  # NIfTI-1 in two files ('ni1')
    data = bytearray((tmp_path / "ct.hdr").read_bytes())
    data[344:348] = b"\0\0\0\0"  # Analyze 7.5 (no magic): valid for a .hdr/.img pair; ITK warns it is deprecated
    (tmp_path / "ct.hdr").write_bytes(bytes(data))
    capfd.readouterr()
    assert read_ct(tmp_path / "ct.hdr").GetSize() == (6, 5, 4)
    assert capfd.readouterr().err == ""


def test_a_slice_with_a_damaged_header_brings_no_pydicom_warning_before_the_line(tmp_path, capsys):
    import warnings

    files = write_series(make_volume(), tmp_path / "ct", uid(97))
    data = bytearray(files[4].read_bytes())
    data[132:400] = b"\xff" * 268  # the preamble kept, the header after it garbage
    files[4].write_bytes(bytes(data))
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        _refused(capsys, _detect(tmp_path / "ct", tmp_path), "missing slice")
    assert not [w for w in caught if "pydicom" in w.filename], [str(w.message) for w in caught]


def test_itks_warning_display_is_restored_after_the_reads():
    from EMRegModule.io.itk_messages import quiet_itk

    before = sitk.ProcessObject.GetGlobalWarningDisplay()
    with ThreadPoolExecutor(2) as pool:
        def silenced() -> bool:
            with quiet_itk():
                return bool(sitk.ProcessObject.GetGlobalWarningDisplay())

        assert not any(pool.map(lambda _: silenced(), range(8)))
    assert sitk.ProcessObject.GetGlobalWarningDisplay() == before


# --- exit after a DICOM refusal -----------------------------------------------------------------


def _refused_while_allocating(folder: Path) -> Path:
    """A folder refused right after its header scan while a 350 MB volume is still being allocated for it: a
    384 x 384 CT slice first (its size and the files beside it size the early allocation), then 1200 tiny MR
    slices (a scan about as long as the allocation; no CT volume among the series). On the code before, 3 of
    16 runs of it, two at a time, died of SIGABRT or SIGSEGV."""
    slice_ = sitk.GetImageFromArray(np.full((1, 384, 384), -1000, np.int16))
    slice_.SetSpacing((0.5, 0.5, 0.8))
    write_series(slice_, folder, uid(94), prefix="IM0")
    write_series(sitk.GetImageFromArray(np.zeros((1200, 2, 2), np.int16)), folder, uid(95), modality="MR",
                 prefix="IM1")
    return folder


def test_many_dicom_refusals_two_at_a_time_all_exit_2(tmp_path):
    """Each run ends with its one-line refusal and exit 2, never SIGABRT ("FATAL: exception not rethrown") or
    SIGSEGV from a thread still allocating the volume in SimpleITK while the interpreter exits (6 of 40 runs of
    a refused 0.8 mm hard case before)."""
    folder = _refused_while_allocating(tmp_path / "ct")
    env = dict(os.environ, PYTHONFAULTHANDLER="1")

    def run(k: int) -> tuple[int, str]:
        result = subprocess.run([*EMREG, "detect", str(folder), "--out", str(tmp_path / f"out{k}"), "--quiet"],
                                capture_output=True, text=True, env=env, timeout=300)
        return result.returncode, result.stderr

    with ThreadPoolExecutor(2) as pool:
        results = list(pool.map(run, range(20)))
    for code, err in results:
        assert code == 2, (code, err)
        assert len(err.strip().splitlines()) == 1 and "no CT volume" in err, err


def test_the_threads_that_run_simpleitk_are_no_daemons(tmp_path, monkeypatch):
    """The interpreter waits for them at exit (a daemon inside SimpleITK is ended from within C++ code)."""
    from EMRegModule.io.image import read_ct

    started: list[threading.Thread] = []
    original = threading.Thread.start

    def start(thread: threading.Thread) -> None:
        if thread.name.startswith("emreg-dicom"):
            started.append(thread)
        original(thread)

    monkeypatch.setattr(threading.Thread, "start", start)
    write_series(make_volume(), tmp_path / "ct", uid(96))
    read_ct(tmp_path / "ct")
    assert {t.name for t in started} >= {"emreg-dicom-read", "emreg-dicom-allocate"}
    assert not [t.name for t in started if t.daemon]


def test_a_refusal_exits_after_the_background_import_not_during_it(tmp_path):
    """The detection stage's import runs on a thread while the CT is read; a command refused at once exits only
    once that import is done (the interpreter ends a daemon thread from inside a C++ extension's initialisation
    at exit: SIGSEGV after the refusal). A module that takes a while to import, and notes when it is done, stands
    in for VTK."""
    (tmp_path / "slow_module.py").write_text(
        "import pathlib, sys, time\n"
        "time.sleep(0.5)\n"
        "pathlib.Path(sys.argv[1]).write_text('imported')\n")
    done = tmp_path / "done.txt"
    script = ("import sys\n"
              "from EMRegModule.pipeline.background import import_in_background\n"
              "import_in_background('slow_module')\n"
              "sys.exit(2)\n")
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(tmp_path), *sys.path]))
    result = subprocess.run([sys.executable, "-c", script, str(done)], env=env, capture_output=True, text=True,
                            timeout=120)
    assert result.returncode == 2, result.stderr
    assert done.read_text() == "imported"  # the import ran to its end before the interpreter exited
