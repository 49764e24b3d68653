"""Ring buffer and recorder: wrap, counters, windows, lock-free consistency, no allocation, no loss."""

from __future__ import annotations

import math
import threading
import tracemalloc

import numpy as np
import pytest

from hw.recorder import (
    EVENT_DTYPE,
    LEGS,
    Recorder,
    RecorderConfig,
    imu_dtype,
    lowcmd_dtype,
    lowstate_dtype,
    wireless_dtype,
)
from hw.ringbuffer import RingBuffer, blob_fields

SMALL = np.dtype([("t_host_ns", "i8"), ("q", "f4", (3,)), ("k", "u2")])


def _fill(ring: RingBuffer, n: int, start: int = 0) -> None:
    for k in range(start, start + n):
        ring.append(t_host_ns=10 * k, q=[k, k + 0.5, -k], k=k % 65536)


# ---------------------------------------------------------------- RingBuffer basics


def test_ring_before_wrap_keeps_everything_in_order():
    ring = RingBuffer(SMALL, 8)
    _fill(ring, 5)
    rows = ring.snapshot()
    assert rows["t_host_ns"].tolist() == [0, 10, 20, 30, 40]
    assert rows["q"][3].tolist() == [3.0, 3.5, -3.0]
    assert (ring.total_written, ring.overwritten, len(ring)) == (5, 0, 5)


def test_ring_wraps_and_counts_overwritten_exactly():
    ring = RingBuffer(SMALL, 5)
    _fill(ring, 12)
    rows = ring.snapshot()
    assert rows["t_host_ns"].tolist() == [70, 80, 90, 100, 110]
    assert rows["k"].tolist() == [7, 8, 9, 10, 11]
    assert (ring.total_written, ring.overwritten) == (12, 7)
    # exactly full, wrapped onto slot 0
    ring2 = RingBuffer(SMALL, 4)
    _fill(ring2, 8)
    assert ring2.snapshot()["k"].tolist() == [4, 5, 6, 7]
    res = ring2.read()
    assert (res.total_written, res.overwritten) == (8, 4)


def test_ring_snapshot_is_a_copy():
    ring = RingBuffer(SMALL, 4)
    _fill(ring, 3)
    rows = ring.snapshot()
    _fill(ring, 4, start=3)
    assert rows["k"].tolist() == [0, 1, 2]


def test_ring_window_half_open_and_after_wrap():
    ring = RingBuffer(SMALL, 10)
    _fill(ring, 25)  # holds k = 15..24, t = 150..240
    assert ring.window(170, 200)["k"].tolist() == [17, 18, 19]
    assert ring.window(None, 170)["k"].tolist() == [15, 16]
    assert ring.window(235, None)["k"].tolist() == [24]
    assert ring.window(0, 100).shape == (0,)
    assert ring.window(None, None)["k"].tolist() == list(range(15, 25))
    assert ring.window(150, 160, time_field="t_host_ns")["k"].tolist() == [15]
    with pytest.raises(ValueError, match="time field"):
        ring.window(0, 1, time_field="nope")


def test_ring_window_on_another_time_field():
    dt = np.dtype([("t_host_ns", "i8"), ("t_device_ns", "i8")])
    ring = RingBuffer(dt, 6)
    for k in range(6):
        ring.append_row(k, 100 - 10 * k)  # device clock runs backwards here: mask, not bisect
    assert ring.window(60, 90, time_field="t_device_ns")["t_host_ns"].tolist() == [2, 3, 4]


def test_ring_rejects_bad_input_and_keeps_state():
    ring = RingBuffer(SMALL, 4)
    _fill(ring, 2)
    with pytest.raises(ValueError, match="missing"):
        ring.append(t_host_ns=1, q=[0, 0, 0])
    with pytest.raises(ValueError, match="unknown"):
        ring.append(t_host_ns=1, q=[0, 0, 0], kk=1)
    with pytest.raises(ValueError, match="needs 3 values"):
        ring.append_row(1, [0, 0, 0])
    with pytest.raises(ValueError):
        ring.append_row(1, [0, 0], 3)  # wrong shape, after t was written into the slot
    assert ring.snapshot()["k"].tolist() == [0, 1]
    _fill(ring, 1, start=2)
    assert ring.snapshot()["k"].tolist() == [0, 1, 2]
    with pytest.raises(ValueError):
        RingBuffer(SMALL, 0)
    with pytest.raises(ValueError):
        RingBuffer(np.dtype("f8"), 4)


