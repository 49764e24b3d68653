"""The mock robot: real Zenoh on 127.0.0.1, real ptys, lockstep where determinism matters."""

from __future__ import annotations

import json
import threading
import time

import numpy as np
import pytest
from loopback import free_endpoint, wait_until

from calib.joints import LIE_POSE_LEG, STAND_POSE_LEG, full_pose, sdk_indices
from calib.kinematics import closed_form_foot_angular_velocity
from calib.metrics import geodesic_error_deg, rotation_from_rpy_deg
from calib.solver import solve
from hw.go2_msgs import (
    decode_lowstate,
    decode_wireless_controller,
    lowstate_crc,
    new_lowcmd,
)
from hw.imu_serial import ImuReaderError, SerialImuReader
from hw.joystick import key_mask
from hw.mock.config import MockConfig, load_config
from hw.mock.robot import MockRobot
from hw.transport import KEY_LOWCMD, KEY_LOWSTATE, KEY_WIRELESS, Transport, TransportConfig
from sim.model import FOOT_RADIUS

Q_LIE = full_pose(LIE_POSE_LEG, order="sdk")
Q_STAND = full_pose(STAND_POSE_LEG, order="sdk")
NO_IMUS = {"all": {"enabled": False}}


def stand_cmd(i: int, kp: float = 60.0, kd: float = 5.0) -> bytes:
    """Command ``i`` of a 50 Hz stand-up: lying -> stand over 1.5 s, then hold."""
    a = min(1.0, i * 0.02 / 1.5)
    b = new_lowcmd()
    b.set_motors(Q_LIE + (Q_STAND - Q_LIE) * a, np.zeros(12), np.full(12, kp), np.full(12, kd),
                 np.zeros(12))
    return b.finalize()


def hold_cmd(q, kp: float = 60.0, kd: float = 5.0) -> bytes:
    b = new_lowcmd()
    b.set_motors(q, np.zeros(12), np.full(12, kp), np.full(12, kd), np.zeros(12))
    return b.finalize()


def corrupt(frame: bytes) -> bytes:
    bad = bytearray(frame)
    bad[-1] ^= 0x5A  # the crc's last byte
    return bytes(bad)


class LockstepClient:
    """A 50 Hz controller driving a lockstep mock: wait for the quantum's last lowstate (its
    tick), then send the next command."""

    def __init__(self, endpoint: str, quantum_ms: int = 20):
        self.t = Transport(TransportConfig(connect=[endpoint])).open()
        self.lv = self.t.latest(KEY_LOWSTATE)
        self.pub = self.t.publisher(KEY_LOWCMD)
        self.quantum_ms = quantum_ms
        self.received: dict[int, bytes] = {}
        self.t.subscribe(KEY_LOWSTATE, self._keep)
        self.tick = self.wait_tick(None)
        # the mock repeats its lowstate while idle: wait until the second subscriber has it too
        assert wait_until(lambda: self.tick in self.received, 5.0)

    def _keep(self, payload: bytes, t_ns: int) -> None:
        self.received.setdefault(decode_lowstate(payload).tick, payload)

    def wait_tick(self, tick: int | None, timeout: float = 5.0) -> int:
        deadline = time.monotonic() + timeout
        count = 0
        while True:
            v = self.lv.wait_new(count, max(0.0, deadline - time.monotonic()))
            assert v is not None, f"no lowstate with tick {tick} within {timeout} s"
            payload, _, count = v
            got = decode_lowstate(payload).tick
            if tick is None or got >= tick:
                return got

    def step(self, payload: bytes) -> bytes:
        self.pub.put(payload)
        self.tick = self.wait_tick(self.tick + self.quantum_ms)
        return self.lv.get()[0]

    def close(self) -> None:
        self.t.close()


@pytest.fixture
def lockstep_mock():
    robots = []

    def make(**kw):
        ep = free_endpoint()
        # LockstepClient is a plain 50 Hz controller, one rt/lowcmd per 20 ms quantum
        kw.setdefault("lockstep_quantum_s", 0.02)
        cfg = MockConfig(listen=[ep], clock="lockstep", **kw)
        r = MockRobot(cfg).start()
        robots.append(r)
        return r, ep

    yield make
    for r in robots:
        r.stop()


