"""OpenIGTLink: the STATUS message through pyigtl's own parser, and the multi-client server over real TCP."""

from __future__ import annotations

import socket
import struct
import threading
import time

import numpy as np
import pyigtl
import pytest
from pyigtl.messages import CRC64, MessageBase, TransformMessage

from EMRegModule.devices.igtl_client import IGTLReceiver
from EMRegModule.devices.igtl_server import IGTLServer
from EMRegModule.devices.igtl_status import STATUS_NOT_PRESENT, StatusMessage
from EMRegModule.errors import EMRegError


def _parse_with_pyigtl(data: bytes) -> MessageBase:
    header = MessageBase.parse_header(data[:MessageBase.IGTL_HEADER_SIZE])
    message = MessageBase.create_message(header["message_type"])
    message.unpack(header, data[MessageBase.IGTL_HEADER_SIZE:])
    return message


def test_status_round_trips_through_pyigtl_parser():
    sent = StatusMessage(STATUS_NOT_PRESENT, -12345678901, "ReferenceMissing", "reference sensor (port 1) missing",
                         timestamp=1700000000.25, device_name="ProbeToImage")
    data = sent.pack()
    # wire layout per the OpenIGTLink spec: 58-byte header, then C (uint16) S (int64) E (char[20]) M
    header = struct.unpack("> H 12s 20s II Q Q", data[:58])
    assert header[1].rstrip(b"\0") == b"STATUS" and header[5] == len(data) - 58
    assert header[6] == CRC64(data[58:])
    code, subcode, name = struct.unpack("> H q 20s", data[58:88])
    assert (code, subcode, name.rstrip(b"\0")) == (16, -12345678901, b"ReferenceMissing")
    assert data[88:].rstrip(b"\0") == b"reference sensor (port 1) missing"
    received = _parse_with_pyigtl(data)
    assert isinstance(received, StatusMessage)
    assert (received.code, received.subcode, received.error_name, received.status_message) == \
        (16, -12345678901, "ReferenceMissing", "reference sensor (port 1) missing")
    assert received.device_name == "ProbeToImage" and received.timestamp == pytest.approx(1700000000.25, abs=1e-6)
    with pytest.raises(ValueError):
        StatusMessage(1, 0, "a name longer than twenty bytes")


def test_pyigtl_client_receives_transform_and_status_over_tcp():
    with IGTLServer("127.0.0.1", 0) as server:
        client = pyigtl.OpenIGTLinkClient("127.0.0.1", server.port)
        try:
            assert server.wait_for_clients(1, 30.0)
            matrix = np.array([[0, -1, 0, 10.5], [1, 0, 0, -2.25], [0, 0, 1, 3], [0, 0, 0, 1]], dtype=float)
            server.send_transform("ProbeToImage", matrix)
            server.send(StatusMessage(1, 0, "OK", "tracking data good", device_name="Tracker"))
            transform = client.wait_for_message("ProbeToImage", timeout=30)
            status = client.wait_for_message("Tracker", timeout=30)
        finally:
            client.stop()
    np.testing.assert_allclose(transform.matrix, matrix, atol=1e-6)
    assert isinstance(status, StatusMessage) and status.code == 1 and status.status_message == "tracking data good"


def test_many_clients_and_a_stalled_one_never_block_the_sender():
    with IGTLServer("127.0.0.1", 0, max_pending_bytes=64 * 1024) as server:
        # a client that connects and never reads, with a tiny receive buffer
        stalled = socket.socket()
        stalled.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
        stalled.connect(("127.0.0.1", server.port))
        received: list[list[MessageBase]] = [[], [], []]
        readers = [IGTLReceiver("127.0.0.1", server.port, received[k].append) for k in range(3)]
        sent = threading.Event()
        last_x = {}

        def send_all() -> None:
            for i in range(2000):
                if i % 10 == 0:  # bulky messages too, so that the stalled client's socket buffers fill up
                    server.send(pyigtl.StringMessage("x" * 16000, device_name="Bulk"))
                matrix = np.eye(4)
                matrix[0, 3] = i
                server.send(TransformMessage(matrix, device_name=f"T{i % 3}"))
                last_x[f"T{i % 3}"] = i
                if i % 200 == 0:
                    time.sleep(0.002)  # let the readers' threads run
            sent.set()

        def newest_arrived(messages: list[MessageBase]) -> bool:
            newest = {}
            for m in list(messages):
                if m.message_type == "TRANSFORM":
                    newest[m.device_name] = m.matrix[0][3]
            return newest == last_x

        try:
            assert server.wait_for_clients(4, 30.0)
            sender = threading.Thread(target=send_all, daemon=True)
            sender.start()
            # A sender blocked by the client that never reads would never finish: the stalled
            # client's socket stays full for the whole test (no time limit on each send is asserted).
            assert sent.wait(120), "the sender is blocked by the stalled client"
            deadline = time.monotonic() + 60
            while not all(newest_arrived(m) for m in received) and time.monotonic() < deadline:
                time.sleep(0.01)
            clients = {c.address[1]: c for c in server._clients}
            stalled_client = clients[stalled.getsockname()[1]]
            reader_clients = [clients[r._sock.getsockname()[1]] for r in readers]
        finally:
            for reader in readers:
                reader.close()
            stalled.close()
        assert all(r.crc_errors == 0 for r in readers)
        # the stalled client's queue is bounded: its older queued messages were dropped
        assert stalled_client.dropped_messages > 0
        assert stalled_client.pending_bytes <= 64 * 1024 + 16100
        # every reader ends with the newest pose of each device and got every message the server did not drop
        # for it: all 2200 unless it fell behind (the flood may put a Python reader further behind than the hold
        # limit, or fill its queue). Exact either way: a reader held only after the last message lost nothing.
        for reader, client, messages in zip(readers, reader_clients, received, strict=True):
            assert newest_arrived(messages)
            assert reader.messages == 2200 - client.dropped_messages, (reader.messages, client.dropped_messages,
                                                                       client.times_held)


