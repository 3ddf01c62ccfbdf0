"""``OUT/EMReg.mrb`` of a run: its scene written from the run's outputs (:func:`write_run_bundle`), here or in a
process of its own (:class:`BundleProcess`, the subprocess protocol: arguments OUT, CASE and ``held``; ``go`` on
standard input releases a held child; one JSON line ``{"path", "message", "sha256"}`` on standard output).
"""

from __future__ import annotations

import contextlib
import importlib.util
import json
import os
import signal
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

from ..errors import EMRegError
from ..interrupts import signals_held, vtk_imports_uninterrupted
from ..io.case import run_ct_path
from ..io.run_folder import recorded_run
from ..names import BUNDLE_MRB, VOLUME_NODE_NAME
from .mrb import bundle_needs_ct_image
from .mrml import SlicerScene, slicer_mrml_missing
from .run_scene import build_run_scene, collect_run


def write_run_bundle(out_dir: str | os.PathLike[str], case_dir: str | os.PathLike[str] | None = None,
                            image: Any = None, may_write: Callable[[], bool] | None = None
                            ) -> tuple[Path | None, str, str | None]:
    """Write ``OUT/EMReg.mrb`` from a run's outputs; returns ``(path, message, sha256)``.

    Never raises for a bundle that cannot be made (Slicer's MRML missing, unreadable outputs,
    disk full, no permission): ``path`` is then ``None`` and ``message`` says why; the run's
    other outputs are untouched and a previous bundle is removed only when this one replaces it.
    The sha256 (None without a bundle) is computed as it was written (for ``run.json``: the bundle is not read
    again). ``image``: the CT in memory (a ``SimpleITK.Image``), when the caller holds it.

    ``may_write``: asked (once) before anything in OUT is written or removed; False: nothing is, and the
    message says the bundle was not wanted (a bundle process started ahead of its command's checks)."""
    out = Path(out_dir)
    allowed: list[bool] = []

    def allowed_to_write() -> bool:
        if not allowed:
            allowed.append(may_write is None or may_write())
        return allowed[0]

    unwanted = None, f"no {BUNDLE_MRB} written: not wanted any more", None

    def no_bundle(reason: str) -> tuple[None, str, None]:
        if allowed_to_write():
            _remove_stale_bundle(out)
            return None, f"no {BUNDLE_MRB} written: {reason}", None
        return unwanted

    vtk_imports_uninterrupted()  # the scene's nodes and writers load VTK modules
    missing = slicer_mrml_missing()
    if missing:
        return no_bundle(missing)
    try:
        content = collect_run(out, case_dir, image)
        if not content.marker_ids and not content.calibration_labels and content.robot is None:
            return no_bundle(f"no markers, calibration or robot outputs in {out}")
        with signals_held():  # the modules its logics and nodes load: never cut, the signal acts once they are
            holder = SlicerScene()
            built = build_run_scene(holder.scene, content)
        stored = {built[VOLUME_NODE_NAME].GetID(): content.stored_ct} if content.stored_ct is not None else {}
        if not allowed_to_write():
            return unwanted
        path = holder.write_bundle(out / BUNDLE_MRB, stored)
    except (EMRegError, OSError, KeyError, ValueError, TypeError) as exc:
        return no_bundle(str(exc))
    notes = f" ({'; '.join(content.notes)})" if content.notes else ""
    return path, f"{path}{notes}", holder.bundle_sha256


