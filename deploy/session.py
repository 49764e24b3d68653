"""The calibration state machine: what the robot is told to do at every 50 Hz tick.

States and their exits (every transition is reported with its cause)::

    PASSIVE   damping (kp 0). -> STAND after ``passive_s`` (legs given on the command line)
              or on L2+A (joystick mode).
    STAND     timed interpolation from the joints at entry to the policy's default pose with the
              stand gains, then a settle. -> SOLVE if a leg was just lowered; -> TRIPOD(leg) if
              a leg is queued (or its joystick combo fired); -> SIT when nothing is left on
              the command line. Timeout: pose not reached -> DAMP.
    TRIPOD    the leg's ONNX policy (switched in here when legs have their own) with the
              leg's lift command; the leg's motors follow the lift
              schedule (shift, lift, hold). -> CALIBRATE when the excitation begins.
              The lifted leg must track its targets by the end of hold, else abort -> LOWER.
              A lift or hold that tips the body past ``max_tip`` from its tilt when the
              lift began aborts -> LOWER (``deploy.tip_guard``); the leg is then lifted
              once more, after REPLANT, with its shift ``tip_retry_shift_s`` longer.
              The foot leaves the floor only once the centre of mass, estimated from the
              joints and the body IMU, stands ``lift_gate`` inside the stance triangle: the
              shift is held longer for it, and a margin that does not come aborts the same
              way (``deploy.lift_gate``).
    CALIBRATE the excitation plan on the lifted leg; its span is the recording window of SOLVE.
              -> LOWER when it ends; a failed foot IMU aborts -> LOWER (no result).
    LOWER     the schedule's lower phase, then ``lower_settle_s`` of the policy alone (none by
              default). -> STAND.
    SOLVE     stand hold while the solver runs on a worker (never in the loop; in lockstep the
              runtime waits for it before the next tick). -> REPORT.
              Timeout ``solve_timeout_s`` -> REPORT with the error.
    REPORT    the outcome is published (once). -> TRIPOD(next leg), or STAND (joystick mode),
              or SIT. -> REPLANT instead of TRIPOD once a leg has been lifted since the last
              stand-up (also from STAND).
    REPLANT   interpolation to the lying pose and a hold, the base down and the feet unloaded,
              -> STAND, which stands up and starts the leg: after a lift the feet stay where
              the tripod left them (friction; the stand holds its joints up to 0.3 rad off
              the default pose) and a lift from there starts where the policy was never
              evaluated. Off with ``SessionConfig.replant`` False.
    SIT       interpolation to the lying pose, then damping. -> DONE.
    DAMP      kp 0, kd ``damp_kd`` on every joint. Final after a fault; after L2+B in joystick
              mode, L2+A stands up again.
    DONE      damping; the loop exits.

L2+B (combo "damp") and a stop request (combo "stop": Ctrl-C) go to DAMP from every state
within the tick they are seen. Any supervisor fault (passed in
``TickInput.fault``) or a non-finite observation / action goes to DAMP in the same tick.

Pure logic: inputs arrive as :class:`TickInput`, the policy and the solver are injected, the
output is the tick's :class:`Command`. Times are tick counts x ``dt`` (deterministic).
Joint vectors in SDK order (FR, FL, RR, RL), rad, rad/s, N m/rad, N m s/rad.
"""

from __future__ import annotations

import dataclasses
import enum
import logging
import math
from collections import deque
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np

from calib.joints import (
    EFFORT_LIMIT,
    LEGS,
    LIE_POSE_LEG,
    check_leg,
    full_pose,
    sdk_indices,
    sdk_to_model,
)
from calib.support import go2_support
from deploy.lift_gate import DEFAULT_GATE, GateLimits, LiftGate
from deploy.lift_schedule import COMMANDS_PER_TICK, LegTarget, abort_targets
from deploy.observation import build_observation, observe_lifted_leg, projected_gravity
from deploy.supervisor import DAMP_KD, SafetySupervisor
from deploy.tip_guard import DEFAULT_TIP_LIMITS, RETRY_SHIFT_S, TipGuard, TipLimits
from deploy.tracking_adapter import TrackingAdapter

__all__ = ["Command", "Session", "SessionConfig", "State", "TickInput"]

log = logging.getLogger(__name__)


class State(enum.Enum):
    PASSIVE = "PASSIVE"
    STAND = "STAND"
    TRIPOD = "TRIPOD"
    CALIBRATE = "CALIBRATE"
    LOWER = "LOWER"
    SOLVE = "SOLVE"
    REPORT = "REPORT"
    SIT = "SIT"
    DAMP = "DAMP"
    DONE = "DONE"
    REPLANT = "REPLANT"  # last: a state's place in this list is its recorded event code


