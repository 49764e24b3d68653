"""Leg forward kinematics and foot angular velocity, vectorised over samples.

A leg is the chain of revolute joints from the base (the URDF root link, fixed) to a foot
frame. The chain is read once from a URDF with pinocchio; evaluation is plain numpy over N
samples (Rodrigues per joint), so 20 000 samples cost milliseconds, not a Python loop of
pinocchio calls.

Frames
------
* ``B``: the base (root link of the URDF; on the Go2, ``base``, where the body IMU sits).
* ``F``: the foot frame. On the Go2 of example-robot-data, ``<LEG>_foot`` is fixed on the calf
  with the calf link's orientation, 0.213 m below the knee, so "foot frame" = "calf link frame".
* ``R_B^F`` maps foot-frame vectors into the base frame (``v_B = R_B^F v_F``).

Angular velocities of the foot are always **expressed in the foot frame** (what a gyro bolted
to the calf sees, up to the unknown mounting rotation ``R_I^F`` that the calibration finds).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from calib.joints import check_leg
from calib.robot import go2_urdf_path

__all__ = [
    "PAPER_FROM_URDF_FOOT",
    "LegKinematics",
    "base_angular_velocity_from_quaternions",
    "closed_form_foot_angular_velocity",
]

PAPER_FROM_URDF_FOOT: np.ndarray = np.array(
    [
        [0.0, 0.0, -1.0],
        [-1.0, 0.0, 0.0],
        [0.0, 1.0, 0.0],
    ]
)
PAPER_FROM_URDF_FOOT.setflags(write=False)
"""Constant rotation from the URDF foot (= calf) frame to the paper's foot frame (Go2 legs).

``omega_paper = PAPER_FROM_URDF_FOOT @ omega_urdf`` for every q, dq, where ``omega_paper`` is
the paper's closed form (Eq. FK of A2I-Calib, modified Denavit-Hartenberg frames)::

    omega_paper = [-dq_hip sin(th + calf), -dq_hip cos(th + calf), dq_th + dq_calf]

