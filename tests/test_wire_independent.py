"""The mock robot at the wire, seen by a client that knows only the public Go2 layout.

Nothing of the project is imported: `a2i-mock` runs as a separate process, this client uses raw
zenoh, `struct` and its own CRC (FACTS.md), so a layout or CRC mistake shared by our encoder and
decoder cannot hide here.
"""

from __future__ import annotations

import itertools
import json
import os
import signal
import socket
import struct
import subprocess
import sys
import time

import pytest

zenoh = pytest.importorskip("zenoh")


def _crc32_core(words) -> int:
    """The Unitree SDK's crc32_core, bit by bit (poly 0x04C11DB7, init ~0, MSB first)."""
    crc = 0xFFFFFFFF
    for w in words:
        bit = 1 << 31
        for _ in range(32):
            crc = ((crc << 1) ^ 0x04C11DB7) & 0xFFFFFFFF if crc & 0x80000000 else (crc << 1)
            if w & bit:
                crc ^= 0x04C11DB7
            bit >>= 1
    return crc


# C struct images (natural alignment, little-endian), as in unitree_go's C++ headers.
MOTOR_CMD_C = "<B3xfffff3I"  # mode, q, dq, tau, kp, kd, reserve[3]  (40 bytes)


def _cdr_lowcmd(q12, kp, kd, bad_crc=False) -> bytes:
    """LowCmd_ as CDR (XCDR1 LE) with a CRC over its C image, written from the layout alone."""
    motors = []
    for i in range(20):
        if i < 12:
            motors.append((1, q12[i], 0.0, 0.0, kp, kd))
        else:
            motors.append((1, 2.146e9, 16000.0, 0.0, 0.0, 0.0))
    # C image for the CRC
    c = bytearray()
    c += struct.pack("<2sBB2I2IH2x", b"\xfe\xef", 0xFF, 0, 0, 0, 0, 0, 0)
    for m in motors:
        c += struct.pack(MOTOR_CMD_C, *m, 0, 0, 0)
    c += bytes(4) + bytes(40) + bytes(12) + bytes(2) + bytes(1) + bytes(1) + struct.pack("<I", 0)
    assert len(c) == 808, len(c)
    crc = _crc32_core(struct.unpack("<202I", bytes(c)))
    if bad_crc:
        crc ^= 0x1
    # CDR body: alignment relative to the body start
    b = bytearray()

    def align(n):
        while len(b) % n:
            b.append(0)

    b += b"\xfe\xef" + bytes([0xFF, 0])
    b += struct.pack("<4I", 0, 0, 0, 0)
    b += struct.pack("<H", 0)
    for m in motors:
        b += struct.pack("<B", m[0])
        align(4)
        b += struct.pack("<5f3I", *m[1:], 0, 0, 0)
    b += bytes(4)  # bms_cmd: off + reserve[3]
    b += bytes(40) + bytes(12) + bytes(2) + bytes(1)
    align(4)
    b += struct.pack("<I", 0)  # reserve
    b += struct.pack("<I", crc)
    out = b"\x00\x01\x00\x00" + bytes(b)
    assert len(out) == 812, len(out)
    return out


def _parse_lowstate(buf: bytes) -> dict:
    """Walk the CDR body of LowState_ field by field (alignment from the body start)."""
    body = buf[4:]
    pos = 0

    def take(fmt, align):
        nonlocal pos
        pos += (-pos) % align
        v = struct.unpack_from("<" + fmt, body, pos)
        pos += struct.calcsize("<" + fmt)
        return v

    d = {"head": take("2B", 1), "level_flag": take("B", 1)[0]}
    take("B", 1)
    take("2I", 4)
    take("2I", 4)
    take("H", 2)
    d["quat"] = take("4f", 4)
    d["gyro"] = take("3f", 4)
    d["acc"] = take("3f", 4)
    take("3f", 4)
    take("B", 1)
    qs = []
    for _ in range(20):
        take("B", 1)
        q, _dq, _ddq, _tau = take("4f", 4)
        take("3f", 4)
        take("B", 1)
        take("I", 4)
        take("2I", 4)
        qs.append(q)
    d["q"] = qs[:12]
    take("4B", 1)  # bms: version_high, version_low, status, soc
    take("i", 4)
    take("H", 2)
    take("2B", 1)
    take("2B", 1)
    take("15H", 2)
    d["foot_force"] = take("4h", 2)
    take("4h", 2)
    d["tick"] = take("I", 4)[0]
    take("40B", 1)
    take("B", 1)
    take("f", 4)
    take("2B", 1)
    take("f", 4)
    take("f", 4)
    take("4H", 2)
    take("I", 4)
    d["crc"] = take("I", 4)[0]
    d["end"] = pos
    return d


