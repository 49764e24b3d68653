"""Mock robot benchmarks: lockstep real-time factor and realtime lowstate latency.

    .venv/bin/python bench/bench_mock.py [--sim-s 5] [--rt-s 5]

1. Lockstep RTF (sim seconds per wall second), the robot standing under a kp 60 / kd 5 hold
   command, 4 foot IMUs at 400 Hz on their own ptys: (a) in-process (handle_lowcmd + advance)
   with no reader on the ports, (b) in-process with a SerialImuReader draining every port,
   (c) over Zenoh on 127.0.0.1 with a 50 Hz lockstep client (waits for the quantum's last
   lowstate, then sends the next command). Without readers (a, c) the full ports drop their
   frames at once (``lockstep_port_wait_s`` 0) instead of waiting for a reader first.
2. Realtime: lowstate latency from the instant it is due (start + tau + D) to its arrival in a
   Zenoh subscriber in the same process, p50 / p99 / max, and the mock's late physics ticks.
"""

from __future__ import annotations

import argparse
import socket
import time

import numpy as np

from calib.joints import STAND_POSE_LEG, full_pose
from hw.go2_msgs import decode_lowstate, new_lowcmd
from hw.imu_serial import SerialImuReader
from hw.mock.config import MockConfig
from hw.mock.robot import MockRobot
from hw.transport import KEY_LOWCMD, KEY_LOWSTATE, Transport, TransportConfig

IMUS_400 = {"all": {"rate_hz": 400}}


def free_endpoint() -> str:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return f"tcp/127.0.0.1:{s.getsockname()[1]}"


def hold_stand() -> bytes:
    b = new_lowcmd()
    b.set_motors(full_pose(STAND_POSE_LEG, order="sdk"), np.zeros(12), np.full(12, 60.0),
                 np.full(12, 5.0), np.zeros(12))
    return b.finalize()


def lockstep_inprocess(sim_s: float, readers: bool) -> float:
    cfg = MockConfig(listen=[], clock="lockstep", initial_pose="standing", foot_imus=IMUS_400,
                     lockstep_quantum_s=0.02,  # a 50 Hz client: one 20 ms quantum per command
                     **({} if readers else {"lockstep_port_wait_s": 0.0}))
    cmd = hold_stand()
    with MockRobot(cfg, transport=False) as r:
        rd = [SerialImuReader(p).start() for p in r.imu_ports.values()] if readers else []
        try:
            r.advance(0.0)
            n = round(sim_s / cfg.lockstep_quantum_s)
            t0 = time.perf_counter()
            for _ in range(n):
                r.handle_lowcmd(cmd)
                r.advance()
            wall = time.perf_counter() - t0
        finally:
            for x in rd:
                x.stop()
    return r.sim_time / wall


def lockstep_zenoh(sim_s: float) -> float:
    ep = free_endpoint()
    cfg = MockConfig(listen=[ep], clock="lockstep", initial_pose="standing", foot_imus=IMUS_400,
                     lockstep_quantum_s=0.02, lockstep_port_wait_s=0.0)
    cmd = hold_stand()
    robot = MockRobot(cfg).start()
    client = Transport(TransportConfig(connect=[ep])).open()
    try:
        lv = client.latest(KEY_LOWSTATE)
        pub = client.publisher(KEY_LOWCMD)
        v = lv.wait_new(0, 5.0)
        tick = decode_lowstate(v[0]).tick
        count = v[2]
        n = round(sim_s / cfg.lockstep_quantum_s)
        t0 = time.perf_counter()
        for _ in range(n):
            pub.put(cmd)
            want = tick + 20
            while tick < want:
                payload, _, count = lv.wait_new(count, 5.0)
                tick = decode_lowstate(payload).tick
        wall = time.perf_counter() - t0
        sim = n * cfg.lockstep_quantum_s
    finally:
        client.close()
        robot.stop()
    return sim / wall


def realtime_latency(seconds: float) -> dict:
    ep = free_endpoint()
    cfg = MockConfig(listen=[ep], clock="realtime", initial_pose="standing", foot_imus=IMUS_400)
    robot = MockRobot(cfg).open()
    client = Transport(TransportConfig(connect=[ep])).open()
    q = client.queue(KEY_LOWSTATE, maxlen=100000)
    time.sleep(0.3)
    robot.start()
    try:
        time.sleep(seconds)
        samples = q.drain()
        st = robot.stats()
    finally:
        robot.stop()
        client.close()
    d = robot.output_delay_s
    lat = []
    for s in samples:
        tau = decode_lowstate(s.payload).tick * 1e-3 - cfg.tick_epoch_s
        lat.append((s.t_ns - robot._start_ns) * 1e-9 - (tau + d))
    lat_ms = np.array(lat) * 1e3
    span = (samples[-1].t_ns - samples[0].t_ns) * 1e-9
    return {"n": len(samples), "rate": (len(samples) - 1) / span, "p50": np.percentile(lat_ms, 50),
            "p99": np.percentile(lat_ms, 99), "max": lat_ms.max(), "late": st["late_ticks"],
            "max_late_ms": st["max_lateness_s"] * 1e3, "resyncs": st["resyncs"],
            "rtf": st["rtf"], "delay_ms": d * 1e3}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sim-s", type=float, default=5.0, help="lockstep sim seconds per case")
    ap.add_argument("--rt-s", type=float, default=5.0, help="realtime wall seconds")
    a = ap.parse_args()
    print("Lockstep real-time factor (standing, 4 foot IMUs at 400 Hz)")
    print(f"{'case':44s} {'RTF':>8s}")
    for name, fn in (("in-process, no port reader", lambda: lockstep_inprocess(a.sim_s, False)),
                     ("in-process, 4 SerialImuReaders", lambda: lockstep_inprocess(a.sim_s, True)),
                     ("Zenoh 127.0.0.1, 50 Hz lockstep client", lambda: lockstep_zenoh(a.sim_s))):
        print(f"{name:44s} {fn():8.2f}")
    r = realtime_latency(a.rt_s)
    print()
    print(f"Realtime ({a.rt_s:g} s, 4 foot IMUs at 400 Hz, output delay D = "
          f"{r['delay_ms']:.1f} ms): lowstate due -> Zenoh subscriber (same process)")
    print(f"{'messages':>9s} {'rate Hz':>8s} {'p50 ms':>7s} {'p99 ms':>7s} {'max ms':>7s} "
          f"{'RTF':>6s} {'late ticks':>10s} {'max late ms':>11s} {'resyncs':>7s}")
    print(f"{r['n']:9d} {r['rate']:8.1f} {r['p50']:7.3f} {r['p99']:7.3f} {r['max']:7.3f} "
          f"{r['rtf']:6.3f} {r['late']:10d} {r['max_late_ms']:11.2f} {r['resyncs']:7d}")


if __name__ == "__main__":
    main()
