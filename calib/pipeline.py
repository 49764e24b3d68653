"""One leg's calibration from its logs: forward kinematics, then the correlation solver.

This is the path every caller shares (``a2i-calib solve`` on CSV files, the simulated demo and
bench, and SOLVE on the robot from the recorder's snapshot), so that they cannot disagree.
"""

from __future__ import annotations

import numpy as np

from calib.csvio import EncoderLog, ImuLog
from calib.kinematics import LegKinematics
from calib.result import CalibrationResult
from calib.solver import CalibrationRefused, SolverConfig, SolverResult, solve

__all__ = ["CalibrationRefused", "calibrate_leg", "calibrate_logs", "foot_omega_from_encoders"]


def foot_omega_from_encoders(
    kin: LegKinematics, q: np.ndarray, dq: np.ndarray, base_omega: np.ndarray | None = None
) -> np.ndarray:
    """Foot angular velocity (N, 3) in the foot frame, rad/s.

    With ``base_omega`` (body gyro, base frame) the base rotation is compensated, so the result
    is what a foot gyro sees (absolute); without it, relative to the base (the paper's
    still-base assumption).
    """
    return kin.foot_angular_velocity(q, dq, base_omega)


def calibrate_leg(
    leg: str,
    t_enc: np.ndarray,
    q_leg: np.ndarray,
    dq_leg: np.ndarray,
    t_imu: np.ndarray,
    gyro: np.ndarray,
    base_omega: np.ndarray | None = None,
    kin: LegKinematics | None = None,
    config: SolverConfig | None = None,
) -> tuple[CalibrationResult, SolverResult]:
    """Calibrate one foot IMU.

    t_enc (N,) s and q_leg, dq_leg (N, 3) rad, rad/s (hip, thigh, calf of ``leg``, URDF signs);
    t_imu (M,) s (the IMU's stamps on the encoders' clock up to the unknown t_d) and gyro (M, 3)
    rad/s in the IMU frame; base_omega (N, 3) rad/s in the base frame, or None.
    Returns the result file content and the solver's full output (curves for plots). Raises
    :class:`calib.solver.CalibrationRefused` when the data do not support a calibration.
    """
    kin = kin or LegKinematics.from_urdf(leg=leg)
    if kin.n_joints != 3:
        raise ValueError(f"leg {leg}: the foot frame {kin.foot_frame} hangs on {kin.n_joints} "
                         "joints; encoder logs give hip, thigh and calf")
    omega_f = foot_omega_from_encoders(kin, q_leg, dq_leg, base_omega)
    sol = solve(t_enc, omega_f, t_imu, gyro, config or SolverConfig())
    return CalibrationResult.from_solver(leg, sol, foot_frame=kin.foot_frame), sol


def calibrate_logs(
    enc: EncoderLog,
    imu: ImuLog,
    kin: LegKinematics | None = None,
    config: SolverConfig | None = None,
) -> tuple[CalibrationResult, SolverResult]:
    """:func:`calibrate_leg` on logs read by :mod:`calib.csvio`."""
    return calibrate_leg(enc.leg, enc.t, enc.q, enc.dq, imu.t, imu.gyro, enc.base_omega, kin,
                         config)
