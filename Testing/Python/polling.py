"""Waiting on events and counts in the live tests: never an assertion of how long something took."""

from __future__ import annotations

import os
import re
import select
import subprocess
import time
from collections.abc import Callable


def wait_for(condition: Callable[[], object], timeout_s: float = 30.0) -> bool:
    """Poll ``condition()`` every 10 ms until it holds (True) or ``timeout_s`` passes (False, a generous
    bound for a starved machine)."""
    deadline = time.monotonic() + timeout_s
    while not condition():
        if time.monotonic() > deadline:
            return False
        time.sleep(0.01)
    return True


#: How ``emreg navigate`` / ``emreg serve`` say where their OpenIGTLink server listens (stderr, unless --quiet).
_LISTENING = re.compile(rb"(?:->|on) OpenIGTLink [0-9.]+:(\d+) ")


def announced_igtl_port(process: subprocess.Popen, timeout_s: float = 180.0) -> tuple[int, str]:
    """The port of the OpenIGTLink server of ``emreg navigate`` / ``serve`` started with ``--igtl-port 0``, from
    the line it says it on, and what it wrote to stderr up to there (to put before what ``communicate()``
    reads; nothing is read through ``process.stderr`` itself).

    Port 0 lets the kernel choose a free port as the server binds it. A port found free beforehand (bound to 0,
    closed, then given to the command) can be taken in between by any other process, such as a test of
    another pytest-xdist worker, and a client of this test then meets that process's server.
    ``timeout_s`` only guards against a hang (a loaded machine starts the command late)."""
    fd = process.stderr.fileno()
    said = b""
    deadline = time.monotonic() + timeout_s
    while True:
        match = _LISTENING.search(said[:said.rfind(b"\n") + 1])  # whole lines only
        if match:
            return int(match.group(1)), said.decode()
        left = deadline - time.monotonic()
        assert left > 0, f"no OpenIGTLink port said within {timeout_s} s; stderr so far:\n{said.decode()}"
        if select.select([fd], [], [], min(left, 1.0))[0]:
            chunk = os.read(fd, 65536)
            assert chunk, f"stderr ended before the OpenIGTLink port was said:\n{said.decode()}"
            said += chunk
