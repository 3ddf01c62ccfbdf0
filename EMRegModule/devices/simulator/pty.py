"""A simulated serial device on a pseudo-terminal: the pty and its link, the serving loop, and the faults
both simulated trackers share (stalls; sensor states switched on by ``--fault`` windows or by hand).

The device opens a pty pair (``os.openpty``), puts it in raw mode and serves the master side; any
RS-232 client opens the slave path (e.g. ``/dev/pts/7``) or the ``--link`` symbolic link to it through
the operating system's serial stack, exactly as it would open ``/dev/ttyUSB0``. The device emulations
(:mod:`.trakstar`, :mod:`.aurora`) fill in what the loop does with bytes read and replies due.
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import os
import select
import threading
import time
import tty
from pathlib import Path

from ...errors import EMRegError
from .faults import WINDOW_KINDS, FaultPlan

#: Longest sleep of the serving loop with nothing due (ns): how soon it sees ``stop()``.
IDLE_WAKE_NS = 50_000_000


class PtyDevice:
    """A simulated serial device serving the master side of a pseudo-terminal in raw mode.

    Clients open ``path`` (the slave side) or ``link``, a symbolic link to it. Subclasses call
    ``super().__init__`` (which opens the pty) and implement :meth:`_receive` (bytes from the host) and
    :meth:`_flush_due` (write the replies whose time has come); they may configure the line in
    :meth:`_configure_pty` and act on their own clock in :meth:`_tick`. ``run()`` serves until ``stop()``
    or ``duration_s``; ``start()`` runs it in a thread.
    """

    thread_name = "pty-device"
    duration_s: float | None = None

    def __init__(self, faults: FaultPlan, link: str | os.PathLike[str] | None) -> None:
        self.faults = faults
        self._manual: dict[str, set[int]] = {kind: set() for kind in WINDOW_KINDS}
        self._stall_until_ns = 0
        self._start_ns = time.monotonic_ns()
        self._open_pty(link)

    # -- the pty --------------------------------------------------------------------------------
    def _open_pty(self, link: str | os.PathLike[str] | None) -> None:
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.master_fd, self.slave_fd = os.openpty()
        tty.setraw(self.slave_fd)
        self._configure_pty()
        flags = fcntl.fcntl(self.master_fd, fcntl.F_GETFL)
        fcntl.fcntl(self.master_fd, fcntl.F_SETFL, flags | os.O_NONBLOCK)
        self.path = os.ttyname(self.slave_fd)
        self.link = Path(link) if link else None
        if self.link is not None:
            self._make_link()
        self._closed = False

    def _configure_pty(self) -> None:
        """Line settings beyond raw mode (none by default)."""

    def _make_link(self) -> None:
        assert self.link is not None
        if self.link.is_symlink():
            self.link.unlink()
        elif self.link.exists():
            self._close_fds()
            raise EMRegError(f"--link {self.link}: a file of that name exists and is not a symbolic link; "
                             "choose another path")
        folder = self.link.parent
        if not folder.is_dir():
            self._close_fds()
            raise EMRegError(f"--link {self.link}: the folder {folder} does not exist; make it or choose another path")
        try:
            os.symlink(self.path, self.link)
        except OSError as exc:  # named after the link, never the pty it points to
            self._close_fds()
            raise EMRegError(f"--link {self.link}: cannot make the link ({exc.strerror or exc})") from None

    def _close_fds(self) -> None:
        for fd in (self.master_fd, self.slave_fd):
            with contextlib.suppress(OSError):
                os.close(fd)

    def start(self) -> PtyDevice:
        """Serve in a background thread (daemon; stops with ``stop()``)."""
        self._thread = threading.Thread(target=self.run, name=self.thread_name, daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        """Stop serving, close the pty and remove the link (idempotent)."""
        self._stop.set()
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join(timeout=5.0)
        self.close()

    def __enter__(self) -> PtyDevice:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        self._close_fds()
        if self.link is not None and self.link.is_symlink():
            with contextlib.suppress(OSError):
                self.link.unlink()

    # -- the serving loop -----------------------------------------------------------------------
    def run(self) -> None:
        """Serve until ``stop()`` or ``duration_s`` (or :meth:`_done`)."""
        self._start_ns = time.monotonic_ns()
        deadline = None if self.duration_s is None else self._start_ns + int(self.duration_s * 1e9)
        try:
            while not self._stop.is_set():
                now = time.monotonic_ns()
                if (deadline is not None and now >= deadline) or self._done():
                    break
                self._flush_due(now)
                self._tick(now)
                wake = self._wake_ns(now + IDLE_WAKE_NS)
                if deadline is not None:
                    wake = min(wake, deadline)
                timeout = max(0.0, (wake - time.monotonic_ns()) / 1e9)
                try:
                    readable, _, _ = select.select([self.master_fd], [], [], timeout)
                except (OSError, ValueError):
                    break
                if readable:
                    data = self._read()
                    if data:
                        self._receive(data)
        finally:
            self._stop.set()
            self.close()

    def _read(self) -> bytes:
        try:
            return os.read(self.master_fd, 4096)
        except BlockingIOError:
            return b""
        except OSError as exc:
            if exc.errno == errno.EIO:  # no client has the slave side open
                time.sleep(0.01)
                return b""
            raise

    def _done(self) -> bool:
        """True to end the loop (a limit of the device's own)."""
        return False

    def _tick(self, now: int) -> None:
        """Act on the device's own clock (``now``: ``time.monotonic_ns()``)."""

    def _wake_ns(self, wake: int) -> int:
        """When the loop must look again at the latest (ns, monotonic): ``wake`` or the next reply due."""
        raise NotImplementedError

    def _receive(self, data: bytes) -> None:
        """Bytes the host wrote."""
        raise NotImplementedError

    def _flush_due(self, now: int) -> None:
        """Write the replies due by ``now``."""
        raise NotImplementedError

    def _elapsed_s(self, now_ns: int | None = None) -> float:
        """Seconds since the start (``now_ns``: a ``time.monotonic_ns()``; default now)."""
        return ((now_ns or time.monotonic_ns()) - self._start_ns) / 1e9

    # -- shared faults --------------------------------------------------------------------------
    def stall(self, seconds: float) -> None:
        """Fall silent for ``seconds`` from now (replies wait, measurements due meanwhile are skipped)."""
        self._stall_until_ns = time.monotonic_ns() + int(seconds * 1e9)

    def _stall_active(self, now: int) -> bool:
        f = self.faults
        if now < self._stall_until_ns:
            return True
        if f.stall_every_s > 0 and f.stall_s > 0:
            t = self._elapsed_s(now)
            phase = t % f.stall_every_s
            if t >= f.stall_every_s and phase < f.stall_s:
                self._stall_until_ns = now + int((f.stall_s - phase) * 1e9)
                return True
        return False

    def set_state(self, kind: str, sensor: int, on: bool = True) -> None:
        """Turn a sensor state on or off now (a :data:`~.faults.WINDOW_KINDS` name the device honours:
        trakSTAR unplug, out-of-range, distort; Aurora also missing, partly-out)."""
        (self._manual[kind].add if on else self._manual[kind].discard)(sensor)

    def _active(self, kind: str, sensor: int, t_s: float) -> bool:
        """Whether state ``kind`` holds ``sensor`` at ``t_s`` seconds after the start (by hand or by window)."""
        return sensor in self._manual[kind] or self.faults.active(kind, sensor, t_s)
