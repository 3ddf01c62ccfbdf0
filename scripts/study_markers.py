#!/usr/bin/env python3
"""Study (beyond the paper): how FRE and TRE grow when fewer markers are calibrated.

For each number of markers N, random subsets of N markers are calibrated in simulated sessions
(the CT still shows all of them, so the pairing must also find the right N among the detected
ones); the real calibration, pairing and registration run on each. TRE is the true registration
error at the targets (RMS). A refusal (ambiguous pairing, l not determined...) is counted, not
hidden.

    .venv/bin/python scripts/study_markers.py [--counts 4 6 8 12 16 20 28] [--repetitions 10] [--quick]
"""

from __future__ import annotations

import argparse
from collections import Counter

import numpy as np
import study_common as sc


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sc.add_common_arguments(parser)
    parser.add_argument("--counts", type=int, nargs="+", default=None)
    parser.add_argument("--repetitions", type=int, default=None, help="sessions per count (default 10; 3 quick)")
    args = parser.parse_args(argv)
    repetitions = args.repetitions or (3 if args.quick else 10)
    frame = sc.prepare_frame(args)
    available = np.nonzero(frame.in_ct)[0]
    counts = args.counts or [n for n in (3, 4, 5, 6, 8, 12, 16, 20, 28) if n <= len(available)]
    rows = []
    reasons: Counter = Counter()
    for n in counts:
        rng = np.random.default_rng(100 + n)
        sessions = [sc.calibrate_and_register(frame, rng, subset=np.sort(rng.choice(available, n, replace=False)))
                    for _ in range(repetitions)]
        done = [s for s in sessions if s.registration is not None]
        for s in sessions:
            if s.refused:
                reasons[s.refused.split(";")[0].strip()[:100]] += 1
        fre = [s.registration.fre_mm for s in done]
        tre = [float(np.sqrt(np.mean(s.target_errors_mm ** 2))) for s in done]
        worst = [float(np.max(s.target_errors_mm)) for s in done]
        predicted = [float(np.sqrt(np.mean(np.square(s.registration.predicted_tre_mm)))) for s in done
                     if s.registration.predicted_tre_mm is not None]
        rows.append([str(n), f"{len(sessions) - len(done)}/{len(sessions)}", sc.mean_std(fre) if fre else "-",
                     sc.mean_std(tre) if tre else "-", f"{np.max(worst):.2f}" if worst else "-",
                     f"{np.mean(predicted):.2f}" if predicted else "-"])
    print(f"\nFRE and TRE against the number of calibrated markers ({repetitions} sessions per row; "
          f"{len(frame.detection.markers)} markers in the CT)\n")
    print(sc.table(["markers", "refused", "FRE (mm)", "registration TRE RMS (mm)", "worst target (mm)",
                    "predicted TRE RMS (mm)"], rows))
    if reasons:
        print("\nrefusals: " + "; ".join(f"{count} x {reason}" for reason, count in reasons.most_common()))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
