#!/usr/bin/env python3
"""Benchmark: automatic pairing time and correctness against a plain baseline, in the same run.

Cases (synthetic frames, markers on the top and side faces, image and calibration sets each
missing some true markers and holding extra random points, shuffled):
  - 28 markers, 3 missing + 3 extra per side   (target: < 50 ms)
  - 100 markers, 5 missing + 5 extra per side  (target: < 1 s)

Baseline: the Hungarian algorithm (scipy ``linear_sum_assignment``) on distance signatures
(per point, a histogram of its distances to all other points, image pinholes taken at the
middle of the pinhole), a common plain approach. It is fast but knows nothing of missing or
extra points nor of geometric consistency; its time and pairing correctness are printed
beside EMReg's. Usage: ``.venv/bin/python scripts/bench_pairing.py [--repeats 20]``.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import numpy as np
from scipy.optimize import linear_sum_assignment

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "Testing" / "Python"))

from synth_registration import pairing_problem  # noqa: E402

from EMRegModule.core.pairing import pair_markers  # noqa: E402

L_RANGE = (11.0, 18.5)


def hungarian_on_signatures(origins, axes, points, bin_mm: float = 4.0) -> list[tuple[int, int]]:
    """The baseline: pairs (image, calibration) by minimum-cost assignment of distance histograms."""
    pinholes = origins + 0.5 * (L_RANGE[0] + L_RANGE[1]) * axes
    top = max(np.ptp(pinholes, axis=0).max(), np.ptp(points, axis=0).max()) * 2.0

    def signatures(p):
        d = np.linalg.norm(p[:, None] - p[None], axis=2)
        bins = np.arange(0.0, top + bin_mm, bin_mm)
        return np.stack([np.histogram(row[row > 0], bins)[0] for row in d]).astype(float)

    image_sig = signatures(pinholes)
    cal_sig = signatures(points)
    cost = np.abs(image_sig[:, None] - cal_sig[None]).sum(axis=2)
    rows, cols = linear_sum_assignment(cost)
    return list(zip(rows.tolist(), cols.tolist(), strict=True))


def run_case(name: str, n: int, missing: int, extra: int, repeats: int, limit_s: float) -> None:
    ours, base = [], []
    ours_correct = base_correct = base_wrong = 0
    ours_complete = 0
    for seed in range(repeats):
        problem = pairing_problem(seed, n_markers=n, missing_image=missing, extra_image=extra,
                                  missing_calibration=missing, extra_calibration=extra)
        args = (problem.origins_image, problem.axes_image, problem.points_reference)
        start = time.perf_counter()
        result = pair_markers(*args, problem.directions_reference, L_RANGE)
        ours.append(time.perf_counter() - start)
        ours_correct += problem.correct(result.pairs)
        ours_complete += problem.correct(result.pairs) and result.support == problem.expected_pairs
        start = time.perf_counter()
        pairs = hungarian_on_signatures(*args)
        base.append(time.perf_counter() - start)
        good = sum(1 for j, i in pairs if problem.image_truth[j] >= 0
                   and problem.image_truth[j] == problem.calibration_truth[i])
        base_correct += good / max(1, problem.expected_pairs)
        base_wrong += len(pairs) - good
    median_ours, median_base = statistics.median(ours), statistics.median(base)
    print(f"{name}: {repeats} cases")
    print(f"  EMReg pairing      median {1000 * median_ours:8.1f} ms  max {1000 * max(ours):8.1f} ms  "
          f"correct {ours_correct}/{repeats}, complete {ours_complete}/{repeats}  "
          f"(target < {1000 * limit_s:.0f} ms: {'met' if median_ours < limit_s else 'MISSED'})")
    print(f"  baseline Hungarian median {1000 * median_base:8.1f} ms  max {1000 * max(base):8.1f} ms  "
          f"found {100 * base_correct / repeats:5.1f}% of the true pairs, "
          f"{base_wrong / repeats:.1f} wrong pairs per case (extras forced into pairs)")
    print(f"  time ratio EMReg / baseline: {median_ours / median_base:.2f}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=20)
    args = parser.parse_args()
    warm = pairing_problem(99)
    pair_markers(warm.origins_image, warm.axes_image, warm.points_reference, warm.directions_reference, L_RANGE)
    run_case("28 markers, 3 missing + 3 extra per side", 28, 3, 3, args.repeats, 0.050)
    run_case("100 markers, 5 missing + 5 extra per side", 100, 5, 5, max(3, args.repeats // 4), 1.0)


if __name__ == "__main__":
    main()
