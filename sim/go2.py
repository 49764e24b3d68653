"""``Go2Sim``: one simulated Go2 with the motor driver's PD law and ground-truth accessors.

Motor model
-----------
Each physics step the driver computes, from the **latest active command** and the current joint
state, ``tau = kp*(q_des - q) + kd*(dq_des - dq) + tau_ff``, clamps it to the torque limits, lets
the effects' ``on_torque`` hooks act, and applies it for that step. The PD law is recomputed
every physics step (FACTS.md: a public bridge holds torques 20 ms between 50 Hz commands; the
real driver does not). All joint vectors here are **model order** (FL, FR, RL, RR); the
``*_sdk`` methods convert through :mod:`calib.joints`.

Step structure and consistency
------------------------------
A physics step is "prepare" (PD torque from the state at time t, ``mj_forward``) followed by
"integrate" (``mj_Euler``). Accessors that need derived quantities (site poses, sensors,
contacts, torques) run the prepare stage for the current state if it has not been run, and the
next step reuses it, so reading the truth every step costs no second ``mj_forward``. Every
accessor therefore describes the state at :attr:`Go2Sim.time` exactly (MuJoCo's plain
``mj_step`` leaves ``sensordata`` one step behind ``qpos``: 1 ms of fake time offset, which is
what the foot-IMU calibration measures).

Base modes (``SimConfig.base``)
-------------------------------
``"free"``: the robot on the floor. ``"fixed"``: base hung at ``SimConfig.fixed_base_pos``.
``"mocap"``: base pose and velocity prescribed. Before each step the base's free-joint pose and
velocity are overwritten from the trajectory (or the last :meth:`Go2Sim.set_base_state`), so
the base angular velocity seen by every IMU is exactly the prescribed one; then a base wrench
(``qfrc_applied`` on the free joint, from ``M^-1``) is applied so the base acceleration equals
the prescribed one (finite difference of the trajectory's velocities over the step; zero for a
held state), so the legs feel the correct inertial and gravity loads. The acceleration is exact
without active constraints; with contacts or joint limits active it is refined iteratively and
is approximate (the pose and velocity stay exact: they are overwritten every step). (A MuJoCo mocap body
was not used: MuJoCo gives mocap bodies zero velocity, so the leg gyros would miss the base
rotation; a weld to a mocap body lags.)
"""

from __future__ import annotations

import bisect
import copy
import dataclasses
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field

import mujoco
import numpy as np

from calib.joints import (
    EFFORT_LIMIT,
    MODEL_LEGS,
    NUM_MOTORS,
    STAND_POSE_LEG,
    check_leg,
    full_pose,
    model_to_sdk,
    sdk_to_model,
)
from sim.effects import Effect, MotorCommand
from sim.external_model import build_go2_spec_from_mjcf
from sim.model import FIXED_BASE_POS, FOOT_RADIUS, build_go2_spec

__all__ = [
    "BaseState",
    "Go2BatchSim",
    "Go2Sim",
    "MotorCommand",
    "SimConfig",
    "build_model_for",
    "rotation_about_axis_trajectory",
    "stand_pose",
]

_TIME_EPS = 1e-9  # s; float tolerance when comparing command times with the step grid


def stand_pose() -> np.ndarray:
    """The stand pose (calib.joints.STAND_POSE_LEG on every leg), (12,) model order, rad."""
    return full_pose(STAND_POSE_LEG, order="model")


@dataclass
class SimConfig:
    """Configuration of one :class:`Go2Sim`.

    base: ``"free"``, ``"fixed"`` or ``"mocap"``. timestep: physics step, s (0.001 = 1 kHz).
    torque_limits: (12,) model order or scalar, N m; None = the URDF effort limits (the model's
    actuator ``ctrlrange`` caps at those in any case). seed: for effects that draw random
    numbers (``Go2Sim.rng``). effects: :class:`sim.effects.Effect` objects, applied in order.
    floor: add the ground plane. fixed_base_pos: world position of the base for ``"fixed"`` and
    the default start of ``"mocap"``, m. model_xml: path of another MJCF model of the Go2 to
    simulate instead of the URDF's (:mod:`sim.external_model`; None: the URDF's).
    """

    base: str = "free"
    timestep: float = 0.001
    torque_limits: np.ndarray | float | None = None
    seed: int = 0
    effects: list[Effect] = field(default_factory=list)
    floor: bool = True
    fixed_base_pos: tuple[float, float, float] = FIXED_BASE_POS
    model_xml: str | None = None


