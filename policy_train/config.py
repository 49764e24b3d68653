"""Configuration of the tripod environment, its rewards, domain randomisation and PPO.

Everything is plain dataclasses so that the whole configuration can be written into the policy
JSON (``train_config``). Units SI; ranges are (low, high) drawn uniformly. Design decisions are
explained in ``docs/policy-training.md``.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field, replace

import numpy as np

from calib.excitation import ExcitationConfig
from calib.joints import position_limits

__all__ = ["DR_GROUPS", "DRConfig", "EnvConfig", "PPOConfig", "RewardConfig", "TrainConfig"]


@dataclass
class RewardConfig:
    """Weights (paper Table III), each multiplied by the policy period (legged_gym convention).

    Error forms follow legged_gym, whose defaults these weights are: squared errors for the
    normalised terms, ``exp(-|err|^2 / sigma)`` for tracking. ``base_height_target`` m.
    """

    lift: float = 1.0             # b_lift in {-1, +1}: lifted foot in the air / touching
    track_ang_vel: float = 2.0    # exp(-|w* - w|^2 / sigma)
    track_sigma: float = 0.25
    slip: float = -0.1            # sum over stance feet in contact of |v_foot_xy|
    termination: float = -2500.0  # base touches the ground (or the body falls); paper -100
    collision: float = -5.0       # count of non-foot geoms touching the ground (> 1 N); paper -1
    base_height: float = -30.0    # (h - h*)^2; v1 -10 let it crouch to 0.24 m
    base_height_target: float = 0.31
    orientation: float = -20.0    # |g_xy|^2 (projected gravity); paper -1
    lin_vel: float = -1.0         # |v_B|^2
    joint_acc: float = -2.5e-7    # sum ddq^2
    torques: float = -1e-5        # sum tau^2
    action_rate: float = -0.01    # sum (a_t - a_{t-1})^2
    # not in the paper (v2, docs/policy-training.md): a level, still base and a clean tripod
    upright: float = 2.0          # exp(-|g_xy|^2 / upright_sigma)
    upright_sigma: float = 0.005  # |g_xy|^2 = 0.005 at 4.1 deg
    ang_vel_xy: float = -2.0      # |w_xy|^2, roll/pitch rate
    lift_clearance: float = -10.0 # shortfall of the lifted foot below lift_clearance_m, in [0, 1]
    lift_clearance_m: float = 0.04
    support: float = -20.0        # m the COM lies short of support_margin_m inside the triangle
    support_margin_m: float = 0.03

    def with_settings(self, settings: dict) -> RewardConfig:
        """A copy with the named weights set (``a2i-train tripod --reward``). ValueError on an
        unknown name."""
        unknown = [k for k in settings if k not in self.__dataclass_fields__]
        if unknown:
            raise ValueError(f"unknown reward term(s) {', '.join(map(repr, unknown))}")
        bad = [k for k, v in settings.items() if k.endswith("_sigma") and not float(v) > 0]
        if bad:  # the exp(-err^2 / sigma) terms
            raise ValueError(f"{', '.join(bad)} must be > 0")
        return replace(self, **{k: float(v) for k, v in settings.items()})

    @classmethod
    def paper(cls) -> RewardConfig:
        """Paper Table III only (v1): the terms added for v2 switched off."""
        return cls(termination=-100.0, collision=-1.0, orientation=-1.0, upright=0.0,
                   ang_vel_xy=0.0, lift_clearance=0.0, support=0.0)


@dataclass
class DRConfig:
    """Domain randomisation; drawn per environment (masses once, the rest per episode)."""

    enabled: bool = True
    base_mass_add: tuple[float, float] = (-1.0, 2.0)        # kg added to the base
    link_mass_scale: tuple[float, float] = (0.9, 1.1)       # other links' masses
    base_com_offset: tuple[float, float, float] = (0.03, 0.02, 0.02)  # +- m (x, y, z)
    # joint armature (rotor inertia through the gearbox), kg m^2; nominal 0.01. v5 balanced in
    # the training model but fell in sim.go2 (no armature) when this was fixed at 0.01
    armature: tuple[float, float] = (0.0, 0.02)
    friction: tuple[float, float] = (0.4, 1.25)             # floor and feet sliding friction
    kp_scale: tuple[float, float] = (0.85, 1.15)
    kd_scale: tuple[float, float] = (0.8, 1.2)
    motor_strength: tuple[float, float] = (0.9, 1.1)        # scales the motor torque law
    latency_steps: tuple[int, int] = (0, 4)                 # physics steps (x 5 ms): 0-20 ms
    # dry (Coulomb) friction of each leg joint, N m, drawn per joint and episode. Off in v7's
    # training (v7 did better with it on sim.go2 than without: docs/results/policy_transfer*.md)
    joint_friction: tuple[float, float] = (0.0, 0.0)
    push_interval: tuple[float, float] = (4.0, 8.0)         # s between pushes
    push_vel: float = 0.3                                   # m/s added to base vx, vy (+-)
    init_joint_noise: float = 0.1                           # rad added to the start pose
    noise_ang_vel: float = 0.2                              # rad/s, uniform +-
    noise_gravity: float = 0.05
    noise_joint_pos: float = 0.01                           # rad
    noise_joint_vel: float = 1.5                            # rad/s
    # every noise amplitude above times this, drawn per episode (drawn only when the range is
    # not (1, 1), so that configurations without it keep their draws): a distilled student
    # also sees quiet sensors (docs/policy-training.md, v8)
    noise_scale: tuple[float, float] = (1.0, 1.0)
    # deg: the floor's tilt, drawn per episode, downhill any way; trained as gravity turned
    # away from the floor's normal by as much (the same physics on an infinite plane). Drawn
    # only when on: configurations without it keep their draws (the transfer check's `slope`)
    floor_tilt_deg: tuple[float, float] = (0.0, 0.0)
    # s: a floor that gives, its contacts' solref time constant drawn per episode (MuJoCo's
    # default, 0.02, is the hard floor: standing feet sink 2 mm; 0.03-0.045 sink 4-11 mm, the
    # transfer check's `soft_floor`). At least two physics steps, or MuJoCo stiffens it
    # silently. Drawn only when on, like the tilt
    floor_timeconst: tuple[float, float] = (0.0, 0.0)
    # the fraction of episodes whose contacts run on MuJoCo's default friction cone (pyramidal,
    # impratio 1), as a plain URDF or MJCF load and unitree_rl_gym's model do, instead of the
    # model's elliptic one with impratio 100 (the transfer check's `default_cone`). Drawn only
    # when on, like the tilt
    default_cone: float = 0.0

    def with_settings(self, settings: dict) -> DRConfig:
        """A copy with the named fields set (``a2i-train tripod / distill / eval --dr``; lists,
        as JSON stores ranges, become tuples). ValueError on an unknown field."""
        unknown = [k for k in settings if k not in self.__dataclass_fields__ or k == "enabled"]
        if unknown:
            raise ValueError(f"unknown randomisation field(s) {', '.join(map(repr, unknown))}")
        return replace(self, **{k: tuple(v) if isinstance(v, list) else v
                                for k, v in settings.items()})

    def without(self, *groups: str) -> DRConfig:
        """A copy with the named groups of ``DR_GROUPS`` at their nominal values."""
        unknown = [g for g in groups if g not in DR_GROUPS]
        if unknown:
            raise ValueError(f"unknown randomisation group(s) {', '.join(unknown)}; "
                             f"known: {', '.join(DR_GROUPS)}")
        out = replace(self)
        for g in groups:
            for k, v in DR_GROUPS[g].items():
                setattr(out, k, v)
        return out


OBS_NOISE: tuple[tuple[str, str], ...] = (
    ("base_ang_vel", "noise_ang_vel"), ("projected_gravity", "noise_gravity"),
    ("joint_pos", "noise_joint_pos"), ("joint_vel", "noise_joint_vel"))
"""Observation term -> the ``DRConfig`` field of its uniform noise half-width (the term's
signal units), in the order the noise is drawn (``TripodEnv``; ``policy_motion.Disturbance``
has fields of the same names)."""


# the randomisation in groups that can be switched off one at a time (``a2i-train eval
# --dr-off``), to see which one costs the policy what: each maps fields to nominal values
DR_GROUPS: dict[str, dict] = {
    "masses": {"base_mass_add": (0.0, 0.0), "link_mass_scale": (1.0, 1.0),
               "base_com_offset": (0.0, 0.0, 0.0)},
    "armature": {"armature": (0.01, 0.01)},
    "friction": {"friction": (0.8, 0.8)},
    "gains": {"kp_scale": (1.0, 1.0), "kd_scale": (1.0, 1.0), "motor_strength": (1.0, 1.0)},
    "latency": {"latency_steps": (0, 0)},
    "joint_friction": {"joint_friction": (0.0, 0.0)},
    "pushes": {"push_vel": 0.0},
    "obs_noise": {"noise_ang_vel": 0.0, "noise_gravity": 0.0, "noise_joint_pos": 0.0,
                  "noise_joint_vel": 0.0},
}


RANDOMISATIONS = ("standard", "training")
"""Which ranges an evaluation draws from: ``standard``, ``DRConfig``'s defaults (latency
0-20 ms, ...), the same for every policy, so policies trained on different ranges compare;
``training``, the policy's own training ranges (its JSON's)."""


@dataclass
class EnvConfig:
    """The tripod environment (paper section IV-C). Times s, gains N m/rad, N m s/rad."""

    num_envs: int = 256
    physics_dt: float = 0.005
    decimation: int = 4
    episode_s: float = 20.0
    command_resample_s: float = 10.0
    # one gain for every joint, or 12 in model order (an evaluation of a JSON whose deploy gains
    # differ between joints; training takes one)
    kp: float | tuple[float, ...] = 20.0
    kd: float | tuple[float, ...] = 0.5
    action_scale: float = 0.1
    action_clip: float = 1.0
    # rad, 12 in model order: how far a joint's target may lead the joint (deploy.action; the
    # JSON's action.target_lead_max, effort / kp: no further does the motor give more torque);
    # None: no bound, as every policy trained so far
    target_lead_max: tuple[float, ...] | None = None
    obs_clip: float = 100.0
    # observation frames the policy sees, newest first (deploy.observation.ObservationHistory):
    # 1 is the paper's policy (v1-v7); the distilled v8 sees a few (docs/policy-training.md)
    obs_history: int = 1
    soft_limit_margin: float = 0.05   # rad inside the URDF limits
    # rad inside the calf's upper (extension) limit where its target is clamped instead (< 0:
    # beyond it); None: soft_limit_margin. A stance calf sits on this clamp, a kp spring about
    # it, and soft motors let it fold (docs/policy-training.md, "The stance calves are springs
    # on the target clamp")
    calf_upper_margin: float | None = None
    # a curriculum for that clamp (a2i-train tripod --calf-margin-ramp): each iteration moves
    # calf_upper_margin this many rad towards calf_margin_target, so a checkpoint holds the
    # margin it reached and a resume goes on from there. Raised at once, a policy trained on
    # the clamp winds its stance calves up to the new one and falls (v10 on board)
    calf_margin_target: float | None = None
    calf_margin_step: float = 0.0
    p_no_lift: float = 0.15           # probability that a command lifts no leg
    p_yaw_command: float = 0.5        # with no lift: probability of a yaw-rate command
    yaw_command: float = 0.5          # rad/s, uniform +-
    p_excite: float = 1.0             # probability that a lift plays an excitation (stage 2)
    hold_range: tuple[float, float] = (2.0, 6.0)  # s of pure tripod hold when not exciting
    # lifted leg: schedule (deploy.lift_schedule) and the pool of excitation plans
    lift_kp: float = 40.0
    lift_kd: float = 1.0
    # also the planned motion's inverse-dynamics torque on the lifted leg (LiftSchedule's
    # feedforward; deploy.leg_dynamics): a quarter of the lag, the executed CN ~1.05 not 1.11
    lift_feedforward: bool = True
    # the lifted leg's tracking adapter (LiftSchedule's adapt; deploy.tracking_adapter): the
    # evaluation plays the JSON's; training has not used it (the network never sees the lifted
    # leg's motors)
    lift_adapt: bool = False
    # the fraction of the lifted leg's excursion from its plan's start pose (plan.q0) the policy
    # observes while it excites (LiftSchedule's excitation_seen;
    # deploy.observation.observe_lifted_leg; the critic sees the leg as measured): the export
    # writes it, the evaluation plays the JSON's; every committed policy trained at 1
    excitation_seen: float = 1.0
    shift_s: float = 1.0
    # {leg: s} lifts whose shift is not shift_s (the evaluation plays the JSON's shift_by_leg)
    shift_by_leg: dict | None = None
    lift_s: float = 0.6
    hold_s: float = 0.5
    lower_s: float = 0.6
    t_r_range: tuple[float, float] = (0.3, 0.65)
    n_basis: int = 10
    # lifted foot centre this far (m) above the stance feet in the generator's model (base at
    # the stand height, 0.34 m below the hips); the tripod stands at base_height_target 0.31 m,
    # so 0.12 keeps the foot ~7 cm off the floor where the default 0.08 left 3-4 cm (v1-v4)
    ground_clearance: float = 0.12
    # periods per training plan, drawn per plan from this range (inclusive). v1-v5 used 1 (one
    # plan fits a 10 s command window); deploy plays 4 (18 s), and a one-period policy's evaluation
    # failed mostly after the first period, where it had never been trained. A lifted
    # leg finishes its schedule past the command resample, so longer plans run to the end
    # (or to the episode's time-out)
    train_periods: tuple[int, int] = (1, 4)
    plans_per_leg: int = 6
    fall_tilt: float = 1.0            # rad; beyond: terminated
    fall_height: float = 0.12         # m; base below: terminated
    # the evaluation's failure conditions also end the episode: a thigh, calf or body on the
    # ground, or the lifted foot down during hold / excitation
    terminate_on_contact: bool = True
    # reference-state initialisation (sim.tripod_pose): this share of the resets
    # starts in a level, statically balanced tripod, in the schedule's hold phase
    p_reference_start: float = 0.3
    reference_margin_m: float = 0.05  # centre of mass inside the support triangle
    reference_joint_noise: float = 0.02  # rad
    # share of the reference starts placed in the shift phase instead, part-way (uniform)
    # from the four-leg stance to the shifted stance (body over the other three feet, foot
    # still down): the transition learnt backwards from its end (front legs need ~8 cm)
    p_reference_shift: float = 0.5
    # front legs are drawn twice as often: their lift needs the larger shift (v3 learnt the
    # rear legs first and the front ones not at all)
    lift_leg_weights: tuple[float, float, float, float] = (2.0, 2.0, 1.0, 1.0)  # FL FR RL RR
    seed: int = 0
    threads: int = 0                  # MuJoCo batch threads; 0 = all CPUs
    # the envs in this many blocks, each's commands computed while another's physics steps,
    # so that a physics step's numpy overlaps MuJoCo's; 0: 2 where the batch has 4 threads or
    # more, else 1 (on 2 cores it gains nothing: docs/policy-training.md, "Stop 51")
    blocks: int = 0
    model_file: str | None = None     # compiled .mjb (TrainModel.save) instead of the URDF
    plan_pool_file: str | None = None  # precomputed PlanPool (.npz) instead of optimising
    # the lifted legs' inverse dynamics (LiftSchedule.save_dynamics_pack) instead of the URDF's through
    # pinocchio: with the two above, training needs neither (a lent machine has none)
    leg_dynamics_file: str | None = None
    rewards: RewardConfig = field(default_factory=RewardConfig)
    dr: DRConfig = field(default_factory=DRConfig)

    def soft_limits(self, legs) -> tuple[np.ndarray, np.ndarray]:
        """(lower, upper) clamp of the joint targets, rad, hip / thigh / calf of each of
        ``legs`` in turn (the env's model order, the JSON's SDK order): the URDF limits less
        ``soft_limit_margin``, the calves' upper one less ``calf_upper_margin`` if set."""
        lo = np.concatenate([position_limits(leg)[0] for leg in legs]) + self.soft_limit_margin
        hi = np.concatenate([position_limits(leg)[1] for leg in legs]) - self.soft_limit_margin
        if self.calf_upper_margin is not None:
            calves = 3 * np.arange(len(legs)) + 2
            hi[calves] += self.soft_limit_margin - self.calf_upper_margin
        return lo, hi


