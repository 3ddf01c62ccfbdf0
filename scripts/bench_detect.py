#!/usr/bin/env python3
"""Benchmark ``emreg detect`` on a full-size CT against plain SimpleITK baselines measured in the same run.

Measured, each in its own process so that peak memory (``ru_maxrss``) is per task:

(a) ``emreg detect CASE --out OUT``, end to end: interpreter start, imports, reading the CT,
    detection and the pose of every marker, writing the two files (wall time);
(b) the plain full-resolution SimpleITK pipeline on the same file: BinaryThreshold ->
    BinaryMorphologicalOpening (radius 1) -> ConnectedComponent -> LabelShapeStatistics
    (centroids only); the time of the filters alone, reading excluded;
(c) SimpleITK merely reading the file (the ``ReadImage`` call alone).

It prints the three times, a/b (goal <= 0.15), a/c (goal <= 2.5), the peak memory of (a)
over the volume's bytes (goal < 1.5 on the 0.3 mm scan), the accuracy against the case's
truth, and the time taken to pose all markers (goal: well under 1 s for 28).

Cases: ``--spacing 0.6`` (default) simulates the full frame with ``emreg simulate``
(about 210 M voxels); ``--spacing 0.3`` writes the paper's scan size (about 1.2 G voxels,
2.3 GB as int16) with a streaming generator in this script: a blurred POM block with 28
markers in slots on its faces, bone rods, white noise, written slab by slab as a
gzip-compressed NRRD like the simulator's (never holding the volume in memory).

``--dicom`` (issue 13) measures instead ``emreg detect`` on the hard case's DICOM series at
0.5 x 0.5 x 0.8 mm (the full frame, ``emreg simulate --difficulty hard``), uncompressed and
re-encoded as JPEG lossless by GDCM's ``gdcmconv``, against ``SimpleITK.ImageSeriesReader``
reading the same series (``GetGDCMSeriesFileNames`` + ``Execute``), each in its own process:
goals a/c <= 1.2 uncompressed and <= 1.0 for JPEG lossless; same markers from both folders.
Run it under ``flock /work/heavy.lock`` (about 1.5 GB).

Usage: ``.venv/bin/python scripts/bench_detect.py [--spacing 0.6|0.3] [--work DIR] [--skip-baseline] [--dicom]``
"""

from __future__ import annotations

import argparse
import json
import os
import re
import subprocess
import sys
import textwrap
import time
import zlib
from pathlib import Path

import numpy as np
from scipy import ndimage, special

ROOT = Path(__file__).resolve().parents[1]
PYTHON = sys.executable
sys.path.insert(0, str(ROOT / "Testing" / "Python"))

from fixtures.phantom import marker_object  # noqa: E402

from EMRegModule.marker_model import MarkerModel  # noqa: E402
from EMRegModule.simulation.ct import Grid, Layer, paint_layers  # noqa: E402
from EMRegModule.simulation.shapes import CylinderY, Difference, Posed  # noqa: E402

# --- running a measured child process -----------------------------------------------------------


def run_child(command: list[str]) -> tuple[float, float, str, str, int]:
    """Run ``command``, wait with ``os.wait4`` to get its own peak RSS; wall time (s), peak (bytes), out, err, code.

    The wall time ends with the command's process; ``run_child.cpu_seconds`` also counts the processes it left to
    end after it (``emreg detect``'s DICOM reader, which gives the volume's memory back once the command is over):
    this process is their subreaper, and waits for them before returning, so that the next run starts alone."""
    _become_subreaper()
    start = time.perf_counter()
    out_file = Path(os.environ.get("TMPDIR", "/tmp")) / f"bench_detect_{os.getpid()}.out"
    err_file = out_file.with_suffix(".err")
    with out_file.open("w") as out, err_file.open("w") as err:
        process = subprocess.Popen(command, stdout=out, stderr=err)
        _, status, usage = os.wait4(process.pid, 0)
    wall = time.perf_counter() - start
    cpu = usage.ru_utime + usage.ru_stime  # the child's CPU time (user + system), its waited-for children's too
    while True:  # the processes it left behind, reparented here
        try:
            _, _, left = os.wait4(-1, 0)
        except ChildProcessError:
            break
        cpu += left.ru_utime + left.ru_stime
    run_child.cpu_seconds = cpu
    process.returncode = os.waitstatus_to_exitcode(status)
    texts = out_file.read_text(), err_file.read_text()
    out_file.unlink()
    err_file.unlink()
    return wall, usage.ru_maxrss * 1024.0, texts[0], texts[1], process.returncode


