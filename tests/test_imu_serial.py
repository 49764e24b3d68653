"""ClockMapper accuracy, PtyPair, and SerialImuReader end to end on a real pty."""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest
import serial
from loopback import wait_until

from hw.clock_sync import ClockMapper
from hw.hipnuc import encode_imu_frame
from hw.imu_protocol import ImuFrame, encode_frame
from hw.imu_serial import ImuReaderError, SerialImuReader
from hw.pty_link import PtyPair

LEGS = {0: "FR", 1: "FL", 2: "RR", 3: "RL"}


# -- ClockMapper ----------------------------------------------------------------


def simulate(drift, seconds=12.0, rate=200.0, seed=0, dev_start_s=5000.0, spikes=0.01):
    """(device ns, host receive ns, true host ns of the sample) for a drifting clock."""
    rng = np.random.default_rng(seed)
    n = int(seconds * rate)
    t_true = 77.0 + np.arange(n) / rate  # host seconds at which each sample was taken
    dev = dev_start_s + (t_true - 77.0) / (1.0 + drift)
    lat = rng.exponential(1e-3, n)
    lat[rng.random(n) < spikes] += 0.020
    host = t_true + lat
    return (np.round(dev * 1e9).astype(np.int64), np.round(host * 1e9).astype(np.int64),
            np.round(t_true * 1e9).astype(np.int64))


def run_mapper(mapper, dev, host):
    return np.array([mapper.update(int(d), int(h)) for d, h in zip(dev, host)])


@pytest.mark.parametrize("drift", [100e-6, -100e-6, 0.0, 37e-6])
def test_clock_mapper_accuracy_with_drift_and_latency_spikes(drift):
    dev, host, true = simulate(drift, seed=int(abs(drift) * 1e7))
    m = ClockMapper()
    mapped = run_mapper(m, dev, host)
    err = (mapped - true)[3 * 200:] * 1e-9  # after 3 s
    assert np.abs(err).max() < 0.5e-3
    assert m.drift_ppm == pytest.approx(drift * 1e6, abs=5.0)
    # Naive mapping by the latest receive stamp would be off by the latency itself.
    assert np.abs(host - true).max() * 1e-9 > 10e-3


def test_clock_mapper_batched_host_stamps():
    # The reader stamps every frame of one read() with the same host time.
    dev, host, true = simulate(80e-6, seconds=8.0, seed=4)
    batched = host.copy()
    for k in range(0, len(host), 4):
        batched[k:k + 4] = host[min(k + 3, len(host) - 1)]
    mapped = run_mapper(ClockMapper(), dev, batched)
    assert np.abs(mapped - true)[600:].max() * 1e-9 < 0.5e-3


@pytest.mark.parametrize("seed", range(4))
def test_clock_mapper_never_ties_or_steps_back(seed):
    # 400 Hz, 1 ms device stamps, reads of 1-6 frames under one host stamp from the first frame
    # on, and 5 % latency spikes: the mapped stamps the recorder interpolates on must rise.
    dev, host, true = simulate(60e-6, seconds=8.0, rate=400.0, seed=seed, spikes=0.05)
    dev = dev // 1_000_000 * 1_000_000
    rng = np.random.default_rng(seed)
    batched, k = host.copy(), 0
    while k < len(host):
        n = int(rng.integers(1, 7))
        batched[k:k + n] = host[min(k + n, len(host)) - 1]
        k += n
    mapped = run_mapper(ClockMapper(), dev, batched)
    assert np.all(np.diff(mapped) > 0)
    assert np.abs(mapped - true)[1200:].max() * 1e-9 < 1.5e-3


def test_clock_mapper_unwraps_device_counter():
    wrap = 4_000_000_000  # a 4 s counter wraps three times in 12 s
    dev, host, true = simulate(-60e-6, seed=5, dev_start_s=1.0)
    m = ClockMapper(wrap_period_ns=wrap)
    mapped = run_mapper(m, dev % wrap, host)
    assert m.wraps == 3 and m.resets == 0
    assert np.abs(mapped - true)[600:].max() * 1e-9 < 0.5e-3


