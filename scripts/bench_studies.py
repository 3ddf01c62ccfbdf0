#!/usr/bin/env python3
"""Benchmark: an accuracy study on 1 and on 2 Dask workers (local processes), same tasks and seeds.

Prints the wall time of each and the speed-up; the two runs' results must be identical (checked).

    .venv/bin/python scripts/bench_studies.py [--study prediction] [--work DIR] [--full]
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from EMRegModule.studies import run_study  # noqa: E402
from EMRegModule.studies.frame import prepare_frame  # noqa: E402


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--study", default="prediction")
    parser.add_argument("--work", type=Path, default=Path("study-work"), help="simulated case kept here between runs")
    parser.add_argument("--full", action="store_true", help="the full study instead of --quick")
    args = parser.parse_args(argv)
    prepare_frame(args.work, quick=not args.full)  # simulate and detect once, outside the timing
    times, results = {}, {}
    for workers in (1, 2):
        with tempfile.TemporaryDirectory() as out:
            start = time.perf_counter()
            run_study(args.study, Path(out), quick=not args.full, workers=workers, work=args.work)
            times[workers] = time.perf_counter() - start
            results[workers] = json.loads((Path(out) / f"{args.study}.json").read_text())
    assert results[1] == results[2], "results differ between 1 and 2 workers"
    print(f"study {args.study} ({'full' if args.full else 'quick'}): 1 worker {times[1]:.1f} s, "
          f"2 workers {times[2]:.1f} s, speed-up {times[1] / times[2]:.2f}x (identical results)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