# -- end to end over Zenoh ---------------------------------------------------------------

def test_stand_up_over_zenoh_and_lockstep_is_deterministic(lockstep_mock):
    robot, ep = lockstep_mock(foot_imus=NO_IMUS)
    client = LockstepClient(ep)
    try:
        assert client.tick == 1000  # tick_epoch_s = 1 s at sim time 0
        n = 125  # 2.5 s: 1.5 s interpolation + 1 s hold
        for i in range(n):
            last = client.step(stand_cmd(i))
        wait_until(lambda: len(client.received) == 10 * n + 1, 2.0)
        received = dict(client.received)
    finally:
        client.close()
    v = decode_lowstate(last)
    assert v.tick == 1000 + 20 * n
    err = np.abs(v.q - Q_STAND)
    # Hips and thighs reach the pose; the calves sag by the gravity torque over kp (a PD
    # joint under load settles at q_des - tau/kp), about 0.08 rad at kp 60.
    assert err.max() < 0.12, err
    assert np.abs(np.delete(v.q - Q_STAND, [2, 5, 8, 11])).max() < 0.05
    np.testing.assert_allclose(v.q, Q_STAND - v.tau_est / 60.0, atol=0.01)
    assert 0.25 < robot.sim.base_pos[2] < 0.40
    assert robot.sim.body_contacts() == []
    assert robot.commands_good == n and robot.commands_bad_crc == 0
    assert len(received) == 10 * n + 1  # every lowstate of every quantum, none lost

    # The same commands in-process give byte-identical lowstates (determinism, and Zenoh
    # carries the bytes unchanged).
    replay: dict[int, bytes] = {}
    cfg = MockConfig(listen=[], clock="lockstep", foot_imus=NO_IMUS, lockstep_quantum_s=0.02)
    with MockRobot(cfg, transport=False, on_lowstate=lambda d, t: replay.setdefault(t, d)) as r2:
        r2.advance(0.0)
        for i in range(n):
            r2.handle_lowcmd(stand_cmd(i))
            r2.advance()
    assert replay == received


def test_bad_crc_command_is_ignored_counted_and_still_advances_time(lockstep_mock):
    robot, ep = lockstep_mock(foot_imus=NO_IMUS, base="fixed")
    client = LockstepClient(ep)
    try:
        for _ in range(10):
            client.step(hold_cmd(Q_LIE))
        q_before = decode_lowstate(client.lv.get()[0]).q.copy()
        tick0 = client.tick
        for i in range(25):
            client.step(corrupt(stand_cmd(200)))  # the full stand pose, wrong crc
        client.step(b"\x00\x01\x00\x00" + bytes(20))  # malformed: wrong size
        v = decode_lowstate(client.lv.get()[0])
    finally:
        client.close()
    assert v.tick == tick0 + 26 * 20  # every rt/lowcmd sample is a lockstep tick
    assert np.abs(v.q - q_before).max() < 0.01  # nothing moved toward the stand pose
    assert np.abs(v.q - Q_STAND).max() > 0.5
    assert robot.commands_good == 10
    assert robot.commands_bad_crc == 25
    assert robot.commands_malformed == 1


