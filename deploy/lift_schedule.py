"""Joint targets of the lifted leg during a calibration, the same in training and on board.

Pure numpy + ``calib`` (no torch, no mujoco). After the lift command for ``leg`` is given
(time ``t = 0``), the phases follow each other:

========  ==============================================================================
shift     ``[0, shift)``: the policy alone; it moves the body over the other three feet
          (the leg is still on the ground). No targets.
lift      quintic blend from ``q_start`` (the leg's joints when shift ended) to the
          excitation start pose ``plan.q0`` (``calib.excitation.TRIPOD_LIFT_POSE_LEG``).
hold      hold ``plan.q0`` (the body settles on the tripod).
excite    the anti-noise trajectory ``calib.excitation.ExcitationPlan`` of the leg (built once
          from ``t_r``, ``n_basis``, ``periods`` and ``seed``, cached), which starts and ends
          at ``plan.q0`` with zero velocity.
lower     quintic blend from ``plan.q0`` back to ``q_start``.
done      the policy alone again (deploy goes on to LOWER -> STAND; training clears the lift
          command). No targets.
========  ==============================================================================

While targets exist, the lifted leg's three motors get ``q_des``, ``dq_des`` and this
schedule's ``kp`` / ``kd`` (the policy's actions for that leg are ignored, but they still feed
``previous_actions``), and, with ``feedforward``, the torque ``tau`` that the planned motion
takes with the base still (:mod:`deploy.leg_dynamics`), within the motors' effort limits. With
``adapt``, whoever runs the motors (``deploy.session``, the free-base runs, the evaluation) adds
the torque of :class:`deploy.tracking_adapter.TrackingAdapter` in excite and lower: what the
leg's tracking shows the model lacks, identified during the excitation.
Joint triples are (hip, thigh, calf) in the leg's own URDF signs, rad.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import asdict, dataclass, replace

import numpy as np

from calib.excitation import ExcitationConfig, ExcitationPlan, plan_excitation
from calib.joints import EFFORT_LIMIT, check_leg

__all__ = ["COMMANDS_PER_TICK", "PHASES", "LegTarget", "LiftSchedule", "abort_targets",
           "blend_accelerations", "blend_targets"]

COMMANDS_PER_TICK = 5
"""LowCmd_ frames per 50 Hz policy tick (250 Hz, 4 ms apart), each with the lifted leg's
targets at its own time: deploy's default (``deploy.session.SessionConfig.commands_per_tick``),
and how the free-base runs of :mod:`policy_train.policy_motion` play the schedule."""

PHASES: tuple[str, ...] = ("shift", "lift", "hold", "excite", "lower", "done")


def _smooth(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Quintic smoothstep on [0, 1] (clipped) and its derivative in x."""
    x = np.clip(x, 0.0, 1.0)
    return x**3 * (10 - 15 * x + 6 * x**2), 30 * x**2 * (1 - x) ** 2


def _smooth_dd(x: np.ndarray) -> np.ndarray:
    """Second derivative in x of the quintic smoothstep (zero outside [0, 1])."""
    inside = (x >= 0.0) & (x <= 1.0)
    return np.where(inside, 60 * x * (1 - x) * (1 - 2 * x), 0.0)


def abort_targets(t, duration: float, q_from, q_to) -> tuple[np.ndarray, np.ndarray]:
    """An aborted lift's way back: quintic from ``q_from`` (the leg's last target) to ``q_to``
    (where it stood) over ``duration`` s (:attr:`LiftSchedule.abort_lower`). t: (N,) s since
    the abort. Returns q_des, dq_des (N, 3) rad, rad/s; q_to and zero from ``duration`` on."""
    t = np.asarray(t, dtype=float)
    q_from, q_to = np.asarray(q_from, dtype=float), np.asarray(q_to, dtype=float)
    w, dw = _smooth(t / duration)
    return (q_from + w[..., None] * (q_to - q_from),
            (dw / duration)[..., None] * (q_to - q_from))


