"""Imports started on a thread, to overlap a heavy module's import with a CT's read."""

from __future__ import annotations

import contextlib


def import_in_background(module: str) -> None:
    """Start importing a heavy module on a thread; a later ``import`` waits for it or finds it done.

    SimpleITK's reader releases the GIL, so importing the detection stage (scipy, VTK) while a
    large CT is read takes its ~0.5 s off the critical path. Import errors surface later, where
    the module is really imported.

    The thread is no daemon: a command that refuses its input at once (a damaged NIfTI header) exits while the
    import may still be inside a C++ extension's initialisation (VTK's, ITK's), and the interpreter ends a daemon
    thread from within that code at exit (SIGSEGV or SIGABRT after the one-line refusal, seen once in 7 runs).
    The exit waits for the import instead (at most its ~0.5 s).
    """
    import importlib
    import threading

    def run() -> None:
        with contextlib.suppress(Exception):
            importlib.import_module(module)

    threading.Thread(target=run, name=f"import {module}").start()  # no daemon: see above
