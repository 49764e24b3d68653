"""Replay a recording in ``sim`` by multiple shooting: short windows, each re-synchronised to
the recorded state, driven by the recorded commands at their send times.

Re-synchronisation at a window start ``t0`` (sample ``i0``):

* joints: ``q``, ``dq`` of the recording;
* suspended (``SimConfig(base="fixed")``): nothing else;
* ground (``base="free"``): the base tilt comes from the legs, not the IMU (a misaligned or
  biased IMU must not move the simulated robot): the floor normal in the base frame is the normal
  of the plane through the four feet, the base is placed with that normal vertical and the feet
  on the floor (``Go2Sim.reset``); the base velocity is the one that keeps the feet still
  (least squares over the four foot Jacobians). Motion capture (``base_pos``/``base_vel``),
  when present, sets the base position and linear velocity instead (no burn-in); the tilt
  still comes from the legs, the heading from the IMU, and the body rate is the one that keeps
  the feet still at that velocity.
* commands: every command sent in the 0.07 s before ``t0`` is re-issued at its own send time, so
  that a delayed command still arrives inside the window.

The recorded sample ``i`` at time ``t_i`` is compared with the simulated state after
``round((t_i - t0) / timestep)`` physics steps.
"""

from __future__ import annotations

import copy
import itertools
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import mujoco
import numpy as np
from scipy.signal import savgol_filter

from calib.joints import MODEL_LEGS, NUM_MOTORS, model_to_sdk, sdk_to_model
from sim.effects import Effect, ImuEffect, apply_imu_effects
from sim.go2 import Go2Sim, SimConfig, build_model_for
from sim2real.recording import CMD_FIELDS, Recording

__all__ = ["Prediction", "Replayer", "make_windows"]

LOOKBACK = 0.07  # s of commands re-issued before a window start
BURN_IN = 0.1  # s before a ground window start during which the base settles on its contacts
FOOT_LOADED = 10.0  # foot_force above which a foot is on the floor (docs/sim2real.md)
OBS_KP, OBS_KD = 100.0, 0.0  # N m/rad, N m s/rad: burn-in observer (kd small: the explicit
# integration of a swinging calf, about 4e-3 kg m^2, is unstable above 2 I / dt in total damping)
CONTACT_SINK = 0.002  # m: the feet's soft-contact penetration of the standing Go2 (about 40 N each)


def make_windows(rec: Recording, length: float = 0.5) -> list[tuple[int, int]]:
    """Consecutive windows ``(i0, i1)`` (sample indices, i1 exclusive) of about ``length`` s."""
    # a window holds 5 samples at least (shorter ones are dropped below), so a length under
    # that would only cost memory: 1e-9 s asked numpy for 15 GiB of edges
    shortest = 5 * rec.sample_period
    if not (np.isfinite(length) and length >= shortest):
        raise ValueError(f"window length must be at least {shortest:g} s (5 samples of the "
                         f"recording), got {length!r}")
    edges = np.searchsorted(rec.t, np.arange(rec.t[0], rec.t[-1], length))
    edges = np.unique(np.append(edges, rec.n))
    return [(int(a), int(b)) for a, b in itertools.pairwise(edges) if b - a >= 5]


@dataclass
class Prediction:
    """Simulated channels at the recorded sample times, SDK order, NaN outside the windows.

    q, dq (N, 12); gyro, acc (N, 3) base frame (after any IMU effects); contact (N, 4) bool
    (legs FR, FL, RR, RL; ground only); mask (N,) bool: samples compared (window starts, where
    sim and recording agree by construction, excluded). failed: windows that diverged.
    """

    q: np.ndarray
    dq: np.ndarray
    gyro: np.ndarray
    acc: np.ndarray
    contact: np.ndarray
    mask: np.ndarray
    failed: int = 0


