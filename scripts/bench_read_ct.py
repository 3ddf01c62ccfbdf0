#!/usr/bin/env python3
"""Benchmark reading a CT (``read_ct``) against ``SimpleITK.ReadImage`` of the same file, in the same run.

The CT is the simulator's full frame at 0.6 mm (``emreg simulate``, reused when already in
``--work``), written again as compressed NRRD, NIfTI and MetaImage and as raw NRRD. For each
file it prints the best of ``--repeat`` wall times of both readers, their ratio, and checks
that both give the same voxels and geometry. ``read_ct`` inflates with ISA-L straight into the
image's buffer; SimpleITK inflates with zlib.

DICOM (issue 13): the same CT written as a series of slices (SimpleITK's GDCM writer, one file per
slice, 16-bit stored values with a rescale intercept) and re-encoded JPEG lossless by ``gdcmconv``,
read by ``read_ct`` (series scan and choice, slices decoded on a thread pool, the folder's sha256
made in the same pass) against ``SimpleITK.ImageSeriesReader`` (``GetGDCMSeriesFileNames`` +
``Execute``); ``--dicom FOLDER`` adds a series of your own (e.g. ``bench_detect.py --dicom``'s).

DICOM detection (issue 28): ``emreg detect`` on hard oblique uncompressed series (0.5 x 0.5 x 0.8 mm,
``--difficulty hard``): a mid-sized frame (280 x 250 x 180 mm, 22 markers, 399 slices: the size of the issue's own
series), the full frame (``emreg simulate``, the case ``bench_detect.py --dicom`` uses, 653 slices) and a CI-sized
frame (220 x 220 x 140 mm, 16 markers, 388 slices), ``--detect-cases`` choosing, plus the folders
of ``--dicom-detect``; against ``SimpleITK.ImageSeriesReader`` reading the same folder (``GetGDCMSeriesFileNames``
+ ``Execute``), each in its own process, alternated ``--repeat`` times after a warm-up; medians of ``emreg
detect``'s whole process against the reader's ``Execute`` (goal <= 1.0) and against the reader's whole process,
with both processes' CPU time (user + system) and the load average while they ran: on a shared machine the wall
times follow the CPU each process gets, so take the ratio from a run at low load. ``--before TREE`` runs an earlier
revision's ``emreg detect`` (a git worktree of it) in the same rounds and compares the two ``markers.json``.

Usage: ``.venv/bin/python scripts/bench_read_ct.py [--work DIR] [--repeat 3] [--dicom FOLDER ...] [--no-dicom]
[--detect-only] [--detect-cases mid,full,ci|none] [--dicom-detect FOLDER ...] [--before TREE]``
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

ROOT = Path(__file__).resolve().parents[1]


def series_reader(folder: Path) -> sitk.Image:
    reader = sitk.ImageSeriesReader()
    reader.SetFileNames(sitk.ImageSeriesReader.GetGDCMSeriesFileNames(str(folder)))
    return reader.Execute()


def dicom_copies(image: sitk.Image, work: Path) -> list[Path]:
    """``image`` as an uncompressed DICOM series and as a JPEG-lossless one (reused when already there)."""
    sys.path.insert(0, str(ROOT / "Testing" / "Python"))
    from dicom_files import uid, write_series

    plain, jpeg = work / "read-ct" / "dicom", work / "read-ct" / "dicom-jpeg-lossless"
    if not (plain / ".complete").is_file():
        print(f"writing the CT as a DICOM series into {plain} ...", flush=True)
        hu = sitk.Cast(image, sitk.sitkInt32) + 1024  # stored values; the files' intercept -1024 gives the HU back
        write_series(sitk.Cast(hu, sitk.sitkInt16), plain, uid(900), rescale=[(1.0, -1024.0)] * image.GetSize()[2])
        (plain / ".complete").write_text("")
    if not (jpeg / ".complete").is_file():
        print(f"re-encoding it as JPEG lossless into {jpeg} ...", flush=True)
        jpeg.mkdir(parents=True, exist_ok=True)
        for path in sorted(plain.glob("*.dcm")):
            subprocess.run(["gdcmconv", "--jpeg", str(path), str(jpeg / path.name)], check=True)
        (jpeg / ".complete").write_text("")
    return [plain, jpeg]


def best_time(read, path: Path, repeat: int) -> tuple[float, sitk.Image]:
    best, image = float("inf"), None
    for _ in range(repeat):
        image = None  # free the previous copy before reading again
        start = time.perf_counter()
        image = read(path)
        best = min(best, time.perf_counter() - start)
    return best, image


#: The DICOM detection cases (issue 28): the hard full frame of ``emreg simulate --difficulty hard`` (971 x 753 x 653
#: voxels of 0.5 x 0.5 x 0.8 mm, oblique), a mid-sized hard frame (280 x 250 x 180 mm, 22 markers: 399 slices, 300 MB
#: as int16, which SimpleITK's series read takes 0.90 s to read here: the size of the issue's own series, read in
#: 0.88 s) and a CI-sized hard frame (220 x 220 x 140 mm, 16 markers: 613 x 447 x 388).
DETECT_CASES = {
    "mid": ("hard-dicom-mid", ["-c", "from EMRegModule.simulation.case import simulate_case; simulate_case('{case}', "
                                     "seed=13, difficulty='hard', frame_size_mm=(280.0, 250.0, 180.0), n_markers=22)"]),
    "full": ("hard-dicom", ["-m", "EMRegModule", "simulate", "{case}", "--seed", "1", "--difficulty", "hard",
                            "--quiet"]),
    "ci": ("hard-dicom-ci", ["-c", "from EMRegModule.simulation.case import simulate_case; simulate_case('{case}', "
                                   "seed=12, difficulty='hard', frame_size_mm=(220.0, 220.0, 140.0), n_markers=16)"]),
}


def detect_case(work: Path, name: str) -> Path:
    """The DICOM folder of the detection case ``name`` (:data:`DETECT_CASES`), simulated when not in ``work``."""
    folder, command = DETECT_CASES[name]
    case = work / folder
    if not (case / "truth.json").is_file():
        print(f"simulating the {name} hard case (DICOM, 0.5 x 0.5 x 0.8 mm) into {case} ...", flush=True)
        subprocess.run([sys.executable, *(part.replace("{case}", str(case)) for part in command)], check=True)
    return case / "ct"


def dicom_detect(folder: Path, out: Path, repeat: int, before: Path | None = None) -> None:
    """``emreg detect`` on the DICOM series ``folder`` against ``ImageSeriesReader`` (see the module docstring):
    medians of ``repeat`` alternated runs, each process's CPU time (user + system) and the load meanwhile.
    ``before``: a source tree of another revision (a git worktree), whose ``emreg detect`` is run in the same
    rounds (``PYTHONPATH`` set to it) and whose ``markers.json`` is compared with this one's."""
    import json
    import os
    import re

    from bench_detect import DICOM_READ_ONLY, run_child

    import EMRegModule

    def emreg_detect(tree: Path, into: Path) -> list[str]:
        # the package of ``tree`` and no other: -P keeps the current directory off sys.path (``python -m`` puts it
        # first, so that run from a checkout every command would run that checkout's code)
        return ["env", f"PYTHONPATH={tree}", sys.executable, "-P", "-m", "EMRegModule", "detect", str(folder),
                "--out", str(into), "--quiet"]

    read = [sys.executable, "-c", DICOM_READ_ONLY, str(folder)]
    detect = emreg_detect(Path(EMRegModule.__file__).resolve().parents[1], out)  # the code this script imports
    earlier = None if before is None else emreg_detect(before, Path(str(out) + "-before"))
    run_child(read)  # warm-up: the files in the page cache, the modules compiled
    run_child(detect)
    reads, read_process, read_cpu, detects, detect_cpu, peaks, loads = [], [], [], [], [], [], []
    befores, before_cpu = [], []
    for _ in range(repeat):
        loads.append(os.getloadavg()[0])
        wall, _, text, err, code = run_child(read)
        if code != 0:
            sys.exit(f"ImageSeriesReader failed ({code}): {err.strip()[-300:]}")
        reads.append(float(re.search(r"read (\S+)", text).group(1)))
        read_process.append(wall)
        read_cpu.append(run_child.cpu_seconds)
        wall, peak, _, err, code = run_child(detect)
        if code != 0:
            sys.exit(f"emreg detect failed ({code}): {err.strip()[-300:]}")
        detects.append(wall)
        detect_cpu.append(run_child.cpu_seconds)
        peaks.append(peak)
        if earlier is not None:
            wall, _, _, err, code = run_child(earlier)
            if code != 0:
                sys.exit(f"emreg detect of {before} failed ({code}): {err.strip()[-300:]}")
            befores.append(wall)
            before_cpu.append(run_child.cpu_seconds)
    loads.append(os.getloadavg()[0])
    t_read, t_process, t_detect = (float(np.median(v)) for v in (reads, read_process, detects))
    print(f"\nDICOM detection: {folder} ({len(list(folder.glob('*.dcm')))} files), medians of {repeat} alternated "
          f"runs, load {min(loads):.2f}-{max(loads):.2f} (1-minute average)")
    print(f"  emreg detect (whole process)             {t_detect:6.2f} s  CPU {np.median(detect_cpu):.2f} s  "
          f"peak {np.max(peaks) / 1e9:.2f} GB  ({' '.join(f'{v:.2f}' for v in detects)})")
    print(f"  ImageSeriesReader (file names + Execute) {t_read:6.2f} s  its whole process {t_process:.2f} s, CPU "
          f"{np.median(read_cpu):.2f} s  ({' '.join(f'{v:.2f}' for v in reads)})")
    print(f"  detect / read = {t_detect / t_read:.2f} (goal <= 1.0); detect / the reader's whole process = "
          f"{t_detect / t_process:.2f}", flush=True)
    if earlier is not None:
        t_before = float(np.median(befores))
        mine, theirs = ((folder_out / "markers.json").read_bytes() for folder_out in (out, Path(str(out) + "-before")))
        same = "byte-identical" if mine == theirs else "DIFFERENT"
        if mine != theirs:
            documents = [json.loads(text) for text in (mine, theirs)]
            for document in documents:
                document.pop("provenance", None)
            same = "identical apart from provenance" if documents[0] == documents[1] else "DIFFERENT"
        print(f"  before ({before}): emreg detect {t_before:6.2f} s  CPU {np.median(before_cpu):.2f} s  "
              f"({' '.join(f'{v:.2f}' for v in befores)}); detect / read = {t_before / t_read:.2f}; "
              f"markers.json {same}", flush=True)


