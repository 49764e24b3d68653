"""Make "real" recordings from ``sim`` with injected effects (for the bench and the tests).

A recording is what the robot's logger would keep: the state at 500 Hz (encoders quantised, a
little velocity noise; body IMU with white noise; estimated torque), the host's commands at
50 Hz (SDK order, the command in force at each state sample), and the mount. Effects act as
they would on the robot: dynamic ones through the ``Effect`` hooks of :class:`sim.go2.Go2Sim`,
IMU ones on the reported IMU samples (:func:`sim.effects.apply_imu_effects`).

Motions:

* ``"suspended"`` (base fixed in the air): every joint plays a sum of three sines (0.3-5 Hz,
  random phases, seeded) about the stand pose, with the analytic velocity as ``dq_des``;
  PD kp 25 N m/rad, kd 0.6 N m s/rad (policy-like gains);
* ``"ground"``: standing under the stand PD (kp 60, kd 5) while the legs sway the body in heave,
  pitch and roll (0.4-2 Hz), after 0.5 s of settling that is not recorded.
"""

from __future__ import annotations

import copy
from dataclasses import dataclass

import numpy as np

from calib.joints import NUM_MOTORS, full_pose, model_to_sdk
from sim.effects import Effect, ImuEffect, apply_imu_effects
from sim.go2 import Go2Sim, SimConfig, stand_pose
from sim.sensors import BodyImuModel, EncoderModel
from sim2real.recording import CMD_FIELDS, Recording

__all__ = ["SynthConfig", "excitation", "recording_to_snapshot", "synthesize", "write_mcap_recording"]


@dataclass
class SynthConfig:
    """mount "suspended" | "ground"; duration s; seed; state_rate, cmd_rate Hz; noise levels:
    dq_noise rad/s, tau_noise N m, gyro_noise rad/s/sqrt(Hz), accel_noise m/s^2/sqrt(Hz); q is
    quantised to the :class:`sim.sensors.EncoderModel` default step. base_truth: keep the true
    base position and velocity (the motion-capture columns ``base_p*``, ``base_v*``)."""

    mount: str = "suspended"
    duration: float = 12.0
    seed: int = 0
    state_rate: float = 500.0
    cmd_rate: float = 50.0
    dq_noise: float = 0.01
    tau_noise: float = 0.05
    gyro_noise: float = 0.0005
    accel_noise: float = 0.002
    base_truth: bool = False


def excitation(mount: str, duration: float, cmd_rate: float, seed: int):
    """(cmd_t (M,), {field: (M, 12) model order}) of the motion described in the module doc."""
    rng = np.random.default_rng(seed)
    t = np.arange(0.0, duration, 1.0 / cmd_rate)
    q0 = stand_pose()
    if mount == "suspended":
        amp_leg = np.array([0.22, 0.32, 0.32])
        q = np.tile(q0, (t.size, 1))
        dq = np.zeros_like(q)
        for j in range(NUM_MOTORS):
            f = rng.uniform(0.3, 5.0, 3)
            a = amp_leg[j % 3] * rng.dirichlet(np.ones(3)) / np.sqrt(np.maximum(f / 1.0, 1.0))
            ph = rng.uniform(0, 2 * np.pi, 3)
            # ramp in over the first 0.5 s so the first window starts near rest
            ramp = np.clip(t / 0.5, 0.0, 1.0)
            s = (a[:, None] * np.sin(2 * np.pi * f[:, None] * t + ph[:, None])).sum(0)
            ds = (a[:, None] * 2 * np.pi * f[:, None]
                  * np.cos(2 * np.pi * f[:, None] * t + ph[:, None])).sum(0)
            s0 = (a * np.sin(ph)).sum()
            q[:, j] += ramp * (s - s0)
            dq[:, j] = ramp * ds
        kp, kd = 25.0, 0.6
    elif mount == "ground":
        heave = full_pose(np.array([0.0, 0.35, -0.7]))
        pitch = full_pose({"FL": [0, 0.3, -0.6], "FR": [0, 0.3, -0.6],
                           "RL": [0, -0.3, 0.6], "RR": [0, -0.3, 0.6]})
        roll = full_pose({"FL": [0, 0.3, -0.6], "FR": [0, -0.3, 0.6],
                          "RL": [0, 0.3, -0.6], "RR": [0, -0.3, 0.6]})
        q = np.tile(q0, (t.size, 1))
        dq = np.zeros_like(q)
        ramp = np.clip(t / 0.5, 0.0, 1.0)
        for vec in (heave, pitch, roll):
            f = rng.uniform(0.4, 2.0)
            a = rng.uniform(0.06, 0.1)
            ph = rng.uniform(0, 2 * np.pi)
            s = a * (np.sin(2 * np.pi * f * t + ph) - np.sin(ph))
            q += ramp[:, None] * s[:, None] * vec[None, :]
            dq += (ramp * a * 2 * np.pi * f * np.cos(2 * np.pi * f * t + ph))[:, None] * vec
        kp, kd = 60.0, 5.0
    else:
        raise ValueError(f"mount must be 'suspended' or 'ground', got {mount!r}")
    z = np.zeros_like(q)
    return t, {"q": q, "dq": dq, "kp": z + kp, "kd": z + kd, "tau": z}


