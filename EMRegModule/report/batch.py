"""Reports for many runs: ``emreg report --batch DIR --jobs N``, within the machine's memory.

Each report holds its case's CT in memory once (plus the rendering libraries), so the number of
reports rendered at the same time is limited by an estimate per case: the CT's voxel bytes
(from its header, no voxels read) times :data:`CT_MEMORY_FACTOR` plus :data:`LIBRARY_BYTES`,
against the memory the system says is available. The limit is said on the terminal, and the
progress bar shows the throughput in cases per minute.
"""

from __future__ import annotations

import multiprocessing
import os
from collections.abc import Sequence
from concurrent.futures import ProcessPoolExecutor, as_completed
from pathlib import Path

from ..errors import EMRegError
from ..io.case import find_ct
from ..io.itk_messages import quiet_itk
from ..io.run_folder import check_outputs, recorded_run
from ..progress import QUIET, Progress
from ..settings import load_settings
from ..slicer_export.bundle import write_run_bundle
from ..slicer_export.mrb import bundle_needs_ct_image
from .inputs import has_report_inputs

#: A scene bundle written by a batch job: its path (None when none could be written) and its message.
BundleResult = tuple[str | None, str, str | None]

#: Peak memory of one report over its CT's bytes (the CT once, its binned copy, the slices).
CT_MEMORY_FACTOR = 1.1
#: Memory of one report process besides its CT: Python, VTK/pyvista, OpenCV, SciPy, the scene.
LIBRARY_BYTES = 450e6
#: Memory a case's 3D Slicer scene bundle adds to its report's process (slicer-core's libraries and the
#: writer's buffers; the CT is the report's own, shared with the volume node, not copied). Measured:
#: +0.33 GB for the 0.6 mm (0.43 GB) and the 0.32 mm (2.8 GB) CT alike.
BUNDLE_BYTES = 350e6
#: Share of the available memory the batch may plan to use.
MEMORY_SHARE = 0.85


def available_memory_bytes() -> float | None:
    """``MemAvailable`` of ``/proc/meminfo`` (bytes), or None where the system does not say."""
    try:
        with open("/proc/meminfo", encoding="ascii") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return float(line.split()[1]) * 1024.0
    except OSError:
        return None
    return None


def ct_bytes_of_run(folder: Path) -> float:
    """Voxel bytes of the CT a run's report will read (from the CT's header), 0 when unknown."""
    import SimpleITK as sitk

    try:
        run = recorded_run(folder) or {}
        ct = Path(run["ct"]) if run.get("ct") else find_ct(run["case"])
        if ct is None or ct.is_dir():  # a DICOM series: no single header to ask
            return 0.0
        reader = sitk.ImageFileReader()
        reader.SetFileName(str(ct))
        with quiet_itk(capture=True):  # a damaged header is said by the report that reads it, not by ITK here
            reader.ReadImageInformation()
    except (EMRegError, OSError, KeyError, TypeError, RuntimeError):
        return 0.0
    size = 1.0
    for n in reader.GetSize():
        size *= n
    pixel = sitk.Image([1] * reader.GetDimension(), reader.GetPixelID(), reader.GetNumberOfComponents())
    return size * pixel.GetNumberOfComponentsPerPixel() * pixel.GetSizeOfPixelComponent()


def memory_limited_jobs(folders: Sequence[str], jobs: int, progress: Progress = QUIET, bundles: bool = False) -> int:
    """``jobs`` lowered so that the largest cases, rendered together, fit in the available memory
    (``bundles``: each job also writes its case's scene bundle, :data:`BUNDLE_BYTES` more)."""
    if jobs <= 1 or len(folders) <= 1:
        return max(1, min(jobs, len(folders)))
    jobs = min(jobs, len(folders))
    available = available_memory_bytes()
    extra = LIBRARY_BYTES + (BUNDLE_BYTES if bundles else 0.0)
    per_case = sorted((CT_MEMORY_FACTOR * ct_bytes_of_run(Path(f)) + extra for f in folders), reverse=True)
    if available is None:
        return jobs
    budget = MEMORY_SHARE * available
    fitting = max(1, next((n - 1 for n in range(1, jobs + 1) if sum(per_case[:n]) > budget), jobs))
    if fitting < jobs:
        progress.message(f"[emreg] report: {fitting} of the {jobs} jobs asked at a time: up to "
                         f"{per_case[0] / 1e9:.1f} GB per case, {available / 1e9:.1f} GB available")
    else:
        progress.message(f"[emreg] report: {jobs} jobs (estimated {sum(per_case[:jobs]) / 1e9:.1f} GB of "
                         f"{available / 1e9:.1f} GB available)")
    return fitting


