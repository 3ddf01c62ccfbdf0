"""Trust during navigation (issue 27, parts 2 and 4): checkpoints at the pinholes, the pose status they give,
and the warning when the reference sensor jumps.

The CI-sized case of ``conftest.small_case`` (its run's registration and markers), with navigation recordings
simulated anew for the same seed: unlabelled rests of the probe in marker pinholes, and a slip of the reference
sensor in its slot (2 mm) halfway through, whose ground truth the simulator gives.
"""

from __future__ import annotations

import contextlib
import io
import json
from pathlib import Path

import numpy as np
import pytest
from conftest import SMALL_CASE_OPTIONS

from EMRegModule.cli.main import main
from EMRegModule.core.checkpoints import (
    Checkpoint,
    Pinholes,
    TrustMonitor,
    find_checkpoints,
    pinholes_from_detection,
    pose_status,
    reference_jumps,
)
from EMRegModule.core.navigation import navigate_recording
from EMRegModule.core.transforms import apply_transform, axis_angle_to_rotation, make_transform
from EMRegModule.io.markers_json import markers_beside
from EMRegModule.io.recording import read_recording
from EMRegModule.io.registration_files import read_registration
from EMRegModule.settings import NavigationSettings, Settings
from EMRegModule.simulation.case import simulate_recordings

CHECKPOINTS = 4


def _navigate(case: Path, registration: Path, out: Path, *extra: str) -> tuple[int, str]:
    """``emreg navigate`` on ``case/navigation.csv`` in this process; (exit code, stderr)."""
    err = io.StringIO()
    with contextlib.redirect_stderr(err):
        code = main(["navigate", "--registration", str(registration), "--source", f"replay:{case / 'navigation.csv'}",
                     "--out", str(out), "--quiet", *extra])
    return code, err.getvalue()


def _rows(path: Path) -> list[list[str]]:
    lines = path.read_text().splitlines()
    assert lines[0] == "time_s,x_mm,y_mm,z_mm,label,status"
    return [line.split(",") for line in lines[1:]]


@pytest.fixture(scope="module")
def sessions(small_case: Path, tmp_path_factory: pytest.TempPathFactory) -> dict:
    """Navigations of the small case's frame with rests in pinholes: ``clean`` and ``slip`` (2 mm at mid-session),
    each navigated offline by ``emreg navigate`` against the small case's run."""
    registration = small_case.parent / "out" / "registration.json"
    out = {}
    for name, slip in (("clean", 0.0), ("slip", 2.0)):
        folder = tmp_path_factory.mktemp(name)
        truth = simulate_recordings(folder / "case", seed=6, navigation_checkpoints=CHECKPOINTS,
                                    reference_slip_mm=slip, **SMALL_CASE_OPTIONS)
        code, err = _navigate(folder / "case", registration, folder / "out")
        assert code == 0, err
        out[name] = {"case": folder / "case", "out": folder / "out", "truth": truth, "stderr": err,
                     "checkpoints": json.loads((folder / "out" / "checkpoints.json").read_text())}
    out["registration"] = registration
    return out


def test_clean_checkpoints_pass_and_no_jump_is_warned(sessions):
    report = sessions["clean"]["checkpoints"]
    assert report["max_error_mm"] == NavigationSettings().max_checkpoint_error_mm
    assert len(report["checkpoints"]) == CHECKPOINTS  # every rest in a pinhole is found without a label
    truth_names = [d["name"] for d in sessions["clean"]["truth"]["dwells"] if not d["label"]]
    assert len(truth_names) == CHECKPOINTS
    assert all(c["ok"] for c in report["checkpoints"]), report["checkpoints"]
    assert max(c["error_mm"] for c in report["checkpoints"]) < 1.0
    assert report["reference_jumps"] == [] and "jumped" not in sessions["clean"]["stderr"]
    # the poses are INVALID only where the tracker's quality number is bad (the simulator's wild samples)
    rows = _rows(sessions["clean"]["out"] / "navigation.csv")
    settings = Settings()
    recording = read_recording(sessions["clean"]["case"] / "navigation.csv", settings, 1, 2)
    navigation = navigate_recording(recording, read_registration(sessions["registration"]).reference_to_image)
    bad = navigation.quality > settings.navigation.max_quality
    assert [row[5] == "INVALID" for row in rows] == bad.tolist() and 0 < np.count_nonzero(bad) < 0.02 * len(rows)