def test_disconnecting_client_is_dropped_and_new_client_gets_last_status():
    with IGTLServer("127.0.0.1", 0) as server:
        first = socket.create_connection(("127.0.0.1", server.port))
        assert server.wait_for_clients(1, 30.0)
        first.close()
        server.send(StatusMessage(16, 0, "ReferenceMissing", "reference sensor missing", device_name="ProbeToImage"))
        deadline = time.monotonic() + 30
        while server.client_count and time.monotonic() < deadline:
            server.send_transform("ProbeToImage", np.eye(4))
            time.sleep(0.01)
        assert server.client_count == 0
        messages: list[MessageBase] = []
        late = IGTLReceiver("127.0.0.1", server.port, messages.append)
        try:
            deadline = time.monotonic() + 30
            while not messages and time.monotonic() < deadline:
                time.sleep(0.01)
        finally:
            late.close()
        assert isinstance(messages[0], StatusMessage) and messages[0].code == 16


def test_port_in_use_is_a_clear_error():
    with IGTLServer("127.0.0.1", 0) as server, pytest.raises(EMRegError, match="cannot listen"):
        IGTLServer("127.0.0.1", server.port)


def _transform_x(data: bytes) -> list[float]:
    """x translation of each TRANSFORM (header version 1, 106 bytes) in a byte stream."""
    size = 58 + 48
    return [float(np.frombuffer(data[k * size + 58 + 36:k * size + 58 + 40], dtype=">f4")[0])
            for k in range(len(data) // size)]


def test_a_client_that_stops_reading_is_held_and_then_gets_the_newest_pose_not_a_backlog():
    """A client with the system's default buffers stops reading: Linux keeps accepting for it (its receive
    buffer grows), so without the hold it would later read every pose sent meanwhile. The server sees the
    unread bytes (sock_diag), holds the client once it is more than 0.5 s behind, hands it nothing more,
    and when it reads again it finds only what it had been handed before the hold, then the newest pose."""
    import io

    log = io.StringIO()
    with IGTLServer("127.0.0.1", 0, log=log) as server:
        slow = socket.create_connection(("127.0.0.1", server.port))
        assert server.wait_for_clients(1, 30.0)
        client = server._clients[0]
        sent = 0

        def send() -> None:
            nonlocal sent
            sent += 1
            matrix = np.eye(4)
            matrix[0, 3] = sent
            server.send(TransformMessage(matrix, device_name="ProbeToImage"))
            time.sleep(0.001)

        while not client.held and sent < 100_000:  # until the server notices (an event, not a time)
            send()
        assert client.held, "the server never noticed the client stopped reading"
        at_hold = sent
        for _ in range(1000):  # the client still does not read
            send()
        assert client.held and client.observable
        slow.settimeout(0.1)
        data = b""
        deadline = time.monotonic() + 30
        while time.monotonic() < deadline and not (len(data) % 106 == 0 and data and _transform_x(data)[-1] == sent):
            try:
                chunk = slow.recv(1 << 20)
            except TimeoutError:
                continue
            if not chunk:
                break
            data += chunk
        released = not client.held
        slow.close()
    xs = _transform_x(data)
    assert xs[-1] == sent  # the newest pose arrived
    # nothing handed after the hold but the newest: the client read at most what it held plus that one
    assert len(xs) <= at_hold + 1 and xs[:-1] == sorted(xs[:-1]) and max(xs[:-1]) <= at_hold, (len(xs), at_hold)
    assert len(xs) < sent - 900
    assert released and "stopped reading" in log.getvalue() and "reads again" in log.getvalue()


def test_a_normal_pyigtl_client_gets_every_pose_at_100_hz():
    """A client that reads continuously (pyigtl's thread, as Slicer's OpenIGTLinkIF) is never held: every
    pose of 3 s at 100 Hz arrives, in order."""
    import io

    seen: list[float] = []

    class Client(pyigtl.OpenIGTLinkClient):
        def _receive_message_from_socket(self, ssocket):
            got = super()._receive_message_from_socket(ssocket)
            if got:
                with self.lock_incoming_messages:
                    message = self.incoming_messages.pop("ProbeToImage", None)
                if message is not None:
                    seen.append(float(message.matrix[0][3]))
            return got

    log = io.StringIO()
    with IGTLServer("127.0.0.1", 0, log=log) as server:
        client = Client("127.0.0.1", server.port)
        try:
            assert server.wait_for_clients(1, 30.0)
            for k in range(1, 301):
                matrix = np.eye(4)
                matrix[0, 3] = k
                server.send_transform("ProbeToImage", matrix)
                time.sleep(0.01)
            deadline = time.monotonic() + 30
            while (not seen or seen[-1] != 300) and time.monotonic() < deadline:
                time.sleep(0.01)
            times_held = server._clients[0].times_held
        finally:
            client.stop()
    assert seen == list(range(1, 301))
    assert times_held == 0 and log.getvalue() == ""
