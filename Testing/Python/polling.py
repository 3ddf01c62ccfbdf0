"""Waiting on events and counts in the live tests: never an assertion of how long something took."""

from __future__ import annotations

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
