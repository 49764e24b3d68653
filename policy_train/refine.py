"""``a2i-train refine``: a linear residual on the body's rate and tilt, added to an exported
policy's actions while it lifts one leg, tuned by evolution strategies on the evaluation's
episodes with common random numbers.

Why not PPO: continued from these policies, PPO on 2 cores moves them off their level within
100-200 iterations (docs/policy-training.md). The residual has 72 numbers, so a gradient
estimate from a few antithetic pairs of whole calibration motions finds its direction; and
every candidate of a generation plays the same episodes (masses, friction, gains, latency,
pushes, observation noise: :class:`BlockRNG`), so the difference between a pair is the
residual's, not the draws'.

The residual, on the newest observation frame ``x`` (its scaled terms), while the lift
command is the refined leg's::

    a = actor(x) + D @ [omega_b * s_omega, g_b[x, y]] + b

``a`` is a change of the joint targets per policy step (``delta_target``), so ``D`` on the
body's rate adds an attitude term to the targets, ``D`` on the tilt an integral one, and
``b`` a steady drift the policy must meet. Legs whose lifts the graph mirrors onto the refined
leg's (``mirrored_legs``) get its mirror image. A refined policy's residuals of other lifts
stay in the graph, fixed (``refined_from.kept``): v41's rear lifts were refined over v32, whose
front lifts keep theirs.

With ``velocity`` the residual also reads the base's horizontal velocity ``v`` as the three
stance legs' kinematics give it (:func:`stance_velocity_map`: their joint angles differenced
over four policy steps, the feet taken as still on the floor; base frame, m/s). The policy
observes no base velocity, and after a shove the velocity, not the tilt, says where the
capture point went. ``v`` is linear in the observation's frames, so the graph holds it as one
more matrix::

    a = actor(x) + D @ [omega_b * s_omega, g_b[x, y], v[x, y]] + b
"""

from __future__ import annotations

import datetime
import json
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
import torch

from calib.atomic import write_bytes_atomic, write_text_atomic
from calib.joints import MODEL_LEGS, check_leg
from deploy.lift_schedule import LiftSchedule
from policy_train.env import LIFT_VALUES
from policy_train.rewards import tripod_feet
from sim.tripod_pose import capture_margins

__all__ = ["BlockRNG", "RefineConfig", "ResidualActor", "paired_rollouts", "refine",
           "refine_start", "residual_columns", "score", "stance_velocity_map"]

N_IN = 5  # body rate (3) and the gravity's x, y in the base frame (2)
N_VEL = 2  # with ``velocity``: the stance legs' base velocity x, y (m/s, base frame)
INPUTS = ["base_ang_vel x", "base_ang_vel y", "base_ang_vel z", "projected_gravity x",
          "projected_gravity y", "stance-leg base velocity x", "stance-leg base velocity y"]
"""The residual's inputs, in D's column order (the JSON's ``refined_from.inputs``)."""


