"""Driving a real robot protocol (issue 39, section 3): the unmodified client franky-control (``franka://``) against
franky-sim, a MuJoCo server speaking libfranka's protocol, in its own process; the trakSTAR simulator (a real pty)
sees the flange sensor through a hidden SensorToFlange (X) and TrackerToBase (Y).

- every move keeps its velocity limit; each safety stop fires (flange sensor INVALID, stale tracker, reference
  jump, sensor out of the tracker's volume) and the robot stops short of its target.

Skipped where the optional extra ``robot`` (franky-control, franky-sim) is not installed.
"""

from __future__ import annotations

import os
import threading
import time
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("franky")
pytest.importorskip("franky_sim")

from robot_sim import FlangeScene, RobotSim  # noqa: E402

from EMRegModule.errors import EMRegError, NoSafeAnswerError  # noqa: E402
from EMRegModule.live.robot.driver import MotionLimits  # noqa: E402
from EMRegModule.live.robot.guard import TrackerWatch, guarded_move, wait_for_tracker  # noqa: E402
from EMRegModule.live.robot.url import open_robot, parse_robot_url  # noqa: E402
from EMRegModule.live.simulator.trakstar import TrackerSimulator  # noqa: E402
from EMRegModule.live.sources import open_source  # noqa: E402
from EMRegModule.transforms import axis_angle_to_rotation  # noqa: E402

FLANGE_PORT = 3
#: Fast but limited moves and short dwells, so that the module runs in well under a minute.
SETTINGS = """
[robot]
flange_sensor = 3
max_velocity_mm_s = 150.0
max_acceleration_mm_s2 = 600.0
max_rotation_deg_s = 60.0
max_rotation_acceleration_deg_s2 = 240.0
calibration_poses = 9
calibration_angle_deg = 20.0
calibration_translation_mm = 15.0
dwell_s = 0.5
measure_s = 0.3
approach_mm = 20.0
tolerance_mm = 0.4
tolerance_deg = 0.3
stale_s = 0.5
"""


def _pose(rotvec, translation) -> np.ndarray:
    pose = np.eye(4)
    angle = float(np.linalg.norm(rotvec))
    pose[:3, :3] = axis_angle_to_rotation(np.asarray(rotvec) / angle, angle) if angle else np.eye(3)
    pose[:3, 3] = translation
    return pose


class World:
    """The robot simulator, the trakSTAR simulator over the scene, and the hidden truth."""

    def __init__(self, folder: Path) -> None:
        host = f"127.0.{os.getpid() % 250 + 1}.{np.random.default_rng().integers(2, 250)}"
        self.robot = RobotSim(folder, host)
        try:
            start = self.robot.flange_to_base()
            self.x = _pose([0.3, -0.2, 0.5], [25.0, -15.0, 60.0])  # SensorToFlange, hidden
            rotation_y = _pose([0.1, 0.4, -1.2], [0, 0, 0])[:3, :3]
            sensor_base = (start @ self.x)[:3, 3]
            self.y = np.eye(4)  # TrackerToBase, hidden: the flange sensor starts at (320, 60, 150) in the tracker
            self.y[:3, :3] = rotation_y
            self.y[:3, 3] = sensor_base - rotation_y @ np.array([320.0, 60.0, 150.0])
            self.reference = _pose([0.2, -0.1, 0.3], [300.0, -120.0, 100.0])
            self.guide = _pose([0.05, 0.1, 0.0], [0.0, 10.0, 35.0])  # NeedleGuideToSensor
            self.scene = FlangeScene(self.robot, self.x, self.y, self.reference, FLANGE_PORT)
            self.tracker = TrackerSimulator(scene=self.scene, seed=4)
            self.tracker.start()
        except BaseException:
            self.robot.close()
            raise
        self.start = start
        self.settings = folder / "robot.toml"
        self.settings.write_text(SETTINGS, encoding="utf-8")

    @property
    def tracker_url(self) -> str:
        return f"trakstar://{self.tracker.path}?rate=80"

    def close(self) -> None:
        self.tracker.stop()
        self.robot.close()


@pytest.fixture(scope="module")
def world(tmp_path_factory):
    w = World(tmp_path_factory.mktemp("robot"))
    yield w
    w.close()


