"""Zenoh transport latency: LowState-sized payloads at 500 Hz on 127.0.0.1.

Measures publish -> subscriber-callback latency (both stamps from CLOCK_MONOTONIC, which
is system-wide on Linux, so the two-process figure is valid too) and the time spent in
``put`` (BLOCK congestion control). Prints one table.

    .venv/bin/python bench/bench_transport.py --seconds 3
    .venv/bin/python bench/bench_transport.py --seconds 3 --two-process
"""

from __future__ import annotations

import argparse
import json
import socket
import struct
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from hw.transport import KEY_LOWSTATE, Transport, TransportConfig

PAYLOAD_BYTES = 1180  # a CDR LowState_, header included
WARMUP, MEASURE, END = 0, 1, 2
# After the 4-byte encapsulation header: phase u8, pad, seq u32, send stamp u64 (ns).
_HDR = struct.Struct("<4sBxxxIQ")


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class Receiver:
    """Collects (seq, latency ns) of MEASURE samples; sets ``done`` on END."""

    def __init__(self, n_max: int):
        self.lat = np.zeros(n_max, dtype=np.int64)
        self.seq = np.zeros(n_max, dtype=np.int64)
        self.n = 0
        self.warm = threading.Event()
        self.done = threading.Event()

    def __call__(self, payload: bytes, t_ns: int) -> None:
        _, phase, seq, sent = _HDR.unpack_from(payload)
        if phase == MEASURE and self.n < len(self.lat):
            self.lat[self.n] = t_ns - sent
            self.seq[self.n] = seq
            self.n += 1
        elif phase == WARMUP:
            self.warm.set()
        elif phase == END:
            self.done.set()

    def stats(self) -> dict:
        lat = self.lat[: self.n] / 1e3
        in_order = bool(np.all(np.diff(self.seq[: self.n]) > 0))
        return {"received": self.n, "in_order": in_order,
                "p50_us": float(np.percentile(lat, 50)) if self.n else float("nan"),
                "p99_us": float(np.percentile(lat, 99)) if self.n else float("nan"),
                "max_us": float(lat.max()) if self.n else float("nan")}


def publish(tr: Transport, rate_hz: float, seconds: float, warm: threading.Event | None,
            done: threading.Event | None) -> tuple[int, np.ndarray]:
    """Warm up until ``warm`` (or 0.5 s), then publish at ``rate_hz`` for ``seconds``."""
    pub = tr.publisher(KEY_LOWSTATE)
    buf = bytearray(PAYLOAD_BYTES)
    # Warm up until the subscriber's route exists (acknowledged in-process; a fixed
    # 0.5 s across processes, where there is no channel back).
    t_end = time.monotonic() + (5.0 if warm is not None else 0.5)
    while time.monotonic() < t_end:
        _HDR.pack_into(buf, 0, b"\x00\x01\x00\x00", WARMUP, 0, time.monotonic_ns())
        pub.put(bytes(buf))
        if warm is None:
            time.sleep(0.01)
        elif warm.wait(0.01):
            break
    n = round(seconds * rate_hz)
    put_ns = np.zeros(n, dtype=np.int64)
    t0 = time.monotonic()
    for i in range(n):
        delay = t0 + i / rate_hz - time.monotonic()
        if delay > 0:
            time.sleep(delay)
        _HDR.pack_into(buf, 0, b"\x00\x01\x00\x00", MEASURE, i, time.monotonic_ns())
        data = bytes(buf)
        a = time.perf_counter_ns()
        pub.put(data)
        put_ns[i] = time.perf_counter_ns() - a
    # END until acknowledged (in-process) or a few times (two processes: loss-free anyway).
    for _ in range(50):
        _HDR.pack_into(buf, 0, b"\x00\x01\x00\x00", END, n, time.monotonic_ns())
        pub.put(bytes(buf))
        if done is not None and done.wait(0.02):
            break
        if done is None:
            time.sleep(0.02)
    return n, put_ns