def _become_subreaper() -> None:
    """Have the processes a command leaves behind reparented to this one (Linux ``PR_SET_CHILD_SUBREAPER``)."""
    import ctypes

    ctypes.CDLL(None, use_errno=True).prctl(36, 1)  # PR_SET_CHILD_SUBREAPER


# --- the cases ---------------------------------------------------------------------------------------


def simulated_case(folder: Path, spacing: float, seed: int) -> Path:
    """A full-frame case from ``emreg simulate`` (reused when already there)."""
    if not (folder / "truth.json").is_file():
        print(f"simulating the full frame at {spacing} mm into {folder} ...", flush=True)
        subprocess.run([PYTHON, "-m", "EMRegModule", "simulate", str(folder), "--seed", str(seed), "--spacing",
                        str(spacing), "--quiet"], check=True)
    return folder


def large_case(folder: Path, spacing: float, seed: int, size_mm=(360.0, 360.0, 230.0)) -> Path:
    """A large CT written slab by slab (see module docstring), with ``truth.json`` of its markers."""
    if (folder / "truth.json").is_file():
        return folder
    folder.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    model = MarkerModel()
    size = np.array([int(round(v / spacing)) for v in size_mm])  # i, j, k
    print(f"writing a {size[0]}x{size[1]}x{size[2]} CT ({np.prod(size) / 1e9:.2f} G voxels) into {folder} ...",
          flush=True)
    sigma = 1.0 / 2.3548  # PSF FWHM 1 mm
    air, pom, pvc, noise = -1000.0, 340.0, 1100.0, 20.0
    coords = [np.arange(n) * spacing for n in size]  # mm along i, j, k (origin 0, identity direction)
    block_lo = np.array([15.0, 15.0, 15.0])
    block_hi = np.array(size_mm) - [15.0, 15.0, 55.0]

    def ramp(x: np.ndarray, lo: float, hi: float) -> np.ndarray:
        s = np.sqrt(2) * sigma
        return (0.5 * (special.erf((x - lo) / s) - special.erf((x - hi) / s))).astype(np.float32)

    fractions = [ramp(c, lo, hi) for c, lo, hi in zip(coords, block_lo, block_hi, strict=True)]
    # 28 markers in slots: the bottom cylinder inside the block, the shoulder flush with the face
    markers, patches = [], []
    faces = [("top", 2, +1), ("+x", 0, +1), ("-x", 0, -1), ("+y", 1, +1), ("-y", 1, -1)]
    placed: list[np.ndarray] = []
    while len(markers) < 28:
        name, axis_index, sign = faces[rng.integers(len(faces))]
        normal = np.zeros(3)
        normal[axis_index] = sign
        point = rng.uniform(block_lo + 25, block_hi - 25)
        point[axis_index] = block_hi[axis_index] if sign > 0 else block_lo[axis_index]
        if any(np.linalg.norm(point - p) < 40 for p in placed):
            continue
        placed.append(point)
        origin = point - normal * model.bottom_height_mm
        obj = marker_object(model, origin, normal, pvc, spin_deg=float(rng.uniform(0, 360)))
        markers.append({"label": f"M{len(markers) + 1:02d}", "origin": origin.tolist(), "axis": normal.tolist(),
                        "in_ct": True, "face": name})
        lo_index, patch = _marker_patch(model, obj, spacing, sigma, pvc - pom, pvc - air)
        patches.append((lo_index, patch))
    # bone rods along j above the block (a patient's bones): cortex 1500 HU, marrow 300 HU
    rods = [(rng.uniform(60, size_mm[0] - 60), block_hi[2] + rng.uniform(10, 30), rng.uniform(3, 6))
            for _ in range(6)]
    header = textwrap.dedent(f"""\
        NRRD0004
        type: short
        dimension: 3
        space: left-posterior-superior
        sizes: {size[0]} {size[1]} {size[2]}
        space directions: ({spacing},0,0) (0,{spacing},0) (0,0,{spacing})
        kinds: domain domain domain
        endian: little
        encoding: gzip
        space origin: (0,0,0)

        """)
    path = folder / "ct.nrrd"
    tmp = folder / ".ct-tmp.nrrd"
    compressor = zlib.compressobj(1, zlib.DEFLATED, 31)
    noise_rng = np.random.default_rng(seed + 1)
    with tmp.open("wb") as f:
        f.write(header.encode("ascii"))
        slab_size = 16
        for k0 in range(0, size[2], slab_size):
            k1 = min(k0 + slab_size, size[2])
            f_k = fractions[2][k0:k1]
            slab = air + (pom - air) * (f_k[:, None, None] * fractions[1][None, :, None] * fractions[0][None, None, :])
            for x_c, z_c, radius in rods:
                z = coords[2][k0:k1][:, None]
                x = coords[0][None, :]
                r = np.sqrt((x - x_c) ** 2 + (z - z_c) ** 2)
                cortex = 0.5 * special.erfc((r - radius) / (np.sqrt(2) * sigma))
                marrow = 0.5 * special.erfc((r - radius + 1.2) / (np.sqrt(2) * sigma))
                j_in = ramp(coords[1], 40.0, size_mm[1] - 40.0)
                add = ((1500 - air) * cortex + (300 - 1500) * marrow).astype(np.float32)
                slab += add[:, None, :] * j_in[None, :, None]
            for lo_index, patch in patches:
                a, b = max(k0, lo_index[2]), min(k1, lo_index[2] + patch.shape[2])
                if a >= b:
                    continue
                (i0, j0), n = lo_index[:2], patch.shape[1]
                ia, ib = max(i0, 0), min(i0 + n, size[0])
                ja, jb = max(j0, 0), min(j0 + n, size[1])
                slab[a - k0:b - k0, ja:jb, ia:ib] += patch[a - lo_index[2]:b - lo_index[2], ja - j0:jb - j0,
                                                           ia - i0:ib - i0]
            slab += noise_rng.standard_normal(slab.shape, dtype=np.float32) * noise
            f.write(compressor.compress(np.clip(np.rint(slab), -1024, 3071).astype("<i2").tobytes()))
        f.write(compressor.flush())
    tmp.replace(path)
    truth = {"image": {"size": size.tolist(), "spacing": [spacing] * 3}, "markers": markers, "decoys": []}
    (folder / "truth.json").write_text(json.dumps(truth, indent=1))
    return folder