@dataclass
class RefineConfig:
    """ES settings. leg: the lift whose residual is tuned (mirrored legs follow). pairs:
    antithetic pairs per generation; episodes: per leg and candidate; step: the update's
    length as a fraction of one perturbation's; sigma_rate, sigma_tilt, sigma_bias: the
    perturbations' scale of ``D``'s rate and tilt columns and of ``b`` (action units per
    observation unit; action units). fail_cost: the score's cost of a failed episode, rad/s
    per failed fraction of the episodes. seed: the directions and the episodes' draws
    (generation g plays evaluation seed ``seed + g``). dr: ``DRConfig`` fields set over the
    evaluation's standard ranges for the episodes played (``{"push_vel": 0.5}``: harder
    shoves, so that falls are frequent enough to have a gradient). margin_cost: the score's
    cost of the capture point's shortfall, rad/s per metre (0: not scored); margin_target: m,
    how far inside the stance feet's triangle the capture point should stay at its lowest in
    each episode (the shortfall: :func:`paired_rollouts`'s ``short``). tilt_cost: the score's
    cost of the body's tilt RMS over the excitation beyond ``tilt_target_deg``, rad/s per rad
    (0: not scored): a residual that keeps the capture point in by leaning the body pays for
    the lean (docs/policy-training.md, stop 55). velocity: the residual also reads the stance
    legs' base velocity (two more columns of ``D``, 96 parameters instead of 72);
    sigma_vel: their perturbation's scale, action units per m/s. clearance_cost: the score's
    cost of the stance calves' shortfall, rad/s per metre (0: not scored); clearance_target:
    m, how high over the floor the stance calves' lowest point should stay at its lowest in
    each episode's excitation (the shortfall: :func:`paired_rollouts`'s ``calf_short``): the
    residual that holds harder shoves crouches the stance legs, and a weak motor or a tilted
    floor then puts a calf on the floor (docs/policy-training.md, stop 58)."""

    leg: str = "FL"
    pairs: int = 4
    episodes: int = 24
    step: float = 0.3
    sigma_rate: float = 0.2
    sigma_tilt: float = 0.3
    sigma_bias: float = 0.005
    fail_cost: float = 0.1
    seed: int = 1000
    dr: dict = field(default_factory=dict)
    margin_cost: float = 0.0
    margin_target: float = 0.08
    tilt_cost: float = 0.0
    tilt_target_deg: float = 1.0
    velocity: bool = False
    sigma_vel: float = 0.1
    clearance_cost: float = 0.0
    clearance_target: float = 0.008

    @property
    def tilt_target(self) -> float:
        """rad: the tilt RMS the score lets pass unpriced."""
        return float(np.radians(self.tilt_target_deg))

    def __post_init__(self) -> None:
        from policy_train.config import DRConfig

        self.leg = check_leg(self.leg)
        DRConfig().with_settings(self.dr)  # ValueError on an unknown field
        if self.pairs < 1 or self.episodes < 1:
            raise ValueError(f"pairs and episodes must be >= 1, got {self.pairs}, {self.episodes}")
        if not isinstance(self.velocity, bool):
            # a bad state file's value, reported like the others (the CLI catches ValueError)
            raise ValueError(  # noqa: TRY004
                f"velocity must be true or false, got {self.velocity!r}")
        for k in ("step", "sigma_rate", "sigma_tilt", "sigma_bias", "sigma_vel", "fail_cost"):
            v = getattr(self, k)
            if not (np.isfinite(v) and v > 0):
                raise ValueError(f"{k} must be > 0, got {v}")
        for k in ("margin_cost", "margin_target", "tilt_cost", "tilt_target_deg",
                  "clearance_cost", "clearance_target"):
            v = getattr(self, k)
            if not (np.isfinite(v) and v >= 0):
                raise ValueError(f"{k} must be >= 0, got {v}")

    @property
    def n_inputs(self) -> int:
        """Columns of ``D``: 5, or 7 with ``velocity``."""
        return N_IN + N_VEL * self.velocity

    @property
    def scales(self) -> np.ndarray:
        """(72,) or (96,) the perturbation scale of each parameter (:func:`pack`'s order): D's
        rate columns, tilt columns, b, then with ``velocity`` D's velocity columns."""
        return np.r_[np.full(36, self.sigma_rate), np.full(24, self.sigma_tilt),
                     np.full(12, self.sigma_bias),
                     np.full(12 * N_VEL * self.velocity, self.sigma_vel)]