def test_lowstate_wire_format_rate_and_joystick_in_realtime():
    ep = free_endpoint()
    cfg = MockConfig(listen=[ep], clock="realtime", foot_imus=NO_IMUS,
                     joystick=[{"t_s": 0.8, "keys": ["L2", "A"], "duration_s": 0.4}])
    cfg = MockConfig.from_dict(cfg.to_dict())
    robot = MockRobot(cfg).open()
    client = Transport(TransportConfig(connect=[ep])).open()
    q = client.queue(KEY_LOWSTATE, maxlen=10000)
    wq = client.queue(KEY_WIRELESS, maxlen=1000)
    robot.start()
    try:
        assert wait_until(lambda: q.received > 0, 5.0)
        time.sleep(2.2)
        # none lost on the way: everything it had published arrives (while it runs: a stopped
        # session drops what is still in flight)
        sent = robot.stats()["lowstates_published"]
        assert wait_until(lambda: q.received >= sent, 5.0), (q.received, sent)
        samples = q.drain()
        wireless = wq.drain()
        st = robot.stats()
    finally:
        robot.stop()
        client.close()
    assert len(samples) >= sent > 900
    ticks = []
    for s in samples:
        assert len(s.payload) == 1180
        assert s.payload[:4] == b"\x00\x01\x00\x00"
        v = decode_lowstate(s.payload)
        assert v.crc == lowstate_crc(s.payload)
        ticks.append(v.tick)
    # the realtime tick is the mock's wall clock: 2 ms per message on average (a mock the OS
    # held up publishes what it owes in a burst, a few at one tick: checked over the span)
    d = np.diff(ticks)
    assert d.min() >= 0
    if st["resyncs"] == 0:  # (a resync skips simulated time the wall clock has passed)
        assert abs((ticks[-1] - ticks[0]) - 2 * (len(ticks) - 1)) <= 20, st
    t = np.array([s.t_ns for s in samples]) * 1e-9
    span = samples[-1].t_ns - samples[0].t_ns
    mask = t - t[0] <= 2.0
    rate = (mask.sum() - 1) / (t[mask][-1] - t[0])
    assert abs(rate - 500.0) < 25.0, (rate, span, st)
    # the scripted press: in both wireless_remote (bytes 2-3) and rt/wirelesscontroller
    want = key_mask("L2", "A")
    remote_keys = [int.from_bytes(bytes(decode_lowstate(s.payload).wireless_remote[2:4]),
                                  "little") for s in samples]
    pressed = [tk for tk, k in zip(ticks, remote_keys) if k == want]
    # the press is scripted in simulated time, the tick is the wall clock's: they part by up to
    # resync_after_s before the mock resynchronises (a loaded machine)
    slack = 5 + 1000 * cfg.resync_after_s
    assert pressed and abs(min(pressed) - 1800) <= slack and abs(max(pressed) - 2198) <= slack
    assert set(remote_keys) == {0, want}
    wkeys = [int(decode_wireless_controller(w.payload)["keys"]) for w in wireless]
    assert want in wkeys and 0 in wkeys
    assert 20 <= wkeys.count(want) <= 21  # 0.4 s at 50 Hz


# -- foot IMU ports ----------------------------------------------------------------------

def _collect(reader: SerialImuReader, n: int, timeout: float = 5.0) -> list:
    out = []
    deadline = time.monotonic() + timeout
    while len(out) < n and time.monotonic() < deadline:
        s = reader.get(timeout_s=0.05)
        if s is not None:
            out.append(s)
    return out


