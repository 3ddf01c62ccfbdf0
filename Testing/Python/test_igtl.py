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

from EMRegModule.errors import EMRegError
from EMRegModule.live.igtl_client import IGTLReceiver
from EMRegModule.live.igtl_server import IGTLServer
from EMRegModule.live.igtl_status import STATUS_NOT_PRESENT, StatusMessage


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
            assert server.wait_for_clients(1, 5.0)
            matrix = np.array([[0, -1, 0, 10.5], [1, 0, 0, -2.25], [0, 0, 1, 3], [0, 0, 0, 1]], dtype=float)
            server.send_transform("ProbeToImage", matrix)
            server.send(StatusMessage(1, 0, "OK", "tracking data good", device_name="Tracker"))
            transform = client.wait_for_message("ProbeToImage", timeout=5)
            status = client.wait_for_message("Tracker", timeout=5)
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
        received: list[MessageBase] = []
        readers = [IGTLReceiver("127.0.0.1", server.port, received.append) for _ in range(3)]
        sent = threading.Event()

        def send_all() -> None:
            for i in range(2000):
                if i % 10 == 0:  # bulky messages too, so that the stalled client's socket buffers fill up
                    server.send(pyigtl.StringMessage("x" * 16000, device_name="Bulk"))
                server.send(TransformMessage(np.eye(4), device_name=f"T{i % 3}"))
                if i % 200 == 0:
                    time.sleep(0.002)  # let the readers' threads run
            sent.set()

        try:
            assert server.wait_for_clients(4, 5.0)
            sender = threading.Thread(target=send_all, daemon=True)
            sender.start()
            # A sender blocked by the client that never reads would never finish: the stalled
            # client's socket stays full for the whole test (no time limit on each send is asserted).
            assert sent.wait(120), "the sender is blocked by the stalled client"
            deadline = time.monotonic() + 30
            while len(received) < 3 * 2200 and time.monotonic() < deadline:
                time.sleep(0.01)
            stalled_client = [c for c in server._clients if c.pending_bytes or c.dropped_messages]
        finally:
            for reader in readers:
                reader.close()
            stalled.close()
        assert all(r.crc_errors == 0 for r in readers)
        # the stalled client's queue is bounded: its oldest queued messages were dropped
        assert len(stalled_client) == 1 and stalled_client[0].dropped_messages > 0
        assert stalled_client[0].pending_bytes <= 64 * 1024 + 16100
        # readers that keep up lose nothing (unless they fell behind by more than the queue bound)
        assert len(received) >= 0.95 * 3 * 2200, len(received)


def test_disconnecting_client_is_dropped_and_new_client_gets_last_status():
    with IGTLServer("127.0.0.1", 0) as server:
        first = socket.create_connection(("127.0.0.1", server.port))
        assert server.wait_for_clients(1, 5.0)
        first.close()
        server.send(StatusMessage(16, 0, "ReferenceMissing", "reference sensor missing", device_name="ProbeToImage"))
        deadline = time.monotonic() + 5
        while server.client_count and time.monotonic() < deadline:
            server.send_transform("ProbeToImage", np.eye(4))
            time.sleep(0.01)
        assert server.client_count == 0
        messages: list[MessageBase] = []
        late = IGTLReceiver("127.0.0.1", server.port, messages.append)
        try:
            deadline = time.monotonic() + 5
            while not messages and time.monotonic() < deadline:
                time.sleep(0.01)
        finally:
            late.close()
        assert isinstance(messages[0], StatusMessage) and messages[0].code == 16


def test_port_in_use_is_a_clear_error():
    with IGTLServer("127.0.0.1", 0) as server, pytest.raises(EMRegError, match="cannot listen"):
        IGTLServer("127.0.0.1", server.port)