def unpack(params: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(72,) parameters -> D (12, 5) (rate x, y, z, then tilt x, y columns), b (12,); (96,)
    -> D (12, 7), its last two the velocity's x, y columns (stored after ``b``, so that a
    residual without them is the first 72)."""
    p = np.asarray(params, dtype=float)
    if p.shape not in ((72,), (96,)):
        raise ValueError(f"a residual has 72 parameters (96 with the velocity), got {p.shape}")
    D = np.concatenate([p[:36].reshape(12, 3), p[36:60].reshape(12, 2)]
                       + ([p[72:].reshape(12, N_VEL)] if p.size == 96 else []), 1)
    return D, p[60:72]


def pack(D, b, n_inputs: int | None = None) -> np.ndarray:
    """The inverse of :func:`unpack`: D (12, 5 or 7), b (12,) -> (72,) or (96,) parameters.
    ``n_inputs`` 7 widens a D of 5 columns with zero velocity columns (a refinement with the
    velocity going on from one without); 5 refuses a D of 7."""
    D, b = np.asarray(D, dtype=float), np.asarray(b, dtype=float)
    if D.ndim != 2 or D.shape[0] != 12 or D.shape[1] not in (N_IN, N_IN + N_VEL) \
            or b.shape != (12,):
        raise ValueError(f"a residual is D (12, {N_IN} or {N_IN + N_VEL}) and b (12,), got "
                         f"{D.shape}, {b.shape}")
    n = D.shape[1] if n_inputs is None else int(n_inputs)
    if n < D.shape[1]:
        raise ValueError("this residual reads the stance legs' velocity: refine it with "
                         "--velocity")
    D = np.pad(D, ((0, 0), (0, n - D.shape[1])))
    return np.r_[D[:, :3].ravel(), D[:, 3:5].ravel(), b, D[:, 5:].ravel()]


def _terms_at(obs_terms) -> tuple[dict[str, tuple[int, float, int]], int]:
    """({name: (first column, scale, size)} of one frame, the frame's size), from the JSON's
    ``observation.terms``."""
    at, size = {}, 0
    for t in obs_terms:
        at[t["name"]] = (size, float(np.ravel(t.get("scale", 1.0))[0]), int(t["size"]))
        size += int(t["size"])
    return at, size


def residual_columns(obs_terms) -> tuple[list[int], int, float]:
    """The newest frame's columns the residual reads (base_ang_vel, projected_gravity x, y),
    the lift command's column and its scale, from the JSON's ``observation.terms``."""
    at, _ = _terms_at(obs_terms)
    for name in ("base_ang_vel", "projected_gravity", "lift_command"):
        if name not in at:
            raise ValueError(f"the observation has no {name} term")
    w, g = at["base_ang_vel"][0], at["projected_gravity"][0]
    return [w, w + 1, w + 2, g, g + 1], at["lift_command"][0], at["lift_command"][1]


VEL_FRAMES = 4
"""Policy steps over which :func:`stance_velocity_map` differences the joint angles (0.08 s at
50 Hz): the observed joint rates carry +-1.5 rad/s of noise, the angles +-0.01 rad."""


def stance_velocity_map(obs_terms, default_pose, leg: str, n_obs: int,
                        dt: float) -> np.ndarray:
    """(2, n_obs): the base's velocity x, y (m/s, base frame) from an observation row (frames
    newest first), as the stance legs of a ``leg`` lift give it with their feet still on the
    floor: ``v = -mean_i [J_i (q_i(t) - q_i(t - k dt)) / (k dt) + omega x p_i]`` over the three
    other legs, ``J_i`` and ``p_i`` their feet's position Jacobian and position at
    ``default_pose`` (12, SDK order, rad), ``k`` = :data:`VEL_FRAMES`, ``omega`` the observed
    body rate averaged over the same frames. Linear in the row, so the graph holds it as one
    matrix. dt: s between frames (the policy step)."""
    from calib.joints import SDK_LEGS
    from calib.kinematics import LegKinematics

    at, size = _terms_at(obs_terms)
    for name, n in (("joint_pos", 12), ("base_ang_vel", 3)):
        if at.get(name, (0, 0, 0))[2] != n:
            raise ValueError(f"the observation has no {n} {name} columns")
    k = VEL_FRAMES
    if n_obs < (k + 1) * size or n_obs % size:
        raise ValueError(f"the stance legs' velocity needs {k + 1} frames of {size} "
                         f"observations, the row has {n_obs}")
    qc, qs, _ = at["joint_pos"]
    wc, ws, _ = at["base_ang_vel"]
    q0 = np.asarray(default_pose, dtype=float).reshape(4, 3)
    M = np.zeros((2, n_obs))
    h, feet = 1e-6, []
    for i, g in enumerate(SDK_LEGS):
        if g == check_leg(leg):
            continue
        kin = LegKinematics.from_urdf(leg=g)
        J = np.stack([(kin.foot_position(q0[i] + h * e) - kin.foot_position(q0[i] - h * e))
                      / (2 * h) for e in np.eye(3)], 1)  # (3, 3): d foot / d q
        c = qc + 3 * i
        M[:, c:c + 3] -= J[:2] / (3 * k * dt * qs)
        M[:, k * size + c:k * size + c + 3] += J[:2] / (3 * k * dt * qs)
        feet.append(kin.foot_position(q0[i]))
    # -(omega x p)_xy = -[omega_y p_z - omega_z p_y, omega_z p_x - omega_x p_z], p the feet's mean
    px, py, pz = np.mean(feet, 0)
    wx_wy_wz = np.array([[0.0, -pz, py], [pz, 0.0, -px]])
    for f in range(k):
        M[:, f * size + wc:f * size + wc + 3] += wx_wy_wz / (k * ws)
    return M


class ResidualActor(torch.nn.Module):
    """``mlp(x) + mask * (u @ D[group].T + b[group])``, ``u`` the newest frame's rate and
    tilt (``x[:, cols]``) and, with ``vel_map`` (2, n_obs), the stance legs' base velocity
    ``x @ vel_map.T``; mask: rows whose newest lift command is ``lift_value``
    (scaled). ``D`` (G, 12, 5 or 7) and ``b`` (G, 12) hold one residual per group; ``group``
    (rows,) picks each row's (None: group 0), so one batch can play several candidates.
    Exported with one group."""

    def __init__(self, mlp: torch.nn.Module, cols: list[int], lift_col: int, lift_value: float,
                 D: np.ndarray, b: np.ndarray, vel_map: np.ndarray | None = None):
        super().__init__()
        self.mlp = mlp
        self.register_buffer("cols", torch.tensor(cols, dtype=torch.long))
        self.register_buffer("vel_map", None if vel_map is None
                             else torch.tensor(vel_map, dtype=torch.float32))
        self.lift_col, self.lift_value = int(lift_col), float(lift_value)
        self.set_residual(D, b)
        self.group: torch.Tensor | None = None

    @property
    def n_inputs(self) -> int:
        return N_IN + (0 if self.vel_map is None else N_VEL)

    def set_residual(self, D: np.ndarray, b: np.ndarray) -> None:
        D, b = np.asarray(D, dtype=np.float32), np.asarray(b, dtype=np.float32)
        if D.ndim == 2:
            D, b = D[None], b[None]
        if D.shape[-1] != self.n_inputs:
            raise ValueError(f"this residual reads {self.n_inputs} inputs, D has {D.shape[-1]}")
        self.register_buffer("D", torch.from_numpy(D.copy()))
        self.register_buffer("b", torch.from_numpy(b.copy()))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        on = (torch.abs(x[:, self.lift_col] - self.lift_value) < 1e-3).to(x.dtype).unsqueeze(-1)
        u = x[:, self.cols]
        if self.vel_map is not None:
            u = torch.cat([u, x @ self.vel_map.T], 1)
        if self.group is None:
            r = u @ self.D[0].T + self.b[0]
        else:
            r = torch.einsum("noi,ni->no", self.D[self.group], u) + self.b[self.group]
        return self.mlp(x) + on * r


def _as_network_reads(key: str, value):
    """A JSON entry as far as its network is concerned: the action's ``target_lead_max`` is
    deploy's bound on the targets around the joints (``derive --target-lead``), set beside the
    network as its gains are, so a policy derived with it still names its network's action."""
    if key == "action" and isinstance(value, dict):
        return {k: v for k, v in value.items() if k != "target_lead_max"}
    return value


