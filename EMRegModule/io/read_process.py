"""A CT read in a child process, for a caller whose own process is busy meanwhile (``emreg detect``).

A reader's threads share the interpreter's lock with the rest of the process: while the detection stage is
imported (scipy, VTK: ~0.3 s of Python holding it), every slice read waits for it between its system calls, and the
read of a few hundred MB stretches to the import's end. Forked, the reader has an interpreter of its own: the voxels
go into memory shared with this process (:meth:`~EMRegModule.io.ct_handle.CTHandle.in_anonymous_memory`,
``shared``) and what the reader tells its handle (slices in, the sha256, the end or its error) comes back over a
pipe, one JSON line each, where a thread of this process hands it to the real handle.

A reader that read the CT well stays until this process lets go of the handle (or ends), then ends itself: the
last process that maps the voxels gives their pages back to the system, 0.05-0.1 s for a few hundred MB, and that
is then the reader, after the command's end, rather than the command before it (``emreg detect`` on a 300 MB
series: 1.22 -> 1.11 s). It holds nothing else of the command's (its standard streams are /dev/null) and dies
with it.

Only a process with no other thread than the one forking may fork (a lock held by another thread would stay held
in the child for ever): :func:`can_fork_reader` says so, and the caller reads on threads otherwise.
"""

from __future__ import annotations

import contextlib
import json
import os
import signal
import sys
import threading
import weakref
from collections.abc import Callable
from pathlib import Path

import numpy as np

from .. import errors
from ..errors import EMRegError
from ..interrupts import die_with_parent
from .ct_handle import CancelledReadError, CTHandle


def can_fork_reader() -> bool:
    """Whether a reading process may be forked here: Linux (fork without exec is safe there for a process with a
    single thread) and no thread but this one."""
    return sys.platform.startswith("linux") and hasattr(os, "fork") and threading.active_count() == 1


class ReaderSide:
    """What a reading function needs of a :class:`CTHandle` (``voxels``, ``provided``, ``cancelled``, ``announce``,
    ``sha256``, ``finish``), in the reading process: each call becomes a line on the pipe."""

    provided = True
    cancelled = False

    def __init__(self, voxels: np.ndarray, descriptor: int) -> None:
        self.voxels = voxels
        self._descriptor = descriptor
        self.sha256 = _PipedDigest(self)
        self.failed = True  # until the read ends well

    def send(self, *message: object) -> None:
        data = (json.dumps(message) + "\n").encode()
        while data:
            data = data[os.write(self._descriptor, data):]

    def announce(self, slices: int) -> None:
        self.send("slices", int(slices))

    def finish(self, error: BaseException | None = None) -> None:
        self.failed = error is not None
        self.send("end", *([] if error is None else [type(error).__name__, str(error)]))


class _PipedDigest:
    """The reading process's side of :class:`~EMRegModule.io.provenance.Digest`."""

    def __init__(self, side: ReaderSide) -> None:
        self._side = side
        self._done = False

    def set(self, value: str) -> None:
        self._done = True
        self._side.send("sha256", value)

    def fail(self, error: BaseException) -> None:
        self._done = True
        self._side.send("sha256-error", str(error))

    def done(self) -> bool:
        return self._done