@dataclass(frozen=True)
class BaseState:
    """Base pose and velocity: position (world, m), orientation (w, x, y, z, base->world),
    linear velocity of the base origin (world frame, m/s), angular velocity (base frame, rad/s).
    """

    pos: np.ndarray
    quat_wxyz: np.ndarray
    lin_vel_world: np.ndarray
    ang_vel_base: np.ndarray


BaseTrajectory = Callable[[float], "BaseState | tuple"]


def build_model_for(config: SimConfig) -> mujoco.MjModel:
    """Compile the model a :class:`Go2Sim` with ``config`` uses (effects' ``modify_spec`` applied).

    Build once and pass it to many ``Go2Sim(config, model=...)`` to share it (read-only).
    """
    if config.model_xml is None:
        spec = build_go2_spec(config.base, config.floor, config.timestep, config.fixed_base_pos)
    else:
        spec = build_go2_spec_from_mjcf(config.model_xml, config.base, config.floor,
                                        config.timestep, config.fixed_base_pos)
    for e in config.effects:
        e.modify_spec(spec)
    return spec.compile()


def _vec(x, n: int, name: str) -> np.ndarray:
    a = np.asarray(x, dtype=float)
    try:
        a = np.broadcast_to(a, (n,)).copy()
    except ValueError:
        raise ValueError(f"{name} must have shape ({n},) or be a scalar, got {np.shape(x)}") from None
    if not np.all(np.isfinite(a)):
        raise ValueError(f"{name} must be finite")
    return a


def _unit_quat(q, name: str = "quat_wxyz") -> np.ndarray:
    a = _vec(q, 4, name)
    n = np.linalg.norm(a)
    if n < 1e-9:
        raise ValueError(f"{name} must be a non-zero quaternion (w, x, y, z)")
    return a / n


def _as_base_state(s) -> BaseState:
    """Validate a trajectory sample (called every mocap step, hence one concatenation)."""
    if isinstance(s, BaseState):
        parts = (s.pos, s.quat_wxyz, s.lin_vel_world, s.ang_vel_base)
    else:
        parts = s
    try:
        flat = np.concatenate([np.asarray(p, dtype=float).reshape(-1) for p in parts])
    except (TypeError, ValueError):
        flat = None
    if flat is None or len(parts) != 4 or flat.shape != (13,) or not np.isfinite(flat).all():
        raise ValueError(
            "a base trajectory must return finite BaseState or (pos (3,), quat_wxyz (4,), "
            "lin_vel_world (3,), ang_vel_base (3,))"
        )
    quat = flat[3:7]
    n = np.sqrt(quat @ quat)
    if n < 1e-9:
        raise ValueError("the base trajectory returned a zero quaternion")
    return BaseState(flat[0:3], quat / n, flat[7:10], flat[10:13])


def rotation_about_axis_trajectory(
    axis, amplitude: float, frequency: float, pos=FIXED_BASE_POS
) -> BaseTrajectory:
    """A base trajectory for ``"mocap"``: oscillation about a fixed world axis through ``pos``.

    angle(t) = amplitude * sin(2 pi frequency t) (rad, Hz); angular velocity in the base frame
    equals axis * angle'(t) (a fixed-axis rotation leaves the axis unchanged in the base frame).
    """
    ax = _vec(axis, 3, "axis")
    n = np.linalg.norm(ax)
    if n < 1e-12:
        raise ValueError("axis must be non-zero")
    ax = ax / n
    p = _vec(pos, 3, "pos")
    w0 = 2.0 * np.pi * float(frequency)
    amp = float(amplitude)
    zero = np.zeros(3)

    def traj(t: float) -> BaseState:
        ang = amp * np.sin(w0 * t)
        rate = amp * w0 * np.cos(w0 * t)
        quat = np.concatenate(([np.cos(ang / 2)], np.sin(ang / 2) * ax))
        return BaseState(p, quat, zero, ax * rate)

    return traj


