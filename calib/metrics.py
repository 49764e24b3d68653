"""Calibration metrics: CN, CC (the paper's), rotation errors (paper's Euler RE and geodesic),
offset error, and rotation conversions.

Euler convention (x-y-z, the paper's RE): roll about x, pitch about y, yaw about z, composed
``R = Rz(yaw) @ Ry(pitch) @ Rx(roll)``. Angles in degrees only where the name says ``_deg``.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation


def _as_rotation_matrix(r, name: str = "rotation") -> np.ndarray:
    r = np.asarray(r, dtype=float)
    if r.shape != (3, 3):
        raise ValueError(f"{name} must be a 3x3 matrix, got shape {r.shape}")
    if not np.all(np.isfinite(r)):
        raise ValueError(f"{name} has non-finite entries")
    return r


def _as_samples(omega, name: str) -> np.ndarray:
    omega = np.asarray(omega, dtype=float)
    if omega.ndim != 2 or omega.shape[1] != 3 or omega.shape[0] < 2:
        raise ValueError(f"{name} must be (N>=2, 3), got shape {omega.shape}")
    return omega


def covariance(omega) -> np.ndarray:
    """Sample covariance (3, 3) of (N, 3) samples, 1/(N-1) normalisation (paper Eq. for S_FF)."""
    return np.cov(_as_samples(omega, "omega"), rowvar=False)


def covariance_condition(cov) -> float:
    """kappa = lambda_max / lambda_min of a symmetric positive semi-definite matrix; inf when it
    is singular: a smallest eigenvalue at or under 1e-13 lambda_max is round-off, not signal."""
    eig = np.linalg.eigvalsh(np.asarray(cov, dtype=float))
    if not eig[-1] > 0 or not eig[0] > eig[-1] * 1e-13:
        return float("inf")
    return float(eig[-1] / eig[0])


def condition_number(omega) -> float:
    """CN: kappa of the covariance of (N, 3) angular velocities (ideal 1; inf if singular)."""
    return covariance_condition(covariance(omega))


def trace_correlation(omega_i, omega_f) -> float:
    """CC: r = sqrt(tr(S_II^-1 S_IF S_FF^-1 S_FI) / 3) of two aligned (N, 3) sequences
    (any frames: invariant to a rotation of either). 1 = perfectly linearly related."""
    wi, wf = _as_samples(omega_i, "omega_i"), _as_samples(omega_f, "omega_f")
    if wi.shape != wf.shape:
        raise ValueError(f"omega_i {wi.shape} and omega_f {wf.shape} differ in shape")
    c = np.cov(np.hstack([wi, wf]), rowvar=False)
    s_ii, s_if, s_ff = c[:3, :3], c[:3, 3:], c[3:, 3:]
    m = np.linalg.solve(s_ii, s_if) @ np.linalg.solve(s_ff, s_if.T)
    return float(np.sqrt(max(np.trace(m) / 3.0, 0.0)))


def rpy_deg(rotation) -> np.ndarray:
    """(roll, pitch, yaw) in degrees of R = Rz(yaw) Ry(pitch) Rx(roll)."""
    r = _as_rotation_matrix(rotation)
    return Rotation.from_matrix(r).as_euler("xyz", degrees=True)


def rotation_from_rpy_deg(roll: float, pitch: float, yaw: float) -> np.ndarray:
    """R = Rz(yaw) Ry(pitch) Rx(roll) from angles in degrees."""
    return Rotation.from_euler("xyz", [roll, pitch, yaw], degrees=True).as_matrix()


def quaternion_wxyz(rotation) -> np.ndarray:
    """Unit quaternion (w, x, y, z) of a rotation matrix, with w >= 0."""
    q = Rotation.from_matrix(_as_rotation_matrix(rotation)).as_quat()  # x, y, z, w
    q = np.array([q[3], q[0], q[1], q[2]])
    return -q if q[0] < 0 else q


def _wrap_deg(a: np.ndarray) -> np.ndarray:
    return (np.asarray(a) + 180.0) % 360.0 - 180.0


def euler_rotation_error_deg(r_est, r_true) -> float:
    """The paper's RE (degrees): sqrt of the summed squared differences of roll, pitch, yaw,
    each difference wrapped to [-180, 180). Not a metric on rotations (see geodesic)."""
    d = _wrap_deg(rpy_deg(_as_rotation_matrix(r_est, "r_est"))
                  - rpy_deg(_as_rotation_matrix(r_true, "r_true")))
    return float(np.sqrt(np.sum(d**2)))


def geodesic_error_deg(r_est, r_true) -> float:
    """Angle (degrees) of R_est^T R_true: the rotation separating estimate and truth."""
    a = _as_rotation_matrix(r_est, "r_est")
    b = _as_rotation_matrix(r_true, "r_true")
    c = np.clip((np.trace(a.T @ b) - 1.0) / 2.0, -1.0, 1.0)
    # arccos is inaccurate near 0: use the norm of the skew part there
    m = a.T @ b
    s = 0.5 * np.linalg.norm([m[2, 1] - m[1, 2], m[0, 2] - m[2, 0], m[1, 0] - m[0, 1]])
    return float(np.degrees(np.arctan2(s, c)))


def offset_error_s(est: float, true: float) -> float:
    """Absolute time-offset error |est - true| (s)."""
    return float(abs(float(est) - float(true)))
