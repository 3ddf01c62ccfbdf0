"""The robot of the robot tests: franky-sim (a MuJoCo simulation server that speaks libfranka's network protocol)
in its own process, driven by the unmodified client franky-control through ``franka://HOST``; and the EM world
around it: a trakSTAR simulator (a real pty) whose flange sensor is where the simulated flange truly is, seen
through a hidden ``SensorToFlange`` (X) and ``TrackerToBase`` (Y).

The server process (``python robot_sim.py --hostname H --truth FILE``) runs franky-sim's own server unchanged and
writes, after every physics step, the flange's true pose (the TCP frame's forward kinematics of the simulated
joints, 4x4, m) to a small memory-mapped file, with a sequence number around it (odd while writing). The EM
scene reads it whenever the trakSTAR simulator measures.
"""

from __future__ import annotations

import argparse
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

#: The truth file: [sequence, time s, 16 numbers of FlangeToBase (m), row-major].
TRUTH_FLOATS = 18


def _serve(hostname: str, truth_path: str) -> None:
    from franky_sim import SimulationServer
    from franky_sim.mujoco_simulator import MujocoSimulator

    truth = np.memmap(truth_path, dtype=np.float64, mode="r+", shape=(TRUTH_FLOATS,))
    count = [0]

    def publish(sim) -> None:
        count[0] += 1
        if count[0] % 2:  # every 2 ms is plenty for a tracker at 80 Hz
            return
        robot = sim.robots[0]
        pose = robot.kinematics(np.asarray(robot.inner_state.q, dtype=float)).homogeneous
        truth[0] += 1.0
        truth[1] = time.monotonic()
        truth[2:] = np.asarray(pose, dtype=float).reshape(-1)
        truth[0] += 1.0

    stop = []
    signal.signal(signal.SIGTERM, lambda *_: stop.append(1))
    with MujocoSimulator(enable_visualization=False) as sim:
        sim.add_robot()
        sim.register_post_step_callback(publish)
        with SimulationServer(sim, hostname_candidates=[hostname]) as server:
            server.running = True
            print(f"ready {hostname}", flush=True)
            while not stop:
                server.run_once(True)


class FlangeScene:
    """The EM world of the robot tests, for the trakSTAR simulator: port 1 the patient's reference sensor (where
    :attr:`reference_to_tracker` puts it; a test may move it), ``flange_port`` the sensor on the flange at
    ``inv(TrackerToBase) @ FlangeToBase_true @ SensorToFlange`` (the hidden X and Y), each with Gaussian noise
    (``noise_mm`` per axis, ``noise_deg`` per angle)."""

    period_s = None

    def __init__(self, robot: RobotSim, sensor_to_flange: np.ndarray, tracker_to_base: np.ndarray,
                 reference_to_tracker: np.ndarray, flange_port: int = 3, noise_mm: float = 0.05,
                 noise_deg: float = 0.03, seed: int = 0) -> None:
        self.robot = robot
        self.sensor_to_flange = sensor_to_flange
        self.tracker_to_base = tracker_to_base
        self.reference_to_tracker = reference_to_tracker
        self.flange_port = flange_port
        self.sensors = (1, flange_port)
        self.noise_mm, self.noise_deg = noise_mm, noise_deg
        self.rng = np.random.default_rng(seed)

    def sensor_to_tracker(self) -> np.ndarray:
        """The flange sensor's true pose now (4x4, mm)."""
        return np.linalg.inv(self.tracker_to_base) @ self.robot.flange_to_base() @ self.sensor_to_flange

    def pose(self, sensor: int, t_s: float):
        from EMRegModule.core.transforms import rotation_to_angles
        from EMRegModule.devices.trakstar.protocol import Pose

        truth = self.reference_to_tracker if sensor == 1 else self.sensor_to_tracker()
        angles = rotation_to_angles(truth[:3, :3][None])[0] + self.rng.normal(0.0, self.noise_deg, 3)
        return Pose(truth[:3, 3] + self.rng.normal(0.0, self.noise_mm, 3), angles)


class RobotSim:
    """franky-sim in a child process at ``hostname`` (a loopback address), with its truth file in ``folder``."""

    def __init__(self, folder: Path, hostname: str = "127.0.0.1") -> None:
        self.hostname = hostname
        self.truth_path = Path(folder) / "flange_truth.bin"
        np.memmap(self.truth_path, dtype=np.float64, mode="w+", shape=(TRUTH_FLOATS,)).flush()
        self.truth = np.memmap(self.truth_path, dtype=np.float64, mode="r", shape=(TRUTH_FLOATS,))
        env = dict(os.environ, PYTHONUNBUFFERED="1")
        self.process = subprocess.Popen([sys.executable, __file__, "--hostname", hostname, "--truth",
                                         str(self.truth_path)], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                                        text=True, env=env)
        line = self.process.stdout.readline()
        if not line.startswith("ready"):
            self.close()
            raise RuntimeError(f"franky-sim did not start: {line!r} {self.process.stderr.read()[-2000:]}")
        end = time.monotonic() + 5.0
        while self.truth[0] < 2 and time.monotonic() < end:
            time.sleep(0.01)

    @property
    def url(self) -> str:
        return f"franka://{self.hostname}"

    def flange_to_base(self) -> np.ndarray:
        """The flange's true pose now (4x4, mm)."""
        return self.stamped_flange_to_base()[1]

    def stamped_flange_to_base(self) -> tuple[float, np.ndarray]:
        """The simulator's time (s, its monotonic clock) of the latest step and the flange's true pose then."""
        while True:
            before = float(self.truth[0])
            values = np.array(self.truth[1:], dtype=float)
            if before % 2 == 0 and float(self.truth[0]) == before:
                break
        pose = values[1:].reshape(4, 4)
        pose[:3, 3] *= 1000.0
        return float(values[0]), pose

    def close(self) -> None:
        if self.process.poll() is None:
            self.process.send_signal(signal.SIGTERM)
            try:
                self.process.wait(timeout=5.0)
            except subprocess.TimeoutExpired:
                self.process.kill()
                self.process.wait()
        for stream in (self.process.stdout, self.process.stderr):
            if stream:
                stream.close()


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--hostname", default="127.0.0.1")
    parser.add_argument("--truth", required=True)
    args = parser.parse_args()
    _serve(args.hostname, args.truth)
