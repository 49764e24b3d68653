"""Vectorised tripod environment: N Go2s in ``mujoco.batch.Batch``, numpy over N for the rest.

One policy step (50 Hz) = ``decimation`` physics steps (200 Hz) stepped in C on the batch's
thread pool (all CPUs by default). Per policy step:

1. actions (N, 12), **SDK order**, raw network outputs; ``target += scale * clip(a)``, held
   within ``target_lead_max`` of the joints if set, clamped to the soft limits
   (:mod:`deploy.action`, the on-board rule; ``docs/policy-format.md``, ``action``);
2. for each physics substep, the motor controls: the policy targets (after the randomised
   actuation latency, whole physics steps) and, for the lifted leg while
   :mod:`deploy.lift_schedule` gives targets, the schedule's trajectory with its own gains;
3. observations through :func:`deploy.observation.build_observation` (the on-board code), with
   observation noise; privileged critic observations (true base velocity, height, contacts,
   randomised parameters, schedule phase); rewards (:mod:`policy_train.rewards`); resets.

Joint vectors inside are model order (FL, FR, RL, RR); conversion at the policy boundary
through :mod:`calib.joints`.
"""

from __future__ import annotations

import os
import weakref
from concurrent.futures import ThreadPoolExecutor
from itertools import pairwise

import mujoco
import numpy as np
from mujoco.batch import Batch

from calib.excitation import ExcitationConfig, plan_excitation
from calib.joints import (
    EFFORT_LIMIT,
    MODEL_LEGS,
    default_crouch,
    model_to_sdk,
    sdk_to_model,
)
from deploy.action import next_target
from deploy.lift_schedule import PHASES, LiftSchedule, blend_accelerations, blend_targets
from deploy.observation import (
    OBS_SIZE,
    TERM_SIZES,
    ObservationHistory,
    build_observation,
    default_terms,
    observe_lifted_leg,
    projected_gravity,
)
from deploy.tracking_adapter import TrackingAdapter
from policy_train.config import OBS_NOISE, EnvConfig
from policy_train.model import TrainModel
from policy_train.rewards import compute_rewards
from sim.effects import FLOOR_SOLMIX, FrictionCone, check_floor_timeconst
from sim.tripod_pose import tripod_pose

__all__ = ["LIFT_VALUES", "OBS_NOISE", "PRIV_TERMS", "PlanPool", "TripodEnv", "noise_amplitude"]

LIFT_VALUES = {"none": 0, "FL": 1, "FR": 2, "RL": 3, "RR": 4}
"""Value of the ``lift_command`` observation per leg (paper: c_lift in {0, ..., 4})."""

_LEG_NAMES = np.array(MODEL_LEGS)  # model leg index -> name


def noise_amplitude(terms: list[dict], dr) -> np.ndarray:
    """(49,) half-width of the policy observation's uniform noise under ``dr`` (a
    ``DRConfig``), observation units: each term's scale times its signal's noise; 0 for
    noiseless or zero-filled terms, and everywhere when the randomisation is off."""
    noise = {name: getattr(dr, field) if dr.enabled else 0.0 for name, field in OBS_NOISE}
    return np.concatenate([
        np.zeros(TERM_SIZES[t["name"]]) if t.get("source", "measured") == "zero" else
        np.abs(np.broadcast_to(np.asarray(t.get("scale", 1.0), dtype=float),
                               TERM_SIZES[t["name"]])) * noise.get(t["name"], 0.0)
        for t in terms])


PRIV_TERMS: tuple[tuple[str, int], ...] = (
    ("lin_vel", 3), ("height", 1), ("foot_contact", 4), ("params", 4), ("phase", 6),
    ("phase_time", 1), ("state", 8), ("lift_error", 3))
"""Privileged critic terms after the policy observation, in order (:meth:`TripodEnv.observations`)."""
PRIV_SIZE = sum(n for _, n in PRIV_TERMS)


def _columns(idx: np.ndarray) -> slice | np.ndarray:
    """Column indices as a strided slice where they are evenly spaced (the contact sensors lie
    every 4 columns: a view of the batch's sensor rows, read after every physics step, instead
    of a copy), else the indices."""
    idx = np.asarray(idx, dtype=int)
    step = np.diff(idx) if len(idx) > 1 else np.ones(1, int)
    if len(idx) and step[0] > 0 and np.all(step == step[0]):
        return slice(int(idx[0]), int(idx[-1]) + 1, int(step[0]))
    return idx