def _marker_patch(model, obj, spacing: float, sigma: float, contrast_bottom: float,
                  contrast_top: float) -> tuple[np.ndarray, np.ndarray]:
    """A marker's contribution over what it displaces (i, j, k block and its first index), blurred by the PSF.

    The bottom cylinder displaces plastic (it fills its slot), the top cylinder air; both
    contributions are linear, so blurring them separately is the blurred composite.
    """
    half = 16.0
    centre = obj.object_to_image[:3, 3] + obj.object_to_image[:3, 1] * model.height_mm / 2
    lo_index = np.floor((centre - half) / spacing).astype(int)
    n = int(np.ceil(2 * half / spacing))
    grid = Grid((n, n, n), np.full(3, spacing), lo_index * spacing, np.eye(3))
    h_b, height = model.bottom_height_mm, model.height_mm
    bottom = CylinderY(model.bottom_diameter_mm / 2, 0.0, h_b)
    top = Difference(CylinderY(model.top_diameter_mm / 2, h_b, height),
                     [CylinderY(model.pinhole_diameter_mm / 2, model.pinhole_bottom_mm, height + 1.0)])
    patch = np.zeros((n, n, n), dtype=np.float32)  # indexed (k, j, i)
    for solid, contrast in ((bottom, contrast_bottom), (top, contrast_top)):
        occupancy = np.zeros((n, n, n), dtype=np.float32)  # painting 1 over 0 leaves the fill fraction
        paint_layers(occupancy, grid, np.eye(4), [Layer("marker part", Posed(solid, obj.object_to_image), 1.0, 5)])
        patch += contrast * ndimage.gaussian_filter(occupancy, sigma / spacing)
    return lo_index, patch


