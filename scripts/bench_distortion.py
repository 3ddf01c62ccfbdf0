#!/usr/bin/env python3
"""Benchmark: the distortion check at registration, against the test alone, in the same run.

The check (:func:`.distortion.detect.estimate_distortion`) is the test (candidates, Monte Carlo null, the
one-bad-pair check), the field's fit when one is found, and the detectable size (300 random smooth fields, each
one's smallest detected size by bisection). The baseline is the test alone (``scan_residuals``: the candidates and
the null draws), what the check cost before the detectable size was added. Frames of 8, 16 and 28 pinholes with the
tracker's noise known from the dwells, clean and with a 1 mm induced-dipole field. Prints the median time of each
and their ratio. Usage: ``.venv/bin/python scripts/bench_distortion.py [--repeats 5]``.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "Testing" / "Python"))

from EMRegModule.core.distortion import NoisePrior, estimate_distortion  # noqa: E402
from EMRegModule.core.distortion.scan import scan_residuals  # noqa: E402
from EMRegModule.core.transforms import invert_rigid, make_transform, random_rotation  # noqa: E402
from EMRegModule.simulation.distortion import nonrigid_errors, place_object  # noqa: E402
from EMRegModule.simulation.field_families import place_field  # noqa: E402


def session(n: int, size_mm: float, seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Pinholes (n, 3) of a 200 mm frame, their axes, residuals (0.25 mm noise plus a rod's field of ``size_mm``
    RMS) and the transmitter's pose per point."""
    rng = np.random.default_rng(seed)
    points = rng.uniform(-100.0, 100.0, (n, 3)) * np.array([1.0, 1.0, 0.5])
    axes = rng.normal(size=(n, 3))
    axes /= np.linalg.norm(axes, axis=1)[:, None]
    reference_to_tracker = make_transform(random_rotation(rng, 180.0), [330.0, 20.0, 10.0])
    residuals = rng.normal(0.0, 0.25, points.shape)
    if size_mm:
        rod = place_object(rng, points, reference_to_tracker, np.eye(4), size_mm)
        residuals += nonrigid_errors(rod, points, reference_to_tracker, np.eye(4))[1]
    poses = np.broadcast_to(invert_rigid(reference_to_tracker), (n, 4, 4))
    return points, residuals, axes, poses


def timed(function, arguments: tuple, repeats: int, **keywords) -> float:
    """Median seconds of ``function(*arguments, **keywords)`` over ``repeats`` calls."""
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        function(*arguments, **keywords)
        times.append(time.perf_counter() - start)
    return statistics.median(times)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=5)
    args = parser.parse_args()
    prior = NoisePrior(0.25, "known")
    print(f"{'pinholes':>8} {'field':>6} {'check ms':>9} {'test alone ms':>14} {'ratio':>6} {'detected':>9} "
          f"{'detectable mm':>14}")
    for n in (8, 16, 28):
        for size in (0.0, 1.0):
            points, residuals, axes, poses = session(n, size, 11 + n)
            full = timed(estimate_distortion, (points, residuals, axes, 0.002), args.repeats,
                         tracker_to_reference=poses, noise=prior, max_fre_mm=2.0)
            alone = timed(scan_residuals, (points, axes, poses, residuals, prior), args.repeats)
            estimate = estimate_distortion(points, residuals, axes, 0.002, tracker_to_reference=poses, noise=prior,
                                           max_fre_mm=2.0)
            print(f"{n:>8} {size:>6.1f} {full * 1e3:>9.0f} {alone * 1e3:>14.0f} {full / alone:>6.2f} "
                  f"{str(estimate.detected):>9} {estimate.detectable_rms_mm:>14.2f}")

    map_term(args.repeats)


def map_term(repeats: int) -> None:
    """The distortion term of ``tre_map.nrrd`` (64^3 points) for a field fitted by a Gaussian process's modes: the
    whole term (``mean_square_at``) and, within it, the process's posterior variance added in issue 37's third round
    (``_unseen_ms``); the ratio is the whole against the whole without that part, in the same run."""
    for seed in range(40):
        rng = np.random.default_rng([41, seed])
        points, _, axes, poses = session(28, 0.0, 100 + seed)
        reference_to_tracker = invert_rigid(poses[0])
        field = place_field("gp", rng, points, reference_to_tracker, np.eye(4), 1.0)
        residuals = rng.normal(0.0, 0.25, points.shape) + nonrigid_errors(field, points, reference_to_tracker,
                                                                            np.eye(4))[1]
        estimate = estimate_distortion(points, residuals, axes, 0.002)
        if estimate.detected and estimate.to_json()["field"]["model"]["kind"] == "modes":
            break
    else:
        print("no Gaussian-process modes fit among the fields tried")
        return
    axis = np.linspace(-150.0, 150.0, 64)
    grid = np.stack(np.meshgrid(axis, axis, axis, indexing="ij"), -1).reshape(-1, 3)
    whole = timed(estimate.mean_square_at, (grid,), repeats)
    unseen = timed(estimate._unseen_ms, (grid,), repeats)
    print(f"tre_map distortion term, 64^3 points, Gaussian-process modes fit: {whole * 1e3:.0f} ms, of which the "
          f"posterior variance {unseen * 1e3:.0f} ms; ratio to the term without it {whole / (whole - unseen):.2f}")


if __name__ == "__main__":
    main()