def synthesize(effects: list[Effect] | tuple = (), config: SynthConfig | None = None) -> Recording:
    """A recording of the motion of ``config.mount`` with ``effects`` injected (deep-copied)."""
    cfg = config or SynthConfig()
    dyn = [e for e in copy.deepcopy(list(effects)) if not isinstance(e, ImuEffect)]
    imu_fx = [e for e in effects if isinstance(e, ImuEffect)]
    base = "fixed" if cfg.mount == "suspended" else "free"
    sim = Go2Sim(SimConfig(base=base, timestep=0.001, effects=dyn, seed=cfg.seed))
    ct, cm = excitation(cfg.mount, cfg.duration, cfg.cmd_rate, cfg.seed)
    dt = sim.model.opt.timestep
    per_state = round(1.0 / (cfg.state_rate * dt))
    per_cmd = round(1.0 / (cfg.cmd_rate * dt))
    sim.reset(stand_pose())
    settle = 0
    if base == "free":
        sim.set_command(stand_pose(), 0.0, cm["kp"][0], cm["kd"][0], 0.0)
        settle = 500
        sim.run(settle)
    n_steps = round(cfg.duration / dt)
    n = n_steps // per_state
    q = np.zeros((n, NUM_MOTORS))
    dq = np.zeros_like(q)
    tau = np.zeros_like(q)
    gyro = np.zeros((n, 3))
    acc = np.zeros((n, 3))
    quat = np.zeros((n, 4))
    ff = np.zeros((n, 4))
    bpos = np.zeros((n, 3))
    bvel = np.zeros((n, 3))
    cmd_rows = {f: np.zeros((n, NUM_MOTORS)) for f in CMD_FIELDS}
    current = {f: np.zeros(NUM_MOTORS) for f in CMD_FIELDS}
    k = 0
    for s in range(n_steps):
        if s % per_cmd == 0 and s // per_cmd < ct.size:
            c = s // per_cmd
            current = {f: cm[f][c] for f in CMD_FIELDS}
        if s % per_state == 0 and k < n:
            q[k], dq[k], tau[k] = sim.q, sim.dq, sim.tau
            gyro[k], acc[k], quat[k] = sim.base_ang_vel, sim.base_specific_force, sim.base_quat_wxyz
            if base == "free":
                ff[k] = sim.foot_contact_forces
                bpos[k] = sim.base_pos
                bvel[k] = sim.base_rotation @ sim.base_lin_vel
            for f in CMD_FIELDS:
                cmd_rows[f][k] = current[f]
            k += 1
        if s % per_cmd == 0 and s // per_cmd < ct.size:
            sim.set_command(*(current[f] for f in CMD_FIELDS))
        sim.run(1)
    t = np.arange(n) * per_state * dt
    enc = EncoderModel(dq_noise_std=cfg.dq_noise, seed=cfg.seed + 1)
    q_meas, dq_meas = enc.measure(q, dq)
    rng = np.random.default_rng(cfg.seed + 2)
    tau_meas = tau + rng.normal(0.0, cfg.tau_noise, tau.shape)
    gyro, acc, quat = apply_imu_effects(imu_fx, t, gyro, acc, quat)
    imu = BodyImuModel(cfg.gyro_noise, cfg.accel_noise, cfg.state_rate, seed=cfg.seed + 3)
    gyro, acc = imu.measure(gyro, acc)
    sdk = {f: model_to_sdk(cmd_rows[f]) for f in CMD_FIELDS}
    cmd_t = ct[: int(np.ceil(n * per_state / per_cmd))]
    cmd_ev = {f: model_to_sdk(cm[f][: cmd_t.size]) for f in CMD_FIELDS}
    return Recording(
        t=t, q=model_to_sdk(q_meas), dq=model_to_sdk(dq_meas), cmd=sdk, cmd_t=cmd_t,
        cmd_events=cmd_ev, base_quat=quat, base_gyro=gyro, base_acc=acc, mount=cfg.mount,
        tau=model_to_sdk(tau_meas), foot_force=None if base == "fixed" else ff[:, [1, 0, 3, 2]],
        base_pos=bpos if cfg.base_truth and base == "free" else None,
        base_vel=bvel if cfg.base_truth and base == "free" else None,
        source="synth",
    )