def build_actor(source_onnx: str | Path, leg: str, groups: int = 1,
                meta_json: str | Path | None = None, velocity: bool = False,
                kept: list[dict] = ()):
    """(meta, actor, residual): the source policy's MLP under a zero residual of ``groups``
    candidates for lifts of ``leg``, wrapped as the source's graph mirrors its legs. meta: the
    JSON ``meta_json`` (default: the source's), whose gains and lift schedule the rollouts play
    and the refined policy keeps: the policy the user named, when that is a derived or refined
    one whose network is ``source_onnx``. velocity: the residual also reads the stance legs'
    base velocity (:func:`stance_velocity_map`). kept: other lifts' residuals, fixed, under the
    one tuned (``refined_from`` records of :func:`refine_start`: their ``leg``, ``D``, ``b``)."""
    from rsl_rl.modules import MLP

    from policy_train.config import TrainConfig
    from policy_train.symmetry import MirroredLegsActor
    from policy_train.warm_start import policy_start

    start = policy_start(source_onnx)  # ValueError unless an exported (unrefined) policy
    meta = json.loads(Path(source_onnx).with_suffix(".json").read_text())
    if meta_json is not None:
        named = json.loads(Path(meta_json).read_text())
        for key in ("observation", "action", "joint_order", "mirrored_legs"):
            if _as_network_reads(key, named.get(key)) != _as_network_reads(key, meta.get(key)):
                raise ValueError(f"{Path(meta_json).name}'s {key} is not its network's "
                                 f"({Path(source_onnx).name})")
        meta = named
    cfg = TrainConfig.from_dict(meta["train_config"])
    n_in = int(meta["observation"]["size"])
    mlp = MLP(n_in, 12, _hidden(start), "elu")
    mlp.load_state_dict(start["actor_mlp"])
    terms = meta["observation"]["terms"]
    cols, lift_col, lift_scale = residual_columns(terms)

    def vel_map(g: str, on: bool):
        return (stance_velocity_map(terms, meta["default_pose"], g, n_in,
                                    float(meta["control_dt"])) if on else None)

    mirrored = meta.get("mirrored_legs") or {}
    if leg in mirrored:
        raise ValueError(f"{leg}'s lifts are the mirror of {mirrored[leg]}'s: refine "
                         f"{mirrored[leg]}")
    base = mlp
    for k in kept:  # each acts on its own lift command only, so their order does not matter
        D = np.asarray(k["D"], dtype=float)
        base = ResidualActor(base, cols, lift_col, LIFT_VALUES[k["leg"]] * lift_scale, D,
                             np.asarray(k["b"], dtype=float), vel_map(k["leg"], D.shape[1] > N_IN))
    res = ResidualActor(base, cols, lift_col, LIFT_VALUES[leg] * lift_scale,
                        np.zeros((groups, 12, N_IN + N_VEL * velocity)), np.zeros((groups, 12)),
                        vel_map(leg, velocity))
    actor = (MirroredLegsActor(res, terms, mirrored, cfg.env.obs_history) if mirrored
             else res).eval()
    return meta, actor, res


