#!/usr/bin/env python3
"""Benchmark ``emreg report`` and ``emreg run`` at full-frame scan sizes against ``emreg detect`` and a baseline.

Measured in one run, each command in its own process:

(a) ``emreg detect CASE`` (the detection alone: read the CT, find and pose the markers);
(b) ``emreg report OUT`` on the outputs of an ``emreg run``, as the run left them: the report finds the CT
    products the run's report kept (``report_figures/ct_context.npz``) and an up-to-date 3D Slicer bundle
    ``EMReg.mrb``, so it hashes the CT (checked against ``run.json``) instead of reading it and keeps the
    bundle; (b') the same report as the first of its folder (no report, no bundle: nothing to reuse; it reads
    the CT and writes the bundle when ``slicer-core`` is installed);
(c) the baseline: the same ``emreg report`` of an earlier EMReg revision (``--baseline-rev``, by
    default main before the lean-report work of issue 17's second round; extracted with
    ``git archive``), on a copy of the same outputs;
(d) ``emreg run CASE`` end to end, and (e) the baseline revision's ``emreg run``.

Peak memory is the largest of the process's own ``ru_maxrss`` and the summed RSS of the process and
its children sampled every 20 ms (``emreg report`` writes the bundle in a child process while it
renders: both count); CPU time is the user + system time ``os.wait4`` reports for the process and the
children it waited for. Printed per case: times, CPU times and peaks, the CT's voxel bytes, and the goals of
issue 17: report time / detect time <= 1.0; report peak and run peak / CT bytes <= 1.3; the same
ratios for the baseline, measured in the same run. It also compares every figure the two reports
wrote, pixel for pixel.

Cases come from ``emreg simulate`` (reused when present in ``--work``), or ``--case``: ``--spacing 0.6``
and the paper's scan size; the simulator refuses 0.3 mm for the full frame (1.7 G voxels, above its
limit of 1.5 G), so the finest default is 0.32 mm (1.40 G voxels, 2.8 GB as int16, the size of
the 0.3 mm scan of issue 17: 1.37 G voxels). Simulating that case needs about 10 GB once.

``--cold-report`` (issue 28) measures instead a cold ``emreg report OUT --case CASE`` over the outputs of the
per-stage commands (``detect``, ``calibrate``, ``register``, ``navigate``, ``evaluate``: their ``run.json`` names
no CT; no report, no bundle, no kept CT products), bundle included, against ``emreg detect CASE``, and the same
report of ``--baseline-rev``: the three alternated ``--repeat`` times, medians printed (goals: report time /
detect time <= 1.5, report peak / CT bytes <= 1.3).

Usage: ``.venv/bin/python scripts/bench_report.py [--spacing 0.6 0.32 | --case DIR ...] [--work DIR]
[--baseline-rev REV] [--cold-report [--repeat 3]]`` (run it under ``flock /work/heavy.lock`` on a shared machine).
"""

from __future__ import annotations

import argparse
import importlib.util
import os
import shutil
import subprocess
import sys
import tarfile
import tempfile
import threading
import time
from pathlib import Path

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
PYTHON = sys.executable
#: main before the second round of issue 17 (the report streaming its CT, the bundle copying it from its file).
#: ``c81b885`` is the last revision before the report package of issues 10 and 17 (the first round's baseline).
DEFAULT_BASELINE_REV = "c6c5ab6"
FIGURES = ("scene_oblique", "scene_top", "marker_slices", "residuals", "fre_curve", "tre_targets", "error_budget",
           "tre_map")


def run_child(command: list[str], env: dict[str, str] | None = None, cwd: Path | None = None
              ) -> tuple[float, float, float]:
    """Run ``command``; wall time (s), its peak memory (bytes): the larger of its own ``ru_maxrss``
    (``os.wait4``) and the summed RSS of it and its children, sampled every 20 ms, and its CPU time
    (s, user + system, its own and its waited-for children's, as ``os.wait4`` reports it). Raises on
    failure."""
    peak = [0.0]
    start = time.perf_counter()
    with tempfile.TemporaryFile() as err:
        process = subprocess.Popen(command, stdout=subprocess.DEVNULL, stderr=err, env=env, cwd=cwd)
        done = threading.Event()

        def sample() -> None:
            while not done.is_set():
                peak[0] = max(peak[0], tree_rss(process.pid))
                done.wait(0.02)

        sampler = threading.Thread(target=sample, daemon=True)
        sampler.start()
        _, status, usage = os.wait4(process.pid, 0)
        wall = time.perf_counter() - start
        done.set()
        sampler.join()
        if os.waitstatus_to_exitcode(status) != 0:
            err.seek(0)
            raise SystemExit(f"{' '.join(command)} failed: {err.read().decode(errors='replace')[-600:]}")
    return wall, max(usage.ru_maxrss * 1024.0, peak[0]), usage.ru_utime + usage.ru_stime


