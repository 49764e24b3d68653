"""The mock's foot-IMU port: a full pty drops frames in realtime, holds the lockstep simulation
back until its reader takes them, and gives up waiting on a port nobody reads."""

from __future__ import annotations

import threading
import time

import pytest
import serial

from hw.mock.foot_imus import PortWriter

FRAME = bytes(range(57))  # an A2I frame's length


def fill(w: PortWriter) -> int:
    """Write frames until the port refuses one; how many it took."""
    n = 0
    while w.write(FRAME):
        n += 1
    return n


def test_without_a_wait_a_full_port_drops_the_frame_at_once():
    w = PortWriter()
    port = serial.Serial(w.port_path, 921600, timeout=0.01)  # open, nobody reads
    try:
        assert fill(w) > 50
        assert w.writes_dropped_full + w.writes_truncated == 1
        t0 = time.monotonic()
        assert not w.write(FRAME)
        assert time.monotonic() - t0 < 0.05
        assert w.writes_waited == 0
    finally:
        port.close()
        w.close()


def test_with_a_wait_a_full_port_holds_the_write_until_its_reader_comes():
    w = PortWriter(wait_s=2.0)
    port = serial.Serial(w.port_path, 921600, timeout=0.05)
    got = bytearray()
    stop = threading.Event()

    def late_reader():
        time.sleep(0.2)
        while not stop.is_set():
            got.extend(port.read(4096))

    t = threading.Thread(target=late_reader)
    t.start()
    try:
        n = 1000  # 57 kB: three times what the pty holds
        assert all(w.write(FRAME) for _ in range(n))
        deadline = time.monotonic() + 5.0
        while len(got) < n * len(FRAME) and time.monotonic() < deadline:
            time.sleep(0.01)
    finally:
        stop.set()
        t.join()
        port.close()
        w.close()
    assert bytes(got) == FRAME * n  # nothing lost, nothing cut, in order
    assert w.writes_dropped_full == w.writes_truncated == 0
    assert w.writes_waited >= 1 and 0.1 < w.wait_max_s < 2.0


def test_a_port_nobody_reads_costs_one_wait_then_drops_until_a_write_gets_through():
    w = PortWriter(wait_s=0.3)
    port = serial.Serial(w.port_path, 921600, timeout=0.05)
    try:
        t0 = time.monotonic()
        fill(w)
        assert 0.3 <= time.monotonic() - t0 < 2.0
        assert w.writes_dropped_full + w.writes_truncated == 1
        t0 = time.monotonic()
        assert not w.write(FRAME)  # given up on: no second wait
        assert time.monotonic() - t0 < 0.05
        while port.read(4096):  # a reader turns up and empties the port
            pass
        assert w.write(FRAME)
    finally:
        port.close()
        w.close()


def test_a_bad_wait_is_refused():
    with pytest.raises(ValueError, match="wait_s"):
        PortWriter(wait_s=-1.0)
    with pytest.raises(ValueError, match="wait_s"):
        PortWriter(wait_s=float("nan"))
