"""Detection's examiners (``EMRegModule.core.detection.examiners``): a forked process beside the threads works on the
voxels as they are written into shared memory, gives the same answers, hands its errors back, and dies with the
command (``interrupts.die_with_parent``); regions wait in one queue for whichever examiner is free. The scripts run
in a fresh interpreter (a single thread, as the command)."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import numpy as np

from EMRegModule.core.detection.examiners import Examiners

_SCRIPT = """
import json, os
import numpy as np
from EMRegModule.core.detection.examiners import Examiners
from EMRegModule.io.ct_handle import anonymous_voxels

_, volume = anonymous_voxels((8, 6, 5), np.int16, shared=True)  # 5 slices of 6 x 8, written after the fork

def where_and_sum(voxels, k):
    if k < 0:
        raise ValueError(f"no slice {k}")
    return os.getpid(), int(voxels[k].sum())

with Examiners(volume, 2, fork=True) as examiners:
    assert examiners.forked
    for k in range(5):
        volume[k] = k + 1  # written after the fork: the examiner sees it through the shared memory
    futures = [examiners.submit(where_and_sum, k) for k in range(5)]
    answers = [f.result() for f in futures]
    try:
        examiners.submit(where_and_sum, -1).result()
        error = None
    except ValueError as exc:
        error = str(exc)
print(json.dumps({"answers": answers, "me": os.getpid(), "error": error}))
"""


def test_a_forked_examiner_sees_the_voxels_written_after_it_and_gives_the_threads_answers():
    done = subprocess.run([sys.executable, "-c", _SCRIPT], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    report = json.loads(done.stdout.splitlines()[-1])
    assert [total for _, total in report["answers"]] == [48 * (k + 1) for k in range(5)]
    assert {pid for pid, _ in report["answers"]} - {report["me"]}, "the forked examiner took some of the regions"
    assert report["error"] == "no slice -1"  # its error, back with its own type and message


def test_examiners_without_fork_are_threads_with_the_same_answers():
    volume = np.arange(5 * 6 * 8, dtype=np.int16).reshape(5, 6, 8)
    with Examiners(volume, 2) as examiners:
        assert not examiners.forked
        totals = [examiners.submit(lambda voxels, k: int(voxels[k].sum()), k).result() for k in range(5)]
    assert totals == [int(volume[k].sum()) for k in range(5)]


def test_a_forked_helper_dies_with_its_command():
    """``kill -9`` of the command must not leave a reader or an examiner running (or waiting for work) alone."""
    script = ("import os, signal, sys, time\n"
              "from EMRegModule.interrupts import die_with_parent\n"
              "parent = os.getpid()\n"
              "child = os.fork()\n"
              "if child == 0:\n"
              "    die_with_parent(parent)\n"
              "    time.sleep(600)\n"
              "    os._exit(0)\n"
              "print(child, flush=True)\n"
              "sys.stdin.read()\n")  # until the test has the child's pid
    command = subprocess.Popen([sys.executable, "-c", script], stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                               text=True)
    child = int(command.stdout.readline())
    assert _alive(child)
    command.kill()
    command.wait(timeout=60)
    for _ in range(600):  # the kernel ends the child once the parent is gone (a reparented zombie is reaped)
        if not _alive(child):
            break
        subprocess.run(["sleep", "0.05"], check=True)
    assert not _alive(child)


def _alive(pid: int) -> bool:
    try:
        with open(f"/proc/{pid}/stat") as stat:
            return stat.read().split(")")[-1].split()[0] != "Z"
    except FileNotFoundError:
        return False


def test_examiners_fall_back_to_threads_when_the_system_refuses_a_process(monkeypatch):
    """A fork refused (too many processes, too little memory: EAGAIN / ENOMEM) is no reason to fail a detection."""
    def refused() -> int:
        raise BlockingIOError(11, "Resource temporarily unavailable")

    monkeypatch.setattr(os, "fork", refused)
    volume = np.ones((3, 4, 5), dtype=np.int16)
    with Examiners(volume, 2, fork=True) as examiners:
        assert not examiners.forked
        assert examiners.submit(lambda voxels, k: int(voxels[k].sum()), 1).result() == 20


def test_no_region_waits_behind_a_slow_one_while_an_examiner_is_free():
    """Regions wait in the examiners' common queue, not in one examiner's: while one examiner is held by a slow
    region (a decoy tried from every start), every later region goes to the other."""
    import threading
    from concurrent.futures import wait

    release = threading.Event()

    def slow(voxels, _):
        release.wait(120)
        return "slow"

    volume = np.zeros((2, 2, 2), dtype=np.int16)
    with Examiners(volume, 2) as examiners:
        held = examiners.submit(slow, 0)
        quick = [examiners.submit(lambda voxels, k: k, k) for k in range(6)]
        done, _ = wait(quick, timeout=120)
        assert len(done) == 6 and not held.done(), "a region waited behind the slow one"
        release.set()
        assert held.result() == "slow" and [f.result() for f in quick] == list(range(6))


def test_shutting_examiners_down_on_a_failure_drops_the_regions_not_started():
    import threading

    release = threading.Event()
    volume = np.zeros((2, 2, 2), dtype=np.int16)
    examiners = Examiners(volume, 1)
    held = examiners.submit(lambda voxels: release.wait(120))
    waiting = [examiners.submit(lambda voxels, k: k, k) for k in range(3)]
    waiting[-1].add_done_callback(lambda _: release.set())  # the held region ends once the others are dropped
    examiners.shutdown(cancel=True)
    assert held.result() is True and all(f.cancelled() for f in waiting)