def tree_rss(pid: int) -> float:
    """Resident bytes of a process and all its descendants (0 once it is gone)."""
    total, pending = 0.0, [pid]
    while pending:
        current = pending.pop()
        try:
            with open(f"/proc/{current}/status", encoding="ascii") as f:
                total += next((float(line.split()[1]) * 1024.0 for line in f if line.startswith("VmRSS:")), 0.0)
            with open(f"/proc/{current}/task/{current}/children", encoding="ascii") as f:
                pending += [int(child) for child in f.read().split()]
        except (OSError, ValueError):
            continue
    return total


def emreg(*args: str) -> list[str]:
    return [PYTHON, "-m", "EMRegModule", *args, "--quiet"]


def baseline_tree(rev: str, work: Path) -> Path:
    """The source of revision ``rev`` in ``work/baseline-REV`` (``git archive``; reused when there)."""
    folder = work / f"baseline-{rev}"
    if not (folder / "EMRegModule").is_dir():
        folder.mkdir(parents=True, exist_ok=True)
        archive = subprocess.run(["git", "-C", str(ROOT), "archive", rev], check=True, capture_output=True).stdout
        with tempfile.TemporaryFile() as f:
            f.write(archive)
            f.seek(0)
            with tarfile.open(fileobj=f) as tar:
                tar.extractall(folder, filter="data")
    return folder


def simulated_case(work: Path, spacing: float, seed: int) -> Path:
    folder = work / f"case-{spacing:g}mm-seed{seed}"
    if not (folder / "truth.json").is_file():
        print(f"simulating the full frame at {spacing:g} mm into {folder} ...", flush=True)
        subprocess.run(emreg("simulate", str(folder), "--seed", str(seed), "--spacing", str(spacing)), check=True)
    return folder


def ct_bytes(case: Path) -> float:
    import SimpleITK as sitk

    from EMRegModule.io.case import find_ct

    ct = find_ct(case)
    if ct.is_dir():  # a DICOM folder: the series the detection uses, as it stores its voxels
        from EMRegModule.io.dicom_series import choose_series, scan_series

        series = choose_series(scan_series(ct), ct)
        return float(np.prod(series.size)) * series.headers[0].bits_allocated // 8
    reader = sitk.ImageFileReader()
    reader.SetFileName(str(ct))
    reader.ReadImageInformation()
    pixel = sitk.Image([1, 1, 1], reader.GetPixelID())
    return float(np.prod(reader.GetSize())) * pixel.GetSizeOfPixelComponent()


def copy_outputs(source: Path, target: Path, as_left: bool = True) -> None:
    """The run's outputs as the run left them (``as_left``: its report, the CT products that report kept and its
    bundle included, as a user's ``emreg report OUT`` after ``emreg run`` finds them), or without any report or
    bundle (a first report of the folder: nothing to reuse). Hard links where possible (a replaced file is a new
    one: a report writes atomically)."""
    def link_or_copy(src: str, dst: str) -> None:
        try:
            os.link(src, dst)
        except OSError:
            shutil.copy2(src, dst)

    ignored = ("previous",) if as_left else ("previous", "report.html", "report_figures", "EMReg.mrb")
    shutil.rmtree(target, ignore_errors=True)
    shutil.copytree(source, target, ignore=shutil.ignore_patterns(*ignored), copy_function=link_or_copy)


def same_figures(a: Path, b: Path) -> dict[str, str]:
    """Per figure: "identical pixels", "differs (max N)" or "missing"."""
    verdicts = {}
    for name in FIGURES:
        fa, fb = a / "report_figures" / f"{name}.png", b / "report_figures" / f"{name}.png"
        if not fa.is_file() or not fb.is_file():
            verdicts[name] = "missing"
            continue
        ia, ib = cv2.imread(str(fa)), cv2.imread(str(fb))
        if ia.shape != ib.shape:
            verdicts[name] = f"differs (size {ia.shape[:2]} vs {ib.shape[:2]})"
        elif np.array_equal(ia, ib):
            verdicts[name] = "identical pixels"
        else:
            changed = np.any(ia != ib, axis=2).mean() * 100
            verdicts[name] = f"differs ({changed:.1f} % of pixels)"
    return verdicts