def blend_targets(t, durations, q_start, q_lift, q_exc, dq_exc):
    """Vectorised phase logic (used by :class:`LiftSchedule` and by the training env).

    t: (N,) s since the lift command. durations: (N, 5) or (5,) s of shift, lift, hold, excite,
    lower. q_start, q_lift: (N, 3) rad. q_exc, dq_exc: (N, 3) the excitation plan evaluated at
    ``t - (shift + lift + hold)`` (rad, rad/s). Returns (q_des (N, 3), dq_des (N, 3),
    phase (N,) int index into :data:`PHASES`); ``q_des`` is NaN in shift and done.
    """
    t = np.asarray(t, dtype=float)
    d = np.broadcast_to(np.asarray(durations, dtype=float), t.shape + (5,))
    ends = np.cumsum(d, axis=-1)
    phase = (t[..., None] >= ends).sum(-1)  # 0..5
    q_start = np.asarray(q_start, dtype=float)
    q_lift = np.asarray(q_lift, dtype=float)
    # lift: q_start -> q_lift over d1
    w1, dw1 = _smooth((t - ends[..., 0]) / d[..., 1])
    q_l = q_start + w1[..., None] * (q_lift - q_start)
    dq_l = (dw1 / d[..., 1])[..., None] * (q_lift - q_start)
    # lower: q_lift -> q_start over d4
    w4, dw4 = _smooth((t - ends[..., 3]) / d[..., 4])
    q_d = q_lift + w4[..., None] * (q_start - q_lift)
    dq_d = (dw4 / d[..., 4])[..., None] * (q_start - q_lift)
    p = phase[..., None]
    q_des = np.where(p == 1, q_l, np.where(p == 2, q_lift, np.where(p == 3, q_exc, q_d)))
    dq_des = np.where(p == 1, dq_l, np.where(p == 2, 0.0, np.where(p == 3, dq_exc, dq_d)))
    none = (p == 0) | (p == 5)
    q_des = np.where(none, np.nan, q_des)
    dq_des = np.where(none, np.nan, dq_des)
    return q_des, dq_des, phase


def blend_accelerations(t, durations, q_start, q_lift, ddq_exc):
    """Joint accelerations (N, 3), rad/s^2, of :func:`blend_targets`' ``q_des`` (same
    arguments; ``ddq_exc`` the plan's accelerations at ``t - (shift + lift + hold)``); NaN in
    shift and done."""
    t = np.asarray(t, dtype=float)
    d = np.broadcast_to(np.asarray(durations, dtype=float), t.shape + (5,))
    ends = np.cumsum(d, axis=-1)
    phase = (t[..., None] >= ends).sum(-1)
    step = np.asarray(q_lift, dtype=float) - np.asarray(q_start, dtype=float)
    a_l = (_smooth_dd((t - ends[..., 0]) / d[..., 1]) / d[..., 1] ** 2)[..., None] * step
    a_d = -(_smooth_dd((t - ends[..., 3]) / d[..., 4]) / d[..., 4] ** 2)[..., None] * step
    p = phase[..., None]
    dd = np.where(p == 1, a_l, np.where(p == 2, 0.0, np.where(p == 3, ddq_exc, a_d)))
    return np.where((p == 0) | (p == 5), np.nan, dd)


@dataclass(frozen=True)
class LegTarget:
    """Targets of the lifted leg's three motors now. q_des rad, dq_des rad/s, kp N m/rad, kd
    N m s/rad (hip, thigh, calf; leg's own URDF signs); phase one of :data:`PHASES`.
    ``q_des``/``dq_des`` are None in shift and done (the policy commands the leg). tau: the
    feed-forward torque, N m, or None (no ``feedforward``, or no targets). ddq_des: the plan's
    acceleration, rad/s^2, where it has targets (the tracking adapter's feature).
    """

    phase: str
    q_des: np.ndarray | None
    dq_des: np.ndarray | None
    kp: float
    kd: float
    tau: np.ndarray | None = None
    ddq_des: np.ndarray | None = None


