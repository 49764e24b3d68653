"""Reward terms of the tripod policy (paper Table III), vectorised over environments.

Each term is a function of plain arrays so that its sign can be checked on hand-made states;
:func:`compute_rewards` gathers them from a :class:`policy_train.env.TripodEnv` and applies
the weights of :class:`policy_train.config.RewardConfig` times the policy period (legged_gym
convention, the source of the paper's weights). Why each form was chosen where the paper's
table is ambiguous: ``docs/policy-training.md``.
"""

from __future__ import annotations

import numpy as np

from calib.support import polygon_margin
from sim.model import FOOT_RADIUS  # a foot site's height when the foot stands on the floor

__all__ = [
    "action_rate",
    "ang_vel_xy",
    "base_height",
    "collision",
    "compute_rewards",
    "joint_acc",
    "lift_clearance",
    "lift_indicator",
    "lin_vel",
    "orientation",
    "slip",
    "stance_mask",
    "support_margin",
    "torques",
    "track_ang_vel",
    "tripod_feet",
    "upright",
]


def lift_indicator(active: np.ndarray, touching: np.ndarray) -> np.ndarray:
    """b_lift: +1 where the lift is active and the lifted foot is in the air, -1 where it
    touches, 0 where no lift is active."""
    return np.where(active, np.where(touching, -1.0, 1.0), 0.0)


def track_ang_vel(cmd: np.ndarray, ang_vel: np.ndarray, sigma: float) -> np.ndarray:
    """exp(-|w* - w|^2 / sigma), w base frame rad/s, (N, 3) -> (N,), in (0, 1]."""
    return np.exp(-np.sum((cmd - ang_vel) ** 2, -1) / sigma)


def slip(foot_vel_xy: np.ndarray, stance_contact: np.ndarray) -> np.ndarray:
    """Sum over stance feet in contact of their horizontal speed, m/s; (N, 4, 2), (N, 4)."""
    return np.sum(np.linalg.norm(foot_vel_xy, axis=-1) * stance_contact, -1)


def collision(other_forces: np.ndarray, threshold: float = 1.0) -> np.ndarray:
    """Number of non-foot geoms pressing on the ground with more than ``threshold`` N; (N, G)."""
    return np.sum(other_forces > threshold, -1).astype(float)


def base_height(h: np.ndarray, target: float) -> np.ndarray:
    """(h - h*)^2, m^2."""
    return (h - target) ** 2


def orientation(gravity_b: np.ndarray) -> np.ndarray:
    """|g_xy|^2 of the projected gravity (0 when level)."""
    return np.sum(gravity_b[:, :2] ** 2, -1)


def upright(gravity_b: np.ndarray, sigma: float) -> np.ndarray:
    """exp(-|g_xy|^2 / sigma) in (0, 1]: 1 when level (a bounded, positive shaping term that
    keeps a level robot's step reward positive, so falling never pays)."""
    return np.exp(-np.sum(gravity_b[:, :2] ** 2, -1) / sigma)


def ang_vel_xy(ang_vel_b: np.ndarray) -> np.ndarray:
    """|w_xy|^2 of the base angular velocity (roll and pitch rates), (rad/s)^2."""
    return np.sum(ang_vel_b[:, :2] ** 2, -1)


def lift_clearance(foot_z: np.ndarray, active: np.ndarray, clearance: float) -> np.ndarray:
    """Shortfall of the lifted foot's height above the floor below ``clearance`` m, as a
    fraction in [0, 1] (1 = on the floor); 0 where no lift is active. foot_z: (N,) site z, m."""
    short = np.clip((clearance - (foot_z - FOOT_RADIUS)) / clearance, 0.0, 1.0)
    return np.where(active, short, 0.0)


def stance_mask(lifted: np.ndarray) -> np.ndarray:
    """(N, 4) bool: every foot but the lifted one (``lifted`` (N,), model leg index; < 0:
    none lifted, all four)."""
    stance = np.ones((len(lifted), 4), dtype=bool)
    has = lifted >= 0
    stance[np.flatnonzero(has), lifted[has]] = False
    return stance