class Go2Sim:
    """One simulated Go2 (see the module docstring for the motor model and the base modes).

    Cheap to create (about 10 ms to compile the model; pass ``model=`` to share one compiled
    :class:`mujoco.MjModel` between many instances). Each instance owns its ``MjData``, so
    separate instances can be stepped from separate threads (MuJoCo releases the GIL in
    ``mj_forward`` / ``mj_Euler``).
    """

    def __init__(self, config: SimConfig | None = None, model: mujoco.MjModel | None = None):
        cfg = config if config is not None else SimConfig()
        if cfg.base not in ("free", "fixed", "mocap"):
            raise ValueError(f"unknown base mode {cfg.base!r}: expected free, fixed or mocap")
        self.config = cfg
        m = model if model is not None else build_model_for(cfg)
        if abs(m.opt.timestep - cfg.timestep) > 1e-12:
            raise ValueError("model timestep differs from config.timestep")
        self.model = m
        self.data = mujoco.MjData(m)
        d = self.data
        self.rng = np.random.default_rng(cfg.seed)
        self.effects: list[Effect] = list(cfg.effects)
        self._torque_effects = [
            e for e in self.effects if type(e).on_torque is not Effect.on_torque
        ]

        hinge0 = m.joint("FL_hip_joint").id
        qa, da = int(m.jnt_qposadr[hinge0]), int(m.jnt_dofadr[hinge0])
        self._q = d.qpos[qa:qa + NUM_MOTORS]
        self._dq = d.qvel[da:da + NUM_MOTORS]
        self._ctrl = d.ctrl
        self._has_free = cfg.base in ("free", "mocap")
        if self._has_free:
            fj = m.joint("base_free").id
            self._bq = int(m.jnt_qposadr[fj])
            self._bv = int(m.jnt_dofadr[fj])
            if self._bv != 0:
                raise RuntimeError("the base free joint must come first in the model")
        elif m.nq != NUM_MOTORS:
            raise ValueError("a fixed-base model must have exactly 12 joints")
        self._base_id = m.body("base").id
        self._foot_sites = np.array([m.site(f"{leg}_foot").id for leg in MODEL_LEGS])
        self._foot_geoms = np.array([m.geom(f"{leg}_foot").id for leg in MODEL_LEGS])
        self._floor = m.geom("floor").id if cfg.floor else -1
        self._calf_bodies = np.array([m.body(f"{leg}_calf").id for leg in MODEL_LEGS])

        def sens(name: str) -> slice:
            s = m.sensor(name)
            return slice(int(s.adr[0]), int(s.adr[0]) + int(s.dim[0]))

        self._s_gyro = sens("imu_gyro")
        self._s_acc = sens("imu_acc")
        self._s_foot_gyro = {leg: sens(f"{leg}_imu_gyro") for leg in MODEL_LEGS}
        self._s_foot_acc = {leg: sens(f"{leg}_imu_acc") for leg in MODEL_LEGS}

        lim = (np.tile(EFFORT_LIMIT, len(MODEL_LEGS)) if cfg.torque_limits is None
               else _vec(cfg.torque_limits, NUM_MOTORS, "torque_limits"))
        if np.any(lim <= 0):
            raise ValueError("torque_limits must be > 0")
        self._tau_hi = lim.copy()
        self._tau_lo = -lim
        self._tau = np.zeros(NUM_MOTORS)
        self._tmp = np.zeros(NUM_MOTORS)
        # active command, kept in preallocated arrays for the per-step PD law
        self._cq = np.zeros(NUM_MOTORS)
        self._cdq = np.zeros(NUM_MOTORS)
        self._ckp = np.zeros(NUM_MOTORS)
        self._ckd = np.zeros(NUM_MOTORS)
        self._cff = np.zeros(NUM_MOTORS)
        self._active = MotorCommand.passive()
        self._pending: list[MotorCommand] = []

        integ = m.opt.integrator
        if integ == mujoco.mjtIntegrator.mjINT_EULER:
            self._integrate = mujoco.mj_Euler
        elif integ in (mujoco.mjtIntegrator.mjINT_IMPLICIT, mujoco.mjtIntegrator.mjINT_IMPLICITFAST):
            self._integrate = mujoco.mj_implicit
        else:
            raise ValueError("Go2Sim supports the Euler and implicit integrators only")

        # mocap state
        self._traj: BaseTrajectory | None = None
        self._traj_cache: tuple[float, BaseState] | None = None
        if cfg.base == "mocap":
            nv = m.nv
            self._unit_rows = np.zeros((6, nv))
            self._unit_rows[np.arange(6), np.arange(6)] = 1.0
            self._minv_cols = np.zeros((6, nv))
        self._stage = 0  # 0: state changed, 1: command changed (acc stage only), 2: prepared
        self._bad_qacc = 0
        self.reset()

    # ------------------------------------------------------------------ reset and commands
    def reset(self, q=None, base_pos=None, base_quat_wxyz=None) -> None:
        """Reset time to 0, the joints to ``q`` ((12,) model order, rad; default the stand
        pose) at rest, the motors passive (zero command), and the base.

        free: ``base_pos`` None places the robot with its feet touching the floor under the
        origin (height from the foot positions). mocap: a set trajectory defines the base;
        otherwise ``base_pos`` (default ``fixed_base_pos``) at rest. fixed: the base pose is
        part of the model (``SimConfig.fixed_base_pos``); passing one raises ValueError.
        """
        m, d = self.model, self.data
        mode = self.config.base
        qj = stand_pose() if q is None else _vec(q, NUM_MOTORS, "q")
        if mode == "fixed" and (base_pos is not None or base_quat_wxyz is not None):
            raise ValueError("the fixed base pose is set by SimConfig.fixed_base_pos")
        if mode == "mocap" and self._traj is not None and (
            base_pos is not None or base_quat_wxyz is not None
        ):
            raise ValueError("a base trajectory is set: it defines the base pose")
        mujoco.mj_resetData(m, d)
        self._q[:] = qj
        if self._has_free:
            quat = (np.array([1.0, 0.0, 0.0, 0.0]) if base_quat_wxyz is None
                    else _unit_quat(base_quat_wxyz, "base_quat_wxyz"))
            b = self._bq
            d.qpos[b + 3:b + 7] = quat
            if mode == "mocap" and self._traj is not None:
                self._traj_cache = None
                self._write_base(self._traj_state(0.0))
            elif base_pos is not None:
                d.qpos[b:b + 3] = _vec(base_pos, 3, "base_pos")
            elif mode == "mocap":
                d.qpos[b:b + 3] = self.config.fixed_base_pos
            else:
                d.qpos[b:b + 3] = 0.0
                mujoco.mj_kinematics(m, d)
                lowest = d.site_xpos[self._foot_sites, 2].min()
                d.qpos[b + 2] = FOOT_RADIUS - lowest
        self._active = MotorCommand.passive()
        for a in (self._cq, self._cdq, self._ckp, self._ckd, self._cff):
            a[:] = 0.0
        self._pending.clear()
        self._stage = 0
        self._bad_qacc = int(d.warning[mujoco.mjtWarning.mjWARN_BADQACC].number)
        for e in self.effects:
            e.reset(self)

    def set_command(self, q_des, dq_des, kp, kd, tau_ff) -> None:
        """Send a motor command, **model order** (FL, FR, RL, RR); each (12,) or scalar.

        q_des rad, dq_des rad/s, kp N m/rad (>= 0), kd N m s/rad (>= 0), tau_ff N m. It becomes
        the active command now (or later / never, per the effects' ``on_command``) and stays
        active until the next one; the PD torque is recomputed from it every physics step.
        """
        kp_a = _vec(kp, NUM_MOTORS, "kp")
        kd_a = _vec(kd, NUM_MOTORS, "kd")
        if np.any(kp_a < 0) or np.any(kd_a < 0):
            raise ValueError("kp and kd must be >= 0")
        t = self.data.time
        cmd: MotorCommand | None = MotorCommand(
            _vec(q_des, NUM_MOTORS, "q_des"), _vec(dq_des, NUM_MOTORS, "dq_des"), kp_a, kd_a,
            _vec(tau_ff, NUM_MOTORS, "tau_ff"), t, t,
        )
        for e in self.effects:
            cmd = e.on_command(cmd, self)
            if cmd is None:
                return
        keys = [c.t_apply for c in self._pending]
        self._pending.insert(bisect.bisect_right(keys, cmd.t_apply), cmd)
        if self._stage == 2:
            self._stage = 1

    def set_command_sdk(self, q_des, dq_des, kp, kd, tau_ff) -> None:
        """:meth:`set_command` with (12,) vectors in **SDK order** (FR, FL, RR, RL)."""
        conv = [sdk_to_model(_vec(x, NUM_MOTORS, n)) for x, n in
                ((q_des, "q_des"), (dq_des, "dq_des"), (kp, "kp"), (kd, "kd"), (tau_ff, "tau_ff"))]
        self.set_command(*conv)

    @property
    def command(self) -> MotorCommand:
        """The command the motors obey at :attr:`time`."""
        self._sync()
        return self._active

    # ------------------------------------------------------------------ base prescription
    def set_base_trajectory(self, fn: BaseTrajectory | None) -> None:
        """``"mocap"`` only: prescribe the base by ``fn(t) -> BaseState`` (or a 4-tuple
        (pos, quat_wxyz, lin_vel_world, ang_vel_base)), sim time t in s. None clears it (the
        base then keeps its current velocity, see :meth:`set_base_state`).
        """
        if self.config.base != "mocap":
            raise ValueError("set_base_trajectory needs SimConfig(base='mocap')")
        if fn is not None and not callable(fn):
            raise ValueError("the base trajectory must be callable: t -> BaseState")
        self._traj = fn
        self._traj_cache = None
        if fn is not None:
            self._write_base(self._traj_state(self.data.time))
        self._stage = 0

    def set_base_state(self, pos, quat_wxyz, lin_vel_world=(0, 0, 0), ang_vel_base=(0, 0, 0)):
        """Set the base pose and velocity now (world pos m, quat w,x,y,z, world m/s, base rad/s).

        ``"mocap"``: the base then moves at this constant velocity (world linear, base-frame
        angular) until the next call; not allowed while a trajectory is set. ``"free"``: a
        teleport, after which physics takes over.
        """
        if self.config.base == "fixed":
            raise ValueError("the fixed base cannot be moved")
        if self._traj is not None:
            raise ValueError("a base trajectory is set: clear it with set_base_trajectory(None)")
        self._write_base(BaseState(_vec(pos, 3, "pos"), _unit_quat(quat_wxyz),
                                   _vec(lin_vel_world, 3, "lin_vel_world"),
                                   _vec(ang_vel_base, 3, "ang_vel_base")))
        self._stage = 0

    def push(self, dv_world) -> None:
        """Add ``dv_world`` (m/s, (3,), world frame) to the free base's linear velocity now: a
        shove, as the training's pushes give one. Only for the ``"free"`` base."""
        if self.config.base != "free":
            raise ValueError("only a free base can be pushed")
        self.data.qvel[self._bv:self._bv + 3] += _vec(dv_world, 3, "dv_world")
        self._stage = 0

    def _write_base(self, s: BaseState) -> None:
        d, b, v = self.data, self._bq, self._bv
        d.qpos[b:b + 3] = s.pos
        d.qpos[b + 3:b + 7] = s.quat_wxyz
        d.qvel[v:v + 3] = s.lin_vel_world
        d.qvel[v + 3:v + 6] = s.ang_vel_base

    def _traj_state(self, t: float) -> BaseState:
        c = self._traj_cache
        if c is not None and c[0] == t:
            return c[1]
        s = _as_base_state(self._traj(t))
        self._traj_cache = (t, s)
        return s

    def _prescribe_base_acc(self, skipsensor: int) -> None:
        """After a forward pass: add the base wrench that gives the prescribed base qacc."""
        m, d = self.model, self.data
        if self._traj is not None:
            t = d.time
            dt = m.opt.timestep
            now = self._traj_state(t)
            nxt = _as_base_state(self._traj(t + dt))
            a_des = np.concatenate(((nxt.lin_vel_world - now.lin_vel_world) / dt,
                                    (nxt.ang_vel_base - now.ang_vel_base) / dt))
            self._traj_cache = (t + dt, nxt)
        else:
            a_des = np.zeros(6)
        mujoco.mj_solveM(m, d, self._minv_cols, self._unit_rows)
        minv_bb = self._minv_cols[:, :6]
        # Exact in one pass when no constraint is active; constraint forces (contacts, joint
        # limits) respond to the base wrench, so then refine a few times.
        for _ in range(1 if d.nefc == 0 else 4):
            err = a_des - d.qacc[:6]
            if np.max(np.abs(err)) < 1e-9:
                break
            d.qfrc_applied[:6] += np.linalg.solve(minv_bb, err)
            mujoco.mj_forwardSkip(m, d, mujoco.mjtStage.mjSTAGE_VEL, skipsensor)

    # ------------------------------------------------------------------ stepping
    def _prepare(self, sensors: bool) -> None:
        """PD torque for the state at ``time`` and the forward pass (the step's first half)."""
        m, d = self.model, self.data
        full = self._stage == 0
        if self._pending and self._pending[0].t_apply <= d.time + _TIME_EPS:
            self._activate(d.time)
        mocap = self.config.base == "mocap"
        if mocap and full and self._traj is not None:
            self._write_base(self._traj_state(d.time))
        if mocap:
            d.qfrc_applied[:6] = 0.0
        tau = self._tau
        np.subtract(self._cq, self._q, out=tau)
        tau *= self._ckp
        np.subtract(self._cdq, self._dq, out=self._tmp)
        self._tmp *= self._ckd
        tau += self._tmp
        tau += self._cff
        np.clip(tau, self._tau_lo, self._tau_hi, out=tau)
        for e in self._torque_effects:
            tau = e.on_torque(tau, self)
        self._ctrl[:] = tau
        skipsensor = 0 if sensors else 1
        skip = mujoco.mjtStage.mjSTAGE_NONE if full else mujoco.mjtStage.mjSTAGE_VEL
        mujoco.mj_forwardSkip(m, d, skip, skipsensor)
        if mocap:
            self._prescribe_base_acc(skipsensor)
        # as mj_step does: a NaN / huge acceleration resets the data and counts a warning
        mujoco.mj_checkAcc(m, d)
        self._stage = 2

    def _activate(self, t: float) -> None:
        p = self._pending
        while p and p[0].t_apply <= t + _TIME_EPS:
            self._active = p.pop(0)
        c = self._active
        self._cq[:] = c.q_des
        self._cdq[:] = c.dq_des
        self._ckp[:] = c.kp
        self._ckd[:] = c.kd
        self._cff[:] = c.tau_ff

    def _sync(self) -> None:
        if self._stage != 2:
            self._prepare(True)
            self._check_diverged()

    def _check_diverged(self) -> None:
        bad = int(self.data.warning[mujoco.mjtWarning.mjWARN_BADQACC].number)
        if bad != self._bad_qacc:
            self._bad_qacc = bad
            raise RuntimeError(
                f"simulation diverged (bad qacc; MuJoCo reset the state) before "
                f"t={self.data.time:.4f} s: gains too stiff for the timestep, or a NaN state"
            )

    def step(self, n: int = 1) -> None:
        """Advance ``n`` physics steps (``n * timestep`` seconds). Same as :meth:`run`."""
        self.run(n)

    def run(self, n_steps: int) -> None:
        """Advance ``n_steps`` physics steps with the latest command; the lean loop.

        Raises RuntimeError if MuJoCo reports a diverged acceleration (gains too stiff for the
        timestep, or an invalid state).
        """
        n = int(n_steps)
        if n < 0:
            raise ValueError(f"n_steps must be >= 0, got {n_steps!r}")
        m, d = self.model, self.data
        integrate = self._integrate
        prepare = self._prepare
        for _ in range(n):
            if self._stage != 2:
                prepare(False)
            integrate(m, d)
            self._stage = 0
        self._check_diverged()

    # ------------------------------------------------------------------ truth accessors
    @property
    def time(self) -> float:
        """Sim time, s."""
        return float(self.data.time)

    @property
    def q(self) -> np.ndarray:
        """Joint positions, (12,) model order, rad."""
        return self._q.copy()

    @property
    def dq(self) -> np.ndarray:
        """Joint velocities, (12,) model order, rad/s."""
        return self._dq.copy()

    @property
    def q_sdk(self) -> np.ndarray:
        """Joint positions, (12,) SDK order, rad."""
        return model_to_sdk(self._q).copy()

    @property
    def dq_sdk(self) -> np.ndarray:
        """Joint velocities, (12,) SDK order, rad/s."""
        return model_to_sdk(self._dq).copy()

    @property
    def tau(self) -> np.ndarray:
        """Motor torques applied from :attr:`time` over the next step, (12,) model order, N m
        (after the clamp, the effects and the actuator ``ctrlrange``)."""
        self._sync()
        return self.data.actuator_force.copy()

    @property
    def base_pos(self) -> np.ndarray:
        """Base origin, world frame, m."""
        self._sync()
        return self.data.xpos[self._base_id].copy()

    @property
    def base_quat_wxyz(self) -> np.ndarray:
        """Base orientation (w, x, y, z), rotating base-frame vectors into the world frame."""
        self._sync()
        return self.data.xquat[self._base_id].copy()

    @property
    def base_rotation(self) -> np.ndarray:
        """R_W^B (3, 3): base-frame vectors into the world frame."""
        self._sync()
        return self.data.xmat[self._base_id].reshape(3, 3).copy()

    def _base_velocity_local(self) -> np.ndarray:
        self._sync()
        out = np.zeros(6)
        mujoco.mj_objectVelocity(
            self.model, self.data, mujoco.mjtObj.mjOBJ_XBODY, self._base_id, out, 1
        )
        return out

    @property
    def base_lin_vel(self) -> np.ndarray:
        """Linear velocity of the base origin, base frame, m/s."""
        return self._base_velocity_local()[3:]

    @property
    def base_ang_vel(self) -> np.ndarray:
        """Angular velocity of the base, base frame, rad/s (the body gyro's truth)."""
        self._sync()
        return self.data.sensordata[self._s_gyro].copy()

    @property
    def base_specific_force(self) -> np.ndarray:
        """Specific force at the body IMU (acceleration minus gravity), base frame, m/s^2;
        +9.81 on z at rest (the body accelerometer's truth)."""
        self._sync()
        return self.data.sensordata[self._s_acc].copy()

    def com_state(self) -> tuple[np.ndarray, np.ndarray]:
        """The whole robot's centre of mass (the base's subtree): position, m, and velocity,
        m/s, both (3,) world frame."""
        self._sync()
        m, d = self.model, self.data
        mujoco.mj_subtreeVel(m, d)  # from the forward pass's body velocities; no state change
        return d.subtree_com[self._base_id].copy(), d.subtree_linvel[self._base_id].copy()

    @property
    def base_tilt(self) -> float:
        """Angle between the base z axis and the world vertical, rad."""
        self._sync()
        return float(np.arccos(np.clip(self.data.xmat[self._base_id][8], -1.0, 1.0)))

    @property
    def foot_positions(self) -> np.ndarray:
        """Foot frame origins (ball centres), (4, 3) world frame, m, legs FL, FR, RL, RR."""
        self._sync()
        return self.data.site_xpos[self._foot_sites].copy()

    @property
    def foot_contact_forces(self) -> np.ndarray:
        """Normal contact force on each foot sphere, (4,) N, legs FL, FR, RL, RR."""
        self._sync()
        m, d = self.model, self.data
        out = np.zeros(4)
        ncon = d.ncon
        if ncon == 0:
            return out
        geoms = d.contact.geom[:ncon]
        f6 = np.zeros(6)
        for k, g in enumerate(self._foot_geoms):
            for i in np.nonzero((geoms[:, 0] == g) | (geoms[:, 1] == g))[0]:
                mujoco.mj_contactForce(m, d, int(i), f6)
                out[k] += f6[0]
        return out

    def foot_angular_velocity(self, leg: str) -> np.ndarray:
        """Absolute angular velocity of ``leg``'s foot (calf) frame, in that frame, (3,) rad/s:
        what a gyro bolted to the foot with identity mounting measures."""
        self._sync()
        return self.data.sensordata[self._s_foot_gyro[check_leg(leg)]].copy()

    def foot_specific_force(self, leg: str) -> np.ndarray:
        """Specific force at ``leg``'s foot frame origin, foot frame, (3,) m/s^2."""
        self._sync()
        return self.data.sensordata[self._s_foot_acc[check_leg(leg)]].copy()

    def foot_angular_velocities(self) -> np.ndarray:
        """:meth:`foot_angular_velocity` of FL, FR, RL, RR, (4, 3) rad/s."""
        return np.stack([self.foot_angular_velocity(leg) for leg in MODEL_LEGS])

    def foot_specific_forces(self) -> np.ndarray:
        """:meth:`foot_specific_force` of FL, FR, RL, RR, (4, 3) m/s^2."""
        return np.stack([self.foot_specific_force(leg) for leg in MODEL_LEGS])

    def _floor_touches(self) -> tuple[np.ndarray, np.ndarray]:
        """(contact indices, the geom each touches the floor with) for the contacts between the
        floor and anything but a foot sphere."""
        self._sync()
        d = self.data
        if self._floor < 0 or d.ncon == 0:
            return np.zeros(0, dtype=int), np.zeros(0, dtype=int)
        geoms = d.contact.geom[:d.ncon]
        other = np.where(geoms[:, 0] == self._floor, geoms[:, 1],
                         np.where(geoms[:, 1] == self._floor, geoms[:, 0], -1))
        idx = np.flatnonzero((other >= 0) & ~np.isin(other, self._foot_geoms))
        return idx, other[idx]

    def body_contacts(self) -> list[str]:
        """Names of the bodies touching the floor with anything but a foot sphere (sorted,
        unique): non-empty means the robot fell or knelt."""
        _, other = self._floor_touches()
        bodies = {self.model.body(int(self.model.geom_bodyid[g])).name for g in other}
        return sorted(bodies)

    def calf_contact_reach(self) -> np.ndarray:
        """How far from its foot each calf touches the floor, (4,) m, legs FL, FR, RL, RR: the
        farthest point of contact between the floor and a calf geom other than the foot sphere,
        from that leg's foot centre (NaN: no such contact). The URDF's lower calf hull wraps
        the top of the foot, its vertices there 19-30 mm from the foot centre: a contact that
        far is the calf's lower end brushing the floor beside the foot, not its shank or knee
        (213 mm up)."""
        idx, other = self._floor_touches()
        d = self.data
        out = np.full(4, np.nan)
        for i, g in zip(idx, other, strict=True):
            legs = np.flatnonzero(self._calf_bodies == self.model.geom_bodyid[g])
            if legs.size:
                k = int(legs[0])
                r = float(np.linalg.norm(d.contact.pos[i] - d.site_xpos[self._foot_sites[k]]))
                out[k] = np.fmax(out[k], r)
        return out