def test_foot_imu_ports_rate_garbage_and_hang_up():
    cfg = MockConfig(listen=[], clock="lockstep", initial_pose="standing", foot_imus={
        "all": {"enabled": False},
        "FL": {"enabled": True, "rate_hz": 400, "time_offset_s": 0.03},
        "RR": {"enabled": True, "rate_hz": 200, "time_offset_s": -0.02, "dropout_prob": 0.05},
    })
    with MockRobot(cfg, transport=False) as robot:
        ports = robot.imu_ports
        assert set(ports) == {"FL", "RR"}
        readers = {leg: SerialImuReader(p).start() for leg, p in ports.items()}
        try:
            robot.advance(0.0)
            for _ in range(10):  # 1 s of sim time in 0.1 s chunks
                robot.advance(0.1)
                time.sleep(0.01)
            truth = robot.truth()
            # sample instants phase + k / rate in [0, 1] s
            n_fl = int((1.0 - truth["FL"]["phase_s"]) * 400 + 1e-9) + 1
            n_rr = int((1.0 - truth["RR"]["phase_s"]) * 200 + 1e-9) + 1
            ch = robot.channels
            fl = _collect(readers["FL"], n_fl)
            rr = _collect(readers["RR"], ch["RR"].samples)
            assert ch["FL"].frames_dropped == 0 and ch["RR"].frames_dropped == 0
            # FL: every sample at 400 Hz, 2500 us apart on the device clock
            assert len(fl) == ch["FL"].samples == n_fl
            assert set(np.diff([s.t_device_ns for s in fl])) <= {2_499_000, 2_500_000, 2_501_000}
            assert [s.seq for s in fl] == list(range(n_fl))
            assert all(s.node_id == 1 for s in fl)
            # RR: 200 Hz with 5 % dropouts: the gaps show in seq, the rest arrives
            assert len(rr) == ch["RR"].samples and 0.9 * n_rr < len(rr) < n_rr
            assert rr[-1].seq + 1 - len(rr) == readers["RR"].stats()["seq_gaps_total"] + rr[0].seq
            # time offset in lockstep: t_device = sim time of the motion + epoch + t_d
            assert fl[0].t_device_ns == round((truth["FL"]["phase_s"] + 1.0 + 0.03) * 1e6) * 1000

            # garbage is discarded by the decoder, frames keep coming
            assert robot.inject_garbage("FL", 100) == 100
            robot.advance(0.1)
            more = _collect(readers["FL"], 40)
            assert len(more) == 40 and more[0].seq == n_fl
            assert readers["FL"].stats()["bytes_discarded"] == 100
            assert readers["FL"].stats()["crc_errors"] == 0

            # hang-up: the reader fails loudly
            robot.close_imu_port("RR")
            robot.advance(0.1)
            assert wait_until(lambda: readers["RR"].state == "error", 3.0)
            with pytest.raises(ImuReaderError):
                while True:
                    readers["RR"].get(timeout_s=0.5)
            assert readers["FL"].state == "running"
        finally:
            for r in readers.values():
                r.stop()


def test_garbage_probability_is_survived():
    cfg = MockConfig(listen=[], clock="lockstep", foot_imus={
        "all": {"enabled": False},
        "FR": {"enabled": True, "rate_hz": 200, "garbage_prob": 0.3, "garbage_max_bytes": 8},
    })
    with MockRobot(cfg, transport=False) as robot:
        reader = SerialImuReader(robot.imu_ports["FR"]).start()
        try:
            robot.advance(0.5)
            n = robot.channels["FR"].samples
            got = _collect(reader, n)
            assert n >= 100 and len(got) == n
            assert [s.seq for s in got] == list(range(n))
            assert reader.stats()["bytes_discarded"] == robot.channels["FR"].garbage_bytes > 0
        finally:
            reader.stop()


