"""Anti-noise excitation generator (A2I-Calib section IV-B, Theorem 1, Algorithm 1).

The lifted leg plays a periodic motion whose foot angular velocity has a covariance
``Sigma_FF`` that is as close to a scalar matrix as possible (condition number ``kappa -> 1``),
which makes the correlation calibration least sensitive to gyro noise.

Closed form of the foot angular velocity (Go2: hip about x, thigh and calf about y; checked
against pinocchio ``getFrameVelocity(..., LOCAL)`` of ``<LEG>_foot`` in the tests). Relative to
the base and expressed in the foot (= calf) frame, with ``s = q_thigh + q_calf``::

    omega = (dq_hip * cos(s),  ds,  dq_hip * sin(s))          [rad/s]

Theorem 1 basis (velocities), ``f = pi / (4 t_r)``, period ``T = 2 pi / f = 8 t_r``::

    dq_hip(tau)  = sum_k A_k sin(k f tau)
    ds(tau)      = sum_k B_k cos(k f tau)        (thigh + calf)
    dq_calf(tau) = sum_k C_k cos(k f tau)        (the split; thigh = s - calf)

Positions: ``q_hip = h0 - sum A_k/(k f) cos``, ``s = s0 + sum B_k/(k f) sin``,
``q_calf = c0 + sum C_k/(k f) sin``. ``h0``, ``s0``, ``c0`` are the means over a period.
By parity, ``Sigma_xy = Sigma_xz = 0`` on whole periods in the frame rotated by ``s0`` about y
(``s0`` only rotates x/z, which leaves kappa unchanged); the remaining off-diagonal term and the
unequal diagonal are removed by the optimiser. Kappa depends on ``(A, B)`` only; ``C``, ``h0``,
``s0``, ``c0`` are used to keep the joints inside their limits and the lifted foot clear of the
ground and of the trunk.

Objective (smooth, exact gradient): ``3 log(tr Sigma / 3) - log det Sigma`` (>= 0, zero exactly
when Sigma is scalar, i.e. kappa = 1; scale invariant) plus squared-hinge penalties for joint
positions outside ``limits - margin``, joint velocities above ``velocity_fraction * limit``, and
foot-clearance violations, evaluated on the steady period and on both ramps.

Trajectory: ``q(t) = q0 + w(t) (q_ss(t - ramp) - q0)`` with the quintic smoothstep ``w`` rising
over ``[0, ramp]`` and falling over the last ``ramp`` seconds. It starts and ends at ``q0`` with
zero velocity and acceleration, is C2, and equals the optimised periodic motion exactly on the
steady window. During the ramps every joint is a convex combination of ``q0`` and the periodic
motion, so position limits hold there when they hold for both.

Frames/units: joint angles rad, rates rad/s, times s; joints of one leg in (hip, thigh, calf)
order with the URDF sign conventions. Foot positions in the clearance model are in the base
frame relative to the leg's hip joint, with ``y`` pointing outward (mirrored for right legs).
"""

from __future__ import annotations

import csv
import io
import time
from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import minimize

from calib.atomic import write_text_atomic
from calib.joints import VELOCITY_LIMIT, check_leg, is_front, is_left, pose_for_leg, position_limits
from calib.metrics import condition_number

# Lifted-leg pose of the tripod stance (left-leg signs; mirrored by pose_for_leg): hip neutral,
# thigh raised, knee folded. The foot sits ~0.17 m below the hip axis, i.e. ~0.17 m above the
# stance feet of a robot standing at STAND_POSE_LEG (foot ~0.34 m below the hip axis), and
# directly under the hip, so the lifted foot is clearly off the ground and away from the trunk.
TRIPOD_LIFT_POSE_LEG = np.array([0.0, 1.1, -2.3])
MAX_PLAN_KAPPA = 1.02
"""Most kappa(Sigma_FF) a plan may reach and still be written or played (the paper's goal is
1; the optimiser stops at 1.00000 for every plan a policy has played)."""

# Go2 leg geometry (example-robot-data URDF, checked against pinocchio in the tests), m.
HIP_OFFSET_X = 0.1934  # base -> hip joint, +front / -rear
HIP_OFFSET_Y = 0.0465  # base -> hip joint, +left / -right
THIGH_OFFSET_Y = 0.0955  # hip joint -> thigh joint along the hip's y, outward
THIGH_LENGTH = 0.213  # thigh joint -> calf joint
CALF_LENGTH = 0.213  # calf joint -> foot centre
FOOT_RADIUS = 0.022
"""Radius of the Go2's foot contact sphere, m (the simulator's foot geom, ``sim.model``)."""
TRUNK_HALF_WIDTH = 0.097  # collision mesh of the base, |y| extent
TRUNK_BOTTOM_Z = -0.107  # collision mesh of the base, lowest z