@dataclass
class LiftSchedule:
    """Phase durations (s), the lifted leg's PD gains, and the excitation settings.

    shift, lift, hold, lower: s. shift_by_leg: {leg: s} the shift of those legs' lifts where it
    is not ``shift`` (None: every leg's is ``shift``; v25: the front legs' 2 s, the rear legs'
    the training's 1 s). kp N m/rad, kd N m s/rad: gains of the lifted leg's motors
    while targets exist. t_r (s), n_basis, periods, seed, ground_clearance (m):
    :class:`calib.excitation.ExcitationConfig` of each leg's plan (other settings at their
    defaults). A policy JSON without ``ground_clearance`` was trained on plans with the
    generator's default. feedforward: also command the planned motion's inverse-dynamics
    torque (:class:`deploy.leg_dynamics.LegDynamics`); a JSON without it has none. adapt: from
    2 s into the excitation on, also command the torque the leg's tracking shows the model
    lacks (:class:`deploy.tracking_adapter.TrackingAdapter`: damping, friction, inertia, a
    torque constant off); a JSON without it has none. excitation_seen (in [0, 1]): while the
    excitation plays, the policy observes the lifted leg at ``q0 + excitation_seen (q - q0)``
    rad and ``excitation_seen dq`` rad/s (:func:`deploy.observation.observe_lifted_leg`; q0 the
    plan's start pose ``plan.q0``, where the hold held the leg and the excitation starts and
    ends, not its mean pose): 1, the leg as measured; 0, still at q0. The policy's answer to
    the motion it sees, not the leg's reaction on the body, is half of v43's body rotation
    over the excitation; shown none of it the policy loses lifts on weak motors, which it meets
    by seeing where the leg is (docs/policy-training.md, stop 67). A JSON without it observes
    the leg as measured.
    """

    shift: float = 1.0
    shift_by_leg: dict[str, float] | None = None
    lift: float = 0.6
    hold: float = 0.5
    lower: float = 0.6
    kp: float = 40.0
    kd: float = 1.0
    t_r: float = 0.5
    n_basis: int = 10
    periods: int = 4
    seed: int = 0
    ground_clearance: float = ExcitationConfig.ground_clearance
    feedforward: bool = False
    adapt: bool = False
    excitation_seen: float = 1.0

    def __post_init__(self) -> None:
        for k in ("shift", "lift", "hold", "lower", "kp", "kd", "t_r", "ground_clearance",
                  "n_basis", "periods", "seed", "excitation_seen"):
            v = getattr(self, k)  # a JSON string or null: one line here, not a TypeError later
            if isinstance(v, bool) or not isinstance(v, int | float | np.number):
                raise ValueError(f"{k} must be a number, got {v!r}")  # noqa: TRY004
        for k in ("shift", "lift", "hold", "lower"):
            v = getattr(self, k)
            if not (np.isfinite(v) and v > 0):
                raise ValueError(f"{k} must be a positive duration (s), got {v}")
        if self.shift_by_leg is not None:
            if not isinstance(self.shift_by_leg, Mapping):
                raise ValueError(
                    f"shift_by_leg must map legs to seconds, got {self.shift_by_leg!r}")
            for leg, v in self.shift_by_leg.items():
                check_leg(leg)
                if isinstance(v, bool) or not (isinstance(v, (int, float)) and np.isfinite(v)
                                               and v > 0):
                    raise ValueError(f"shift_by_leg[{leg}] must be a positive duration (s), "
                                     f"got {v!r}")
            # legs as shift_of() asks for them: "fl" would be accepted and never found
            by_leg = {check_leg(leg): float(v) for leg, v in self.shift_by_leg.items()}
            if len(by_leg) != len(self.shift_by_leg):
                raise ValueError(f"shift_by_leg names a leg twice: {sorted(self.shift_by_leg)}")
            self.shift_by_leg = by_leg
        if not (np.isfinite(self.kp) and self.kp > 0 and np.isfinite(self.kd) and self.kd >= 0):
            raise ValueError(f"kp must be > 0 and kd >= 0 (finite), got kp {self.kp}, kd {self.kd}")
        if not (np.isfinite(self.ground_clearance) and self.ground_clearance >= 0):
            raise ValueError(f"ground_clearance must be >= 0 m, got {self.ground_clearance}")
        if not 0.0 <= self.excitation_seen <= 1.0:
            raise ValueError(f"excitation_seen must be in [0, 1], got {self.excitation_seen}")
        for k in ("feedforward", "adapt"):
            if not isinstance(getattr(self, k), bool):
                # a bad JSON value, reported like the others (the loaders catch ValueError)
                raise ValueError(  # noqa: TRY004
                    f"{k} must be true or false, got {getattr(self, k)!r}")
        self.excitation_config("FL")  # t_r, n_basis, periods: checked now, not at the plan
        self._plans: dict[str, ExcitationPlan] = {}

    # ------------------------------------------------------------------ metadata
    @classmethod
    def from_metadata(cls, d: Mapping) -> LiftSchedule:
        """From the policy JSON's ``lift_schedule`` object (unknown keys raise ValueError)."""
        names = {f for f in cls.__dataclass_fields__ if not f.startswith("_")}
        extra = set(d) - names
        if extra:
            raise ValueError(f"unknown lift_schedule keys: {sorted(extra)}")
        return cls(**{k: d[k] for k in d})

    def to_metadata(self) -> dict:
        """The JSON ``lift_schedule`` object (plain floats and ints; ``shift_by_leg`` only
        where set)."""
        return {k: v for k, v in asdict(self).items()
                if not k.startswith("_") and not (k == "shift_by_leg" and v is None)}

    def shift_of(self, leg: str) -> float:
        """The shift phase of ``leg``'s lift, s."""
        return float((self.shift_by_leg or {}).get(check_leg(leg), self.shift))

    # ------------------------------------------------------------------ plans and phases
    def excitation_config(self, leg: str) -> ExcitationConfig:
        return ExcitationConfig(leg=check_leg(leg), t_r=self.t_r, n_basis=self.n_basis,
                                periods=self.periods, seed=self.seed,
                                ground_clearance=self.ground_clearance)

    def plan(self, leg: str) -> ExcitationPlan:
        """The leg's excitation plan (optimised on first use, ~0.1-0.4 s, then cached)."""
        leg = check_leg(leg)
        if leg not in self._plans:
            plan = plan_excitation(self.excitation_config(leg))
            problems = plan.problems()
            if problems:  # refused before a lift plays it, not found in its results
                raise ValueError(f"the lift schedule's excitation for {leg} cannot be played: "
                                 + "; ".join(problems))
            self._plans[leg] = plan
        return self._plans[leg]

    def prepare(self, leg: str) -> None:
        """Build now what :meth:`targets` of ``leg`` needs (its plan; with ``feedforward``, the
        leg's dynamics, read from the URDF): a control loop calls this before it starts."""
        self.plan(leg)
        if self.feedforward:
            from deploy.leg_dynamics import LegDynamics

            LegDynamics.of_leg(leg)

    def durations(self, leg: str) -> np.ndarray:
        """(5,) s: shift, lift, hold, excite, lower."""
        return np.array([self.shift_of(leg), self.lift, self.hold,
                         self.excitation_config(leg).duration, self.lower])

    def with_shift(self, leg: str, shift: float) -> LiftSchedule:
        """This schedule with ``leg``'s shift ``shift`` s (a tipped lift's retry); the
        excitation plans, which the shift leaves alone, are shared, not optimised again."""
        leg = check_leg(leg)
        out = replace(self, shift_by_leg={**(self.shift_by_leg or {}), leg: float(shift)})
        out._plans = self._plans
        return out

    @property
    def abort_lower(self) -> float:
        """s to bring an aborted lift's leg back to where it stood: half again the lower
        phase, since the leg may be anywhere in its plan."""
        return 1.5 * self.lower

    def total(self, leg: str) -> float:
        """Time from the command to the start of ``done``, s."""
        return float(self.durations(leg).sum())

    def phase(self, leg: str, t: float) -> str:
        """Phase name at ``t`` s after the lift command."""
        ends = np.cumsum(self.durations(leg))
        return PHASES[int((float(t) >= ends).sum())]

    def targets(self, leg: str, t: float, q_start, gravity_b=None) -> LegTarget:
        """Targets of ``leg`` at ``t`` s after the lift command.

        q_start: (3,) rad, the leg's joint positions when the shift phase ended (the caller
        latches them at the first call in ``lift``; during ``shift`` pass the current ones).
        gravity_b: (3,) unit direction of gravity in the base frame (the projected gravity)
        for the feed-forward torque; None: level.
        """
        return self.targets_at(leg, [t], q_start, gravity_b)[0]

    def targets_at(self, leg: str, ts, q_start, gravity_b=None) -> list[LegTarget]:
        """:meth:`targets` at each of the times ``ts`` (s after the lift command) in one
        vectorised evaluation (a tick's LowCmd_ frames: the feed-forward's dynamics cost
        about as much for one time as for five)."""
        t = np.asarray(ts, dtype=float).reshape(-1)
        if t.size == 0 or not np.all(np.isfinite(t)) or np.any(t < 0):
            raise ValueError(f"times must be finite and >= 0 s, got {ts}")
        qs = np.asarray(q_start, dtype=float)
        if qs.shape != (3,) or not np.all(np.isfinite(qs)):
            raise ValueError("q_start must be 3 finite joint angles (rad)")
        plan = self.plan(leg)
        d = self.durations(leg)
        te = t - d[:3].sum()
        q, dq, ph = blend_targets(t, d, qs[None], plan.q0[None], plan.positions(te),
                                  plan.velocities(te))
        ddq = blend_accelerations(t, d, qs[None], plan.q0[None], plan.accelerations(te))
        tau = None
        if self.feedforward:
            tau = self.feedforward_torque(leg, q, dq, np.nan_to_num(ddq), gravity_b)
        out = []
        for i, p in enumerate(ph):
            name = PHASES[int(p)]
            if name in ("shift", "done"):
                out.append(LegTarget(name, None, None, self.kp, self.kd))
            else:
                out.append(LegTarget(name, q[i], dq[i], self.kp, self.kd,
                                     None if tau is None else tau[i], ddq[i]))
        return out

    @staticmethod
    def feedforward_torque(leg, q, dq, ddq, gravity_b=None) -> np.ndarray:
        """(N, 3) N m: the torque of the planned (q, dq, ddq) of ``leg`` (a name, or N names:
        one per sample), base still, clipped to the motors' effort limits (a bad tilt input
        must not ask for more)."""
        from deploy.leg_dynamics import LegDynamics  # deferred: reads the URDF once

        tau = (LegDynamics.of_leg(leg).torques(q, dq, ddq, gravity_b) if isinstance(leg, str)
               else LegDynamics.torques_of_legs(leg, q, dq, ddq, gravity_b))
        return np.clip(tau, -EFFORT_LIMIT, EFFORT_LIMIT)

    @staticmethod
    def save_dynamics_pack(path) -> None:
        """Write the legs' inverse dynamics the feed-forward uses, for a machine without the
        URDF or pinocchio (:meth:`deploy.leg_dynamics.LegDynamics.save_pack`)."""
        from deploy.leg_dynamics import LegDynamics

        LegDynamics.save_pack(path)

    @staticmethod
    def load_dynamics_pack(path) -> tuple[str, ...]:
        """Take the feed-forward's leg dynamics from a :meth:`save_dynamics_pack` file from now
        on (this process); returns its legs. ValueError if it is not such a file."""
        from deploy.leg_dynamics import LegDynamics

        return LegDynamics.load_pack(path)

    @staticmethod
    def feedforward_table(leg: str, q, dq, ddq):
        """:meth:`feedforward_torque` of a tabulated plan (N, 3 each) as a
        :class:`deploy.leg_dynamics.TorqueTable`, the tilt given per sample."""
        from deploy.leg_dynamics import LegDynamics

        return LegDynamics.of_leg(leg).table(q, dq, ddq, EFFORT_LIMIT)