def test_ring_failed_append_when_full_drops_only_the_clobbered_row():
    ring = RingBuffer(SMALL, 4)
    _fill(ring, 6)  # holds 2..5
    with pytest.raises(ValueError):
        ring.append_row(999, [0, 0], 3)  # slot of row 2 partly overwritten
    assert ring.snapshot()["k"].tolist() == [3, 4, 5]
    assert (ring.total_written, ring.overwritten) == (6, 3)
    _fill(ring, 1, start=6)
    assert ring.snapshot()["k"].tolist() == [3, 4, 5, 6]
    assert ring.overwritten == 3


def test_ring_write_from_record():
    ring = RingBuffer(SMALL, 3)
    src = np.zeros(2, SMALL)
    src[0] = (5, [1, 2, 3], 7)
    src[1] = (6, [4, 5, 6], 8)
    ring.write_from(src[0])
    ring.write_from(src[1:2])
    assert np.array_equal(ring.snapshot(), src)
    with pytest.raises(ValueError, match="dtype"):
        ring.write_from(np.zeros(1, EVENT_DTYPE)[0])
    with pytest.raises(ValueError, match="one record"):
        ring.write_from(src)


def test_ring_blob_field_length_and_zeroed_tail():
    dt = np.dtype([("t_host_ns", "i8"), *blob_fields("raw", 8)])
    ring = RingBuffer(dt, 2)
    assert ring.field_names == ("t_host_ns", "raw")
    ring.append(t_host_ns=1, raw=b"\xff" * 8)
    ring.append(t_host_ns=2, raw=bytearray(b"\x01\x02\x03"))
    ring.append(t_host_ns=3, raw=memoryview(b"\x09\x08"))  # overwrites the all-0xff slot
    rows = ring.snapshot()
    assert rows["raw_len"].tolist() == [3, 2]
    assert rows["raw"][1].tolist() == [9, 8, 0, 0, 0, 0, 0, 0]
    assert rows["raw"][0, :3].tobytes() == b"\x01\x02\x03"
    with pytest.raises(ValueError, match="at most 8 bytes"):
        ring.append(t_host_ns=4, raw=bytes(9))
    ring.append(t_host_ns=5, raw=np.arange(8, dtype=np.uint8))
    assert ring.snapshot()["raw"][-1].tolist() == list(range(8))
    with pytest.raises(ValueError):
        blob_fields("raw", 0)


# ---------------------------------------------------------------- allocation


def _alloc_over(fn, n: int) -> tuple[int, int]:
    """(net bytes still allocated, peak bytes above start) over n calls of fn, after warm-up."""
    for _ in range(200):
        fn()
    tracemalloc.start()
    try:
        base, _ = tracemalloc.get_traced_memory()
        tracemalloc.reset_peak()
        for _ in range(n):
            fn()
        now, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    return now - base, peak - base


def test_steady_state_append_allocates_nothing():
    ring = RingBuffer(lowstate_dtype(), 64)
    raw = bytes(range(256)) * 4 + bytes(156)
    q = np.linspace(-1, 1, 12)
    quat, gyro, acc = np.array([1.0, 0, 0, 0]), np.zeros(3), np.array([0, 0, 9.81])
    net, peak = _alloc_over(lambda: ring.append_row(7, raw, q, q, q, quat, gyro, acc, 3), 5000)
    assert ring.total_written == 5200 and ring.overwritten == 5200 - 64
    assert net <= 256, f"append_row left {net} bytes allocated over 5000 calls"
    assert peak <= 4096, f"append_row peaked at {peak} bytes"

    small = RingBuffer(SMALL, 16)
    net, peak = _alloc_over(lambda: small.append(t_host_ns=1, q=q[:3], k=2), 5000)
    assert net <= 256 and peak <= 4096, (net, peak)


