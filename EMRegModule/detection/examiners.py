"""Where detection examines its candidate regions: threads of this process, and a forked process beside them when
the volume is memory that such a process sees as it is written (a CT read by a reading process:
:attr:`~EMRegModule.io.ct_handle.CTHandle.shared`).

Examining a region (segmentation, measures, pose fits) is numpy, scipy.ndimage and VTK between lines of Python:
two threads at it share the interpreter's lock and use some 1.45 of 2 cores, while a process of its own takes a
core whole. The regions' outcomes do not depend on where they were examined (the caller collects them in region
order). The forked examiner is made before this pool's threads exist, from a process whose other threads (a
reading process's follower) it never needs; it ignores SIGINT / SIGTERM (the command stops it).
"""

from __future__ import annotations

import contextlib
import os
import signal
import warnings
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor
from typing import Any

import numpy as np

from ..interrupts import die_with_parent, signals_held

_VOLUME: list[np.ndarray] = []
"""The volume of the forked examiner: set before the fork, inherited by it (never pickled)."""


def _on_volume(function: Callable[..., Any], *args: Any) -> Any:
    return function(_VOLUME[0], *args)


def _start_examiner(parent: int) -> None:
    """The forked examiner's start: SIGINT / SIGTERM ignored (the command stops it), killed when the command dies."""
    for number in (signal.SIGINT, signal.SIGTERM):
        signal.signal(number, signal.SIG_IGN)
    die_with_parent(parent)


def _forked_examiner(volume: np.ndarray) -> Any:
    """A pool of one forked process examining ``volume`` (a ``ProcessPoolExecutor``), forked now; None when the
    system refuses a process (too many, too little memory): the threads then examine every region."""
    import multiprocessing
    from concurrent.futures import BrokenExecutor, ProcessPoolExecutor

    _VOLUME[:] = [volume]
    pool = ProcessPoolExecutor(1, mp_context=multiprocessing.get_context("fork"), initializer=_start_examiner,
                               initargs=(os.getpid(),))
    try:
        with warnings.catch_warnings():  # Python 3.12 warns of a fork beside other threads (see above)
            warnings.simplefilter("ignore", DeprecationWarning)
            pool.submit(int).result()  # the fork, now: before the caller's threads exist
    except (OSError, BrokenExecutor):
        pool.shutdown(wait=False, cancel_futures=True)
        _VOLUME.clear()
        return None
    return pool


class Examiners:
    """``workers`` examiners of ``volume``'s regions: with ``fork``, one is a forked process, the others threads.

    :meth:`submit` runs ``function(volume, *args)`` (``function`` a module-level function and ``args`` picklable,
    for the process) on the examiner with the fewest outstanding regions per worker.
    """

    def __init__(self, volume: np.ndarray, workers: int, fork: bool = False) -> None:
        self._volume = volume
        self._process = None
        if fork and workers >= 2:
            self._process = _forked_examiner(volume)
            workers -= 1 if self._process is not None else 0
        self._threads = ThreadPoolExecutor(max_workers=workers)
        self._thread_count = workers
        self._outstanding: dict[str, list[Future]] = {"process": [], "threads": []}

    @property
    def forked(self) -> bool:
        """Whether one examiner is a forked process."""
        return self._process is not None

    def submit(self, function: Callable[..., Any], *args: Any) -> Future:
        for futures in self._outstanding.values():
            futures[:] = [f for f in futures if not f.done()]
        busy_process = len(self._outstanding["process"])
        busy_threads = len(self._outstanding["threads"]) / self._thread_count
        if self._process is not None and busy_process <= busy_threads:
            future = self._process.submit(_on_volume, function, *args)
            self._outstanding["process"].append(future)
        else:
            future = self._threads.submit(function, self._volume, *args)
            self._outstanding["threads"].append(future)
        return future

    def shutdown(self, cancel: bool = False) -> None:
        """End the examiners once the regions they are examining are done (they read the volume, which the caller
        may let go of next); ``cancel``: drop those not started (detection failed, e.g. the CT turned out
        truncated)."""
        # SIGINT / SIGTERM held meanwhile (delivered right after): the workers' thread objects are let go here, and
        # a signal whose exception is raised in their weak references' callbacks is lost ("Exception ignored" and
        # a traceback, the command going on)
        with signals_held():
            self._threads.shutdown(cancel_futures=cancel)
            if self._process is not None:
                with contextlib.suppress(Exception):  # a process already gone (killed) has nothing left to end
                    self._process.shutdown(cancel_futures=cancel)
                _VOLUME.clear()

    def __enter__(self) -> Examiners:
        return self

    def __exit__(self, kind: type[BaseException] | None, *_: object) -> None:
        self.shutdown(cancel=kind is not None)