def bench_case(case: Path, work: Path, baseline: Path, rev: str) -> None:
    size = ct_bytes(case)
    base_env = {**os.environ, "PYTHONPATH": str(baseline)}
    tag = case.name
    outs = {name: work / f"{tag}-{name}" for name in ("run", "run-base", "detect", "report", "report-base",
                                                       "report-first")}
    for folder in outs.values():
        shutil.rmtree(folder, ignore_errors=True)
    results: dict[str, tuple[float, float, float]] = {}
    print(f"\n{case} (CT {size / 1e9:.2f} GB; load {os.getloadavg()[0]:.1f})", flush=True)
    # warm-up (not timed): the CT in the page cache and every module compiled, for whichever runs first
    run_child(emreg("detect", str(case), "--out", str(outs["detect"])), cwd=ROOT)
    run_child(emreg("detect", str(case), "--out", str(outs["detect"])), env=base_env, cwd=baseline)
    results["run"] = run_child(emreg("run", str(case), "--out", str(outs["run"])), cwd=ROOT)
    results["run (baseline)"] = run_child(emreg("run", str(case), "--out", str(outs["run-base"])), env=base_env,
                                          cwd=baseline)
    results["detect"] = run_child(emreg("detect", str(case), "--out", str(outs["detect"])), cwd=ROOT)
    for name in ("report", "report-base"):
        copy_outputs(outs["run"], outs[name])
    copy_outputs(outs["run"], outs["report-first"], as_left=False)
    results["report (baseline)"] = run_child(emreg("report", str(outs["report-base"])), env=base_env,
                                             cwd=baseline)
    results["report"] = run_child(emreg("report", str(outs["report"])), cwd=ROOT)
    results["report, first"] = run_child(emreg("report", str(outs["report-first"])), cwd=ROOT)
    print(f"{'command':<20} {'time (s)':>9} {'CPU (s)':>8} {'peak (GB)':>10} {'peak / CT':>10}")
    for name, (wall, peak, cpu) in results.items():
        print(f"{name:<20} {wall:9.2f} {cpu:8.2f} {peak / 1e9:10.2f} {peak / size:10.2f}")
    detect = results["detect"]
    for what, new, base in (("emreg report", results["report"], results["report (baseline)"]),
                            ("emreg report, first", results["report, first"], results["report (baseline)"]),
                            ("emreg run", results["run"], results["run (baseline)"])):
        timing = (f"time / detect time {new[0] / detect[0]:.2f} (goal <= 1.0; baseline {base[0] / detect[0]:.2f}), "
                  f"CPU / detect CPU {new[2] / detect[2]:.2f} (baseline {base[2] / detect[2]:.2f}), "
                  if what != "emreg run" else "")
        print(f"{what}: {timing}peak / CT bytes {new[1] / size:.2f} (goal <= 1.3; baseline {base[1] / size:.2f}); "
              f"against the baseline: time {new[0] / base[0]:.2f}x, peak {new[1] / base[1]:.2f}x")
    bundle = "" if importlib.util.find_spec("slicer") is None else \
        " (slicer-core is installed: emreg run and emreg report also write EMReg.mrb, the CT included)"
    print(f"baseline: EMReg at {rev}" + bundle)
    first = same_figures(outs["report-first"], outs["report"])
    for name, verdict in same_figures(outs["report"], outs["report-base"]).items():
        print(f"  {name:<15} {verdict} (against the baseline's); the first report's: {first[name]}")


def per_stage_outputs(case: Path, out: Path) -> None:
    """The per-stage commands on ``case`` into ``out`` (no report): what a cold report starts from."""
    shutil.rmtree(out, ignore_errors=True)
    for command in (["detect", str(case), "--out", str(out)],
                    ["calibrate", str(case / "calibration.csv"), "--out", str(out)],
                    ["register", "--markers", str(out / "markers.json"), "--calibration",
                     str(out / "frame_calibration.json"), "--targets", str(case / "targets.mrk.json"), "--out",
                     str(out)],
                    ["navigate", "--registration", str(out / "registration.json"), "--source",
                     f"replay:{case / 'navigation.csv'}", "--out", str(out)],
                    ["evaluate", str(case), "--registration", str(out / "registration.json"), "--out", str(out)]):
        run_child(emreg(*command), cwd=ROOT)