@pytest.mark.parametrize("jump_s", [-4000.0, +2.0])
def test_clock_mapper_recovers_from_device_clock_reset(jump_s):
    dev, host, true = simulate(50e-6, seconds=14.0, seed=6)
    k = len(dev) // 2
    dev = dev.copy()
    dev[k:] += int(jump_s * 1e9)  # reboot (backwards) or a forward jump
    m = ClockMapper()
    mapped = run_mapper(m, dev, host)
    assert m.resets == 1
    assert np.abs(mapped - true)[k + 600:].max() * 1e-9 < 0.5e-3


def test_clock_mapper_bad_arguments():
    with pytest.raises(ValueError):
        ClockMapper(bin_s=30.0, window_s=20.0)
    with pytest.raises(ValueError):
        ClockMapper(wrap_period_ns=0)
    with pytest.raises(ValueError):
        ClockMapper(max_slew=1.0)
    with pytest.raises(ValueError):
        ClockMapper().map(0)
    with pytest.raises(ValueError):
        ClockMapper(wrap_period_ns=1000).update(1000, 0)


# -- PtyPair / SerialImuReader ------------------------------------------------------------


def imu_frame(node, k, t_us):
    w = 2 * np.pi * 1.5 * t_us * 1e-6
    return ImuFrame(node, k % 65536, t_us, (np.sin(w), np.cos(w), 0.1 * node),
                    (0.0, 0.0, 9.81), (1.0, 0.0, 0.0, 0.0))


def paced_writer(pair, rate_hz, seconds, nodes, encode=encode_frame, stop_after=None):
    """Write one frame per node every 1/rate_hz s; device clock = 10 s + elapsed."""
    t0 = time.monotonic()
    n = int(rate_hz * seconds)
    for k in range(n):
        target = t0 + k / rate_hz
        delay = target - time.monotonic()
        if delay > 0:
            time.sleep(delay)
        t_us = 10_000_000 + round(k * 1e6 / rate_hz)
        pair.write(b"".join(encode(imu_frame(node, k, t_us)) for node in nodes))
        if stop_after is not None and k + 1 == stop_after:
            return


def test_pty_pair_basics():
    with PtyPair() as pair:
        port = serial.Serial(pair.port_path, 921600, timeout=0.5)
        pair.write(b"\x00\x0d\x0a\x11\x13\xff")  # raw: no CR/LF mangling, no XON/XOFF
        assert port.read(6) == b"\x00\x0d\x0a\x11\x13\xff"
        port.write(b"AT+EOUT=1\r\n")
        assert pair.read(64, timeout_s=0.5) == b"AT+EOUT=1\r\n"
        port.close()
    assert pair.closed
    with pytest.raises(OSError):
        pair.write(b"x")


def test_four_imus_200hz_two_seconds_nothing_lost():
    with PtyPair() as pair:
        reader = SerialImuReader(pair.port_path, node_map=LEGS).start()
        try:
            paced_writer(pair, 200.0, 2.0, nodes=range(4))
            deadline = time.monotonic() + 2.0
            while reader.stats()["samples"] < 1600 and time.monotonic() < deadline:
                time.sleep(0.01)
            samples = reader.drain()
            st = reader.stats()
        finally:
            reader.stop()
    assert len(samples) == 1600
    assert st["crc_errors"] == 0 and st["bytes_discarded"] == 0
    assert st["seq_gaps_total"] == 0 and st["queue_overflows"] == 0
    for node, leg in LEGS.items():
        mine = [s for s in samples if s.node_id == node]
        assert len(mine) == 400 and all(s.name == leg for s in mine)
        assert [s.seq for s in mine] == list(range(400))
        t_host = np.array([s.t_host_ns for s in mine])
        t_map = np.array([s.t_mapped_ns for s in mine])
        t_dev = np.array([s.t_device_ns for s in mine])
        assert np.all(np.diff(t_host) >= 0)
        assert np.all(np.diff(t_map) > 0)
        assert np.all(np.diff(t_dev) > 0)
        # Mapped time is the sample's creation time: never after its receipt
        # (beyond fit noise), and the whole stream agrees with the host clock.
        assert np.all(t_map <= t_host + 1_000_000)
        assert np.median(t_host - t_map) < 5e6
        assert mine[10].gyro.shape == (3,) and mine[10].quat.shape == (4,)
    assert reader.state == "stopped" and not reader.running


