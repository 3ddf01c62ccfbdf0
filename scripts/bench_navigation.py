#!/usr/bin/env python3
"""Benchmark: offline navigation throughput (paper Eq. 12) against a per-sample Python loop.

A recording of ``--samples`` probe samples (plus as many reference samples, 80 Hz, the frame
moving) is mapped into image space by :func:`EMRegModule.core.navigation.navigate_recording`
(vectorised); the baseline maps each sample with the single-pose function in a Python loop
(building each sample's two 4x4 poses, the way a naive replay would), on a slice, both
in the same run. Prints samples per second
of both and their ratio, plus the time to write ``navigation.csv``.
Usage: ``.venv/bin/python scripts/bench_navigation.py [--samples 500000]``.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np

from EMRegModule.core.navigation import navigate_recording, probe_to_image
from EMRegModule.core.tracking import TrackingRecording
from EMRegModule.core.transforms import make_transform, quaternion_to_rotation, random_rotation
from EMRegModule.io.navigation_csv import write_navigation_csv


def synthetic_recording(n: int, seed: int = 0) -> TrackingRecording:
    """Interleaved reference (port 1) and probe (port 2) rows, random smooth-ish poses."""
    rng = np.random.default_rng(seed)
    time_s = np.repeat(np.arange(n) / 80.0, 2)
    sensor = np.tile([1, 2], n)
    position = rng.normal(0, 100, (2 * n, 3)) + [0, 0, 300]
    rotation = quaternion_to_rotation(rng.normal(size=(2 * n, 4)))
    quality = rng.uniform(0, 1, 2 * n)
    label = np.full(2 * n, "", dtype=object)
    return TrackingRecording(time_s, sensor, position, rotation, quality, label, source="bench")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--samples", type=int, default=500_000, help="probe samples in the recording")
    parser.add_argument("--baseline-samples", type=int, default=20_000)
    args = parser.parse_args()
    recording = synthetic_recording(args.samples)
    reference_to_image = make_transform(random_rotation(np.random.default_rng(1)), [10.0, -20.0, 30.0])

    navigate_recording(recording.select(slice(0, 2000)), reference_to_image)  # warm-up
    start = time.perf_counter()
    result = navigate_recording(recording, reference_to_image, 1, 2)
    vectorised_s = time.perf_counter() - start
    rate = len(result) / vectorised_s

    reference = recording.for_sensor(1)
    probe = recording.for_sensor(2)
    m = min(args.baseline_samples, len(probe))
    start = time.perf_counter()
    loop = [probe_to_image(reference_to_image, make_transform(reference.rotation[k], reference.position_mm[k]),
                           make_transform(probe.rotation[k], probe.position_mm[k])) for k in range(m)]
    loop_s = time.perf_counter() - start
    loop_rate = m / loop_s
    assert np.allclose(np.asarray(loop), result.probe_to_image[:m], atol=1e-9)

    with tempfile.TemporaryDirectory() as tmp:
        start = time.perf_counter()
        write_navigation_csv(result, Path(tmp) / "navigation.csv")
        csv_s = time.perf_counter() - start

    print(f"navigate_recording: {len(result)} probe samples in {vectorised_s:.3f} s = {rate:,.0f} samples/s "
          "(reading the pairs of moments, Eq. 3-5 and Eq. 12 included)")
    print(f"per-sample loop baseline: {m} samples in {loop_s:.3f} s = {loop_rate:,.0f} samples/s")
    print(f"speed-up vectorised / loop: {rate / loop_rate:.1f}x")
    print(f"write navigation.csv: {len(result)} rows in {csv_s:.2f} s = {len(result) / csv_s:,.0f} rows/s")


if __name__ == "__main__":
    main()