@dataclass(frozen=True)
class SessionConfig:
    """Durations (s), gains (N m/rad, N m s/rad), tolerances (rad) of the state machine."""

    passive_s: float = 0.5
    stand_s: float = 2.0
    stand_settle_s: float = 1.0
    stand_kp: float = 60.0
    stand_kd: float = 5.0
    # max joint error of a settled stand: after a tripod the feet stay where it left them
    # (friction), so the hips' abduction settles 0.20-0.28 rad from the default pose on the
    # mock (thighs and calves converge); 0.25 refused a good stand after RR
    stand_tolerance: float = 0.35
    stand_timeout_s: float = 3.0
    track_tolerance: float = 0.35
    # s of the policy alone, with no lift command, once the foot is down. Zero: after an FR
    # lift the graphs of v17's network (v17-v21) spin the body (randomised, 45-47 of 50 past
    # 0.8 rad/s within 0.5 s; after FL 1-3), and the stand that followed tipped the mock past
    # 30 deg.
    # Likely why: the graph plays FR's lift as FL's mirrored and stops mirroring with the
    # command (JSON mirrored_legs), leaving its own network a pose it did not make
    lower_settle_s: float = 0.0
    tripod_margin_s: float = 1.0
    solve_timeout_s: float = 180.0
    sit_s: float = 2.0
    sit_hold_s: float = 0.5
    # sit down and stand up again between lifts (REPLANT), so that every lift starts from the
    # stand-up's stance, as the evaluation's do: without it a run of all four legs on the mock
    # on a floor tilted 4 deg (front or left side down) tipped over lifting FL, third, from
    # where RL and RR had left the feet, while FL lifted first held
    replant: bool = True
    # a lift that tips the body this many deg from its tilt when the lift began (lifting,
    # holding) is called off, the foot put back down (deploy.tip_guard, which says where the
    # limits come from; a2i-deploy --max-tip); None: never
    max_tip: TipLimits | None = DEFAULT_TIP_LIMITS
    # a lift the tip guard or the lift gate called off is tried once more, after REPLANT, with
    # its shift this much longer (s); None: not tried again
    tip_retry_shift_s: float | None = RETRY_SHIFT_S
    # the foot leaves the floor only once the estimated centre of mass stands this far inside
    # the stance triangle, the shift held up to this much longer for it (deploy.lift_gate,
    # which says where the numbers come from; a2i-deploy --lift-gate); None: lift on time
    lift_gate: GateLimits | None = DEFAULT_GATE
    damp_kd: float = DAMP_KD
    # LowCmd_ frames per tick. The motors hold each frame's target, so a lifted leg whose
    # target moved once per 20 ms tick lagged its plan in a 20 ms staircase: at its kp 80 that
    # shook the tripod (nominal base rate 0.11-0.15 rad/s against 0.08-0.10 with the target
    # moved every 4 ms; docs/deploy.md). Training moves it every 5 ms physics step.
    commands_per_tick: int = COMMANDS_PER_TICK

    def __post_init__(self) -> None:
        # a bad limit is refused here, not at the first lift; a number or a pair is taken too
        object.__setattr__(self, "max_tip", TipLimits.of(self.max_tip))
        object.__setattr__(self, "lift_gate", GateLimits.of(self.lift_gate))
        r = self.tip_retry_shift_s
        if r is not None and not (isinstance(r, (int, float)) and math.isfinite(r) and r > 0):
            raise ValueError(f"tip_retry_shift_s must be a positive number of s or None, got {r!r}")
        n = self.commands_per_tick
        if isinstance(n, bool) or not isinstance(n, int) or n < 1:
            raise ValueError(f"commands_per_tick must be an integer >= 1, got {n!r}")


@dataclass
class TickInput:
    """One tick's inputs. q, dq (12,) SDK order; tau (12,) SDK order, N m: the torque the
    motors report (LowState's ``tau_est``; the lifted leg's tracking adapter identifies the
    command's delay from it; None: not reported); quat (w, x, y, z) body -> world; gyro (3,)
    rad/s body frame; combos: names of the joystick combos fired this tick ("damp", "stand",
    "calibrate_FL", ...); fault: supervisor fault cause; imu_errors: leg -> error text;
    window_mark: opaque marker of the newest LowState (what SOLVE's window is made of)."""

    q: np.ndarray | None
    dq: np.ndarray | None = None
    tau: np.ndarray | None = None
    quat: np.ndarray | None = None
    gyro: np.ndarray | None = None
    combos: Sequence[str] = ()
    fault: str | None = None
    imu_errors: dict[str, str] = field(default_factory=dict)
    window_mark: object = None


@dataclass
class Command:
    """The LowCmd_ content at the start of a tick (12,) each, and what produced it.

    substeps: the frames for the rest of the tick, sent ``dt / commands_per_tick`` apart
    (the lifted leg's schedule evaluated at their times, every other motor as here); empty:
    this frame is repeated.
    """

    q: np.ndarray
    dq: np.ndarray
    kp: np.ndarray
    kd: np.ndarray
    tau: np.ndarray
    source: str = ""
    obs: np.ndarray | None = None
    actions: np.ndarray | None = None
    substeps: tuple[Command, ...] = ()


