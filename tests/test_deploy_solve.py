"""SOLVE's inputs: time bases and the extraction of one leg's streams from the recorder."""

import numpy as np
import pytest

from calib.joints import sdk_indices
from deploy.solve import WindowMark, extract_leg_data, solve_leg
from deploy.timebase import LockstepTimeBase, RealtimeTimeBase, map_lower_envelope
from hw.recorder import Recorder, RecorderConfig


def test_lower_envelope_maps_a_drifting_clock_through_jittery_delivery():
    rng = np.random.default_rng(3)
    n = 10_000  # 20 s at 500 Hz
    t_true = np.arange(n) * 2_000_000 + 5_000_000_000  # host ns when each sample was taken
    dev = np.round((t_true - t_true[0]) * (1 + 80e-6)).astype(np.int64) + 123_000_000_000
    lat = 300_000 + rng.exponential(400_000, n).astype(np.int64)  # 0.3 ms floor
    spikes = rng.random(n) < 0.02
    lat[spikes] += rng.integers(5_000_000, 30_000_000, spikes.sum())
    mapped = map_lower_envelope(dev, t_true + lat)
    err = (mapped - (t_true + 300_000)) * 1e-6  # ms; the floor stays in, as documented
    assert np.abs(err).max() < 0.05
    assert map_lower_envelope(dev[:100], (t_true + lat)[:100]) is None  # 0.2 s: too short


def _recorder_with(ticks_ms, host_ns, imu_dev_ns, legs=("FL",)):
    rec = Recorder(RecorderConfig(seconds=10, legs=legs))
    raw = bytes(1180)
    for k, (tick, h) in enumerate(zip(ticks_ms, host_ns)):
        q = np.arange(12) + 0.001 * k
        rec.record_lowstate(int(h), raw, q, -q, np.zeros(12), [1, 0, 0, 0], [0, 0, 0.1 * k],
                            [0, 0, 9.8], int(tick))
    for j, d in enumerate(imu_dev_ns):
        rec.record_imu("FL", 1_000_000_000 + j, int(d), -1, j, 1, [j, 0, 0], [0, 0, 9.8],
                       [1, 0, 0, 0])
    return rec


def test_extract_on_the_lockstep_clock():
    ticks = 1000 + 2 * np.arange(500)  # ms, 1 s of 500 Hz
    ticks = np.insert(ticks, 100, ticks[99])  # a repeated state (the mock's idle repeat)
    host = 10**9 + np.arange(ticks.size) * 1000
    dev = (1.0 + np.arange(400) / 400.0) * 1e9  # 400 Hz device clock on the same epoch
    rec = _recorder_with(ticks, host, dev)
    d = extract_leg_data(rec.snapshot(), "FL", LockstepTimeBase(), t0=1.3, t1=1.6, pad_s=0.1)
    assert d.t_enc[0] == pytest.approx(1.2) and d.t_enc[-1] == pytest.approx(1.7)
    assert np.all(np.diff(d.t_enc) > 0)  # the repeat is gone
    assert d.t_imu[0] == pytest.approx(1.3) and d.t_imu[-1] == pytest.approx(1.6)
    assert d.q.shape == (len(d.t_enc), 3) and d.gyro.shape == (len(d.t_imu), 3)
    # the leg's own joints (SDK order FR, FL, ...: FL is motors 3-5)
    np.testing.assert_allclose(np.floor(d.q[0]), sdk_indices("FL"))
    np.testing.assert_allclose(d.dq, -d.q, rtol=1e-6)
    assert d.base_omega.shape == (len(d.t_enc), 3)


def test_lockstep_tick_unwraps_across_the_u32_wrap():
    rows = np.zeros(4, dtype=[("tick", "u4")])
    rows["tick"] = [2**32 - 4, 2**32 - 2, 0, 2]
    np.testing.assert_allclose(np.diff(LockstepTimeBase().encoder_times(rows)), 0.002,
                               atol=1e-8)


def test_realtime_uses_mapped_imu_stamps_and_dejittered_encoders():
    rng = np.random.default_rng(0)
    n = 2500
    ticks = 5000 + 2 * np.arange(n)
    host = 7 * 10**9 + np.arange(n) * 2_000_000 + rng.integers(200_000, 900_000, n)
    rec = _recorder_with(ticks, host, [])
    rows = rec.snapshot().lowstate
    tb = RealtimeTimeBase()
    t = tb.encoder_times(rows)
    assert np.abs(np.diff(t) - 0.002).max() < 1e-6  # the robot's tick spacing, no jitter
    assert np.abs(t - host * 1e-9).max() < 1e-3
    raw = RealtimeTimeBase(map_tick=False).encoder_times(rows)
    np.testing.assert_allclose(raw, host * 1e-9)
    imu = np.zeros(3, dtype=[("t_device_ns", "i8"), ("t_mapped_ns", "i8")])
    imu["t_device_ns"] = [5, -1, 7]
    imu["t_mapped_ns"] = [-1, 5, 7]
    assert tb.imu_valid(imu).tolist() == [False, False, True]


