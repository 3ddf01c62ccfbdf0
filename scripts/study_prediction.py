#!/usr/bin/env python3
"""Study (beyond the paper): predicted vs measured TRE (Fitzpatrick, West & Maurer 1998).

Each registration estimates the fiducial localisation error from its FRE
(FLE = FRE * sqrt(N / (N - 2))) and predicts the RMS TRE at each target from the marker
configuration. Here the prediction is compared with the true registration error at the same
target over many simulated calibration sessions (RMS over sessions), and the estimated FLE with
the actual localisation errors of both sides (tracker: calibration point vs true pinhole;
image: detected sensor point at the true l vs the true one).

    .venv/bin/python scripts/study_prediction.py [--repetitions 30] [--quick] [--work DIR]
"""

from __future__ import annotations

import argparse

import numpy as np
import study_common as sc


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sc.add_common_arguments(parser)
    parser.add_argument("--repetitions", type=int, default=None, help="sessions (default 30; 6 with --quick)")
    args = parser.parse_args(argv)

    repetitions = args.repetitions or (6 if args.quick else 30)
    frame = sc.prepare_frame(args)
    rng = np.random.default_rng(1998)
    predicted, measured, fle_estimated = [], [], []
    for _ in range(repetitions):
        session = sc.calibrate_and_register(frame, rng, sc.noise_model(args.noise_scale))
        if session.registration is None or session.registration.predicted_tre_mm is None:
            continue
        predicted.append(np.asarray(session.registration.predicted_tre_mm, dtype=float))
        measured.append(session.target_errors_mm)
        fle_estimated.append(session.registration.fle_mm)
    predicted, measured = np.array(predicted), np.array(measured)

    # actual localisation errors: image side (detection at the true l) and, from one session, the tracker side
    l_true = frame.truth["sensor_offset_l_mm"]
    truth_by_label = {m["label"]: m for m in frame.truth["markers"]}
    image_errors = []
    for marker in frame.detection.markers:
        nearest = min(truth_by_label.values(), key=lambda m: np.linalg.norm(np.asarray(m["origin"]) - marker.origin))
        true_point = np.asarray(nearest["origin"]) + l_true * np.asarray(nearest["axis"])
        image_errors.append(np.linalg.norm(marker.origin + l_true * marker.axis - true_point))
    from EMRegModule.calibration import calibrate_frame

    tracker_errors = []
    for _ in range(5):
        calibration = calibrate_frame(sc.simulate_calibration(frame, rng, sc.noise_model(args.noise_scale)), 1, 2,
                                      None)
        index = {label: i for i, label in enumerate(frame.labels)}
        tracker_errors += [np.linalg.norm(p.position - frame.pinholes[index[p.label]]) for p in calibration.points]
    fle_image = float(np.sqrt(np.mean(np.square(image_errors))))
    fle_tracker = float(np.sqrt(np.mean(np.square(tracker_errors))))

    print(f"\nPredicted (Fitzpatrick) vs measured TRE over {len(measured)} registrations "
          f"({len(frame.labels)} markers)\n")
    rows = []
    for k, label in enumerate(frame.target_labels):
        p = float(np.sqrt(np.mean(predicted[:, k] ** 2)))
        m = float(np.sqrt(np.mean(measured[:, k] ** 2)))
        rows.append([label, f"{p:.2f}", f"{m:.2f}", f"{m / p:.2f}"])
    p_all = float(np.sqrt(np.mean(predicted ** 2)))
    m_all = float(np.sqrt(np.mean(measured ** 2)))
    rows.append(["all", f"{p_all:.2f}", f"{m_all:.2f}", f"{m_all / p_all:.2f}"])
    print(sc.table(["target", "predicted RMS TRE (mm)", "measured RMS TRE (mm)", "measured / predicted"], rows))
    print("\nFiducial localisation error (RMS, mm)\n")
    print(sc.table(["source", "FLE (mm)"], [
        ["estimated by the registration from FRE (mean)", f"{np.mean(fle_estimated):.2f}"],
        ["tracker side: calibration point vs true pinhole", f"{fle_tracker:.2f}"],
        ["image side: detected sensor point vs true", f"{fle_image:.2f}"],
        ["both sides combined (root sum of squares)", f"{np.hypot(fle_tracker, fle_image):.2f}"],
    ]))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
