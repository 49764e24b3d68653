"""Calibration motions on a *free* base standing on the floor, recorded as :mod:`sim.calibration_run`
records them.

:func:`sim.calibration_run.run_motion` holds the base on the motion's prescribed trajectory.
Here nothing holds it: the Go2 stands on the floor (``SimConfig(base="free", floor=True)``),
the joints follow the motion's trajectory open-loop under the motor PD law (every physics step,
velocity feed-forward), and the base goes where the contact forces take it. That is how the
paper's baselines behave on a robot without a balance controller: walk and spin as open-loop
gaits, wave as the naive single-foot waving.

Sequence: reset standing (stand pose, feet on the floor), hold the stand pose ``settle_s``,
blend (quintic, ``blend_s``) to the motion's first pose, then play the motion; only the motion
is recorded. What is recorded is exactly :func:`~sim.calibration_run.run_motion`'s record
(encoders quantised, body gyro, true foot angular velocity and specific force, every
``record_every`` physics steps), plus a :class:`RunHealth`: how upright the robot stayed.

:class:`RunRecorder` and :class:`HealthTracker` are the two pieces, public so that other
drivers of a free-base :class:`~sim.go2.Go2Sim` (the tripod policy, ``policy_train``) record
the same way.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

import numpy as np

from calib.excitation import TRIPOD_LIFT_POSE_LEG
from calib.joints import (
    MODEL_LEGS,
    STAND_POSE_LEG,
    check_leg,
    full_pose,
    model_to_sdk,
    pose_for_leg,
)
from calib.motions import Motion, tripod_pose, wave_motion
from sim.calibration_run import TRACKING_KD, TRACKING_KP, MotionRun
from sim.go2 import Go2Sim, SimConfig, build_model_for
from sim.sensors import BodyImuModel, EncoderModel
from sim.tripod_pose import capture_margins
from sim.tripod_pose import tripod_pose as static_tripod

__all__ = [
    "FALL_HEIGHT",
    "FALL_TILT",
    "HealthTracker",
    "PushRecord",
    "RunHealth",
    "RunRecorder",
    "free_base_sim",
    "naive_wave_free",
    "push_record",
    "run_motion_free",
]

FALL_TILT = 1.0
"""Base tilt beyond which the robot counts as fallen, rad (the tripod training's threshold)."""
FALL_HEIGHT = 0.12
"""Base height under which the robot counts as fallen, m (the tripod training's threshold)."""
WAVE_SHIFT_S = 2.0
"""s, the naive wave's move of the body over the three other feet (the policy's front-lift
shift)."""
WAVE_MARGIN = 0.05
"""m, where that move puts the centre of mass inside the support triangle (the training's
reference stances')."""


@dataclass(frozen=True)
class PushRecord:
    """A shove given to a free-base run, with where it left the robot against its stance.

    t_s: sim time, s. phase: the lift schedule's phase it came in (``"settle"`` before the
    lift command). dv: the base's horizontal velocity change, m/s, world x and y. stance: the
    legs the schedule stood on (three while a leg is lifted, from the lift to the end of the
    lowering; four otherwise). com_margin_m: the margin, m, of the whole robot's centre of
    mass (its ground projection) in the polygon of those feet
    (:func:`calib.support.polygon_margin`: > 0 inside, < 0 outside), just before the push.
    capture_margin_m: the same of the instantaneous capture point just after it, ``c + v / w0`` with ``w0 = sqrt(g / h)``, h the
    centre of mass's height over the stance feet's soles: a linear inverted pendulum on point
    feet (as the Go2's are) whose capture point leaves the support polygon cannot be stopped
    without a step, whatever its controller does (a body that turns about its centre of
    mass gains a little).
    """

    t_s: float
    phase: str
    dv: tuple[float, float]
    stance: tuple[str, ...]
    com_margin_m: float
    capture_margin_m: float

    def to_dict(self) -> dict:
        return {**self.__dict__, "dv": list(self.dv), "stance": list(self.stance)}

    @classmethod
    def from_dict(cls, d: dict) -> PushRecord:
        return cls(**{**d, "dv": tuple(d["dv"]), "stance": tuple(d["stance"])})


def push_record(sim: Go2Sim, phase: str, dv_world, stance) -> PushRecord:
    """The :class:`PushRecord` of a push of ``dv_world`` (m/s, world; its x and y count)
    about to be given to ``sim`` now, the robot standing on the legs ``stance``."""
    stance = tuple(check_leg(g) for g in stance)
    if len(stance) < 3:
        raise ValueError(f"a support polygon needs three feet or more, got {stance}")
    # the feet in order around the body (FL, FR, RR, RL), as polygon_margin takes them
    ring = [g for g in ("FL", "FR", "RR", "RL") if g in stance]
    feet = sim.foot_positions[[MODEL_LEGS.index(g) for g in ring]]
    com, vel = sim.com_state()
    dv = np.asarray(dv_world, dtype=float)[:2]
    m_com, m_xi = capture_margins(com[None], (vel[:2] + dv)[None], feet[None],
                                  -float(sim.model.opt.gravity[2]))
    return PushRecord(float(sim.time), str(phase), (float(dv[0]), float(dv[1])), stance,
                      float(m_com[0]), float(m_xi[0]))


@dataclass
class RunHealth:
    """How the robot fared over the watched part of a free-base run.

    max_tilt_deg / tilt_rms_deg: angle of the base z axis from the vertical, deg.
    min_base_z / final_base_z: height of the base origin, m. body_contacts: bodies other than a
    foot sphere that touched the floor (sorted). lifted_leg: the leg that should stay in the air
    (None for gaits); lifted_foot_touched: whether its foot touched the floor (None without a
    lifted leg); lifted_foot_min_z: lowest height of its foot centre, m (NaN without one).
    fell: tilt beyond :data:`FALL_TILT`, base below :data:`FALL_HEIGHT` or the base body on the
    floor. duration_s: watched time, s. calf_reach_mm: for each leg whose calf touched the floor
    with more than its foot sphere, the farthest such contact from its foot centre, mm
    (:meth:`~sim.go2.Go2Sim.calf_contact_reach`: up to 30 mm the calf's lower end, which wraps
    the top of the foot; the knee is 213 mm up). aborted: why the run's driver called its lift
    off (deploy's tip guard), None if it did not; the watch then ends where it was called off.
    excite_tilt_rms_deg: the tilt RMS over the excitation alone, deg (a policy's run; None for
    the others), what the evaluation reports: ``tilt_rms_deg`` also covers the hold.
    fall_time_s: sim time, s, at which the run's driver first saw the tilt or the height past
    the fall thresholds (a policy's run; None if it did not). pushes: the shoves the run was
    given (:class:`PushRecord`; a policy's run under a disturbance with pushes).
    lift_wait_s: s the run's driver held the shift longer before the lift (deploy's lift gate).
    """

    max_tilt_deg: float
    tilt_rms_deg: float
    min_base_z: float
    final_base_z: float
    body_contacts: tuple[str, ...]
    lifted_leg: str | None
    lifted_foot_touched: bool | None
    lifted_foot_min_z: float
    fell: bool
    duration_s: float
    calf_reach_mm: dict[str, float] = field(default_factory=dict)
    aborted: str | None = None
    excite_tilt_rms_deg: float | None = None
    fall_time_s: float | None = None
    pushes: tuple[PushRecord, ...] = ()
    lift_wait_s: float = 0.0

    def to_dict(self) -> dict:
        d = dict(self.__dict__)
        d["body_contacts"] = list(self.body_contacts)
        d["calf_reach_mm"] = dict(self.calf_reach_mm)
        d["pushes"] = [p.to_dict() for p in self.pushes]
        return d

    @classmethod
    def from_dict(cls, d: dict) -> RunHealth:
        d = dict(d)
        d["body_contacts"] = tuple(d["body_contacts"])
        d["pushes"] = tuple(PushRecord.from_dict(p) for p in d.get("pushes", ()))
        return cls(**d)


class HealthTracker:
    """Accumulates :class:`RunHealth` from a free-base :class:`Go2Sim`, one :meth:`update` per
    watched sample."""

    def __init__(self, lifted_leg: str | None = None):
        self.lifted_leg = None if lifted_leg is None else check_leg(lifted_leg)
        self._li = None if lifted_leg is None else MODEL_LEGS.index(self.lifted_leg)
        self._n = 0
        self._tilt_max = 0.0
        self._tilt_sq = 0.0
        self._z_min = np.inf
        self._z_last = np.nan
        self._bodies: set[str] = set()
        self._touched = False
        self._foot_min = np.inf
        self._t0: float | None = None
        self._t1 = 0.0
        self._reach = np.full(4, np.nan)

    def watch_contacts(self, sim: Go2Sim) -> None:
        """Only the floor contacts of bodies other than the feet: for the parts of a run whose
        tilt and lifted foot are not judged (a policy's shift, lift and lowering), where a
        knee or thigh on the floor is a failure all the same."""
        bodies = sim.body_contacts()
        if bodies:
            self._bodies.update(bodies)
            if any(b.endswith("_calf") for b in bodies):
                self._reach = np.fmax(self._reach, sim.calf_contact_reach())

    def update(self, sim: Go2Sim) -> None:
        tilt = sim.base_tilt
        z = float(sim.base_pos[2])
        self._n += 1
        self._tilt_max = max(self._tilt_max, tilt)
        self._tilt_sq += tilt * tilt
        self._z_min = min(self._z_min, z)
        self._z_last = z
        self.watch_contacts(sim)
        if self._li is not None:
            self._touched |= bool(sim.foot_contact_forces[self._li] > 0.0)
            self._foot_min = min(self._foot_min, float(sim.foot_positions[self._li, 2]))
        if self._t0 is None:
            self._t0 = sim.time
        self._t1 = sim.time

    def result(self) -> RunHealth:
        if self._n == 0:
            raise ValueError("no sample was watched")
        fell = (self._tilt_max > FALL_TILT or self._z_min < FALL_HEIGHT
                or "base" in self._bodies)
        return RunHealth(
            float(np.degrees(self._tilt_max)), float(np.degrees(np.sqrt(self._tilt_sq / self._n))),
            float(self._z_min), float(self._z_last), tuple(sorted(self._bodies)),
            self.lifted_leg, None if self._li is None else bool(self._touched),
            float(self._foot_min) if self._li is not None else float("nan"), bool(fell),
            float(self._t1 - (self._t0 or 0.0)),
            {leg: round(float(1e3 * r), 2) for leg, r in zip(MODEL_LEGS, self._reach, strict=True)
             if np.isfinite(r)})


class RunRecorder:
    """What :func:`sim.calibration_run.run_motion` records, from any driver of a :class:`Go2Sim`:
    call :meth:`record` after the physics steps to record, then :meth:`finish`."""

    def __init__(self, capacity: int):
        if capacity < 2:
            raise ValueError(f"capacity must be >= 2 samples, got {capacity}")
        self.n = 0
        self.t = np.empty(capacity)
        self.q = np.empty((capacity, 12))
        self.dq = np.empty((capacity, 12))
        self.w = np.empty((capacity, 3))
        self.sf = np.empty((capacity, 3))
        self.fw = np.empty((4, capacity, 3))
        self.fsf = np.empty((4, capacity, 3))
        self.q_cmd = np.empty((capacity, 12))

    def record(self, sim: Go2Sim, q_cmd: np.ndarray) -> None:
        """One sample of the truth at ``sim.time``; q_cmd: (12,) model order, the commanded joint
        positions (for the tracking RMSE), rad."""
        i = self.n
        if i >= len(self.t):
            raise ValueError("RunRecorder is full")
        self.t[i] = sim.time
        self.q[i] = sim.q
        self.dq[i] = sim.dq
        self.w[i] = sim.base_ang_vel
        self.sf[i] = sim.base_specific_force
        self.fw[:, i] = sim.foot_angular_velocities()
        self.fsf[:, i] = sim.foot_specific_forces()
        self.q_cmd[i] = q_cmd
        self.n = i + 1

    def finish(self, name: str, encoder: EncoderModel | None = None,
               body_imu: BodyImuModel | None = None) -> MotionRun:
        """The :class:`MotionRun` of the recorded samples (encoders and body gyro measured)."""
        n = self.n
        if n < 2:
            raise ValueError("fewer than 2 samples recorded")
        q_meas, dq_meas = (encoder or EncoderModel()).measure(self.q[:n], self.dq[:n])
        gyro = (body_imu or BodyImuModel()).measure(self.w[:n], self.sf[:n])[0]
        rmse = np.sqrt(np.mean((self.q[:n] - self.q_cmd[:n]) ** 2, axis=0))
        return MotionRun(name, self.t[:n].copy(), model_to_sdk(q_meas), model_to_sdk(dq_meas),
                         gyro, self.fw[:, :n].copy(), self.fsf[:, :n].copy(), rmse)


def free_base_sim(timestep: float = 0.001, q0=None, effects=(), seed: int = 0,
                  model_xml: str | None = None) -> Go2Sim:
    """A :class:`Go2Sim` on the floor, free base, reset with its joints at ``q0`` ((12,) model
    order, rad; default the stand pose) and the lowest foot touching the floor. effects:
    :class:`sim.effects.Effect` objects (fresh ones per simulation); seed: their ``sim.rng``.
    model_xml: another MJCF model of the Go2 (:mod:`sim.external_model`; None: the URDF's)."""
    cfg = SimConfig(base="free", floor=True, timestep=timestep, effects=list(effects), seed=seed,
                    model_xml=None if model_xml is None else str(model_xml))
    sim = Go2Sim(cfg, model=build_model_for(cfg))
    sim.reset(q=q0)
    return sim


def _quintic(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    x = np.clip(x, 0.0, 1.0)
    return x**3 * (10 - 15 * x + 6 * x**2), 30 * x**2 * (1 - x) ** 2


def run_motion_free(
    motion: Motion,
    *,
    lifted_leg: str | None = None,
    settle_s: float = 1.0,
    blend_s: float = 1.0,
    timestep: float = 0.001,
    record_every: int = 2,
    kp: float = TRACKING_KP,
    kd: float = TRACKING_KD,
    encoder: EncoderModel | None = None,
    body_imu: BodyImuModel | None = None,
    via: tuple[tuple[np.ndarray, float], ...] = (),
    progress=None,
) -> tuple[MotionRun, RunHealth]:
    """Play ``motion``'s joint trajectory open-loop on the free-base Go2 standing on the floor.

    The prescribed base of ``motion`` is ignored (nothing holds the base). The robot starts in
    the stand pose, holds it ``settle_s`` s, blends through each ``via`` pose ((12,) model
    order, rad; quintic over its seconds), then to ``motion.q[0]`` over ``blend_s`` s (skipped
    when the pose is already there), then plays the motion (PD ``kp`` N m/rad, ``kd`` N m s/rad,
    velocity feed-forward, every physics step of ``timestep`` s). lifted_leg: the leg the
    motion keeps in the air (wave), watched for touchdowns. Returns the recorded
    :class:`MotionRun` (the motion part only, stamped in sim time) and the :class:`RunHealth`
    over it. progress(fraction): optional, about 20 calls.
    """
    if record_every < 1:
        raise ValueError(f"record_every must be >= 1, got {record_every}")
    if not (settle_s >= 0 and blend_s >= 0 and all(v[1] > 0 for v in via)):
        raise ValueError("settle_s and blend_s must be >= 0 s, via durations > 0 s")
    stand = full_pose(STAND_POSE_LEG, order="model")
    sim = free_base_sim(timestep, stand)
    zeros = np.zeros(12)
    kp_v, kd_v = np.full(12, float(kp)), np.full(12, float(kd))

    sim.set_command(stand, zeros, kp_v, kd_v, zeros)
    sim.run(round(settle_s / timestep))
    here = stand
    for pose, secs in (*((np.asarray(p, float), float(s)) for p, s in via),
                       (motion.q[0], float(blend_s))):
        nb = round(secs / timestep) if np.max(np.abs(pose - here)) > 1e-6 else 0
        for k in range(nb):
            w, dw = _quintic(np.array((k + 1) / nb))
            sim.set_command(here + w * (pose - here), dw / secs * (pose - here),
                            kp_v, kd_v, zeros)
            sim.step()
        here = pose

    tm = motion.t - motion.t[0]
    n = int(np.floor(tm[-1] / timestep + 1e-9))
    t_cmd = np.arange(n) * timestep
    q_cmd = np.stack([np.interp(t_cmd, tm, motion.q[:, j]) for j in range(12)], axis=1)
    dq_cmd = np.stack([np.interp(t_cmd, tm, motion.dq[:, j]) for j in range(12)], axis=1)
    m = n // record_every
    rec = RunRecorder(m)
    health = HealthTracker(lifted_leg)
    for k in range(m * record_every):
        sim.set_command(q_cmd[k], dq_cmd[k], kp_v, kd_v, zeros)
        sim.step()
        if (k + 1) % record_every:
            continue
        # the command that the state just recorded was tracking
        rec.record(sim, q_cmd[min(k + 1, n - 1)])
        health.update(sim)
        i = rec.n - 1
        if progress is not None and i % max(1, m // 20) == 0:
            progress(i / m)
    if progress is not None:
        progress(1.0)
    return rec.finish(motion.name, encoder, body_imu), health.result()


def naive_wave_free(leg: str, duration: float, seed: int = 0, rate: float = 200.0,
                    kp: float = TRACKING_KP, timestep: float = 0.001
                    ) -> tuple[Motion, tuple[tuple[np.ndarray, float], ...]]:
    """The naive single-foot waving on the free base: ``(motion, via)`` for
    :func:`run_motion_free` (``lifted_leg=leg``).

    Open loop, as the paper's baseline, but it does not start by tipping over: blended straight
    from the stand to the lifted pose, the robot tipped 52° by the end of the 1 s lift and lay on
    its back for the whole record (which the free-base table then scored as a calibration). So,
    as anyone lifting a standing robot's leg by hand would, the body first moves over the three
    other feet (``via``: :data:`WAVE_SHIFT_S` s to the static stance with the centre of mass
    :data:`WAVE_MARGIN` m inside their triangle, the foot still down, :mod:`sim.tripod_pose`),
    the leg then rises to the wave's lifted pose (``run_motion_free``'s blend) with the stance
    legs' targets holding the static load at ``kp``, and waves with
    :func:`calib.motions.wave_motion`'s joint trajectory (seed ``seed``, ``duration`` s).
    Nothing corrects the body's motion as it waves.
    """
    leg = check_leg(leg)
    li = MODEL_LEGS.index(leg)
    stand = full_pose(STAND_POSE_LEG, order="model")
    sim = free_base_sim(timestep, stand)
    height = float(sim.base_pos[2])
    q_lift = pose_for_leg(leg, TRIPOD_LIFT_POSE_LEG)
    shift = static_tripod(sim.model, li, stand, q_lift, height, WAVE_MARGIN, kp, kp,
                          lifted=False)
    lifted = static_tripod(sim.model, li, stand, q_lift, height, WAVE_MARGIN, kp, kp)
    wave = wave_motion(leg, duration, rate, seed)
    # the wave's swing about its own tripod pose, played about the static stance's targets
    q = lifted.target + (wave.q - tripod_pose(leg))
    return dataclasses.replace(wave, q=q), ((shift.target, WAVE_SHIFT_S),)