def test_a_2mm_slip_is_flagged_at_the_first_checkpoint_after_it(sessions):
    slip = sessions["slip"]["truth"]["reference_slip"]
    assert slip["translation_mm"] == pytest.approx(2.0) and slip["rotation_deg"] == pytest.approx(0.0, abs=1e-6)
    checkpoints = sessions["slip"]["checkpoints"]["checkpoints"]
    before = [c for c in checkpoints if c["end_s"] < slip["time_s"]]
    after = [c for c in checkpoints if c["start_s"] > slip["time_s"]]
    assert before and after and len(before) + len(after) == CHECKPOINTS
    assert all(c["ok"] for c in before)
    assert not after[0]["ok"]  # the first checkpoint after the slip
    true_after = [c["true_error_mm"] for c in slip["checkpoints"] if c["start_s"] > slip["time_s"]]
    measured = [c["error_mm"] for c in after]
    assert np.allclose(measured, true_after, atol=0.8), (measured, true_after)
    assert "FAILED" in sessions["slip"]["stderr"]
    # every pose from the failed checkpoint on is INVALID (no checkpoint passes again: the slip stays)
    rows = _rows(sessions["slip"]["out"] / "navigation.csv")
    time_s = np.array([float(r[0]) for r in rows])
    status = np.array([r[5] for r in rows])
    assert np.all(status[time_s >= after[0]["start_s"]] == "INVALID")
    assert np.mean(status[time_s < slip["time_s"]] == "OK") > 0.98


def test_a_reference_jump_is_warned_between_checkpoints(sessions):
    slip = sessions["slip"]["truth"]["reference_slip"]
    jumps = sessions["slip"]["checkpoints"]["reference_jumps"]
    assert len(jumps) == 1
    assert jumps[0]["time_s"] == pytest.approx(slip["time_s"], abs=0.05)
    assert jumps[0]["jump_mm"] == pytest.approx(2.0, abs=0.4)
    assert "the reference sensor jumped" in sessions["slip"]["stderr"]


def test_run_writes_checkpoints_json(small_case: Path):
    out = small_case.parent / "out"
    report = json.loads((out / "checkpoints.json").read_text())
    assert report["checkpoints"] == [] and report["max_error_mm"] == 1.5  # the case's navigation has no pinhole rest
    assert "checkpoints.json" in json.loads((out / "run.json").read_text())["outputs"]
    assert _rows(out / "navigation.csv")


def test_live_navigation_streams_checkpoints_and_invalidates_poses(sessions, tmp_path):
    """The live path (replay source, OpenIGTLink server on a free port) finds the same checkpoints, writes
    checkpoints.json and navigation.csv with the status, and says each result on the terminal."""
    out = tmp_path / "live"
    code, err = _navigate(sessions["slip"]["case"], sessions["registration"], out, "--fast", "--igtl-port", "0")
    assert code == 0, err
    live = json.loads((out / "checkpoints.json").read_text())
    offline = sessions["slip"]["checkpoints"]
    assert [(c["image_marker"], c["ok"]) for c in live["checkpoints"]] == \
        [(c["image_marker"], c["ok"]) for c in offline["checkpoints"]]
    assert len(live["reference_jumps"]) == 1
    failed = next(c for c in live["checkpoints"] if not c["ok"])
    rows = _rows(out / "navigation.csv")
    status = {float(r[0]): r[5] for r in rows}
    assert all(s == "INVALID" for t, s in status.items() if t > failed["end_s"] + 0.5)
    assert all(s == "OK" for t, s in status.items() if t < failed["start_s"])
    assert live["invalid_poses"] == list(status.values()).count("INVALID") > 0 and live["poses"] == len(rows)