def bench_cold_report(case: Path, work: Path, baseline: Path, rev: str, repeat: int) -> None:
    """A cold ``emreg report OUT --case CASE`` (this tree and ``rev``) against ``emreg detect``, alternated."""
    size = ct_bytes(case)
    base_env = {**os.environ, "PYTHONPATH": str(baseline)}
    stages, detect_out = work / f"{case.name}-stages", work / f"{case.name}-detect"
    print(f"\n{case} (CT {size / 1e9:.2f} GB; load {os.getloadavg()[0]:.1f}): cold report after the per-stage "
          "commands", flush=True)
    per_stage_outputs(case, stages)
    run_child(emreg("detect", str(case), "--out", str(detect_out)), cwd=ROOT)  # warm-up: the CT in the page cache
    results: dict[str, list[tuple[float, float, float]]] = {"detect": [], "report": [], "report (baseline)": []}
    for _ in range(repeat):
        results["detect"].append(run_child(emreg("detect", str(case), "--out", str(detect_out)), cwd=ROOT))
        for name, env, cwd in (("report", None, ROOT), ("report (baseline)", base_env, baseline)):
            cold = work / f"{case.name}-cold"
            copy_outputs(stages, cold, as_left=False)
            results[name].append(run_child(emreg("report", str(cold), "--case", str(case)), env=env, cwd=cwd))
            if name == "report" and not (cold / "EMReg.mrb").is_file() and importlib.util.find_spec("slicer"):
                raise SystemExit(f"{cold}: the cold report wrote no EMReg.mrb")
            shutil.rmtree(cold, ignore_errors=True)
    medians = {name: tuple(float(np.median([r[i] for r in runs])) for i in range(3)) for name, runs in results.items()}
    print(f"{'command (median of ' + str(repeat) + ')':<24} {'time (s)':>9} {'CPU (s)':>8} {'peak (GB)':>10} "
          f"{'peak / CT':>10}  all times")
    for name, (wall, peak, cpu) in medians.items():
        every = " ".join(f"{r[0]:.2f}" for r in results[name])
        print(f"{name:<24} {wall:9.2f} {cpu:8.2f} {peak / 1e9:10.2f} {peak / size:10.2f}  {every}")
    detect = medians["detect"]
    for name in ("report", "report (baseline)"):
        wall, peak, cpu = medians[name]
        print(f"{name}: time / detect time {wall / detect[0]:.2f} (goal <= 1.5), CPU / detect CPU "
              f"{cpu / detect[2]:.2f}, peak / CT bytes {peak / size:.2f} (goal <= 1.3)")
    print(f"baseline: EMReg at {rev}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--spacing", type=float, nargs="+", default=[0.6, 0.32], help="voxel sizes (mm)")
    parser.add_argument("--work", type=Path, default=Path("/tmp/emreg-bench-report"),
                        help="folder for the cases and outputs (cases kept for reuse)")
    parser.add_argument("--case", type=Path, nargs="*", default=[], help="use these case folders instead")
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--baseline-rev", default=DEFAULT_BASELINE_REV, help="git revision measured as baseline")
    parser.add_argument("--cold-report", action="store_true",
                        help="a cold report after the per-stage commands against detect (issue 28)")
    parser.add_argument("--repeat", type=int, default=3, help="alternated runs of --cold-report (medians printed)")
    args = parser.parse_args()
    args.work.mkdir(parents=True, exist_ok=True)
    baseline = baseline_tree(args.baseline_rev, args.work)
    cases = args.case or [simulated_case(args.work, spacing, args.seed) for spacing in args.spacing]
    print(f"baseline: EMReg at {args.baseline_rev} ({baseline}); {os.cpu_count()} CPUs; load "
          f"{os.getloadavg()[0]:.1f}", flush=True)
    for case in cases:
        if args.cold_report:
            bench_cold_report(case.resolve(), args.work, baseline, args.baseline_rev, args.repeat)
        else:
            bench_case(case.resolve(), args.work, baseline, args.baseline_rev)


if __name__ == "__main__":
    main()