def test_calibration_recovers_the_mock_truth():
    """The mock's conventions are the calibration's: the correlation solver, fed the mock's
    lowstates (t_E = tick) and FL's frames from its pty (t_I = device stamp), finds the
    configured rotation and time offset."""
    r_true = rotation_from_rpy_deg(25.0, -40.0, 110.0)
    cfg = MockConfig(listen=[], clock="lockstep", base="fixed", initial_pose="standing",
                     seed=3, lockstep_quantum_s=0.02, foot_imus={"all": {"enabled": False},
                                        "FL": {"enabled": True, "rate_hz": 400,
                                               "rotation_matrix": r_true.tolist(),
                                               "time_offset_s": -0.0437}})
    enc: list[tuple[int, np.ndarray, np.ndarray]] = []
    idx = sdk_indices("FL")

    def keep(data, tick):
        v = decode_lowstate(data)
        enc.append((tick, v.q[idx].astype(float), v.dq[idx].astype(float)))

    # hip fast, thigh + calf slow and wide: the foot axis swings, kappa(S_FF) about 4
    amp = np.array([0.5, 0.5, 0.4])
    freq = np.array([1.5, 0.4, 0.6])
    ph = np.array([0.0, 0.0, 0.5])
    with MockRobot(cfg, transport=False, on_lowstate=keep) as robot:
        reader = SerialImuReader(robot.imu_ports["FL"]).start()
        frames = []
        try:
            robot.advance(0.0)
            for i in range(300):  # 6 s at 50 Hz
                t = i * 0.02
                q = Q_STAND.copy()
                dq = np.zeros(12)
                q[idx] += amp * np.sin(2 * np.pi * freq * t + ph)
                dq[idx] = amp * 2 * np.pi * freq * np.cos(2 * np.pi * freq * t + ph)
                b = new_lowcmd()
                b.set_motors(q, dq, np.full(12, 40.0), np.full(12, 1.0), np.zeros(12))
                robot.handle_lowcmd(b.finalize())
                robot.advance()
                if i % 5 == 4:
                    frames += reader.drain()
                    time.sleep(0.002)
            frames += _collect(reader, robot.channels["FL"].samples - len(frames))
        finally:
            reader.stop()
        assert len(frames) == robot.channels["FL"].samples
    t_e = np.array([e[0] for e in enc]) * 1e-3
    w_f = closed_form_foot_angular_velocity(np.array([e[1] for e in enc]),
                                            np.array([e[2] for e in enc]))
    t_i = np.array([f.t_device_ns for f in frames]) * 1e-9
    w_i = np.array([f.gyro for f in frames])
    res = solve(t_e, w_f, t_i, w_i)
    assert abs(res.time_offset - (-0.0437)) < 1e-3, res.time_offset
    assert geodesic_error_deg(res.rotation, r_true) < 1.0


# -- determinism, config and truth -------------------------------------------------------

def _run_inprocess(seed: int, n: int = 20) -> list[bytes]:
    out: list[bytes] = []
    cfg = MockConfig(listen=[], clock="lockstep", seed=seed, encoder_q_noise_std=1e-3,
                     body_gyro_noise_density=1e-3, foot_imus=NO_IMUS, lockstep_quantum_s=0.02)
    with MockRobot(cfg, transport=False, on_lowstate=lambda d, t: out.append(d)) as r:
        r.advance(0.0)
        for i in range(n):
            r.handle_lowcmd(stand_cmd(i))
            r.advance()
    return out


def test_lockstep_same_seed_same_bytes_other_seed_other_bytes():
    a, b, c = _run_inprocess(5), _run_inprocess(5), _run_inprocess(6)
    assert len(a) == 201
    assert a == b
    assert a != c


def test_truth_file_matches_config(tmp_path):
    path = tmp_path / "truth.json"
    cfg = MockConfig(listen=[], clock="lockstep", seed=11, truth_path=str(path), foot_imus={
        "FL": {"rotation_rpy_deg": [10.0, 20.0, 30.0], "time_offset_s": 0.05, "node_id": 7},
        "FR": {"enabled": False},
    })
    with MockRobot(cfg, transport=False) as robot:
        truth = json.loads(path.read_text())
        ports = robot.imu_ports
    assert set(truth) == {"FL", "RL", "RR"}
    fl = truth["FL"]
    np.testing.assert_allclose(fl["rotation_matrix"], rotation_from_rpy_deg(10, 20, 30),
                               atol=1e-12)
    np.testing.assert_allclose(fl["rpy_deg"], [10, 20, 30], atol=1e-9)
    assert fl["time_offset_s"] == 0.05 and fl["node_id"] == 7
    assert fl["foot_frame"] == "FL_foot"
    for leg in ("RL", "RR"):
        r = np.array(truth[leg]["rotation_matrix"])
        np.testing.assert_allclose(r.T @ r, np.eye(3), atol=1e-9)
        assert abs(truth[leg]["time_offset_s"]) <= 0.1
        assert truth[leg]["port"] == ports[leg]
    # the random draws are the seed's: same seed, same truth; another seed, another
    again = MockConfig(listen=[], seed=11, foot_imus=cfg.foot_imus).resolve_imus()
    other = MockConfig(listen=[], seed=12, foot_imus=cfg.foot_imus).resolve_imus()
    np.testing.assert_array_equal(again["RL"].sensor.rotation, truth["RL"]["rotation_matrix"])
    assert other["RL"].sensor.time_offset != truth["RL"]["time_offset_s"]
    # disabling a leg leaves the others' draws alone
    full = MockConfig(listen=[], seed=11).resolve_imus()
    assert full["RR"].sensor.time_offset == truth["RR"]["time_offset_s"]