def _bundle_needs_ct(folder: Path) -> bool:
    """Whether the run's scene bundle needs its CT in memory (not when it copies the CT from its file)."""
    ct = (recorded_run(folder) or {}).get("ct")
    return bundle_needs_ct_image(ct if isinstance(ct, str) else None)


def _batch_worker(folder: str, bundle: bool = False,
                  settings_file: str | None = None) -> tuple[str, str | None, str | None, BundleResult | None]:
    from .writer import write_report_keeping_ct

    try:
        check_outputs(folder)  # outputs of two runs are refused, never reported together
        keep = bundle and _bundle_needs_ct(Path(folder))  # else the CT is streamed, never whole in memory
        settings = load_settings(settings_file, required=True) if settings_file else None  # else each case's
        page, ct = write_report_keeping_ct(Path(folder), keep_ct=keep, settings=settings)
    except EMRegError as exc:
        return folder, None, str(exc), None
    except Exception as exc:  # noqa: BLE001 - one broken folder must not stop the batch; reported below
        return folder, None, f"{type(exc).__name__}: {exc}", None
    written = None
    if bundle:  # with the CT the report holds: not read a second time
        path, message, sha = write_run_bundle(folder, image=ct)
        written = (None if path is None else str(path), message, sha)
    return folder, str(page), None, written


def write_reports_batch(folders: Sequence[str | os.PathLike[str]], jobs: int = 1,
                        progress: Progress | None = None,
                        bundles: list[tuple[str, BundleResult]] | None = None,
                        settings_file: str | os.PathLike[str] | None = None) -> list[Path]:
    """Render a report in every output folder, up to ``jobs`` processes at a time, with a progress bar.

    Folders without any run output are skipped (with a message); ``jobs`` is lowered to what the
    available memory holds (:func:`memory_limited_jobs`). Each report finds its CT through its
    ``run.json``; its outputs are first checked to belong together
    (:func:`~EMRegModule.io.run_folder.check_outputs`: a folder mixing two runs' outputs fails). Returns the written
    pages
    in the order of ``folders``; when a folder fails the others are still rendered, then :class:`EMRegError` lists
    the failures.

    ``bundles``: when a list is given, each job also writes its case's 3D Slicer scene bundle
    (``write_run_bundle``, with the CT its report read) and ``(folder, (bundle path or None, message,
    its sha256 computed as it was written))`` is appended to it for every reported folder, in the order of ``folders``.
    ``settings_file``: the settings every report is made with (``--settings``); by default each case's ``case.toml``.
    """
    settings = str(settings_file) if settings_file else None
    progress = progress or QUIET
    if jobs < 1:
        raise EMRegError(f"report --jobs must be at least 1, got {jobs}")
    selected = []
    for folder in folders:
        if has_report_inputs(folder):
            selected.append(str(folder))
        else:
            progress.message(f"[emreg] report: skipping {folder} (no run outputs in it)")
    jobs = memory_limited_jobs(selected, jobs, progress, bundles=bundles is not None)
    results: dict[str, tuple[str | None, str | None]] = {}
    written: dict[str, BundleResult] = {}
    with progress.step("reports", total=len(selected), per_minute="cases") as step:
        if jobs == 1:
            for folder in selected:
                _, path, error, bundle = _batch_worker(folder, bundles is not None, settings)
                results[folder] = (path, error)
                if bundle is not None:
                    written[folder] = bundle
                step.advance()
        else:
            context = multiprocessing.get_context("spawn")  # VTK/EGL state must not be forked
            with ProcessPoolExecutor(max_workers=jobs, mp_context=context) as pool:
                futures = [pool.submit(_batch_worker, folder, bundles is not None, settings) for folder in selected]
                for future in as_completed(futures):
                    folder, path, error, bundle = future.result()
                    results[folder] = (path, error)
                    if bundle is not None:
                        written[folder] = bundle
                    step.advance()
    if bundles is not None:  # also when other folders failed: these bundles were written
        bundles.extend((folder, written[folder]) for folder in selected if folder in written)
    failures = [f"{folder}: {error}" for folder in selected for path, error in [results[folder]] if error]
    if failures:
        raise EMRegError(f"{len(failures)} of {len(selected)} reports failed: " + "; ".join(failures))
    return [Path(results[folder][0]) for folder in selected]
