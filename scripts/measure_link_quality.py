"""Evidence for the live link guard's limits: rejected fractions and pose errors per fault level.

Runs the trakSTAR simulator on a real pseudo-terminal, reads it with the real driver, passes every
sample through a :class:`~EMRegModule.devices.link_quality.LinkGuard` and compares each sample with the
pose the simulator really sent (its truth log). For each fault level it prints:

- records read, rejected by framing / value checks, rejected by the jump test;
- the failed fraction over the monitor's sliding window: mean and maximum after the warm-up;
- samples that were accepted and are wrong (> 1 mm from the truth): with the jump test alone, and
  those that would have been *published* (the monitor's state OK at that moment);
- on clean data, the fastest motion the jump test saw (mm/s), i.e. the margin to its limit.

Usage: ``python scripts/measure_link_quality.py [--seconds 8] [--levels 0,0.01,0.05] [--replay FILE.csv]``.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from EMRegModule.devices.device_url import parse_device_url
from EMRegModule.devices.link_quality import LinkGuard, LinkQualityMonitor
from EMRegModule.devices.simulator.faults import FaultPlan
from EMRegModule.devices.simulator.trakstar import TrackerSimulator
from EMRegModule.devices.trakstar.source import TrakstarSource

WRONG_MM = 1.0


def measure(level: float, seconds: float, seed: int, kind: str, replay: str | None = None) -> dict:
    faults = FaultPlan(**{kind: level}) if level > 0 else FaultPlan()
    samples = []
    states = []
    scene = None
    if replay:
        from EMRegModule.devices.simulator.scene import ReplayScene
        from EMRegModule.io.tracking_csv import read_tracking_csv

        scene = ReplayScene(read_tracking_csv(replay))
    with TrackerSimulator(scene, faults=faults, seed=seed, keep_truth=True, attached=(1, 2)) as sim:
        source = TrakstarSource(parse_device_url(f"trakstar://{sim.path}?rate=80"))
        guard = LinkGuard(source.link_counts, LinkQualityMonitor(), period_s=source.period_s)
        fractions = []

        def on_sample(sample) -> None:
            admitted = guard.admit(sample)
            state = guard.monitor.state()
            if state.judged >= guard.monitor.min_records:
                fractions.append(state.fraction)
            samples.append((sample, admitted))
            states.append(state.ok)

        source.start(on_sample)
        time.sleep(seconds)
        source.stop()
        truth = list(sim.truth)
        stats = source.driver.stats
    by_sensor: dict[int, tuple[np.ndarray, np.ndarray]] = {}
    for sensor in (1, 2, 3, 4):
        rows = [t for t in truth if t.sensor == sensor and t.emit_ns and t.pose is not None]
        if rows:
            by_sensor[sensor] = (np.array([t.emit_ns for t in rows]), np.array([t.pose.position_mm for t in rows]))
    wrong_accepted = wrong_published = 0
    max_error_published = 0.0
    for (sample, admitted), ok in zip(samples, states, strict=True):
        if not sample.valid or sample.sensor not in by_sensor:
            continue
        emit, position = by_sensor[sample.sensor]
        k = int(np.searchsorted(emit, sample.received_ns, side="right")) - 1
        near = position[max(0, k - 8):k + 2] if k >= 0 else position[:1]  # reads lag behind under load
        error = float(np.min(np.linalg.norm(near - sample.position_mm, axis=1)))
        if admitted and error > WRONG_MM:
            wrong_accepted += 1
            if ok:
                wrong_published += 1
        if admitted and ok:
            max_error_published = max(max_error_published, error)
    return {
        "level": level, "kind": kind, "records": stats.records + stats.rejected, "framing_rejected": stats.rejected,
        "jump_rejected": guard.jump.rejected,
        "mean_fraction": float(np.mean(fractions)) if fractions else float("nan"),
        "max_fraction": float(np.max(fractions)) if fractions else float("nan"),
        "alarms": guard.monitor.alarms, "wrong_accepted": wrong_accepted, "wrong_published": wrong_published,
        "published": int(sum(1 for (s, a), ok in zip(samples, states, strict=True) if a and ok and s.valid)),
        "max_error_published_mm": max_error_published, "max_speed_mm_s": guard.jump.max_speed_seen_mm_s,
        "max_deviation_mm": guard.jump.max_deviation_seen_mm,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=8.0)
    parser.add_argument("--levels", default="0,0.002,0.01,0.05")
    parser.add_argument("--kinds", default="corrupt,drop")
    parser.add_argument("--seed", type=int, default=5)
    parser.add_argument("--replay", metavar="FILE.csv", help="replay this recording (hand motion) instead of "
                        "the built-in scene")
    args = parser.parse_args()
    print("kind     level  records  framing  jump  mean_frac  max_frac  alarms  published  wrong_acc  wrong_pub  "
          "max_err_pub_mm  max_speed_mm_s  max_dev_mm")
    for kind in args.kinds.split(","):
        for level in (float(v) for v in args.levels.split(",")):
            if level == 0 and kind != args.kinds.split(",")[0]:
                continue
            r = measure(level, args.seconds, args.seed, kind, args.replay)
            print(f"{kind:8s} {level:5.3f}  {r['records']:7d}  {r['framing_rejected']:7d}  {r['jump_rejected']:4d}  "
                  f"{r['mean_fraction']:9.3f}  {r['max_fraction']:8.3f}  {r['alarms']:6d}  {r['published']:9d}  "
                  f"{r['wrong_accepted']:9d}  {r['wrong_published']:9d}  {r['max_error_published_mm']:14.3f}  "
                  f"{r['max_speed_mm_s']:14.0f}  {r['max_deviation_mm']:10.2f}", flush=True)


if __name__ == "__main__":
    main()