def dicom_detection(work: Path, repeat: int, cases: list[str], folders: list[Path], before: Path | None) -> None:
    """The DICOM detection section: the cases named (:data:`DETECT_CASES`), then the ``folders`` given."""
    for name in cases:
        dicom_detect(detect_case(work, name), work / f"out-read-ct-dicom-{name}", repeat, before)
    for k, folder in enumerate(folders):
        dicom_detect(folder, work / f"out-read-ct-dicom-given-{k}", repeat, before)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--work", default="/tmp/emreg-bench-detect", help="folder for the case (kept for reuse)")
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--dicom", type=Path, nargs="*", default=[], help="more DICOM series folders to read")
    parser.add_argument("--no-dicom", action="store_true", help="leave out the DICOM copies of the CT")
    parser.add_argument("--detect-only", action="store_true", help="only emreg detect on the hard DICOM series")
    parser.add_argument("--detect-cases", default="mid,full,ci",
                        help="DICOM detection cases, comma separated: mid (a mid-sized hard frame, 399 slices), full "
                             "(the hard full frame, 653 slices), ci (a CI-sized hard frame, 388 slices), or none")
    parser.add_argument("--dicom-detect", type=Path, nargs="*", default=[], metavar="FOLDER",
                        help="more DICOM series folders to run emreg detect on against ImageSeriesReader")
    parser.add_argument("--before", type=Path, default=None, metavar="TREE",
                        help="also run the emreg detect of this source tree (a worktree of an earlier revision) in "
                             "the same alternated rounds, and compare its markers.json")
    args = parser.parse_args()
    cases = [c for c in args.detect_cases.split(",") if c and c != "none"]
    unknown = sorted(set(cases) - set(DETECT_CASES))
    if unknown:
        parser.error(f"--detect-cases: unknown {', '.join(unknown)} (known: {', '.join(DETECT_CASES)}, none)")
    if args.detect_only:
        dicom_detection(Path(args.work), args.repeat, cases, args.dicom_detect, args.before)
        return
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
    folders = [] if args.no_dicom else dicom_copies(image, Path(args.work))
    folders += list(args.dicom)
    del image
    print(f"{'file':<22} {'MB on disk':>10} {'read_ct':>9} {'SimpleITK':>10} {'speed-up':>9}")
    for path in [*files, *folders]:
        dicom = path.is_dir()
        baseline = series_reader if dicom else (lambda p: sitk.ReadImage(str(p)))
        t_fast, fast = best_time(read_ct, path, args.repeat)
        t_sitk, plain = best_time(baseline, path, args.repeat)
        same = (np.allclose(fast.GetOrigin(), plain.GetOrigin(), atol=1e-4)
                and np.allclose(fast.GetDirection(), plain.GetDirection(), atol=1e-6)
                and np.allclose(fast.GetSpacing(), plain.GetSpacing(), rtol=1e-5) if dicom  # z from all positions
                else fast.GetOrigin() == plain.GetOrigin() and fast.GetDirection() == plain.GetDirection()
                and fast.GetSpacing() == plain.GetSpacing())
        same = same and np.array_equal(sitk.GetArrayViewFromImage(fast), sitk.GetArrayViewFromImage(plain))
        del fast, plain
        size = sum(p.stat().st_size for p in path.iterdir()) if dicom else path.stat().st_size
        name = f"{path.name}/ (DICOM)" if dicom else path.name
        print(f"{name:<22} {size / 1e6:>10.0f} {t_fast:>8.2f}s {t_sitk:>9.2f}s "
              f"{t_sitk / t_fast:>8.2f}x  {'identical' if same else 'DIFFERENT'}", flush=True)
        if not same:
            sys.exit(f"{path}: read_ct and SimpleITK disagree")
    if not args.no_dicom:
        dicom_detection(Path(args.work), args.repeat, cases, args.dicom_detect, args.before)


if __name__ == "__main__":
    main()
