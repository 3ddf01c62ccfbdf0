"""Defects a sweep of the live tracking paths found (the Aurora, the trakSTAR, ``emreg record`` and the
OpenIGTLink stream in the situations an operating room brings), each checked over a real pseudo-terminal
or real TCP, against outside code where it exists.

- A tool unplugged and plugged back in during tracking never came back: on the Aurora the unplugged
  tool's port handle goes stale and the replugged tool appears under a new handle that waits for PINIT /
  PENA (which the Aurora takes only outside tracking), announced by system status 0x0040 in every BX/TX
  reply. EMReg's driver polled the old handle for ever (the probe "not attached" for the rest of the
  recording), and the simulator hid it by giving the replugged tool its old handle back. The simulator
  now allocates a new handle as the Aurora does, and the driver, on that status bit, stops tracking,
  frees the stale handle, initialises and enables the new one under the port's sensor number and starts
  again, its frame numbers and times still increasing (once per rise of the bit). A tool without SROM
  plugged in meanwhile ends tracking with the one-line error that names its port, as at start-up.
- A tool partially out of the Aurora's characterised volume (port status bit 0x80 on a transform the
  Aurora reports as valid) was taken as a good measurement, while one wholly out of it (bit 0x40) was
  marked out of range: the same pose of unvouched accuracy was recorded and navigated on. Both bits now
  mark the sample out of range; the simulator has the state (``--fault partly-out=SENSOR@START-END``).

Checked and held (tests here where no existing test covered it): ``emreg record`` killed (SIGKILL) or
interrupted (Ctrl-C) mid-recording leaves a CSV that reads whole - rows reach the file in whole writes,
Ctrl-C ends cleanly (exit 0) with every counted sample in the file; a byte duplicated anywhere in a
trakSTAR stream record never makes a wrong record, and the records after it are read again.
"""

from __future__ import annotations

import contextlib
import os
import signal
import subprocess
import sys

import numpy as np
from polling import wait_for

from EMRegModule.devices.aurora import protocol as ndi
from EMRegModule.devices.aurora.driver import AuroraDriver
from EMRegModule.devices.samples import STATUS_NOT_ATTACHED, STATUS_OK, STATUS_OUT_OF_RANGE
from EMRegModule.devices.simulator.aurora import AuroraSimulator, parse_tools
from EMRegModule.devices.simulator.trakstar import TrackerSimulator
from EMRegModule.devices.trakstar import protocol as tp
from EMRegModule.devices.trakstar.protocol import Pose
from EMRegModule.io.tracking_csv import read_tracking_csv

EMREG = [sys.executable, "-m", "EMRegModule"]
ENV = dict(os.environ, PYTHONUNBUFFERED="1")


# --- the Aurora ---------------------------------------------------------------------------------------------


@contextlib.contextmanager
def _aurora(tmp_path, tools: str, unplugged: int | None = None):
    """An Aurora simulator with ``tools`` (the tool of port ``unplugged`` out of its socket at start) and EMReg's
    driver opened on it: ``(simulator, driver, samples)``, the samples the driver gives out once started; the
    driver is closed afterwards."""
    link = tmp_path / "aurora"
    with AuroraSimulator(tools=parse_tools(tools), link=link) as sim:
        if unplugged is not None:
            sim.set_state("unplug", unplugged)
        driver = AuroraDriver(str(link), 115200).open()
        try:
            yield sim, driver, []
        finally:
            driver.close()


def test_aurora_tool_unplugged_and_plugged_back_is_tracked_again_under_a_new_handle(tmp_path):
    with _aurora(tmp_path, "1:6dof,2:6dof,3:6dof") as (sim, driver, samples):
        assert [(t.handle, t.sensor) for t in driver.tools] == [(0x0A, 1), (0x0B, 2), (0x0C, 3)]
        driver.start(samples.append)
        assert wait_for(lambda: len(samples) >= 30)
        sim.set_state("unplug", 2)
        assert wait_for(lambda: sum(s.sensor == 2 and s.status == STATUS_NOT_ATTACHED for s in samples) >= 5)
        mark = len(samples)
        sim.set_state("unplug", 2, False)
        back = wait_for(lambda: any(s.sensor == 2 and s.status == STATUS_OK for s in samples[mark:]), 15.0)
        driver.stop()
    assert back, "the replugged probe never came back"
    assert driver.stats.replugs == 1 and driver.error is None
    assert "PHF" in sim.commands  # the stale handle was freed
    handle = next(t.handle for t in driver.tools if t.sensor == 2)
    assert handle not in (0x0A, 0x0B, 0x0C)
    # every pose given out is the one the device measured for its frame, never another tool's or handle's
    for s in samples:
        if s.status == STATUS_OK:
            q, p = sim.truth_for_frame(s.sensor, s.extra["device_frame"])
            assert np.array_equal(np.float32(s.position_mm), np.float32(p))
    # frame numbers and times keep increasing across the restart (the device counts anew from TSTART)
    frames = [s.frame for s in samples if s.sensor == 1]
    assert all(b > a for a, b in zip(frames, frames[1:], strict=False))
    assert all(s.time_s == (s.frame - samples[0].frame) / 40.0 for s in samples)


