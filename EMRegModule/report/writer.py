"""``write_report``: read a run's outputs, check them, render the figures, write the page atomically.

The CT starts being read first (in the background); the figures that do not need it are
rendered meanwhile; the 3D view's context surface is binned from the CT as its slices arrive.
"""

from __future__ import annotations

import contextlib
import ctypes
import os
from collections.abc import Iterator
from pathlib import Path
from typing import TYPE_CHECKING

from ..errors import EMRegError
from ..interrupts import vtk_imports_uninterrupted
from ..io.atomic import atomic_write_bytes, atomic_write_text
from ..io.ct_handle import CTHandle
from ..names import REPORT_FIGURES, REPORT_HTML
from ..progress import QUIET, Progress
from .checks import collect_warnings
from .ct_memo import carry_forward, memo_path, recorded_ct_sha256, save_ct_memo
from .derived import calibration_points, marker_rows, report_fre_curve
from .figures import FIGURE_NAMES, ReportData, prepare_ct_products, render_figures
from .inputs import ReportInputs, load_report_inputs
from .sections import build_html

if TYPE_CHECKING:
    import SimpleITK as sitk

    from ..settings import Settings


def write_report(out_dir: str | os.PathLike[str], case_dir: str | os.PathLike[str] | None = None,
                 progress: Progress | None = None, image: sitk.Image | None = None) -> Path:
    """Render ``OUT/report.html`` (see :func:`write_report_keeping_ct`); returns the path of the page.
    A CT read here is streamed (never whole in memory)."""
    return write_report_keeping_ct(out_dir, case_dir, progress, image, keep_ct=False)[0]


def write_report_keeping_ct(out_dir: str | os.PathLike[str], case_dir: str | os.PathLike[str] | None = None,
                            progress: Progress | None = None, image: sitk.Image | CTHandle | None = None,
                            keep_ct: bool = True, settings: Settings | None = None) -> tuple[Path, sitk.Image | None]:
    """Render ``OUT/report.html`` (and ``OUT/report_figures/*.png``) from what the run left in OUT.

    ``case_dir`` is the case folder (for the CT and targets); by default the one recorded in
    ``OUT/run.json``. ``image``: the case's CT already in memory (``SimpleITK.Image``), which spares
    reading it again; handed over as a :class:`~EMRegModule.io.ct_handle.CTHandle` read in full (``is_complete``),
    the report lets it go as soon as it has used it (the caller keeps no other reference); a handle still being
    read is the report's CT when it is the case's (a streamed read started earlier). Returns the path
    of the page and the CT the report used (None without one, or
    when it could not be read), so that the caller can reuse it (the 3D Slicer bundle). ``keep_ct=False``:
    the caller does not need the CT, so a CT read here is streamed and never whole in memory (None is
    returned for it). ``settings``: those to report with (by default the case's ``case.toml``). Raises
    :class:`EMRegError` when OUT holds nothing to report.
    """
    with _one_blas_thread():
        return _write_report(out_dir, case_dir, progress or QUIET, image, keep_ct, settings)


def _use_and_release_ct(data: ReportData) -> None:
    """Take from a handed CT what the figures need, then let it go (its geometry stays)."""
    prepare_ct_products(data)
    if data.marker_views is not None:
        data.marker_views.release()
    if data.inputs.ct is not None:
        data.inputs.ct.release()


@contextlib.contextmanager
def _one_blas_thread() -> Iterator[None]:
    """numpy's OpenBLAS on one thread while the report renders, then as it was.

    The report's matrix products are small (points of N x 3 by 3 x 3 matrices), where OpenBLAS's
    thread pool is slower than one thread (measured 7x for the marker planes' points) and its
    spinning threads take the second core from the CT's read and the bundle's process. Where
    numpy's BLAS is not the OpenBLAS it ships with, nothing changes.
    """
    calls = _openblas_thread_calls()
    before = calls[0]() if calls else None
    if calls:
        calls[1](1)
    try:
        yield
    finally:
        if calls and before:
            calls[1](before)


def _openblas_thread_calls() -> tuple | None:
    """(get, set) of the number of threads of the OpenBLAS numpy loaded, or None."""
    try:
        with open("/proc/self/maps", encoding="utf-8", errors="replace") as maps:
            paths = sorted({line.split()[-1] for line in maps if "scipy_openblas" in line and "numpy" in line})
        library = ctypes.CDLL(paths[0]) if paths else None
    except (OSError, IndexError):
        return None
    for suffix in ("64_", ""):
        get = getattr(library, f"scipy_openblas_get_num_threads{suffix}", None)
        put = getattr(library, f"scipy_openblas_set_num_threads{suffix}", None)
        if get is not None and put is not None:
            get.restype, put.argtypes = ctypes.c_int, [ctypes.c_int]
            return get, put
    return None