def _hidden(start: dict) -> list[int]:
    """Hidden widths from the MLP's weights (a distilled student may differ from PPO's)."""
    ws = [v for k, v in sorted(start["actor_mlp"].items(), key=lambda kv: int(kv[0].split(".")[0]))
          if k.endswith("weight")]
    return [int(w.shape[0]) for w in ws[:-1]]


_SIZE_AT = {"uniform": 2, "integers": 2, "random": 0, "choice": 1, "normal": 2}
"""Where each Generator method takes its ``size``, positionally."""


class BlockRNG:
    """A ``numpy.random.Generator`` for ``blocks`` equal blocks of envs laid out one after
    another: a draw whose first dimension is a multiple of ``blocks`` is drawn for one block
    and repeated, so every block sees the same randomness (a draw over all envs, or over the
    same envs of every block: resets, pushes, observation noise). Other draws pass through."""

    def __init__(self, rng: np.random.Generator, blocks: int):
        self.rng, self.blocks = rng, int(blocks)

    def __getattr__(self, name: str):
        f = getattr(self.rng, name)
        if name not in _SIZE_AT:
            return f
        at = _SIZE_AT[name]

        def draw(*args, **kw):
            args = list(args)
            size = kw.get("size", args[at] if len(args) > at else None)
            if size is None:
                return f(*args, **kw)
            shape = (int(size),) if np.isscalar(size) else tuple(size)
            if shape[0] == 0 or shape[0] % self.blocks:
                return f(*args, **kw)
            one = (shape[0] // self.blocks,) + shape[1:]
            if "size" in kw:
                kw["size"] = one
            else:
                args[at] = one
            return np.concatenate([f(*args, **kw)] * self.blocks, axis=0)

        return draw


def paired_rollouts(meta: dict, actor: torch.nn.Module, res: ResidualActor, candidates,
                    legs, episodes: int, seed: int, dr_set: dict | None = None,
                    margin_target: float = 0.08, clearance_target: float = 0.008) -> list[dict]:
    """Each candidate (D, b) over the same ``episodes`` per leg of ``legs`` (the evaluation's
    environment, :func:`policy_train.evaluate.evaluation_env`, with seed ``seed`` and
    ``dr_set``'s fields over its standard ranges), one batch. Per candidate and leg: ``rate``
    (rad/s RMS of the body rate in the excitation, failed episodes up to their fall, as the
    evaluation), ``tilt`` (rad RMS of the body's tilt from the vertical, over the same steps),
    ``fails`` (falls, other contacts, the lifted foot down), ``track`` (rad),
    ``cp_min`` (m: the median over the episodes of each one's lowest margin of the capture
    point inside the three stance feet over the lift and the excitation while it stood,
    :func:`sim.tripod_pose.capture_margins` of the whole robot's centre of mass, its velocity
    from its change over a policy step) and ``short`` (m: the mean over those episodes of how
    far that lowest margin falls short of ``margin_target``, at most twice that: where a
    fall starts, it is below 0); ``calf_min`` (m: the median over the episodes of each one's
    lowest stance-calf point over the floor in the excitation,
    :meth:`TripodEnv.stance_calf_clearance`, as the evaluation's ``calf_clearance_mm``) and
    ``calf_short`` (m: the mean over those episodes of how far it falls short of
    ``clearance_target``, at most twice that). A fallen env is reset with new draws; its push
    timer is kept with its twins' so the blocks' pushes stay common."""
    from policy_train.evaluate import evaluation_env

    C = len(candidates)
    env, leg_of = evaluation_env(meta, tuple(legs) * C, episodes, seed, dr_set=dr_set)
    env.rng = BlockRNG(np.random.default_rng(seed), C)  # redraw every env as blocks
    env._randomize_masses()
    env.reset_all()
    env.p_excite = 1.0
    env._sample_commands(np.arange(env.N), legs=leg_of)
    env.lift_plan[:] = leg_of
    env.lift_dur[:, 3] = env.pool.duration[leg_of]
    N, B = env.N, env.N // C
    res.set_residual(np.stack([c[0] for c in candidates]), np.stack([c[1] for c in candidates]))
    res.group = torch.as_tensor(np.repeat(np.arange(C), B))
    sched = LiftSchedule.from_metadata(meta["lift_schedule"])
    n_steps = int(np.ceil((max(float(sched.total(g)) for g in legs) + 0.5) / env.dt))
    alive = np.ones(N, dtype=bool)
    failed = np.zeros(N, dtype=bool)
    rate2, tilt2, err2, nexc = np.zeros(N), np.zeros(N), np.zeros(N), np.zeros(N)
    cp_min = np.full(N, np.inf)
    calf_min = np.full(N, np.inf)
    tm = env.tm
    com_prev = env.com_over_floor()
    obs = env.observations()["policy"]
    try:
        with torch.no_grad():
            for _ in range(n_steps):
                ob, _, _, extras = env.step(actor(torch.as_tensor(obs, dtype=torch.float32)).numpy())
                obs = ob["policy"]
                alive &= ~extras["terminated"]
                failed |= ~alive | ((env.other_touch | env.lift_touch) & alive)
                exc = alive & (env.phase == 3)
                rate2[exc] += np.sum(env.ang_vel_b[exc] ** 2, 1)
                tilt2[exc] += env.tilt[exc] ** 2
                err2[exc] += np.nanmean(env.lift_err[exc] ** 2, 1)
                nexc[exc] += 1
                if exc.any():
                    calf_min[exc] = np.minimum(calf_min[exc], env.stance_calf_clearance(exc))
                com = env.com_over_floor()
                up = alive & ((env.phase == 2) | (env.phase == 3)) & (env.lift_leg >= 0)
                if up.any():
                    feet = tripod_feet(env.sensordata[:, tm.foot_pos[:, None] + np.arange(3)][up],
                                       env.lift_leg[up])
                    _, m = capture_margins(com[up], (com[up, :2] - com_prev[up, :2]) / env.dt,
                                           feet)
                    cp_min[up] = np.minimum(cp_min[up], m)
                com_prev = com
                a, t = alive.reshape(C, B), env.push_timer.reshape(C, B)
                if not a.all():
                    twin = t[a.argmax(0), np.arange(B)]
                    t[:] = np.where(a, t, np.where(a.any(0), twin, np.inf))
    finally:
        res.group = None
    out = []
    for c in range(C):
        sl = slice(c * B, (c + 1) * B)
        row = {}
        for leg in legs:
            sel = leg_of[sl] == MODEL_LEGS.index(leg)
            ok = sel & (nexc[sl] > 0)
            n = nexc[sl][ok].sum()
            row[leg] = {"rate": float(np.sqrt(rate2[sl][ok].sum() / n)) if n else float("inf"),
                        "tilt": float(np.sqrt(tilt2[sl][ok].sum() / n)) if n else float("inf"),
                        "fails": int(failed[sl][sel].sum()),
                        "track": float(np.sqrt(err2[sl][ok].sum() / n)) if n else float("inf")}
            lows = cp_min[sl][sel & np.isfinite(cp_min[sl])]
            # a fall's margin runs far outside before it ends the episode; fail_cost prices it
            row[leg]["short"] = (float(np.mean(np.clip(margin_target - lows, 0.0,
                                                       2 * margin_target)))
                                 if lows.size else float("inf"))
            row[leg]["cp_min"] = float(np.median(lows)) if lows.size else float("nan")
            calf = calf_min[sl][sel & np.isfinite(calf_min[sl])]
            # a calf on the floor ends the episode's success; fail_cost prices that
            row[leg]["calf_short"] = (float(np.mean(np.clip(clearance_target - calf, 0.0,
                                                            2 * clearance_target)))
                                      if calf.size else float("inf"))
            row[leg]["calf_min"] = float(np.median(calf)) if calf.size else float("nan")
        out.append(row)
    return out


def score(row: dict, episodes: int, fail_cost: float, margin_cost: float = 0.0,
          tilt_cost: float = 0.0, tilt_target: float = 0.0,
          clearance_cost: float = 0.0) -> float:
    """Sum over the legs of the body-rate RMS (rad/s), ``fail_cost`` times the failed
    fraction, ``margin_cost`` times the capture point's shortfall (m), ``tilt_cost`` times
    the tilt RMS beyond ``tilt_target`` (rad) and ``clearance_cost`` times the stance calves'
    shortfall (m); a cost of 0 does not read its figure. Lower is better (inf where a leg
    never reached its excitation)."""
    return float(sum(v["rate"] + fail_cost * v["fails"] / episodes
                     + (margin_cost * v["short"] if margin_cost else 0.0)
                     + (tilt_cost * max(v["tilt"] - tilt_target, 0.0) if tilt_cost else 0.0)
                     + (clearance_cost * v["calf_short"] if clearance_cost else 0.0)
                     for v in row.values()))


@dataclass
class RefineState:
    """Where a refinement stands: the residual's parameters (:func:`pack`'s, 72 or 96) and one
    record per generation done."""

    params: list[float] = field(default_factory=lambda: [0.0] * 72)
    history: list[dict] = field(default_factory=list)


def refine_start(start_onnx: str | Path, leg: str, velocity: bool = False
                 ) -> tuple[Path, RefineState, dict | None, list[dict]]:
    """(network, state, continued, kept): where a refinement of ``start_onnx`` begins. A plain
    exported policy is the network, under a zero residual. A refined one (its JSON's
    ``refined_from``) goes on from its residual for ``leg`` over its source's network (the
    file of that name beside it), with its generations as the history, so that generation
    numbers and hence the seeds played go on; ``continued`` then records the policy continued,
    its generations and settings. Its residuals of other lifts stay in the graph as they are:
    ``kept``, their ``refined_from`` records (a refinement of the rear lifts of a policy
    refined on its front ones keeps the front lifts' residual). A lift it has no residual for
    starts from zero. velocity: the residual is to read the stance legs' velocity too (a
    refined residual without it goes on with those columns at zero; ValueError the other way
    round)."""
    start_onnx, leg = Path(start_onnx), check_leg(leg)
    rf = json.loads(start_onnx.with_suffix(".json").read_text()).get("refined_from")
    zero = RefineState([0.0] * (72 + 12 * N_VEL * velocity))
    if not rf:
        return start_onnx, zero, None, []
    network = start_onnx.with_name(rf["policy"])
    if not network.is_file():
        raise ValueError(f"{start_onnx.name} is refined from {rf['policy']}, which is not "
                         f"beside it")
    residuals = [{k: v for k, v in rf.items() if k != "kept"}, *rf.get("kept", [])]
    own = [r for r in residuals if r["leg"] == leg]
    kept = [r for r in residuals if r["leg"] != leg]
    if not own:
        return network, zero, None, kept
    r = own[0]
    state = RefineState(pack(r["D"], r["b"], N_IN + N_VEL * velocity).tolist(),
                        [dict(g) for g in r["generations"]])
    continued = {"policy": start_onnx.name, "generations": len(r["generations"]),
                 "config": r["config"], **({"continued_from": r["continued_from"]}
                                           if "continued_from" in r else {})}
    return network, state, continued, kept


def refine(source_onnx: str | Path, out_stem: str | Path, generations: int, cfg: RefineConfig,
           state_path: str | Path, resume: bool = False, log=print) -> tuple[Path, Path]:
    """Tune the residual for ``generations`` more generations from ``state_path`` (resume), or
    from where ``source_onnx`` leaves it (:func:`refine_start`: zero, or a refined policy's
    residual), saving the state after each; then write ``<out_stem>.onnx`` / ``.json``: the
    network with the residual in its graph, the JSON the network's with ``refined_from`` and
    no evaluation (run ``a2i-train eval``)."""
    state_path = Path(state_path)
    start = Path(source_onnx).name
    # its deploy settings (gains, lift schedule: a2i-train derive's) are played and kept, over
    # whichever network it is built on
    named_json = Path(source_onnx).with_suffix(".json")
    if resume:
        saved = json.loads(state_path.read_text())
        if saved.get("start", saved["source"]) != start:
            raise ValueError(f"{state_path} refines {saved.get('start', saved['source'])}, "
                             f"not {start}")
        cfg = RefineConfig(**saved["config"])
        source_onnx, _, continued, kept = refine_start(source_onnx, cfg.leg, cfg.velocity)
        state = RefineState(saved["params"], saved["history"])
    else:
        source_onnx, state, continued, kept = refine_start(source_onnx, cfg.leg, cfg.velocity)
    legs = _legs_of(source_onnx, cfg.leg)
    K = cfg.pairs
    meta, actor, res = build_actor(source_onnx, cfg.leg, 2 * K + 1, named_json, cfg.velocity,
                                   kept)
    theta = np.asarray(state.params, dtype=float) / cfg.scales  # in units of the perturbation
    dim = theta.size
    for _ in range(generations):
        gen = len(state.history)
        t0 = time.time()
        eps = np.random.default_rng([cfg.seed, gen]).normal(size=(K, dim))
        cands = [theta] + [theta + e for e in eps] + [theta - e for e in eps]
        rows = paired_rollouts(meta, actor, res, [unpack(c * cfg.scales) for c in cands], legs,
                               cfg.episodes, cfg.seed + gen, cfg.dr, cfg.margin_target,
                               cfg.clearance_target)
        J = np.array([score(r, cfg.episodes, cfg.fail_cost, cfg.margin_cost, cfg.tilt_cost,
                            cfg.tilt_target, cfg.clearance_cost) for r in rows])
        diff = np.nan_to_num(J[1:K + 1] - J[K + 1:], posinf=1.0, neginf=-1.0) / 2
        grad = diff @ eps / K
        norm = np.linalg.norm(grad)
        if norm > 0:
            theta = theta - cfg.step * np.sqrt(dim) * grad / norm
        rec = {"generation": gen, "seed": cfg.seed + gen, "score": float(J[0]),
               "score_best": float(J.min()), "score_mean": float(J[1:].mean()),
               "legs": rows[0], "wall_s": round(time.time() - t0, 1)}
        state.params = (theta * cfg.scales).tolist()
        state.history.append(rec)
        write_text_atomic(state_path, json.dumps(
            {"source": Path(source_onnx).name, "start": start, "config": asdict(cfg),
             **asdict(state)}, indent=1) + "\n")
        log(f"generation {gen}: score {J[0]:.4f} (candidates {J.min():.4f}-{J.max():.4f}); "
            + ", ".join(f"{g} {v['rate']:.3f} rad/s, tilt {np.degrees(v['tilt']):.2f} deg, "
                        f"{v['fails']} failed, capture point "
                        f"{100 * v['short']:.2f} cm short of {100 * cfg.margin_target:.0f} "
                        f"(lowest {100 * v['cp_min']:.1f} cm), stance calves "
                        f"{1e3 * v['calf_min']:.1f} mm up"
                        for g, v in rows[0].items())
            + f"; |residual| {np.linalg.norm(theta):.2f} sigma, {rec['wall_s']:.0f} s")
    return export_refined(source_onnx, out_stem, np.asarray(state.params), cfg, state.history,
                          continued, named_json, kept)


def _legs_of(source_onnx, leg: str) -> tuple[str, ...]:
    """The refined leg and the legs whose lifts mirror it: the lifts the residual acts on."""
    meta = json.loads(Path(source_onnx).with_suffix(".json").read_text())
    mirrored = meta.get("mirrored_legs") or {}
    return (leg, *sorted(g for g, src in mirrored.items() if src == leg))


def export_refined(source_onnx, out_stem, params: np.ndarray, cfg: RefineConfig,
                   history: list[dict], continued: dict | None = None,
                   meta_json: str | Path | None = None,
                   kept: list[dict] = ()) -> tuple[Path, Path]:
    """Write the refined policy: ONNX (checked against torch) and the JSON ``meta_json``
    (default: the source's; :func:`build_actor`) with
    ``refined_from`` (source, commit, leg, the residual, the settings, each generation's
    score and, for a continued refinement, ``continued_from``: the refined policy it went on
    from, its generations and settings; ``kept``: the other lifts' residuals in the graph, as
    their own records) and its evaluation cleared."""
    from deploy.policy import PolicyMeta
    from policy_train.export import git_commit, onnx_bytes
    from policy_train.stand import apply_stand

    meta, actor, res = build_actor(source_onnx, cfg.leg, 1, meta_json, cfg.velocity, kept)
    D, b = unpack(params)
    res.set_residual(D, b)
    # the JSON's stand is kept, so its graph gets it too (derive --stand)
    data = apply_stand(onnx_bytes(actor, int(meta["observation"]["size"])), meta)
    out_stem = Path(out_stem)
    name = out_stem.name.removesuffix(".onnx")
    src = Path(source_onnx)
    meta["refined_from"] = {
        "policy": src.name, "commit": meta.get("commit"), "leg": cfg.leg,
        "legs": list(_legs_of(source_onnx, cfg.leg)),
        "inputs": INPUTS[:D.shape[1]],
        "D": D.round(6).tolist(), "b": b.round(6).tolist(), "config": asdict(cfg),
        "generations": [{k: h[k] for k in ("generation", "seed", "score", "score_best",
                                           "score_mean")} for h in history],
        **({"continued_from": continued} if continued else {}),
        **({"kept": list(kept)} if kept else {})}
    meta.update(name=name, onnx=f"{name}.onnx", commit=git_commit(), evaluation={},
                created_utc=datetime.datetime.now(datetime.UTC).strftime("%Y-%m-%dT%H:%M:%SZ"))
    meta.pop("evaluation_nominal", None)
    onnx_path, json_path = out_stem.with_name(name + ".onnx"), out_stem.with_name(name + ".json")
    PolicyMeta.from_dict(meta, json_path)  # as deploy will read it: ValueError before writing
    onnx_path.parent.mkdir(parents=True, exist_ok=True)
    write_bytes_atomic(onnx_path, data)
    write_text_atomic(json_path, json.dumps(meta, indent=1) + "\n")
    return onnx_path, json_path