def test_live_navigator_sends_checkpoint_status_and_invalid_transforms(sessions):
    """LiveNavigator with a TrustMonitor: a STATUS ``Checkpoint`` per result (OK, then the jump, then failed) and,
    after the failed checkpoint, every ProbeToImage with TransformStatus INVALID."""
    from EMRegModule.devices.samples import SensorSample
    from EMRegModule.live.navigator import CHECKPOINT_STATUS_NAME, LiveNavigator

    class Server:
        def __init__(self):
            self.log = []  # ("status", error name) and ("pose", TransformStatus), in the order sent

        def send(self, message):
            if message.device_name == CHECKPOINT_STATUS_NAME:
                self.log.append(("status", message.error_name))
            return 0

        def send_transform(self, name, matrix, stamp, status):
            self.log.append(("pose", status))
            return 0

    markers, note = markers_beside(sessions["registration"])
    assert note is None
    registration = read_registration(sessions["registration"])
    pinholes = pinholes_from_detection(markers, registration.sensor_offset_l_mm)
    server = Server()
    navigator = LiveNavigator(registration.reference_to_image, 1, 2, server, period_s=1.0, out=None,
                              trust=TrustMonitor(pinholes))  # fed as fast as it goes: never stale
    recording = read_recording(sessions["slip"]["case"] / "navigation.csv", Settings(), 1, 2)
    frame = -1
    for i in range(len(recording)):
        if recording.sensor[i] == 1:
            frame += 1
        navigator.on_sample(SensorSample(int(recording.sensor[i]), float(recording.time_s[i]),
                                         recording.position_mm[i], recording.rotation[i],
                                         float(recording.quality[i]), frame=frame))
    navigator.finish_trust()
    status = [value for kind, value in server.log if kind == "status"]
    assert status[:3] == ["CheckpointOK", "CheckpointOK", "ReferenceJump"] and status[3:] == ["CheckpointFailed"] * 2
    failed = server.log.index(("status", "CheckpointFailed"))
    before = [value for kind, value in server.log[:failed] if kind == "pose"]
    after = [value for kind, value in server.log[failed:] if kind == "pose"]
    assert len(after) > 500 and set(after) == {"INVALID"}
    bad = int(np.count_nonzero(recording.quality > 20))  # before: INVALID only while the watchdog withholds a pose
    assert len(before) - before.count("OK") <= bad < 0.02 * len(before)


# --- units -------------------------------------------------------------------------------------------------------


def _still_track(rng, centre, n=80, sigma=0.05):
    return centre + rng.normal(0, sigma, (n, 3))


def test_checkpoints_need_a_rest_near_a_pinhole_along_its_axis():
    rng = np.random.default_rng(0)
    pinholes = Pinholes(["I01", "I02"], np.array([[0.0, 0.0, 0.0], [60.0, 0.0, 0.0]]), np.array([[0, 0, 1.0]] * 2))
    along = np.tile([0.0, 0.0, -1.0], (80, 1))
    across = np.tile([1.0, 0.0, 0.0], (80, 1))
    moving = np.linspace([200.0, 0, 0], [100.0, 0, 0], 80)
    position = np.concatenate([_still_track(rng, [0.3, 0.0, 0.0]), moving, _still_track(rng, [62.0, 0, 0]), moving,
                               _still_track(rng, [60.0, 0.0, 0.5])])
    direction = np.concatenate([along, along, along, along, across])
    time_s = np.arange(len(position)) / 80.0
    found = find_checkpoints(time_s, position, direction, None, pinholes)
    assert [(c.image_marker, c.ok) for c in found] == [("I01", True), ("I02", False)]  # the third: wrong axis
    assert found[0].error_mm == pytest.approx(0.3, abs=0.05) and found[1].error_mm == pytest.approx(2.0, abs=0.05)
    # without an orientation the third rest counts too
    assert len(find_checkpoints(time_s, position, None, None, pinholes)) == 3