class Go2BatchSim:
    """``n`` independent :class:`Go2Sim` sharing one compiled model, stepped by a thread pool.

    Each environment gets a deep copy of ``config.effects`` and seed ``config.seed + i``.
    Threads help because ``mj_forward`` / ``mj_Euler`` release the GIL; the per-step Python
    (PD law) does not, so expect well under linear scaling with small models.
    """

    def __init__(self, config: SimConfig, n: int, threads: int | None = None):
        if int(n) < 1:
            raise ValueError(f"n must be >= 1, got {n!r}")
        model = build_model_for(config)
        self.model = model
        self.envs: list[Go2Sim] = [
            Go2Sim(dataclasses.replace(config, seed=config.seed + i,
                                       effects=copy.deepcopy(config.effects)), model=model)
            for i in range(int(n))
        ]
        self._pool = ThreadPoolExecutor(max_workers=threads) if (threads or 0) > 1 else None

    def __len__(self) -> int:
        return len(self.envs)

    def step(self, n: int = 1) -> None:
        """Advance every environment ``n`` physics steps."""
        if self._pool is None:
            for e in self.envs:
                e.run(n)
        else:
            list(self._pool.map(lambda e: e.run(n), self.envs))

    def set_commands(self, q_des, dq_des, kp, kd, tau_ff) -> None:
        """Per-environment commands, each (n, 12) model order (or broadcastable)."""
        n = len(self.envs)
        arrs = [np.broadcast_to(np.asarray(x, dtype=float), (n, NUM_MOTORS))
                for x in (q_des, dq_des, kp, kd, tau_ff)]
        for i, e in enumerate(self.envs):
            e.set_command(*(a[i] for a in arrs))

    def close(self) -> None:
        if self._pool is not None:
            self._pool.shutdown()
            self._pool = None