and ``omega_urdf = [dq_hip cos(th + calf), dq_th + dq_calf, dq_hip sin(th + calf)]`` is the
same physical angular velocity in the URDF calf frame (hip about x, thigh and calf about y,
all joint placements unrotated). The rows of the matrix are the paper's foot axes written in
URDF-foot coordinates: ``x_paper = -z_urdf`` (down the calf, knee to foot), ``y_paper =
-x_urdf``, ``z_paper = +y_urdf`` (the pitch axis: modified DH puts each joint axis on z, and
``alpha_th = -90 deg`` turns the hip's x axis into the thigh/calf pitch axis). It is a proper
rotation (det +1), and the joint angles are the same numbers in both conventions (same zeros,
same signs), which is why no q-dependent term appears.

Why it does not matter for the condition number: the auto-covariance of a rotated signal is
``Sigma_FF' = P Sigma_FF P^T`` (``P`` this matrix; the mean rotates the same way). ``P`` is
orthogonal, so ``Sigma_FF'`` is similar to ``Sigma_FF``: same eigenvalues, hence the same
condition number, the same trace correlation r, the same time offset; only the rotation
estimate changes, ``R_I^F' = P R_I^F``. Optimising kappa(Sigma_FF) in either frame is the same
problem. (The diagonal structure of the paper's theorem also survives: P only permutes and
negates axes.)
"""

# pinocchio joint models that are a single rotation about a fixed axis.
_REVOLUTE = {
    "JointModelRX",
    "JointModelRY",
    "JointModelRZ",
    "JointModelRevoluteUnaligned",
    "JointModelRUBX",
    "JointModelRUBY",
    "JointModelRUBZ",
    "JointModelRevoluteUnboundedUnaligned",
}


def _mul33(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Matrix product of stacks laid out (3, 3, N) (b may be (3, 3, 1)), element-wise.

    Not ``np.matmul`` on (N, 3, 3): numpy loops over the stack there, ~5x slower.
    """
    return a[:, 0:1] * b[0][None] + a[:, 1:2] * b[1][None] + a[:, 2:3] * b[2][None]


def _skew(a: np.ndarray) -> np.ndarray:
    return np.array([[0.0, -a[2], a[1]], [a[2], 0.0, -a[0]], [-a[1], a[0], 0.0]])


def _as_samples(x, n: int, name: str) -> tuple[np.ndarray, bool]:
    """(N, n) float array and whether the input was a single sample (shape (n,))."""
    a = np.asarray(x, dtype=float)
    single = a.ndim == 1
    if single:
        a = a[None, :]
    if a.ndim != 2 or a.shape[1] != n:
        raise ValueError(f"{name} must have shape (N, {n}) or ({n},), got {np.shape(x)}")
    return a, single


class LegKinematics:
    """Serial chain of revolute joints from the base to a foot frame, evaluated with numpy.

    Build it with :meth:`from_urdf`; the constructor takes the extracted constants directly
    (useful for robots described otherwise).

    Parameters (all per joint, in chain order root -> foot)
    ----------
    placement_rotation : (n, 3, 3) rotation of joint k's frame (at q_k = 0) in its parent
        joint's frame (the base for k = 0).
    placement_translation : (n, 3) origin of joint k's frame in its parent's frame, m.
    axes : (n, 3) unit rotation axis of joint k in its own frame.
    foot_rotation, foot_translation : (3, 3), (3,) placement of the foot frame in the last
        joint's frame (m).
    lower, upper : (n,) position limits, rad (inf for continuous joints).
    velocity_limit : (n,) rad/s.
    """

    def __init__(
        self,
        *,
        leg: str,
        foot_frame: str,
        joint_names: tuple[str, ...],
        placement_rotation: np.ndarray,
        placement_translation: np.ndarray,
        axes: np.ndarray,
        foot_rotation: np.ndarray,
        foot_translation: np.ndarray,
        lower: np.ndarray,
        upper: np.ndarray,
        velocity_limit: np.ndarray,
    ) -> None:
        n = len(joint_names)
        if n == 0:
            raise ValueError("a leg needs at least one joint")
        self.leg = leg
        self.foot_frame = foot_frame
        self.joint_names = tuple(joint_names)
        self.n_joints = n
        self.lower = np.asarray(lower, dtype=float).reshape(n)
        self.upper = np.asarray(upper, dtype=float).reshape(n)
        self.velocity_limit = np.asarray(velocity_limit, dtype=float).reshape(n)
        r0 = np.asarray(placement_rotation, dtype=float).reshape(n, 3, 3)
        self._p0 = np.asarray(placement_translation, dtype=float).reshape(n, 3)
        ax = np.asarray(axes, dtype=float).reshape(n, 3)
        norms = np.linalg.norm(ax, axis=1)
        if np.any(norms < 1e-12):
            raise ValueError("joint axes must be non-zero")
        self._axes = ax / norms[:, None]
        self.placement_rotation = r0.copy()
        self.placement_translation = self._p0.copy()
        self.axes = self._axes.copy()
        self._r_foot = np.asarray(foot_rotation, dtype=float).reshape(3, 3)
        self._p_foot = np.asarray(foot_translation, dtype=float).reshape(3)
        # Rodrigues with the placement folded in, for samples laid out as columns (3, N):
        #   A_k v   = R0 v + sin(q) R0 K v + (1 - cos q) R0 K^2 v
        #   A_k^T v = u - sin(q) K u + (1 - cos q) K^2 u,  u = R0^T v
        # so each product is one (9,3) @ (3,N) matmul plus element-wise work.
        k = np.stack([_skew(a) for a in self._axes])
        self._fwd = np.stack([np.vstack([r, r @ kk, r @ kk @ kk]) for r, kk in zip(r0, k)])
        self._inv = np.stack([np.vstack([r.T, kk @ r.T, kk @ kk @ r.T]) for r, kk in zip(r0, k)])

    def __repr__(self) -> str:
        return (
            f"LegKinematics(leg={self.leg!r}, foot_frame={self.foot_frame!r}, "
            f"joints={list(self.joint_names)})"
        )

    # ------------------------------------------------------------------ construction
    @classmethod
    def from_urdf(
        cls,
        urdf_path: str | Path | None = None,
        leg: str = "FL",
        foot_frame: str | None = None,
    ) -> LegKinematics:
        """Extract the chain from the base to ``foot_frame`` (default ``f"{leg}_foot"``).

        ``urdf_path`` None means the Go2 of example-robot-data (``leg`` must then be FL, FR,
        RL or RR). The URDF is loaded with a fixed base: its root link is the base frame.
        Raises ValueError if the file or frame does not exist, or if a joint of the chain is
        not a single revolute joint (prismatic, helical, mimic, spherical, ...).
        """
        import pinocchio as pin  # deferred: reading CSVs or using the closed form needs no pin

        if urdf_path is None:
            leg = check_leg(leg)
            urdf_path = go2_urdf_path()
        path = Path(urdf_path)
        if not path.is_file():
            raise ValueError(f"URDF not found: {path}")
        if foot_frame is None:
            foot_frame = f"{leg}_foot"
        try:
            model = pin.buildModelFromUrdf(str(path))
        except (RuntimeError, ValueError) as exc:
            msg = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
            raise ValueError(f"cannot load URDF {path}: {msg}") from exc
        if not model.existFrame(foot_frame):
            feet = [f.name for f in model.frames if "foot" in f.name.lower()]
            hint = f"; frames with 'foot' in their name: {', '.join(feet)}" if feet else ""
            raise ValueError(f"frame {foot_frame!r} not found in {path.name}{hint}")
        frame = model.frames[model.getFrameId(foot_frame)]

        chain: list[int] = []
        j = frame.parentJoint
        while j != 0:
            chain.append(j)
            j = model.parents[j]
        chain.reverse()
        if not chain:
            raise ValueError(f"frame {foot_frame!r} is fixed to the base: no joint moves it")

        q_neutral = pin.neutral(model)
        names, r0, p0, axes, lo, hi, vmax = [], [], [], [], [], [], []
        for j in chain:
            jm = model.joints[j]
            kind = jm.shortname()
            if kind not in _REVOLUTE or jm.nv != 1:
                raise ValueError(
                    f"joint {model.names[j]!r} on the chain to {foot_frame!r} is {kind}, "
                    "not a revolute joint"
                )
            jd = jm.createData()
            jm.calc(jd, q_neutral[jm.idx_q : jm.idx_q + jm.nq])
            s = np.asarray(jd.S, dtype=float).reshape(6)  # (linear, angular) in the joint frame
            names.append(model.names[j])
            r0.append(np.array(model.jointPlacements[j].rotation))
            p0.append(np.array(model.jointPlacements[j].translation))
            axes.append(s[3:])
            if jm.nq == 1:  # bounded revolute; continuous joints (nq = 2) have no limits
                lo.append(float(model.lowerPositionLimit[jm.idx_q]))
                hi.append(float(model.upperPositionLimit[jm.idx_q]))
            else:
                lo.append(-np.inf)
                hi.append(np.inf)
            vmax.append(float(model.velocityLimit[jm.idx_v]))
        return cls(
            leg=leg,
            foot_frame=foot_frame,
            joint_names=tuple(names),
            placement_rotation=np.array(r0),
            placement_translation=np.array(p0),
            axes=np.array(axes),
            foot_rotation=np.array(frame.placement.rotation),
            foot_translation=np.array(frame.placement.translation),
            lower=np.array(lo),
            upper=np.array(hi),
            velocity_limit=np.array(vmax),
        )

    # ------------------------------------------------------------------ evaluation
    def _sin_cos(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """sin q and 1 - cos q, each (n, N), from q (N, n)."""
        qt = np.ascontiguousarray(q.T)
        return np.sin(qt), 1.0 - np.cos(qt)

    def _apply(self, k: int, v: np.ndarray, s: np.ndarray, c1: np.ndarray) -> np.ndarray:
        """A_k(q) v for columns v (3, M); s, c1 broadcast against (M,)."""
        p = self._fwd[k] @ v
        return p[0:3] + s * p[3:6] + c1 * p[6:9]

    def _apply_t(self, k: int, v: np.ndarray, s: np.ndarray, c1: np.ndarray) -> np.ndarray:
        """A_k(q)^T v for columns v (3, M)."""
        p = self._inv[k] @ v
        return p[0:3] - s * p[3:6] + c1 * p[6:9]

    def foot_rotation(self, q) -> np.ndarray:
        """R_B^F, (N,3,3): maps foot-frame vectors into the base frame. q: (N,n) or (n,) rad.

        A single sample (shape (n,)) gives a (3,3) result.
        """
        qa, single = _as_samples(q, self.n_joints, "q")
        s, c1 = self._sin_cos(qa)
        # Element-wise 3x3 products over (3, 3, N) stacks: out[i, j] = sum_l out[i, l] A[l, j].
        out = None
        for k in range(self.n_joints):
            f = self._fwd[k]  # rows: R0, R0 K, R0 K^2
            a = f[0:3, :, None] + s[k] * f[3:6, :, None] + c1[k] * f[6:9, :, None]
            out = a if out is None else _mul33(out, a)
        out = _mul33(out, self._r_foot[:, :, None])
        r = out.transpose(2, 0, 1)
        return r[0].copy() if single else np.ascontiguousarray(r)

    def foot_position(self, q) -> np.ndarray:
        """Foot-frame origin in the base frame, (N,3) m. q: (N,n) or (n,) rad."""
        qa, single = _as_samples(q, self.n_joints, "q")
        s, c1 = self._sin_cos(qa)
        v = np.broadcast_to(self._p_foot[:, None], (3, qa.shape[0]))
        for k in range(self.n_joints - 1, -1, -1):
            v = self._p0[k][:, None] + self._apply(k, v, s[k], c1[k])
        return v[:, 0].copy() if single else np.ascontiguousarray(v.T)

    def foot_angular_velocity(self, q, dq, base_omega=None) -> np.ndarray:
        """Angular velocity of the foot, expressed in the foot frame, (N,3) rad/s.

        q, dq: (N,n) or (n,), rad and rad/s, chain order. Without ``base_omega`` the velocity
        is relative to the base (the paper's forward kinematics). With ``base_omega`` ((N,3),
        or (3,) for all samples: the base's angular velocity in the base frame, i.e. the body
        gyro) it is the absolute one a foot-mounted gyro sees:
        ``omega_rel + R_B^F(q)^T @ base_omega``.
        A single sample (q of shape (n,)) gives a (3,) result.
        """
        qa, single = _as_samples(q, self.n_joints, "q")
        dqa, _ = _as_samples(dq, self.n_joints, "dq")
        n = qa.shape[0]
        if dqa.shape[0] != n:
            raise ValueError(f"q and dq differ in length: {n} vs {dqa.shape[0]}")
        if base_omega is None:
            w = np.zeros((3, n))
        else:
            wb, _ = _as_samples(base_omega, 3, "base_omega")
            if wb.shape[0] == 1:  # one base rate for every sample
                wb = np.broadcast_to(wb, (n, 3))
            if wb.shape[0] != n:
                raise ValueError(f"base_omega has {wb.shape[0]} samples, q has {n}")
            w = wb.T
        s, c1 = self._sin_cos(qa)
        dqt = dqa.T
        # Outward recursion in each joint's own frame: w_k = A_k^T w_{k-1} + axis_k dq_k
        # (the axis is fixed in the joint frame). Starting from the base's own angular
        # velocity makes it absolute; starting from zero makes it relative.
        for k in range(self.n_joints):
            w = self._apply_t(k, w, s[k], c1[k]) + self._axes[k][:, None] * dqt[k]
        w = self._r_foot.T @ w
        return w[:, 0].copy() if single else np.ascontiguousarray(w.T)


def closed_form_foot_angular_velocity(q, dq) -> np.ndarray:
    """Relative foot angular velocity in the URDF foot (calf) frame, closed form, (N,3) rad/s.

    Valid for the Go2's axis structure: hip about x, thigh and calf about y, joint placements
    unrotated (all four legs of the example-robot-data Go2). With ``phi = q_thigh + q_calf``::

        omega_F = [dq_hip cos(phi), dq_thigh + dq_calf, dq_hip sin(phi)]

    Its partial derivatives are immediate (d/dphi of the x, z terms is -z, +x times dq_hip), which
    is what the excitation optimiser needs. ``PAPER_FROM_URDF_FOOT @`` this gives the paper's Eq.
    q, dq: (N,3) or (3,) in (hip, thigh, calf) order.
    """
    qa, single = _as_samples(q, 3, "q")
    dqa, _ = _as_samples(dq, 3, "dq")
    if dqa.shape[0] != qa.shape[0]:
        raise ValueError(f"q and dq differ in length: {qa.shape[0]} vs {dqa.shape[0]}")
    phi = qa[:, 1] + qa[:, 2]
    out = np.stack(
        [dqa[:, 0] * np.cos(phi), dqa[:, 1] + dqa[:, 2], dqa[:, 0] * np.sin(phi)], axis=1
    )
    return out[0] if single else out


def base_angular_velocity_from_quaternions(t, quat_wxyz) -> np.ndarray:
    """Base angular velocity in the base frame, (N,3) rad/s, from orientation samples.

    t: (N,) s, strictly increasing (irregular steps are fine). quat_wxyz: (N,4) scalar-first
    quaternions of R_W^B (base-frame vectors into the world frame, the Go2 IMUState
    convention); they need not be normalised, and q and -q may alternate freely (each step
    uses the relative rotation R_k^T R_{k+1}, which is blind to the sign).

    Each step gives the body rate at the step's midpoint, ``log(R_k^T R_{k+1}) / dt``; sample
    k gets the two neighbouring midpoint rates interpolated linearly in time (second-order
    accurate on irregular stamps); the end samples take their one neighbouring step.
    """
    ta = np.asarray(t, dtype=float).reshape(-1)
    qa = np.asarray(quat_wxyz, dtype=float)
    if qa.ndim != 2 or qa.shape[1] != 4 or qa.shape[0] != ta.shape[0]:
        raise ValueError(f"quat_wxyz must have shape ({ta.shape[0]}, 4), got {qa.shape}")
    if ta.shape[0] < 2:
        raise ValueError("need at least 2 orientation samples to differentiate")
    if not (np.all(np.isfinite(ta)) and np.all(np.isfinite(qa))):
        raise ValueError("t and quat_wxyz must be finite")
    h = np.diff(ta)
    if np.any(h <= 0):
        raise ValueError("t must be strictly increasing")
    if np.any(np.linalg.norm(qa, axis=1) < 1e-9):
        raise ValueError("quat_wxyz contains a zero quaternion")
    rot = Rotation.from_quat(qa, scalar_first=True)
    mid = (rot[:-1].inv() * rot[1:]).as_rotvec() / h[:, None]
    out = np.empty((ta.shape[0], 3))
    out[0] = mid[0]
    out[-1] = mid[-1]
    if ta.shape[0] > 2:
        h0, h1 = h[:-1, None], h[1:, None]
        out[1:-1] = (h1 * mid[:-1] + h0 * mid[1:]) / (h0 + h1)
    return out