def test_realtime_offsets_are_realised_as_delays():
    """Realtime: negative offsets delay everything by D = -min t_d; each IMU's frames are
    written t_d + D after the motion, the lowstate D after it."""
    cfg = MockConfig(listen=[], clock="realtime", foot_imus={
        "all": {"enabled": False},
        "FL": {"enabled": True, "time_offset_s": -0.04, "rate_hz": 200},
        "RL": {"enabled": True, "time_offset_s": 0.03, "rate_hz": 200},
    })
    lows: list[tuple[int, int]] = []
    imu: dict[str, list[tuple[int, float]]] = {"FL": [], "RL": []}
    robot = MockRobot(cfg, transport=False,
                      on_lowstate=lambda d, t: lows.append((time.monotonic_ns(), t)),
                      on_imu_frame=lambda leg, d, s: imu[leg].append(
                          (time.monotonic_ns(), s.true_time)))
    assert robot.output_delay_s == pytest.approx(0.04)
    with robot:
        robot.start()
        time.sleep(1.0)
    t0 = robot._start_ns
    low = np.array([(w - t0) * 1e-9 - (t * 1e-3 - 1.0) for w, t in lows])
    # outputs leave up to one physics step late (more on a loaded machine): loose absolute
    # bounds, tight ones on the difference, which is what a host measures. A resync (the mock
    # fell too far behind the wall clock) moves the schedule's origin, so the absolute bounds
    # only hold without one; outputs of the same instant keep their relative delays regardless.
    if robot.max_lateness_s > 0.02:
        # Outputs due while the mock is late leave together, so delays shorter than the
        # lateness cannot be realised: the machine is too loaded for this measurement.
        pytest.skip(f"mock ran {robot.max_lateness_s * 1e3:.0f} ms late (machine overloaded); "
                    "realtime delays below that cannot be checked")
    absolute = robot.resyncs == 0
    if absolute:
        assert np.median(low) == pytest.approx(0.04, abs=0.01)
    for leg, td in (("FL", -0.04), ("RL", 0.03)):
        lag = np.array([(w - t0) * 1e-9 - tau for w, tau in imu[leg]])
        if absolute:
            assert np.median(lag) == pytest.approx(td + 0.04, abs=0.01), leg
        # IMU arrival minus lowstate arrival of the same motion is t_d
        assert np.median(lag) - np.median(low) == pytest.approx(td, abs=0.003), leg