def test_pose_status_is_invalid_from_a_failed_checkpoint_until_one_passes():
    time_s = np.arange(0.0, 10.0, 0.5)
    checkpoints = [Checkpoint(1.0, 1.5, "I01", 0.3, True), Checkpoint(3.0, 3.5, "I02", 2.5, False),
                   Checkpoint(4.0, 4.5, "I03", 2.6, False), Checkpoint(6.0, 6.5, "I01", 0.4, True),
                   Checkpoint(8.0, 8.5, "I02", 1.9, False)]
    quality = np.zeros(len(time_s))
    quality[2] = 50.0
    status = pose_status(time_s, quality, checkpoints, max_quality=20.0)
    invalid = time_s[status == "INVALID"].tolist()
    assert invalid == [1.0, 3.0, 3.5, 4.0, 4.5, 5.0, 5.5, 8.0, 8.5, 9.0, 9.5]


def test_reference_jump_is_a_step_that_stays_not_motion_or_a_wild_sample():
    rng = np.random.default_rng(3)
    n = 400
    time_s = np.arange(n) / 80.0
    rotation = np.repeat(np.eye(3)[None], n, axis=0)
    # the table moves the frame steadily at 80 mm/s (1 mm per sample), with the tracker's jitter
    position = np.outer(time_s, [80.0, 0.0, 0.0]) + rng.normal(0, 0.04, (n, 3))
    assert reference_jumps(time_s, position, rotation) == []
    wild = position.copy()
    wild[150] += [0.0, 30.0, 0.0]  # one wild sample: not a jump
    assert reference_jumps(time_s, wild, rotation) == []
    slipped = position.copy()
    slipped[200:] += [0.0, 0.0, 1.0]  # the reference slipped 1 mm
    jumps = reference_jumps(time_s, slipped, rotation)
    assert len(jumps) == 1 and jumps[0].time_s == pytest.approx(time_s[200]) and jumps[0].jump_mm > 0.8
    turned = rotation.copy()
    turned[300:] = axis_angle_to_rotation([0.0, 1.0, 0.0], np.radians(0.6))
    jumps = reference_jumps(time_s, position, turned)
    assert len(jumps) == 1 and jumps[0].jump_deg == pytest.approx(0.6, abs=0.05)
    # live, one sample at a time: the same jump, once its window after it has arrived
    monitor = TrustMonitor(None)
    events = []
    for t, p, r in zip(time_s, slipped, rotation, strict=True):
        pose = np.eye(4)
        pose[:3, :3], pose[:3, 3] = r, p
        events += monitor.observe(float(t), None, pose)
    assert len(events) == 1 and events[0].time_s == pytest.approx(time_s[200])


def test_navigation_settings_are_checked_when_read():
    from EMRegModule.errors import EMRegError

    settings = Settings.from_mapping({"navigation": {"max_checkpoint_error_mm": 1.0, "reference_jump_mm": 0.8}})
    assert settings.navigation.max_checkpoint_error_mm == 1.0 and settings.navigation.still_radius_mm == 0.5
    for table in ({"max_checkpoint_error_mm": 6.0}, {"max_checkpoint_eror_mm": 1.0}, {"reference_jump_mm": "1"}):
        with pytest.raises(EMRegError, match=r"\[navigation\]"):
            Settings.from_mapping({"navigation": table})


# --- the noise-aware decision ------------------------------------------------------------------------------------


def _checked(case: Path, out: Path, with_model: bool):
    """The checkpoints of ``case/navigation.csv`` navigated with the registration in ``out`` (``emreg run``'s),
    judged with its error model (``with_model``) or by the fixed limit alone."""
    from EMRegModule.core.checkpoints import check_navigation

    registration = read_registration(out / "registration.json")
    markers, note = markers_beside(out / "registration.json")
    assert note is None
    pinholes = pinholes_from_detection(markers, registration.sensor_offset_l_mm,
                                       registration if with_model else None)
    recording = read_recording(case / "navigation.csv", Settings(), 1, 2)
    navigation = navigate_recording(recording, registration.reference_to_image)
    return check_navigation(navigation, recording, pinholes, 1, NavigationSettings())


