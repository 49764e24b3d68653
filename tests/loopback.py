"""Helpers shared by the tests that talk over loopback (not a test module)."""

from __future__ import annotations

import socket
import time


def free_port() -> int:
    """A TCP port on 127.0.0.1 that is free now."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def free_endpoint() -> str:
    """A Zenoh endpoint on a free loopback port."""
    return f"tcp/127.0.0.1:{free_port()}"


def wait_until(pred, timeout: float) -> bool:
    """Poll ``pred`` every 5 ms until it holds (True) or ``timeout`` s pass (False)."""
    deadline = time.monotonic() + timeout
    while not pred():
        if time.monotonic() > deadline:
            return False
        time.sleep(0.005)
    return True