def test_config_files_and_errors(tmp_path):
    y = tmp_path / "m.yaml"
    y.write_text("clock: lockstep\nseed: 4\nfoot_imus:\n  all: {rate_hz: 200}\n"
                 "  RR: {enabled: false}\njoystick:\n  - [1.0, L2+A, 0.5]\n")
    cfg = load_config(y)
    assert cfg.clock == "lockstep" and cfg.seed == 4
    imus = cfg.resolve_imus()
    assert set(imus) == {"FL", "FR", "RL"} and imus["FL"].sensor.rate == 200
    assert cfg.joystick[0].keys == ("L2", "A")
    j = tmp_path / "m.json"
    j.write_text(json.dumps({"clock": "lockstep", "listen": "tcp/127.0.0.1:7999"}))
    assert load_config(j, seed=9).seed == 9
    for text, words in [
        ("clok: lockstep\n", "unknown key 'clok'"),
        ("foot_imus: {FL: {rate: 100}}\n", "unknown key 'rate'"),
        ("foot_imus: {XX: {}}\n", "unknown leg"),
        ("listen: [tcp/127.0.0.1]\n", "proto/host:port"),
        ("clock: fast\n", "clock"),
        ("imu_ports: shared\n", "one 921600-baud port"),
        ("joystick: [[0.5, L9, 0.2]]\n", "unknown key 'L9'"),
        ("lockstep_quantum_s: 0.003\n", "whole number"),
        ("floor_slope_deg: 30\n", "floor_slope_deg"),
        ("floor_slope_deg: 3\nbase: fixed\n", "needs base: free"),
        ("floor_slope_azimuth_deg: .nan\n", "floor_slope_azimuth_deg"),
        ("floor_timeconst_s: 0.001\n", "floor_timeconst_s"),
        ("floor_timeconst_s: soft\n", "floor_timeconst_s"),
        ("lockstep_port_wait_s: -1\n", "lockstep_port_wait_s"),
        ("lockstep_port_wait_s: .inf\n", "lockstep_port_wait_s"),
        ("model_xml: no/such/go2.xml\n", "model_xml must name an MJCF file"),
        ("foot_imus: {FL: {rotation_matrix: [[1, 0, 0], [0, 1, 0], [0, 0, -1]]}}\n",
         "proper rotation"),
        ("[1, 2]\n", "mapping"),
        ("a: [\n", "not valid YAML"),
        # each once a traceback (ZeroDivisionError, OverflowError, AttributeError, TypeError)
        ("physics_hz: 0\n", "physics_hz must be a finite number > 0"),
        ("seed: 1.5\n", "seed must be a whole number"),
        ("seed: .inf\n", "seed must be a whole number"),
        ("motor_temperature_c: .inf\n", "motor_temperature_c must be a whole number in 0..255"),
        ("foot_imus: {FL: {node_id: .inf}}\n", "node_id must be a whole number in 0..255"),
        ("foot_imus: {all: {garbage_max_bytes: .inf}}\n", "garbage_max_bytes"),
        ("foot_imus: [FL]\n", "foot_imus must be a mapping"),
        ("foot_imus: {RR: {mass_kg: -0.05}}\n", "foot_imus.RR.mass_kg must be in"),
        ("foot_imus: {RR: {mass_kg: heavy}}\n", "foot_imus.RR.mass_kg"),
        ("foot_imus: {FL: {rate_hz: 200}, fl: {node_id: 9}}\n", "names a leg twice"),
        ("lockstep_idle_repeat_s: .inf\n", "lockstep_idle_repeat_s"),
        ("lockstep_port_wait_s: 1.0e+300\n", "lockstep_port_wait_s"),
    ]:
        y.write_text(text)
        with pytest.raises(ValueError, match=words) as ei:
            load_config(y)
        assert "\n" not in str(ei.value)
    with pytest.raises(ValueError, match="cannot read"):
        load_config(tmp_path / "missing.yaml")
    # shared port fits at 4 x 200 Hz
    y.write_text("imu_ports: shared\nfoot_imus: {all: {rate_hz: 200}}\n")
    assert load_config(y).imu_ports == "shared"


def test_realtime_draws_no_negative_time_offset_and_so_no_lowstate_delay():
    """A negative offset in realtime delays every lowstate by as much (the loop's latency):
    the drawn ones are made non-negative there, the same magnitudes as lockstep's; one given
    in the config is kept."""
    def offsets(**kw):
        return {leg: r.sensor.time_offset
                for leg, r in MockConfig(listen=[], seed=101, **kw).resolve_imus().items()}

    lock, real = offsets(clock="lockstep"), offsets(clock="realtime")
    assert min(lock.values()) < -0.05  # seed 101 draws FR -77 ms
    assert real == {leg: abs(t) for leg, t in lock.items()}
    with MockRobot(MockConfig(listen=[], clock="realtime", seed=101), transport=False) as robot:
        assert robot.output_delay_s == 0.0
    given = offsets(clock="realtime", foot_imus={"FL": {"time_offset_s": -0.02}})
    assert given["FL"] == -0.02 and given["FR"] == real["FR"]


