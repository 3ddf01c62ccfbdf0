"""An OpenIGTLink server for any number of clients that never lets one client slow the others.

pyigtl's own ``OpenIGTLinkServer`` serves one client from one shared queue with blocking sends, so
a stalled client would stall the tracker loop. This server keeps pyigtl for the message encoding
(TRANSFORM, STATUS, ...) and does the TCP part itself:

- ``send(message)`` packs once and offers the bytes to every client with a non-blocking ``send``
  from the caller's thread (the tracker loop: no queue hop on the latency path); what a client's
  socket cannot take now waits in that client's own queue, flushed by the server thread when the
  socket becomes writable;
- a queued message older than ``STALE_AFTER_S`` is replaced by a newer one of the same type and device
  name (a newer TRANSFORM ``ProbeToImage`` supersedes it); a client whose queue exceeds
  ``max_pending_bytes`` loses its oldest whole queued messages - it is never allowed to block anyone;
- a client that stops reading is *held*: the server measures how far behind each client is - how long
  ago the oldest bytes it has not read yet were handed to its socket, from the bytes still in the
  kernels (our unacknowledged send queue, ``SIOCOUTQ``, and, for a client on this host, its unread
  receive queue through Linux's ``sock_diag``: see :mod:`.tcp_backlog`). More than ``hold_after_s``
  (default ``STALE_AFTER_S``) behind, nothing more is handed to its socket and its queue keeps only the
  newest message of each type and device name; once it has read everything it was handed it gets those
  newest messages and is fed normally again (both moments logged). So a client that stops for 30 s at
  100 Hz reads, when it resumes, the few poses handed to it in the first ``hold_after_s`` of its stall
  (plus one poll interval), then the latest - not 3000. The oldest of those few is as old as the stall:
  a byte the client's kernel has accepted is the client's (a reset does not discard it), so no server
  can bound that age, only how many such poses there are. A client on another host: only a closed
  receive window is visible (Linux clients keep it open while they buffer), so its own buffer may still
  hold a backlog; ``TCP_NOTSENT_LOWAT`` keeps the server's kernel from queueing more than
  ``notsent_lowat`` bytes for it.
  A client is never disconnected for being slow;
- clients that disconnect are dropped; what they send is read and ignored;
- the last STATUS message of each device name is replayed to every new client, so a client that
  connects while the watchdog holds poses back learns why.

Binds 127.0.0.1 unless told otherwise. ``port=0`` picks a free port (see ``.port``).
"""

from __future__ import annotations

import contextlib
import selectors
import socket
import threading
import time
from collections import deque
from typing import TextIO

import numpy as np
from pyigtl.messages import MessageBase, TransformMessage

from ..errors import EMRegError
from ..names import DEFAULT_IGTL_PORT
from .igtl_status import StatusMessage
from .tcp_backlog import PeerBacklog, unsent_or_unacked_bytes

#: ``TransformStatus`` of a valid pose (PLUS's tool status names: ``OK``, ``INVALID``, ``MISSING`` ...).
TRANSFORM_OK = "OK"
TRANSFORM_INVALID = "INVALID"


def transform_message(device_name: str, matrix: np.ndarray, timestamp: float | None = None,
                      status: str = TRANSFORM_OK) -> TransformMessage:
    """A TRANSFORM message with header version 2 and the metadata PLUS sends with each transform:
    ``TransformStatus`` and ``TransformValid``."""
    message = TransformMessage(np.asarray(matrix, dtype=np.float32), timestamp=timestamp, device_name=device_name)
    message.header_version = 2
    message.metadata = {"TransformStatus": status, "TransformValid": "true" if status == TRANSFORM_OK else "false"}
    return message


def transform_status(message) -> str:
    """The ``TransformStatus`` a received TRANSFORM carries (``OK`` when it carries none, as from a
    header-version-1 sender); ``TransformValid`` false without a status counts as ``INVALID``."""
    metadata = getattr(message, "metadata", None) or {}
    status = str(metadata.get("TransformStatus", "")).strip().upper()
    valid = str(metadata.get("TransformValid", "")).strip().lower()
    if status:
        return status
    if valid in ("false", "0", "\x00", "no"):
        return TRANSFORM_INVALID
    return TRANSFORM_OK