@pytest.fixture
def watched(world):
    """The driver, the tracker's source and a watch on flange and reference; the robot is back at the start after."""
    robot = open_robot(world.robot.url)
    source = open_source(world.tracker_url, probe_sensor=FLANGE_PORT)
    watch = TrackerWatch(FLANGE_PORT, 1, 660.0, 0.5)
    source.start(watch.on_sample)
    wait_for_tracker(watch)
    yield robot, watch
    for kind in ("unplug", "out-of-range"):
        world.tracker.set_state(kind, FLANGE_PORT, False)
    world.scene.reference_to_tracker = world.reference
    time.sleep(0.3)
    watch.max_tracker_distance_mm = 660.0
    wait_for_tracker(watch)
    guarded_move(robot, world.start, MotionLimits(150.0, 600.0, 60.0, 240.0), watch)
    source.stop()
    robot.close()


def test_robot_url() -> None:
    assert parse_robot_url("franka://172.16.0.2").host == "172.16.0.2"
    for bad in ("franka:172.16.0.2", "ur://10.0.0.1", "franka://10.0.0.1:1337", "franka://"):
        with pytest.raises(EMRegError):
            parse_robot_url(bad)


SLOW = MotionLimits(50.0, 250.0, 20.0, 90.0)


def _during_move(robot, watch, world, fault, direction, limits=SLOW):
    """Start a 60 mm move along ``direction`` (base frame), apply ``fault`` 0.3 s in; the stop's message, and how
    far from the target the flange truly stands still."""
    target = world.start.copy()
    target[:3, 3] += 60.0 * np.asarray(direction) / np.linalg.norm(direction)
    timer = threading.Timer(0.3, fault)
    timer.start()
    try:
        with pytest.raises(NoSafeAnswerError) as stopped:
            guarded_move(robot, target, limits, watch)
    finally:
        timer.cancel()
    time.sleep(0.4)
    here = world.robot.flange_to_base()[:3, 3]
    time.sleep(0.2)
    assert np.linalg.norm(world.robot.flange_to_base()[:3, 3] - here) < 0.5  # at rest
    return str(stopped.value), float(np.linalg.norm(here - target[:3, 3]))


@pytest.mark.parametrize("fault, words", [
    ("invalid", "flange sensor (port 3) is INVALID"),
    ("stale", "is stale"),
    ("jump", "reference sensor"),
    ("out_of_range", "left the tracker's volume"),
    ("volume", "left the tracker's volume"),
])
def test_safety_stops(world, watched, fault, words) -> None:
    robot, watch = watched
    actions = {
        "invalid": lambda: world.tracker.set_state("unplug", FLANGE_PORT, True),
        "stale": lambda: world.tracker.stall(1.0),
        "jump": lambda: setattr(world.scene, "reference_to_tracker",
                                _pose([0, 0, 0], [3.0, 0.0, 0.0]) @ world.reference),
        "out_of_range": lambda: world.tracker.set_state("out-of-range", FLANGE_PORT, True),
        "volume": lambda: None,
    }
    direction = [0.0, 1.0, 0.0]
    if fault == "volume":  # the volume's edge 10 mm farther than the sensor now, the move away from the generator
        sensor = world.scene.sensor_to_tracker()[:3, 3]
        watch.max_tracker_distance_mm = float(np.linalg.norm(sensor)) + 10.0
        direction = world.y[:3, :3] @ sensor
    message, short_mm = _during_move(robot, watch, world, actions[fault], direction)
    print(f"\n{fault}: {message} ({short_mm:.1f} mm short of the target)")
    assert words in message and message.startswith("robot: stopped:")
    assert short_mm > 10.0


def test_velocity_limit(world, watched) -> None:
    """A move keeps its velocity limit (the flange's true speed over 50 ms steps of the simulator's own clock)."""
    robot, watch = watched
    target = world.start.copy()
    target[:3, 3] += np.array([30.0, 0.0, -20.0])
    speeds = []
    done = threading.Event()

    def sample() -> None:
        last = world.robot.stamped_flange_to_base()
        while not done.wait(0.05):
            now = world.robot.stamped_flange_to_base()
            if now[0] > last[0]:
                speeds.append(np.linalg.norm(now[1][:3, 3] - last[1][:3, 3]) / (now[0] - last[0]))
            last = now

    thread = threading.Thread(target=sample)
    thread.start()
    try:
        guarded_move(robot, target, MotionLimits(40.0, 200.0, 20.0, 90.0), watch)
    finally:
        done.set()
        thread.join()
    print(f"\nlargest speed {max(speeds):.1f} mm/s (limit 40)")
    assert 30.0 < max(speeds) < 40.0 * 1.1