def test_a_soft_floor_lets_the_lying_robot_sink_in():
    """floor_timeconst_s reaches the simulator: the feet of the lying robot settle deeper into a
    floor that gives than into MuJoCo's default one."""
    sinks = []
    for tc in (0.02, 0.05):
        cfg = MockConfig(listen=[], clock="lockstep", foot_imus=NO_IMUS, floor_timeconst_s=tc)
        with MockRobot(cfg, transport=False) as robot:
            robot.advance(1.0)
            sinks.append(FOOT_RADIUS - robot.sim.foot_positions[:, 2].min())
    assert sinks[0] < 0.001 and sinks[1] > 0.003, sinks  # 0.8 and 3.5 mm


def test_a_sloped_floor_is_what_the_body_imu_reports():
    """The lying robot starts on the tilted floor: its lowstate IMU reads the slope (roll for a
    floor falling away to the side, here +y: the left side down)."""
    got = []
    cfg = MockConfig(listen=[], clock="lockstep", foot_imus=NO_IMUS, floor_slope_deg=6.0,
                     floor_slope_azimuth_deg=90.0)
    with MockRobot(cfg, transport=False, on_lowstate=lambda d, t: got.append(d)) as robot:
        robot.advance(0.0)
        v = decode_lowstate(got[-1])
        assert np.degrees(robot.sim.base_tilt) == pytest.approx(6.0, abs=1e-3)
    roll, pitch, _ = np.degrees(v.rpy)
    assert roll == pytest.approx(-6.0, abs=0.05) and abs(pitch) < 0.05


def test_a_foot_imu_node_weighs_on_its_foot_only_where_it_is_fitted():
    """``mass_kg`` puts the node on the mock's simulated calf (``sim.effects.FootPayload``); a
    disabled IMU carries no node."""
    cfg = MockConfig(listen=[], clock="lockstep",
                     foot_imus={"all": {"mass_kg": 0.06}, "RR": {"enabled": False}})
    assert cfg.foot_payloads() == {"FL": 0.06, "FR": 0.06, "RL": 0.06}
    bare = MockConfig(listen=[], clock="lockstep", foot_imus=NO_IMUS)
    with MockRobot(cfg, transport=False) as robot, MockRobot(bare, transport=False) as plain:
        m, m0 = robot.sim.model, plain.sim.model
        for leg, kg in (("FL", 0.06), ("RR", 0.0)):
            c = m.body(f"{leg}_calf").id
            assert m.body_mass[c] == pytest.approx(m0.body_mass[c] + kg)


def test_shared_port_carries_all_nodes():
    cfg = MockConfig(listen=[], clock="lockstep", imu_ports="shared",
                     foot_imus={"all": {"rate_hz": 200}})
    with MockRobot(cfg, transport=False) as robot:
        ports = set(robot.imu_ports.values())
        assert len(ports) == 1
        reader = SerialImuReader(ports.pop(), node_map={1: "FL", 2: "FR", 3: "RL", 4: "RR"})
        reader.start()
        try:
            robot.advance(0.2)
            n = sum(c.samples for c in robot.channels.values())
            got = _collect(reader, n)
        finally:
            reader.stop()
    assert sorted({s.name for s in got}) == ["FL", "FR", "RL", "RR"]
    assert n >= 4 * 40 and len(got) == n


def test_kill_stops_publishing_at_once():
    cfg = MockConfig(listen=[], clock="realtime", foot_imus={"all": {"enabled": False},
                                                             "FL": {"enabled": True, "time_offset_s": 0.0}})
    count = [0]
    lock = threading.Lock()

    def on_ls(d, t):
        with lock:
            count[0] += 1

    robot = MockRobot(cfg, transport=False, on_lowstate=on_ls)
    with robot:
        robot.start()
        assert wait_until(lambda: count[0] > 50, 3.0)
        robot.kill()
        n = count[0]
        frames = robot.channels["FL"].frames_written + robot.channels["FL"].frames_dropped
        time.sleep(0.2)
        assert count[0] == n
        assert robot.channels["FL"].frames_written + robot.channels["FL"].frames_dropped == frames
        assert not robot.running