@dataclass(frozen=True)
class ExcitationConfig:
    """Settings of the anti-noise excitation of one leg.

    leg: FL, FR, RL or RR. t_r: time-offset search range (s); sets f = pi/(4 t_r) and the period
    8 t_r. n_basis: number of sine/cosine terms. periods: steady periods played. position_margin:
    rad kept inside each joint limit. velocity_fraction: fraction of each joint's velocity limit
    allowed. start_pose: (hip, thigh, calf) rad of this leg, None for the tripod lifted pose.
    ramp: lead-in / lead-out (s). grid_rate: optimisation grid (Hz). seed: initial guess.
    ground_clearance: lifted foot centre kept this far (m) above the stance foot centres (stance
    legs at STAND_POSE_LEG, base level). body_clearance: foot surface kept this far (m) from the
    trunk side while the foot is at trunk height. reach_x: max fore-aft distance (m) of the foot
    from its hip joint. max_iter: optimiser iterations per start.
    """

    leg: str
    t_r: float = 0.5
    n_basis: int = 10
    periods: int = 4
    position_margin: float = 0.1
    velocity_fraction: float = 0.5
    start_pose: tuple[float, float, float] | None = None
    ramp: float = 1.0
    grid_rate: float = 200.0
    seed: int = 0
    ground_clearance: float = 0.08
    body_clearance: float = 0.03
    reach_x: float = 0.25
    max_iter: int = 3000

    def __post_init__(self) -> None:
        object.__setattr__(self, "leg", check_leg(self.leg))
        if not (np.isfinite(self.t_r) and self.t_r > 0):
            raise ValueError(f"t_r must be a positive number of seconds, got {self.t_r}")
        if int(self.n_basis) != self.n_basis or self.n_basis < 2:
            raise ValueError(f"n_basis must be an integer >= 2, got {self.n_basis}")
        if int(self.periods) != self.periods or self.periods < 1:
            raise ValueError(f"periods must be an integer >= 1, got {self.periods}")
        if isinstance(self.seed, bool) or int(self.seed) != self.seed or self.seed < 0:
            raise ValueError(f"seed must be an integer >= 0, got {self.seed}")
        # a JSON's 10.0 is the integer 10 (numpy's ranges and seeds refuse the float)
        for name in ("n_basis", "periods", "seed"):
            object.__setattr__(self, name, int(getattr(self, name)))
        if not (0 <= self.position_margin < 0.5):
            raise ValueError(f"position_margin must be in [0, 0.5) rad, got {self.position_margin}")
        if not (0 < self.velocity_fraction <= 1):
            raise ValueError(f"velocity_fraction must be in (0, 1], got {self.velocity_fraction}")
        if not (np.isfinite(self.ramp) and self.ramp > 0):
            raise ValueError(f"ramp must be a positive number of seconds, got {self.ramp}")
        if not (np.isfinite(self.grid_rate) and self.grid_rate > 0):
            raise ValueError(f"grid_rate must be positive (Hz), got {self.grid_rate}")
        if self.start_pose is not None:
            p = np.asarray(self.start_pose, dtype=float)
            if p.shape != (3,) or not np.all(np.isfinite(p)):
                raise ValueError("start_pose must be 3 finite angles (hip, thigh, calf) in rad")
            object.__setattr__(self, "start_pose", tuple(float(x) for x in p))

    @property
    def f(self) -> float:
        """Fundamental angular frequency pi / (4 t_r), rad/s."""
        return float(np.pi / (4.0 * self.t_r))

    @property
    def period(self) -> float:
        """Period 2 pi / f = 8 t_r, s."""
        return 8.0 * float(self.t_r)

    @property
    def duration(self) -> float:
        """Length of the played excitation, lead-in and lead-out ramps included, s."""
        return 2.0 * float(self.ramp) + self.periods * self.period

    def q0(self) -> np.ndarray:
        """Start/end pose of the leg (hip, thigh, calf), rad."""
        if self.start_pose is None:
            return pose_for_leg(self.leg, TRIPOD_LIFT_POSE_LEG)
        return np.array(self.start_pose, dtype=float)


# --------------------------------------------------------------------------------------------
# closed-form foot angular velocity and kappa