def test_a_noisy_clean_session_passes_its_checkpoints_where_the_fixed_limit_fails_them(tmp_path: Path):
    """A tracker three times as noisy, calibrated and navigated (``emreg run``) with rests in pinholes: the error
    model's thresholds grow with the measured noise and every clean checkpoint passes; the fixed 1.5 mm limit alone
    fails some of the same checkpoints."""
    from EMRegModule.simulation.case import simulate_case

    case = tmp_path / "case"
    simulate_case(case, seed=6, spacing_mm=1.0, tracker_noise_scale=3.0, navigation_checkpoints=6,
                  **SMALL_CASE_OPTIONS)
    assert main(["run", str(case), "--out", str(tmp_path / "out"), "--quiet"]) == 0
    aware = _checked(case, tmp_path / "out", True)
    fixed = _checked(case, tmp_path / "out", False)
    assert len(aware.checkpoints) == len(fixed.checkpoints) >= 5
    assert all(c.ok for c in aware.checkpoints), [c.to_json() for c in aware.checkpoints]
    assert not all(c.ok for c in fixed.checkpoints)
    assert all(c.threshold_mm > NavigationSettings().max_checkpoint_error_mm for c in aware.checkpoints)
    document = aware.to_json()
    assert {"start_s", "end_s", "image_marker", "error_mm", "ok", "expected_mm", "threshold_mm"} <= \
        set(document["checkpoints"][0]) and document["max_error_mm"] == 1.5 and document["false_alarm"] == 1e-4
    assert any("cannot verify the limit" in line for line in aware.warnings())


def test_the_noise_aware_decision_flags_a_2mm_slip_at_the_first_checkpoint_after_it(sessions):
    """At the tracker's usual noise the model's threshold stays near the user's limit (8 markers: the probe's
    error known from 17 degrees of freedom): the slip fails the first checkpoint after it, the clean ones pass."""
    slip = sessions["slip"]["truth"]["reference_slip"]
    report = _checked(sessions["slip"]["case"], sessions["registration"].parent, True)
    after = [c for c in report.checkpoints if c.start_s > slip["time_s"]]
    assert all(c.ok for c in report.checkpoints if c.end_s < slip["time_s"])
    assert after and not after[0].ok
    assert all(1.5 <= c.threshold_mm < 2.0 and 0.2 < c.expected_mm < 1.0 for c in report.checkpoints), \
        [c.to_json() for c in report.checkpoints]


# --- a reference jump judged at the next checkpoint: slip or bump (EMRegModule.core.slip) -----------------------------


def _knocked(recording, time_s: float, tracker_motion: np.ndarray, sensors: tuple[int, ...]):
    """A copy of ``recording`` whose ``sensors`` are moved by ``tracker_motion`` (4x4, Tracker frame) from ``time_s``
    on: the reference alone (a slip in its slot) or every sensor (the frame and the probe in it knocked)."""
    from EMRegModule.core.tracking import TrackingRecording

    moved = (recording.time_s >= time_s) & np.isin(recording.sensor, sensors)
    position, rotation = recording.position_mm.copy(), recording.rotation.copy()
    position[moved] = position[moved] @ tracker_motion[:3, :3].T + tracker_motion[:3, 3]
    rotation[moved] = tracker_motion[:3, :3] @ rotation[moved]
    return TrackingRecording(recording.time_s, recording.sensor, position, rotation, recording.quality,
                             recording.label, recording.source)