def run_in_process(rate_hz: float, seconds: float) -> dict:
    ep = f"tcp/127.0.0.1:{free_port()}"
    n_max = round(seconds * rate_hz) + 10
    rx = Receiver(n_max)
    with Transport(TransportConfig(listen=[ep])) as robot, \
            Transport(TransportConfig(connect=[ep])) as host:
        host.subscribe(KEY_LOWSTATE, rx)
        sent, put_ns = publish(robot, rate_hz, seconds, rx.warm, rx.done)
        rx.done.wait(2.0)
    return {"setup": "1 process, 2 sessions", "sent": sent, **rx.stats(),
            "put_p50_us": float(np.percentile(put_ns, 50) / 1e3),
            "put_p99_us": float(np.percentile(put_ns, 99) / 1e3)}


def child(ep: str, n_max: int, timeout: float) -> None:
    """Subscriber process: listens on ``ep``, prints its stats as JSON at END."""
    rx = Receiver(n_max)
    with Transport(TransportConfig(listen=[ep])) as tr:
        tr.subscribe(KEY_LOWSTATE, rx)
        print("ready", flush=True)
        rx.done.wait(timeout)
    print(json.dumps(rx.stats()), flush=True)


def run_two_process(rate_hz: float, seconds: float) -> dict:
    ep = f"tcp/127.0.0.1:{free_port()}"
    n_max = round(seconds * rate_hz) + 10
    proc = subprocess.Popen(
        [sys.executable, __file__, "--child", ep, "--n-max", str(n_max),
         "--timeout", str(seconds + 15)], stdout=subprocess.PIPE, text=True)
    try:
        assert proc.stdout.readline().strip() == "ready", "child did not start"
        with Transport(TransportConfig(connect=[ep])) as host:
            sent, put_ns = publish(host, rate_hz, seconds, None, None)
        out, _ = proc.communicate(timeout=seconds + 20)
    finally:
        if proc.poll() is None:
            proc.kill()
    stats = json.loads(out.strip().splitlines()[-1])
    return {"setup": "2 processes", "sent": sent, **stats,
            "put_p50_us": float(np.percentile(put_ns, 50) / 1e3),
            "put_p99_us": float(np.percentile(put_ns, 99) / 1e3)}


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=3.0)
    ap.add_argument("--rate", type=float, default=500.0, help="Hz")
    ap.add_argument("--two-process", action="store_true")
    ap.add_argument("--child", help=argparse.SUPPRESS)
    ap.add_argument("--n-max", type=int, default=0, help=argparse.SUPPRESS)
    ap.add_argument("--timeout", type=float, default=30.0, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.child:
        child(args.child, args.n_max, args.timeout)
        return
    rows = [run_in_process(args.rate, args.seconds)]
    if args.two_process:
        rows.append(run_two_process(args.rate, args.seconds))
    print(f"\n{PAYLOAD_BYTES} B payloads at {args.rate:g} Hz for {args.seconds:g} s, "
          "congestion control BLOCK, express, loopback TCP; latency = publish -> callback")
    head = (f"{'setup':<24}{'sent':>7}{'recv':>7}{'lost':>6}{'order':>7}"
            f"{'p50 us':>9}{'p99 us':>9}{'max us':>9}{'put p50':>9}{'put p99':>9}")
    print(head)
    print("-" * len(head))
    for r in rows:
        print(f"{r['setup']:<24}{r['sent']:>7}{r['received']:>7}{r['sent'] - r['received']:>6}"
              f"{'ok' if r['in_order'] else 'NO':>7}{r['p50_us']:>9.0f}{r['p99_us']:>9.0f}"
              f"{r['max_us']:>9.0f}{r['put_p50_us']:>9.1f}{r['put_p99_us']:>9.1f}")
    if len(rows) == 2:
        print(f"p50 ratio two-process / in-process: {rows[1]['p50_us'] / rows[0]['p50_us']:.2f}")


if __name__ == "__main__":
    main()