def _lowstate_c_words(buf: bytes) -> list[int]:
    """Rebuild the C image of LowState_ from the parsed CDR (for the CRC), field by field."""
    body = buf[4:]
    cdr = 0
    c = bytearray()

    def copy(fmt, cdr_align, c_align):
        nonlocal cdr
        cdr += (-cdr) % cdr_align
        n = struct.calcsize("<" + fmt)
        while len(c) % c_align:
            c.append(0)
        c.extend(body[cdr:cdr + n])
        cdr += n

    copy("2B", 1, 1); copy("B", 1, 1); copy("B", 1, 1)
    copy("2I", 4, 4); copy("2I", 4, 4); copy("H", 2, 2)
    copy("4f", 4, 4); copy("3f", 4, 4); copy("3f", 4, 4); copy("3f", 4, 4)
    copy("B", 1, 1)
    for _ in range(20):
        copy("B", 1, 4); copy("7f", 4, 4); copy("B", 1, 1); copy("I", 4, 4)
        copy("2I", 4, 4)
    copy("4B", 1, 4); copy("i", 4, 4); copy("H", 2, 2); copy("2B", 1, 1)
    copy("2B", 1, 1); copy("15H", 2, 2)
    copy("4h", 2, 2); copy("4h", 2, 2); copy("I", 4, 4); copy("40B", 1, 1)
    copy("B", 1, 1); copy("f", 4, 4); copy("2B", 1, 1); copy("f", 4, 4)
    copy("f", 4, 4); copy("4H", 2, 2); copy("I", 4, 4); copy("I", 4, 4)
    while len(c) % 4:
        c.append(0)
    return list(struct.unpack(f"<{len(c) // 4}I", bytes(c)))


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture
def mock(tmp_path):
    port = _free_port()
    truth = tmp_path / "truth.json"
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    p = subprocess.Popen(
        [sys.executable, "-m", "hw.mock.cli", "--listen", f"tcp/127.0.0.1:{port}",
         "--seed", "5", "--truth", str(truth), "--clock", "realtime"],
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=env)
    deadline = time.time() + 60
    while not truth.exists() and time.time() < deadline and p.poll() is None:
        time.sleep(0.1)
    assert truth.exists(), "a2i-mock did not start"
    yield port, truth
    p.send_signal(signal.SIGINT)
    try:
        p.wait(10)
    finally:
        if p.poll() is None:
            p.kill()


def test_independent_client_at_the_wire(mock):
    port, truth = mock
    assert set(json.loads(truth.read_text())) >= {"FL", "FR", "RL", "RR"}
    conf = zenoh.Config()
    conf.insert_json5("mode", '"client"')
    conf.insert_json5("connect/endpoints", json.dumps([f"tcp/127.0.0.1:{port}"]))
    conf.insert_json5("scouting/multicast/enabled", "false")
    got: list[tuple[float, bytes]] = []
    with zenoh.open(conf) as s:
        sub = s.declare_subscriber("rt/lowstate",
                                   lambda smp: got.append((time.monotonic(),
                                                           smp.payload.to_bytes())))
        pub = s.declare_publisher("rt/lowcmd", congestion_control=zenoh.CongestionControl.BLOCK)
        t0 = time.monotonic()
        while len(got) < 400 and time.monotonic() - t0 < 20:
            time.sleep(0.05)
        frames = [b for _, b in got]
        assert len(frames) >= 400, f"only {len(frames)} lowstates in 20 s"
        ticks = []
        for b in frames[-300:]:
            assert len(b) == 1180 and b[:4] == b"\x00\x01\x00\x00"
            d = _parse_lowstate(b)
            assert d["end"] == 1176
            assert d["head"] == (0xFE, 0xEF)
            words = _lowstate_c_words(b)
            assert _crc32_core(words[:-1]) == d["crc"]
            ticks.append(d["tick"])
        steps = [b - a for a, b in itertools.pairwise(ticks)]
        # 500 Hz, tick in ms from the robot's free-running clock: 2 ms a message, more where
        # the (simulated) sender was held up and less while it caught up; never backwards
        assert min(steps) >= 0 and sorted(steps)[len(steps) // 2] == 2, steps
        rate = (len(got) - 1) / (got[-1][0] - got[0][0])
        assert 100 < rate < 650, rate  # 500 Hz nominal; the exact rate is the mock tests' job

        q0 = _parse_lowstate(frames[-1])["q"]
        target = [0.0, 0.67, -1.3] * 4
        target = [(-v if i % 3 == 0 and (i // 3) in (0, 2) else v) for i, v in enumerate(target)]
        # a bad CRC is ignored: nothing moves
        for _ in range(50):
            pub.put(_cdr_lowcmd(target, 60.0, 5.0, bad_crc=True))
            time.sleep(0.02)
        q_bad = _parse_lowstate(got[-1][1])["q"]
        assert max(abs(a - b) for a, b in zip(q_bad, q0)) < 0.05
        # a good one is obeyed: the joints go to the stand pose
        t1 = time.monotonic()
        while time.monotonic() - t1 < 20:  # the mock may run slower than real time when loaded
            pub.put(_cdr_lowcmd(target, 60.0, 5.0))
            time.sleep(0.02)
            q_good = _parse_lowstate(got[-1][1])["q"]
            if max(abs(a - b) for a, b in zip(q_good, target)) < 0.12:
                break
        assert max(abs(a - b) for a, b in zip(q_good, target)) < 0.15
        assert max(abs(a - b) for a, b in zip(q_good, q0)) > 0.3
        sub.undeclare()
        pub.undeclare()