@dataclass
class PPOConfig:
    """rsl-rl PPO settings (its ``train_cfg`` is built from these)."""

    num_steps_per_env: int = 24
    actor_hidden: tuple[int, ...] = (256, 128, 64)
    critic_hidden: tuple[int, ...] = (256, 128, 64)
    init_std: float = 0.5
    learning_rate: float = 1e-3
    num_learning_epochs: int = 5
    num_mini_batches: int = 4
    clip_param: float = 0.2
    gamma: float = 0.99
    lam: float = 0.95
    entropy_coef: float = 0.005
    desired_kl: float = 0.01
    max_grad_norm: float = 1.0
    stage1_fraction: float = 0.15     # first fraction of iterations: tripod only (paper phase 1)
    # every mini-batch also trains on its left-right mirror image (policy_train.symmetry)
    mirror_augmentation: bool = True
    save_interval: int = 25


@dataclass
class TrainConfig:
    env: EnvConfig = field(default_factory=EnvConfig)
    ppo: PPOConfig = field(default_factory=PPOConfig)

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict) -> TrainConfig:
        e = dict(d["env"])
        r = e.pop("rewards")
        # configurations written before the v2 terms existed: those terms were off
        rw = RewardConfig(**{**{k: 0.0 for k in ("upright", "ang_vel_xy", "lift_clearance",
                                                 "support")}, **r})
        # ... and so were the episode-ending contacts and the reference starts
        e.setdefault("terminate_on_contact", False)
        e.setdefault("p_reference_start", 0.0)
        e.setdefault("p_reference_shift", 0.0)
        e.setdefault("lift_leg_weights", (1.0, 1.0, 1.0, 1.0))
        e.setdefault("ground_clearance", ExcitationConfig.ground_clearance)  # the default then
        e.setdefault("train_periods", 1)
        e.setdefault("lift_feedforward", False)  # the lifted leg had PD alone before it
        if isinstance(e["train_periods"], int):  # a single count before v6
            e["train_periods"] = (e["train_periods"], e["train_periods"])
        dr = {k: tuple(v) if isinstance(v, list) else v for k, v in e.pop("dr").items()}
        dr.setdefault("armature", (0.01, 0.01))  # fixed at the model's ARMATURE before v5
        dr.setdefault("joint_friction", (0.0, 0.0))  # configurations before it had none
        # the stance-calf margin of one experiment (commit f2cd54b, docs/policy-training.md)
        # is gone: its runs load, and train, without it
        e.pop("calf_margin_m", None)
        e = {k: tuple(v) if isinstance(v, list) else v for k, v in e.items()}
        p = {k: tuple(v) if isinstance(v, list) else v for k, v in d["ppo"].items()}
        p.setdefault("mirror_augmentation", False)  # not used before v5
        # the observation-noise smoothness loss of one experiment after v7 (commit 363d034,
        # docs/policy-training.md) is gone: its runs load, and train on, without it
        p.pop("smoothness_coef", None)
        return cls(EnvConfig(**e, rewards=rw, dr=DRConfig(**dr)), PPOConfig(**p))