# --- the measurements ----------------------------------------------------------------------------------

READ_ONLY = """
import sys, time, SimpleITK as sitk
t = time.perf_counter(); image = sitk.ReadImage(sys.argv[1]); t = time.perf_counter() - t
n = image.GetNumberOfPixels()
print(f"read {t:.4f} size {n} bytes {n * image.GetSizeOfPixelComponent()}")
"""

DICOM_READ_ONLY = """
import sys, time, SimpleITK as sitk
t = time.perf_counter()
files = sitk.ImageSeriesReader.GetGDCMSeriesFileNames(sys.argv[1])
reader = sitk.ImageSeriesReader()
reader.SetFileNames(files)
image = reader.Execute()
t = time.perf_counter() - t
n = image.GetNumberOfPixels()
print(f"read {t:.4f} size {n} bytes {n * image.GetSizeOfPixelComponent()}")
"""

SITK_PIPELINE = """
import sys, time, SimpleITK as sitk
t0 = time.perf_counter(); image = sitk.ReadImage(sys.argv[1]); t1 = time.perf_counter()
mask = sitk.BinaryThreshold(image, float(sys.argv[2]), float(sys.argv[3]), 1, 0)
del image
opened = sitk.BinaryMorphologicalOpening(mask, [1, 1, 1], sitk.sitkBall, 0, 1)
del mask
labels = sitk.ConnectedComponent(opened)
del opened
stats = sitk.LabelShapeStatisticsImageFilter()
stats.ComputePerimeterOff()
stats.ComputeFeretDiameterOff()
stats.ComputeOrientedBoundingBoxOff()
stats.Execute(labels)
centroids = [stats.GetCentroid(label) for label in stats.GetLabels()]
t2 = time.perf_counter()
print(f"read {t1 - t0:.4f} pipeline {t2 - t1:.4f} components {len(centroids)}")
"""


def pose_timing(ct: Path) -> tuple[float, int]:
    """Time ``fit_pose`` for every marker the detection keeps (in this process, one thread)."""
    from EMRegModule.core.detection import detect as detect_module
    from EMRegModule.core.detection import detect_markers
    from EMRegModule.io.image import read_ct
    from EMRegModule.marker_model import MarkerModel

    image = read_ct(ct)
    calls: list[float] = []
    original = detect_module.fit_pose

    def timed(*args, **kwargs):
        start = time.perf_counter()
        result = original(*args, **kwargs)
        calls.append((time.perf_counter() - start, result.fit_rms_mm))
        return result

    workers = detect_module._workers
    detect_module.fit_pose = timed
    detect_module._workers = lambda: 1  # one thread: each pose's own time
    try:
        result = detect_markers(image, MarkerModel())
    finally:
        detect_module.fit_pose = original
        detect_module._workers = workers
    kept = {round(float(m.fit_rms_mm), 6) for m in result.markers}
    total = sum(t for t, rms in calls if round(float(rms), 6) in kept)
    return total, len(result.markers)


def accuracy(markers_json: Path, truth_json: Path) -> str:
    from EMRegModule.core.transforms import angle_between_deg

    truth = json.loads(truth_json.read_text())
    found = json.loads(markers_json.read_text())["markers"]
    present = [m for m in truth["markers"] if m.get("in_ct", True)]
    origins = np.array([m["origin"] for m in present])
    errors, angles, false = [], [], 0
    for m in found:
        d = np.linalg.norm(origins - m["origin"], axis=1)
        j = int(np.argmin(d))
        if d[j] > 2:
            false += 1
            continue
        errors.append(d[j])
        angles.append(float(angle_between_deg(m["axis"], present[j]["axis"])))
    errors, angles = np.array(errors), np.array(angles)
    return (f"{len(errors)}/{len(present)} markers found, {false} false; origin error median {np.median(errors):.3f} "
            f"max {errors.max():.3f} mm; axis error median {np.median(angles):.2f} max {angles.max():.2f} deg")


