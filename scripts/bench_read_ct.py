#!/usr/bin/env python3
"""Benchmark reading a CT (``read_ct``) against ``SimpleITK.ReadImage`` of the same file, in the same run.

The CT is the simulator's full frame at 0.6 mm (``emreg simulate``, reused when already in
``--work``), written again as compressed NRRD, NIfTI and MetaImage and as raw NRRD. For each
file it prints the best of ``--repeat`` wall times of both readers, their ratio, and checks
that both give the same voxels and geometry. ``read_ct`` inflates with ISA-L straight into the
image's buffer; SimpleITK inflates with zlib.

Usage: ``.venv/bin/python scripts/bench_read_ct.py [--work DIR] [--repeat 3]``
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import SimpleITK as sitk

from EMRegModule.io.image import read_ct


def best_time(read, path: Path, repeat: int) -> tuple[float, sitk.Image]:
    best, image = float("inf"), None
    for _ in range(repeat):
        image = None  # free the previous copy before reading again
        start = time.perf_counter()
        image = read(path)
        best = min(best, time.perf_counter() - start)
    return best, image


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--work", default="/tmp/emreg-bench-detect", help="folder for the case (kept for reuse)")
    parser.add_argument("--repeat", type=int, default=3)
    args = parser.parse_args()
    case = Path(args.work) / "sim-0.6"
    if not (case / "truth.json").is_file():
        print(f"simulating the full frame at 0.6 mm into {case} ...", flush=True)
        subprocess.run([sys.executable, "-m", "EMRegModule", "simulate", str(case), "--seed", "1", "--spacing", "0.6",
                        "--quiet"], check=True)
    source = case / "ct.nrrd"
    files = [source]
    image = sitk.ReadImage(str(source))
    for name, compress in (("ct.nii.gz", True), ("ct.mha", True), ("ct-raw.nrrd", False)):
        path = Path(args.work) / "read-ct" / name
        if not path.is_file():
            path.parent.mkdir(parents=True, exist_ok=True)
            sitk.WriteImage(image, str(path), compress)
        files.append(path)
    del image
    print(f"{'file':<14} {'MB on disk':>10} {'read_ct':>9} {'SimpleITK':>10} {'speed-up':>9}")
    for path in files:
        t_fast, fast = best_time(read_ct, path, args.repeat)
        t_sitk, plain = best_time(lambda p: sitk.ReadImage(str(p)), path, args.repeat)
        same = (fast.GetOrigin() == plain.GetOrigin() and fast.GetDirection() == plain.GetDirection()
                and fast.GetSpacing() == plain.GetSpacing()
                and np.array_equal(sitk.GetArrayViewFromImage(fast), sitk.GetArrayViewFromImage(plain)))
        print(f"{path.name:<14} {path.stat().st_size / 1e6:>10.0f} {t_fast:>8.2f}s {t_sitk:>9.2f}s "
              f"{t_sitk / t_fast:>8.2f}x  {'identical' if same else 'DIFFERENT'}", flush=True)
        if not same:
            sys.exit(f"{path}: read_ct and SimpleITK disagree")


if __name__ == "__main__":
    main()
