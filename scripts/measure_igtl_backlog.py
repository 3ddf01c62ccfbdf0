"""What an OpenIGTLink client that stops reading gets when it reads again (issue 11: "slow clients get the
latest pose, not a backlog").

EMReg's ``IGTLServer`` (real TCP on 127.0.0.1) sends a TRANSFORM ``ProbeToImage`` at ``--rate`` Hz, stamped
with the wall clock. A client reads for 2 s, stops reading for ``--stall`` s, then reads again. Printed per
client: the poses it read after resuming before the first fresh one (less than ``FRESH_S`` old), the oldest
age among them, and how long after resuming the first fresh pose was read. Clients:

- ``raw``: a plain socket that stops calling ``recv`` (default Linux buffers: the kernel keeps accepting
  for it, growing its receive buffer);
- ``pyigtl``: ``pyigtl.OpenIGTLinkClient`` in a child process frozen with SIGSTOP and woken with SIGCONT
  (a hung Slicer: its reading thread stops too). pyigtl keeps the latest message per device, as
  Slicer's OpenIGTLinkIF does; counted here is every message its thread parsed.

Usage: ``python scripts/measure_igtl_backlog.py [--rate 100] [--stall 30] [--client raw|pyigtl|both]``.
This is a measurement, not a benchmark of speed: run it under ``flock /work/heavy.lock`` on a quiet machine.
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import socket
import struct
import subprocess
import sys
import threading
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np  # noqa: E402

#: A pose less old than this (s) is fresh.
FRESH_S = 0.1
HEADER = struct.Struct(">H12s20sQQQ")


def _stamp(value: int) -> float:
    return (value >> 32) + (value & 0xFFFFFFFF) / 2**32


def _sender(server, rate_hz: float, stop: threading.Event) -> None:
    period = 1.0 / rate_hz
    k = 0
    next_t = time.monotonic()
    while not stop.is_set():
        k += 1
        matrix = np.eye(4)
        matrix[0, 3] = k
        server.send_transform("ProbeToImage", matrix, time.time())
        next_t += period
        delay = next_t - time.monotonic()
        if delay > 0:
            time.sleep(delay)


def _summary(after: list[tuple[float, float]], resume_wall: float) -> dict:
    """``after``: (receive wall time, stamp) of the messages read after resuming."""
    ages = [received - stamp for received, stamp in after]
    first_fresh = next((i for i, age in enumerate(ages) if age < FRESH_S), None)
    stale = ages if first_fresh is None else ages[:first_fresh]
    return {"poses_read_before_a_fresh_one": len(stale),
            "oldest_age_s": round(max(stale), 2) if stale else 0.0,
            "first_fresh_after_s": None if first_fresh is None else round(after[first_fresh][0] - resume_wall, 3),
            "read_after_resume": len(after)}


def measure_raw(port: int, stall_s: float) -> dict:
    sock = socket.create_connection(("127.0.0.1", port))
    sock.settimeout(0.05)
    buffer = bytearray()

    def read_for(seconds: float) -> list[tuple[float, float]]:
        out = []
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            try:
                chunk = sock.recv(1 << 20)
            except TimeoutError:
                continue
            if not chunk:
                break
            buffer.extend(chunk)
            now = time.time()
            while len(buffer) >= HEADER.size:
                _, _, _, stamp, body, _ = HEADER.unpack_from(buffer)
                if len(buffer) < HEADER.size + body:
                    break
                out.append((now, _stamp(stamp)))
                del buffer[:HEADER.size + body]
        return out

    before = read_for(2.0)
    time.sleep(stall_s)  # no recv: the client has stopped reading
    resume = time.time()
    after = read_for(3.0)
    sock.close()
    return {"read_before_stall": len(before), **_summary(after, resume)}


def _pyigtl_child(port: int, seconds: float) -> None:
    import pyigtl

    log: list[tuple[float, float]] = []

    class Client(pyigtl.OpenIGTLinkClient):
        def _receive_message_from_socket(self, ssocket):
            got = super()._receive_message_from_socket(ssocket)
            if got:
                with self.lock_incoming_messages:
                    message = self.incoming_messages.get("ProbeToImage")
                if message is not None:
                    log.append((time.time(), float(message.timestamp)))
            return got

    client = Client("127.0.0.1", port)
    end = time.time() + seconds
    while time.time() < end:
        time.sleep(0.05)
    client.stop()
    print(json.dumps(log))


def measure_pyigtl(port: int, stall_s: float) -> dict:
    child = subprocess.Popen([sys.executable, __file__, "--pyigtl-child", str(port), "--seconds", str(stall_s + 6)],
                             stdout=subprocess.PIPE, text=True)
    time.sleep(2.5)
    child.send_signal(signal.SIGSTOP)
    time.sleep(stall_s)
    resume = time.time()
    child.send_signal(signal.SIGCONT)
    out, _ = child.communicate(timeout=stall_s + 60)
    log = json.loads(out)
    before = [r for r in log if r[0] < resume - stall_s]
    after = [r for r in log if r[0] >= resume]
    return {"read_before_stall": len(before), **_summary(after, resume)}


def reset_discards_nothing() -> str:
    """Why a server cannot take back what a client's kernel accepted: queue 50000 bytes for a client that is
    not reading, reset the connection (SO_LINGER 0), then let the client read."""
    listener = socket.create_server(("127.0.0.1", 0))
    client = socket.create_connection(listener.getsockname())
    conn, _ = listener.accept()
    conn.sendall(b"x" * 50000)
    time.sleep(0.2)
    conn.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))
    conn.close()
    time.sleep(0.2)
    got, end = 0, "end of stream"
    try:
        while chunk := client.recv(65536):
            got += len(chunk)
    except OSError as exc:
        end = exc.strerror or str(exc)
    client.close()
    listener.close()
    return f"after a reset the client still read {got} of the 50000 bytes queued before it, then: {end}"


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rate", type=float, default=100.0)
    parser.add_argument("--stall", type=float, default=30.0)
    parser.add_argument("--client", choices=("raw", "pyigtl", "both"), default="both")
    parser.add_argument("--pyigtl-child", type=int, default=None, help=argparse.SUPPRESS)
    parser.add_argument("--seconds", type=float, default=0.0, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.pyigtl_child is not None:
        _pyigtl_child(args.pyigtl_child, args.seconds)
        return 0
    from EMRegModule.devices.igtl_server import IGTLServer

    print(f"load average {os.getloadavg()[0]:.2f}; {args.rate:g} Hz, client stops reading for {args.stall:g} s")
    print(reset_discards_nothing())
    for kind in (("raw", "pyigtl") if args.client == "both" else (args.client,)):
        with IGTLServer("127.0.0.1", 0) as server:
            stop = threading.Event()
            sender = threading.Thread(target=_sender, args=(server, args.rate, stop), daemon=True)
            sender.start()
            try:
                result = (measure_raw if kind == "raw" else measure_pyigtl)(server.port, args.stall)
            finally:
                stop.set()
                sender.join()
        print(f"{kind:7s} " + json.dumps(result), flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
