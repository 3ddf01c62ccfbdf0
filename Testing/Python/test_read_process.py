"""``emreg detect`` reads a DICOM series that it cannot index in its files (compressed slices, 8- or 32-bit ones:
not a :class:`~EMRegModule.io.dicom_slices.DicomSliceStack`) in a forked process (``EMRegModule.io.read_process``),
beside the import of the detection stage: the same voxels and sha256 as a read on threads, its errors (a short
slice, values beyond a compact read) coming back as the same one-line errors, a reader that dies or is cancelled
ending the read cleanly. The series here are plain 16-bit ones, which the stack is kept from taking
(in the reading scripts and the test process): what the reading process does does not depend on how the slices are
stored.

A process may fork a reader only while it has a single thread; the scripts here run in a fresh interpreter so that
they do (the test process may run others: pytest-xdist's), and each says whether its read went through a reader.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

import numpy as np
import SimpleITK as sitk
from dicom_files import make_volume, uid, write_series

from EMRegModule.io import dicom_read
from EMRegModule.io.dicom_read import open_dicom_series
from EMRegModule.io.image import read_ct

_OPEN = """
import json, sys
import numpy as np
from EMRegModule.io import dicom_read
folder, compact, out = sys.argv[1], sys.argv[2] == "compact", sys.argv[3]
dicom_read.DicomSliceStack.of = lambda *args, **kw: None  # read into memory (module docstring)
{patch}
fill, _ = dicom_read.open_dicom_series(folder, compact=compact, voxels_only=True)
report = {{"forked": fill.on_cancel is not None}}
{act}
try:
    fill.result()
    np.save(out, fill.voxels)
    report["sha256"] = fill.sha256.result()
except BaseException as exc:
    report["error"] = [type(exc).__name__, str(exc)]
import os, time
def children():
    found = []
    for task in os.listdir("/proc/self/task"):
        try:
            with open(f"/proc/self/task/{{task}}/children") as listed:
                found += listed.read().split()
        except FileNotFoundError:  # a thread that has just ended
            pass
    return found
report["reader while held"] = bool(children())
del fill
for _ in range(4000):  # until the reader, let go, has ended and been reaped
    if not children():
        break
    time.sleep(0.005)
