"""``MockRobot``: the simulated Go2 (:class:`sim.go2.Go2Sim`) behind the robot's own wire.

It speaks exactly what the robot speaks (ARCHITECTURE.md): it consumes ``rt/lowcmd`` and
publishes ``rt/lowstate`` (500 Hz) and ``rt/wirelesscontroller`` as CDR bytes on the Zenoh
keys of the same names, and its foot IMUs stream A2I v1 frames on pty serial ports. The full
reference (config, clocks, the lockstep protocol, the time-offset semantics, the truth file,
the fault hooks) is ``docs/mock-robot.md``; the essentials:

Commands. A ``rt/lowcmd`` whose CRC does not match is ignored and counted (the robot does
the same); a frame of the wrong size or header, or with non-finite numbers or negative gains,
is ignored and counted as malformed. A good one becomes the motors' command (SDK order ->
model order through :mod:`calib.joints`); the PD law of the latest command runs every 1 kHz
physics step (Go2Sim). Motor mode 0x01 = servo; any other mode = motor off (zero torque, no
damping). ``q = PosStopF`` drops the position term (kp := 0), ``dq = VelStopF`` means a zero
velocity target.

Clocks. ``realtime``: one thread steps the physics on absolute 1 ms deadlines of the
monotonic clock and releases every output at its due wall time. ``lockstep``: the simulation
advances one quantum (4 ms: a2i-deploy's five frames per 20 ms tick) per ``rt/lowcmd``
received, as fast as the CPU allows, and is deterministic.

Time offsets. ``t_d = t_I - t_E``. Lockstep: the IMU device clock is the simulation clock
(+ ``tick_epoch_s``, like the lowstate tick): a frame describing sim time tau carries
``t_device_us = round((tau + tick_epoch_s + t_d) * 1e6)`` and the lowstate of tau carries
``tick = round((tau + tick_epoch_s) * 1000)``. Realtime: the stamps come from the monotonic wall
clock, not from sim time, so they never jump when the simulation falls behind. The state of
sim time tau stands for the wall instant ``W(tau) = max(its slot on the schedule, the moment
it was computed)`` (linear between physics steps); its lowstate carries the tick of ``W(tau)``
(ms since the mock's start + epoch) and is published at ``W(tau) + D``; the IMU frame describing
tau is written at ``W(tau) + t_d + D`` stamped by the IMU's own clock (offset, drift) at that
instant, ``D = max(0, -min t_d)``. Any W keeps ``t_I - t_E = t_d`` for the same motion.
"""

from __future__ import annotations

import heapq
import itertools
import logging
import math
import queue
import threading
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Self

import numpy as np

from calib.atomic import write_text_atomic
from calib.joints import (
    LIE_POSE_LEG,
    MODEL_LEGS,
    NUM_MOTORS,
    SDK_LEGS,
    STAND_POSE_LEG,
    check_leg,
    full_pose,
    model_to_sdk,
)
from calib.metrics import quaternion_wxyz, rpy_deg
from hw.go2_msgs import (
    NUM_MOTOR_SLOTS,
    POS_STOP_F,
    VEL_STOP_F,
    LowStateBuffer,
    decode_lowcmd,
    encode_wireless_controller,
)
from hw.joystick import encode_wireless_remote, key_mask
from hw.mock.config import MockConfig
from hw.mock.foot_imus import FootImuChannel, PortWriter, rotation_to_quat_wxyz
from hw.transport import KEY_LOWCMD, KEY_LOWSTATE, KEY_WIRELESS, Transport
from sim.effects import MUJOCO_TIMECONST_S, FloorSlope, FloorSoftness, FootPayload
from sim.go2 import Go2Sim, SimConfig
from sim.sensors import BodyImuModel, EncoderModel

__all__ = ["FOOT_FORCE_UNITS_PER_N", "MockRobot", "quat_to_rpy"]

log = logging.getLogger(__name__)

FOOT_FORCE_UNITS_PER_N = 1.0
"""Scale of ``LowState_.foot_force`` (int16): raw units per newton of normal contact force.
The Go2's foot sensors are uncalibrated raw counts; the mock publishes about 1 unit per N
(a standing Go2 gives ~40 per foot), an assumption, not a measured calibration."""

