"""Decode throughput of the foot-IMU decoders and the cost of ClockMapper.update.

Run: .venv/bin/python bench/bench_imu_decoder.py [--frames 20000]
Prints frames/s per protocol, chunk size and garbage level, the ratio to a
byte-at-a-time reference decoder with a pure-Python CRC (the usual naive
port of a C state machine), and the headroom over the real load of
4 IMUs x 400 Hz = 1600 frames/s.
"""

from __future__ import annotations

import argparse
import random
import struct
import time

from hw.clock_sync import ClockMapper
from hw.hipnuc import HipnucDecoder, encode_imu_frame
from hw.imu_protocol import FRAME_LEN, SYNC, FrameDecoder, ImuFrame, encode_frame

LOAD_FPS = 4 * 400


def make_frames(n: int) -> list[ImuFrame]:
    rng = random.Random(0)
    return [
        ImuFrame(k % 4, (k // 4) % 65536, 1000 * k,
                 tuple(rng.uniform(-5, 5) for _ in range(3)),
                 tuple(rng.uniform(-20, 20) for _ in range(3)),
                 (1.0, 0.0, 0.0, 0.0))
        for k in range(n)
    ]


def with_garbage(frames: list[bytes], fraction: float) -> bytes:
    rng = random.Random(1)
    parts = []
    for f in frames:
        if rng.random() < fraction:
            parts.append(bytes(rng.randrange(256) for _ in range(rng.randrange(1, 40))))
        parts.append(f)
    return b"".join(parts)


class NaiveDecoder:
    """Byte-at-a-time state machine with a bitwise CRC: the baseline."""

    _body = struct.Struct("<BHQ10f")

    def __init__(self) -> None:
        self.buf = bytearray()

    @staticmethod
    def _crc(data: bytes) -> int:
        crc = 0xFFFF
        for b in data:
            crc ^= b << 8
            for _ in range(8):
                crc = ((crc << 1) ^ 0x1021) & 0xFFFF if crc & 0x8000 else (crc << 1) & 0xFFFF
        return crc

    def feed(self, data: bytes) -> list[ImuFrame]:
        out = []
        for byte in data:
            self.buf.append(byte)
            if len(self.buf) == 1 and byte != SYNC[0] or len(self.buf) == 2 and byte != SYNC[1]:
                self.buf.clear()
            elif len(self.buf) == FRAME_LEN:
                frame = bytes(self.buf)
                self.buf.clear()
                if self._crc(frame[2:-2]) == struct.unpack_from("<H", frame, FRAME_LEN - 2)[0]:
                    v = self._body.unpack_from(frame, 4)
                    out.append(ImuFrame(v[0], v[1], v[2], v[3:6], v[6:9], v[9:13]))
        return out


def rate(make_decoder, stream: bytes, chunk: int, expected: int, repeat: int = 3) -> float:
    best = 0.0
    for _ in range(repeat):
        dec = make_decoder()
        t0 = time.perf_counter()
        n = 0
        for k in range(0, len(stream), chunk):
            n += len(dec.feed(stream[k:k + chunk]))
        dt = time.perf_counter() - t0
        if n != expected:
            raise RuntimeError(f"decoded {n} frames, expected {expected}")
        best = max(best, n / dt)
    return best


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=20000)
    args = ap.parse_args()
    frames = make_frames(args.frames)
    a2i = [encode_frame(f) for f in frames]
    hip = [encode_imu_frame(f) for f in frames]
    n = len(frames)

    naive_n = min(n, 3000)
    naive = rate(NaiveDecoder, b"".join(a2i[:naive_n]), 4096, naive_n, repeat=1)

    print(f"{'protocol':<8} {'stream':<12} {'chunk B':>8} {'frames/s':>12} "
          f"{'vs naive':>9} {'x load':>8}")
    rows = [
        ("a2i", "clean", FrameDecoder, b"".join(a2i), 57),
        ("a2i", "clean", FrameDecoder, b"".join(a2i), 512),
        ("a2i", "clean", FrameDecoder, b"".join(a2i), 4096),
        ("a2i", "30% garbage", FrameDecoder, with_garbage(a2i, 0.3), 4096),
        ("hipnuc", "clean", HipnucDecoder, b"".join(hip), 82),
        ("hipnuc", "clean", HipnucDecoder, b"".join(hip), 4096),
        ("hipnuc", "30% garbage", HipnucDecoder, with_garbage(hip, 0.3), 4096),
    ]
    for proto, kind, cls, stream, chunk in rows:
        fps = rate(cls, stream, chunk, n)
        print(f"{proto:<8} {kind:<12} {chunk:>8} {fps:>12,.0f} {fps / naive:>8.1f}x "
              f"{fps / LOAD_FPS:>7.0f}x")
    print(f"{'naive':<8} {'clean':<12} {4096:>8} {naive:>12,.0f} {1.0:>8.1f}x "
          f"{naive / LOAD_FPS:>7.0f}x")

    m = ClockMapper()
    t0 = time.perf_counter()
    for k in range(n):
        m.update(5_000_000 * k, 1_000_000 + 5_000_000 * k + (k * 7919) % 1_000_000)
    dt = time.perf_counter() - t0
    print(f"\nClockMapper.update: {dt / n * 1e6:.2f} us/sample "
          f"({n / dt:,.0f} samples/s, {n / dt / LOAD_FPS:.0f}x load)")


if __name__ == "__main__":
    main()
