"""Play a calibration motion on the simulated Go2 and record what the robot's loggers would.

The motion (:class:`calib.motions.Motion`) is executed by the joint PD law at every physics step
(1 kHz) tracking the motion's positions with its velocities as feed-forward, while the base
follows the motion's prescribed pose (``"mocap"`` base: the base is *held* on the prescribed
trajectory, it does not balance). No floor: the motions are kinematic patterns, and feet pushing
on a prescribed base would only add contact forces the calibration does not care about.

What is recorded is what a Go2 gives: joint encoders (quantised, stamped with true time, every
physics step), the body gyro (base frame), and one foot IMU per leg through
:class:`sim.sensors.FootImuModel` (mounting rotation, time offset, noise, rate, jitter,
dropouts), sampling the foot's *true absolute* angular velocity. Because the simulation is run
once per motion, the foot IMUs are applied afterwards: one run serves every noise level.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from calib.joints import LEGS, check_leg, model_to_sdk, sdk_indices
from calib.motions import Motion
from sim.go2 import BaseState, Go2Sim, SimConfig, build_model_for
from sim.sensors import BodyImuModel, EncoderModel, FootImuConfig, FootImuModel, ImuBatch

TRACKING_KP = 60.0
"""PD stiffness used to play motions, N m/rad (the Go2 stand examples' value)."""
TRACKING_KD = 2.0
"""PD damping used to play motions, N m s/rad."""


@dataclass
class MotionRun:
    """One simulated execution of a motion.

    t: (N,) encoder stamps, s (true time). q, dq: (N, 12) measured joint positions and velocities,
    **SDK order** (FR, FL, RR, RL), rad, rad/s. base_gyro: (N, 3) body-IMU angular velocity, base
    frame, rad/s. foot_omega: (4, N, 3) true absolute foot angular velocity per leg in
    ``calib.joints.LEGS`` order, foot frame, rad/s. foot_sf: (4, N, 3) true specific force at the
    foot, foot frame, m/s^2. tracking_rmse: (12,) model order, rad: executed vs commanded joints.
    """

    motion_name: str
    t: np.ndarray
    q: np.ndarray
    dq: np.ndarray
    base_gyro: np.ndarray
    foot_omega: np.ndarray
    foot_sf: np.ndarray
    tracking_rmse: np.ndarray

    def leg_joints(self, leg: str) -> tuple[np.ndarray, np.ndarray]:
        """(q, dq) of ``leg`` as measured, (N, 3) each, (hip, thigh, calf)."""
        idx = sdk_indices(leg)
        return self.q[:, idx], self.dq[:, idx]

    def head(self, seconds: float) -> MotionRun:
        """The first ``seconds`` s of the record (samples stamped up to ``t[0] + seconds``), to
        compare motions on records of one length. tracking_rmse is the whole run's."""
        if not seconds > 0:
            raise ValueError(f"record length must be > 0 s, got {seconds}")
        n = int(np.searchsorted(self.t, self.t[0] + seconds + 1e-9, side="right"))
        return dataclasses.replace(self, t=self.t[:n], q=self.q[:n], dq=self.dq[:n],
                                   base_gyro=self.base_gyro[:n],
                                   foot_omega=self.foot_omega[:, :n], foot_sf=self.foot_sf[:, :n])

    def foot_imu(self, leg: str, config: FootImuConfig) -> ImuBatch:
        """Samples of a foot IMU mounted on ``leg`` with ``config``, from this run's truth."""
        i = LEGS.index(check_leg(leg))
        return FootImuModel(config).sample(self.t, self.foot_omega[i], self.foot_sf[i])


def _interp_rows(tq: float, t: np.ndarray, x: np.ndarray) -> np.ndarray:
    """Row of ``x`` linearly interpolated at time ``tq`` (clamped to the ends)."""
    k = int(np.clip(np.searchsorted(t, tq) - 1, 0, len(t) - 2))
    a = float(np.clip((tq - t[k]) / (t[k + 1] - t[k]), 0.0, 1.0))
    return (1.0 - a) * x[k] + a * x[k + 1]


def _base_trajectory(motion: Motion):
    """BaseState(t) following the motion's prescribed base; world velocity by differentiation."""
    vel = np.gradient(motion.base_pos, motion.t, axis=0)

    def traj(t: float) -> BaseState:
        quat = _interp_rows(t, motion.t, motion.base_quat_wxyz)
        return BaseState(
            _interp_rows(t, motion.t, motion.base_pos),
            quat / np.linalg.norm(quat),
            _interp_rows(t, motion.t, vel),
            _interp_rows(t, motion.t, motion.base_omega),
        )

    return traj


def run_motion(
    motion: Motion,
    *,
    timestep: float = 0.001,
    record_every: int = 2,
    kp: float = TRACKING_KP,
    kd: float = TRACKING_KD,
    encoder: EncoderModel | None = None,
    body_imu: BodyImuModel | None = None,
    progress=None,
) -> MotionRun:
    """Execute ``motion`` on the simulated Go2 (base held on its prescribed trajectory).

    timestep: physics step, s (the PD law runs every step). record_every: physics steps per
    recorded sample (2 at 1 kHz = the Go2's 500 Hz LowState). progress: optional callable
    ``progress(fraction)`` called about 20 times.
    """
    if record_every < 1:
        raise ValueError(f"record_every must be >= 1, got {record_every}")
    cfg = SimConfig(base="mocap", timestep=timestep, floor=False)
    sim = Go2Sim(cfg, model=build_model_for(cfg))
    traj = _base_trajectory(motion)
    s0 = traj(float(motion.t[0]))
    sim.reset(q=motion.q[0], base_pos=s0.pos, base_quat_wxyz=s0.quat_wxyz)
    sim.set_base_trajectory(lambda t: traj(t + float(motion.t[0])))
    encoder = encoder or EncoderModel()
    body_imu = body_imu or BodyImuModel()

    tm = motion.t - motion.t[0]
    n = int(np.floor(tm[-1] / timestep))
    # The command for physics step k is the motion at the step's start time: precomputed,
    # so the per-step Python work is only the PD command write and the recording.
    t_cmd = np.arange(n) * timestep
    q_cmd = np.stack([np.interp(t_cmd, tm, motion.q[:, j]) for j in range(12)], axis=1)
    dq_cmd = np.stack([np.interp(t_cmd, tm, motion.dq[:, j]) for j in range(12)], axis=1)
    m = n // record_every
    t = np.empty(m)
    q_true = np.empty((m, 12))
    dq_true = np.empty((m, 12))
    w_true = np.empty((m, 3))
    sf_true = np.empty((m, 3))
    fw = np.empty((4, m, 3))
    fsf = np.empty((4, m, 3))
    kp_v = np.full(12, kp)
    kd_v = np.full(12, kd)
    zeros = np.zeros(12)
    for k in range(m * record_every):
        sim.set_command(q_cmd[k], dq_cmd[k], kp_v, kd_v, zeros)
        sim.step()
        if (k + 1) % record_every:
            continue
        i = (k + 1) // record_every - 1
        t[i] = sim.time
        q_true[i] = sim.q
        dq_true[i] = sim.dq
        w_true[i] = sim.base_ang_vel
        sf_true[i] = sim.base_specific_force
        fw[:, i] = sim.foot_angular_velocities()
        fsf[:, i] = sim.foot_specific_forces()
        if progress is not None and i % max(1, m // 20) == 0:
            progress(i / m)
    if progress is not None:
        progress(1.0)
    q_meas, dq_meas = encoder.measure(q_true, dq_true)
    gyro = body_imu.measure(w_true, sf_true)[0]
    q_ref = np.stack([np.interp(t, tm, motion.q[:, j]) for j in range(12)], axis=1)
    rmse = np.sqrt(np.mean((q_true - q_ref) ** 2, axis=0))
    return MotionRun(motion.name, t + motion.t[0], model_to_sdk(q_meas), model_to_sdk(dq_meas),
                     gyro, fw, fsf, rmse)


def executed_leg_kappa(run: MotionRun, leg: str) -> float:
    """kappa of the *executed* relative foot angular velocity of ``leg`` (closed form)."""
    from calib.excitation import foot_kappa

    qm, dqm = run.leg_joints(leg)
    return foot_kappa(qm, dqm)