def _imu_rows(t_dev_ns, lat_ns):
    rows = np.zeros(len(t_dev_ns), dtype=[("t_host_ns", "i8"), ("t_device_ns", "i8"),
                                          ("t_mapped_ns", "i8")])
    rows["t_device_ns"] = t_dev_ns
    rows["t_host_ns"] = np.asarray(t_dev_ns) + 3 * 10**9 + lat_ns
    rows["t_mapped_ns"] = rows["t_host_ns"]  # the driver's online mapping: not used
    return rows


def test_realtime_imu_times_come_from_the_device_clock():
    rng = np.random.default_rng(2)
    dev = 10**9 + np.arange(8000) * 2_500_000  # 400 Hz, 20 s
    lat = 200_000 + rng.exponential(700_000, dev.size).astype(np.int64)
    t = RealtimeTimeBase().imu_times(_imu_rows(dev, lat))
    assert np.abs(np.diff(t) - 0.0025).max() < 2e-6  # the device's spacing, no delivery jitter
    assert np.abs(t - (dev + 3 * 10**9 + 200_000) * 1e-9).max() < 5e-5


def test_solve_reports_a_missing_window_or_empty_imu_without_raising(tmp_path):
    rec = _recorder_with(1000 + 2 * np.arange(100), 10**9 + np.arange(100) * 10**6, [])
    out = solve_leg(rec, "FL", (None, None), LockstepTimeBase(), tmp_path)
    assert not out.accepted and "window was not recorded" in out.error
    w = (WindowMark(10**9, 1.0), WindowMark(10**9 + 10**8, 1.1))
    out = solve_leg(rec, "FL", w, LockstepTimeBase(), tmp_path)
    assert not out.accepted and "no foot-IMU samples of FL" in out.error
    assert list(tmp_path.iterdir()) == []


def test_realtime_clock_check_refuses_a_clock_that_jumped():
    rng = np.random.default_rng(5)
    n = 5000
    host = 7 * 10**9 + np.arange(n) * 2_000_000 + rng.integers(200_000, 900_000, n)
    ticks = 5000 + 2 * np.arange(n)
    dev = 10**9 + np.arange(4000) * 2_500_000
    imu = _imu_rows(dev, rng.integers(200_000, 900_000, dev.size))
    tb = RealtimeTimeBase()
    steady = _recorder_with(ticks, host, []).snapshot().lowstate
    assert tb.check(steady, imu) == []
    # the robot (or a simulator behind real time) paused 50 ms half-way: its tick no longer
    # follows the host clock on one line
    step = np.where(np.arange(n) > n // 2, 50_000_000, 0)
    jumped = _recorder_with(ticks, host + step, []).snapshot().lowstate
    (reason,) = tb.check(jumped, imu)
    assert reason.startswith("the robot's LowState tick does not follow the host clock")
    # the IMU's clock stepped by 30 ms (a reset, a pause)
    bad = _imu_rows(dev, rng.integers(200_000, 900_000, dev.size))
    bad["t_device_ns"] += np.where(np.arange(dev.size) > 1000, 30_000_000, 0)
    (reason,) = tb.check(steady, bad)
    assert reason.startswith("the foot IMU's clock does not follow the host clock")
    assert LockstepTimeBase().check(jumped, bad) == []


def test_a_wrapped_ring_is_refused_not_solved_on_what_is_left(tmp_path):
    # 10 s of history, 15 s recorded: a window from 2 s on has lost its first 3 s
    n = 7500
    rec = _recorder_with(1000 + 2 * np.arange(n), 10**9 + np.arange(n) * 2 * 10**6,
                         (1.0 + np.arange(6000) / 400.0) * 1e9)
    w = (WindowMark(10**9 + 500 * 2 * 10**6, 2.0), WindowMark(10**9 + 5500 * 2 * 10**6, 12.0))
    out = solve_leg(rec, "FL", w, LockstepTimeBase(), tmp_path)
    assert not out.accepted and "ring wrapped" in out.error and "--record-seconds" in out.error
    assert list(tmp_path.iterdir()) == []


def test_the_worker_outlives_a_job_that_raises(monkeypatch):
    from deploy import solve
    from deploy.solve import SolveJob, SolveWorker

    def broken():  # e.g. matplotlib that cannot import on the robot
        raise ModuleNotFoundError("no matplotlib")

    monkeypatch.setattr(solve, "_warm_figure", broken)
    w = SolveWorker()
    try:
        w.warm_up(timeout=5.0)
        job = SolveJob((), {}, fn=lambda: "solved")
        w._q.put(job)
        job.join(5.0)
        assert job.done() and job.outcome() == "solved"  # the next job still runs
    finally:
        w.close()