def _quat_rotate_inv(q: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Rotate world vectors v (N, 3) into the frame of the unit quaternions q (N, 4) wxyz."""
    w, x, y, z = q[:, 0:1], q[:, 1:2], q[:, 2:3], q[:, 3:4]
    u = np.concatenate([x, y, z], 1)
    a = v * (2.0 * w**2 - 1.0)
    b = np.cross(u, v) * w * 2.0
    c = u * (np.sum(u * v, 1, keepdims=True) * 2.0)
    return a - b + c


class PlanPool:
    """Excitation plans of every leg tabulated at the physics rate (randomised t_r and seeds).

    q[k], dq[k]: (T, 3) of plan k (padded with its end pose / zero); length[k] samples;
    leg[k]: model leg index; duration[k] s.
    """

    def __init__(self, per_leg: int, t_r_range, n_basis: int, periods, dt: float,
                 rng: np.random.Generator,
                 ground_clearance: float = ExcitationConfig.ground_clearance):
        """periods: count per plan, or an inclusive (low, high) range drawn per plan."""
        lo, hi = (periods, periods) if np.isscalar(periods) else periods
        qs, dqs, self.leg, self.duration, self.t_r = [], [], [], [], []
        for li, leg in enumerate(MODEL_LEGS):
            for _ in range(per_leg):
                t_r = float(rng.uniform(*t_r_range))
                k = int(lo) if lo == hi else int(rng.integers(lo, hi + 1))
                plan = plan_excitation(ExcitationConfig(
                    leg=leg, t_r=t_r, n_basis=n_basis, periods=k,
                    seed=int(rng.integers(1 << 30)), ground_clearance=ground_clearance))
                t = np.arange(int(np.ceil(plan.duration / dt)) + 1) * dt
                qs.append(plan.positions(t))
                dqs.append(plan.velocities(t))
                self.leg.append(li)
                self.duration.append(plan.duration)
                self.t_r.append(t_r)
        n = max(len(q) for q in qs)
        self.length = np.array([len(q) for q in qs])
        self.q = np.stack([np.concatenate([q, np.repeat(q[-1:], n - len(q), 0)]) for q in qs])
        self.dq = np.stack([np.concatenate([d, np.zeros((n - len(d), 3))]) for d in dqs])
        self.leg = np.array(self.leg)
        self.duration = np.array(self.duration)
        self.q0 = self.q[:, 0].copy()
        self.dt = dt

    @classmethod
    def from_plans(cls, plans: list, dt: float) -> PlanPool:
        """A pool of given :class:`calib.excitation.ExcitationPlan` objects (evaluation)."""
        p = cls.__new__(cls)
        qs, dqs = [], []
        for plan in plans:
            t = np.arange(int(np.ceil(plan.duration / dt)) + 1) * dt
            qs.append(plan.positions(t))
            dqs.append(plan.velocities(t))
        n = max(len(q) for q in qs)
        p.length = np.array([len(q) for q in qs])
        p.q = np.stack([np.concatenate([q, np.repeat(q[-1:], n - len(q), 0)]) for q in qs])
        p.dq = np.stack([np.concatenate([d, np.zeros((n - len(d), 3))]) for d in dqs])
        p.leg = np.array([MODEL_LEGS.index(plan.leg) for plan in plans])
        p.duration = np.array([plan.duration for plan in plans])
        p.t_r = [plan.config.t_r for plan in plans]
        p.q0 = p.q[:, 0].copy()
        p.dt = dt
        return p

    def save(self, path) -> None:
        np.savez(path, q=self.q, dq=self.dq, leg=self.leg, duration=self.duration,
                 length=self.length, t_r=np.asarray(self.t_r), dt=self.dt)

    @classmethod
    def load(cls, path) -> PlanPool:
        z = np.load(path)
        p = cls.__new__(cls)
        p.q, p.dq, p.leg, p.duration = z["q"], z["dq"], z["leg"], z["duration"]
        p.length, p.t_r, p.dt = z["length"], list(z["t_r"]), float(z["dt"])
        p.q0 = p.q[:, 0].copy()
        return p

    def of_leg(self, li: int) -> np.ndarray:
        return np.flatnonzero(self.leg == li)

    def sample(self, k: np.ndarray, te: np.ndarray, accelerations: bool = False):
        """Plan k (N,) at te (N,) s from its start: (q (N, 3), dq (N, 3)), with
        ``accelerations`` also ddq (N, 3), rad/s^2 (:meth:`sample_acceleration`)."""
        i = np.clip(np.rint(te / self.dt).astype(int), 0, self.length[k] - 1)
        inside = ((te >= 0) & (te <= self.duration[k]))[:, None]
        q, dq = self.q[k, i], np.where(inside, self.dq[k, i], 0.0)
        return (q, dq, np.where(inside, self._accelerations()[k, i], 0.0)) if accelerations \
            else (q, dq)

    def sample_acceleration(self, k: np.ndarray, te: np.ndarray) -> np.ndarray:
        """Plan k (N,) at te (N,) s: ddq (N, 3), rad/s^2 (central differences of the tabulated
        rates, which pools saved before it also give)."""
        return self.sample(k, te, accelerations=True)[2]

    def _accelerations(self) -> np.ndarray:
        if not hasattr(self, "_ddq"):
            self._ddq = np.gradient(self.dq, self.dt, axis=1)
        return self._ddq


class TripodEnv:
    """The tripod calibration-action environment (rsl-rl ``VecEnv`` protocol in numpy;
    :class:`policy_train.runner.TorchVecEnv` wraps it for torch)."""

    def __init__(self, cfg: EnvConfig | None = None, plan_pool: PlanPool | None = None,
                 train_model: TrainModel | None = None):
        self.cfg = cfg = cfg if cfg is not None else EnvConfig()
        if cfg.num_envs < 1:
            raise ValueError("num_envs must be >= 1")
        self.rng = np.random.default_rng(cfg.seed)
        # (12,) model order, N m/rad and N m s/rad; step() writes every environment's gains
        # before each physics step, so the compiled model's only need to be plausible
        self._kp, self._kd = (np.broadcast_to(np.asarray(g, dtype=float), (12,)).copy()
                              for g in (cfg.kp, cfg.kd))
        if np.any(self._kp <= 0) or np.any(self._kd < 0):
            raise ValueError("kp must be > 0 and kd >= 0")
        self.tm = train_model if train_model is not None else TrainModel(
            cfg.physics_dt, float(self._kp.mean()), float(self._kd.mean()),
            model_file=cfg.model_file)
        m = self.tm.model
        self.N = N = cfg.num_envs
        if cfg.obs_history < 1:
            raise ValueError("obs_history must be >= 1")
        self.num_envs, self.num_actions, self.num_obs = N, 12, OBS_SIZE * cfg.obs_history
        # the policy's frames, newest first; None for the paper's single frame
        self.obs_hist = ObservationHistory(cfg.obs_history, OBS_SIZE, (N,)) \
            if cfg.obs_history > 1 else None
        self.dt = cfg.physics_dt * cfg.decimation
        self.max_episode_length = round(cfg.episode_s / self.dt)
        self.resample_steps = round(cfg.command_resample_s / self.dt)
        self.batch = Batch(m, N, nthread=cfg.threads)
        if cfg.blocks < 0:
            raise ValueError(f"blocks must be >= 0 (0: automatic), not {cfg.blocks}")
        # a training run's blocks may reach an evaluation of fewer envs: at most one env each
        blocks = min(cfg.blocks, N) if cfg.blocks else (
            2 if N >= 2 and (cfg.threads or os.cpu_count() or 1) >= 4 else 1)
        # (rows, ids for Batch.step) per block; one block steps on this thread
        edges = np.linspace(0, N, blocks + 1).round().astype(int)
        self._blocks = [(slice(lo, hi), None if blocks == 1 else np.arange(lo, hi))
                        for lo, hi in pairwise(edges)]
        self._physics = None
        if blocks > 1:
            self._physics = ThreadPoolExecutor(1, thread_name_prefix="tripod-physics")
            weakref.finalize(self, self._physics.shutdown, wait=False)
        b = self.batch
        self.qpos, self.qvel, self.ctrl = b.bind("qpos"), b.bind("qvel"), b.bind("ctrl")
        self.sensordata, self.act_force = b.bind("sensordata"), b.bind("actuator_force")
        self.subtree_com = b.bind("subtree_com")  # (N, nbody, 3); the base's = whole robot's
        self.gainprm, self.biasprm = b.expand("actuator_gainprm"), b.expand("actuator_biasprm")
        # per env: a motor of strength s delivers s times the clamped PD torque, so its peak
        # is s times the effort limit (never above it), as sim.effects.MotorStrength on the
        # mock's simulator. Scaling the gains alone left a weak motor the full peak: the
        # refinement then favoured policies whose rear hips saturate under weak motors there
        # (docs/policy-training.md, "Stop 59")
        self.forcerange = b.expand("actuator_forcerange")
        self._effort = np.tile(np.asarray(EFFORT_LIMIT, dtype=float), len(MODEL_LEGS))
        self.default_pose = default_crouch("model")
        self.soft_lo, self.soft_hi = cfg.soft_limits(MODEL_LEGS)
        self._lead_max = None if cfg.target_lead_max is None else np.asarray(
            cfg.target_lead_max, dtype=float)
        if self._lead_max is not None and (self._lead_max.shape != (12,)
                                           or not np.all(self._lead_max > 0)):
            raise ValueError("target_lead_max must be 12 positive numbers (model order), got "
                             f"{cfg.target_lead_max}")
        self.obs_terms = default_terms(model_to_sdk(self.default_pose), "zero")
        if cfg.leg_dynamics_file:
            LiftSchedule.load_dynamics_pack(cfg.leg_dynamics_file)
        if plan_pool is None and cfg.plan_pool_file:
            plan_pool = PlanPool.load(cfg.plan_pool_file)
        self.pool = plan_pool if plan_pool is not None else PlanPool(
            cfg.plans_per_leg, cfg.t_r_range, cfg.n_basis, cfg.train_periods, cfg.physics_dt,
            np.random.default_rng(cfg.seed + 1), cfg.ground_clearance)
        # start height: feet on the floor at the default pose
        d = mujoco.MjData(m)
        d.qpos[3] = 1.0
        d.qpos[7:19] = self.default_pose
        mujoco.mj_kinematics(m, d)
        foot_sites = [m.site(f"{leg}_foot").id for leg in MODEL_LEGS]
        self.start_height = 0.022 - d.site_xpos[foot_sites, 2].min() + 0.005

        self._masses_nominal = m.body_mass.copy()
        self._inertia_nominal = m.body_inertia.copy()
        self._ipos_nominal = m.body_ipos.copy()
        self._fric = b.expand("geom_friction")
        self._joint_fric = b.expand("dof_frictionloss")
        self._g = float(np.linalg.norm(m.opt.gravity))
        self._gravity = None  # opt.gravity per env, expanded at the first tilted floor drawn
        # the floor's solref per env, expanded at the first floor that gives drawn: until then
        # every env has the model's own contact, and configurations without it keep their physics
        self._floor_geom = m.geom("floor").id
        self._floor_solref = None
        # opt.cone / opt.impratio per env, expanded at the first episode drawn on MuJoCo's
        # default cone (DRConfig.default_cone); the model's own until then
        self._cone = None
        self._cone_own = (int(m.opt.cone), float(m.opt.impratio))
        # the contact sensors' columns in sensordata, read after every physics step
        tm = self.tm
        self._foot_cols, self._base_cols = _columns(tm.foot_contact), _columns(tm.base_contact)
        self._other_cols = tuple(_columns(tm.other_contact + k) for k in (1, 2, 3))  # world f
        self._feet_geoms = np.array([m.geom(f"{leg}_foot").id for leg in MODEL_LEGS] + [m.geom("floor").id])
        # level tripod stances in static equilibrium, one per lifted leg (reference starts)
        self.ref_poses = [tripod_pose(
            m, li, self.default_pose, self.pool.q0[self.pool.of_leg(li)[0]],
            cfg.rewards.base_height_target, cfg.reference_margin_m, self._kp, cfg.lift_kp)
            for li in range(4)] if cfg.p_reference_start > 0 else []
        self.shift_poses = [tripod_pose(
            m, li, self.default_pose, self.pool.q0[self.pool.of_leg(li)[0]],
            cfg.rewards.base_height_target, cfg.reference_margin_m, self._kp, cfg.lift_kp,
            lifted=False) for li in range(4)] if self.ref_poses else []
        w = np.asarray(cfg.lift_leg_weights, dtype=float)
        if w.shape != (4,) or np.any(w < 0) or w.sum() <= 0:
            raise ValueError("lift_leg_weights must be 4 non-negative weights, not all zero")
        self.leg_p = w / w.sum()
        self._init_buffers()
        self._randomize_masses()
        self.reset_all()

    def get_observations(self) -> dict[str, np.ndarray]:
        return self.observations()

    # ------------------------------------------------------------------ buffers
    def _init_buffers(self) -> None:
        N = self.N
        z = np.zeros
        self.target = z((N, 12))
        # the motor commands (ctrl, kp, kd) of the last physics steps, a ring whose newest slot
        # is ``_hist_new``: a motor runs on the one issued ``latency`` steps ago. The whole
        # command is delayed, the lifted leg's schedule too, as deploy's LowCmd frames are (the
        # schedule once bypassed it). A ring, not a shift: moving the whole buffer each physics
        # step was 0.55 ms of every substep at 2 048 envs. Resets fill every slot alike
        cfg = self.cfg
        depth = cfg.dr.latency_steps[1] + 1 if cfg.dr.enabled else 1
        self.cmd_hist = z((N, depth, 3, 12))
        self._gains = z((N, 2, 12))  # the (kp, kd) the batch's actuators have (_set_gains)
        self._hist_new = 0
        self.actions = z((N, 12))          # raw, SDK order
        self.prev_actions = z((N, 12))
        self.last_qvel = z((N, 12))
        self.commands = z((N, 3))
        self.lift_leg = np.full(N, -1)     # model leg index, -1 none
        self.lift_t = z(N)                 # s since the lift command
        self.lift_q_start = z((N, 3))
        self.lift_plan = np.zeros(N, dtype=int)
        self.lift_excite = np.zeros(N, dtype=bool)
        self.lift_latched = np.zeros(N, dtype=bool)
        self.lift_dur = z((N, 5))
        # the lifted leg's tracking adapter (cfg.lift_adapt), one row per env, and the torque it
        # added in the physics step just played (what the motors held at the next measurement)
        self.adapter = TrackingAdapter(cfg.lift_kp, cfg.lift_kd, N) if cfg.lift_adapt else None
        self.lift_applied = z((N, 3))
        self.phase = np.zeros(N, dtype=int)
        self.episode_length_buf = np.zeros(N, dtype=int)
        self.push_timer = z(N)
        self.kp_s, self.kd_s, self.strength = np.ones(N), np.ones(N), np.ones(N)
        self.latency = np.zeros(N, dtype=int)
        self.noise_scale = np.ones(N)      # times the observation noise (DRConfig.noise_scale)
        self.friction = np.ones(N)
        # unit vector of gravity in the world (the floor is z = 0): straight down unless the
        # floor is drawn tilted (DRConfig.floor_tilt_deg)
        self.down = np.tile([0.0, 0.0, -1.0], (N, 1))
        self.mass_add = z(N)
        self.foot_touch = np.zeros((N, 4), dtype=bool)
        self.other_touch = np.zeros(N, dtype=bool)
        # which non-foot geoms (train_model.collision_geoms) pressed on the floor in the step
        self.geom_touch = np.zeros((N, len(self.tm.collision_geoms)), dtype=bool)
        self.base_touch = np.zeros(N, dtype=bool)
        self.lift_q_des = np.full((N, 3), np.nan)
        self.episode_sums: dict[str, np.ndarray] = {}
        self.p_excite = self.cfg.p_excite
        # (N, 49) clean frames at the moment each env's newest action reaches its motors, kept
        # by step() once set to an array (distillation's actuation labels); None: not kept
        self.actuation_frames: np.ndarray | None = None

    def _randomize_masses(self) -> None:
        dr = self.cfg.dr
        if not dr.enabled:
            return
        mass = self.batch.expand("body_mass")
        ipos = self.batch.expand("body_ipos")
        base = self.tm.base_body
        N = self.N
        scale = self.rng.uniform(*dr.link_mass_scale, size=(N, mass.shape[1]))
        mass[:] = self._masses_nominal * scale
        self.mass_add = self.rng.uniform(*dr.base_mass_add, size=N)
        mass[:, base] = self._masses_nominal[base] + self.mass_add
        # a body drawn heavier or lighter keeps its density: its rotational inertia scales
        # with its mass (a base 2 kg heavier is not 2 kg more at one point of no size)
        nominal = self._masses_nominal
        ratio = np.divide(mass, nominal, out=np.ones_like(mass), where=nominal > 0)
        self.batch.expand("body_inertia")[:] = self._inertia_nominal * ratio[:, :, None]
        off = np.asarray(dr.base_com_offset)
        ipos[:, base] = self._ipos_nominal[base] + self.rng.uniform(-off, off, size=(N, 3))
        arm = self.batch.expand("dof_armature")
        arm[:, 6:] = self.rng.uniform(*dr.armature, size=(N, 1))
        self.batch.set_const()

    def set_calf_upper_margin(self, margin: float | None) -> None:
        """Move the clamp of the calves' targets to ``margin`` rad inside their extension
        limit (< 0: beyond it; None: ``soft_limit_margin``) from the next step on; targets
        already past it are pulled back by the next step's clamp."""
        self.cfg.calf_upper_margin = None if margin is None else float(margin)
        self.soft_lo, self.soft_hi = self.cfg.soft_limits(MODEL_LEGS)

    # ------------------------------------------------------------------ reset
    def reset_all(self) -> None:
        self.reset_idx(np.arange(self.N))
        self._compute_state()

    def torque_peak(self, strength: np.ndarray) -> np.ndarray:
        """(n, 12) the most torque each motor delivers, N m, model order, for motor
        strengths ``strength`` (n,): ``min(s, 1)`` times the effort limits (the PD law is
        clamped to them, then scaled; the current limit still caps a strong motor)."""
        return np.minimum(np.asarray(strength, dtype=float), 1.0)[:, None] * self._effort

    def reset_idx(self, ids: np.ndarray) -> None:
        if len(ids) == 0:
            return
        dr, n, rng = self.cfg.dr, len(ids), self.rng
        if self.obs_hist is not None:  # a new episode's first frame fills its history
            self.obs_hist.reset(ids)
        self.batch.reset(ids, stage=mujoco.mjtStage.mjSTAGE_NONE)
        q = self.default_pose + (rng.uniform(-1, 1, (n, 12)) * dr.init_joint_noise
                                 if dr.enabled else 0.0)
        q = np.clip(q, self.soft_lo, self.soft_hi)
        yaw = rng.uniform(-np.pi, np.pi, n)
        qp = self.qpos
        qp[ids, 0:2] = 0.0
        qp[ids, 2] = self.start_height
        qp[ids, 3] = np.cos(yaw / 2)
        qp[ids, 4:6] = 0.0
        qp[ids, 6] = np.sin(yaw / 2)
        qp[ids, 7:19] = q
        self.qvel[ids] = 0.0
        self.ctrl[ids] = q
        self.target[ids] = q
        self.actions[ids] = 0.0
        self.prev_actions[ids] = 0.0
        self.last_qvel[ids] = 0.0
        self.episode_length_buf[ids] = 0
        if dr.enabled:
            self.kp_s[ids] = rng.uniform(*dr.kp_scale, n)
            self.kd_s[ids] = rng.uniform(*dr.kd_scale, n)
            self.strength[ids] = rng.uniform(*dr.motor_strength, n)
            self.latency[ids] = rng.integers(dr.latency_steps[0], dr.latency_steps[1] + 1, n)
            self.friction[ids] = rng.uniform(*dr.friction, n)
            self.push_timer[ids] = rng.uniform(*dr.push_interval, n)
            if dr.joint_friction[1] > 0:  # drawn only when on: older configs keep their draws
                self._joint_fric[ids, 6:] = rng.uniform(*dr.joint_friction, (n, 12))
            if tuple(dr.noise_scale) != (1.0, 1.0):  # likewise
                self.noise_scale[ids] = rng.uniform(*dr.noise_scale, n)
            if dr.floor_tilt_deg[1] > 0:  # likewise
                a = np.radians(rng.uniform(*dr.floor_tilt_deg, n))
                az = rng.uniform(-np.pi, np.pi, n)
                self.down[ids] = np.stack([np.sin(a) * np.cos(az), np.sin(a) * np.sin(az),
                                           -np.cos(a)], 1)
                if self._gravity is None:
                    self._gravity = self.batch.expand("opt.gravity")
                self._gravity[ids] = self._g * self.down[ids]
            if dr.floor_timeconst[1] > 0:  # likewise
                check_floor_timeconst(dr.floor_timeconst[0], self.cfg.physics_dt)
                if self._floor_solref is None:  # as sim.effects.FloorSoftness sets the model's
                    self._floor_solref = self.batch.expand("geom_solref")
                    self.batch.expand("geom_solmix")[:, self._floor_geom] = FLOOR_SOLMIX
                self._floor_solref[ids, self._floor_geom, 0] = rng.uniform(*dr.floor_timeconst, n)
            if dr.default_cone > 0:  # likewise
                if not dr.default_cone <= 1:
                    raise ValueError(f"default_cone is a fraction of the episodes, in [0, 1], "
                                     f"got {dr.default_cone}")
                if self._cone is None:
                    self._cone = (self.batch.expand("opt.cone"), self.batch.expand("opt.impratio"))
                on = rng.random(n) < dr.default_cone
                mj = FrictionCone()  # MuJoCo's default contacts, as the transfer check sets them
                self._cone[0][ids] = np.where(on, mj.mjt_cone, self._cone_own[0])
                self._cone[1][ids] = np.where(on, mj.impratio, self._cone_own[1])
        else:
            self.kp_s[ids] = self.kd_s[ids] = self.strength[ids] = 1.0
            self.latency[ids] = 0
            self.friction[ids] = 0.8
            self.push_timer[ids] = np.inf
        self._fric[np.ix_(ids, self._feet_geoms, [0])] = self.friction[ids, None, None]
        # before the reset the motors held the reset pose with the env's own gains
        self.cmd_hist[ids, :, 0] = np.broadcast_to(q, (n, 12))[:, None]
        self.cmd_hist[ids, :, 1] = self._kp * (self.kp_s[ids] * self.strength[ids])[:, None, None]
        self.cmd_hist[ids, :, 2] = self._kd * (self.kd_s[ids] * self.strength[ids])[:, None, None]
        self.forcerange[ids] = self.torque_peak(self.strength[ids])[:, :, None] * [-1.0, 1.0]
        self._set_gains(ids, self.cmd_hist[ids, 0, 1:])
        self._sample_commands(ids)
        if self.ref_poses:
            ref = rng.random(n) < self.cfg.p_reference_start
            self._reference_start(ids[ref], yaw[ref])
        self.batch.forward(ids)
        for v in self.episode_sums.values():
            v[ids] = 0.0

    def _reference_start(self, ids: np.ndarray, yaw: np.ndarray) -> None:
        """Put ``ids`` (just reset on four legs) into a reference state of a leg drawn with
        ``lift_leg_weights``, rotated by ``yaw`` rad: the level tripod (:attr:`ref_poses`)
        part-way through the schedule's hold phase, or (``p_reference_shift``) part-way
        through the shift phase, between the four-leg stance and :attr:`shift_poses` (the
        body over the other three feet, the leg still down). The lift command and its plan
        are drawn as for any lift; the leg is lowered back to the four-leg stance it was
        reset to (hold) or to where it stood when the shift ended (shift)."""
        if len(ids) == 0:
            return
        rng, n = self.rng, len(ids)
        legs = rng.choice(4, n, p=self.leg_p)
        self._sample_commands(ids, legs=legs)
        qp = np.stack([self.ref_poses[li].qpos for li in legs])
        tg = np.stack([self.ref_poses[li].target for li in legs])
        sh = rng.random(n) < self.cfg.p_reference_shift
        alpha = rng.uniform(0.0, 1.0, n)[:, None]
        # from the noise-free four-leg stance with the feet on the floor (the reset's joint
        # noise would put interpolated feet up to a centimetre into or above the floor)
        q4 = np.zeros((n, 19))
        q4[:, 2], q4[:, 3], q4[:, 7:19] = self.start_height - 0.005, 1.0, self.default_pose
        sq = np.stack([self.shift_poses[li].qpos for li in legs])
        stg = np.stack([self.shift_poses[li].target for li in legs])
        qp[sh] = (1 - alpha[sh]) * q4[sh] + alpha[sh] * sq[sh]
        qp[sh, 3:7] = (1.0, 0.0, 0.0, 0.0)
        tg[sh] = (1 - alpha[sh]) * q4[sh, 7:19] + alpha[sh] * stg[sh]
        c, s = np.cos(yaw), np.sin(yaw)
        x, y = qp[:, 0].copy(), qp[:, 1].copy()
        qp[:, 0], qp[:, 1] = c * x - s * y, s * x + c * y
        qp[:, 3], qp[:, 4:6], qp[:, 6] = np.cos(yaw / 2), 0.0, np.sin(yaw / 2)
        qp[:, 7:19] += rng.uniform(-1, 1, (n, 12)) * self.cfg.reference_joint_noise
        qp[:, 2] += 0.003  # the joint noise moves the feet a few mm: start them above the floor
        self.qpos[ids] = qp
        self.qvel[ids] = 0.0
        self.target[ids] = tg
        self.ctrl[ids] = tg
        self.cmd_hist[ids, :, 0] = tg[:, None]
        # in the hold the lifted leg was on the schedule's gains (tg holds it there statically)
        hold, lj = ids[~sh][:, None], 3 * legs[~sh][:, None] + np.arange(3)
        st, sd = (self.strength[hold] * g[hold] for g in (self.kp_s, self.kd_s))
        self.cmd_hist[hold, :, 1, lj] = (self.cfg.lift_kp * st)[:, :, None]
        self.cmd_hist[hold, :, 2, lj] = (self.cfg.lift_kd * sd)[:, :, None]
        d = self.lift_dur[ids]
        self.lift_t[ids] = np.where(sh, alpha[:, 0] * d[:, 0],
                                    d[:, 0] + d[:, 1] + rng.uniform(0.0, 1.0, n) * d[:, 2])
        self.lift_latched[ids] = ~sh
        self.phase[ids] = np.where(sh, 0, 2)

    def _sample_commands(self, ids: np.ndarray, legs: np.ndarray | None = None) -> None:
        """New lift / angular-velocity command for ``ids`` (legs: forced leg indices)."""
        cfg, rng, n = self.cfg, self.rng, len(ids)
        if legs is None:
            legs = rng.choice(4, n, p=self.leg_p)
            legs[rng.random(n) < cfg.p_no_lift] = -1
        # a leg already lifted must come down first: keep schedules running past the resample
        self.lift_leg[ids] = legs
        self.lift_t[ids] = 0.0
        self.commands[ids] = 0.0
        yaw = (legs < 0) & (rng.random(n) < cfg.p_yaw_command)
        self.commands[ids[yaw], 2] = rng.uniform(-cfg.yaw_command, cfg.yaw_command, yaw.sum())
        lifted = legs >= 0
        li = ids[lifted]
        if len(li):
            plans = np.array([rng.choice(self.pool.of_leg(int(g))) for g in legs[lifted]])
            self.lift_plan[li] = plans
            exc = rng.random(len(li)) < self.p_excite
            self.lift_excite[li] = exc
            hold = rng.uniform(*cfg.hold_range, len(li))
            d = np.empty((len(li), 5))
            shift = np.array([(cfg.shift_by_leg or {}).get(g, cfg.shift_s) for g in MODEL_LEGS])
            d[:, 0], d[:, 2], d[:, 4] = shift[legs[lifted]], cfg.hold_s, cfg.lower_s
            d[:, 1] = cfg.lift_s
            d[:, 3] = np.where(exc, self.pool.duration[plans], hold)
            self.lift_dur[li] = d
            self.lift_q_start[li] = self.qpos[li[:, None], 7 + 3 * legs[lifted][:, None] + np.arange(3)]
            self.lift_latched[li] = False
            self.lift_applied[li] = 0.0
            if self.adapter is not None:
                self.adapter.reset(li)
        self.phase[ids] = np.where(lifted, 0, 5)

    # ------------------------------------------------------------------ lifted leg
    def _plan(self, act: np.ndarray, t: np.ndarray, accelerations: bool = False):
        """(q_des, dq_des (n, 3), phase (n,)) of the lifted legs of envs ``act`` at their lift
        times ``t`` (s): the schedule's plan, nothing latched or measured; with
        ``accelerations`` also ddq_des (n, 3), rad/s^2, and the time into the excitation te
        (n,), s."""
        d = self.lift_dur[act]
        k = self.lift_plan[act]
        te = t - d[:, :3].sum(1)
        q_exc, dq_exc, *ddq_exc = self.pool.sample(k, te, accelerations)
        q0 = self.pool.q0[k]
        hold = ~self.lift_excite[act][:, None]
        q_exc = np.where(hold, q0, q_exc)
        dq_exc = np.where(hold, 0.0, dq_exc)
        q_start = self.lift_q_start[act]
        out = blend_targets(t, d, q_start, q0, q_exc, dq_exc)
        if not accelerations:
            return out
        ddq_exc = np.where(hold, 0.0, ddq_exc[0])
        return (*out, blend_accelerations(t, d, q_start, q0, ddq_exc), te)

    def _lift_targets(self, t: np.ndarray, tick: bool = False, rows: slice = slice(None)):
        """(ids, joint idx (n, 3), q_des, dq_des, tau (n, 3) N m or None, phase) of the envs of
        ``rows`` whose lifted leg is overridden, at their lift times ``t`` (N,), s; tau is the
        feed-forward torque (``cfg.lift_feedforward``, plus the tracking adapter's with
        ``cfg.lift_adapt``). tick: the policy step's first physics step, where the adapter
        measures the leg (as deploy does once a tick)."""
        act = np.arange(self.N)[rows][self.lift_leg[rows] >= 0]
        if len(act) == 0:
            return act, None, None, None, None, np.zeros(0, int)
        d = self.lift_dur[act]
        # latch the leg's joints when the shift phase ends (deploy.lift_schedule's q_start)
        latch = act[(t[act] >= d[:, 0]) & ~self.lift_latched[act]]
        if len(latch):
            jl = 7 + 3 * self.lift_leg[latch][:, None] + np.arange(3)
            self.lift_q_start[latch] = self.qpos[latch[:, None], jl]
            self.lift_latched[latch] = True
        need_ddq = self.cfg.lift_feedforward or self.adapter is not None
        t_cmd = t[act]
        if self.adapter is not None:
            # the plan commanded ahead by the delay the adapter found, so that it is played on
            # time (the adapter's clock stays the excitation's own)
            te = t_cmd - d[:, :3].sum(1)
            t_cmd = t_cmd + self.adapter.lead(te, rows=act)
        qd, dqd, ph, *ddq_te = self._plan(act, t_cmd, accelerations=need_ddq)
        ddq = ddq_te[0] if ddq_te else None
        jidx = 3 * self.lift_leg[act][:, None] + np.arange(3)
        tau = None
        if self.cfg.lift_feedforward:
            on = (ph >= 1) & (ph <= 4)
            tau = np.zeros((len(act), 3))
            if on.any():  # every leg in one pass: per leg, the calls cost more than the sums
                tau[on] = LiftSchedule.feedforward_torque(
                    _LEG_NAMES[self.lift_leg[act[on]]], qd[on], dqd[on], ddq[on],
                    self.gravity_b[act[on]])
        if self.adapter is not None:
            tau = self._adapt(act, jidx, te, qd, dqd, ddq, tau, ph, tick)
        return act, jidx, qd, dqd, tau, ph

    def _adapt(self, act, jidx, te, qd, dqd, ddq, model, ph, tick: bool) -> np.ndarray:
        """The feed-forward ``model`` (None: none) of the envs ``act`` plus the tracking
        adapter's torque in excite and lower, clipped to the motors' limits; at a ``tick`` the
        excitation's envs first give the adapter their measurement (deploy's
        ``Session._adapt``)."""
        model = np.zeros((len(act), 3)) if model is None else model
        if tick:
            m = ph == PHASES.index("excite")
            if m.any():
                a, j = act[m][:, None], jidx[m]
                self.adapter.observe(te[m], qd[m], dqd[m], ddq[m], self.qpos[a, 7 + j],
                                     self.qvel[a, 6 + j], model[m], self.lift_applied[act[m]],
                                     rows=act[m], tau_motor=self.act_force[a, j])
        on = (ph == PHASES.index("excite")) | (ph == PHASES.index("lower"))
        c = np.zeros((len(act), 3))
        if on.any():
            c[on] = self.adapter.torque(te[on], dqd[on], ddq[on], model[on], rows=act[on])
        self.lift_applied[act] = c
        return np.clip(model + c, -EFFORT_LIMIT, EFFORT_LIMIT)

    # ------------------------------------------------------------------ step
    def step(self, actions_sdk: np.ndarray):
        cfg = self.cfg
        a = np.asarray(actions_sdk, dtype=float).reshape(self.N, 12)
        self.prev_actions[:] = self.actions
        self.actions[:] = a
        a_m = sdk_to_model(np.clip(a, -cfg.action_clip, cfg.action_clip))
        self.target[:] = next_target(self.target, cfg.action_scale * a_m, self.soft_lo,
                                     self.soft_hi, self.qpos[:, 7:19], self._lead_max)
        kp = self._kp * (self.kp_s * self.strength)[:, None]
        kd = self._kd * (self.kd_s * self.strength)[:, None]
        self.foot_touch[:] = False
        self.geom_touch[:] = False
        self.base_touch[:] = False
        self.lift_touch = np.zeros(self.N, dtype=bool)
        self.lift_err = np.full((self.N, 3), np.nan)
        last = []
        # each block's commands are computed while the previous block's physics runs (MuJoCo
        # releases the GIL); a block's next substep waits for its own physics and contacts
        inflight = None
        depth = self.cmd_hist.shape[1]
        for s in range(cfg.decimation):
            t = self.lift_t + s * cfg.physics_dt
            self._hist_new = (self._hist_new - 1) % depth  # this substep's slot, every block's
            for rows, ids in self._blocks:
                if inflight is not None and inflight[0] is rows:
                    self._contacts(self._finish(inflight))
                    inflight = None
                self._command(rows, s, t, kp, kd, last)
                done = self._finish(inflight)
                inflight = (rows, ids, self._launch(ids))
                if done is not None:
                    self._contacts(done)
        self._contacts(self._finish(inflight))
        # lifted-leg tracking error after the last substep, against the plan at that instant
        # (the target of the substep's start led it by a physics step: 90 % of the figure)
        self.lift_q_des[:] = np.nan
        if last:
            ai, ji = (np.concatenate(x) for x in zip(*last))
            qd_last = self._plan(ai, self.lift_t[ai] + cfg.decimation * cfg.physics_dt)[0]
            self.lift_err[ai] = self.qpos[ai[:, None], 7 + ji] - qd_last
            self.lift_q_des[ai] = qd_last
        self.lift_t += self.dt
        self.other_touch[:] = self.geom_touch.any(1)
        self.episode_length_buf += 1
        # pushes
        if cfg.dr.enabled:
            self.push_timer -= self.dt
            p = np.flatnonzero(self.push_timer <= 0)
            if len(p):
                self.qvel[p, 0:2] += self.rng.uniform(-cfg.dr.push_vel, cfg.dr.push_vel, (len(p), 2))
                self.push_timer[p] = self.rng.uniform(*cfg.dr.push_interval, len(p))
        if self.actuation_frames is not None:
            self._capture_actuation_frames(cfg.decimation)
        self._compute_state()
        rew, terms, terminated = compute_rewards(self)
        self.last_qvel[:] = self.qvel[:, 6:18]
        for k, v in terms.items():
            self.episode_sums.setdefault(k, np.zeros(self.N))
            self.episode_sums[k] += v
        time_out = self.episode_length_buf >= self.max_episode_length
        dones = terminated | time_out
        extras = {"time_outs": time_out.copy(), "terminated": terminated.copy()}
        ids = np.flatnonzero(dones)
        if len(ids):
            extras["episode"] = {k: v[ids].copy() for k, v in self.episode_sums.items()}
            extras["episode_length"] = self.episode_length_buf[ids].copy()
            self.reset_idx(ids)
            self._compute_state()
        res = np.flatnonzero((self.episode_length_buf % self.resample_steps == 0)
                             & (self.episode_length_buf > 0) & (self.lift_leg < 0))
        if len(res):
            self._sample_commands(res)
        # a leg still lifted at the resample time finishes its schedule; it gets no new command
        return self.observations(), rew, dones, extras

    def _command(self, rows: slice, s: int, t: np.ndarray, kp: np.ndarray, kd: np.ndarray,
                 last: list) -> None:
        """Substep ``s`` of the envs of ``rows``: the policy's targets with the lifted legs'
        schedule over them, through the actuation-latency buffer into the batch's controls and
        gains (t (N,) s since each lift command, kp / kd (N, 12) the drawn gains). At the last
        substep the lifted legs' (envs, joint idx) go to ``last``."""
        cfg = self.cfg
        lo = rows.start
        if self.actuation_frames is not None:
            self._capture_actuation_frames(s, rows)
        # the command issued now; the motors get the one issued `latency` steps ago
        ctrl = self.target[rows].copy()
        kp_s, kd_s = kp[rows].copy(), kd[rows].copy()
        act, jidx, qd, dqd, tau, ph = self._lift_targets(t, tick=s == 0, rows=rows)
        if len(act):
            self.phase[act] = ph
            on = (ph >= 1) & (ph <= 4)
            ai, ji = act[on], jidx[on]
            if len(ai):
                r = (ai - lo)[:, None]
                st = self.strength[ai, None] * self.kp_s[ai, None]
                kl, dl = cfg.lift_kp * st, cfg.lift_kd * self.kd_s[ai, None] * self.strength[ai, None]
                kp_s[r, ji] = kl
                kd_s[r, ji] = dl
                # kp (ctrl - q) - kd dq with the drawn gains: kl (qd - q) + dl (dqd - dq)
                ctrl[r, ji] = qd[on] + (dl / kl) * dqd[on]
                if tau is not None:
                    # the actuator is kp (ctrl - q) - kd dq: tau enters through ctrl,
                    # scaled by the motor strength as the PD law is
                    ctrl[r, ji] += tau[on] / (cfg.lift_kp * self.kp_s[ai, None])
                if s == cfg.decimation - 1:
                    last.append((ai, ji))
            done = ph == 5
            if np.any(done):  # schedule over: back to the policy, lift command cleared
                # as deploy, the policy's target restarts where the leg is before anything
                # is commanded (its actions during the lift moved a target nobody used)
                ad, jd = act[done][:, None], jidx[done]
                self.lift_leg[act[done]] = -1
                self.target[ad, jd] = self.qpos[ad, 7 + jd]
                ctrl[ad - lo, jd] = self.target[ad, jd]
        w = self._hist_new
        new = self.cmd_hist[rows, w]
        new[:, 0], new[:, 1], new[:, 2] = ctrl, kp_s, kd_s
        lag = (w + self.latency[rows]) % self.cmd_hist.shape[1]
        applied = self.cmd_hist[rows][np.arange(len(ctrl)), lag]
        self.ctrl[rows] = applied[:, 0]
        # the gains change only where a lifted leg's schedule switches them (through the
        # latency): those rows are written, not all (each env's gain is a cache line of the
        # batch's model, and rewriting them all was a sixth of the commands' time)
        gains = applied[:, 1:]
        changed = np.flatnonzero((gains != self._gains[rows]).any(axis=(1, 2)))
        if len(changed):
            self._set_gains(lo + changed, gains[changed])

    def _set_gains(self, ids: np.ndarray, gains: np.ndarray) -> None:
        """The actuators' PD gains of the envs ``ids``: gains (n, 2, 12) kp N m/rad, kd
        N m s/rad (MuJoCo's position actuator: kp (ctrl - q) - kd dq)."""
        self._gains[ids] = gains
        self.gainprm[ids, :, 0] = gains[:, 0]
        self.biasprm[ids, :, 1] = -gains[:, 0]
        self.biasprm[ids, :, 2] = -gains[:, 1]

    def _launch(self, ids: np.ndarray | None):
        """One physics step of the envs ``ids`` (None: all, here and now); with row blocks,
        on the physics thread: its future."""
        if self._physics is None:
            self.batch.step(nstep=1)
            return None
        return self._physics.submit(self.batch.step, ids, 1)

    def _finish(self, inflight) -> slice | None:
        """Wait for an in-flight physics step (None: nothing in flight); its rows."""
        if inflight is None:
            return None
        rows, _, future = inflight
        if future is not None:
            future.result()
        return rows

    def _contacts(self, rows: slice) -> None:
        """Accumulate the contacts of the physics step the envs of ``rows`` just took."""
        sd = self.sensordata[rows]
        fc = sd[:, self._foot_cols] > 0
        self.foot_touch[rows] |= fc
        fx, fy, fz = (sd[:, c] for c in self._other_cols)
        self.geom_touch[rows] |= fx * fx + fy * fy + fz * fz > 1.0  # |f| > 1 N
        self.base_touch[rows] |= np.any(sd[:, self._base_cols] > 0, axis=1)
        ll, phase = self.lift_leg[rows], self.phase[rows]
        held = (ll >= 0) & ((phase == 2) | (phase == 3))
        self.lift_touch[rows] |= held & fc[np.arange(len(ll)), np.maximum(ll, 0)]

    # ------------------------------------------------------------------ observations
    def _compute_state(self) -> None:
        qp, qv = self.qpos, self.qvel
        self.quat = qp[:, 3:7]
        self.base_pos = qp[:, 0:3]
        self.com_xy = self.com_over_floor()[:, :2]  # world m
        self.lin_vel_b = _quat_rotate_inv(self.quat, qv[:, 0:3])
        self.ang_vel_b = qv[:, 3:6].copy()
        self.gravity_b = self._gravity_in_base(self.quat, slice(None))
        # rad from the vertical: what falls end on, and the evaluation's and refine's tilt
        self.tilt = np.arccos(np.clip(-self.gravity_b[:, 2], -1.0, 1.0))
        self.q = qp[:, 7:19]
        self.dq = qv[:, 6:18]

    def _gravity_in_base(self, quat: np.ndarray, ids) -> np.ndarray:
        """(n, 3) unit gravity in the base frames of the envs ``ids`` at orientations ``quat``
        (n, 4) wxyz. On a level floor deploy's own function, digit for digit, so that the
        committed evaluations keep their figures."""
        if self._gravity is None:
            return projected_gravity(quat)
        return _quat_rotate_inv(quat, self.down[ids])

    def com_over_floor(self) -> np.ndarray:
        """(N, 3) world m: the whole robot's centre of mass with x, y moved to where gravity
        carries it onto the floor (z = 0); a tilted floor (``DRConfig.floor_tilt_deg``, trained
        as turned gravity) moves it downhill by its height times the tilt's tangent."""
        com = self.subtree_com[:, self.tm.base_body].copy()
        com[:, :2] += com[:, 2:3] * self.down[:, :2] / -self.down[:, 2:3]
        return com

    def stance_calf_clearance(self, ids) -> np.ndarray:
        """(n,) m: how high the lowest point of the stance calves' collision hulls is over the
        floor, for the envs ``ids`` (a mask or indices): the legs but the lifted one (all four
        while none is). Measured along the floor's normal, world z, which a tilted floor
        (turned gravity) leaves where it is (:meth:`TrainModel.calf_low_z`)."""
        foot_z = self.sensordata[ids][:, self.tm.foot_pos + 2]
        low = self.tm.calf_low_z(projected_gravity(self.quat[ids]), self.q[ids], foot_z)
        lifted = self.lift_leg[ids]
        up = np.flatnonzero(lifted >= 0)
        low[up, lifted[up]] = np.inf
        return low.min(1)

    def lift_command_value(self) -> np.ndarray:
        return np.where(self.lift_leg >= 0, self.lift_leg + 1, 0).astype(float)

    def signals(self, noise: bool = True, policy: bool = True) -> dict[str, np.ndarray]:
        """The robot signals deploy would see (SDK order), with observation noise if enabled;
        policy: the lifted leg as the policy is shown it (``cfg.excitation_seen``), else as
        measured (the critic's)."""
        dr = self.cfg.dr
        s = {"base_ang_vel": self.ang_vel_b, "projected_gravity": self.gravity_b,
             "joint_pos": self.q, "joint_vel": self.dq}  # joints in model order here
        if noise and dr.enabled:
            k = self.noise_scale[:, None]
            s = {name: s[name] + self.rng.uniform(-1, 1, s[name].shape) * getattr(dr, field) * k
                 for name, field in OBS_NOISE}
        if policy and self.cfg.excitation_seen != 1.0:
            s = self._observe_excitation(s)
        return self._signals(self.lin_vel_b, s, self.actions, np.arange(self.N))

    def _observe_excitation(self, s: dict) -> dict:
        """Model-order signals ``s`` with each exciting env's lifted leg observed at
        ``cfg.excitation_seen`` of its excursion from its plan's ``q0``, as deploy shows it to
        the policy under a schedule's ``excitation_seen``
        (:func:`deploy.observation.observe_lifted_leg`)."""
        rows = np.flatnonzero((self.phase == PHASES.index("excite")) & (self.lift_leg >= 0))
        if not len(rows):
            return s
        cols = 3 * self.lift_leg[rows, None] + np.arange(3)
        seen = observe_lifted_leg({k: s[k][rows] for k in ("joint_pos", "joint_vel")}, cols,
                                  self.pool.q0[self.lift_plan[rows]], self.cfg.excitation_seen)
        out = dict(s)
        for k in ("joint_pos", "joint_vel"):
            out[k] = np.array(s[k], dtype=float)
            out[k][rows] = seen[k]
        return out

    def _signals(self, lin_vel_b, s: dict, previous_actions, ids) -> dict[str, np.ndarray]:
        """Deploy's signal names and SDK order from model-order joint signals ``s`` of envs
        ``ids``."""
        return {
            "base_lin_vel": lin_vel_b,
            "base_ang_vel": s["base_ang_vel"],
            "projected_gravity": s["projected_gravity"],
            "joint_pos": model_to_sdk(s["joint_pos"]),
            "joint_vel": model_to_sdk(s["joint_vel"]),
            "previous_actions": previous_actions,
            "commands": self.commands[ids],
            "lift_command": self.lift_command_value()[ids],
        }

    def clean_frame(self, ids: np.ndarray, previous_actions: np.ndarray) -> np.ndarray:
        """(len(ids), 49) noise-free policy frame of the physics state as it is now, which
        may be part-way through a policy step (:meth:`step` fills ``actuation_frames`` so)."""
        qp, qv = self.qpos[ids], self.qvel[ids]
        s = {"base_ang_vel": qv[:, 3:6], "projected_gravity": self._gravity_in_base(qp[:, 3:7], ids),
             "joint_pos": qp[:, 7:19], "joint_vel": qv[:, 6:18]}
        sig = self._signals(_quat_rotate_inv(qp[:, 3:7], qv[:, 0:3]), s, previous_actions, ids)
        return build_observation(self.obs_terms, sig, clip=self.cfg.obs_clip)

    def _capture_actuation_frames(self, s: int, rows: slice = slice(None)) -> None:
        """Clean frames of the envs of ``rows`` whose new target reaches the motors at substep
        ``s`` (their actuation latency; ``s == decimation``: at the step's end, where latencies
        past one policy step are taken too), seen with the previous action as the last one
        issued."""
        last = s == self.cfg.decimation
        lat = self.latency[rows]
        ids = np.arange(self.N)[rows][lat >= s if last else lat == s]
        if len(ids):
            self.actuation_frames[ids] = self.clean_frame(ids, self.prev_actions[ids])

    def observation_noise_amplitude(self) -> np.ndarray:
        """(49,) half-width of this env's policy-observation noise (:func:`noise_amplitude`)."""
        return noise_amplitude(self.obs_terms, self.cfg.dr)

    def observations(self) -> dict[str, np.ndarray]:
        """{"policy": (N, 49 * obs_history) float32, "critic": (N, 49 + PRIV_SIZE) float32}.

        The critic sees the newest frame without noise, the lifted leg as measured. With
        ``obs_history`` > 1 each call pushes a frame into the policy's history: call it once
        per step (``step`` does)."""
        pol = build_observation(self.obs_terms, self.signals(True), clip=self.cfg.obs_clip)
        if self.obs_hist is not None:
            pol = self.obs_hist.push(pol)
        clean = build_observation(self.obs_terms, self.signals(False, policy=False),
                                  clip=self.cfg.obs_clip)
        cfg = self.cfg
        tph = np.where(self.lift_leg >= 0, self.lift_t - np.concatenate(
            [np.zeros((self.N, 1)), np.cumsum(self.lift_dur, 1)], 1)[
                np.arange(self.N), np.minimum(self.phase, 5)], 0.0)
        priv = np.concatenate([
            2.0 * self.lin_vel_b,
            (self.base_pos[:, 2:3] - cfg.rewards.base_height_target) * 10.0,
            self.foot_touch.astype(float),
            np.stack([self.friction, self.kp_s, self.strength, self.mass_add / 2.0], 1),
            np.eye(6)[np.clip(self.phase, 0, 5)],
            np.clip(tph, 0, 20)[:, None] * 0.2,
            np.stack([self.latency / 4.0, self.kd_s, self.lift_excite.astype(float),
                      self.other_touch.astype(float), self.base_touch.astype(float),
                      np.minimum(self.push_timer, 10) / 10.0, self.lift_t / 20.0,
                      self.lift_touch.astype(float) if hasattr(self, "lift_touch")
                      else np.zeros(self.N)], 1),
            np.nan_to_num(getattr(self, "lift_err", np.zeros((self.N, 3))), nan=0.0) * 5.0,
        ], 1)
        return {"policy": pol, "critic": np.concatenate([clean, priv.astype(np.float32)], 1)}

    def phase_names(self) -> list[str]:
        return [PHASES[p] for p in self.phase]
