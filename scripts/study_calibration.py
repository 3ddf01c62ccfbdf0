#!/usr/bin/env python3
"""Study: the frame calibration repeated at different frame positions (paper Fig. 8, mean FRE 1.38 mm).

The paper calibrated the fiducial frame 30 times, the frame placed differently in the
transmitter's field each time, solved l and ReferenceToImage each time and reported the FRE of
every calibration (mean 1.38 mm). Here: one simulated case (CT detected once), 30 simulated
calibration sessions with the reference sensor placed anew in the field, each run through the
real calibration, pairing and FRE(l) registration. Besides the FRE: the solved l against the
true one and the true registration error at the six targets (known only in simulation).

    .venv/bin/python scripts/study_calibration.py [--repetitions 30] [--quick] [--work DIR]
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import study_common as sc


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sc.add_common_arguments(parser)
    parser.add_argument("--repetitions", type=int, default=None, help="calibrations (default 30; 5 with --quick)")
    args = parser.parse_args(argv)
    repetitions = args.repetitions or (5 if args.quick else sc.PAPER["calibration_repetitions"])
    frame = sc.prepare_frame(args)
    rng = np.random.default_rng(2020)
    start = time.perf_counter()
    sessions = [sc.calibrate_and_register(frame, rng, sc.noise_model(args.noise_scale)) for _ in range(repetitions)]
    done = [s for s in sessions if s.registration is not None]
    fre = np.array([s.registration.fre_mm for s in done])
    l_err = np.array([s.l_error_mm for s in done])
    tre = np.array([np.sqrt(np.mean(s.target_errors_mm ** 2)) for s in done])
    print(f"\nFrame calibration repeated {repetitions} times at different frame positions "
          f"({len(frame.labels)} markers, tracker noise x{args.noise_scale:g}, {time.perf_counter() - start:.1f} s)\n")
    print(sc.table(["figure", "EMReg (simulated)", "paper (Fig. 8)"], [
        ["calibrations", f"{len(done)} ({len(sessions) - len(done)} refused)", "30"],
        ["FRE mean (mm)", f"{fre.mean():.2f}", f"{sc.PAPER['calibration_fre_mean_mm']:.2f}"],
        ["FRE std (mm)", f"{fre.std(ddof=1):.2f}" if len(fre) > 1 else "-", "n/a"],
        ["FRE min / median / max (mm)", f"{fre.min():.2f} / {np.median(fre):.2f} / {fre.max():.2f}", "n/a"],
        ["l error mean +/- std (mm)", sc.mean_std(l_err), "n/a (l unknown)"],
        ["registration error at targets, RMS (mm)", sc.mean_std(tre), "n/a (no ground truth)"],
    ]))
    edges = np.linspace(np.floor(fre.min() * 20) / 20, np.ceil(fre.max() * 20) / 20 + 1e-9, 7)
    counts, _ = np.histogram(fre, edges)
    print("\nFRE distribution\n")
    print(sc.table(["FRE (mm)", "calibrations", ""], [
        [f"{a:.2f}-{b:.2f}", str(c), "#" * int(c)] for a, b, c in zip(edges[:-1], edges[1:], counts, strict=True)]))
    print("\nper calibration: " + ", ".join(f"{v:.2f}" for v in fre))
    for s in sessions:
        if s.refused:
            print(f"refused: {s.refused}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