def tripod_feet(foot_pos: np.ndarray, lifted: np.ndarray) -> np.ndarray:
    """(N, 3, 3) the three feet other than the lifted one (world m; the first three where no
    leg is lifted, ``lifted`` < 0), in model order. foot_pos (N, 4, 3), lifted (N,)."""
    order = np.argsort(~stance_mask(lifted), axis=1, kind="stable")[:, :3]  # stance first
    return np.take_along_axis(foot_pos, order[:, :, None], 1)


def support_margin(com_xy: np.ndarray, feet_xy: np.ndarray, active: np.ndarray,
                   margin: float) -> np.ndarray:
    """How far (m) the centre of mass's ground projection lies short of ``margin`` inside the
    triangle of the three stance feet: max(0, margin - d), d its :func:`polygon_margin`.
    com_xy (N, 2), feet_xy (N, 3, 2) world m; 0 where not ``active``."""
    d = polygon_margin(com_xy, feet_xy)
    return np.where(active, np.maximum(0.0, margin - d), 0.0)


def lin_vel(v_b: np.ndarray) -> np.ndarray:
    """|v_B|^2, (m/s)^2."""
    return np.sum(v_b**2, -1)


def joint_acc(dq: np.ndarray, last_dq: np.ndarray, dt: float) -> np.ndarray:
    """sum ((dq - dq_prev) / dt)^2, (rad/s^2)^2."""
    return np.sum(((dq - last_dq) / dt) ** 2, -1)


def torques(tau: np.ndarray) -> np.ndarray:
    """sum tau^2, (N m)^2."""
    return np.sum(tau**2, -1)


def action_rate(a: np.ndarray, a_prev: np.ndarray) -> np.ndarray:
    """sum (a_t - a_{t-1})^2 of the raw actions."""
    return np.sum((a - a_prev) ** 2, -1)


def compute_rewards(env) -> tuple[np.ndarray, dict[str, np.ndarray], np.ndarray]:
    """(reward (N,), weighted terms {name: (N,)}, terminated (N,)) for the env's current state."""
    cfg, w = env.cfg, env.cfg.rewards
    N, dt = env.N, env.dt
    sd, tm = env.sensordata, env.tm
    h = env.base_pos[:, 2]
    tilt = env.tilt
    terminated = env.base_touch | (tilt > cfg.fall_tilt) | (h < cfg.fall_height)
    if cfg.terminate_on_contact:
        terminated = terminated | env.other_touch | env.lift_touch

    lifted = env.lift_leg
    active = (lifted >= 0) & ((env.phase == 2) | (env.phase == 3))
    stance = stance_mask(lifted)
    has = lifted >= 0
    foot_vel = sd[:, tm.foot_vel[:, None] + np.arange(2)]
    contact_now = sd[:, tm.foot_contact] > 0
    other_f = np.linalg.norm(sd[:, tm.other_contact[:, None] + 1 + np.arange(3)], axis=-1)
    foot_pos = sd[:, tm.foot_pos[:, None] + np.arange(3)]          # (N, 4, 3) world m
    li = np.maximum(lifted, 0)
    # the body must stand over the stance feet from the lift until the leg is back down
    tripod = has & (env.phase >= 1) & (env.phase <= 4)
    feet_xy = tripod_feet(foot_pos, lifted)[:, :, :2]

    raw = {
        "lift": lift_indicator(active, env.lift_touch),
        "track_ang_vel": track_ang_vel(env.commands, env.ang_vel_b, w.track_sigma),
        "slip": slip(foot_vel, stance & contact_now),
        "termination": terminated.astype(float),
        "collision": collision(other_f),
        "base_height": base_height(h, w.base_height_target),
        "orientation": orientation(env.gravity_b),
        "upright": upright(env.gravity_b, w.upright_sigma),
        "ang_vel_xy": ang_vel_xy(env.ang_vel_b),
        "lift_clearance": lift_clearance(foot_pos[np.arange(N), li, 2], active, w.lift_clearance_m),
        "support": support_margin(env.com_xy, feet_xy, tripod, w.support_margin_m),
        "lin_vel": lin_vel(env.lin_vel_b),
        "joint_acc": joint_acc(env.dq, env.last_qvel, dt),
        "torques": torques(env.act_force),
        "action_rate": action_rate(env.actions, env.prev_actions),
    }
    terms = {k: v * getattr(w, k) * dt for k, v in raw.items() if getattr(w, k) != 0.0}
    rew = np.sum(np.stack(list(terms.values())), 0)
    return rew, terms, terminated
