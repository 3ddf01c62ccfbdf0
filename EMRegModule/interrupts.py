"""SIGINT / SIGTERM during EMReg's bookkeeping: held back while a manifest and its files must agree, noted so that
an error a signal caused inside VTK is still told from a real failure, and kept out of VTK's lazy module loads.

Lowest layer: every writer (the output folder, the report, the Slicer export) uses it; it uses nothing of EMReg.
"""

from __future__ import annotations

import contextlib
import ctypes
import os
import signal
import threading
from collections.abc import Iterator
from typing import Any


@contextlib.contextmanager
def signals_held(redeliver: bool = True) -> Iterator[list[int]]:
    """Hold SIGINT / SIGTERM back during a short piece of bookkeeping that must not be cut in two (``run.json``
    and the files it lists must agree); yields the list of signals that arrived. On leaving, the handlers are
    restored and, with ``redeliver``, the first held signal is delivered (KeyboardInterrupt / the SIGTERM
    handler's exception). Only Python-level handlers are held (an ignored signal stays ignored); outside the
    main thread nothing is held."""
    pending: list[int] = []
    if threading.current_thread() is not threading.main_thread():
        yield pending
        return

    def hold(signum: int, frame: object) -> None:
        pending.append(signum)

    previous: dict[int, Any] = {}
    try:
        for signum in (signal.SIGINT, signal.SIGTERM):
            handler = signal.getsignal(signum)
            if callable(handler):
                previous[signum] = signal.signal(signum, hold)
        yield pending
    finally:
        for signum, handler in previous.items():
            signal.signal(signum, handler)
        if redeliver and pending:
            signal.raise_signal(pending[0])


#: The signals (names) that asked this process to stop, in order (:func:`note_interrupt`).
_INTERRUPTS: list[str] = []


def note_interrupt(name: str | None) -> None:
    """Record that SIGINT / SIGTERM (``name``) asked the command to stop; None forgets earlier ones (a new command).

    The signal's exception does not always reach the command: raised inside a callback that VTK calls (a
    pyvista filter), VTK logs it and the filter fails with an error of its own. :func:`interrupted_by` then
    still tells that error from a real failure."""
    if name is None:
        _INTERRUPTS.clear()
    else:
        _INTERRUPTS.append(name)


def interrupted_by() -> str | None:
    """The first signal :func:`note_interrupt` recorded since the command began (None: none)."""
    return _INTERRUPTS[0] if _INTERRUPTS else None


def vtk_imports_uninterrupted() -> None:
    """From now on, every VTK extension module loads with SIGINT / SIGTERM held back (:func:`signals_held`) and
    delivered once it is loaded. VTK loads its modules lazily (pyvista's first Plotter, slicer-core's import), and
    an interrupt inside one became an ImportError (a traceback, or a false "slicer-core is not installed") or left
    a half-initialised module that crashed the process (SIGSEGV). Call it where VTK's use begins; idempotent."""
    try:
        import vtkmodules  # the package alone (its loader), not an extension module
    except ImportError:
        return
    loader = getattr(vtkmodules, "VTKLoader", None)
    if loader is None or getattr(loader, "emreg_uninterrupted", False):
        return
    load = loader.exec_module

    def exec_module(self: Any, module: Any) -> None:
        with signals_held():
            load(self, module)

    loader.exec_module = exec_module
    loader.emreg_uninterrupted = True


def die_with_parent(parent: int) -> None:
    """In a forked helper process: have the kernel kill it when its parent (pid ``parent``) dies (Linux
    ``prctl(PR_SET_PDEATHSIG, SIGKILL)``), so that a helper does not go on alone, or wait for work for ever, after
    ``kill -9`` of the command; ends it at once if the parent died before."""
    with contextlib.suppress(Exception):
        ctypes.CDLL(None, use_errno=True).prctl(1, signal.SIGKILL)  # PR_SET_PDEATHSIG
    if os.getppid() != parent:
        os._exit(1)