MODE_SERVO = 0x01
_POS_STOP_MIN = 0.5 * POS_STOP_F  # any q this large is the "no position" sentinel
_VEL_STOP_MIN = 0.5 * VEL_STOP_F
_SDK_FROM_MODEL_LEG = np.array([MODEL_LEGS.index(leg) for leg in SDK_LEGS])
_OUT_LOWSTATE, _OUT_WIRELESS, _OUT_IMU = 0, 1, 2


def quat_to_rpy(q_wxyz) -> np.ndarray:
    """Roll, pitch, yaw (rad; R = Rz(yaw) Ry(pitch) Rx(roll)) of a (w, x, y, z) quaternion."""
    w, x, y, z = (float(v) for v in q_wxyz)
    roll = math.atan2(2.0 * (w * x + y * z), 1.0 - 2.0 * (x * x + y * y))
    pitch = math.asin(max(-1.0, min(1.0, 2.0 * (w * y - z * x))))
    yaw = math.atan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))
    return np.array([roll, pitch, yaw])


@dataclass(frozen=True)
class _Command:
    q: np.ndarray
    dq: np.ndarray
    kp: np.ndarray
    kd: np.ndarray
    tau: np.ndarray
    modes: np.ndarray


class MockRobot:
    """The simulated Go2 behind ``rt/lowcmd`` / ``rt/lowstate`` / ``rt/wirelesscontroller`` and
    pty foot-IMU ports (module docstring; ``docs/mock-robot.md``).

    transport: False runs without Zenoh (in-process use: drive a lockstep mock with
        :meth:`handle_lowcmd` and :meth:`advance`; outputs go to the callbacks only).
    on_lowstate(payload, tick_ms), on_wireless(payload): called with every message published
        (in the publishing thread), e.g. for tests and benches.
    on_imu_frame(leg, payload, sample): called with every foot-IMU frame handed to its port
        (``sample``: :class:`sim.sensors.ImuSample`, with the true time it describes).
    """

    def __init__(self, config: MockConfig | None = None, *, transport: bool = True,
                 on_lowstate: Callable[[bytes, int], None] | None = None,
                 on_wireless: Callable[[bytes], None] | None = None,
                 on_imu_frame: Callable | None = None) -> None:
        cfg = config if config is not None else MockConfig()
        cfg.validate()
        self.config = cfg
        self._use_transport = bool(transport) and bool(cfg.listen or cfg.connect)
        self.on_lowstate = on_lowstate
        self.on_wireless = on_wireless
        self.on_imu_frame = on_imu_frame
        self.lockstep = cfg.clock == "lockstep"

        floor = ([FloorSlope(math.radians(cfg.floor_slope_deg),
                             math.radians(cfg.floor_slope_azimuth_deg))]
                 if cfg.floor_slope_deg else [])
        if cfg.floor_timeconst_s != MUJOCO_TIMECONST_S:
            floor.append(FloorSoftness(cfg.floor_timeconst_s))
        nodes = [FootPayload(kg, leg) for leg, kg in cfg.foot_payloads().items()]
        self.sim = Go2Sim(SimConfig(base=cfg.base, timestep=cfg.physics_dt, seed=cfg.seed,
                                    effects=floor + nodes, model_xml=cfg.model_xml))
        pose = LIE_POSE_LEG if cfg.initial_pose == "lying" else STAND_POSE_LEG
        self.sim.reset(q=full_pose(pose, order="model"))
        self._dt = cfg.physics_dt
        self._ls_every = cfg.steps_per(cfg.lowstate_hz)
        self._wl_every = cfg.steps_per(cfg.wireless_hz)
        self._epoch = cfg.tick_epoch_s

        s_enc, s_body = np.random.SeedSequence([int(cfg.seed), 0xB0D1]).spawn(2)
        self._enc = EncoderModel(resolution=cfg.encoder_resolution,
                                 q_noise_std=cfg.encoder_q_noise_std,
                                 dq_noise_std=cfg.encoder_dq_noise_std,
                                 seed=int(s_enc.generate_state(1)[0]))
        self._body = BodyImuModel(gyro_noise_density=cfg.body_gyro_noise_density,
                                  accel_noise_density=cfg.body_accel_noise_density,
                                  rate=cfg.lowstate_hz, seed=int(s_body.generate_state(1)[0]))
        self._ls = LowStateBuffer()
        temp = np.full(NUM_MOTORS, int(cfg.motor_temperature_c), np.uint8)
        self._ls.set_motors(np.zeros(12), np.zeros(12), np.zeros(12), temperature=temp,
                            lost=np.zeros(12, np.uint32))
        self._modes20 = np.zeros(NUM_MOTOR_SLOTS, np.uint8)

        self.imus = cfg.resolve_imus()
        self.time_offsets = {leg: r.sensor.time_offset for leg, r in self.imus.items()}
        self.output_delay_s = 0.0 if self.lockstep else max(
            [0.0] + [-t for t in self.time_offsets.values()])
        self._foot_sites = {leg: self.sim.model.site(f"{leg}_foot").id for leg in MODEL_LEGS}
        self.channels: dict[str, FootImuChannel] = {}
        self._writers: list[PortWriter] = []

        self._steps = 0
        self._dt_ns = round(self._dt * 1e9)
        self._delay_ns = round(self.output_delay_s * 1e9)
        self._epoch_ms = round(self._epoch * 1000.0)
        # Realtime stamps: wall instants (monotonic ns) of the last two physics steps' states,
        # and the fixed origin of the tick and of the IMU device clocks (the mock's start; the
        # schedule's origin ``_start_ns`` moves on a resync, this one never does).
        self._w_ns = 0
        self._w_prev_ns = 0
        self._clock0_ns = 0
        self._started_outputs = False
        self._last_lowstate: tuple[bytes, int] | None = None
        self._last_publish_wall = 0.0
        self._presses: list[tuple[float, float, int]] = []
        self._press_lock = threading.Lock()
        for p in cfg.joystick:
            self._presses.append((p.t_s, p.t_s + p.duration_s, key_mask(*p.keys)))

        self._pending: _Command | None = None
        self._pending_lock = threading.Lock()
        self._cmd_queue: queue.SimpleQueue = queue.SimpleQueue()
        self._heap: list = []
        self._heap_seq = itertools.count()
        self._start_ns = 0

        self.transport: Transport | None = None
        self._opened = False
        self._closed = False
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self._killed = False
        self.error: BaseException | None = None
        self.truth_path: Path | None = None

        # counters
        self.commands_good = 0
        self.commands_bad_crc = 0
        self.commands_malformed = 0
        self.lowstates_published = 0
        self.lowstates_repeated = 0
        self.wireless_published = 0
        self.late_ticks = 0
        self.max_lateness_s = 0.0
        self.resyncs = 0
        self._wall_start = 0.0

    # ------------------------------------------------------------------ lifecycle
    def open(self) -> MockRobot:
        """Create the IMU ports, open the transport, write the truth file (idempotent)."""
        if self._opened:
            return self
        if self._closed:
            raise RuntimeError("MockRobot is closed")
        cfg = self.config
        try:
            wait_s = cfg.lockstep_port_wait_s if self.lockstep else 0.0
            shared = (PortWriter(wait_s) if (cfg.imu_ports == "shared" and self.imus)
                      else None)
            if shared is not None:
                self._writers.append(shared)
            for leg, imu in self.imus.items():
                w = shared
                if w is None:
                    w = PortWriter(wait_s)
                    self._writers.append(w)
                self.channels[leg] = FootImuChannel(imu, w)
            if self._use_transport:
                t = Transport(cfg.transport_config()).open()
                self.transport = t
                t.publisher(KEY_LOWSTATE)
                t.publisher(KEY_WIRELESS)
                t.subscribe(KEY_LOWCMD, self._on_lowcmd)
            if cfg.truth_path:
                self.truth_path = Path(cfg.truth_path)
                write_text_atomic(self.truth_path, self.truth_json())
        except BaseException:
            self._close_resources()
            raise
        self._opened = True
        return self

    def start(self) -> MockRobot:
        """Open if needed and start the simulation thread (realtime or lockstep)."""
        self.open()
        if self._thread is not None:
            raise RuntimeError("MockRobot already started")
        target = self._run_lockstep if self.lockstep else self._run_realtime
        self._thread = threading.Thread(target=self._guarded, args=(target,),
                                        name="a2i-mock", daemon=True)
        self._wall_start = time.monotonic()
        self._thread.start()
        return self

    def run_forever(self) -> None:
        """Start and block until :meth:`stop` (from another thread or a signal handler) or a
        simulation error (re-raised)."""
        if self._thread is None:
            self.start()
        while not self._stop.wait(0.2):
            if self._thread is not None and not self._thread.is_alive():
                break
        if self.error is not None:
            raise self.error

    def stop(self) -> None:
        """Stop the thread, close the transport and the IMU ports (idempotent)."""
        self._stop.set()
        self._cmd_queue.put(None)
        th = self._thread
        if th is not None and th is not threading.current_thread():
            th.join(5.0)
        self._close_resources()
        self._closed = True

    close = stop

    def _close_resources(self) -> None:
        t, self.transport = self.transport, None
        if t is not None:
            t.close()
        for w in self._writers:
            w.close()

    def __enter__(self) -> Self:
        return self.open()

    def __exit__(self, *exc) -> None:
        self.stop()

    @property
    def running(self) -> bool:
        return self._thread is not None and self._thread.is_alive()

    # ------------------------------------------------------------------ fault hooks
    def kill(self) -> None:
        """Stop publishing abruptly (the robot froze): no lowstate, wireless or IMU byte
        after this call, pending outputs are discarded; the Zenoh session and the ports stay
        open until :meth:`stop`."""
        self._killed = True
        self._stop.set()
        self._cmd_queue.put(None)
        th = self._thread
        if th is not None and th is not threading.current_thread():
            th.join(5.0)
        self._heap.clear()

    def close_imu_port(self, leg: str) -> None:
        """Hang up ``leg``'s port (unplugged adapter): its reader gets an I/O error. With
        ``imu_ports: shared`` this closes the one port of all the IMUs."""
        self._channel(leg).writer.hang_up()

    def inject_garbage(self, leg: str, nbytes: int) -> int:
        """Write ``nbytes`` random bytes (never 0xA2) to ``leg``'s port now; bytes written."""
        if int(nbytes) < 1:
            raise ValueError(f"nbytes must be >= 1, got {nbytes}")
        return self._channel(leg).inject_garbage(int(nbytes))

    def _channel(self, leg: str) -> FootImuChannel:
        leg = check_leg(leg)
        if leg not in self.channels:
            raise ValueError(f"no foot IMU port for {leg} (disabled, or the mock is not open)")
        return self.channels[leg]

    # ------------------------------------------------------------------ joystick
    def press(self, keys: str | Iterable[str], duration_s: float = 0.3,
              at_s: float | None = None) -> None:
        """Hold ``keys`` (names, or "L2+A") on the remote for ``duration_s`` s of sim time,
        from ``at_s`` (sim time, s) or now. Shows in ``wireless_remote`` and
        ``rt/wirelesscontroller``."""
        names = keys.replace("+", " ").split() if isinstance(keys, str) else list(keys)
        mask = key_mask(*names)
        if not duration_s > 0:
            raise ValueError(f"duration_s must be > 0, got {duration_s}")
        t0 = self.sim_time if at_s is None else float(at_s)
        with self._press_lock:
            self._presses.append((t0, t0 + float(duration_s), mask))

    def keys_at(self, t: float) -> int:
        """Key bitmask held at sim time ``t``."""
        mask = 0
        with self._press_lock:
            for t0, t1, m in self._presses:
                if t0 <= t + 1e-9 < t1:
                    mask |= m
        return mask

    # ------------------------------------------------------------------ commands
    def _on_lowcmd(self, payload: bytes, t_ns: int) -> None:
        if self._killed or self._stop.is_set():
            return
        if self.lockstep:
            self._cmd_queue.put(payload)
            return
        cmd = self._parse_lowcmd(payload)
        if cmd is not None:
            with self._pending_lock:
                self._pending = cmd

    def _parse_lowcmd(self, payload: bytes) -> _Command | None:
        """Check and convert one LowCmd_ frame, counting it; None if it must be ignored."""
        try:
            v = decode_lowcmd(payload)
        except ValueError:
            self.commands_malformed += 1
            return None
        if not v.crc_ok():
            self.commands_bad_crc += 1
            return None
        q = v.q.astype(float)
        dq = v.dq.astype(float)
        kp = v.kp.astype(float)
        kd = v.kd.astype(float)
        tau = v.tau.astype(float)
        if not all(np.all(np.isfinite(a)) for a in (q, dq, kp, kd, tau)) or \
                np.any(kp < 0) or np.any(kd < 0):
            self.commands_malformed += 1
            return None
        modes = np.asarray(v.mode, np.uint8).copy()
        nopos = np.abs(q) >= _POS_STOP_MIN
        kp[nopos] = 0.0
        q[nopos] = 0.0
        dq[np.abs(dq) >= _VEL_STOP_MIN] = 0.0
        off = modes != MODE_SERVO
        for a in (kp, kd, tau):
            a[off] = 0.0
        self.commands_good += 1
        return _Command(q, dq, kp, kd, tau, modes)

    def _apply(self, cmd: _Command) -> None:
        self.sim.set_command_sdk(cmd.q, cmd.dq, cmd.kp, cmd.kd, cmd.tau)
        self._modes20[:NUM_MOTORS] = cmd.modes

    def handle_lowcmd(self, payload: bytes) -> bool:
        """Lockstep, in-process: check one LowCmd_ frame and apply it now if good (counted
        either way). True if applied. (The realtime thread applies at its next step.)"""
        cmd = self._parse_lowcmd(payload)
        if cmd is None:
            return False
        if self.lockstep:
            self._apply(cmd)
        else:
            with self._pending_lock:
                self._pending = cmd
        return True

    # ------------------------------------------------------------------ stepping and outputs
    @property
    def sim_time(self) -> float:
        """Simulation time, s (physics steps x timestep)."""
        return self._steps * self._dt

    def tick_ms(self, t: float | None = None) -> int:
        """The lockstep lowstate tick (ms) of sim time ``t`` (default now). (The realtime tick
        is read from the wall clock instead: the module docstring.)"""
        tt = self.sim_time if t is None else t
        return round((tt + self._epoch) * 1000.0)

    def advance(self, quantum_s: float | None = None) -> None:
        """Lockstep, in-process: advance the simulation by ``quantum_s`` (default the config's
        quantum; a whole number of physics steps), emitting every output of that span."""
        if not self.lockstep:
            raise RuntimeError("advance() is for the lockstep clock")
        if self.running and threading.current_thread() is not self._thread:
            raise RuntimeError("the lockstep thread is running: send rt/lowcmd instead")
        if self._killed:
            return
        n = (self.config.quantum_steps if quantum_s is None
             else round(float(quantum_s) / self._dt))
        if n < 0:
            raise ValueError(f"quantum_s must be >= 0, got {quantum_s}")
        self._emit_initial()
        for _ in range(n):
            self._step_once()

    def _emit_initial(self) -> None:
        if not self._started_outputs:
            self._started_outputs = True
            self._outputs()

    def _step_once(self) -> None:
        self.sim.step(1)
        self._steps += 1
        self._outputs()

    def _outputs(self) -> None:
        """Everything the robot emits for the state at the current sim time."""
        k = self._steps
        tau = k * self._dt
        if not self.lockstep:
            self._stamp_step(k)
        for leg, ch in self.channels.items():
            if ch.wants(tau, self._dt):
                om = self.sim.foot_angular_velocity(leg)
                sf = self.sim.foot_specific_force(leg)
                for s in ch.update(tau, om, sf):
                    self._emit_imu(ch, s)
        if k % self._ls_every == 0:
            tick = self.tick_ms(tau) if self.lockstep else self._wall_tick_ms(self._w_ns)
            item = (self._lowstate_bytes(tau, tick), tick)
            self._last_lowstate = item
            self._emit(_OUT_LOWSTATE, tau, item)
        if k % self._wl_every == 0:
            keys = self.keys_at(tau)
            self._emit(_OUT_WIRELESS, tau, encode_wireless_controller(keys=keys))

    def _stamp_step(self, k: int) -> None:
        """Realtime: the wall instant (monotonic ns) that the state of physics step ``k``
        stands for: its slot on the schedule, or now if the simulation is late for it (the
        robot's clocks run on while the simulation catches up). Non-decreasing: the schedule
        only moves forward (resyncs) and so does the clock."""
        w = max(self._start_ns + k * self._dt_ns, time.monotonic_ns(), self._w_ns)
        self._w_prev_ns = w if k == 0 else self._w_ns
        self._w_ns = w

    def _wall_ns_at(self, t: float) -> int:
        """Realtime: the wall instant (ns) of sim time ``t`` within the last physics step,
        linear between the two steps' instants (IMU samples fall between steps)."""
        frac = min(1.0, max(0.0, (t - (self._steps - 1) * self._dt) / self._dt))
        return self._w_prev_ns + round(frac * (self._w_ns - self._w_prev_ns))

    def _wall_tick_ms(self, w_ns: int) -> int:
        """Realtime lowstate tick (ms) of wall instant ``w_ns``: the free-running clock started
        at the mock's start, with the same epoch as the lockstep tick."""
        return self._epoch_ms + (w_ns - self._clock0_ns + 500_000) // 1_000_000

    def _emit_imu(self, ch: FootImuChannel, s) -> None:
        # Orientation of the IMU frame in the world (the frame's quat field): R_W^F R_I^F, at
        # the current physics step (within one step of the sample's instant).
        r_wf = self.sim.data.site_xmat[self._foot_sites[ch.leg]].reshape(3, 3)
        quat = rotation_to_quat_wxyz(r_wf @ ch.rotation)
        if self.lockstep:
            data = ch.frame(s, ch.device_us_lockstep(s.stamp, self._epoch), quat)
            self._send_imu(ch, data, s)
        else:
            # The sample describes the motion at s.true_time, i.e. the wall instant w; the
            # device clock stamps it t_d (+ jitter) + D later, when it is written.
            w = self._wall_ns_at(s.true_time)
            stamp_ns = w + round((s.stamp - s.true_time) * 1e9) + self._delay_ns
            data = ch.frame(s, ch.device_us_realtime((stamp_ns - self._clock0_ns) * 1e-9), quat)
            release = w + round(ch.imu.sensor.time_offset * 1e9) + self._delay_ns
            self._schedule_at(release, _OUT_IMU, (ch, data, s))

    def _send_imu(self, ch: FootImuChannel, data: bytes, s) -> None:
        if self._killed:
            return
        ch.send(data)
        if self.on_imu_frame is not None:
            self.on_imu_frame(ch.leg, data, s)

    def _lowstate_bytes(self, tau: float, tick: int) -> bytes:
        sim, ls = self.sim, self._ls
        q, dq = self._enc.measure(sim.q_sdk, sim.dq_sdk)
        ls.set_motors(q, dq, model_to_sdk(sim.tau))
        ls.set_modes(self._modes20)
        quat = sim.base_quat_wxyz
        gyro, acc = self._body.measure(sim.base_ang_vel, sim.base_specific_force)
        ls.set_imu(quat, gyro, acc, quat_to_rpy(quat))
        ls.set_foot_force(sim.foot_contact_forces[_SDK_FROM_MODEL_LEG] * FOOT_FORCE_UNITS_PER_N)
        ls.set_wireless_remote(encode_wireless_remote(self.keys_at(tau)))
        ls.set_tick(tick)
        return ls.finalize()

    def _emit(self, kind: int, tau: float, item) -> None:
        if self.lockstep:
            self._publish(kind, item)
        else:
            self._schedule_at(self._w_ns + self._delay_ns, kind, item)

    def _schedule_at(self, t_ns: int, kind: int, item) -> None:
        """Realtime: release ``item`` at wall instant ``t_ns`` (monotonic ns)."""
        heapq.heappush(self._heap, (t_ns, next(self._heap_seq), kind, item))

    def _release(self, now_ns: int) -> None:
        h = self._heap
        while h and h[0][0] <= now_ns:
            _, _, kind, item = heapq.heappop(h)
            if kind == _OUT_IMU:
                self._send_imu(*item)
            else:
                self._publish(kind, item)

    def _publish(self, kind: int, item) -> None:
        """Lowstate items are (bytes, tick); wireless items are bytes."""
        if self._killed:
            return
        t = self.transport
        if kind == _OUT_LOWSTATE:
            data, tick = item
            if t is not None:
                t.put(KEY_LOWSTATE, data)
            self.lowstates_published += 1
            self._last_publish_wall = time.monotonic()
            if self.on_lowstate is not None:
                self.on_lowstate(data, tick)
        else:
            if t is not None:
                t.put(KEY_WIRELESS, item)
            self.wireless_published += 1
            if self.on_wireless is not None:
                self.on_wireless(item)

    # ------------------------------------------------------------------ threads
    def _guarded(self, target) -> None:
        try:
            target()
        except BaseException as e:
            self.error = e
            log.exception("mock robot stopped")
        finally:
            self._stop.set()

    def _run_lockstep(self) -> None:
        self._emit_initial()
        idle = self.config.lockstep_idle_repeat_s
        wait = idle if idle > 0 else 0.1
        while not self._stop.is_set():
            try:
                payload = self._cmd_queue.get(timeout=wait)
            except queue.Empty:
                if (idle > 0 and self._last_lowstate is not None
                        and time.monotonic() - self._last_publish_wall >= idle):
                    self._publish(_OUT_LOWSTATE, self._last_lowstate)
                    self.lowstates_repeated += 1
                continue
            if payload is None or self._stop.is_set():
                break
            cmd = self._parse_lowcmd(payload)
            if cmd is not None:
                self._apply(cmd)
            self.advance()

    def _run_realtime(self) -> None:
        dt_ns = round(self._dt * 1e9)
        resync_ns = int(self.config.resync_after_s * 1e9)
        self._start_ns = time.monotonic_ns()
        self._clock0_ns = self._start_ns
        self._emit_initial()
        stop = self._stop
        while not stop.is_set():
            self._release(time.monotonic_ns())
            if self._pending is not None:
                with self._pending_lock:
                    cmd, self._pending = self._pending, None
                if cmd is not None:
                    self._apply(cmd)
            self._step_once()
            target = self._start_ns + self._steps * dt_ns
            lag = time.monotonic_ns() - target
            if lag > dt_ns:
                self.late_ticks += 1
                self.max_lateness_s = max(self.max_lateness_s, lag * 1e-9)
                if lag > resync_ns:
                    # Too far behind to catch up unnoticed: shift the schedule (sim time
                    # runs slow for a moment) instead of bursting through the backlog.
                    self._start_ns += lag
                    self.resyncs += 1
            elif lag < 0:
                time.sleep(-lag * 1e-9)

    # ------------------------------------------------------------------ reporting
    def stats(self) -> dict:
        """Counters and timing: sim_time_s, wall_s, rtf, commands (good, bad_crc, malformed),
        lowstates, wireless, late_ticks, max_lateness_s, resyncs, per-leg IMU frames."""
        wall = time.monotonic() - self._wall_start if self._wall_start else 0.0
        imu = {leg: {"samples": c.samples, "frames_written": c.frames_written,
                     "frames_dropped": c.frames_dropped, "garbage_bytes": c.garbage_bytes,
                     "port_writes_waited": c.writer.writes_waited,
                     "port_wait_max_s": c.writer.wait_max_s}
               for leg, c in self.channels.items()}
        return {
            "sim_time_s": self.sim_time,
            "wall_s": wall,
            "rtf": self.sim_time / wall if wall > 0 else float("nan"),
            "commands_good": self.commands_good,
            "commands_bad_crc": self.commands_bad_crc,
            "commands_malformed": self.commands_malformed,
            "lowstates_published": self.lowstates_published,
            "lowstates_repeated": self.lowstates_repeated,
            "wireless_published": self.wireless_published,
            "late_ticks": self.late_ticks,
            "max_lateness_s": self.max_lateness_s,
            "resyncs": self.resyncs,
            "imu": imu,
        }

    @property
    def imu_ports(self) -> dict[str, str]:
        """Leg -> pty path of its foot IMU (after :meth:`open`)."""
        return {leg: c.writer.port_path for leg, c in self.channels.items()}

    def truth(self) -> dict:
        """The ground truth per leg, in the calibration result's conventions."""
        out = {}
        for leg, imu in self.imus.items():
            s = imu.sensor
            ch = self.channels.get(leg)
            out[leg] = {
                "leg": leg,
                "rotation_matrix": [[float(v) for v in row] for row in s.rotation],
                "quaternion_wxyz": [float(v) for v in quaternion_wxyz(s.rotation)],
                "rpy_deg": [float(v) for v in rpy_deg(s.rotation)],
                "time_offset_s": float(s.time_offset),
                "foot_frame": f"{leg}_foot",
                "port": ch.writer.port_path if ch is not None else None,
                "node_id": imu.node_id,
                "rate_hz": float(s.rate),
                "phase_s": float(s.phase),
                "gyro_noise_density": float(s.gyro_noise_density),
                "dropout_prob": float(s.dropout_prob),
                "clock": self.config.clock,
                "tick_epoch_s": float(self._epoch),
                "output_delay_s": float(self.output_delay_s),
                "device_clock_offset_s": float(imu.clock_offset_s),
                "device_clock_drift_ppm": float(imu.clock_drift_ppm),
            }
        return out

    def truth_json(self) -> str:
        import json
        return json.dumps(self.truth(), indent=2) + "\n"