report["children left"] = bool(children())
print(json.dumps(report))
"""


def _open_in_fresh_process(folder: Path, tmp_path: Path, compact: bool = False, patch: str = "",
                           act: str = "", forked: bool = True) -> dict:
    script = _OPEN.format(patch=patch, act=act)
    done = subprocess.run([sys.executable, "-c", script, str(folder), "compact" if compact else "exact",
                           str(tmp_path / "voxels.npy")], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    report = json.loads(done.stdout.splitlines()[-1])
    assert report["forked"] == forked, "a single-threaded process reads through a forked reader, if it may fork"
    assert not report["children left"], "the reader ends and is reaped once the voxels are let go"
    return report


def _series(tmp_path: Path, change: Callable[[np.ndarray], None] | None = None) -> tuple[Path, list[Path]]:
    """A 12-slice series stored as scanners often store it: unsigned 16 bits, intercept -1024 (int32 exactly, int16
    for a compact read); ``change`` edits the stored values first."""
    stored = make_volume(pixel=sitk.sitkUInt16, seed=21)  # 0 .. 3000 stored
    if change is not None:
        values = sitk.GetArrayFromImage(stored)
        change(values)
        changed = sitk.GetImageFromArray(values)
        changed.CopyInformation(stored)
        stored = changed
    files = write_series(stored, tmp_path / "series", uid(80), rescale=[(1.0, -1024.0)] * 12, bits_stored=16)
    return tmp_path / "series", files


def test_a_reading_process_gives_the_voxels_and_sha256_of_a_read_on_threads(tmp_path, monkeypatch):
    folder, _ = _series(tmp_path)
    report = _open_in_fresh_process(folder, tmp_path, compact=True)
    forked = np.load(tmp_path / "voxels.npy")
    monkeypatch.setattr(dicom_read, "can_fork_reader", lambda: False)  # this process: threads
    monkeypatch.setattr(dicom_read.DicomSliceStack, "of", lambda *args, **kw: None)
    fill, _ = open_dicom_series(folder, compact=True, voxels_only=True)
    fill.result()
    assert fill.on_cancel is None
    np.testing.assert_array_equal(forked, fill.voxels)
    np.testing.assert_array_equal(forked, sitk.GetArrayFromImage(read_ct(folder)))  # SimpleITK's values
    assert forked.dtype == np.int16
    assert report["sha256"] == fill.sha256.result()
    # the reader keeps the voxels while the command holds them: the memory is freed by the reader, after the command
    assert report["reader while held"]


def test_a_series_is_read_on_threads_when_the_system_refuses_a_reading_process(tmp_path):
    folder, _ = _series(tmp_path)
    refuse = ("def refused():\n"
              "    raise BlockingIOError(11, 'Resource temporarily unavailable')\n"
              "dicom_read.os.fork = refused")  # EAGAIN: too many processes
    report = _open_in_fresh_process(folder, tmp_path, patch=refuse, forked=False)
    assert "error" not in report and report["sha256"]
    np.testing.assert_array_equal(np.load(tmp_path / "voxels.npy"), sitk.GetArrayFromImage(read_ct(folder)))


def test_a_short_slice_read_by_a_reading_process_is_refused_naming_the_file(tmp_path):
    folder, files = _series(tmp_path)
    files[7].write_bytes(files[7].read_bytes()[:-100])
    report = _open_in_fresh_process(folder, tmp_path)
    kind, message = report["error"]
    assert kind == "EMRegError" and files[7].name in message and "cut short" in message and "\n" not in message


def test_a_compact_read_beyond_int16_comes_back_as_narrow_voxels_from_the_reading_process(tmp_path):
    def beyond(values: np.ndarray) -> None:
        values[5, 3, 4] = 40000  # 38976 HU: beyond int16

    folder, files = _series(tmp_path, beyond)
    kind, message = _open_in_fresh_process(folder, tmp_path, compact=True)["error"]
    assert kind == "NarrowVoxelsError" and files[5].name in message  # the controller then reads again as int32
    report = _open_in_fresh_process(folder, tmp_path, compact=False)
    assert "error" not in report and int(np.load(tmp_path / "voxels.npy").max()) == 38976


def test_a_reading_process_that_dies_ends_the_read_with_an_error(tmp_path):
    folder, _ = _series(tmp_path)
    die = ("import os, signal\n"
           "dicom_read._decode_series = lambda *args, **kw: os.kill(os.getpid(), signal.SIGKILL)")
    kind, message = _open_in_fresh_process(folder, tmp_path, patch=die)["error"]
    assert kind == "EMRegError" and str(folder) in message and "killed by SIGKILL" in message


def test_a_reading_process_ignores_the_signals_its_command_ignores(tmp_path):
    """A command started in the background of a script ignores SIGINT (the shell sets it so); its reader must not
    die of the Ctrl-C the command itself does not hear."""
    folder, _ = _series(tmp_path)
    interrupt = ("import os, signal\n"
                 "signal.signal(signal.SIGINT, signal.SIG_IGN)\n"
                 "read = dicom_read._decode_series\n"
                 "dicom_read._decode_series = lambda *args, **kw: (os.kill(os.getpid(), signal.SIGINT), "
                 "read(*args, **kw))")
    report = _open_in_fresh_process(folder, tmp_path, patch=interrupt)
    assert "error" not in report and report["sha256"]


def test_cancelling_a_read_kills_its_reading_process(tmp_path):
    folder, _ = _series(tmp_path)
    hang = "import time\ndicom_read._decode_series = lambda *args, **kw: time.sleep(600)"
    cancel = "fill.cancel()\nreport['read error'] = repr(fill.read_error())"
    report = _open_in_fresh_process(folder, tmp_path, patch=hang, act=cancel)
    assert report["read error"] == "None"  # a cancellation, not the read's own error
    assert report["error"][0] == "CancelledReadError"


def test_emreg_detect_reads_through_a_process_only_when_it_may_fork(small_dicom_case, tmp_path):
    """``emreg detect`` forks a reader when it runs alone (the command), and with more than one CPU an examiner of
    the candidate regions beside its threads (the voxels are then memory it sees as they are written); it reads on
    threads when another thread runs (a fork would leave that thread's locks held in the child), and examines on
    threads alone. The same markers either way."""
    script = ("import json, sys, threading\n"
              "from EMRegModule.io import read_process\n"
              "from EMRegModule.cli.main import main\n"
              "forks = []\n"
              "original = read_process.os.fork\n"
              "read_process.os.fork = lambda: forks.append(1) or original()\n"
              "stop = threading.Event()\n"
              "if sys.argv[3] == 'threads':\n"
              "    threading.Thread(target=stop.wait).start()\n"
              "code = main(['detect', sys.argv[1], '--out', sys.argv[2], '--quiet'])\n"
              "stop.set()\n"
              "print(json.dumps([code, len(forks)]))\n")
    markers = {}
    for mode in ("threads", "process"):
        out = tmp_path / mode
        done = subprocess.run([sys.executable, "-c", script, str(small_dicom_case / "ct"), str(out), mode],
                              capture_output=True, text=True, timeout=300)
        assert done.returncode == 0, done.stderr
        forks = 0 if mode == "threads" else 1 + ((os.cpu_count() or 1) >= 2)  # the reader, and the examiner
        assert json.loads(done.stdout.splitlines()[-1]) == [0, forks]
        document = json.loads((out / "markers.json").read_text())
        document.pop("provenance")
        markers[mode] = document
    assert markers["process"]["markers"] and markers["threads"] == markers["process"]