def test_recorder_writers_allocate_nothing_and_memory_is_fixed():
    cfg = RecorderConfig(seconds=0.5, lowstate_hz=500, lowcmd_hz=50, imu_hz=400)
    rec = Recorder(cfg)
    expected = sum(cfg.capacity(n) * dt.itemsize for n, dt in [
        ("lowstate", lowstate_dtype()), ("lowcmd", lowcmd_dtype()), ("wireless", wireless_dtype()),
        *((f"imu/{leg}", imu_dtype()) for leg in LEGS), ("events", EVENT_DTYPE)])
    assert rec.memory_bytes() == expected
    raw_ls, raw_lc, raw_wl = bytes(1180), bytes(812), bytes(22)
    v12, v4, v3 = np.ones(12, np.float32), np.array([1, 0, 0, 0], np.float32), np.zeros(3)

    def one_tick():
        rec.record_lowstate(1, raw_ls, v12, v12, v12, v4, v3, v3, 9)
        rec.record_lowcmd(1, raw_lc, v12, v12, v12, v12, v12)
        rec.record_wireless(1, raw_wl)
        for leg in LEGS:
            rec.record_imu(leg, 1, 2, 3, 4, 5, v3, v3, v4)

    net, peak = _alloc_over(one_tick, 2000)
    assert net <= 512, f"recorder writers left {net} bytes over 2000 ticks"
    assert peak <= 8192, peak
    assert rec.memory_bytes() == expected
    assert all(w == 2200 for w, _ in rec.counters().values() if w)


# ---------------------------------------------------------------- lock-free readers


def test_snapshot_consistent_under_concurrent_writer():
    """Every copy a reader takes is a run of whole rows, consecutive, none torn, none stale."""
    dt = np.dtype([("t_host_ns", "i8"), *blob_fields("raw", 1180), ("q", "f8", (12,))])
    ring = RingBuffer(dt, 512)
    n_min = 20000
    payloads = [bytes([k]) * 1180 for k in range(256)]
    qs = [np.full(12, float(k)) for k in range(1024)]
    stop = threading.Event()
    enough_reads = threading.Event()

    def writer():  # runs until the reader has looked often enough, however the OS schedules us
        k = 0
        while k < n_min or not enough_reads.is_set():
            ring.append_row(k, payloads[k % 256], qs[k % 1024])
            k += 1
        stop.set()

    checked = {"full": 0, "window": 0, "rows": 0}
    errors: list[str] = []

    def check(rows, res_total, res_over, full):
        t = rows["t_host_ns"]
        if t.size and not np.all(np.diff(t) == 1):
            errors.append("not consecutive")
        if not np.array_equal(rows["q"][:, 0], (t % 1024).astype(float)):
            errors.append("q torn")
        if not np.all(rows["raw"][:, 0] == t % 256) or not np.all(rows["raw"][:, -1] == t % 256):
            errors.append("raw torn")
        if full:
            if t.size != res_total - res_over:
                errors.append(f"count {t.size} != {res_total} - {res_over}")
            if t.size and t[-1] != res_total - 1:
                errors.append("newest row missing")
        checked["rows"] += t.size

    th = threading.Thread(target=writer)
    th.start()
    while not stop.is_set():
        res = ring.read()
        check(res.rows, res.total_written, res.overwritten, True)
        checked["full"] += 1
        t_now = ring.total_written
        res = ring.read(t_now - 300, t_now - 100)
        check(res.rows, res.total_written, res.overwritten, False)
        checked["window"] += 1
        if checked["full"] >= 30:
            enough_reads.set()
    th.join()
    assert not errors, errors[:5]
    assert checked["full"] >= 30 and checked["window"] >= 30, checked
    n_total = ring.total_written
    final = ring.snapshot()
    assert final["t_host_ns"].tolist() == list(range(n_total - 512, n_total))


# ---------------------------------------------------------------- recorder


