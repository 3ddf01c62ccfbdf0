"""How far behind a TCP client is: the bytes still in the kernels between a server's ``send`` and the client's read.

A server sees only its own side of a connection: ``SIOCOUTQ`` gives the bytes of its send queue not yet
acknowledged by the peer. What the peer's kernel has acknowledged but its program has not read yet is
invisible over TCP on Linux: a receiver that stops reading keeps advertising a full window while the
kernel grows its receive buffer (``tcp_clamp_window``, up to ``net.ipv4.tcp_rmem``'s maximum), so a
client that stops for 30 s at 100 Hz silently buffers all 3000 poses, and a reset does not discard them
(Linux lets the program read what was queued before the RST). When the client runs on the same host
(the usual 3D Slicer on the navigation workstation), Linux's ``sock_diag`` netlink interface answers
exactly: the client socket's receive queue (``idiag_rqueue``: received, not yet read), looked up by its
address pair, without privileges. This module asks both.

Linux only; elsewhere (or for a client on another host / network namespace) ``peer_unread_bytes``
returns None and only the server's own queue is known.
"""

from __future__ import annotations

import contextlib
import fcntl
import itertools
import socket
import struct
import sys
import termios

NETLINK_SOCK_DIAG = 4
SOCK_DIAG_BY_FAMILY = 20
NLM_F_REQUEST = 0x1
NLMSG_ERROR = 0x2
INET_DIAG_NOCOOKIE = 0xFFFFFFFF
_NLMSGHDR = struct.Struct("=IHHII")
#: inet_diag_msg after the netlink header: family, state, timer, retrans, sockid (48 bytes), expires, rqueue, ...
_RQUEUE_OFFSET = _NLMSGHDR.size + 4 + 48 + 4


def unsent_or_unacked_bytes(sock: socket.socket) -> int:
    """Bytes in our send queue that the peer has not acknowledged yet (``SIOCOUTQ``; 0 if unknown)."""
    try:
        return struct.unpack("I", fcntl.ioctl(sock.fileno(), termios.TIOCOUTQ, b"\0\0\0\0"))[0]
    except (OSError, ValueError):
        return 0


def _address16(family: int, host: str) -> bytes:
    packed = socket.inet_pton(family, host)
    return packed + b"\0" * (16 - len(packed))


class PeerBacklog:
    """Asks the kernel how many bytes the peer of a connected TCP socket has received and not read yet.

    One netlink socket serves every query (not thread-safe: use it from one thread)."""

    def __init__(self) -> None:
        self._sock: socket.socket | None = None
        self._seq = itertools.count(1)
        if sys.platform.startswith("linux"):
            with contextlib.suppress(OSError, AttributeError):
                self._sock = socket.socket(socket.AF_NETLINK, socket.SOCK_DGRAM, NETLINK_SOCK_DIAG)
                self._sock.settimeout(0.2)

    def peer_unread_bytes(self, conn: socket.socket) -> int | None:
        """The peer socket's receive queue (bytes), or None when it is not visible from here."""
        if self._sock is None:
            return None
        try:
            local = conn.getsockname()
            peer = conn.getpeername()
            family = conn.family
            # the peer's socket: its own address is our peer address, its remote address is ours
            sockid = (struct.pack(">HH", peer[1], local[1]) + _address16(family, peer[0])
                      + _address16(family, local[0]) + struct.pack("=III", 0, INET_DIAG_NOCOOKIE, INET_DIAG_NOCOOKIE))
            body = struct.pack("=BBBBI", family, socket.IPPROTO_TCP, 0, 0, 0xFFFFFFFF) + sockid
            seq = next(self._seq)
            self._sock.send(_NLMSGHDR.pack(_NLMSGHDR.size + len(body), SOCK_DIAG_BY_FAMILY, NLM_F_REQUEST, seq, 0)
                            + body)
            while True:
                reply = self._sock.recv(8192)
                length, kind, _, reply_seq, _ = _NLMSGHDR.unpack_from(reply)
                if reply_seq == seq:
                    break
        except (OSError, ValueError, struct.error):
            return None
        if kind == NLMSG_ERROR or length < _RQUEUE_OFFSET + 4 or len(reply) < _RQUEUE_OFFSET + 4:
            return None  # ENOENT: the peer is on another host or in another network namespace
        return struct.unpack_from("=I", reply, _RQUEUE_OFFSET)[0]

    def close(self) -> None:
        if self._sock is not None:
            with contextlib.suppress(OSError):
                self._sock.close()
            self._sock = None