def jpeg_lossless_copy(source: Path, target: Path) -> Path:
    """``source``'s DICOM files re-encoded as JPEG lossless by ``gdcmconv`` (reused when already there)."""
    if (target / ".complete").is_file():
        return target
    target.mkdir(parents=True, exist_ok=True)
    print(f"re-encoding {source} as JPEG lossless into {target} ...", flush=True)
    for path in sorted(source.iterdir()):
        subprocess.run(["gdcmconv", "--jpeg", str(path), str(target / path.name)], check=True)
    (target / ".complete").write_text("")
    return target


def dicom_main(args: argparse.Namespace) -> None:
    """``emreg detect`` on DICOM series against ``SimpleITK.ImageSeriesReader`` (see module docstring)."""
    work = Path(args.work)
    case = work / "hard-dicom"
    if not (case / "truth.json").is_file():
        print(f"simulating the hard full frame (DICOM, 0.5 x 0.5 x 0.8 mm) into {case} ...", flush=True)
        subprocess.run([PYTHON, "-m", "EMRegModule", "simulate", str(case), "--seed", str(args.seed), "--difficulty",
                        "hard", "--quiet"], check=True)
    folders = {"uncompressed": case / "ct", "JPEG lossless": jpeg_lossless_copy(case / "ct", work / "hard-dicom-jpl")}
    results = {}
    for name, folder in folders.items():
        run_child([PYTHON, "-c", DICOM_READ_ONLY, str(folder)])  # warm the page cache
        reads, read_cpu = [], []
        for _ in range(args.repeat):
            reads.append(run_child([PYTHON, "-c", DICOM_READ_ONLY, str(folder)]))
            read_cpu.append(run_child.cpu_seconds)
        t_read = float(np.median([float(re.search(r"read (\S+)", r[2]).group(1)) for r in reads]))
        t_read_process = float(np.median([r[0] for r in reads]))
        out_dir = work / f"out-dicom-{name.split()[0].lower()}"
        detects, detect_cpu = [], []
        for _ in range(args.repeat):
            detects.append(run_child([PYTHON, "-m", "EMRegModule", "detect", str(folder), "--out", str(out_dir)]))
            detect_cpu.append(run_child.cpu_seconds)
        for _, _, _, err, code in detects:
            if code != 0:
                sys.exit(f"emreg detect failed ({code}): {err.strip()}")
        t_detect, peak, _, err, _ = sorted(detects, key=lambda r: r[0])[len(detects) // 2]
        steps = dict(re.findall(r"\[emreg\] (.+?) done in (\S+)s", err))
        results[name] = json.loads((out_dir / "markers.json").read_text())
        goal = 1.2 if name == "uncompressed" else 1.0
        print(f"\nDICOM {name}: {folder} ({len(list(folder.glob('*.dcm')))} files)")
        print(f"  (a) emreg detect, end to end (median of {args.repeat})     {t_detect:8.2f} s   peak RSS "
              f"{peak / 1e9:5.2f} GB")
        print("      its steps: " + ", ".join(f"{k} {float(v):.2f} s" for k, v in steps.items()))
        print(f"  (c) SimpleITK ImageSeriesReader (file names + Execute)  {t_read:8.2f} s   "
              f"(its whole process {t_read_process:.2f} s)")
        print(f"  a/c = {t_detect / t_read:.2f} (goal <= {goal}); a / c's whole process = "
              f"{t_detect / t_read_process:.2f}")
        print(f"  CPU time (user + system, median): emreg detect {np.median(detect_cpu):.2f} s, the reader's process "
              f"{np.median(read_cpu):.2f} s (on a busy machine the wall times follow the CPU each gets)")
        print(f"  accuracy: {accuracy(out_dir / 'markers.json', case / 'truth.json')}")
    origins = [np.array([m["origin"] for m in document["markers"]]) for document in results.values()]
    same = origins[0].shape == origins[1].shape and np.allclose(origins[0], origins[1], atol=1e-6)
    print(f"\nsame markers from both folders: {'yes' if same else 'NO'}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--spacing", type=float, default=0.6, help="voxel size (mm): 0.6 simulated, 0.3 generated")
    parser.add_argument("--work", default="/tmp/emreg-bench-detect", help="folder for the cases (kept for reuse)")
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--skip-baseline", action="store_true", help="skip (b), the SimpleITK pipeline")
    parser.add_argument("--repeat", type=int, default=3, help="runs of (a) and (c); their medians are reported")
    parser.add_argument("--dicom", action="store_true", help="DICOM series (uncompressed, JPEG lossless) instead")
    args = parser.parse_args()
    if args.dicom:
        dicom_main(args)
        return
    work = Path(args.work)
    if args.spacing >= 0.5:
        case = simulated_case(work / f"sim-{args.spacing:g}", args.spacing, args.seed)
    else:
        case = large_case(work / f"large-{args.spacing:g}", args.spacing, args.seed)
    ct = case / "ct.nrrd"
    env_python = [PYTHON, "-c"]

    run_child(env_python + [READ_ONLY, str(ct)])  # warm the page cache: every task reads from memory
    reads = [run_child(env_python + [READ_ONLY, str(ct)]) for _ in range(args.repeat)]
    _, read_peak, out, _, _ = reads[0]
    t_read = float(np.median([float(re.search(r"read (\S+)", r[2]).group(1)) for r in reads]))
    volume_bytes = int(re.search(r"bytes (\d+)", out).group(1))
    voxels = int(re.search(r"size (\d+)", out).group(1))

    out_dir = work / f"out-{args.spacing:g}"
    detects = [run_child([PYTHON, "-m", "EMRegModule", "detect", str(case), "--out", str(out_dir)])
               for _ in range(args.repeat)]
    for _, _, _, err, code in detects:
        if code != 0:
            sys.exit(f"emreg detect failed ({code}): {err.strip()}")
    t_detect, detect_peak, out, err, code = sorted(detects, key=lambda r: r[0])[len(detects) // 2]  # the median run
    steps = dict(re.findall(r"\[emreg\] (.+?) done in (\S+)s", err))

    t_pipeline = t_pipeline_read = pipeline_peak = float("nan")
    if not args.skip_baseline:
        _, pipeline_peak, out, err, code = run_child(env_python + [SITK_PIPELINE, str(ct), "600", "1800"])
        if code != 0:
            sys.exit(f"SimpleITK pipeline failed ({code}): {err.strip()[-500:]}")
        t_pipeline = float(re.search(r"pipeline (\S+)", out).group(1))
        t_pipeline_read = float(re.search(r"read (\S+)", out).group(1))
    t_pose, n_posed = pose_timing(ct)

    t_inside = sum(float(v) for v in steps.values())  # every step reads the CT or detects
    b_total = t_pipeline + t_pipeline_read
    print(f"\nCT {ct} : {voxels / 1e6:.0f} M voxels, {volume_bytes / 1e9:.2f} GB in memory, "
          f"{ct.stat().st_size / 1e9:.2f} GB on disk, spacing {args.spacing} mm")
    print(f"  (a) emreg detect, end to end (median of {args.repeat})       {t_detect:8.2f} s   peak RSS "
          f"{detect_peak / 1e9:5.2f} GB")
    print("      its steps: " + ", ".join(f"{k} {float(v):.2f} s" for k, v in steps.items())
          + f"; the rest (interpreter, imports, writing) {t_detect - t_inside:.2f} s")
    print(f"  (b) SimpleITK pipeline: read {t_pipeline_read:.2f} s + filters {t_pipeline:.2f} s = {b_total:8.2f} s"
          f"   peak RSS {pipeline_peak / 1e9:5.2f} GB")
    print(f"  (c) SimpleITK ReadImage                              {t_read:8.2f} s   peak RSS "
          f"{read_peak / 1e9:5.2f} GB")
    print(f"  a/b = {t_detect / b_total:.3f} against the whole pipeline from the file, "
          f"{t_detect / t_pipeline:.3f} against its filters alone  (goal <= 0.15)")
    print(f"  a/c = {t_detect / t_read:.2f}; reading + detection inside emreg / c = {t_inside / t_read:.2f}"
          "  (goal <= 2.5)")
    print(f"  peak memory of (a) / volume bytes = {detect_peak / volume_bytes:.2f}  (goal < 1.5)")
    print(f"  posing {n_posed} markers: {t_pose:.3f} s ({1e3 * t_pose / max(1, n_posed):.1f} ms each)")
    print(f"  accuracy: {accuracy(out_dir / 'markers.json', case / 'truth.json')}")


if __name__ == "__main__":
    main()