def test_config_capacities_and_validation():
    cfg = RecorderConfig()
    assert cfg.capacity("lowstate") == math.ceil(120 * 500 * 1.1)
    assert cfg.capacity("imu/RR") == math.ceil(120 * 1000 * 1.1)
    assert cfg.capacity("lowcmd") == math.ceil(120 * 50 * 1.1)
    cfg = RecorderConfig(seconds=2, headroom=1.0, capacity_overrides={"imu/FL": 7})
    assert cfg.capacity("imu/FL") == 7 and cfg.capacity("imu/FR") == 2000
    with pytest.raises(ValueError, match="unknown stream"):
        cfg.capacity("imu/XX")
    for bad in ({"seconds": 0}, {"headroom": 0.5}, {"imu_hz": 0}, {"legs": ("FL", "XX")},
                {"legs": ("FL", "FL")}, {"capacity_overrides": {"nope": 3}},
                {"capacity_overrides": {"lowcmd": 0}}):
        with pytest.raises(ValueError):
            RecorderConfig(**bad)


def test_recorder_streams_fields_and_window():
    rec = Recorder(RecorderConfig(seconds=1, legs=("FL", "RR")))
    rng = np.random.default_rng(3)
    q = rng.normal(size=(10, 12)).astype(np.float32)
    for k in range(10):
        t = 1_000_000 * k
        rec.record_lowstate(t, bytes([k]) * 1180, q[k], q[k] * 2, q[k] * 3, [1, 0, 0, 0],
                            [0.1, 0.2, 0.3], [0, 0, 9.81], 100 + k)
        rec.record_lowcmd(t + 1, bytes([k]) * 812, q[k], -q[k], np.full(12, 20.0),
                          np.full(12, 0.5), np.zeros(12))
        rec.record_imu("FL", t + 2, 5000 + k, t + 1, k, 3, [k, 0, 0], [0, 0, 9.8], [1, 0, 0, 0])
    rec.record_wireless(5, bytes(22))
    rec.record_event(3_000_000, "STAND -> TRIPOD(FL)", code=2)
    snap = rec.snapshot()
    assert snap.lowstate["q"].dtype == np.float32
    assert np.array_equal(snap.lowstate["q"], q)
    assert np.array_equal(snap.lowstate["tau_est"], q * 3)
    assert snap.lowstate["tick"].tolist() == list(range(100, 110))
    assert snap.lowstate["raw_len"].tolist() == [1180] * 10
    assert snap.lowcmd["kp"][0, 0] == 20.0 and snap.lowcmd["raw_len"][0] == 812
    assert snap.imu["FL"]["t_device_ns"].tolist() == list(range(5000, 5010))
    assert snap.imu["RR"].shape == (0,) and set(snap.imu) == {"FL", "RR"}
    assert snap.wireless["raw_len"].tolist() == [22]
    assert snap.events_text() == [(3_000_000, 2, "STAND -> TRIPOD(FL)")]
    assert snap.stream("imu/FL") is snap.imu["FL"]
    assert snap.stream_names == ("lowstate", "lowcmd", "wireless", "imu/FL", "imu/RR", "events")
    assert snap.total_written["imu/FL"] == 10 and snap.overwritten["lowstate"] == 0
    win = rec.snapshot(2_000_000, 4_000_000)
    assert win.lowstate["tick"].tolist() == [102, 103]
    assert win.imu["FL"]["seq"].tolist() == [2, 3]
    assert win.events.shape == (1,) and win.wireless.shape == (0,)
    with pytest.raises(ValueError, match="leg"):
        rec.record_imu("FR", 0, 0, 0, 0, 0, [0, 0, 0], [0, 0, 0], [1, 0, 0, 0])
    with pytest.raises(ValueError):
        snap.stream("imu/FR")


def test_event_text_cut_on_utf8_boundary_and_many_threads():
    rec = Recorder(RecorderConfig(seconds=1, event_capacity=400))
    rec.record_event(1, "é" * 40)  # 80 bytes -> cut to 32 whole characters
    assert rec.snapshot().events_text()[0][2] == "é" * 32

    def emit(base):
        for k in range(100):
            rec.record_event(base + k, f"event {base + k}")

    threads = [threading.Thread(target=emit, args=(1000 * j,)) for j in range(1, 4)]
    for th in threads:
        th.start()
    for th in threads:
        th.join()
    ev = rec.snapshot().events
    assert ev.shape == (301,) and rec.counters()["events"] == (301, 0)
    assert sorted(ev["t_host_ns"].tolist()[1:]) == sorted(
        1000 * j + k for j in range(1, 4) for k in range(100))