class BundleProcess:
    """:func:`write_run_bundle` in a process of its own, started by :func:`start_bundle_process` so that it goes
    on while this one renders the report; :meth:`result` waits for it.

    The child imports slicer-core (not this process), writes ``OUT/EMReg.mrb`` atomically and hashes it as it
    writes it (sha256, for ``run.json``). Interrupting this process interrupts the child (no temporary left behind).

    ``held``: the child reads the outputs and builds the scene but writes nothing into OUT until
    :meth:`release` (its command has checked OUT and moved the stale bundle aside); a child never released (its
    command failed, or :meth:`cancel`) writes nothing. So the bundle's imports can start with the command,
    on a core its own start-up leaves idle.
    """

    def __init__(self, out_dir: Path, case_dir: Path | None, held: bool = False) -> None:
        package_root = str(Path(__file__).resolve().parents[2])  # the EMRegModule this process runs
        env = {**os.environ, "PYTHONPATH": os.pathsep.join(p for p in (package_root, os.environ.get("PYTHONPATH"))
                                                            if p)}
        command = [sys.executable, "-c", "from EMRegModule.slicer_export.bundle import bundle_child; bundle_child()",
                   str(out_dir), str(case_dir) if case_dir is not None else "", "held" if held else ""]
        self.held = held
        self.process = subprocess.Popen(command, stdin=subprocess.PIPE if held else subprocess.DEVNULL,
                                        stdout=subprocess.PIPE, stderr=subprocess.PIPE, env=env)

    def release(self) -> None:
        """Let a held child write the bundle into OUT (nothing for a child not held)."""
        if self.held and self.process.stdin is not None and not self.process.stdin.closed:
            with contextlib.suppress(OSError):  # a child that died already: result() says why
                self.process.stdin.write(_GO)
                self.process.stdin.flush()  # (closed by result(), which must find it open)

    def result(self) -> tuple[Path | None, str, str | None]:
        """``(path, message, sha256 of the bundle)`` as :func:`write_run_bundle` gives them (path None: no
        bundle, and the message says why)."""

        try:
            stdout, stderr = self.process.communicate()
        except BaseException:
            self.cancel()
            raise
        try:
            answer = json.loads(stdout.decode("utf-8").strip().splitlines()[-1])
            path = Path(answer["path"]) if answer.get("path") else None
            return path, str(answer["message"]), answer.get("sha256")
        except (ValueError, IndexError, KeyError, TypeError):
            detail = stderr.decode("utf-8", "replace").strip().splitlines()
            return None, f"no {BUNDLE_MRB} written: its writer failed ({(detail or ['no output'])[-1][:200]})", None

    def cancel(self) -> None:
        """Interrupt the child (it removes its temporary files) and wait for it."""

        if self.process.stdin is not None and not self.process.stdin.closed:  # never released: it may not write
            with contextlib.suppress(OSError):
                self.process.stdin.close()
        if self.process.poll() is None:
            self.process.send_signal(signal.SIGINT)
            try:
                self.process.wait(timeout=30)
            except subprocess.TimeoutExpired:
                self.process.kill()
                self.process.wait()


def start_bundle_process(out_dir: str | os.PathLike[str], case_dir: str | os.PathLike[str] | None = None,
                         held: bool = False) -> BundleProcess | None:
    """Start writing ``OUT/EMReg.mrb`` in a separate process when it needs nothing from this one: Slicer's MRML
    is there and the run's CT is a file the bundle copies (:func:`~.mrb.stored_voxels`). None otherwise (write it
    with :func:`write_run_bundle`, with the CT in memory if needed). ``held``: see :class:`BundleProcess`."""

    out = Path(out_dir)
    try:  # not imported here: slicer-core's libraries stay out of this process
        if importlib.util.find_spec("slicer") is None:
            return None
    except (ImportError, ValueError):
        return None

    run = recorded_run(out)
    ct = None if run is None else run_ct_path(run, case_dir)
    if not isinstance(ct, str) or bundle_needs_ct_image(ct):
        return None
    return BundleProcess(out, Path(case_dir) if case_dir is not None else None, held)


#: What a held bundle process waits for on its standard input before it writes into OUT.
_GO = b"go\n"


def bundle_child() -> None:
    """The bundle process: ``write_run_bundle(OUT, CASE)``, then one JSON line: path, message, sha256.
    Held (third argument ``held``): nothing is written into OUT before ``go`` arrives on standard input."""

    out, case = sys.argv[1], sys.argv[2] or None
    held = len(sys.argv) > 3 and sys.argv[3] == "held"
    with contextlib.suppress(OSError, AttributeError):
        os.nice(5)  # the report's CT read, which the report waits for, goes first on a busy machine

    def released() -> bool:
        return sys.stdin.buffer.readline() == _GO  # end of input (the command ended or gave up): no

    try:
        path, message, sha = write_run_bundle(out, case, may_write=released if held else None)
    except KeyboardInterrupt:
        sys.exit(130)
    except EMRegError as exc:
        path, message, sha = None, f"no {BUNDLE_MRB} written: {exc}", None
    print(json.dumps({"path": str(path) if path is not None else None, "message": message, "sha256": sha}))


def _remove_stale_bundle(out: Path) -> None:
    """A bundle of an earlier run beside this run's outputs would mislead: remove it (if it is a file)."""
    with contextlib.suppress(OSError):
        (out / BUNDLE_MRB).unlink()
