"""The trackers' own flags (issue 27, part 3), from the simulators' field inputs through EMReg's drivers into the
samples, the live watchdog, the TransformStatus and the recordings.

trakSTAR: the METAL byte (0..127) appended to each record follows the distortion at the sensor; the watchdog
withholds a pose whose METAL byte is above its limit. Aurora: each tool's RMS error follows the distortion, and a
tool near the faces of the characterised volume is partly out of it (port status 0x80), outside it out of volume
(0x40): the samples say which, the watchdog names it, and a PLUS sequence recording keeps it as the frame's
TransformStatus. Both simulators take the same inputs (:mod:`EMRegModule.devices.simulator.tracker_flags`), over real
pseudo-terminals and, for the Aurora, NDI's own ndicapi.
"""

from __future__ import annotations

import contextlib

import numpy as np
import pytest
from polling import wait_for

from EMRegModule.devices.aurora import protocol as ndi
from EMRegModule.devices.aurora.driver import AuroraDriver
from EMRegModule.devices.samples import FLAG_OUT_OF_VOLUME, FLAG_PARTLY_OUT_OF_VOLUME, STATUS_OUT_OF_RANGE
from EMRegModule.devices.simulator.aurora import CLEAN_ERROR, AuroraSimulator, parse_tools
from EMRegModule.devices.simulator.scene import BuiltinScene
from EMRegModule.devices.simulator.tracker_flags import (
    METAL_PER_MM,
    MeasurementVolume,
    PointDistortion,
    UniformDistortion,
    parse_distortion,
    parse_volume,
    trakstar_metal,
)
from EMRegModule.devices.simulator.trakstar import TrackerSimulator
from EMRegModule.devices.trakstar.driver import TrakstarDriver
from EMRegModule.errors import EMRegError
from EMRegModule.io.sequence_metafile import read_sequence_metafile
from EMRegModule.live.navigator import Watchdog
from EMRegModule.live.writers import SequenceRecordingWriter


def test_flag_inputs_parse_and_scale():
    assert parse_distortion("0.4") == UniformDistortion(0.4)
    point = parse_distortion("2@300,40,120,50")
    assert isinstance(point, PointDistortion)
    assert point.distortion_mm(np.array([300.0, 40.0, 170.0])) == pytest.approx(2.0)  # at R: MM
    assert point.distortion_mm(np.array([300.0, 40.0, 220.0])) == pytest.approx(0.25)  # at 2 R: 1/8
    assert point.distortion_mm(np.array([300.0, 40.0, 120.0])) == pytest.approx(16.0)  # capped inside R / 2
    for bad in ("-1", "x", "1@1,2,3", "1@1,2,3,0"):
        with pytest.raises(EMRegError, match="--distortion"):
            parse_distortion(bad)
    assert trakstar_metal(0.0, clean=2.0) == 2 and trakstar_metal(0.5) == round(0.5 * METAL_PER_MM)
    assert trakstar_metal(10.0) == 127
    volume = parse_volume("0,0,0,100,100,100:10")
    assert [volume.state(np.array(p)) for p in ([50, 50, 50], [95, 50, 50], [50, 50, 101])] == ["in", "partly", "out"]
    with pytest.raises(EMRegError, match="--volume"):
        parse_volume("0,0,0,100,100")


def test_trakstar_metal_byte_follows_the_distortion_at_each_sensor():
    scene = BuiltinScene(1)
    # a metal object 60 mm from the reference sensor: 0.6 mm of distortion there, far less at the other ports
    centre = scene.reference_position + [0.0, 0.0, 60.0]
    with TrackerSimulator(scene, keep_truth=True, seed=1) as sim:
        sim.distortion = PointDistortion(tuple(centre), 0.6, 60.0)
        with TrakstarDriver(sim.path) as driver:
            driver.configure("POSITION/ANGLES", metal=True, group=True)
            samples = [s for _ in range(5) for s in driver.point_all()]
    expected = {s: [trakstar_metal(sim.distortion.distortion_mm(t.pose.position_mm)) for t in sim.truth[-20:]
                    if t.sensor == s] for s in (1, 2, 3, 4)}
    got = {s: [x.quality for x in samples if x.sensor == s] for s in (1, 2, 3, 4)}
    assert got == {s: [float(v) for v in expected[s]] for s in got}
    assert set(got[1]) == {round(0.6 * METAL_PER_MM)} and max(got[3] + got[4]) < 3
    # the watchdog withholds a pose with the reference's METAL byte above its limit (20)
    dog = Watchdog(period_s=0.0125)
    reference, probe = samples[-4], samples[-3]
    dog.observe(reference, 0.0)
    dog.observe(probe, 0.0)
    verdict = dog.evaluate(0.001)
    assert verdict.reason == "bad_quality" and "reference sensor (port 1) quality 24" in verdict.message