@pytest.fixture(scope="module")
def knock(sessions) -> dict:
    """The clean session knocked between its 2nd and 3rd checkpoints by a 1 degree turn about an axis 60 mm from the
    3rd checkpoint's pinhole (it moves 1 mm there, 2-3 mm at the far pinholes): applied to the reference alone (a
    slip) or to both sensors (a bump). Returns the registration, pinholes, the time, the motion and the recording."""
    registration = read_registration(sessions["registration"])
    markers, _ = markers_beside(sessions["registration"])
    pinholes = pinholes_from_detection(markers, registration.sensor_offset_l_mm, registration)
    recording = read_recording(sessions["clean"]["case"] / "navigation.csv", Settings(), 1, 2)
    clean = _checked(sessions["clean"]["case"], sessions["registration"].parent, True).checkpoints
    time_s = 0.5 * (clean[1].end_s + clean[2].start_s)
    reference = recording.for_sensor(1)
    i = int(np.searchsorted(reference.time_s, time_s))
    image_to_tracker = make_transform(reference.rotation[i], reference.position_mm[i]) \
        @ np.linalg.inv(registration.reference_to_image)
    checked = apply_transform(image_to_tracker, pinholes.position_image[pinholes.ids.index(clean[2].image_marker)])
    away = apply_transform(image_to_tracker, pinholes.position_image.mean(axis=0)) - checked
    away /= np.linalg.norm(away)
    centre = checked + 60.0 * away
    turn = axis_angle_to_rotation(np.cross(away, [0.0, 0.0, 1.0]), np.radians(1.0))
    motion = make_transform(turn, centre - turn @ centre)
    return {"registration": registration, "pinholes": pinholes, "time_s": time_s, "motion": motion,
            "recording": recording, "reference_before": make_transform(reference.rotation[i - 1],
                                                                       reference.position_mm[i - 1])}


def _check(knock: dict, recording):
    from EMRegModule.core.checkpoints import check_navigation

    navigation = navigate_recording(recording, knock["registration"].reference_to_image)
    return check_navigation(navigation, recording, knock["pinholes"], 1, NavigationSettings()), navigation


def test_a_slip_whose_error_here_is_within_the_limit_is_confirmed_by_the_jump_it_made(knock):
    """The reference turned 1 degree in its slot: the first checkpoint after it is off by about 1 mm, within the limit
    and the noise-aware threshold (the decision without the jump passes it), but it matches the error the measured
    jump predicts there, and the slip's predicted error elsewhere on the frame exceeds the limit: it fails, and the
    next one too (a confirmed slip stands); every pose from the first is INVALID."""
    report, navigation = _check(knock, _knocked(knock["recording"], knock["time_s"], knock["motion"], (1,)))
    limit = NavigationSettings().max_checkpoint_error_mm
    assert len(report.reference_jumps) == 1
    jump = report.reference_jumps[0]
    assert jump.time_s == pytest.approx(knock["time_s"], abs=0.02)
    # the measured step is the applied one: ReferenceBeforeToReferenceAfter = inv(ReferenceToTracker) inv(M) RefToTr
    truth = np.linalg.inv(knock["reference_before"]) @ np.linalg.inv(knock["motion"]) @ knock["reference_before"]
    assert np.allclose(jump.reference_before_to_after[:3, 3], truth[:3, 3], atol=0.2)
    assert np.allclose(jump.reference_before_to_after[:3, :3], truth[:3, :3], atol=np.radians(0.1))
    before = [c for c in report.checkpoints if c.end_s < knock["time_s"]]
    after = [c for c in report.checkpoints if c.start_s > knock["time_s"]]
    assert len(before) == 2 and all(c.ok and c.slip is None for c in before)
    first = after[0]
    assert 0.5 < first.error_mm < limit and first.error_mm < first.threshold_mm  # the error alone would pass
    assert not first.ok and first.slip.verdict == "confirmed" and first.slip.fails
    assert first.slip.predicted_mm == pytest.approx(first.error_mm, abs=0.5) and first.slip.largest_mm > limit
    assert not after[1].ok and after[1].slip.fails  # the slip stands
    assert "confirms a slip of the reference" in first.describe(limit)
    assert np.all(navigation.status[navigation.time_s >= first.start_s] == "INVALID")
    document = report.to_json()
    assert document["checkpoints"][2]["slip"]["verdict"] == "confirmed" and "slip_test" in document
    assert len(document["reference_jumps"][0]["ReferenceBeforeToReferenceAfter"]) == 4
    # live, one sample at a time: the same verdicts
    monitor = TrustMonitor(knock["pinholes"])
    recording = _knocked(knock["recording"], knock["time_s"], knock["motion"], (1,))
    for t, probe_to_image, reference_to_tracker in _moments(recording, knock["registration"].reference_to_image):
        monitor.observe(t, probe_to_image, reference_to_tracker)
    monitor.flush()
    assert [(c.image_marker, c.ok, None if c.slip is None else c.slip.verdict) for c in monitor.report.checkpoints] \
        == [(c.image_marker, c.ok, None if c.slip is None else c.slip.verdict) for c in report.checkpoints]
    assert not monitor.valid


