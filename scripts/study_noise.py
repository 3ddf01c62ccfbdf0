#!/usr/bin/env python3
"""Study (beyond the paper): how FRE and TRE grow with the tracker's noise.

Every magnitude of the simulator's trakSTAR error model (per-dwell systematic error and
jitter of both sensors) is scaled by a factor; for each factor, simulated calibration sessions
run through the real calibration and registration. TRE is the true registration error at the
targets (RMS), so it isolates the registration from the navigation's own tracking noise.

    .venv/bin/python scripts/study_noise.py [--scales 0.5 1 2 3 4] [--repetitions 10] [--quick]
"""

from __future__ import annotations

import argparse

import numpy as np
import study_common as sc


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sc.add_common_arguments(parser)
    parser.add_argument("--scales", type=float, nargs="+", default=[0.0, 0.5, 1.0, 2.0, 3.0, 4.0])
    parser.add_argument("--repetitions", type=int, default=None, help="sessions per scale (default 10; 3 quick)")
    args = parser.parse_args(argv)
    repetitions = args.repetitions or (3 if args.quick else 10)
    frame = sc.prepare_frame(args)
    base = sc.noise_model(1.0)
    rows = []
    for scale in args.scales:
        rng = np.random.default_rng(int(scale * 1000) + 7)
        noise = sc.noise_model(scale)
        sessions = [sc.calibrate_and_register(frame, rng, noise) for _ in range(repetitions)]
        done = [s for s in sessions if s.registration is not None]
        fre = [s.registration.fre_mm for s in done]
        tre = [float(np.sqrt(np.mean(s.target_errors_mm ** 2))) for s in done]
        l_err = [abs(s.l_error_mm) for s in done]
        dwell_3d = scale * base.probe_dwell_mm * np.sqrt(3)
        rows.append([f"{scale:g}", f"{dwell_3d:.2f}", str(len(sessions) - len(done)),
                     sc.mean_std(fre) if fre else "-", sc.mean_std(tre) if tre else "-",
                     f"{np.mean(l_err):.2f}" if l_err else "-"])
    print(f"\nFRE and TRE against tracker noise ({len(frame.labels)} markers, {repetitions} sessions per row)\n")
    print(sc.table(["noise scale", "probe dwell error 3D RMS (mm)", "refused", "FRE (mm)",
                    "registration TRE RMS (mm)", "mean |l error| (mm)"], rows))
    print(f"\npaper: mean FRE {sc.PAPER['calibration_fre_mean_mm']:.2f} mm, TRE {sc.PAPER['tre_mean_mm']:.2f} mm "
          "(real trakSTAR, 0.3 mm CT)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
