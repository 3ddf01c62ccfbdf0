"""What a command leaves behind in a process that goes on after it (a test, the Slicer module, a script calling
``EMRegModule.cli.main``): the signal handlers and the C locale are as it found them.

Both once made the suite's result depend on which tests ran before in the same worker: ``main`` left its
SIGTERM handler installed, and GDCM's DICOM writer left every locale category at "C", after which Python's
default text encoding was ASCII for the rest of the process.
"""

from __future__ import annotations

import locale
import signal

import numpy as np
import pytest
import SimpleITK as sitk

from EMRegModule.cli.main import main
from EMRegModule.errors import EMRegError
from EMRegModule.io.image import write_image
from EMRegModule.simulation.ct import write_dicom_series


def _handlers() -> dict[int, object]:
    return {signum: signal.getsignal(signum) for signum in (signal.SIGINT, signal.SIGTERM)}


def _sigterm_handler(signum: int, frame: object) -> None:  # a caller's own handler, to be found again
    raise AssertionError("never called")


@pytest.mark.parametrize("sigint", [signal.default_int_handler, signal.SIG_IGN])
def test_a_command_puts_the_callers_signal_handlers_back(tmp_path, capsys, sigint):
    signal.signal(signal.SIGINT, sigint)
    signal.signal(signal.SIGTERM, _sigterm_handler)
    before = _handlers()
    assert main(["run", str(tmp_path / "missing"), "--out", str(tmp_path / "out"), "--quiet"]) == 2
    assert "error" in capsys.readouterr().err
    assert _handlers() == before


def test_a_command_interrupted_puts_the_callers_signal_handlers_back(tmp_path, capsys, monkeypatch):
    """SIGTERM inside a command ends it as interrupted (143); the caller's own handler is back afterwards."""
    from EMRegModule.cli import run as run_command

    def terminated(args):
        signal.raise_signal(signal.SIGTERM)
        raise AssertionError("the command's SIGTERM handler did not act")

    monkeypatch.setattr(run_command, "cmd_run", terminated)  # the handler is looked up when the command runs
    signal.signal(signal.SIGTERM, _sigterm_handler)
    before = _handlers()
    assert main(["run", str(tmp_path), "--out", str(tmp_path / "out")]) == 143
    assert "interrupted (SIGTERM)" in capsys.readouterr().err
    assert _handlers() == before


@pytest.fixture
def utf8_locale():
    """The process in a UTF-8 locale (as a user's terminal has it), put back after the test."""
    kept = locale.setlocale(locale.LC_ALL)
    try:
        locale.setlocale(locale.LC_ALL, "C.UTF-8")
    except locale.Error:
        pytest.skip("no C.UTF-8 locale on this machine")
    yield locale.setlocale(locale.LC_ALL)
    locale.setlocale(locale.LC_ALL, kept)


def _slices() -> sitk.Image:
    return sitk.GetImageFromArray(np.arange(4 * 6 * 5, dtype=np.int16).reshape(4, 6, 5))


def test_writing_a_dicom_series_keeps_the_locale(utf8_locale, tmp_path):
    write_dicom_series(_slices(), tmp_path / "ct", seed=3)
    assert len(list((tmp_path / "ct").glob("*.dcm"))) == 4
    assert locale.setlocale(locale.LC_ALL) == utf8_locale
    assert locale.getpreferredencoding(False) == "UTF-8"


def test_a_dicom_series_the_writer_fails_on_is_one_line_naming_it_and_leaves_nothing(tmp_path, monkeypatch):
    """GDCM raises RuntimeError on a full disk ("DICOM does not support this component type" was what a full /tmp
    gave): it was a traceback from ``emreg simulate`` of a DICOM case, where an NRRD's is one line."""
    written = []
    execute = sitk.ImageFileWriter.Execute

    def fails_on_the_third(self, *args):
        written.append(1)
        if len(written) == 3:
            raise RuntimeError("ITK ERROR: GDCMImageIO: DICOM does not support this component type")
        return execute(self, *args)

    monkeypatch.setattr(sitk.ImageFileWriter, "Execute", fails_on_the_third)
    with pytest.raises(EMRegError, match=r"ct: cannot write \(the ITK image writer failed"):
        write_dicom_series(_slices(), tmp_path / "ct", seed=3)
    assert list(tmp_path.iterdir()) == []


def test_writing_a_dicom_file_keeps_the_locale(utf8_locale, tmp_path):
    write_image(_slices()[:, :, 0], tmp_path / "slice.dcm", compress=False)
    assert (tmp_path / "slice.dcm").stat().st_size > 0
    assert locale.setlocale(locale.LC_ALL) == utf8_locale