@dataclass
class LegOutcome:
    """What happened to one leg's calibration (filled by the solve job or by an abort)."""

    leg: str
    ok: bool = False
    error: str | None = None
    payload: object = None  # the solve job's result object (deploy.solve.SolveOutcome)
    retried: str | None = None  # why the first lift was called off, if it was tried again
    lift_wait_s: float = 0.0  # s the lift gate held the shift of the lift that counts
    # s: the command path's delay the lifted leg's tracking adapter read from the motors'
    # reported torque (None: not read: no torque reported, the adapter off, or the lift ended
    # before its first fit); trained_delay_s: the (lo, hi) s the policy was trained under
    command_delay_s: float | None = None
    trained_delay_s: tuple[float, float] | None = None
    job: object = field(default=None, repr=False)  # its solve job, once started


def _read_job(o: LegOutcome) -> None:
    out = o.job.outcome()
    o.payload = out
    o.ok = bool(getattr(out, "accepted", False))
    o.error = getattr(out, "error", None)


class Session:
    """The state machine (module docstring). ``step(inp) -> Command`` once per tick.

    policy: a :class:`deploy.policy.PolicyRunner` (or anything with ``meta``, ``act``,
    ``reset``, ``step``, ``prev_actions``, ``target``), or a mapping leg -> runner (each leg
    is balanced by its own policy, switched in at TRIPOD's first tick; combos for legs
    without one are ignored; they must agree on the default pose). start_solve(leg, window) -> job with
    ``done()`` and ``outcome()``; window is (mark at CALIBRATE start, mark at its end).
    legs: calibrated in turn, from the command line; joystick: wait for combos instead.
    on_transition(old, new, cause) and on_report(LegOutcome) are called from ``step``.
    available_legs: legs with a foot IMU (joystick combos for others are ignored).
    """

    def __init__(self, policy, supervisor: SafetySupervisor, dt: float,
                 start_solve: Callable, legs: Sequence[str] = (), joystick: bool = False,
                 config: SessionConfig | None = None,
                 on_transition: Callable[[State, State, str], None] | None = None,
                 on_report: Callable[[LegOutcome], None] | None = None,
                 available_legs: Sequence[str] | None = None):
        self.policies = dict(policy) if isinstance(policy, Mapping) else None
        self.policy = next(iter(self.policies.values())) if self.policies else policy
        self.meta = self.policy.meta
        self.sup = supervisor
        self.dt = float(dt)
        self.start_solve = start_solve
        self.queue: deque[str] = deque(check_leg(leg) for leg in legs)
        self.joystick = bool(joystick)
        self.available_legs = None if available_legs is None else set(available_legs)
        if self.policies is not None:
            # None: every leg a policy serves; an empty set (no foot IMU) is none of them
            given = set(self.policies) if self.available_legs is None else self.available_legs
            self.available_legs = set(self.policies) & given
            missing = [g for g in self.queue if g not in self.policies]
            if missing:
                raise ValueError(f"no policy for {', '.join(missing)}")
        self.cfg = config or SessionConfig()
        self.on_transition = on_transition
        self.on_report = on_report
        self.state = State.PASSIVE
        self.k = 0  # ticks since start
        self._k_entry = 0
        self.leg: str | None = None
        self.fault: str | None = None  # the cause of a final DAMP
        self.user_damp = False
        self.outcomes: list[LegOutcome] = []
        self._prev_target: np.ndarray | None = None
        self._interp_from: np.ndarray | None = None
        self._interp_to: np.ndarray | None = None
        self._q_start: np.ndarray | None = None
        self._window_start = None
        self._window_end = None
        self._pending_solve: str | None = None
        self._abort: str | None = None
        self._job = None
        self._k_lift = 0
        self._abort_from: np.ndarray | None = None
        self._abort_to: np.ndarray | None = None
        self._requested: str | None = None
        self._current: LegOutcome | None = None
        self._stance_used = False  # a leg was lifted since the last stand-up
        self._adapter: TrackingAdapter | None = None  # the lifted leg's, where the schedule's adapt
        self._adapted = np.zeros(3)
        self._tip = TipGuard(self.cfg.max_tip)
        self._called_off = False  # this lift was called off by the tip guard or the lift gate
        self._gate = LiftGate(self.cfg.lift_gate)
        self._support = go2_support() if self.cfg.lift_gate is not None else None
        self._retry: LegOutcome | None = None  # a called-off lift's outcome, to be tried again
        self.lie_pose = full_pose(LIE_POSE_LEG, order="sdk")
        self.phase = ""
        self.last_command: Command | None = None
        n = 12
        self._zeros = np.zeros(n)
        self._damp_kd = np.full(n, self.cfg.damp_kd)

    # ------------------------------------------------------------------ helpers
    @property
    def t_state(self) -> float:
        """Seconds since the current state was entered."""
        return (self.k - self._k_entry) * self.dt

    @property
    def finished(self) -> bool:
        return self.state is State.DONE or (
            self.state is State.DAMP and not (self.user_damp and self.joystick))

    def _go(self, new: State, cause: str) -> None:
        old = self.state
        self.state = new
        self._k_entry = self.k
        if self.on_transition is not None:
            self.on_transition(old, new, cause)

    def _damp_command(self, source: str = "damp") -> Command:
        # q = current target is irrelevant with kp = 0; send zeros-of-PD: q sentinel not needed.
        return Command(self._zeros.copy(), self._zeros.copy(), self._zeros.copy(),
                       self._damp_kd.copy(), self._zeros.copy(), source)

    def _pd(self, q_des, kp: float, kd: float, source: str) -> Command:
        q_des = self.sup.limit(np.asarray(q_des, dtype=float), self._prev_target)
        self._prev_target = q_des
        return Command(q_des, self._zeros.copy(), np.full(12, kp), np.full(12, kd),
                       self._zeros.copy(), source)

    def _start_interp(self, q_now, q_to) -> None:
        self._interp_from = np.asarray(q_now, dtype=float).copy()
        self._interp_to = np.asarray(q_to, dtype=float).copy()

    def _interp(self, duration: float) -> np.ndarray:
        x = min(1.0, self.t_state / duration) if duration > 0 else 1.0
        w = x**3 * (10 - 15 * x + 6 * x**2)
        return self._interp_from + w * (self._interp_to - self._interp_from)

    def enter_damp(self, cause: str, user: bool = False) -> None:
        if self.state is State.DAMP and not (self.user_damp and not user):
            return
        self.user_damp = user
        if not user:
            self.fault = cause
        if self._current is not None and not self._current.ok and self._current.error is None:
            self._current.error = f"aborted: {cause}"
        # A combo pressed before the damp, or a called-off lift's second try, is no order
        # after it: L2+A must only stand the robot up.
        self._requested = None
        if self._retry is not None:
            o, self._retry = self._retry, None
            o.error, o.retried = f"{o.retried}; not lifted again: {cause}", None
        self._go(State.DAMP, cause)

    # ------------------------------------------------------------------ the tick
    def step(self, inp: TickInput) -> Command:
        cmd = self._step(inp)
        self.k += 1
        self.last_command = cmd
        return cmd

    def _step(self, inp: TickInput) -> Command:
        combos = set(inp.combos)
        if "damp" in combos and not (self.state is State.DAMP and self.user_damp):
            self.enter_damp("operator: L2+B", user=True)
            return self._damp_command()
        if "stop" in combos and not (self.state is State.DAMP and self.user_damp):
            self.enter_damp("operator: stop (Ctrl-C)", user=True)
            return self._damp_command()
        if inp.fault is not None and (self.state not in (State.DAMP, State.DONE)
                                      or (self.state is State.DAMP and self.user_damp)):
            self.enter_damp(inp.fault)  # a fault makes even an operator's DAMP final
            return self._damp_command()
        if self.state is State.DAMP:
            if (self.user_damp and self.joystick and "stand" in combos
                    and inp.q is not None):
                self.user_damp = False
                self._stance_used = False  # damped, it lies down: the stand-up re-plants
                self._prev_target = np.asarray(inp.q, dtype=float).copy()
                self._start_interp(inp.q, self.meta.default_pose)
                self._go(State.STAND, "operator: L2+A")
            else:
                return self._damp_command()
        if self.state is State.DONE:
            return self._damp_command("done")
        if inp.q is None:  # nothing received yet: damping is all we can do
            return self._damp_command("passive")
        for name in combos:
            if name.startswith("calibrate_") and self.state is State.STAND:
                leg = name.split("_", 1)[1]
                if self.available_legs is None or leg in self.available_legs:
                    self._requested = leg
                else:
                    log.warning("calibrate %s ignored: no foot IMU configured for %s (give "
                                "--imu %s=PORT)", leg, leg, leg)
        for leg, err in inp.imu_errors.items():
            if (self.leg == leg and self.state in (State.TRIPOD, State.CALIBRATE)
                    and not self._abort):
                self._abort_leg(f"foot IMU {leg} failed: {err}")
        handler = getattr(self, f"_{self.state.value.lower()}")
        return handler(inp, combos)

    # ------------------------------------------------------------------ states
    def _passive(self, inp: TickInput, combos) -> Command:
        go = ("stand" in combos) if self.joystick else (self.t_state >= self.cfg.passive_s
                                                        and bool(self.queue))
        if not self.joystick and not self.queue:
            self._go(State.DONE, "nothing to calibrate")
            return self._damp_command("done")
        if go:
            self._prev_target = np.asarray(inp.q, dtype=float).copy()
            self._start_interp(inp.q, self.meta.default_pose)
            self._go(State.STAND, "operator: L2+A" if self.joystick else "start")
            return self._stand(inp, combos)
        return self._damp_command("passive")

    def _stand(self, inp: TickInput, combos) -> Command:
        c = self.cfg
        cmd = self._pd(self._interp(c.stand_s), c.stand_kp, c.stand_kd, "stand")
        if self.t_state < c.stand_s + c.stand_settle_s:
            return cmd
        err = float(np.max(np.abs(np.asarray(inp.q) - self.meta.default_pose)))
        if err > c.stand_tolerance:
            if self.t_state >= c.stand_s + c.stand_settle_s + c.stand_timeout_s:
                self.enter_damp(f"STAND timeout: pose error {err:.2f} rad > "
                                f"{c.stand_tolerance} rad")
                return self._damp_command()
            return cmd
        if self._pending_solve is not None:
            self._start_solve()
            return cmd
        if self._current is not None and not self._queue_retry():
            # an aborted leg: report it, nothing to solve
            self._go(State.REPORT, f"calibration of {self._current.leg} aborted")
            return cmd
        leg = None
        if self.queue:
            if self._maybe_replant(self.queue[0]):
                return cmd
            leg = self.queue.popleft()
            cause = f"next leg {leg}"
        elif self.joystick:
            if self._requested is not None and self._maybe_replant(self._requested):
                return cmd
            leg, self._requested = self._requested, None
            cause = f"operator: calibrate {leg}"
        else:
            self._start_interp(inp.q, self.lie_pose)
            self._go(State.SIT, "all legs done")
            return cmd
        if leg is not None:
            self._start_tripod(leg, inp, cause)
        return cmd

    def _queue_retry(self) -> bool:
        """Queue the current lift again (True) if the tip guard or the lift gate called it off
        and it was not a retry already (``SessionConfig.tip_retry_shift_s``)."""
        o = self._current
        if not self._called_off or self.cfg.tip_retry_shift_s is None or o.retried is not None:
            return False
        o.retried, o.error = o.error, None
        self._retry, self._current = o, None
        if self.joystick:
            self._requested = o.leg
        else:
            self.queue.appendleft(o.leg)
        log.warning("%s: lift called off (%s); trying again with %.1f s more shift",
                    o.leg, o.retried, self.cfg.tip_retry_shift_s)
        return True

    def _maybe_replant(self, leg: str) -> bool:
        """Go to REPLANT (True) if ``leg``'s lift would start from a stance a lift left."""
        if not (self.cfg.replant and self._stance_used):
            return False
        # from the hold's target, not the joints: the PD torque carries on without a step
        self._start_interp(self._prev_target, self.lie_pose)
        self._go(State.REPLANT, f"re-planting the feet before {leg}")
        return True

    def _replant(self, inp: TickInput, combos) -> Command:
        c = self.cfg
        cmd = self._pd(self._interp(c.sit_s), c.stand_kp, c.stand_kd, "replant")
        if self.t_state >= c.sit_s + c.sit_hold_s:
            self._stance_used = False
            self._start_interp(self._prev_target, self.meta.default_pose)
            self._go(State.STAND, "feet re-planted")
        return cmd

    def _start_tripod(self, leg: str, inp: TickInput, cause: str) -> None:
        self.leg = leg
        if self.policies is not None:
            self.policy = self.policies[leg]
        self.meta = self.policy.meta
        if self._retry is not None and self._retry.leg == leg:  # a called-off lift, again
            self._current, self._retry = self._retry, None
            self._current.lift_wait_s = 0.0  # the second lift is the one that counts
            sched = self.meta.schedule
            shift = sched.shift_of(leg) + self.cfg.tip_retry_shift_s
            self.meta = dataclasses.replace(self.meta, schedule=sched.with_shift(leg, shift))
            cause += f", again with a {shift:g} s shift"
        else:
            self._retry = None
            self._current = LegOutcome(leg)
            self.outcomes.append(self._current)
        self._q_start = None
        self._abort = None
        self._called_off = False
        self._window_start = self._window_end = None
        self.policy.reset(inp.q)
        sched = self.meta.schedule
        self._adapter = TrackingAdapter(sched.kp, sched.kd) if sched.adapt else None
        self._adapted = np.zeros(3)  # the adapter's torque in the frame the motors hold
        self._tip.reset()
        self._gate.reset()
        self._stance_used = True
        self.phase = ""
        self._k_lift = self.k + 1  # the lift command is given at TRIPOD's first tick
        self._go(State.TRIPOD, cause)

    def _frame_offsets(self) -> np.ndarray:
        """s after the tick of each of its LowCmd_ frames."""
        n = self.cfg.commands_per_tick
        return np.arange(n) * (self.dt / n)

    def _schedule_targets(self, lift_leg: str, t_lift: float, inp: TickInput) -> list:
        """The lift schedule's targets of ``lift_leg`` at this tick's frames, ``t_lift`` s
        after the lift command and on (latching q_start at the first tick whose frames reach
        lift); their feed-forward torques, if any, for the body's measured tilt."""
        sched = self.meta.schedule
        q = np.asarray(inp.q, dtype=float)
        idx = sdk_indices(lift_leg)
        ts = t_lift + self._frame_offsets()
        if self._q_start is None and sched.phase(lift_leg, ts[-1]) != "shift":
            self._q_start = q[idx].copy()  # latched at the first tick of lift
        q_start = self._q_start if self._q_start is not None else q[idx]
        gravity = projected_gravity(inp.quat) if inp.quat is not None else None
        ts_cmd = ts
        if self._adapter is not None:
            # the plan ahead by the command delay the adapter found: the motors play it on time
            t0 = float(sched.durations(lift_leg)[:3].sum())
            ts_cmd = ts + np.array([self._adapter.lead(t - t0)[0] for t in ts])
        targets = sched.targets_at(lift_leg, ts_cmd, q_start, gravity)
        if self._adapter is not None:
            targets = self._adapt(lift_leg, ts, targets, inp)
        return targets

    def _adapt(self, lift_leg: str, ts: np.ndarray, targets: list, inp: TickInput) -> list:
        """The tracking adapter (the schedule's ``adapt``): this tick's measurement of the
        lifted leg against its plan now (the tick's first frame), then each frame of the
        excitation and the lowering with the fitted torque added to its feed-forward."""
        t0 = float(self.meta.schedule.durations(lift_leg)[:3].sum())
        idx = sdk_indices(lift_leg)
        now = targets[0]
        if now.phase == "excite" and inp.dq is not None:
            model = now.tau if now.tau is not None else self._zeros[:3]
            tau = None if inp.tau is None else np.asarray(inp.tau, dtype=float)[idx]
            self._adapter.observe(ts[0] - t0, now.q_des, now.dq_des, now.ddq_des,
                                  np.asarray(inp.q, dtype=float)[idx],
                                  np.asarray(inp.dq, dtype=float)[idx], model, self._adapted,
                                  tau_motor=tau)
        out = []
        for t, lt in zip(ts, targets):
            if lt.phase in ("excite", "lower"):
                model = lt.tau if lt.tau is not None else self._zeros[:3]
                self._adapted = self._adapter.torque(t - t0, lt.dq_des, lt.ddq_des, model)[0]
                lt = dataclasses.replace(
                    lt, tau=np.clip(model + self._adapted, -EFFORT_LIMIT, EFFORT_LIMIT))
            out.append(lt)
        return out

    def _policy_command(self, inp: TickInput, lift_leg: str | None, frame_targets) -> Command:
        """Policy tick: observation, ONNX, delta target; the lifted leg from
        ``frame_targets``, its :class:`deploy.lift_schedule.LegTarget` (or None) at each of
        the tick's frames (:meth:`_frame_offsets`)."""
        m = self.meta
        q = np.asarray(inp.q, dtype=float)
        leg_target = frame_targets[0]
        phase = leg_target.phase if leg_target is not None else ""
        lift_on = lift_leg is not None and phase not in ("", "done")
        signals = {
            "base_lin_vel": np.zeros(3),
            "base_ang_vel": inp.gyro if inp.gyro is not None else np.zeros(3),
            "projected_gravity": projected_gravity(inp.quat if inp.quat is not None
                                                   else np.array([1.0, 0, 0, 0])),
            "joint_pos": q,
            "joint_vel": inp.dq if inp.dq is not None else np.zeros(12),
            "previous_actions": self.policy.prev_actions,
            "commands": np.zeros(3),
            "lift_command": m.lift_value(lift_leg if lift_on else None),
        }
        if phase == "excite" and m.schedule.excitation_seen != 1.0:
            signals = observe_lifted_leg(signals, sdk_indices(lift_leg),
                                         m.schedule.plan(lift_leg).q0, m.schedule.excitation_seen)
        obs = build_observation(m.observation, signals)
        bad = SafetySupervisor.check_finite("observation", obs)
        actions = None
        if bad is None:
            actions = self.policy.act(obs)
            bad = SafetySupervisor.check_finite("policy action", actions)
        if bad is not None:
            self.enter_damp(bad)
            cmd = self._damp_command()
            cmd.obs, cmd.actions = obs, actions
            return cmd
        target = self.policy.step(actions, q)
        if phase == "done" and self.phase not in ("done", ""):
            # Hand-back (as in training, policy_train/env.py): the policy's target of the leg
            # restarts from where the leg is; what it accumulated meanwhile was never applied.
            self.policy.target[sdk_indices(lift_leg)] = q[sdk_indices(lift_leg)]
        target = self.policy.target.copy()
        dq = np.zeros(12)
        kp, kd = m.kp.copy(), m.kd.copy()
        if leg_target is not None and leg_target.q_des is not None:
            idx = sdk_indices(lift_leg)
            target[idx] = leg_target.q_des
            dq[idx] = leg_target.dq_des
            kp[idx] = leg_target.kp
            kd[idx] = leg_target.kd
        tau = self._zeros.copy()
        if leg_target is not None and leg_target.tau is not None:
            tau[sdk_indices(lift_leg)] = leg_target.tau
        q_des = self.sup.limit(target, self._prev_target)
        self._prev_target = q_des
        self.phase = phase
        cmd = Command(q_des, dq, kp, kd, tau, f"policy:{phase or 'stand'}", obs, actions)
        if lift_leg is not None:
            cmd.substeps = self._substeps(cmd, lift_leg, frame_targets[1:])
        return cmd

    def _substeps(self, cmd: Command, lift_leg: str, later) -> tuple[Command, ...]:
        """The tick's later frames: ``cmd`` with the lifted leg's targets ``later`` (where
        the schedule gives one; a frame it does not, e.g. past the lowering, repeats the
        previous one). Each is clamped and rate-limited from the frame before it."""
        n = self.cfg.commands_per_tick
        idx = sdk_indices(lift_leg)
        subs = []
        prev = Command(cmd.q, cmd.dq, cmd.kp, cmd.kd, cmd.tau, cmd.source)  # a bare frame
        for lt in later:
            if lt is None or lt.q_des is None:
                subs.append(prev)
                continue
            q = prev.q.copy()
            q[idx] = lt.q_des
            dq, kp, kd, tau = prev.dq.copy(), prev.kp.copy(), prev.kd.copy(), prev.tau.copy()
            dq[idx] = lt.dq_des
            kp[idx], kd[idx] = lt.kp, lt.kd
            tau[idx] = lt.tau if lt.tau is not None else 0.0
            q = self.sup.limit(q, prev.q, fraction=1.0 / n)
            prev = Command(q, dq, kp, kd, tau, cmd.source)
            subs.append(prev)
        self._prev_target = prev.q
        return tuple(subs)

    def _lift_time(self) -> float:
        return (self.k - self._k_lift) * self.dt

    def _tripod(self, inp: TickInput, combos) -> Command:
        if self._abort:
            return self._lower_now(inp)
        sched = self.meta.schedule
        t = self._lift_time()
        gated = None
        if self._support is not None and self._q_start is None \
                and sched.phase(self.leg, t + self._frame_offsets()[-1]) != "shift":
            gated = self._gate.check(self._stance_margin(inp), self.dt)
            if gated != "go":  # this tick stays in the shift
                self._k_lift += 1
                t = self._lift_time()
        cmd = self._policy_command(inp, self.leg, self._schedule_targets(self.leg, t, inp))
        if self.state is State.DAMP:
            return cmd
        if gated not in (None, "go", "wait"):
            self._called_off = True
            self._abort_leg(gated)
            return cmd
        if gated == "go" and self._gate.waited_s > 0:
            self._current.lift_wait_s = self._gate.waited_s
            log.warning("%s: shift held %.2f s longer for the centre of mass", self.leg,
                        self._gate.waited_s)
        tipped = self._tip.check(self.phase, inp.quat)
        if tipped is not None:
            self._called_off = True
            self._abort_leg(tipped)  # the foot goes down from the next tick (_lower_now)
            return cmd
        if self.phase == "excite":
            idx = sdk_indices(self.leg)
            err = float(np.max(np.abs(np.asarray(inp.q)[idx] - sched.plan(self.leg).q0)))
            if err > self.cfg.track_tolerance:
                self._abort_leg(f"lifted leg off its target by {err:.2f} rad at the end of hold")
                return cmd
            self._window_start = inp.window_mark
            self._go(State.CALIBRATE, "lifted; excitation starts")
        elif t > sched.durations(self.leg)[:3].sum() + self.cfg.tripod_margin_s:
            self.enter_damp("TRIPOD timeout")
            return self._damp_command()
        return cmd

    def _stance_margin(self, inp: TickInput) -> float:
        """m, the estimated centre of mass's margin in the lifted leg's stance triangle
        (:meth:`calib.support.SupportModel.margin`); -inf without the body IMU's attitude."""
        if inp.quat is None:
            return -math.inf
        return self._support.margin(sdk_to_model(np.asarray(inp.q, dtype=float)),
                                    projected_gravity(inp.quat),
                                    [g for g in LEGS if g != self.leg])

    def _calibrate(self, inp: TickInput, combos) -> Command:
        if self._abort:
            return self._lower_now(inp)
        t = self._lift_time()
        cmd = self._policy_command(inp, self.leg, self._schedule_targets(self.leg, t, inp))
        if self.state is State.DAMP:
            return cmd
        if self.phase != "excite":
            self._note_command_delay()
            self._window_end = inp.window_mark
            self._pending_solve = self.leg
            self._go(State.LOWER, "excitation done")
        elif self.t_state > self.meta.schedule.plan(self.leg).duration + self.cfg.tripod_margin_s:
            self.enter_damp("CALIBRATE timeout")
            return self._damp_command()
        return cmd

    def _abort_leg(self, why: str) -> None:
        self._abort = why
        if self._current is not None:
            self._current.error = why
        self._pending_solve = None
        log.error("calibration of %s aborted: %s", self.leg, why)

    def _note_command_delay(self) -> None:
        """The command delay the lifted leg's adapter found, onto the leg's outcome."""
        a, o = self._adapter, self._current
        if a is not None and o is not None and a.fitted[0] and a.delay_found[0]:
            o.command_delay_s = float(a.delay[0])
            o.trained_delay_s = self.meta.trained_latency_s

    def _lower_now(self, inp: TickInput) -> Command:
        """Abort: bring the leg from its last target back to where it stood (or, still in
        shift, just drop the lift command), with the policy balancing the body."""
        self._note_command_delay()
        idx = sdk_indices(self.leg)
        self._abort_from = (self._prev_target[idx].copy() if self._prev_target is not None
                            else np.asarray(inp.q, dtype=float)[idx])
        self._abort_to = self._q_start
        self._go(State.LOWER, f"abort: {self._abort}")
        return self._lower(inp, ())

    def _abort_target(self, s: float = 0.0):
        """The aborted leg's way back, ``s`` seconds after this tick."""
        sched = self.meta.schedule
        t = self.t_state + s
        if self._abort_to is None or t >= sched.abort_lower:
            return LegTarget("done", None, None, sched.kp, sched.kd)
        q, dq = abort_targets([t], sched.abort_lower, self._abort_from, self._abort_to)
        return LegTarget("lower", q[0], dq[0], sched.kp, sched.kd)

    def _lower(self, inp: TickInput, combos) -> Command:
        sched = self.meta.schedule
        if self._abort:
            cmd = self._policy_command(inp, self.leg,
                                       [self._abort_target(s) for s in self._frame_offsets()])
            end = sched.abort_lower if self._abort_to is not None else 0.0
            done = self.t_state >= end + self.cfg.lower_settle_s
        else:
            t = self._lift_time()
            cmd = self._policy_command(inp, self.leg, self._schedule_targets(self.leg, t, inp))
            done = t >= sched.total(self.leg) + self.cfg.lower_settle_s
        if self.state is State.DAMP:
            return cmd
        if done:
            q_from = self._bumpless(inp.q, cmd)
            self._prev_target = q_from.copy()
            self._start_interp(q_from, self.meta.default_pose)
            self._go(State.STAND, "foot down")
        elif self.t_state > 2 * sched.lower + sched.total(self.leg) + 5.0:
            self.enter_damp("LOWER timeout")
            return self._damp_command()
        return cmd

    def _bumpless(self, q, cmd: Command) -> np.ndarray:
        """Stand-gain target that gives the same PD torque as ``cmd`` at joints ``q``: the
        policy's stiffness is a third of the stand's, so restarting the stand interpolation
        from its targets would triple every holding torque in one tick and jolt the body."""
        q = np.asarray(q, dtype=float)
        return q + (cmd.kp / self.cfg.stand_kp) * (cmd.q - q)

    def _start_solve(self) -> None:
        leg, self._pending_solve = self._pending_solve, None
        self._job = self.start_solve(leg, (self._window_start, self._window_end))
        if self._current is not None:
            self._current.job = self._job
        self._go(State.SOLVE, f"solving {leg} on a worker")

    def _hold(self) -> Command:
        c = self.cfg
        return self._pd(self.meta.default_pose, c.stand_kp, c.stand_kd, "stand")

    def _solve(self, inp: TickInput, combos) -> Command:
        cmd = self._hold()
        job = self._job
        if job.done():
            _read_job(self._current)
            self._go(State.REPORT, "solver finished")
        elif self.t_state > self.cfg.solve_timeout_s:
            self._current.error = f"solver timed out after {self.cfg.solve_timeout_s:.0f} s"
            self._go(State.REPORT, "solver timeout")
        return cmd

    def adopt_late_results(self) -> list[LegOutcome]:
        """The legs whose solve finished after the session stopped waiting for it (a damp or a
        stop during SOLVE, the solver's timeout): the job has written its files, so the leg's
        outcome is the job's, not the abort's. Call once the jobs are joined."""
        late = [o for o in self.outcomes
                if o.job is not None and o.payload is None and o.job.done()]
        for o in late:
            _read_job(o)
        return late

    def _report(self, inp: TickInput, combos) -> Command:
        cmd = self._hold()
        if self.on_report is not None and self._current is not None:
            self.on_report(self._current)
        self._current = None
        self.leg = None
        if self.queue:
            if not self._maybe_replant(self.queue[0]):
                leg = self.queue.popleft()
                self._start_tripod(leg, inp, f"next leg {leg}")
        elif self.joystick:
            self._prev_target = cmd.q.copy()
            self._start_interp(inp.q, self.meta.default_pose)
            self._go(State.STAND, "report done; waiting for the joystick")
        else:
            self._start_interp(inp.q, self.lie_pose)
            self._go(State.SIT, "all legs done")
        return cmd

    def _sit(self, inp: TickInput, combos) -> Command:
        c = self.cfg
        cmd = self._pd(self._interp(c.sit_s), c.stand_kp, c.stand_kd, "sit")
        if self.t_state >= c.sit_s + c.sit_hold_s:
            self._go(State.DONE, "sat down")
        return cmd
