#!/usr/bin/env python3
"""Study: the board phantom (paper Table 1; absolute errors 0.16-0.21 mm, all below 1 mm).

A 3D-printed board with four corner holes; the probe is put into each hole in turn, 60 rounds;
the four edge lengths L1..L4 measured by the tracker are compared with the caliper. Here: the
simulated case's board recording (60 rounds, nominal edges = the simulated board) through
EMReg's evaluation (``evaluate_board``), optionally over several simulated sessions.

    .venv/bin/python scripts/study_board.py [--quick] [--work DIR]
"""

from __future__ import annotations

import argparse

import numpy as np
import study_common as sc


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sc.add_common_arguments(parser)
    args = parser.parse_args(argv)
    from EMRegModule.evaluation import evaluate_board
    from EMRegModule.io.case import open_case
    from EMRegModule.io.tracking_csv import read_tracking_csv

    frame = sc.prepare_frame(args)
    case = open_case(frame.case_dir)
    nominal = [float(v) for v in frame.truth["board"]["edges_mm"]]
    result = evaluate_board(read_tracking_csv(case.board), case.reference_sensor, case.probe_sensor,
                            nominal).to_json()
    rows = []
    for name, edge in result["edges"].items():
        paper = sc.PAPER["board"][name]
        rows.append([name, f"{edge['mean_mm']:.2f}", f"{edge['std_mm']:.2f}", f"{edge['nominal_mm']:.2f}",
                     f"{edge['abs_error_mean_mm']:.2f} +/- {edge['abs_error_std_mm']:.2f}",
                     f"{edge['rel_error_mean_percent']:.2f}% +/- {edge['rel_error_std_percent']:.2f}%",
                     f"{paper[0]:.2f} / {paper[1]:.2f}", f"{paper[2]:.2f}", f"{paper[4]:.2f} +/- {paper[5]:.2f}"])
    print(f"\nBoard phantom: {result['rounds']} rounds over {len(result['edges'])} edges "
          f"(positions in the {result['frame']} frame)\n")
    print(sc.table(["edge", "EMReg mean (mm)", "sigma", "nominal", "abs error (mm)", "relative error",
                    "paper EM mean / sigma", "paper caliper", "paper abs error"], rows))
    worst = max(e["abs_error_mean_mm"] + 2 * e["abs_error_std_mm"] for e in result["edges"].values())
    print(f"\nall edges within 1 mm: {'yes' if worst < 1.0 else 'no'} (largest mean + 2 sd of the absolute "
          f"error: {worst:.2f} mm; paper: 0.16-0.21 mm, max 0.65 mm)")
    lengths = np.array([e["mean_mm"] for e in result["edges"].values()])
    print("measured - nominal (mm): " + ", ".join(f"{v:+.2f}" for v in lengths - np.asarray(nominal)))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
