"""Cost of the recorder: ns per sample of each writer, snapshot/window copies, MCAP export/import.

Run: ``.venv/bin/python bench/bench_recorder.py [--seconds S]`` (default 120 s of history, the
RecorderConfig default; ``--seconds 10`` for a quick run). Prints tables and the CPU share the
writers take at the Go2's nominal rates.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np

from hw import go2_msgs
from hw.mcap_io import read_mcap, write_mcap
from hw.recorder import LEGS, Recorder, RecorderConfig
from hw.ringbuffer import RingBuffer


def per_call_ns(fn, n: int, repeats: int = 5) -> float:
    """Best-of-``repeats`` mean cost of ``fn()`` in ns (best: least disturbed by other load)."""
    best = float("inf")
    for _ in range(repeats):
        t0 = time.perf_counter_ns()
        for _ in range(n):
            fn()
        best = min(best, (time.perf_counter_ns() - t0) / n)
    return best


def timed(fn, repeats: int = 3):
    best, out = float("inf"), None
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - t0)
    return best, out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=120.0, help="history the rings hold")
    ap.add_argument("--n", type=int, default=20000, help="calls per writer measurement")
    args = ap.parse_args()

    cfg = RecorderConfig(seconds=args.seconds)
    rec = Recorder(cfg)
    rng = np.random.default_rng(0)
    q, dq, tau = rng.normal(size=(3, 12)).astype(np.float32)
    quat = np.array([1, 0, 0, 0], np.float32)
    gyro, acc = rng.normal(size=(2, 3)).astype(np.float32)
    raw_ls = go2_msgs.encode_lowstate(q, dq, tau, quat, gyro, acc, tick=1)
    cmd = go2_msgs.new_lowcmd()
    kp, kd = np.full(12, 20.0, np.float32), np.full(12, 0.5, np.float32)
    cmd.set_motors(q, dq, kp, kd, tau)
    raw_lc = cmd.finalize()
    raw_wl = go2_msgs.encode_wireless_controller(keys=1, lx=0.5)
    clock = iter(range(1, 1 << 62))

    writers = {
        "record_lowstate (1180 B + decoded)": (
            lambda: rec.record_lowstate(next(clock), raw_ls, q, dq, tau, quat, gyro, acc, 7),
            cfg.lowstate_hz),
        "record_lowcmd (812 B + 5x12)": (
            lambda: rec.record_lowcmd(next(clock), raw_lc, q, dq, kp, kd, tau), cfg.lowcmd_hz),
        "record_wireless (24 B)": (lambda: rec.record_wireless(next(clock), raw_wl),
                                   cfg.wireless_hz),
        "record_imu (one foot)": (
            lambda: rec.record_imu("FL", next(clock), 5, 6, 7, 1, gyro, acc, quat),
            cfg.imu_hz * len(LEGS)),
        "record_event (64 B text)": (lambda: rec.record_event(next(clock), "STAND -> TRIPOD"),
                                     0.0),
    }
    small = RingBuffer(np.dtype([("t_host_ns", "i8"), ("q", "f4", (3,)), ("k", "u2")]), 4096)
    row = np.zeros(1, small.dtype)[0]
    v3 = np.zeros(3, np.float32)
    ring_ops = {
        "RingBuffer.append(**fields) 3 fields": lambda: small.append(t_host_ns=1, q=v3, k=2),
        "RingBuffer.append_row(*values) 3 fields": lambda: small.append_row(1, v3, 2),
        "RingBuffer.write_from(record)": lambda: small.write_from(row),
    }

    print(f"Recorder writers (best of 5 x {args.n} calls; GIL held, one thread)")
    print(f"{'writer':40s} {'ns/sample':>10s} {'rate Hz':>9s} {'CPU %':>7s}")
    share = 0.0
    for name, (fn, rate) in writers.items():
        ns = per_call_ns(fn, args.n)
        cpu = ns * 1e-9 * rate * 100
        share += cpu
        print(f"{name:40s} {ns:10.0f} {rate:9.0f} {cpu:7.3f}")
    print(f"{'all writers at nominal rates':40s} {'':10s} {'':9s} {share:7.3f}")
    for name, fn in ring_ops.items():
        print(f"{name:40s} {per_call_ns(fn, args.n):10.0f}")

    # Fill every ring to capacity, then time the copies the calibrator makes.
    rec = Recorder(cfg)
    t_fill = time.perf_counter()
    n_ls = cfg.capacity("lowstate")
    for k in range(n_ls):
        rec.record_lowstate(2_000_000 * k, raw_ls, q, dq, tau, quat, gyro, acc, k)
    for k in range(cfg.capacity("lowcmd")):
        rec.record_lowcmd(20_000_000 * k, raw_lc, q, dq, kp, kd, tau)
    for leg in LEGS:
        for k in range(cfg.capacity(f"imu/{leg}")):
            rec.record_imu(leg, 1_000_000 * k, k, k, k % 65536, 1, gyro, acc, quat)
    t_fill = time.perf_counter() - t_fill
    span_ns = 2_000_000 * n_ls
    mem = rec.memory_bytes()
    print(f"\nRings full: {args.seconds:g} s of history, {mem / 2**20:.1f} MiB fixed "
          f"(filled in {t_fill:.1f} s)")
    print(f"{'reader':40s} {'ms':>9s} {'rows':>9s} {'MB/s':>8s}")
    t_snap, snap = timed(rec.snapshot)
    rows = sum(snap.stream(n).shape[0] for n in snap.stream_names)
    nbytes = sum(snap.stream(n).nbytes for n in snap.stream_names)
    print(f"{'snapshot() everything':40s} {t_snap * 1e3:9.1f} {rows:9d} "
          f"{nbytes / t_snap / 1e6:8.0f}")
    t_win, win = timed(lambda: rec.snapshot(span_ns - 10_000_000_000, span_ns))
    rows_w = sum(win.stream(n).shape[0] for n in win.stream_names)
    print(f"{'snapshot(t0, t1) last 10 s':40s} {t_win * 1e3:9.1f} {rows_w:9d}")

    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "bench.mcap"
        t_w, _ = timed(lambda: write_mcap(path, win, {"bench": True}), repeats=1)
        size = path.stat().st_size
        t_r, _ = timed(lambda: read_mcap(path), repeats=1)
    msgs = rows_w
    print(f"\nMCAP of the last 10 s ({msgs} messages, {size / 2**20:.1f} MiB zstd)")
    print(f"{'write_mcap':40s} {t_w * 1e3:9.0f} ms  {t_w / msgs * 1e9:8.0f} ns/message")
    print(f"{'read_mcap':40s} {t_r * 1e3:9.0f} ms  {t_r / msgs * 1e9:8.0f} ns/message")


if __name__ == "__main__":
    main()
