"""An OpenIGTLink receiving client (for ``igtl://HOST:PORT`` sources), parsing with pyigtl.

Reads whole messages (58-byte header, then the body), checks the header's CRC-64 of the body,
and lets pyigtl build the message object (TRANSFORM, STATUS once registered, ...). Reconnects
when the server goes away. Runs in one daemon thread that stops with ``close()``.
"""

from __future__ import annotations

import contextlib
import socket
import struct
import threading
import time
from collections.abc import Callable

from pyigtl.messages import CRC64, MessageBase

from . import igtl_status  # noqa: F401  (registers STATUS with pyigtl's parser)

_HEADER = struct.Struct("> H 12s 20s II Q Q")
MessageCallback = Callable[[MessageBase], None]


class IGTLReceiver:
    """Connects to an OpenIGTLink server and calls ``callback(message)`` for each message."""

    def __init__(self, host: str, port: int, callback: MessageCallback, reconnect_s: float = 0.2) -> None:
        self.host = host
        self.port = port
        self.callback = callback
        self.reconnect_s = reconnect_s
        self.connected = threading.Event()
        self.messages = 0
        self.crc_errors = 0
        self._stop = threading.Event()
        self._sock: socket.socket | None = None
        self._thread = threading.Thread(target=self._run, name="igtl-receiver", daemon=True)
        self._thread.start()

    def close(self) -> None:
        self._stop.set()
        sock = self._sock
        if sock is not None:
            with contextlib.suppress(OSError):
                sock.shutdown(socket.SHUT_RDWR)
        self._thread.join(timeout=5.0)

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                sock = socket.create_connection((self.host, self.port), timeout=1.0)
            except OSError:
                time.sleep(self.reconnect_s)
                continue
            sock.settimeout(0.2)
            with contextlib.suppress(OSError):
                sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            self._sock = sock
            self.connected.set()
            try:
                self._receive(sock)
            finally:
                self.connected.clear()
                self._sock = None
                with contextlib.suppress(OSError):
                    sock.close()

    def _read_exact(self, sock: socket.socket, n: int) -> bytes | None:
        buf = bytearray()
        while len(buf) < n:
            if self._stop.is_set():
                return None
            try:
                chunk = sock.recv(n - len(buf))
            except TimeoutError:
                continue
            except OSError:
                return None
            if not chunk:
                return None
            buf.extend(chunk)
        return bytes(buf)

    def _receive(self, sock: socket.socket) -> None:
        while not self._stop.is_set():
            header = self._read_exact(sock, MessageBase.IGTL_HEADER_SIZE)
            if header is None:
                return
            crc = _HEADER.unpack(header)[6]
            fields = MessageBase.parse_header(header)
            body = self._read_exact(sock, fields["body_size"])
            if body is None:
                return
            if CRC64(body) != crc:
                self.crc_errors += 1
                continue
            message = MessageBase.create_message(fields["message_type"])
            if message is None:
                continue
            message.unpack(fields, body)
            self.messages += 1
            self.callback(message)
