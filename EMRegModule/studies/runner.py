"""``emreg study NAME --out DIR``: run a study's tasks on Dask and write its table, rows and figure.

The tasks run on a ``dask.distributed`` cluster: a ``LocalCluster`` of ``workers`` processes by
default, or an existing scheduler (``tcp://HOST:PORT``, whose workers must have EMReg installed).
The frame (simulated case and its detection) is prepared once here and sent to the workers; each
task draws its random numbers from ``SeedSequence([study seed, task index])``, so the results
are identical whatever the number of workers or the order they finish in.

Outputs (written atomically): ``DIR/NAME.json`` (parameters, rows, summary table),
``DIR/NAME.csv`` (one line per row), ``DIR/NAME.png`` (the figure).
"""

from __future__ import annotations

import contextlib
import csv
import io
import json
import os
import zlib
from collections.abc import Iterator, Mapping, Sequence
from pathlib import Path

import numpy as np

from ..errors import EMRegError
from ..io.atomic import atomic_write_json, atomic_write_text
from ..progress import QUIET, Progress
from ..rendering.images import write_png
from .catalog import STUDIES, Study, Summary
from .frame import Frame, prepare_frame


def _run_task(frame: Frame, study_name: str, index: int, params: dict) -> list[dict]:
    """One task on a worker: its rows, each tagged with the task's index."""
    study = STUDIES[study_name]
    rng = np.random.default_rng(np.random.SeedSequence([zlib.crc32(study_name.encode()), index]))
    return [{"task": index, **row} for row in study.run(frame, params, rng)]


@contextlib.contextmanager
def dask_client(scheduler: str | None, workers: int | None) -> Iterator[object]:
    """A ``dask.distributed`` client: to ``scheduler`` when given, else to a new local cluster."""
    try:
        from distributed import Client, LocalCluster  # optional: the 'studies' extra
    except ImportError:
        raise EMRegError("emreg study needs Dask: pip install 'emreg[studies]'") from None
    if scheduler:
        try:
            client = Client(scheduler, timeout="5s")
        except OSError as exc:
            raise EMRegError(f"cannot reach the Dask scheduler {scheduler} ({exc})") from None
        with client:
            yield client
        return
    with _environment_kept(), LocalCluster(n_workers=workers or 2, threads_per_worker=1, processes=True,
                                            dashboard_address=None) as cluster, Client(cluster) as client:
        yield client


@contextlib.contextmanager
def _environment_kept() -> Iterator[None]:
    """``os.environ`` as it was before the block, put back after it: distributed's nanny sets the variables it
    gives its workers (OMP_NUM_THREADS=1, PYTHONHASHSEED, ...) in this process's own environment, where a caller
    that goes on after the study (the Slicer module, a script, a test) would pass them to every process it starts."""
    kept = dict(os.environ)
    try:
        yield
    finally:
        if dict(os.environ) != kept:
            os.environ.clear()
            os.environ.update(kept)


def run_study(name: str, out: Path, quick: bool = False, scheduler: str | None = None, workers: int | None = None,
              case_dir: Path | None = None, work: Path | None = None, seed: int = 1,
              progress: Progress = QUIET, only: Mapping[str, Sequence[str]] | None = None) -> Summary:
    """Run study ``name`` and write its outputs under ``out``; returns the summary. ``only``: run just the tasks
    whose parameters take one of the values given for each key (``{"family": ["clean", "magpylib"]}``); each keeps
    its index in the whole study, so its seed and rows are the ones the whole study gives it."""
    study = STUDIES.get(name)
    if study is None:
        raise EMRegError(f"unknown study {name!r}; studies: {', '.join(STUDIES)}")
    if workers is not None and workers < 1:
        raise EMRegError(f"--workers must be at least 1, got {workers}")
    out = Path(out)
    tasks = selected_tasks(study, quick, only or {})
    rows_by_task: dict[int, list[dict]] = {}
    with dask_client(scheduler, workers) as client:  # first: an unreachable scheduler fails before any work
        from distributed import as_completed

        frame = prepare_frame(Path(work or out / "work"), case_dir, seed, quick, log=progress.message)
        with progress.step(f"study {name}", total=len(tasks)) as step:
            frame_future = client.scatter(frame, broadcast=True)
            futures = [client.submit(_run_task, frame_future, name, i, params, pure=False) for i, params in tasks]
            for future in as_completed(futures):
                rows = future.result()
                if rows:
                    rows_by_task[rows[0]["task"]] = rows
                step.advance()
    rows = [row for i in sorted(rows_by_task) for row in rows_by_task[i]]
    summary = study.summarize(rows)
    _write_outputs(out, study, quick, seed, rows, summary, dict(only or {}))
    return summary


def selected_tasks(study: Study, quick: bool, only: Mapping[str, Sequence[str]]) -> list[tuple[int, dict]]:
    """The tasks of ``study`` (with their index in the whole study) whose parameters take one of the values
    ``only`` gives for each key; all of them when ``only`` is empty. A selection that keeps none is refused."""
    tasks = list(enumerate(study.tasks(quick)))
    kept = [(i, params) for i, params in tasks
            if all(str(params.get(key)) in {str(v) for v in values} for key, values in only.items())]
    if not kept:
        wanted = "; ".join(f"{key}={','.join(map(str, values))}" for key, values in only.items())
        seen = sorted({f"{key}={params[key]}" for _, params in tasks for key in only if key in params})
        raise EMRegError(f"study {study.name}: no task has {wanted} (tasks have "
                         f"{', '.join(seen) or 'none of these keys'})")
    return kept


def _write_outputs(out: Path, study: Study, quick: bool, seed: int, rows: list[dict], summary: Summary,
                   only: dict[str, Sequence[str]]) -> None:
    atomic_write_json(out / f"{study.name}.json", {
        "study": study.name, "title": study.title, "quick": quick, "case_seed": seed,
        **({"only": {key: list(values) for key, values in only.items()}} if only else {}),
        "summary": {"header": summary.header, "rows": summary.rows, "notes": summary.notes}, "rows": rows})
    columns = sorted({key for row in rows for key in row})
    text = io.StringIO()
    writer = csv.DictWriter(text, columns, lineterminator="\n")
    writer.writeheader()
    for row in rows:
        writer.writerow({k: json.dumps(v) if isinstance(v, (list, dict)) else v for k, v in row.items()})
    atomic_write_text(out / f"{study.name}.csv", text.getvalue())
    write_png(out / f"{study.name}.png", summary.figure)


def format_table(summary: Summary) -> str:
    """The summary as a Markdown table (readable as plain text), then its notes."""
    widths = [max(len(h), *(len(r[i]) for r in summary.rows)) if summary.rows else len(h)
              for i, h in enumerate(summary.header)]
    lines = ["| " + " | ".join(h.ljust(w) for h, w in zip(summary.header, widths, strict=True)) + " |",
             "|" + "|".join("-" * (w + 2) for w in widths) + "|"]
    lines += ["| " + " | ".join(c.ljust(w) for c, w in zip(r, widths, strict=True)) + " |" for r in summary.rows]
    return "\n".join(lines + summary.notes)
