"""Where detection examines its candidate regions: threads of this process, and a forked process beside them when
such a process sees the volume as it is written (a CT read by a reading process into shared memory, or indexed
in its files: :attr:`~EMRegModule.io.ct_handle.CTHandle.shared`).

Examining a region (segmentation, measures, pose fits) is numpy, scipy.ndimage and VTK between lines of Python:
two threads at it share the interpreter's lock and use some 1.45 of 2 cores, while a process of its own takes a
core whole. The regions' outcomes do not depend on where they were examined (the caller collects them in region
order). The forked examiner is made before this pool's threads exist, from a process whose other threads (a
reading process's follower) it never needs; it ignores SIGINT / SIGTERM (the command stops it).
"""

from __future__ import annotations

import contextlib
import multiprocessing
import os
import signal
import threading
import warnings
from collections import deque
from collections.abc import Callable
from concurrent.futures import BrokenExecutor, CancelledError, Future, ProcessPoolExecutor, ThreadPoolExecutor, wait
from functools import partial
from typing import Any

import numpy as np

from ...interrupts import die_with_parent, signals_held

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
    for the process) on the first examiner that is free, the process first (it does not share this process's
    interpreter lock): regions wait here, not in one examiner's queue, so that none is left waiting behind a slow
    region (a decoy tried from every start takes ten times a marker's 10 ms) while another examiner is idle.
    """

    def __init__(self, volume: np.ndarray, workers: int, fork: bool = False) -> None:
        self._volume = volume
        self._process = None
        if fork and workers >= 2:
            self._process = _forked_examiner(volume)
            workers -= 1 if self._process is not None else 0
        self._threads = ThreadPoolExecutor(max_workers=workers)
        self._free = {"process": int(self._process is not None), "threads": workers}
        self._waiting: deque[tuple[Future, Callable[..., Any], tuple]] = deque()
        self._lock = threading.Lock()

    @property
    def forked(self) -> bool:
        """Whether one examiner is a forked process."""
        return self._process is not None

    def submit(self, function: Callable[..., Any], *args: Any) -> Future:
        future: Future = Future()
        with self._lock:
            self._waiting.append((future, function, args))
        self._start_waiting()
        return future

    def _start_waiting(self) -> None:
        """Hand waiting regions to the free examiners (here, or where an examiner has just finished one)."""
        while True:
            with self._lock:
                side = next((side for side in ("process", "threads") if self._free[side]), None)
                if side is None or not self._waiting:
                    return
                future, function, args = self._waiting.popleft()
                if not future.set_running_or_notify_cancel():
                    continue  # cancelled while it waited
                self._free[side] -= 1
            try:
                if side == "process":
                    started = self._process.submit(_on_volume, function, *args)
                else:
                    started = self._threads.submit(function, self._volume, *args)
            except BaseException as exc:  # noqa: BLE001 - an examiner shut down or broken: the region's error
                self._finished(side, future, None, exc)
                continue
            started.add_done_callback(partial(self._finished, side, future))

    def _finished(self, side: str, future: Future, started: Future | None, error: BaseException | None = None) -> None:
        with self._lock:
            self._free[side] += 1
        if started is not None:
            error = CancelledError() if started.cancelled() else started.exception()
        if error is None:
            future.set_result(started.result())
        else:
            future.set_exception(error)
        self._start_waiting()

    def shutdown(self, cancel: bool = False) -> None:
        """End the examiners once the regions they are examining are done (they read the volume, which the caller
        may let go of next); ``cancel``: drop those not started (detection failed, e.g. the CT turned out
        truncated), else wait for them all."""
        # SIGINT / SIGTERM held meanwhile (delivered right after): the workers' thread objects are let go here, and
        # a signal whose exception is raised in their weak references' callbacks is lost ("Exception ignored" and
        # a traceback, the command going on)
        with signals_held():
            with self._lock:
                waiting = list(self._waiting)
            for future, _, _ in waiting:
                if cancel:
                    future.cancel()
                else:
                    wait([future])
            self._threads.shutdown(cancel_futures=cancel)
            if self._process is not None:
                with contextlib.suppress(Exception):  # a process already gone (killed) has nothing left to end
                    self._process.shutdown(cancel_futures=cancel)
                _VOLUME.clear()

    def __enter__(self) -> Examiners:
        return self

    def __exit__(self, kind: type[BaseException] | None, *_: object) -> None:
        self.shutdown(cancel=kind is not None)