def test_a_bump_of_the_whole_frame_is_warned_and_ruled_out_as_a_slip_at_the_next_checkpoint(knock):
    """The same motion applied to both sensors (the frame, the reference and the probe in its pinholes moved together):
    the jump is warned, the checkpoints after it show no error where the slip would have made 1 mm: none confirms
    it (with 8 markers the model's noise is known from 17 degrees of freedom: 1 mm is too little to rule it out at
    once), and every checkpoint passes."""
    report, navigation = _check(knock, _knocked(knock["recording"], knock["time_s"], knock["motion"], (1, 2)))
    assert len(report.reference_jumps) == 1
    assert all(c.ok for c in report.checkpoints) and len(report.checkpoints) == CHECKPOINTS
    after = [c for c in report.checkpoints if c.start_s > knock["time_s"]]
    assert after and all(c.slip.verdict in ("open", "ruled_out") and not c.slip.fails for c in after)
    assert after[0].error_mm < 1.0 and after[0].slip.predicted_mm > 0.9 and after[0].slip.statistic < 1.0
    assert not np.any((navigation.status == "INVALID") & (navigation.quality <= NavigationSettings().max_quality))


def _moments(recording, reference_to_image: np.ndarray):
    """(time, ProbeToImage, ReferenceToTracker) per moment of a two-sensor recording, as live navigation sees them."""
    from EMRegModule.core.navigation import probe_to_image

    reference, probe = recording.for_sensor(1), recording.for_sensor(2)
    for k in range(min(len(reference.time_s), len(probe.time_s))):
        reference_to_tracker = make_transform(reference.rotation[k], reference.position_mm[k])
        probe_to_tracker = make_transform(probe.rotation[k], probe.position_mm[k])
        yield (float(probe.time_s[k]), probe_to_image(reference_to_image, reference_to_tracker, probe_to_tracker),
               reference_to_tracker)


def test_slip_watch_confirms_lets_a_confirmed_slip_stand_rules_out_and_drops_what_fits_neither():
    """Four pinholes on a line (image = Reference), the error model's covariance 0.3^2 mm^2 per axis: a jump that
    turns the reference 1 degree about the first pinhole (errors 0, 1.75, 3.5, 5.2 mm along the line)."""
    from EMRegModule.core.slip import SlipWatch

    pinholes = np.array([[0.0, 0.0, 0.0], [100.0, 0.0, 0.0], [200.0, 0.0, 0.0], [300.0, 0.0, 0.0]])
    ids = ["I01", "I02", "I03", "I04"]
    covariance = 0.09 * np.eye(3)
    step = make_transform(axis_angle_to_rotation([0.0, 0.0, 1.0], np.radians(1.0)), np.zeros(3))
    predicted = apply_transform(step, pinholes) - pinholes
    watch = SlipWatch(np.eye(4), pinholes, ids, 1.5)
    assert watch.judge(np.zeros(3), covariance, 1) is None  # no jump yet: nothing to judge
    watch.add_jump(10.0, step)
    confirmed = watch.judge(predicted[1] + [0.1, -0.2, 0.1], covariance, 1)
    assert confirmed.verdict == "confirmed" and confirmed.fails and confirmed.largest_at == "I04"
    assert confirmed.largest_mm == pytest.approx(5.24, abs=0.01) and confirmed.since_s == 10.0
    stands = watch.judge(np.array([0.2, 0.1, 0.0]), covariance, 0)  # where the slip makes no error: cannot tell
    assert stands.verdict == "open" and stands.fails
    ruled_out = watch.judge(np.array([0.1, 0.2, -0.1]), covariance, 2)  # no error where the slip makes 3.5 mm
    assert ruled_out.verdict == "ruled_out" and not ruled_out.fails and watch.suspect is None
    assert watch.judge(np.zeros(3), covariance, 2) is None
    # an error a third of the way to the slip's, far from both: neither fits, the test is dropped, nothing fails
    watch.add_jump(20.0, step)
    neither = watch.judge(predicted[3] / 3.0, covariance, 3)
    assert neither.verdict == "neither" and not neither.fails and watch.suspect is None
    # a slip whose predicted error stays within the limit everywhere is confirmed but harmless
    small = SlipWatch(np.eye(4), pinholes[:2], ids[:2], 2.0)
    small.add_jump(5.0, step)
    harmless = small.judge(predicted[1], covariance, 1)
    assert harmless.verdict == "confirmed" and not harmless.fails