def base_to_foot(v_b: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Base-frame vectors expressed in the foot (calf) frame, (N, 3): R^T v with
    R = Rx(hip) Ry(thigh + calf), the Go2 leg's frames being aligned at q = 0.

    ``v_b``: (N, 3) in the base frame; ``q``: (N, 3) joint angles rad (hip, thigh, calf).
    Elementwise (no matrix product), so it is cheap inside a vectorised rollout."""
    h, s = q[:, 0], q[:, 1] + q[:, 2]
    x, y, z = v_b[:, 0], v_b[:, 1], v_b[:, 2]
    y1 = np.cos(h) * y + np.sin(h) * z
    z1 = -np.sin(h) * y + np.cos(h) * z
    return np.stack([np.cos(s) * x - np.sin(s) * z1, y1, np.sin(s) * x + np.cos(s) * z1], 1)


def foot_omega(q: np.ndarray, dq: np.ndarray) -> np.ndarray:
    """Foot angular velocity relative to the base, in the foot (calf) frame, rad/s, (N, 3).

    ``q``, ``dq``: (N, 3) or (3,) joint angles (rad) and rates (rad/s), (hip, thigh, calf).
    """
    q = np.asarray(q, dtype=float)
    dq = np.asarray(dq, dtype=float)
    if q.shape != dq.shape or q.shape[-1] != 3:
        raise ValueError(f"q and dq must both be (N, 3), got {q.shape} and {dq.shape}")
    s = q[..., 1] + q[..., 2]
    return np.stack([dq[..., 0] * np.cos(s), dq[..., 1] + dq[..., 2], dq[..., 0] * np.sin(s)], -1)


def foot_kappa(q: np.ndarray, dq: np.ndarray) -> float:
    """kappa(Sigma_FF) of the relative foot angular velocity of one leg's joint trajectory.

    ``q``, ``dq``: (N, 3) rad, rad/s (hip, thigh, calf), uniformly sampled. inf if singular.
    """
    return condition_number(foot_omega(q, dq))


# --------------------------------------------------------------------------------------------
# clearance model (mirrored leg: hip angle positive outward, y outward)


def stance_foot_z() -> float:
    s = 0.67 - 1.3  # STAND_POSE_LEG thigh + calf
    return float(-THIGH_LENGTH * np.cos(0.67) - CALF_LENGTH * np.cos(s))


def foot_position_mirrored(qm: np.ndarray) -> np.ndarray:
    """Foot centre (x, y_out, z) relative to the hip joint, base axes, m, (N, 3).

    ``qm``: (N, 3) mirrored joints (hip positive outward, thigh, calf), rad.
    """
    qh, qt, qc = qm[..., 0], qm[..., 1], qm[..., 2]
    s = qt + qc
    a = -THIGH_LENGTH * np.sin(qt) - CALF_LENGTH * np.sin(s)
    b = -THIGH_LENGTH * np.cos(qt) - CALF_LENGTH * np.cos(s)
    ch, sh = np.cos(qh), np.sin(qh)
    return np.stack([a, ch * THIGH_OFFSET_Y - sh * b, sh * THIGH_OFFSET_Y + ch * b], -1)


def foot_clearance_excess(qm: np.ndarray, z_min: float, y_min: float,
                          z_trunk: float) -> tuple[float, float]:
    """How far (m, 0 = clear) mirrored joints ``qm`` (N, 3) take the foot centre below ``z_min``
    (the floor) and into the trunk's side: inside ``y_min`` while above ``z_trunk``, the two
    overlaps' smaller (hip-joint frame of :func:`foot_position_mirrored`)."""
    p = foot_position_mirrored(qm)
    ground = np.maximum(z_min - p[:, 2], 0)
    trunk = np.minimum(np.maximum(y_min - p[:, 1], 0), np.maximum(p[:, 2] - z_trunk, 0))
    return float(np.max(ground)), float(np.max(trunk))


def contact_bounds() -> dict[str, float]:
    """:func:`foot_clearance_excess`'s bounds (m) at contact: the foot sphere on the stance feet's
    plane (base level) or touching the trunk's side; the optimiser keeps its margins above these."""
    return {"z_min": stance_foot_z(), "y_min": TRUNK_HALF_WIDTH - HIP_OFFSET_Y + FOOT_RADIUS,
            "z_trunk": TRUNK_BOTTOM_Z - FOOT_RADIUS}


def _foot_position_jac(qm: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Foot position (N, 3) and its Jacobian (N, 3 coords, 3 joints)."""
    qh, qt, qc = qm[:, 0], qm[:, 1], qm[:, 2]
    s = qt + qc
    a = -THIGH_LENGTH * np.sin(qt) - CALF_LENGTH * np.sin(s)
    b = -THIGH_LENGTH * np.cos(qt) - CALF_LENGTH * np.cos(s)
    da_dt = -THIGH_LENGTH * np.cos(qt) - CALF_LENGTH * np.cos(s)
    da_dc = -CALF_LENGTH * np.cos(s)
    db_dt = THIGH_LENGTH * np.sin(qt) + CALF_LENGTH * np.sin(s)
    db_dc = CALF_LENGTH * np.sin(s)
    ch, sh = np.cos(qh), np.sin(qh)
    d = THIGH_OFFSET_Y
    p = np.stack([a, ch * d - sh * b, sh * d + ch * b], -1)
    jac = np.zeros(qm.shape[:1] + (3, 3))
    jac[:, 0, 1], jac[:, 0, 2] = da_dt, da_dc
    jac[:, 1, 0] = -sh * d - ch * b
    jac[:, 1, 1], jac[:, 1, 2] = -sh * db_dt, -sh * db_dc
    jac[:, 2, 0] = ch * d - sh * b
    jac[:, 2, 1], jac[:, 2, 2] = ch * db_dt, ch * db_dc
    return p, jac


# --------------------------------------------------------------------------------------------
# the plan


def _smoothstep(x: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Quintic smoothstep w(x) on [0, 1] (clipped) and its first two derivatives in x."""
    x = np.clip(x, 0.0, 1.0)
    w = x**3 * (10 - 15 * x + 6 * x**2)
    dw = 30 * x**2 * (1 - x) ** 2
    ddw = 60 * x * (1 - x) * (1 - 2 * x)
    return w, dw, ddw


@dataclass
class ExcitationPlan:
    """An optimised excitation of one leg. Joint values in the leg's own URDF signs.

    f: rad/s; period: s; A, B, C: (n_basis,) velocity coefficients of hip (sin), thigh+calf (cos)
    and calf (cos), rad/s; h0, s0, c0: period means of hip, thigh+calf, calf, rad; q0: start/end
    pose (3,), rad; kappa: kappa(Sigma_FF) of the steady part (continuous trajectory sampled on
    the optimisation grid); duration: total s incl. ramps; steady_window: (t_start, t_end), s.
    """

    leg: str
    config: ExcitationConfig
    f: float
    period: float
    A: np.ndarray
    B: np.ndarray
    C: np.ndarray
    h0: float
    s0: float
    c0: float
    q0: np.ndarray
    kappa: float
    duration: float
    steady_window: tuple[float, float]
    iterations: int = 0
    process_time: float = 0.0
    objective: float = 0.0
    restarts: int = 0
    info: dict = field(default_factory=dict)

    # periodic part, tau = phase time (s)
    def _steady(self, tau: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        k = np.arange(1, len(self.A) + 1)
        ph = np.multiply.outer(tau, k * self.f)
        sn, cs = np.sin(ph), np.cos(ph)
        kf = k * self.f
        hip = self.h0 - cs @ (self.A / kf)
        s = self.s0 + sn @ (self.B / kf)
        calf = self.c0 + sn @ (self.C / kf)
        q = np.stack([hip, s - calf, calf], -1)
        dhip = sn @ self.A
        ds = cs @ self.B
        dcalf = cs @ self.C
        dq = np.stack([dhip, ds - dcalf, dcalf], -1)
        ddhip = cs @ (self.A * kf)
        dds = -sn @ (self.B * kf)
        ddcalf = -sn @ (self.C * kf)
        ddq = np.stack([ddhip, dds - ddcalf, ddcalf], -1)
        return q, dq, ddq

    def _window(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        r = self.config.ramp
        w_in, dw_in, ddw_in = _smoothstep(t / r)
        w_out, dw_out, ddw_out = _smoothstep((self.duration - t) / r)
        tail = t > self.duration / 2
        w = np.where(tail, w_out, w_in)
        dw = np.where(tail, -dw_out / r, dw_in / r)
        ddw = np.where(tail, ddw_out / r**2, ddw_in / r**2)
        return w, dw, ddw

    def _evaluate(self, t) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        t = np.atleast_1d(np.asarray(t, dtype=float))
        if t.ndim != 1 or not np.all(np.isfinite(t)):
            raise ValueError("t must be a 1-D array of finite times (s)")
        tc = np.clip(t, 0.0, self.duration)
        qs, dqs, ddqs = self._steady(tc - self.config.ramp)
        w, dw, ddw = self._window(tc)
        e = qs - self.q0
        q = self.q0 + w[:, None] * e
        dq = dw[:, None] * e + w[:, None] * dqs
        ddq = ddw[:, None] * e + 2 * dw[:, None] * dqs + w[:, None] * ddqs
        outside = (t < 0) | (t > self.duration)
        dq[outside] = 0.0
        ddq[outside] = 0.0
        return q, dq, ddq

    def positions(self, t) -> np.ndarray:
        """Joint angles (len(t), 3), rad, (hip, thigh, calf); q0 outside [0, duration]."""
        return self._evaluate(t)[0]

    def velocities(self, t) -> np.ndarray:
        """Joint rates (len(t), 3), rad/s; zero outside [0, duration]."""
        return self._evaluate(t)[1]

    def accelerations(self, t) -> np.ndarray:
        """Joint accelerations (len(t), 3), rad/s^2; zero outside [0, duration]."""
        return self._evaluate(t)[2]

    def sample(self, rate_hz: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(t, q, dq) on t = 0, 1/rate, ... up to and including ``duration`` when on the grid."""
        if not (np.isfinite(rate_hz) and rate_hz > 0):
            raise ValueError(f"rate_hz must be positive, got {rate_hz}")
        n = int(np.floor(self.duration * rate_hz + 1e-9)) + 1
        t = np.arange(n) / float(rate_hz)
        q, dq, _ = self._evaluate(t)
        return t, q, dq

    def steady_kappa(self, rate_hz: float) -> float:
        """kappa(Sigma_FF) of the steady window sampled at ``rate_hz`` (whole periods)."""
        t0, t1 = self.steady_window
        n = round((t1 - t0) * rate_hz)
        t = t0 + np.arange(n) / float(rate_hz)
        q, dq, _ = self._evaluate(t)
        return foot_kappa(q, dq)

    def audit(self, rate_hz: float = 2000.0) -> dict:
        """The returned trajectory checked between the optimiser's grid points, ramps included,
        sampled at ``rate_hz``: ``kappa`` of its steady window; how far (rad, rad/s; 0 =
        within) any joint goes past its position and velocity limits; how far (m; 0 = clear)
        the foot sphere goes into the floor (the stance feet's plane, base level) and into the
        trunk's side. These are the hard bounds (contact, not the config's margins), which the
        optimiser keeps with its margins on the grid only."""
        _, q, dq = self.sample(rate_hz)
        lo, hi = position_limits(self.leg)
        floor, trunk = foot_clearance_excess(q * _mirror(self.leg), **contact_bounds())
        return {"kappa": self.steady_kappa(rate_hz),
                "position_excess": float(max(0.0, np.max(lo - q), np.max(q - hi))),
                "velocity_excess": float(max(0.0, np.max(np.abs(dq) - VELOCITY_LIMIT))),
                "floor_excess": floor, "trunk_excess": trunk}

    def problems(self, max_kappa: float = MAX_PLAN_KAPPA) -> list[str]:
        """Why this plan should not be played (empty: it may): :meth:`audit`'s kappa above
        ``max_kappa``, a joint past its position or velocity limits, or the foot into the floor
        or the trunk, between the optimiser's grid points. The optimiser returns its best
        feasible start whatever kappa it reached (2.5 at t_r 0.04 s, 40 basis functions)."""
        audit = self.audit()
        out = []
        kappa = max(self.kappa, audit["kappa"])
        if kappa > max_kappa:
            out.append(f"the optimiser reached kappa {kappa:.4f} > {max_kappa:g}")
        if audit["position_excess"] > 0 or audit["velocity_excess"] > 0:
            out.append(f"the motion leaves the joint limits between the optimiser's samples "
                       f"({audit['position_excess']:.3g} rad, {audit['velocity_excess']:.3g} "
                       "rad/s past them)")
        if audit["floor_excess"] > 0 or audit["trunk_excess"] > 0:
            out.append(f"the foot goes into the floor ({1e3 * audit['floor_excess']:.3g} mm) or "
                       f"the trunk ({1e3 * audit['trunk_excess']:.3g} mm) between the "
                       "optimiser's samples")
        return out

    def to_csv(self, path, rate_hz: float = 200.0):
        """Write t, q_<LEG>_{hip,thigh,calf}, dq_<LEG>_{...} (s, rad, rad/s) atomically."""
        t, q, dq = self.sample(rate_hz)
        buf = io.StringIO()
        w = csv.writer(buf, lineterminator="\n")
        joints = ("hip", "thigh", "calf")
        w.writerow(["t"] + [f"q_{self.leg}_{j}" for j in joints] + [f"dq_{self.leg}_{j}" for j in joints])
        for i in range(len(t)):
            w.writerow([f"{t[i]:.6f}"] + [f"{x:.9f}" for x in q[i]] + [f"{x:.9f}" for x in dq[i]])
        return write_text_atomic(path, buf.getvalue())


# --------------------------------------------------------------------------------------------
# the optimisation problem (mirrored joints: hip positive outward)


class ExcitationProblem:
    """The optimisation problem of :func:`plan_excitation`, exposed for tests and tooling.

    Parameters ``theta = [A (n), B (n), C (n), h0, s0, c0]`` with the hip mirrored (positive
    outward for every leg). Joint positions and velocities on the grid (one steady period, then
    the interior of the lead-in and lead-out ramps) are affine in theta. ``value_grad(theta)``
    returns the objective and its exact gradient.
    """

    W_POS = 1e3  # per rad^2, mean over samples
    W_VEL = 1e2  # per (rad/s)^2
    W_CLEAR = 1e4  # per m^2
    W_BODY = 1e8  # per m^4 (product of two hinges)

    def __init__(self, cfg: ExcitationConfig, q0m: np.ndarray, tighten: float = 0.02):
        n = cfg.n_basis
        self.n = n
        self.p = 3 * n + 3
        f = cfg.f
        T = cfg.period
        # at least 8 samples per cycle of the highest harmonic: fewer alias it, and the
        # optimiser then shapes a motion the grid does not show (n_basis 40 at t_r 0.04:
        # kappa 1.0 on the grid, 1421 and a thigh at 766 rad/s between its points)
        N = max(int(np.ceil(T * cfg.grid_rate)), 64, 8 * n)
        tau = T * np.arange(N) / N
        nr = max(int(np.ceil(cfg.ramp * cfg.grid_rate)), 16, int(np.ceil(8 * n * cfg.ramp / T)))
        t_ramp = cfg.ramp * np.arange(1, nr) / nr  # interior ramp points
        w, dw, _ = _smoothstep(t_ramp / cfg.ramp)
        dw = dw / cfg.ramp
        # ramp-in: phase tau = t - ramp; ramp-out mirrored: phase periods*T + (ramp - t_ramp)
        tau_in = t_ramp - cfg.ramp
        tau_out = cfg.ramp - t_ramp
        taus = np.concatenate([tau, tau_in, tau_out])
        ws = np.concatenate([np.ones(N), w, w])
        dws = np.concatenate([np.zeros(N), dw, -dw])
        self.N = N
        k = np.arange(1, n + 1)
        kf = k * f
        ph = np.multiply.outer(taus, kf)
        sn, cs = np.sin(ph), np.cos(ph)
        M = len(taus)
        one = np.ones((M, 1))
        z = np.zeros((M, n))
        z1 = np.zeros((M, 1))
        # steady positions / velocities (M, p) per joint
        mq_h = np.hstack([-cs / kf, z, z, one, z1, z1])
        mq_s = np.hstack([z, sn / kf, z, z1, one, z1])
        mq_c = np.hstack([z, z, sn / kf, z1, z1, one])
        mv_h = np.hstack([sn, z, z, z1, z1, z1])
        mv_s = np.hstack([z, cs, z, z1, z1, z1])
        mv_c = np.hstack([z, z, cs, z1, z1, z1])
        mq = [mq_h, mq_s - mq_c, mq_c]
        mv = [mv_h, mv_s - mv_c, mv_c]
        self.Pq = np.stack([ws[:, None] * m for m in mq])  # (3, M, p)
        self.Pv = np.stack([dws[:, None] * a + ws[:, None] * b for a, b in zip(mq, mv)])
        self.oq = (1 - ws)[None, :] * q0m[:, None]  # (3, M)
        self.ov = -dws[None, :] * q0m[:, None]
        # the optimiser works on bounds tightened by ``tighten`` (rad, rad/s fraction, 0.1 x m)
        # so that the small violations a penalty method leaves stay inside the real bounds
        lo, hi = position_limits("FL" if is_front(cfg.leg) else "RL")
        contact = contact_bounds()
        self.bounds = {
            "lo": lo + cfg.position_margin, "hi": hi - cfg.position_margin,
            "vmax": VELOCITY_LIMIT * cfg.velocity_fraction,
            "z_min": contact["z_min"] + cfg.ground_clearance,
            "y_min": contact["y_min"] + cfg.body_clearance,
            "z_trunk": contact["z_trunk"] - cfg.body_clearance,
            "reach_x": cfg.reach_x,
        }
        b = self.bounds
        self.lo, self.hi = b["lo"] + tighten, b["hi"] - tighten
        self.vmax = b["vmax"] * (1 - tighten)
        self.z_min = b["z_min"] + 0.1 * tighten
        self.y_min = b["y_min"] + 0.1 * tighten
        self.z_trunk = b["z_trunk"] - 0.1 * tighten
        self.reach_x = b["reach_x"] - 0.1 * tighten
        self.M = M
        self.iterations = 0

    def joints(self, th: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        q = self.oq + self.Pq @ th
        dq = self.ov + self.Pv @ th
        return q.T, dq.T  # (M, 3)

    def value_grad(self, th: np.ndarray) -> tuple[float, np.ndarray]:
        self.iterations += 1
        q, dq = self.joints(th)
        M, N = self.M, self.N
        gq = np.zeros_like(q)
        gv = np.zeros_like(dq)
        # kappa surrogate on the steady period
        s = q[:N, 1] + q[:N, 2]
        dh = dq[:N, 0]
        ds = dq[:N, 1] + dq[:N, 2]
        cs_, sn_ = np.cos(s), np.sin(s)
        om = np.stack([dh * cs_, ds, dh * sn_], -1)
        d = om - om.mean(0)
        sig = d.T @ d / N
        tr = np.trace(sig)
        sign, logdet = np.linalg.slogdet(sig)
        if sign <= 0 or tr <= 0:
            return 1e6, np.zeros_like(th)
        val = 3 * np.log(tr / 3) - logdet
        G = 3 / tr * np.eye(3) - np.linalg.inv(sig)
        g_om = (2.0 / N) * d @ G  # (N, 3) (G symmetric)
        g_dh = g_om[:, 0] * cs_ + g_om[:, 2] * sn_
        g_s = dh * (-g_om[:, 0] * sn_ + g_om[:, 2] * cs_)
        gv[:N, 0] += g_dh
        gv[:N, 1] += g_om[:, 1]
        gv[:N, 2] += g_om[:, 1]
        gq[:N, 1] += g_s
        gq[:N, 2] += g_s
        # joint position limits
        up = np.maximum(q - self.hi, 0)
        dn = np.maximum(self.lo - q, 0)
        val += self.W_POS * np.sum(up**2 + dn**2) / M
        gq += self.W_POS * 2 * (up - dn) / M
        # velocity limits
        ov = np.maximum(np.abs(dq) - self.vmax, 0)
        val += self.W_VEL * np.sum(ov**2) / M
        gv += self.W_VEL * 2 * ov * np.sign(dq) / M
        # foot clearance
        p, jac = _foot_position_jac(q)
        gp = np.zeros_like(p)
        e = np.maximum(self.z_min - p[:, 2], 0)  # ground
        val += self.W_CLEAR * np.sum(e**2) / M
        gp[:, 2] -= self.W_CLEAR * 2 * e / M
        ex = np.maximum(np.abs(p[:, 0]) - self.reach_x, 0)  # fore-aft reach
        val += self.W_CLEAR * np.sum(ex**2) / M
        gp[:, 0] += self.W_CLEAR * 2 * ex * np.sign(p[:, 0]) / M
        ey = np.maximum(self.y_min - p[:, 1], 0)  # trunk side, only at trunk height
        ez = np.maximum(p[:, 2] - self.z_trunk, 0)
        val += self.W_BODY * np.sum(ey**2 * ez**2) / M
        gp[:, 1] -= self.W_BODY * 2 * ey * ez**2 / M
        gp[:, 2] += self.W_BODY * 2 * ez * ey**2 / M
        gq += np.einsum("nc,ncj->nj", gp, jac)
        grad = np.einsum("jm,jmp->p", gq.T, self.Pq) + np.einsum("jm,jmp->p", gv.T, self.Pv)
        return float(val), grad

    def violations(self, th: np.ndarray) -> dict:
        """Worst violation of each real (untightened) bound on the grid: rad, rad/s, m, m, m."""
        return self.check(*self.joints(th))

    def check(self, q: np.ndarray, dq: np.ndarray) -> dict:
        """Worst violation of each real bound by mirrored joints ``q``, ``dq`` (M, 3)."""
        b = self.bounds
        ground, trunk = foot_clearance_excess(q, b["z_min"], b["y_min"], b["z_trunk"])
        p = foot_position_mirrored(q)
        return {
            "position": float(np.max(np.maximum(q - b["hi"], 0) + np.maximum(b["lo"] - q, 0))),
            "velocity": float(np.max(np.maximum(np.abs(dq) - b["vmax"], 0))),
            "ground": ground,
            "reach": float(np.max(np.maximum(np.abs(p[:, 0]) - b["reach_x"], 0))),
            "trunk": trunk,
        }

    def kappa(self, th: np.ndarray) -> float:
        q, dq = self.joints(th)
        return foot_kappa(q[: self.N], dq[: self.N])


def _mirror(leg: str) -> np.ndarray:
    return np.array([1.0 if is_left(leg) else -1.0, 1.0, 1.0])


def initial_guess(cfg: ExcitationConfig, q0m: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Seeded starting theta (mirrored joints ``q0m``) for :class:`ExcitationProblem`."""
    n, f = cfg.n_basis, cfg.f
    A = np.zeros(n)
    B = np.zeros(n)
    C = np.zeros(n)
    # A swing of the sum angle of ~1 rad and a hip at 2x the frequency: both are needed for
    # kappa ~ 1 (the x/z split needs |s - s0| around pi/4 and beyond while the hip moves).
    B[0] = 1.0 * f
    A[1] = 0.35 * 2 * f
    C[0] = 0.5 * B[0]
    A += rng.normal(scale=0.05 * f, size=n) / np.arange(1, n + 1)
    B += rng.normal(scale=0.05 * f, size=n) / np.arange(1, n + 1)
    h0 = 0.35
    return np.concatenate([A, B, C, [h0, q0m[1] + q0m[2], q0m[2]]])


def plan_excitation(config: ExcitationConfig, kappa_target: float = 1.005,
                    max_starts: int = 4) -> ExcitationPlan:
    """Optimise the Theorem-1 coefficients for ``config`` (L-BFGS-B, exact gradient).

    Restarts from new seeded guesses (at most ``max_starts``) until kappa <= ``kappa_target``
    with every constraint met; returns the best feasible start. Raises RuntimeError if no start
    meets the joint limits (e.g. an infeasible start_pose or margins).
    """
    cfg = config
    t_start = time.process_time()
    mir = _mirror(cfg.leg)
    q0 = cfg.q0()
    lo, hi = position_limits(cfg.leg)
    if np.any(q0 < lo + cfg.position_margin - 1e-12) or np.any(q0 > hi - cfg.position_margin + 1e-12):
        raise ValueError(f"start_pose {q0} is not inside the joint limits minus the margin")
    q0m = q0 * mir
    prob = ExcitationProblem(cfg, q0m)
    v0 = prob.check(q0m[None, :], np.zeros((1, 3)))
    if max(v0.values()) > 0:
        bad = ", ".join(f"{k} by {v:.3f}" for k, v in v0.items() if v > 0)
        raise ValueError(f"start_pose {q0} violates the clearance bounds ({bad}): lift the foot")
    rng = np.random.default_rng(cfg.seed)
    best = None
    starts = 0
    for starts in range(1, max_starts + 1):
        th0 = initial_guess(cfg, q0m, rng)
        res = minimize(prob.value_grad, th0, jac=True, method="L-BFGS-B",
                       options={"maxiter": cfg.max_iter, "ftol": 1e-15, "gtol": 1e-10,
                                "maxcor": 20})
        th = res.x
        kap = prob.kappa(th)
        viol = prob.violations(th)
        feasible = max(viol.values()) <= 0.0
        score = (not feasible, kap)
        if best is None or score < best[0]:
            best = (score, th, kap, viol, res.fun)
        if feasible and kap <= kappa_target:
            break
    (infeasible, _), th, kap, viol, fun = best
    if infeasible:
        raise RuntimeError(f"no excitation inside the limits for {cfg.leg}: violations {viol}")
    n = cfg.n_basis
    A, B, C = th[:n] * mir[0], th[n:2 * n].copy(), th[2 * n:3 * n].copy()
    h0, s0, c0 = float(th[3 * n] * mir[0]), float(th[3 * n + 1]), float(th[3 * n + 2])
    return ExcitationPlan(
        leg=cfg.leg, config=cfg, f=cfg.f, period=cfg.period, A=A, B=B, C=C, h0=h0, s0=s0, c0=c0,
        q0=q0, kappa=float(kap), duration=cfg.duration,
        steady_window=(cfg.ramp, cfg.ramp + cfg.periods * cfg.period),
        iterations=prob.iterations, process_time=time.process_time() - t_start,
        objective=float(fun), restarts=starts - 1, info={"violations": viol},
    )
