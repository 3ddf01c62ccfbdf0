#!/usr/bin/env python3
"""Benchmark the tracking-recording hot paths against plain baselines measured in the same run.

- reading a tracking CSV (``read_tracking_csv``) vs ``numpy.loadtxt`` of the numeric columns alone;
- expressing every probe sample in the Reference frame (``probe_in_reference``, paper Eq. 3-5)
  vs a per-sample Python loop with ``numpy.linalg.inv``.

Usage: ``.venv/bin/python scripts/bench_io.py [--rows 400000]``
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np

from EMRegModule.core.tracking import TrackingRecording, probe_in_reference
from EMRegModule.core.transforms import angles_to_rotation
from EMRegModule.io.tracking_csv import read_tracking_csv, write_tracking_csv


def _timed(func, repeat: int = 3) -> tuple[float, object]:
    best, result = float("inf"), None
    for _ in range(repeat):
        start = time.perf_counter()
        result = func()
        best = min(best, time.perf_counter() - start)
    return best, result


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rows", type=int, default=400_000, help="sensor rows (two sensors per moment)")
    args = parser.parse_args()
    rng = np.random.default_rng(0)
    n = args.rows - args.rows % 2
    angles = rng.uniform([-180, -90, -180], [180, 90, 180], size=(n, 3))
    recording = TrackingRecording(
        time_s=np.repeat(np.arange(n // 2) / 80.0, 2), sensor=np.tile([1, 2], n // 2),
        position_mm=rng.uniform(-300, 300, size=(n, 3)), rotation=angles_to_rotation(*angles.T),
        quality=np.zeros(n), label=np.where(rng.random(n) < 0.5, "M01", ""),
    )
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "rec.csv"
        write_tracking_csv(recording, path)
        size_mb = path.stat().st_size / 1e6
        t_ours, loaded = _timed(lambda: read_tracking_csv(path))
        t_base, _ = _timed(lambda: np.loadtxt(path, delimiter=",", skiprows=1, usecols=range(9)))
    print(f"tracking CSV, {n} rows, {size_mb:.1f} MB")
    print(f"  read_tracking_csv      {t_ours:7.3f} s  ({n / t_ours / 1e3:7.0f} k rows/s)")
    print(f"  numpy.loadtxt baseline {t_base:7.3f} s  ({n / t_base / 1e3:7.0f} k rows/s)")
    print(f"  ratio ours/baseline    {t_ours / t_base:7.2f}")

    t_vec, result = _timed(lambda: probe_in_reference(loaded, 1, 2))
    reference = loaded.for_sensor(1).transforms()
    probe = loaded.for_sensor(2).transforms()
    m = min(len(reference), 20000)

    def loop() -> list:
        return [np.linalg.inv(reference[i]) @ probe[i] for i in range(m)]

    t_loop, looped = _timed(loop, repeat=1)
    np.testing.assert_allclose(result.probe_to_reference[:m], np.asarray(looped), atol=1e-9)
    per_vec = t_vec / len(result)
    per_loop = t_loop / m
    print(f"probe_in_reference, {len(result)} probe samples")
    print(f"  vectorised             {per_vec * 1e6:7.3f} us/sample ({1 / per_vec / 1e3:7.0f} k samples/s)")
    print(f"  per-sample loop        {per_loop * 1e6:7.3f} us/sample ({1 / per_loop / 1e3:7.0f} k samples/s)")
    print(f"  speed-up               {per_loop / per_vec:7.1f}x")


if __name__ == "__main__":
    main()