class Replayer:
    """Multiple-shooting replay of one :class:`Recording` (see the module docstring)."""

    def __init__(self, rec: Recording, timestep: float = 0.001) -> None:
        self.rec = rec
        self.dt = float(timestep)
        self.base = "fixed" if rec.mount == "suspended" else "free"
        self.q_m = sdk_to_model(rec.q)
        self.dq_m = sdk_to_model(rec.dq)
        self.cmd_t = rec.cmd_t
        self.cmd_m = {f: sdk_to_model(rec.cmd_events[f]) for f in CMD_FIELDS}
        self._models: dict[str, mujoco.MjModel] = {}
        # the fixed base cannot turn: its IMU reads the same every sample
        self._static_imu: np.ndarray | None = None
        # feet loaded (model leg order) where the recording has foot forces
        self._loaded = (None if rec.foot_force is None
                        else rec.foot_force[:, [1, 0, 3, 2]] > FOOT_LOADED)
        # ground burn-in: the joints follow a lightly smoothed recording (quantisation and
        # velocity noise would shake the free base)
        self._n_burn = max(1, round(BURN_IN / rec.sample_period))
        win = min(9, rec.n - (1 - rec.n % 2))
        self._q_smooth = savgol_filter(self.q_m, win, 2, axis=0)
        self._dq_smooth = savgol_filter(self.dq_m, win, 2, axis=0)

    # ------------------------------------------------------------------ one replay
    def run(self, effects: Sequence[Effect] = (), windows: Sequence[tuple[int, int]] = (),
            key: str | None = None, drop_times: np.ndarray | None = None) -> Prediction:
        """Replay ``windows`` with ``effects`` (deep-copied; IMU effects act on the outputs).

        key: cache key of the compiled model for these effects' ``modify_spec`` (None: compile).
        """
        rec = self.rec
        dyn = [e for e in effects if not isinstance(e, ImuEffect)]
        imu_fx = [e for e in effects if isinstance(e, ImuEffect)]
        cfg = SimConfig(base=self.base, timestep=self.dt, effects=copy.deepcopy(dyn), seed=0)
        model = self._models.get(key) if key is not None else None
        if model is None:
            model = build_model_for(cfg)
            if self.base == "fixed":
                # hung in the air nothing touches the floor: skip collision detection (-20 %)
                model.opt.disableflags |= int(mujoco.mjtDisableBit.mjDSBL_CONTACT)
            if key is not None:
                self._models[key] = model
        sim = Go2Sim(cfg, model=model)
        n = rec.n
        q = np.full((n, NUM_MOTORS), np.nan)
        dq = np.full((n, NUM_MOTORS), np.nan)
        gyro = np.full((n, 3), np.nan)
        acc = np.full((n, 3), np.nan)
        contact = np.zeros((n, 4), bool)
        mask = np.zeros(n, bool)
        failed = 0
        ground = self.base == "free"
        for i0, i1 in windows:
            try:
                first = self._window(sim, i0, i1, q, dq, gyro, acc, contact, ground)
                mask[first + 1:i1] = True
            except RuntimeError:
                failed += 1
                mask[i0 + 1:i1] = True  # a diverged window counts, with the state it held
                last = np.nan_to_num(q[i0], nan=0.0)
                q[i0:i1] = np.where(np.isnan(q[i0:i1]), last, q[i0:i1])
                dq[i0:i1] = np.nan_to_num(dq[i0:i1], nan=0.0)
                gyro[i0:i1] = np.nan_to_num(gyro[i0:i1], nan=0.0)
                acc[i0:i1] = np.nan_to_num(acc[i0:i1], nan=0.0)
        if not ground:
            # the hung base does not move: the gyro reads zero and the accelerometer gravity in
            # the attitude the IMU itself reports (the sim's base pose is arbitrary)
            sel = ~np.isnan(q[:, 0])
            gyro[sel] = 0.0
            acc[sel] = self._gravity_in_base()[sel]
        if imu_fx:
            gyro, acc, _ = apply_imu_effects(imu_fx, rec.t, np.nan_to_num(gyro),
                                             np.nan_to_num(acc), np.tile([1.0, 0, 0, 0], (n, 1)))
        return Prediction(model_to_sdk(q), model_to_sdk(dq), gyro, acc,
                          contact[:, [1, 0, 3, 2]], mask, failed)

    def _gravity_in_base(self) -> np.ndarray:
        if self._static_imu is None:
            from scipy.spatial.transform import Rotation
            qw = self.rec.base_quat
            rot = Rotation.from_quat(qw[:, [1, 2, 3, 0]])
            self._static_imu = rot.inv().apply(np.array([0.0, 0.0, 9.81]))
        return self._static_imu

    # ------------------------------------------------------------------ one window
    def _resync(self, sim: Go2Sim, i0: int) -> None:
        rec, d, m = self.rec, sim.data, sim.model
        if self.base == "fixed":
            sim.reset(self.q_m[i0])
            d.qvel[:] = self.dq_m[i0]
            return
        tilt = self._leg_tilt(sim, i0)
        mocap = rec.base_pos is not None and rec.base_vel is not None
        if mocap:
            # motion capture says where the base is and how fast it moves, not how it is
            # tilted or turning: those still come from the legs, because the body IMU's
            # attitude and rate are among what is diagnosed (taken from a misaligned IMU they
            # tilted the simulated robot with it, and no IMU candidate could explain the gap).
            # Only the IMU's heading is used, to put the world-frame velocity along the body.
            quat = _with_heading(tilt, _heading(rec.base_quat[i0]))
            sim.reset(self.q_m[i0], base_pos=rec.base_pos[i0], base_quat_wxyz=quat)
        else:
            sim.reset(self.q_m[i0], base_quat_wxyz=tilt)
            d.qpos[2] -= CONTACT_SINK
        d.qvel[6:] = self.dq_m[i0]
        mujoco.mj_kinematics(m, d)
        mujoco.mj_comPos(m, d)
        jac = np.zeros((3, m.nv))
        rows, rhs = [], []
        for leg in MODEL_LEGS:
            mujoco.mj_jacSite(m, d, jac, None, m.site(f"{leg}_foot").id)
            rows.append(jac[:, :6].copy())
            rhs.append(-jac[:, 6:] @ self.dq_m[i0])
        a, b = np.vstack(rows), np.concatenate(rhs)
        if mocap:
            # the body rate that keeps the feet still, given the measured linear velocity
            v_lin = np.asarray(rec.base_vel[i0], dtype=float)
            w, *_ = np.linalg.lstsq(a[:, 3:6], b - a[:, 0:3] @ v_lin, rcond=None)
            d.qvel[0:6] = np.concatenate([v_lin, w])
        else:
            v, *_ = np.linalg.lstsq(a, b, rcond=None)
            d.qvel[0:6] = v

    def _leg_tilt(self, sim: Go2Sim, i0: int) -> np.ndarray:
        """Base orientation (w, x, y, z, zero yaw) that makes the feet plane horizontal."""
        m, d = sim.model, sim.data
        sim.reset(self.q_m[i0], base_pos=[0, 0, 0], base_quat_wxyz=[1, 0, 0, 0])
        mujoco.mj_kinematics(m, d)
        feet = np.array([d.site_xpos[m.site(f"{leg}_foot").id] for leg in MODEL_LEGS])
        if self._loaded is not None and self._loaded[i0].sum() == 3:
            feet = feet[self._loaded[i0]]  # rocking on three feet: their plane is the floor
        c = feet - feet.mean(axis=0)
        nrm = np.linalg.svd(c)[2][2]
        if nrm[2] > 0:  # the normal points from the feet towards the base (base frame +z)
            nrm = -nrm
        up = -nrm  # floor normal (world +z) expressed in the base frame
        axis = np.cross(up, [0.0, 0.0, 1.0])
        s, cth = np.linalg.norm(axis), up[2]
        if s < 1e-12:
            return np.array([1.0, 0.0, 0.0, 0.0])
        ang = np.arctan2(s, cth)
        # rotation taking base-frame 'up' to world z: base->world quaternion
        ax = axis / s
        return np.concatenate(([np.cos(ang / 2)], np.sin(ang / 2) * ax))

    def _window(self, sim, i0, i1, q, dq, gyro, acc, contact, ground) -> int:
        """Replay samples ``i0 .. i1 - 1``; returns the first sample compared (the one after the
        release of the joints, see :data:`BURN_IN`)."""
        rec, d, dt = self.rec, sim.data, self.dt
        burn = ground
        ib = max(0, i0 - self._n_burn) if burn else i0
        release = max(i0, ib + self._n_burn) if burn else i0
        release = min(release, i1 - 1)
        self._resync(sim, ib)
        t0 = float(rec.t[ib])
        ct = self.cmd_t
        first = int(np.searchsorted(ct, t0 - LOOKBACK, side="left"))
        last = int(np.searchsorted(ct, t0 + 1e-9, side="right"))  # commands at or before t0
        first = min(first, max(last - 1, 0))
        for c in range(first, last):
            d.time = float(ct[c])
            self._issue(sim, c)
        d.time = t0
        c_next = last
        steps_done = 0
        ts = rec.t
        t_rel = float(ts[release])
        jq = slice(d.qpos.size - NUM_MOTORS, d.qpos.size)
        jv = slice(d.qvel.size - NUM_MOTORS, d.qvel.size)
        for i in range(ib, i1):
            target = round((ts[i] - t0) / dt)
            pinned = i <= release and burn
            # commands sent before this sample's step; one stamped at the sample acts after it
            while c_next < ct.size:
                cs = round((ct[c_next] - t0) / dt)
                if cs >= target:
                    break
                if cs > steps_done:
                    self._advance(sim, steps_done, cs, t0, pinned, jq, jv, t_rel)
                    steps_done = cs
                self._issue(sim, c_next)
                c_next += 1
            if target > steps_done:
                self._advance(sim, steps_done, target, t0, pinned, jq, jv, t_rel)
                steps_done = target
            if i < release:
                continue
            q[i] = sim.q
            dq[i] = sim.dq
            if ground:
                gyro[i] = sim.base_ang_vel
                acc[i] = sim.base_specific_force
                contact[i] = sim.foot_contact_forces > 1.0
        return release

    def _advance(self, sim: Go2Sim, s0: int, s1: int, t0: float, pinned: bool, jq, jv,
                 t_release: float = 0.0) -> None:
        """Physics steps ``s0 .. s1 - 1`` after ``t0``; ``pinned`` (burn-in): a joint-space
        observer torque pulls the joints towards the (smoothed) recording, fading out towards
        ``t_release``, while the base and the contacts move freely."""
        d = sim.data
        if not pinned:
            d.qfrc_applied[jv] = 0.0
            sim.run(s1 - s0)
            return
        ts = self.rec.t
        for s in range(s0, s1):
            t = t0 + s * self.dt
            k = int(np.clip(np.searchsorted(ts, t) - 1, 0, ts.size - 2))
            w = float(np.clip((t - ts[k]) / (ts[k + 1] - ts[k]), 0.0, 1.0))
            qr = (1 - w) * self._q_smooth[k] + w * self._q_smooth[k + 1]
            vr = (1 - w) * self._dq_smooth[k] + w * self._dq_smooth[k + 1]
            left = max(t_release - t, 0.0)
            alpha = min(1.0, left / (0.5 * BURN_IN))
            d.qfrc_applied[jv] = alpha * (OBS_KP * (qr - d.qpos[jq]) + OBS_KD * (vr - d.qvel[jv]))
            sim.run(1)
        d.qfrc_applied[jv] = 0.0

    def _issue(self, sim: Go2Sim, c: int) -> None:
        cm = self.cmd_m
        sim.set_command(cm["q"][c], cm["dq"][c], cm["kp"][c], cm["kd"][c], cm["tau"][c])


def _heading(quat_wxyz) -> float:
    """Heading (rad) of a base->world quaternion: the world yaw of the base's x axis."""
    w, x, y, z = (float(v) for v in quat_wxyz)
    return float(np.arctan2(2.0 * (x * y + w * z), 1.0 - 2.0 * (y * y + z * z)))


def _with_heading(quat_wxyz, heading: float) -> np.ndarray:
    """``quat_wxyz`` turned about world z so that its heading is ``heading`` (tilt kept)."""
    half = 0.5 * (heading - _heading(quat_wxyz))
    qz = np.array([np.cos(half), 0.0, 0.0, np.sin(half)])
    w1, x1, y1, z1 = qz
    w2, x2, y2, z2 = (float(v) for v in quat_wxyz)
    return np.array([w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2,
                     w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
                     w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2,
                     w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2])


EffectFactory = Callable[[], Sequence[Effect]]
