"""Imports started on a thread, to overlap a heavy module's import with a CT's read."""

from __future__ import annotations

import contextlib


def import_in_background(module: str) -> None:
    """Start importing a heavy module on a thread; a later ``import`` waits for it or finds it done.

    SimpleITK's reader releases the GIL, so importing the detection stage (scipy, VTK) while a
    large CT is read takes its ~0.5 s off the critical path. Import errors surface later, where
    the module is really imported.
    """
    import importlib
    import threading

    def run() -> None:
        with contextlib.suppress(Exception):
            importlib.import_module(module)

    threading.Thread(target=run, name=f"import {module}", daemon=True).start()