#: A message that has waited this long (s) in a client's queue is stale: a newer message of the same
#: type and device name replaces it (a newer pose supersedes an older one). A client that keeps up
#: within this time loses nothing.
STALE_AFTER_S = 0.5

#: How often (s) the server thread measures how far behind each client is.
POLL_S = 0.05
#: Default ``TCP_NOTSENT_LOWAT`` (bytes): the socket counts as writable only while less than this waits unsent.
NOTSENT_LOWAT = 16384
_TCP_NOTSENT_LOWAT = getattr(socket, "TCP_NOTSENT_LOWAT", 25)


class _Client:
    def __init__(self, sock: socket.socket, address: tuple) -> None:
        self.sock = sock
        self.address = address
        self.pending: deque[memoryview] = deque()
        self.keys: deque[str] = deque()  # the device name of each pending message (latest-only per name)
        self.times: deque[float] = deque()  # when each pending message was queued (monotonic s)
        self.pending_bytes = 0
        self.partial = False  # the head of ``pending`` is a message already partly sent
        self.dropped_messages = 0
        self.alive = True
        #: held: more than ``hold_after_s`` behind, fed nothing but the newest message per key until it has read up
        self.held = False
        self.times_held = 0
        self.handed = 0  # bytes handed to the kernel so far
        #: (stream offset just past bytes handed, when they were handed) - how long the client leaves them unread
        self.marks: deque[tuple[int, float]] = deque()
        self.observable: bool | None = None  # its unread receive queue is visible (same host), once known
        self.lag_s = 0.0  # how far behind it was at the last poll (s)

    @property
    def name(self) -> str:
        return f"{self.address[0]}:{self.address[1]}"

    def handed_over(self, n: int, offered_s: float) -> None:
        if n > 0:
            self.handed += n
            self.marks.append((self.handed, offered_s))