# --- emreg evaluate leaves the INVALID poses out of the TRE ------------------------------------------------------


def _evaluate(case: Path, registration: Path, out: Path) -> tuple[int, str]:
    err = io.StringIO()
    with contextlib.redirect_stderr(err):
        code = main(["evaluate", str(case), "--registration", str(registration), "--out", str(out), "--quiet"])
    return code, err.getvalue()


def test_evaluate_leaves_the_invalid_poses_out_of_the_tre_and_counts_them(sessions, small_case: Path, tmp_path: Path):
    """``emreg evaluate`` on the slip session (the small case's targets beside it): the poses navigation.csv marks
    INVALID (from the failed checkpoint after the slip on, and the tracker's bad samples) are left out of the TRE
    and counted; the target dwells after the slip, off by the slip, no longer raise it. The clean session loses
    only the bad samples and no dwell."""
    from EMRegModule.core.evaluation import evaluate_targets
    from EMRegModule.io.case import read_targets

    targets = read_targets(small_case / "targets.mrk.json")
    results = {}
    for name in ("clean", "slip"):
        case = sessions[name]["case"]
        (case / "targets.mrk.json").write_bytes((small_case / "targets.mrk.json").read_bytes())
        code, err = _evaluate(case, sessions["registration"], tmp_path / name)
        assert code == 0, err
        results[name] = (json.loads((tmp_path / name / "evaluation.json").read_text()), err)
    rows = _rows(sessions["slip"]["out"] / "navigation.csv")  # emreg navigate's, of the same recording
    tre, err = results["slip"][0]["tre"], results["slip"][1]
    assert tre["invalid_poses_left_out"] == [r[5] for r in rows].count("INVALID") > 500
    failed = next(c for c in sessions["slip"]["checkpoints"]["checkpoints"] if not c["ok"])
    assert all(d["end_s"] < failed["start_s"] for d in tre["dwells"])  # no dwell from the INVALID period
    assert tre["dwells_left_out"] >= 2 and "INVALID" in err and "left out" in err
    # the same recording without the pose status: the dwells after the slip count, and raise the TRE
    recording = read_recording(sessions["slip"]["case"] / "navigation.csv", Settings(), 1, 2)
    every = evaluate_targets(recording, targets[0], targets[1],
                             read_registration(sessions["registration"]).reference_to_image)
    assert every.invalid_poses_left_out is None and len(every.dwells) == tre["n"] + tre["dwells_left_out"]
    assert every.to_json()["rms_mm"] > tre["rms_mm"] + 0.3
    clean = results["clean"][0]["tre"]
    assert clean["dwells_left_out"] == 0 and "left out" not in results["clean"][1]
    assert clean["invalid_poses_left_out"] == [r[5] for r in _rows(sessions["clean"]["out"] / "navigation.csv")
                                               ].count("INVALID")