def recording_to_snapshot(rec: Recording, t0_ns: int = 1_000_000_000):
    """A :class:`hw.recorder.RecordingSnapshot` holding ``rec`` as the robot's recorder would
    (LowState at the state samples, LowCmd at the command send times)."""
    from hw.go2_msgs import encode_lowstate, new_lowcmd
    from hw.recorder import Recorder, RecorderConfig

    n_cmd = rec.cmd_t.size
    r = Recorder(RecorderConfig(seconds=1.0, capacity_overrides={
        "lowstate": rec.n + 1, "lowcmd": n_cmd + 1, "wireless": 1, "events": 1},
        legs=()))
    for i in range(rec.n):
        tau = rec.tau[i] if rec.tau is not None else np.zeros(12)
        ff = rec.foot_force[i] if rec.foot_force is not None else None
        raw = encode_lowstate(rec.q[i], rec.dq[i], tau, rec.base_quat[i], rec.base_gyro[i],
                              rec.base_acc[i], tick=round(rec.t[i] * 1000), foot_force=ff)
        r.record_lowstate(t0_ns + round(rec.t[i] * 1e9), raw, rec.q[i], rec.dq[i], tau,
                          rec.base_quat[i], rec.base_gyro[i], rec.base_acc[i],
                          round(rec.t[i] * 1000))
    ev = rec.cmd_events
    for c in range(n_cmd):
        b = new_lowcmd()
        b.set_motors(ev["q"][c], ev["dq"][c], ev["kp"][c], ev["kd"][c], ev["tau"][c])
        r.record_lowcmd(t0_ns + round(rec.cmd_t[c] * 1e9), b.finalize(), ev["q"][c],
                        ev["dq"][c], ev["kp"][c], ev["kd"][c], ev["tau"][c])
    return r.snapshot()


def write_mcap_recording(rec: Recording, path, metadata: dict | None = None):
    """Write ``rec`` as a recorder MCAP (``docs/recording.md``) with ``{"mount": ...}`` in the
    session metadata. Returns the path."""
    from hw.mcap_io import write_mcap

    meta = {"mount": rec.mount, **(metadata or {})}
    return write_mcap(path, recording_to_snapshot(rec), meta)
