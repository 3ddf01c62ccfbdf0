"""Imports started on a thread, to overlap a heavy module's import with a CT's read."""

from __future__ import annotations

import contextlib
import gc
import importlib
import sys
import threading

_gc_lock = threading.Lock()
_gc_pauses = 0  # imports running with the cyclic garbage collector paused
_gc_was_enabled = False


def import_in_background(module: str) -> threading.Event:
    """Start importing a heavy module on a thread; a later ``import`` waits for it or finds it done.

    SimpleITK's reader releases the GIL, so importing the detection stage (scipy, VTK) while a
    large CT is read takes its ~0.5 s off the critical path. Import errors surface later, where
    the module is really imported.

    The thread is no daemon: a command that refuses its input at once (a damaged NIfTI header) exits while the
    import may still be inside a C++ extension's initialisation (VTK's, ITK's), and the interpreter ends a daemon
    thread from within that code at exit (SIGSEGV or SIGABRT after the one-line refusal, seen once in 7 runs).
    The exit waits for the import instead (at most its ~0.5 s).

    The cyclic garbage collector is paused during the import (:func:`gc_paused`): scipy's and VTK's modules are
    some 10^5 objects that live as long as the process, which the collector would otherwise walk again and again
    while they are made (42 ms of an ``emreg detect``, all of it holding the GIL the CT's read and the detection
    wait for). A module imported already is not imported again (nor the collector paused). Returns an event set
    once the import and its pause are over (not the thread: a thread object let go in the caller's thread runs a
    weak reference's callback there, where an interrupt's exception is lost).
    """
    done = threading.Event()
    if module in sys.modules:
        done.set()
        return done

    def run() -> None:
        try:
            with contextlib.suppress(Exception), gc_paused():
                importlib.import_module(module)
        finally:
            done.set()

    threading.Thread(target=run, name=f"import {module}").start()  # no daemon: see above
    return done


@contextlib.contextmanager
def gc_paused():
    """Pause the cyclic garbage collector while making objects that live as long as the process (imports).

    When the last pause ends, what exists then is moved out of the collector's generations (``gc.freeze``): the
    modules just imported are never walked, and later collections see only what is made afterwards. Nothing is
    lost: reference counting frees everything as usual; only cycles made meanwhile wait (those among the frozen
    objects until exit). Pauses on several threads nest; the collector's state before the first is restored.
    """
    global _gc_pauses, _gc_was_enabled
    with _gc_lock:
        if _gc_pauses == 0:
            _gc_was_enabled = gc.isenabled()
            gc.disable()
        _gc_pauses += 1
    try:
        yield
    finally:
        with _gc_lock:
            _gc_pauses -= 1
            if _gc_pauses == 0:
                gc.freeze()
                if _gc_was_enabled:
                    gc.enable()