def _produce_60s(rec: Recorder, n_imu: int, n_ls: int):
    """Four IMU threads at 400 Hz and one LowState thread at 500 Hz, 60 s of synthetic time."""
    raw = [bytes([k]) * 1180 for k in range(256)]
    q = np.zeros(12, np.float32)
    v3 = np.zeros(3, np.float32)
    quat = np.array([1, 0, 0, 0], np.float32)

    def imu(leg, node):
        for k in range(n_imu):
            t = 2_500_000 * k + node  # 400 Hz
            rec.record_imu(leg, t, t // 1000, t, k % 65536, node, v3, v3, quat)

    def lowstate():
        for k in range(n_ls):
            rec.record_lowstate(2_000_000 * k, raw[k % 256], q, q, q, quat, v3, v3, k)  # 500 Hz

    threads = [threading.Thread(target=imu, args=(leg, n)) for n, leg in enumerate(LEGS)]
    threads.append(threading.Thread(target=lowstate))
    for th in threads:
        th.start()
    # a reader polls the newest 20 ms meanwhile, as the calibrator does: every copy it gets is
    # whole (consecutive ticks, each row's stamp its own) and the count never goes back
    polls, last_total = 0, 0
    while any(th.is_alive() for th in threads):
        total = rec.counters()["lowstate"][0]
        assert total >= last_total
        last_total = total
        ls = rec.snapshot(2_000_000 * (total - 10), 2_000_000 * total).lowstate
        if len(ls):
            ticks = ls["tick"].astype(np.int64)
            assert np.all(np.diff(ticks) == 1) and np.all(ls["t_host_ns"] == 2_000_000 * ticks)
            polls += 1
    for th in threads:
        th.join()
    return polls


def test_loses_nothing_60s_four_imus_and_lowstate():
    n_imu, n_ls = 60 * 400, 60 * 500
    rec = Recorder(RecorderConfig(seconds=60, imu_hz=400, lowstate_hz=500, headroom=1.0))
    assert _produce_60s(rec, n_imu, n_ls) > 0
    snap = rec.snapshot()
    for node, leg in enumerate(LEGS):
        rows = snap.imu[leg]
        assert rows["t_host_ns"].tolist() == [2_500_000 * k + node for k in range(n_imu)]
        assert rows["seq"].tolist() == [k % 65536 for k in range(n_imu)]
        assert np.all(rows["node"] == node)
        assert snap.overwritten[f"imu/{leg}"] == 0 and snap.total_written[f"imu/{leg}"] == n_imu
    ls = snap.lowstate
    assert ls["tick"].tolist() == list(range(n_ls))
    assert np.array_equal(ls["raw"][:, 100], np.arange(n_ls) % 256)
    assert snap.overwritten["lowstate"] == 0 and snap.total_written["lowstate"] == n_ls
    assert all(v == 0 for v in snap.overwritten.values())


def test_smaller_capacity_overwritten_counter_exact():
    n_imu, n_ls = 60 * 400, 60 * 500
    cfg = RecorderConfig(seconds=20, imu_hz=400, lowstate_hz=500, headroom=1.0,
                         capacity_overrides={"imu/RR": 7919})
    rec = Recorder(cfg)
    assert _produce_60s(rec, n_imu, n_ls) > 0
    snap = rec.snapshot()
    for node, leg in enumerate(LEGS):
        cap = cfg.capacity(f"imu/{leg}")
        assert snap.overwritten[f"imu/{leg}"] == n_imu - cap
        assert snap.total_written[f"imu/{leg}"] == n_imu
        assert snap.imu[leg]["t_host_ns"].tolist() == [
            2_500_000 * k + node for k in range(n_imu - cap, n_imu)]
    assert snap.overwritten["lowstate"] == n_ls - 10000
    assert snap.lowstate["tick"].tolist() == list(range(n_ls - 10000, n_ls))
