"""The on-board runtime: transport, foot-IMU readers, recorder, the 50 Hz loop, SOLVE workers.

Threads:

* the control loop (the caller's thread): each tick drains the queue of every LowState received
  since the last tick (500 Hz; all of them are recorded, the newest one drives the tick),
  records the joystick stream, runs the supervisor and the state machine (observation, ONNX,
  targets), publishes the tick's ``commands_per_tick`` LowCmd_ frames (CRC; the first at once,
  the others ``dt / commands_per_tick`` apart, the lifted leg's target moving between them)
  and records each. Only this thread writes the
  ``lowstate``, ``lowcmd`` and ``wireless`` rings;
* one :class:`hw.imu_serial.SerialImuReader` thread per serial port, each the only writer of
  its legs' ``imu/<LEG>`` rings;
* a SOLVE worker per calibrated leg (snapshot, solver, files), never the loop.

Ticking: ``realtime`` on absolute 20 ms deadlines of the monotonic clock
(:class:`deploy.timing.DeadlineTicker`); ``lockstep`` (the mock's deterministic clock, which
advances one quantum, ``dt / commands_per_tick``, per LowCmd_) on the arrival of the LowState
of the expected tick, the tick's frames sent back to back.
"""

from __future__ import annotations

import logging
import os
import sys
import threading
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field, replace
from datetime import UTC, datetime
from pathlib import Path

import numpy as np

from calib.joints import check_leg
from calib.solver import SolverConfig
from deploy.policy import PolicyMeta, PolicyRunner
from deploy.session import Command, LegOutcome, Session, SessionConfig, State, TickInput
from deploy.solve import SolveJob, SolveWorker, WindowMark
from deploy.supervisor import SafetySupervisor, SupervisorConfig
from deploy.timebase import make_time_base
from deploy.timing import DeadlineTicker, TickStats, TimingSummary
from hw.go2_msgs import LowCmdBuffer, LowStateView, decode_lowstate
from hw.imu_serial import SerialImuReader
from hw.joystick import Joystick, JoystickState
from hw.recorder import Recorder, RecorderConfig
from hw.transport import (
    KEY_LOWCMD,
    KEY_LOWSTATE,
    KEY_WIRELESS,
    LowCmdConflict,
    Transport,
    TransportConfig,
    TransportError,
)

__all__ = ["DeployConfig", "DeployError", "DeployRunner", "ImuPort", "RunResult"]

log = logging.getLogger(__name__)


class DeployError(RuntimeError):
    """A start-up or run-time failure with a one-line, user-facing reason."""


@dataclass(frozen=True)
class ImuPort:
    """A foot IMU: leg, serial port, radio node id (None: the port carries only this leg)."""

    leg: str
    port: str
    node: int | None = None


@dataclass
class DeployConfig:
    """Everything a run needs besides the policy.

    legs: calibrated in turn (empty + joystick: wait for combos). connect: Zenoh endpoints of
    the robot's bridge (or the mock). imus: foot IMUs. clock: "realtime" or "lockstep" (tick
    source and time base, see :mod:`deploy.timebase`; in lockstep the mock must advance
    ``dt / session.commands_per_tick`` per LowCmd_, its ``lockstep_quantum_s``).
    lockstep_wait_s: longest wait for the tick's LowState before the tick counts as stale.
    first_lowstate_s: longest wait for the robot at start.
    record_seconds: recorder history (s); imu_hz: recorder rate of each foot IMU.
    truth: leg -> (R_I^F, t_d) of a simulated mounting (reports errors against it).
    final_ticks: ticks the final (damping) command is repeated before the loop returns.
    keep_solver_output: keep each leg's full SolverResult after its report (memory grows).
    solver: the solver's settings and gates; its ``max_offset`` is replaced, leg by leg, by the
    lift schedule's ``t_r``: the range of offsets that leg's excitation was designed for.
    imu_silence_s: the lifted leg's foot IMU silent this long (s) aborts its calibration.
    max_ticks: stop after this many ticks (benchmarks); None: until the session ends.
    """

    legs: list[str] = field(default_factory=list)
    joystick: bool = False
    out_dir: Path = Path("calibration")
    connect: list[str] = field(default_factory=lambda: ["tcp/127.0.0.1:7447"])
    imus: list[ImuPort] = field(default_factory=list)
    imu_protocol: str = "a2i"
    imu_baud: int = 921600
    clock: str = "realtime"
    lockstep_wait_s: float = 0.5
    first_lowstate_s: float = 5.0
    record_seconds: float = 180.0
    imu_hz: float = 500.0
    force: bool = False
    session: SessionConfig = field(default_factory=SessionConfig)
    supervisor: SupervisorConfig = field(default_factory=SupervisorConfig)
    # The robot plays its own anti-noise motion (kappa ~ 1 by design): the authors' stricter
    # gates apply, so a poorly executed motion is refused rather than reported.
    solver: SolverConfig = field(default_factory=SolverConfig.paper_gates)
    truth: dict[str, tuple[np.ndarray, float]] | None = None
    write_mcap: bool = True
    session_metadata: dict = field(default_factory=dict)
    final_ticks: int = 5
    imu_silence_s: float = 1.0
    keep_solver_output: bool = False
    max_ticks: int | None = None
    progress: Callable[[str], None] | None = None
    progress_every_s: float = 2.0


