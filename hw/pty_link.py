"""A pseudo-terminal pair that behaves like a serial device, for tests and the mock robot.

The device side writes into the master; a SerialImuReader (or any pyserial
client) opens ``port_path``, the slave. Measured pitfalls this class handles
(see FACTS.md):
- the slave is set raw right after ``openpty``: in cooked mode the line
  discipline would echo bytes and translate CR/LF before pyserial configures
  the port;
- the slave fd stays open for the pair's lifetime, so the master never sees a
  hang-up between a client's close and the next open;
- clients must open ``port_path`` *before* the device writes (opening flushes
  pending input): ``write`` does not buffer on behalf of absent readers.

``close()`` (or ``hang_up()``) closes the master: a reader on the slave then
gets EIO, exactly like an unplugged USB-serial adapter.
"""

from __future__ import annotations

import os
import select
import threading
import tty
from typing import Self


class PtyPair:
    """Master/slave pty; ``write`` feeds bytes to whoever opened ``port_path``."""

    def __init__(self) -> None:
        self.master_fd, self.slave_fd = os.openpty()
        tty.setraw(self.slave_fd)
        # Non-blocking master: a writer facing a full buffer (nobody reading)
        # waits in select, never inside os.write, so hang_up() can always run.
        os.set_blocking(self.master_fd, False)
        self.port_path = os.ttyname(self.slave_fd)
        self._lock = threading.Lock()
        self._closed = False

    @property
    def closed(self) -> bool:
        return self._closed

    def write(self, data: bytes | bytearray | memoryview) -> int:
        """Write all of ``data`` to the master (blocks while the pty buffer is full)."""
        view = memoryview(data)
        total = 0
        while total < len(view):
            with self._lock:
                if self._closed:
                    raise OSError("PtyPair is closed")
                try:
                    total += os.write(self.master_fd, view[total:])
                    continue
                except BlockingIOError:
                    fd = self.master_fd
            try:
                select.select([], [fd], [], 0.05)
            except (OSError, ValueError):
                pass  # closed meanwhile: the next pass raises
        return total

    def read(self, max_bytes: int = 4096, timeout_s: float = 0.0) -> bytes:
        """Bytes the client wrote to the port (host -> device direction), b"" if none."""
        if self._closed:
            raise OSError("PtyPair is closed")
        ready, _, _ = select.select([self.master_fd], [], [], timeout_s)
        if not ready:
            return b""
        return os.read(self.master_fd, max_bytes)

    def hang_up(self) -> None:
        """Close the master only: the device is unplugged, readers see EIO."""
        with self._lock:
            if self.master_fd >= 0:
                os.close(self.master_fd)
                self.master_fd = -1
            self._closed = True

    def close(self) -> None:
        """Close both ends (idempotent)."""
        self.hang_up()
        if self.slave_fd >= 0:
            os.close(self.slave_fd)
            self.slave_fd = -1

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def __del__(self) -> None:
        try:
            self.close()
        except OSError:
            pass