def test_the_physical_dipole_model_drives_the_trakstar_metal_byte():
    """The induced dipole that moves the simulated poses (:class:`FieldDistortion`) is a flag model as it is: a steel
    rod 60 mm from the reference sensor gives the METAL byte its position error there, far less at the far ports."""
    from EMRegModule.simulation.distortion import FieldDistortion

    scene = BuiltinScene(1)
    rod = FieldDistortion(scene.reference_position + [0.0, 0.0, 60.0], 1e5 * np.diag([1.0, 0.1, 0.1]))
    size = rod.distortion_mm(scene.reference_position)
    rod = rod.scaled(0.6 / size)  # 0.6 mm at the reference, to first order linear in the strength
    assert rod.distortion_mm(scene.reference_position) == pytest.approx(0.6, rel=1e-6)
    assert rod.distortion_mm(scene.reference_position) == pytest.approx(
        float(np.linalg.norm(rod.errors_at(scene.reference_position)[0][0])))
    with TrackerSimulator(scene, keep_truth=True, seed=1) as sim:
        sim.distortion = rod
        with TrakstarDriver(sim.path) as driver:
            driver.configure("POSITION/ANGLES", metal=True, group=True)
            samples = [s for _ in range(5) for s in driver.point_all()]
    expected = {s: [float(trakstar_metal(rod.distortion_mm(t.pose.position_mm))) for t in sim.truth[-20:]
                    if t.sensor == s] for s in (1, 2, 3, 4)}
    assert {s: [x.quality for x in samples if x.sensor == s] for s in (1, 2, 3, 4)} == expected
    assert set(expected[1]) == {round(0.6 * METAL_PER_MM)}


@contextlib.contextmanager
def _aurora(tmp_path, **flags):
    """An Aurora simulator with two 6-DOF tools, its ``distortion`` / ``volume`` set, and EMReg's driver on it."""
    link = tmp_path / "aurora"
    with AuroraSimulator(tools=parse_tools("1:6dof,2:6dof"), link=link) as sim:
        for name, value in flags.items():
            setattr(sim, name, value)
        driver = AuroraDriver(str(link), 115200).open()
        try:
            yield sim, driver
        finally:
            driver.close()


def test_aurora_rms_error_follows_the_distortion(tmp_path):
    scene = BuiltinScene(0)
    distortion = PointDistortion(tuple(scene.reference_position + [80.0, 0.0, 0.0]), 1.0, 80.0)
    with _aurora(tmp_path, distortion=distortion) as (sim, driver):
        samples = []
        driver.start(samples.append)
        assert wait_for(lambda: len(samples) >= 40)
        driver.stop()
    for sample in samples[-20:]:
        _, position = sim.truth_for_frame(sample.sensor, sample.frame)
        assert sample.valid
        assert sample.quality == pytest.approx(CLEAN_ERROR + distortion.distortion_mm(position), abs=1e-4)
    assert {round(s.quality, 3) for s in samples if s.sensor == 1} == {round(CLEAN_ERROR + 1.0, 3)}


def test_aurora_volume_flags_reach_the_watchdog_and_the_recording(tmp_path):
    """The reference sits 5 mm inside the volume's +X face (partly out); the probe wanders in and out of it."""
    reference = BuiltinScene(0).reference_position
    volume = MeasurementVolume((reference[0] - 400.0, -600.0, -600.0), (reference[0] + 5.0, 600.0, 600.0), 10.0)
    with _aurora(tmp_path, volume=volume) as (sim, driver):
        samples = []
        driver.start(samples.append)
        assert wait_for(lambda: sum(s.sensor == 2 for s in samples) >= 120)
        driver.stop()
    states = {}
    for sample in samples:
        _, position = sim.truth_for_frame(sample.sensor, sample.frame)
        states.setdefault(volume.state(position), []).append(sample)
    assert set(states) == {"in", "partly", "out"}  # the probe crossed the face
    assert all(s.valid and s.transform_status == "OK" for s in states["in"])
    for state, flag, bit, name in (("partly", FLAG_PARTLY_OUT_OF_VOLUME, ndi.PORT_PARTIALLY_IN_VOLUME,
                                    "PARTIALLY_OUT_OF_VOLUME"),
                                   ("out", FLAG_OUT_OF_VOLUME, ndi.PORT_OUT_OF_VOLUME, "OUT_OF_VOLUME")):
        flagged = states[state]
        assert {s.status for s in flagged} == {STATUS_OUT_OF_RANGE} and not any(s.valid for s in flagged)
        assert {s.extra["flag"] for s in flagged} == {flag} and all(s.extra["port_status"] & bit for s in flagged)
        assert {s.transform_status for s in flagged} == {name}
    assert all(s.sensor == 2 for s in states["out"]) and any(s.sensor == 1 for s in states["partly"])
    # the watchdog names it
    dog = Watchdog(period_s=0.025)
    dog.observe(next(s for s in states["partly"] if s.sensor == 1), 0.0)
    dog.observe(next(s for s in states["in"] if s.sensor == 2), 0.0)
    verdict = dog.evaluate(0.001)
    assert verdict.reason == "out_of_range" and verdict.error_name == "PartlyOutOfVolume"
    assert "reference sensor (port 1) partly out of the tracker's measurement volume" in verdict.message
    # a PLUS sequence recording keeps each frame's TransformStatus
    path = tmp_path / "rec.seq.mha"
    writer = SequenceRecordingWriter(path)
    for sample in samples:
        writer.write_sample(sample)
    writer.close()
    text = path.read_text(errors="replace")
    assert "TransformStatus = PARTIALLY_OUT_OF_VOLUME" in text and "TransformStatus = OUT_OF_VOLUME" in text
    recording = read_sequence_metafile(path)  # the flagged frames are never poses
    assert len(recording) == len(states["in"])


def test_sim_tracker_refuses_a_volume_for_the_trakstar_and_a_bad_distortion(capsys):
    from EMRegModule.cli.main import main

    assert main(["sim-tracker", "--volume", "0,0,0,1,1,1"]) == 2
    assert "--volume: only the aurora" in capsys.readouterr().err
    assert main(["sim-tracker", "--model", "aurora", "--distortion", "a@b"]) == 2
    assert "--distortion 'a@b'" in capsys.readouterr().err