@dataclass
class RunResult:
    """What a run produced: per-leg outcomes, the final state and its cause, timing, files."""

    outcomes: list[LegOutcome]
    final_state: State
    fault: str | None
    timing: TimingSummary
    transitions: list[tuple[float, str, str, str]]
    mcap_path: Path | None
    rss_start_bytes: int
    rss_end_bytes: int
    recorder_bytes: int
    ticks: int
    imu_errors: dict[str, str]

    @property
    def ok(self) -> bool:
        return (self.fault is None and bool(self.outcomes)
                and all(o.ok for o in self.outcomes))


def fix_allocator_thresholds(mmap_threshold: int = 256 * 1024) -> bool:
    """glibc: serve every allocation above ``mmap_threshold`` bytes by its own mmap, always.

    By default glibc raises that threshold each time a large block is freed (up to 32 MiB), after
    which the SOLVE worker's tens-of-MiB snapshots and solver arrays come from its heap arena and
    fragment it: a long session's resident memory then creeps up calibration after calibration.
    A fixed threshold returns those blocks to the system when freed. No-op (False) elsewhere.
    """
    try:
        import ctypes

        libc = ctypes.CDLL("libc.so.6")
        m_mmap_threshold = -3  # malloc.h
        return bool(libc.mallopt(m_mmap_threshold, int(mmap_threshold)))
    except (OSError, AttributeError):
        return False


def rss_bytes() -> int:
    """Resident set size of this process (Linux /proc; 0 elsewhere)."""
    try:
        with open("/proc/self/statm") as f:
            return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")
    except (OSError, ValueError, IndexError):
        return 0


def _imus_by_port(imus: Sequence[ImuPort]) -> dict[str, list[ImuPort]]:
    """port -> its IMUs; DeployError unless one port per leg and IMUs sharing a port told
    apart by their node ids: else one leg's ring would hold two IMUs' samples, interleaved."""
    legs = [i.leg for i in imus]
    twice = sorted({g for g in legs if legs.count(g) > 1})
    if twice:
        raise DeployError(f"--imu gives {', '.join(twice)} more than one port")
    by_port: dict[str, list[ImuPort]] = {}
    for imu in imus:
        by_port.setdefault(imu.port, []).append(imu)
    for port, shared in by_port.items():
        nodes = {i.node for i in shared if i.node is not None}
        if len(shared) > 1 and len(nodes) != len(shared):
            raise DeployError(f"port {port} is shared by {len(shared)} IMUs: give every one "
                              "its own node id, e.g. --imu FL=/dev/ttyUSB0#1")
    return by_port