def test_aurora_tool_without_srom_plugged_in_mid_recording_is_a_clear_error(tmp_path):
    with _aurora(tmp_path, "1:6dof,2:6dof,3:nosrom", unplugged=3) as (sim, driver, samples):  # 3: plugged later
        assert [t.sensor for t in driver.tools] == [1, 2]
        driver.start(samples.append)
        assert wait_for(lambda: len(samples) >= 20)
        sim.set_state("unplug", 3, False)
        assert wait_for(lambda: driver.error is not None)
    assert "port 3" in driver.error and "SROM" in driver.error and "\n" not in driver.error


def test_aurora_tool_partially_out_of_volume_is_never_a_measurement(tmp_path):
    with _aurora(tmp_path, "1:6dof,2:6dof") as (sim, driver, samples):
        driver.start(samples.append)
        assert wait_for(lambda: len(samples) >= 20)
        sim.set_state("partly-out", 2)
        flagged = lambda: [s for s in samples if s.extra["port_status"] & ndi.PORT_PARTIALLY_IN_VOLUME]  # noqa: E731
        assert wait_for(lambda: len(flagged()) >= 10)
        sim.set_state("partly-out", 2, False)
        mark = len(samples)
        assert wait_for(lambda: any(s.sensor == 2 and s.status == STATUS_OK for s in samples[mark:]))
        driver.stop()
    assert all(s.sensor == 2 for s in flagged())
    assert {s.status for s in flagged()} == {STATUS_OUT_OF_RANGE}
    assert not any(s.valid for s in flagged())


# --- emreg record ended abruptly ----------------------------------------------------------------------------


def _lines_on_disk(path) -> int:
    try:
        with open(path, "rb") as f:
            return f.read().count(b"\n")
    except FileNotFoundError:
        return 0


def test_record_killed_or_interrupted_keeps_a_readable_recording(tmp_path):
    with TrackerSimulator(seed=5, link=tmp_path / "trakstar") as sim:
        for how in (signal.SIGKILL, signal.SIGINT):
            out = tmp_path / f"rec-{how.name}.csv"
            record = subprocess.Popen([*EMREG, "record", "--device", f"trakstar://{sim.link}?rate=80", "--out",
                                       str(out)], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=ENV)
            try:
                assert wait_for(lambda out=out: _lines_on_disk(out) > 400), record.stderr
                record.send_signal(how)
                stdout, stderr = record.communicate(timeout=30)
            finally:
                if record.poll() is None:
                    record.kill()
                    record.communicate()
            recording = read_tracking_csv(out)  # the recording as the kill or the interrupt left it
            assert len(recording) >= 400 and set(np.unique(recording.sensor)) == {1, 2, 3, 4}
            if how == signal.SIGINT:  # Ctrl-C: a clean end, every sample it counted is in the file
                assert record.returncode == 0, stderr
                assert f"{len(recording)} samples recorded -> {out} (interrupted)" in stdout


# --- the trakSTAR line ----------------------------------------------------------------------------------------


def test_trakstar_byte_duplicated_anywhere_never_makes_a_wrong_record():
    rng = np.random.default_rng(11)
    fmt = tp.FORMATS["POSITION/ANGLES"]
    records = [tp.encode_record(fmt, Pose(rng.uniform(-300, 300, 3), np.array([10.0, 20.0, 30.0])), 36, metal=0,
                                address=i % 4 + 1) for i in range(8)]
    for damaged_index in range(1, 7):
        for position in range(len(records[damaged_index])):
            damaged = list(records)
            record = damaged[damaged_index]
            damaged[damaged_index] = record[:position + 1] + record[position:]  # the line repeated one byte
            parser = tp.RecordParser(len(records[0]), frozenset({1, 2, 3, 4}))
            got = parser.feed(b"".join(damaged), 0)
            assert all(g in records for g in got), (damaged_index, position)  # never a record that was not sent
            if position > 0:  # a repeated data byte: the record is one byte long and dropped
                assert records[damaged_index] not in got
            # resynchronised: every record but the damaged one and (follow check) the one before it is read
            assert len(got) >= len(records) - 2, (damaged_index, position)