def fork_reader(handle: CTHandle, read: Callable[[ReaderSide], None], source: Path,
                error_types: tuple[type[BaseException], ...] = (), holds_voxels: bool = True) -> None:
    """Run ``read`` (a reading function of ``handle``'s voxels, which must be ``shared``) in a forked process.

    ``holds_voxels=False``: ``read`` only hashes the source (the voxels are read elsewhere,
    :meth:`CTHandle.on_files`); its process ends with it rather than staying until the handle is let go.

    ``handle`` then learns what ``read`` tells its :class:`ReaderSide` on a thread of this process;
    :meth:`CTHandle.cancel` kills the reader. An error the reader ends with comes back as its type where that is
    :class:`~EMRegModule.errors.EMRegError` (or a subclass) or one of ``error_types``, with its message; a reader
    that dies (a signal) ends the read with an :class:`EMRegError` naming ``source``. :class:`OSError` when the
    system refuses a process (nothing started).
    """
    voxels = handle.voxels
    parent = os.getpid()
    receive, send = os.pipe()
    held, holding = os.pipe()  # this process's end open while it holds the voxels
    try:
        pid = os.fork()
    except OSError:  # the system refuses a process (EAGAIN, ENOMEM): the caller reads on threads
        for descriptor in (receive, send, held, holding):
            os.close(descriptor)
        raise
    if pid == 0:  # the reading process: it never returns into the caller's code
        code = 0
        try:
            os.close(receive)
            os.close(holding)
            _quiet(parent)
            side = ReaderSide(voxels, send)
            read(side)
            os.close(send)  # the end of the read, for the command
            if holds_voxels and not side.failed:  # keep the voxels until the command lets go of them (docstring)
                os.read(held, 1)
        except BaseException:  # noqa: BLE001 - nothing of the caller's may run in this process
            code = 1
        finally:
            os._exit(code)
    os.close(send)
    os.close(held)
    weakref.finalize(handle, os.close, holding)
    lock = threading.Lock()
    reaped = [False]

    def stop() -> None:
        with lock:
            if not reaped[0]:
                with contextlib.suppress(ProcessLookupError):
                    os.kill(pid, signal.SIGKILL)

    handle.on_cancel = stop
    known = {error.__name__: error for error in error_types}

    def reap() -> int:
        _, status = os.waitpid(pid, 0)
        with lock:
            reaped[0] = True
        return status

    def follow() -> None:
        ended, error, digest_error = False, None, None
        with os.fdopen(receive, "rb") as stream:
            for line in stream:
                kind, *value = json.loads(line)
                if kind == "slices":
                    handle.announce(value[0])
                elif kind == "sha256":
                    handle.sha256.set(value[0])
                elif kind == "sha256-error":
                    digest_error = EMRegError(value[0])
                elif kind == "end":
                    ended, error = True, _error_of(value, known)
        if ended and error is None:  # the reader now waits for the voxels to be let go: reaped when it ends
            threading.Thread(target=reap, name="emreg-read-process-end", daemon=True).start()
        else:
            status = reap()
            if not ended:
                error = CancelledReadError(f"{source}: reading the CT was cancelled") if handle.cancelled else \
                    EMRegError(f"{source}: the process reading the CT ended unexpectedly ({_status_text(status)})")
        if not handle.sha256.done():
            handle.sha256.fail(digest_error or error or EMRegError(f"{source}: the CT's sha256 was not made"))
        handle.finish(error)

    threading.Thread(target=follow, name="emreg-read-process").start()  # no daemon: it reaps a failed reader


def _quiet(parent: int) -> None:
    """The reading process's start: standard input, output and error on /dev/null (a caller reading the command's
    output sees its end when the command ends, not when this process does), SIGINT / SIGTERM as the command takes
    them, killed when the command dies."""
    null = os.open(os.devnull, os.O_RDWR)
    for descriptor in (0, 1, 2):
        os.dup2(null, descriptor)
    os.close(null)
    for number in (signal.SIGINT, signal.SIGTERM):  # Ctrl-C reaches the whole process group: end quietly (the
        if signal.getsignal(number) is not signal.SIG_IGN:  # command says it was interrupted), or not at all
            signal.signal(number, signal.SIG_DFL)  # when the command ignores them
    die_with_parent(parent)


def _error_of(value: list, known: dict[str, type[BaseException]]) -> BaseException | None:
    """The error a reader's ``end`` line names (None for none): its own type where known, else EMRegError."""
    if not value:
        return None
    name, message = value
    kind = known.get(name) or getattr(errors, name, None)
    if isinstance(kind, type) and (issubclass(kind, EMRegError) or name in known):
        return kind(message)
    return EMRegError(f"{message} ({name})" if message else name)


def _status_text(status: int) -> str:
    if os.WIFSIGNALED(status):
        return f"killed by {signal.Signals(os.WTERMSIG(status)).name}"
    return f"exit status {os.WEXITSTATUS(status)}"