class DeployRunner:
    """One run of the on-board program (see the module docstring).

    on_tick(runner) is called at the end of every tick (tests inject faults from it).
    """

    def __init__(self, config: DeployConfig, meta: PolicyMeta | Mapping[str, PolicyMeta],
                 on_tick: Callable[[DeployRunner], None] | None = None):
        """meta: the policy, or leg -> policy (:func:`deploy.policy.policies_for_legs`)."""
        self.cfg = config
        self.metas = dict(meta) if isinstance(meta, Mapping) else dict.fromkeys(meta.legs, meta)
        # the loop's period, the stand pose and the soft limits: the same in every policy
        meta = self.meta = next(iter(self.metas.values()))
        self.on_tick = on_tick
        fix_allocator_thresholds()
        self.time_base = make_time_base(config.clock)
        self.dt = meta.control_dt
        for leg in config.legs:
            check_leg(leg)
        imu_legs = {i.leg for i in config.imus}
        _imus_by_port(config.imus)  # refused here, before anything starts
        if config.joystick and not imu_legs:
            raise DeployError("no foot IMU: give every leg the remote may calibrate its port, "
                              "e.g. --imu FL=/dev/ttyUSB0")
        missing = [leg for leg in config.legs if leg not in imu_legs]
        if missing:
            raise DeployError(f"no foot IMU port for {', '.join(missing)}: give "
                              f"--imu {missing[0]}=/dev/ttyUSB0")
        no_policy = [leg for leg in config.legs if leg not in self.metas]
        if no_policy:
            raise DeployError(f"no policy for {', '.join(no_policy)}")
        runners: dict[Path, PolicyRunner] = {}
        for m in self.metas.values():
            if m.path not in runners:
                runners[m.path] = PolicyRunner(m)
        self.policies = {leg: runners[m.path] for leg, m in self.metas.items()}
        # Plan every excitation (and load the lifted legs' dynamics for the feed-forward) and
        # every leg's kinematics now (0.1-0.4 s each): never inside the loop, nor once per solve.
        from calib.kinematics import LegKinematics

        # The paper's t_r is the range of sensor offsets a plan is designed for (its period is
        # 8 t_r, so the correlation is unambiguous well beyond it): each leg's solve searches its
        # own policy's, for every leg a policy lifts
        self._solver_cfg = {}
        for leg, m in self.metas.items():
            try:
                self._solver_cfg[leg] = replace(config.solver, max_offset=m.schedule.t_r)
            except ValueError as e:
                raise DeployError(f"{leg}'s lift schedule t_r {m.schedule.t_r:g} s: {e}") from None
        self._kin = {}
        for leg in dict.fromkeys(config.legs or sorted(imu_legs)):
            if leg in self.metas:
                sched = self.metas[leg].schedule
                sched.prepare(leg)
                # SOLVE reads the excitation back from the rings after the lowering and the
                # stand: a shorter history would have lost its start by then
                need = sched.plan(leg).duration + sched.lower + 5.0
                if config.record_seconds < need:
                    raise DeployError(f"--record-seconds {config.record_seconds:g} cannot hold "
                                      f"{leg}'s calibration window until SOLVE: give at least "
                                      f"{np.ceil(need):.0f}")
            self._kin[leg] = LegKinematics.from_urdf(leg=leg)
        self.n_cmd = config.session.commands_per_tick
        rec_cfg = RecorderConfig(seconds=config.record_seconds, imu_hz=config.imu_hz,
                                 lowcmd_hz=self.n_cmd / self.dt,
                                 legs=tuple(sorted(imu_legs)) or ("FL",))
        self.recorder = Recorder(rec_cfg)
        self.supervisor = SafetySupervisor(config.supervisor, meta.soft_lower, meta.soft_upper,
                                           self.dt)
        self.transitions: list[tuple[float, str, str, str]] = []
        self.session = Session(self.policies, self.supervisor, self.dt, self._start_solve,
                               legs=config.legs, joystick=config.joystick,
                               config=config.session, on_transition=self._on_transition,
                               on_report=self._on_report, available_legs=sorted(imu_legs))
        self.stats = TickStats()
        self.imu_errors: dict[str, str] = {}
        self._imu_err_lock = threading.Lock()
        self.readers: list[SerialImuReader] = []
        self.transport: Transport | None = None
        self.publisher = None
        self._cmd = LowCmdBuffer()
        self._joy = Joystick()
        self._stop = threading.Event()
        # the realtime schedule's clock (ns) and sleep (s): the ticker's and the frames'
        self._clock: Callable[[], int] = time.monotonic_ns
        self._sleep: Callable[[float], None] = time.sleep
        self.latest = None  # newest LowStateView
        self.latest_ns = 0
        self.last_tick_ms: int | None = None
        self.ticks = 0
        self._next_progress = 0.0
        self._jobs: list[SolveJob] = []
        self._waited_job: SolveJob | None = None  # lockstep: the job SOLVE last waited for
        self._wait_deadline = 0.0
        self._worker: SolveWorker | None = None
        # the lifted leg's IMU: (leg, frames recorded, ticks without a new one, monotonic s of
        # the last new one)
        self._imu_seen: tuple[str | None, int, int, float] = (None, 0, 0, 0.0)

    # ------------------------------------------------------------------ callbacks
    def _on_transition(self, old: State, new: State, cause: str) -> None:
        t = self.session.k * self.dt
        self.transitions.append((t, old.value, new.value, cause))
        text = f"{old.value} -> {new.value}: {cause}"
        level = logging.ERROR if new is State.DAMP else logging.INFO
        log.log(level, "t=%.2f s %s", t, text)
        self.recorder.record_event(self.latest_ns or time.monotonic_ns(), text,
                                   code=list(State).index(new))
        self._say(f"[{t:7.2f} s] {text}")

    def _on_report(self, outcome: LegOutcome) -> None:
        from deploy.report import leg_summary

        self._say(leg_summary(outcome))
        out = outcome.payload
        if out is not None and not self.cfg.keep_solver_output:
            out.solver = None  # its curves are in the PNG; a long session must not grow

    def _say(self, line: str) -> None:
        if self.cfg.progress is not None:
            self.cfg.progress(line)

    def _start_solve(self, leg: str, window) -> SolveJob:
        truth = (self.cfg.truth or {}).get(leg)
        # the solver searches +-t_r and reads that much more of the encoders on each side
        config = self._solver_cfg[leg]
        job = self._worker.submit(self.recorder, leg, window, self.time_base, self.cfg.out_dir,
                                  kin=self._kin.get(leg), config=config, truth=truth,
                                  pad_s=config.max_offset + 0.1)
        self._jobs.append(job)
        return job

    def _on_imu_error(self, legs: list[str], port: str):
        def cb(exc: BaseException) -> None:
            with self._imu_err_lock:
                for leg in legs:
                    self.imu_errors[leg] = (f"serial port {port} failed ({exc!r}): unplugged "
                                            "or the IMU's receiver lost power?")
        return cb

    def _imu_recorder(self, default_leg: str | None):
        rec = self.recorder

        def on_sample(s) -> None:
            leg = s.name or default_leg
            rec.record_imu(leg, s.t_host_ns, s.t_device_ns, s.t_mapped_ns, s.seq & 0xFFFF,
                           s.node_id & 0xFF, s.gyro, s.accel, s.quat)
        return on_sample

    def request_stop(self) -> None:
        """Ask the loop to damp and return (thread-safe; e.g. from a signal handler)."""
        self._stop.set()

    # ------------------------------------------------------------------ start-up
    def _open(self) -> None:
        c = self.cfg
        self._worker = SolveWorker()
        self._worker.warm_up()
        try:
            self.transport = Transport(TransportConfig(connect=list(c.connect))).open()
        except (TransportError, ValueError) as e:
            raise DeployError(str(e)) from None
        self.ls_queue = self.transport.queue(KEY_LOWSTATE, maxlen=5000)
        self.wl_queue = self.transport.queue(KEY_WIRELESS, maxlen=1000)
        for port, imus in _imus_by_port(c.imus).items():
            nodes = {i.node: i.leg for i in imus if i.node is not None}
            legs = [i.leg for i in imus]
            reader = SerialImuReader(
                port, baudrate=c.imu_baud, protocol=c.imu_protocol,
                node_map=nodes or None, on_sample=self._imu_recorder(None if nodes else legs[0]),
                on_error=self._on_imu_error(legs, port), queue_size=0)
            try:
                reader.start()
            except Exception as e:  # noqa: BLE001 - pyserial raises several types
                raise DeployError(f"cannot open foot IMU port {port} for "
                                  f"{', '.join(legs)}: {e}") from None
            self.readers.append(reader)
        # The robot must be there before we claim rt/lowcmd (the claim waits a listen window).
        first = self.ls_queue.get(timeout=c.first_lowstate_s)
        if first is None:
            raise DeployError(f"no LowState on {KEY_LOWSTATE} within {c.first_lowstate_s:g} s "
                              f"from {', '.join(c.connect)}: is the robot (zenoh-bridge-dds) or "
                              "the mock running there?")
        self._ingest([first])
        try:
            self.publisher = self.transport.publisher(KEY_LOWCMD, force=c.force)
        except LowCmdConflict as e:
            raise DeployError(f"{e}. Stop the other controller (or sport mode) first.") from None
        if self.publisher.forced_over:
            log.warning("publishing rt/lowcmd over another publisher: %s",
                        self.publisher.forced_over)
        if c.clock == "lockstep":
            self._check_quantum()

    def _check_quantum(self) -> None:
        """Lockstep: one damping frame, and the robot's answer says how far it advances per
        LowCmd_ (read once it has gone quiet: its idle repeat, or ``lockstep_wait_s`` of
        silence). A robot on another quantum would play the ticks at the wrong speed."""
        self._ingest(self.ls_queue.drain())
        t0 = self.last_tick_ms
        self._publish(self._damp_frame())
        got: list = []
        newest = t0
        while True:
            s = self.ls_queue.get(timeout=self.cfg.lockstep_wait_s)
            if s is None:
                break
            got.append(s)
            tick = _tick_of(s.payload)
            if tick == newest and newest != t0:
                break  # the idle repeat of the quantum's last state
            newest = max(newest, tick)
        self._ingest(got)
        want = self.dt * 1e3 / self.n_cmd
        if abs((newest - t0) - want) > 1e-6:
            raise DeployError(
                f"the lockstep robot advanced {newest - t0} ms on one LowCmd_; this loop sends "
                f"{self.n_cmd} per {self.dt * 1e3:g} ms tick, so it must advance {want:g} ms "
                f"(the mock's lockstep_quantum_s {want / 1e3:g})")

    def _damp_frame(self) -> Command:
        return Command(np.zeros(12), np.zeros(12), np.zeros(12),
                       np.full(12, self.cfg.session.damp_kd), np.zeros(12), "damp")

    def close(self) -> None:
        for r in self.readers:
            try:
                r.stop()
            except RuntimeError as e:
                log.warning("%s", e)
        self.readers = []
        if self.transport is not None:
            self.transport.close()
            self.transport = None

    # ------------------------------------------------------------------ the loop
    def _record_lowstate(self, s) -> LowStateView | None:
        """Decode and record one received LowState; None (logged) if it does not decode."""
        try:
            v = decode_lowstate(s.payload)
        except ValueError as e:
            log.warning("bad LowState ignored: %s", e)
            return None
        self.recorder.record_lowstate(s.t_ns, s.payload, v.q, v.dq, v.tau_est, v.quaternion,
                                      v.gyroscope, v.accelerometer, v.tick)
        return v

    def _ingest(self, samples) -> tuple[bool, set[str]]:
        """Record every LowState; the newest becomes ``latest``. Returns (fresh, combos)."""
        combos: set[str] = set()
        fresh = False
        for s in samples:
            v = self._record_lowstate(s)
            if v is None:
                continue
            tick = v.tick
            if self.last_tick_ms is not None and tick == self.last_tick_ms:
                continue  # a repeat (the lockstep mock repeats its last state when idle)
            ev = self._joy.update(JoystickState.from_wireless_remote(v.wireless_remote))
            combos.update(c.name for c in ev.combos)
            self.latest, self.latest_ns, self.last_tick_ms = v, s.t_ns, tick
            fresh = True
        return fresh, combos

    def _record_late_lowstates(self, lockstep: bool, quiet_s: float = 0.08,
                               max_s: float = 0.5) -> None:
        """Record the LowStates that arrive after the last tick: the robot's answers to its
        frames, which no tick reads. A lockstep robot answers each frame and then falls quiet
        (its idle repeat comes after 0.1 s), so wait for ``quiet_s`` without a state (at most
        ``max_s``); a realtime one never falls quiet: take what has arrived."""
        t0 = last = time.monotonic()
        while True:
            samples = self.ls_queue.drain()
            now = time.monotonic()
            for s in samples:
                self._record_lowstate(s)
            if samples:
                last = now
            if not lockstep or now - last >= quiet_s or now - t0 >= max_s:
                return
            time.sleep(0.002)

    def _wait_lockstep(self, expected_tick: int | None) -> list:
        """Samples up to (and including) the LowState of ``expected_tick`` (or a timeout)."""
        got = self.ls_queue.drain()
        deadline = time.monotonic() + self.cfg.lockstep_wait_s

        def reached() -> bool:
            if expected_tick is None:
                return bool(got)
            return any(_tick_of(s.payload) >= expected_tick for s in got)

        while not reached():
            left = deadline - time.monotonic()
            if left <= 0:
                break
            s = self.ls_queue.get(timeout=left)
            if s is not None:
                got.append(s)
        return got

    def _wait_solver(self) -> None:
        """Lockstep: a tick in SOLVE first waits for the solver (up to the session's
        ``solve_timeout_s``), as the simulation waits for every tick. Else how many ticks the
        robot stands in SOLVE, and so where the next leg starts from, would depend on how fast
        this host solves: two runs of the same seed gave the same first leg and different
        later ones."""
        if self.session.state is not State.SOLVE or not self._jobs or self._jobs[-1].done():
            return
        job = self._jobs[-1]
        if self._waited_job is not job:  # the wait is solve_timeout_s of wall time per job
            self._waited_job = job
            self._wait_deadline = time.monotonic() + self.cfg.session.solve_timeout_s
            self._say(f"  SOLVE {self.session.leg}: solving (the lockstep robot waits)")
        while not job.done() and not self._stop.is_set():
            left = self._wait_deadline - time.monotonic()
            if left <= 0:
                break
            job.join(min(left, 0.02))  # a stop arriving meanwhile ends the wait within 20 ms

    def _watch_imu(self) -> None:
        """A silent foot IMU of the leg being lifted is an error (port open, no frames: wrong
        port, wrong protocol or baud, receiver off), found before SOLVE has nothing to use.
        Silent for ``imu_silence_s`` of ticks and of wall time both: in lockstep the ticks can
        outrun a reader thread short of CPU (and the lockstep mock waits for its ports to take
        its frames rather than drop them: ``hw.mock.foot_imus``)."""
        s = self.session
        leg = s.leg
        if leg is None or s.state not in (State.TRIPOD, State.CALIBRATE):
            self._imu_seen = (None, 0, 0, 0.0)
            return
        n = self.recorder.ring(f"imu/{leg}").total_written
        last_leg, last_n, quiet, t_new = self._imu_seen
        if last_leg == leg and n == last_n:
            quiet += 1
        else:
            quiet, t_new = 0, time.monotonic()
        self._imu_seen = (leg, n, quiet, t_new)
        limit = round(self.cfg.imu_silence_s / self.dt)
        if (quiet >= limit and time.monotonic() - t_new >= self.cfg.imu_silence_s
                and leg not in self.imu_errors):
            port = next((i.port for i in self.cfg.imus if i.leg == leg), "?")
            with self._imu_err_lock:
                self.imu_errors.setdefault(
                    leg, f"no data on {port} for {self.cfg.imu_silence_s:g} s (wrong port, "
                         f"protocol {self.cfg.imu_protocol!r} or baud {self.cfg.imu_baud}, or "
                         "the IMU is off)")

    def _window_mark(self) -> WindowMark | None:
        if self.latest is None:
            return None
        if self.time_base.name == "lockstep":
            t_enc = self.last_tick_ms * 1e-3
        else:
            t_enc = self.latest_ns * 1e-9
        return WindowMark(self.latest_ns, t_enc)

    def _publish(self, cmd: Command) -> None:
        b = self._cmd
        b.set_motors(cmd.q, cmd.dq, cmd.kp, cmd.kd, cmd.tau)
        raw = b.finalize()
        self.publisher.put(raw)
        self.recorder.record_lowcmd(time.monotonic_ns(), raw, cmd.q, cmd.dq, cmd.kp, cmd.kd,
                                    cmd.tau)

    def _publish_rest(self, cmd: Command, deadline_ns: int, lockstep: bool) -> None:
        """The tick's later frames, after ``cmd`` itself: its substeps (or ``cmd`` again) on
        the sub-deadlines ``deadline + i * dt / n`` (lockstep: back to back, each a quantum).
        A frame whose successor is already due is skipped (counted), not sent late."""
        n = self.n_cmd
        frames = list(cmd.substeps) or [cmd] * (n - 1)
        sub_ns = round(self.dt * 1e9 / n)
        for i, f in enumerate(frames, start=1):
            if not lockstep:
                due = deadline_ns + i * sub_ns
                now = self._clock()
                if i < n - 1 and now >= due + sub_ns:
                    self.stats.frames_skipped += 1
                    continue
                if now < due:
                    self._sleep((due - now) * 1e-9)
            self._publish(f)

    def _progress(self) -> None:
        if self.cfg.progress is None:
            return
        now = time.monotonic()
        if now < self._next_progress:
            return
        self._next_progress = now + self.cfg.progress_every_s
        s = self.session
        if s.state in (State.TRIPOD, State.CALIBRATE, State.LOWER):
            sched = s.meta.schedule
            t = s._lift_time()
            total = sched.total(s.leg)
            self._say(f"  {s.state.value} {s.leg}: {s.phase} {t:5.1f}/{total:.1f} s "
                      f"({100 * min(1.0, t / total):3.0f} %)")
        elif s.state is State.SOLVE:
            self._say(f"  SOLVE {s.leg}: solver running ({s.t_state:.1f} s)")

    def run(self) -> RunResult:
        """Start, loop until the session ends (or ``request_stop``), save; never leaves the
        robot without a final damping command when the loop had started."""
        rss0 = rss_bytes()
        c = self.cfg
        mcap_path = None
        try:
            self._open()
            try:
                self._loop()
            except BaseException as e:
                self._emergency_damp(f"deploy error: {type(e).__name__}: {e}")
                raise
            self._record_late_lowstates(c.clock == "lockstep")
        finally:
            for job in self._jobs:
                job.join(timeout=60.0)
            for o in self.session.adopt_late_results():
                self._say(f"  {o.leg}: its solve finished after the session had stopped "
                          f"waiting for it; {'accepted' if o.ok else 'refused'}: its result "
                          "stands")
            if self._worker is not None:
                self._worker.close()
            self.close()
            if c.write_mcap and self.ticks > 0:
                mcap_path = self._save_mcap()
        return RunResult(
            outcomes=list(self.session.outcomes), final_state=self.session.state,
            fault=self.session.fault, timing=self.stats.summary(),
            transitions=list(self.transitions), mcap_path=mcap_path, rss_start_bytes=rss0,
            rss_end_bytes=rss_bytes(), recorder_bytes=self.recorder.memory_bytes(),
            ticks=self.ticks, imu_errors=dict(self.imu_errors))

    def _emergency_damp(self, cause: str) -> None:
        """A bug or an interrupt in the loop: damp the robot before the error propagates."""
        log.critical("%s: damping", cause)
        if self.publisher is None:
            return
        self.session.enter_damp(cause[:200])
        damp = self._damp_frame()
        for _ in range(max(1, self.cfg.final_ticks)):
            try:
                self._publish(damp)
            except Exception:
                log.exception("could not publish the damping command")
                return
            time.sleep(self.dt)

    def _loop(self) -> None:
        c = self.cfg
        lockstep = c.clock == "lockstep"
        ticker = None if lockstep else DeadlineTicker(self.dt, self._clock, self._sleep)
        sess = self.session
        final_left = c.final_ticks
        expected: int | None = None
        first = True  # _open ingested the first LowState: tick on it at once
        while True:
            if first:
                samples = self.ls_queue.drain()
                deadline = start = time.monotonic_ns()
                if ticker is not None:
                    ticker.wait()
            elif lockstep:
                samples = self._wait_lockstep(expected)
                self._wait_solver()
                deadline = start = time.monotonic_ns()
            else:
                _k, deadline, start = ticker.wait()
                samples = self.ls_queue.drain()
            fresh, combos = self._ingest(samples)
            fresh, first = fresh or first, False
            for w in self.wl_queue.drain():
                self.recorder.record_wireless(w.t_ns, w.payload)
            v = self.latest
            fault = self.supervisor.check_state(
                fresh, *(() if v is None else (v.q, v.dq, v.quaternion, v.gyroscope,
                                               v.temperature, v.lost)))
            if fault is None and self.publisher.conflict is not None:
                fault = self.publisher.conflict
            if self._stop.is_set():
                combos.add("stop")
            self._watch_imu()
            with self._imu_err_lock:
                imu_errors = dict(self.imu_errors)
            inp = TickInput(
                q=None if v is None else v.q.astype(float),
                dq=None if v is None else v.dq.astype(float),
                tau=None if v is None else v.tau_est.astype(float),
                quat=None if v is None else v.quaternion.astype(float),
                gyro=None if v is None else v.gyroscope.astype(float),
                combos=tuple(combos), fault=fault, imu_errors=imu_errors,
                window_mark=self._window_mark())
            cmd = sess.step(inp)
            self._publish(cmd)
            end = time.monotonic_ns()
            self._publish_rest(cmd, deadline, lockstep)
            if lockstep and self.last_tick_ms is not None:
                expected = self.last_tick_ms + round(self.dt * 1e3)
            self.stats.add((start - deadline) * 1e-9, (end - start) * 1e-9)
            self.ticks += 1
            if ticker is not None:
                self.stats.missed = ticker.missed
            if self.on_tick is not None:
                self.on_tick(self)
            self._progress()
            if sess.finished or (self._stop.is_set() and sess.state is State.DAMP):
                final_left -= 1
                if final_left <= 0:
                    break
            if c.max_ticks is not None and self.ticks >= c.max_ticks:
                break

    def _save_mcap(self) -> Path | None:
        from hw.mcap_io import write_mcap

        stamp = datetime.now(UTC).strftime("%Y%m%dT%H%M%SZ")
        path = Path(self.cfg.out_dir) / f"session-{stamp}.mcap"
        meta = {
            "program": "a2i-deploy",
            "legs": list(self.cfg.legs),
            "policy": {leg: str(m.path) for leg, m in self.metas.items()},
            "clock": self.cfg.clock,
            "final_state": self.session.state.value,
            "fault": self.session.fault or "",
            "transitions": [list(t) for t in self.transitions],
            # s, per leg whose lift read it from the motors' torque (its report's line)
            "command_delay_s": {o.leg: o.command_delay_s for o in self.session.outcomes
                                if o.command_delay_s is not None},
            **self.cfg.session_metadata,
        }
        if self.cfg.truth:
            meta["mounting_truth"] = {leg: {"rotation_matrix": np.asarray(r).tolist(),
                                            "time_offset_s": float(t)}
                                      for leg, (r, t) in self.cfg.truth.items()}
        try:
            Path(self.cfg.out_dir).mkdir(parents=True, exist_ok=True)
            return write_mcap(path, self.recorder.snapshot(), meta)
        except Exception as e:  # noqa: BLE001 - the session file must not hide the results
            log.error("session recording not written: %r", e)
            print(f"a2i-deploy: session recording not written: {e}", file=sys.stderr)
            return None


def _tick_of(payload: bytes) -> int:
    # LowState_.tick: u32 at wire offset 1100 (docs/go2-messages.md)
    return int.from_bytes(payload[1100:1104], "little") if len(payload) >= 1104 else -1