def _check_run_ct(inputs: ReportInputs) -> str | None:
    """Refuse a report over a CT file that is not the one the run used (replaced since): its slices would be
    drawn under the markers found in the other. Its sha256, computed as the report read (or hashed) it, against
    the one ``run.json`` records; returns that sha256 once checked. Nothing to check (None) for a CT handed over
    in memory (the run's own), not read, or whose read failed (said where the CT is used)."""
    recorded = ((((inputs.run or {}).get("inputs") or {}).get("ct")) or {}).get("sha256")
    digest = getattr(inputs.ct, "sha256", None) if inputs.ct is not None else None
    if not recorded or digest is None:
        return None
    try:
        actual = digest.result()
    except Exception:  # noqa: BLE001 - a read that failed is said where the CT is used
        return None
    if actual != recorded:
        raise EMRegError(f"{inputs.ct_path}: not the CT this run used (its sha256 differs from the one "
                         f"{inputs.out_dir / 'run.json'} records): the report would show another scan under the "
                         "markers; give the run's CT with --case, or run again")
    return actual


def _keep_ct_products(data: ReportData, checked_sha256: str | None, handed: bool) -> None:
    """Keep what the figures took from the CT for the next report of this run (:mod:`.ct_memo`), when they
    were made from the bytes ``run.json`` records for this CT file: a CT whose sha256 :func:`_check_run_ct` checked
    (``checked_sha256``; read, or hashed with its products kept but for the surface), or the CT this very run read
    and handed over in memory."""
    inputs = data.inputs
    if data.binned is None or inputs.ct is None:
        return
    if data.kept_whole:
        carry_forward(inputs.ct.memo, inputs.out_dir)
        return
    recorded = recorded_ct_sha256(inputs.run, inputs.ct_path)
    if recorded is None or (checked_sha256 != recorded and not handed):
        return
    views = data.marker_views.views() if data.marker_views is not None else None
    save_ct_memo(memo_path(inputs.out_dir), recorded, inputs.model, inputs.ct.geometry, data.binned, views,
                 [r.marker_to_image for r in data.rows], data.surface, inputs.settings.report.iso_value)


def _write_report(out_dir: str | os.PathLike[str], case_dir: str | os.PathLike[str] | None, progress: Progress,
                  image: sitk.Image | CTHandle | None, keep_ct: bool,
                  settings: Settings | None = None) -> tuple[Path, sitk.Image | None]:
    vtk_imports_uninterrupted()  # the figures load VTK's modules (pyvista) as they go
    handed = isinstance(image, CTHandle) and image.is_complete
    inputs = load_report_inputs(out_dir, case_dir, image=image, keep_ct=keep_ct, settings=settings)
    del image  # held by ``inputs.ct`` alone (a handed CT is let go below)
    try:
        rows = marker_rows(inputs.detection, inputs.registration)
        points = calibration_points(inputs.frame_calibration)
        curve, stored = report_fre_curve(inputs, rows, points)
    except (KeyError, TypeError, ValueError, ZeroDivisionError) as exc:
        if inputs.ct is not None:
            inputs.ct.cancel()
        raise EMRegError(f"{inputs.out_dir}: an output file does not follow the spec ({exc!s:.120})") from None
    data = ReportData(inputs, rows, points, curve, stored)
    if handed and inputs.ct is not None:
        _use_and_release_ct(data)
    try:
        figures = render_figures(data, progress)
    except BaseException:
        if inputs.ct is not None:
            inputs.ct.cancel()
        raise
    checked = _check_run_ct(inputs)
    data.warnings = collect_warnings(inputs, rows, curve)  # after the figures: a CT that failed to read is a note
    figure_dir = inputs.out_dir / REPORT_FIGURES
    for figure in figures:
        atomic_write_bytes(figure_dir / f"{figure.name}.png", figure.png)
    _keep_ct_products(data, checked, handed)
    produced = {f.name for f in figures}
    for name in FIGURE_NAMES:  # figures of an earlier run that this one did not produce are stale
        if name not in produced:
            (figure_dir / f"{name}.png").unlink(missing_ok=True)
    path = inputs.out_dir / REPORT_HTML
    atomic_write_text(path, build_html(data, figures))
    ct = None
    if inputs.ct is not None and inputs.ct.read_error() is None:
        ct = inputs.ct.result()
    return path, ct