class IGTLServer:
    """OpenIGTLink TCP server: ``send(message)`` to every connected client."""

    def __init__(self, host: str = "127.0.0.1", port: int = DEFAULT_IGTL_PORT, max_pending_bytes: int = 1 << 20,
                 stale_after_s: float | None = None, send_buffer_bytes: int | None = None,
                 hold_after_s: float | None = None, notsent_lowat: int | None = NOTSENT_LOWAT,
                 log: TextIO | None = None) -> None:
        self.host = host
        #: a client further behind than this (s) is held (see the module docstring); None: never held
        self.hold_after_s = STALE_AFTER_S if hold_after_s is None else hold_after_s
        self.notsent_lowat = notsent_lowat
        self.log = log  # one line when a client is held and when it is fed again
        self.max_pending_bytes = max_pending_bytes
        #: queued messages older than this are superseded by newer ones of the same type and device name
        self.stale_after_s = STALE_AFTER_S if stale_after_s is None else stale_after_s
        #: the kernel send buffer of each client socket (None: the system's, autotuned)
        self.send_buffer_bytes = send_buffer_bytes
        self._listener = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        self._listener.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            self._listener.bind((host, port))
        except OSError as exc:
            self._listener.close()
            raise EMRegError(f"OpenIGTLink port {host}:{port}: cannot listen ({exc.strerror}); "
                             "choose another --igtl-port or stop the program using it") from None
        self._listener.listen(16)
        self._listener.setblocking(False)
        self.port = self._listener.getsockname()[1]
        self._clients: list[_Client] = []
        self._lock = threading.Lock()
        self._sticky: dict[str, bytes] = {}
        self._wake_r, self._wake_w = socket.socketpair()
        self._wake_r.setblocking(False)
        self._wake_w.setblocking(False)
        self._stop = threading.Event()
        self.messages_sent = 0
        self.connections = 0
        self._thread = threading.Thread(target=self._serve, name="igtl-server", daemon=True)
        self._thread.start()

    # -- public ------------------------------------------------------------------------------
    @property
    def client_count(self) -> int:
        with self._lock:
            return sum(1 for c in self._clients if c.alive)

    def send(self, message: MessageBase) -> int:
        """Pack ``message`` and offer it to every client now; returns ``time.monotonic_ns()`` after
        the last non-blocking send (the moment the bytes were handed to the operating system)."""
        data = message.pack()
        if isinstance(message, StatusMessage):
            with self._lock:
                self._sticky[message.device_name] = data
        return self.send_bytes(data, f"{message.message_type}:{message.device_name}")

    def send_transform(self, device_name: str, matrix: np.ndarray, timestamp: float | None = None,
                       status: str = TRANSFORM_OK) -> int:
        """Send a TRANSFORM (4x4, mm) under ``device_name`` with PLUS's status metadata (OpenIGTLink
        header version 2): ``TransformStatus`` (``OK``, or why the pose is not valid, e.g. ``INVALID``)
        and ``TransformValid`` (``true`` / ``false``). A client must not use a pose whose status is not OK."""
        return self.send(transform_message(device_name, matrix, timestamp, status))

    def send_bytes(self, data: bytes, key: str = "") -> int:
        """Offer packed bytes to every client. ``key`` (message type and device name): a client that has
        not taken an earlier message of the same key yet gets only this newer one (latest, not backlog)."""
        wake = False
        with self._lock:
            for client in self._clients:
                if client.alive:
                    wake |= self._offer(client, memoryview(data), key)
            self.messages_sent += 1
        done_ns = time.monotonic_ns()
        if wake:
            with contextlib.suppress(OSError):
                self._wake_w.send(b"w")
        return done_ns

    def wait_for_clients(self, count: int = 1, timeout_s: float = 5.0) -> bool:
        """Block until ``count`` clients are connected (True) or the timeout passes (False)."""
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if self.client_count >= count:
                return True
            time.sleep(0.01)
        return False

    def close(self) -> None:
        """Stop the server thread and close every socket (idempotent)."""
        if self._stop.is_set():
            return
        self._stop.set()
        with contextlib.suppress(OSError):
            self._wake_w.send(b"x")
        self._thread.join(timeout=5.0)
        with self._lock:
            for client in self._clients:
                self._drop(client)
            self._clients.clear()
        for sock in (self._listener, self._wake_r, self._wake_w):
            with contextlib.suppress(OSError):
                sock.close()

    def __enter__(self) -> IGTLServer:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- internals (called with the lock held) -------------------------------------------------
    def _offer(self, client: _Client, data: memoryview, key: str = "") -> bool:
        """Send now if nothing is queued, else queue. Returns True if the server thread must watch
        the socket for writability. A queued, not yet started message of the same ``key`` is
        replaced by this one: a slow client gets the latest pose, not a backlog of stale ones."""
        now = time.monotonic()
        if not client.pending and not client.held:
            try:
                n = client.sock.send(data)
            except (BlockingIOError, InterruptedError):
                n = 0
            except OSError:
                self._drop(client)
                return False
            client.handed_over(n, now)
            if n == len(data):
                return False
            client.pending.append(data[n:])
            client.keys.append(key if n == 0 else "")
            client.times.append(now)
            client.pending_bytes += len(data) - n
            client.partial = n > 0
            return True
        stale = now + 1.0 if client.held else now - self.stale_after_s  # held: every queued one is superseded
        if key and client.times and (client.held or client.times[0] < stale):  # behind: latest only
            start = 1 if client.partial else 0
            for index in range(len(client.keys) - 1, start - 1, -1):
                if client.keys[index] == key and client.times[index] < stale:
                    superseded = client.pending[index]
                    del client.pending[index]
                    del client.keys[index]
                    del client.times[index]
                    client.pending_bytes -= len(superseded)
                    client.dropped_messages += 1
        client.pending.append(data)
        client.keys.append(key)
        client.times.append(now)
        client.pending_bytes += len(data)
        while client.pending_bytes > self.max_pending_bytes and len(client.pending) > 1:
            # drop the oldest whole message (never the partly sent head: that would break framing)
            index = 1 if client.partial else 0
            dropped = client.pending[index]
            del client.pending[index]
            del client.keys[index]
            del client.times[index]
            client.pending_bytes -= len(dropped)
            client.dropped_messages += 1
        return not client.held

    def _flush(self, client: _Client) -> None:
        while client.pending and not client.held:
            head = client.pending[0]
            try:
                n = client.sock.send(head)
            except (BlockingIOError, InterruptedError):
                return
            except OSError:
                self._drop(client)
                return
            client.handed_over(n, time.monotonic())  # the client's lag counts from the hand-over
            client.pending_bytes -= n
            if n < len(head):
                client.pending[0] = head[n:]
                client.keys[0] = ""  # partly sent: never replaced
                client.partial = True
                return
            client.pending.popleft()
            client.keys.popleft()
            client.times.popleft()
            client.partial = False

    def _drop(self, client: _Client) -> None:
        client.alive = False
        client.pending.clear()
        client.keys.clear()
        client.times.clear()
        client.marks.clear()
        client.pending_bytes = 0
        with contextlib.suppress(OSError):
            client.sock.close()

    def _poll(self, backlog: PeerBacklog) -> None:
        """Measure how far behind each client is; hold it, or feed it again (see the module docstring)."""
        now = time.monotonic()
        for client in self._clients:
            if not client.alive:
                continue
            unread = None if client.observable is False else backlog.peer_unread_bytes(client.sock)
            if client.observable is None:
                client.observable = unread is not None
            read_up_to = client.handed - unsent_or_unacked_bytes(client.sock) - (unread or 0)
            while client.marks and client.marks[0][0] <= read_up_to:
                client.marks.popleft()
            client.lag_s = now - client.marks[0][1] if client.marks else 0.0
            if not client.held and self.hold_after_s is not None and client.lag_s > self.hold_after_s:
                client.held = True
                client.times_held += 1
                self._say(f"OpenIGTLink client {client.name} stopped reading ({client.lag_s:.1f} s behind): "
                          "holding its messages, the newest of each device only, until it reads again")
            elif client.held and not client.marks:  # it has read everything it was handed
                client.held = False
                self._say(f"OpenIGTLink client {client.name} reads again: sending it the newest messages")
                self._flush(client)

    def _say(self, line: str) -> None:
        if self.log is not None:
            with contextlib.suppress(OSError, ValueError):
                print(f"[emreg] {line}", file=self.log, flush=True)

    # -- server thread -------------------------------------------------------------------------
    def _serve(self) -> None:
        sel = selectors.DefaultSelector()
        sel.register(self._listener, selectors.EVENT_READ, "accept")
        sel.register(self._wake_r, selectors.EVENT_READ, "wake")
        registered: dict[_Client, int] = {}
        backlog = PeerBacklog()
        next_poll = time.monotonic()
        try:
            while not self._stop.is_set():
                with self._lock:
                    if self._clients and time.monotonic() >= next_poll:
                        next_poll = time.monotonic() + POLL_S
                        self._poll(backlog)
                    for client in list(registered):
                        if not client.alive:
                            with contextlib.suppress(KeyError, ValueError):
                                sel.unregister(client.sock)
                            del registered[client]
                    self._clients = [c for c in self._clients if c.alive]
                    for client in self._clients:
                        writing = client.pending and not client.held
                        events = selectors.EVENT_READ | (selectors.EVENT_WRITE if writing else 0)
                        if client not in registered:
                            sel.register(client.sock, events, client)
                            registered[client] = events
                        elif registered[client] != events:
                            sel.modify(client.sock, events, client)
                            registered[client] = events
                for key, mask in sel.select(timeout=POLL_S if registered else 0.2):
                    if key.data == "wake":
                        with contextlib.suppress(OSError):
                            self._wake_r.recv(4096)
                    elif key.data == "accept":
                        self._accept()
                    else:
                        client: _Client = key.data
                        if mask & selectors.EVENT_READ:
                            self._read(client)
                        if mask & selectors.EVENT_WRITE and client.alive:
                            with self._lock:
                                self._flush(client)
        finally:
            sel.close()
            backlog.close()

    def _accept(self) -> None:
        while True:
            try:
                sock, address = self._listener.accept()
            except (BlockingIOError, InterruptedError):
                return
            except OSError:
                return
            sock.setblocking(False)
            with contextlib.suppress(OSError):
                sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            if self.send_buffer_bytes:
                with contextlib.suppress(OSError):
                    sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, self.send_buffer_bytes)
            if self.notsent_lowat:
                with contextlib.suppress(OSError):
                    sock.setsockopt(socket.IPPROTO_TCP, _TCP_NOTSENT_LOWAT, self.notsent_lowat)
            client = _Client(sock, address)
            with self._lock:
                self._clients.append(client)
                self.connections += 1
                for name, data in self._sticky.items():
                    self._offer(client, memoryview(data), f"STATUS:{name}")

    def _read(self, client: _Client) -> None:
        try:
            data = client.sock.recv(65536)
        except (BlockingIOError, InterruptedError):
            return
        except OSError:
            data = b""
        if not data:
            with self._lock:
                self._drop(client)