def test_unplugged_port_surfaces_error_quickly():
    errors = []
    with PtyPair() as pair:
        reader = SerialImuReader(
            pair.port_path, on_error=lambda e: errors.append((time.monotonic(), e))
        ).start()
        paced_writer(pair, 200.0, 0.3, nodes=range(2))
        t_unplug = time.monotonic()
        pair.hang_up()
        deadline = t_unplug + 2.0
        while not errors and time.monotonic() < deadline:
            time.sleep(0.005)
        assert errors, "unplug was not reported"
        assert errors[0][0] - t_unplug < 0.5
        assert isinstance(reader.error, (serial.SerialException, OSError))
        assert reader.state == "error"
        assert len(reader.drain()) > 0  # what arrived before the unplug is kept
        with pytest.raises(ImuReaderError):
            reader.get(timeout_s=1.0)
        reader.stop()
    assert not reader.running


def test_hipnuc_one_imu_per_port_400hz():
    pairs = [PtyPair(), PtyPair()]
    readers = [
        SerialImuReader(p.port_path, protocol="hipnuc",
                        decoder_options={"node_id": i, "rate_hz": 400.0}).start()
        for i, p in enumerate(pairs)
    ]
    try:
        writers = [threading.Thread(target=paced_writer,
                                    args=(p, 400.0, 0.5, [i], encode_imu_frame))
                   for i, p in enumerate(pairs)]
        for w in writers:
            w.start()
        for w in writers:
            w.join()
        # every frame written is read, however long the reader threads were held up
        for r in readers:
            assert wait_until(lambda r=r: r.stats()["samples"] >= 200, 5.0), r.stats()
        for i, r in enumerate(readers):
            got = r.drain()
            assert len(got) == 200 and {s.node_id for s in got} == {i}
            assert r.stats()["seq_gaps_total"] == 0
            assert np.all(np.diff([s.t_mapped_ns for s in got]) > 0)
            assert got[50].accel[2] == pytest.approx(9.81, abs=1e-5)
    finally:
        for r in readers:
            r.stop()
        for p in pairs:
            p.close()


def test_queue_overflow_and_unknown_nodes_are_counted():
    with PtyPair() as pair:
        reader = SerialImuReader(pair.port_path, node_map={0: "FR"}, queue_size=10).start()
        try:
            data = b"".join(encode_frame(imu_frame(n, k, 1000 * k))
                            for k in range(50) for n in (0, 9))
            data = b"\x13\x37garbage" + data
            pair.write(data)
            deadline = time.monotonic() + 2.0
            while reader.stats()["frames"] < 100 and time.monotonic() < deadline:
                time.sleep(0.01)
            st = reader.stats()
        finally:
            reader.stop()
    assert st["frames"] == 100 and st["unknown_node"] == 50
    assert st["samples"] == 50 and st["queue_overflows"] == 40
    assert st["bytes_discarded"] == 9 and reader.queue.qsize() == 10


def test_callback_exception_is_an_error_not_a_dead_thread():
    seen = []

    def boom(sample):
        seen.append(sample)
        raise RuntimeError("consumer bug")

    errors = []
    with PtyPair() as pair:
        reader = SerialImuReader(pair.port_path, on_sample=boom,
                                 on_error=errors.append).start()
        pair.write(encode_frame(imu_frame(0, 0, 0)))
        deadline = time.monotonic() + 2.0
        while reader.error is None and time.monotonic() < deadline:
            time.sleep(0.01)
        reader.stop()
    assert len(seen) == 1 and isinstance(reader.error, RuntimeError)
    assert errors == [reader.error] and reader.state == "error"


def test_open_failure_raises_synchronously():
    with pytest.raises(serial.SerialException):
        SerialImuReader("/dev/does-not-exist-imu").start()
    with pytest.raises(ValueError):
        SerialImuReader("/dev/null", protocol="nmea")


def test_stop_is_prompt_and_idempotent():
    with PtyPair() as pair:
        reader = SerialImuReader(pair.port_path).start()
        t0 = time.monotonic()
        reader.stop()
        reader.stop()
        assert time.monotonic() - t0 < 0.5
        assert not reader.running and reader.state == "stopped"
        assert reader.get(timeout_s=0.05) is None
