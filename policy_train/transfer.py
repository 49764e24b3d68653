"""Transfer check of a tripod policy: its calibration motions re-run in a second simulator, under
perturbations the training never saw.

The evaluation (:mod:`policy_train.evaluate`) runs the policy in the environment it was trained
in (``TripodEnv``: 200 Hz physics, the training model, its randomisation). Here every episode is
:func:`policy_train.policy_motion.run_policy_a2i` instead: the on-board runner (``deploy``'s
observation builder and ONNX Runtime) on :mod:`sim.go2` (1 kHz, the motor PD law every physics
step, the simulator the mock robot and Table I use), one calibration of one leg from standing,
with a :class:`Scenario`'s perturbations drawn afresh per episode:

* ``nominal``: none;
* ``training``: the standard training randomisation (``DRConfig``'s defaults, v7's ranges;
  a policy trained with ``a2i-train tripod --dr`` had others) rebuilt from :mod:`sim.effects` and
  :class:`policy_train.policy_motion.Disturbance` (base mass and centre of mass, foot friction,
  motor strength standing in for the kp / kd / strength scales, actuation latency, pushes,
  observation noise; the other links' masses and the armature are left nominal);
* the others: ``training`` with one thing outside its ranges (a heavier payload, a slipperier
  floor, a longer latency, weaker motors, harder pushes, twice the sensor noise), or not
  modelled in training at all (joint dry friction; MuJoCo Menagerie's Go2 joint model, whose
  damping, rotor inertia and dry friction a checker's own simulation may well carry; a floor
  that is not level), or without the sensor noise.

With ``timestep`` (``--timestep``) the simulator steps at another rate than the mock's 1 kHz, the
motor PD law still computed explicitly every step, as a checker's script may run it (the
training's 200 Hz is 0.005 s); the policy's gains need either a step that short or damping the
integrator takes implicitly (``docs/policy-format.md``, "Motors").

With ``model_xml`` (``a2i-train transfer --model-xml``) every episode runs on another MJCF model
of the Go2 instead of the URDF's (:mod:`sim.external_model`, e.g. MuJoCo Menagerie's): a sim-to-sim
check, on the geometry, masses, joints and contacts a checker's own script may load. Its pages
record the model (path and the compiled model's hash) and do not take episodes of another.

An episode succeeds as the evaluation's do: no fall and no body but a foot on the floor over the
whole run, and the lifted foot never down over the hold and the excitation
(:class:`sim.free_base_run.RunHealth`). A body counts as on the floor at any contact, where the
evaluation counts a contact force above 1 N: a calf's lower end that grazes the floor beside its
foot as the leg leaves it (MuJoCo lists the contact, at 0 N as they part) fails here. With
``max_tip`` (``--max-tip``) deploy's tip guard (:mod:`deploy.tip_guard`) plays as on board: a
lift it calls off is lifted again with a longer shift, here from a stand-up on the same draws,
and the episode is that second lift's (``EpisodeResult.retried``); a second lift called off
fails, "lift called off (tipping)", with a fall if the robot fell all the same. Figures over the
excitation, of the successful episodes: base tilt RMS (deg), base angular rate RMS (rad/s,
true), the lifted leg's joint tracking RMSE (rad, executed vs the plan at the same instant) and
the CN of its true foot angular velocity over the steady periods (the evaluation's definitions).
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, field

import numpy as np

from calib.atomic import write_text_atomic
from calib.joints import LEGS, check_leg, model_indices
from calib.metrics import condition_number
from deploy.lift_gate import GATE_CAUSE, GateLimits
from deploy.tip_guard import RETRY_SHIFT_S, TipLimits
from sim.effects import (
    ActuationLatency,
    Armature,
    Backlash,
    CoulombFriction,
    FloorSlope,
    FloorSoftness,
    FootFriction,
    FootPayload,
    FrictionCone,
    LinkMass,
    MotorStrength,
    ViscousFriction,
)

__all__ = ["SCENARIOS", "EpisodeResult", "PairedScenario", "Scenario", "compare",
           "load_results", "merge_results", "model_identity", "push_summary", "render_comparison",
           "render_markdown", "run_episode", "run_transfer", "summarise", "timed_run",
           "write_results"]

TIMESTEP_S = 0.001
"""The mock's physics step, s: the transfer check's default."""


@dataclass(frozen=True)
class Scenario:
    """Perturbations drawn per episode, each uniform in its (lo, hi) range; None leaves the
    simulator's own value.

    base_mass_add: kg on the base link, exactly, on either model (mass and inertia scaled;
    ``LinkMass(add_kg=)``). base_com_shift: +- m per axis of the base's centre of mass.
    friction: foot-floor sliding friction. motor_strength: scale of every motor's torque.
    latency_s: actuation latency, s. joint_friction: Coulomb friction, N m, on every joint.
    joint_damping: viscous friction, N m s/rad, and armature: rotor inertia, kg m^2, on every
    joint. noise_scale: times the training's observation noise (0: none). push_vel: m/s of the
    pushes (0: none), every 4-8 s. floor_slope: rad the floor is tilted, descending towards a
    direction drawn uniformly (the robot starts standing on it). floor_timeconst: s, the floor
    contacts' solref time constant (MuJoCo's default 0.02; larger: a floor that gives, the feet
    sinking into it). foot_payload: kg of a foot IMU node strapped to each foot, drawn per foot.
    backlash: rad, half the gear play of every joint, drawn per joint. imu_tilt_deg: the body
    IMU mounted turned from the base by this many degrees about an axis drawn uniformly;
    gyro_bias: rad/s, the body gyro's bias, uniform in +- per axis (both as the policy and the
    lifted leg's feed-forward sense the body, :class:`~policy_train.policy_motion.Disturbance`).
    friction_cone: the contacts' friction cone, ``"pyramidal"`` for MuJoCo's default
    (:class:`~sim.effects.FrictionCone`, impratio 1; None: the model's own).
    """

    name: str
    description: str
    base_mass_add: tuple[float, float] | None = None
    base_com_shift: tuple[float, float, float] | None = None
    friction: tuple[float, float] | None = None
    motor_strength: tuple[float, float] | None = None
    latency_s: tuple[float, float] | None = None
    joint_friction: tuple[float, float] | None = None
    joint_damping: tuple[float, float] | None = None
    armature: tuple[float, float] | None = None
    noise_scale: float = 0.0
    push_vel: float = 0.0
    floor_slope: tuple[float, float] | None = None
    floor_timeconst: tuple[float, float] | None = None
    foot_payload: tuple[float, float] | None = None
    backlash: tuple[float, float] | None = None
    imu_tilt_deg: tuple[float, float] | None = None
    gyro_bias: float = 0.0
    friction_cone: str | None = None

    def draw(self, rng: np.random.Generator):
        """This episode's effects (fresh :mod:`sim.effects` objects) and
        :class:`~policy_train.policy_motion.Disturbance` (seeded from ``rng``)."""
        from policy_train.config import OBS_NOISE, DRConfig
        from policy_train.policy_motion import Disturbance

        def u(r):
            return float(rng.uniform(*r))

        effects = []
        if self.base_mass_add is not None or self.base_com_shift is not None:
            add = u(self.base_mass_add) if self.base_mass_add is not None else 0.0
            c = np.asarray(self.base_com_shift if self.base_com_shift is not None else (0, 0, 0))
            effects.append(LinkMass(1.0, "base", rng.uniform(-c, c), add_kg=add))
        if self.friction is not None:
            effects.append(FootFriction(u(self.friction)))
        if self.motor_strength is not None:
            effects.append(MotorStrength(u(self.motor_strength)))
        if self.latency_s is not None:
            effects.append(ActuationLatency(u(self.latency_s)))
        if self.joint_friction is not None:
            effects.append(CoulombFriction(u(self.joint_friction)))
        if self.joint_damping is not None:
            effects.append(ViscousFriction(u(self.joint_damping)))
        if self.armature is not None:
            effects.append(Armature(u(self.armature)))
        if self.floor_slope is not None:
            effects.append(FloorSlope(u(self.floor_slope), rng.uniform(-math.pi, math.pi)))
        if self.floor_timeconst is not None:
            effects.append(FloorSoftness(u(self.floor_timeconst)))
        if self.foot_payload is not None:
            effects += [FootPayload(u(self.foot_payload), leg) for leg in LEGS]
        if self.friction_cone is not None:
            effects.append(FrictionCone(self.friction_cone))
        if self.backlash is not None:  # last: it follows the commands as the motors get them
            effects.append(Backlash(rng.uniform(*self.backlash, size=12)))
        imu = {}
        if self.imu_tilt_deg is not None:
            axis = rng.normal(size=3)
            angle = math.radians(u(self.imu_tilt_deg))
            imu["imu_tilt"] = tuple(axis / np.linalg.norm(axis) * angle)
        if self.gyro_bias:
            imu["gyro_bias"] = tuple(rng.uniform(-self.gyro_bias, self.gyro_bias, 3))
        dr = DRConfig()
        noise = {fld: self.noise_scale * getattr(dr, fld) for _, fld in OBS_NOISE}
        dist = Disturbance(**noise, push_vel=self.push_vel, push_interval=dr.push_interval,
                           seed=int(rng.integers(1 << 31)), **imu)
        return effects, dist


def _training_like(name: str, description: str, **changes) -> Scenario:
    from policy_train.config import DRConfig

    dr = DRConfig()
    base = Scenario(name, description, base_mass_add=dr.base_mass_add,
                    base_com_shift=dr.base_com_offset, friction=dr.friction,
                    motor_strength=(dr.kp_scale[0] * dr.motor_strength[0],
                                    dr.kp_scale[1] * dr.motor_strength[1]),
                    latency_s=(0.0, 0.005 * dr.latency_steps[1]), noise_scale=1.0,
                    push_vel=dr.push_vel)
    return dataclasses.replace(base, **changes)


SCENARIOS: dict[str, Scenario] = {s.name: s for s in [
    Scenario("nominal", "no perturbation"),
    _training_like("training", "the standard training ranges: base -1..+2 kg, CoM +-3/2/2 cm, friction "
                   "0.4-1.25, motors x0.77-1.27, latency 0-20 ms, pushes 0.3 m/s, sensor noise"),
    _training_like("heavy", "training, base payload +3..+5 kg", base_mass_add=(3.0, 5.0)),
    _training_like("slippery", "training, friction 0.25-0.4", friction=(0.25, 0.4)),
    _training_like("late", "training, latency 20-40 ms", latency_s=(0.02, 0.04)),
    _training_like("weak", "training, motors x0.65-0.8", motor_strength=(0.65, 0.8)),
    _training_like("joint_friction", "training, joint dry friction 0.2-0.6 N m added to the "
                   "model's own (none on the URDF's, 0.2 N m on Menagerie's: 0.4-0.8 there; not "
                   "in the standard ranges)",
                   joint_friction=(0.2, 0.6)),
    _training_like("shoves", "training, pushes 0.6 m/s", push_vel=0.6),
    _training_like("noisy", "training, twice the sensor noise", noise_scale=2.0),
    _training_like("quiet", "training without sensor noise", noise_scale=0.0),
    # appended last: a scenario's draws are seeded by its place in this list
    _training_like("damped_joints", "training on MuJoCo Menagerie's Go2 joints: damping 2 N m s/rad, "
                   "armature 0.01 kg m^2, dry friction 0.2 N m (none in the standard ranges)",
                   joint_damping=(2.0, 2.0), armature=(0.01, 0.01), joint_friction=(0.2, 0.2)),
    _training_like("slope", "training on a floor tilted 2-5 deg, downhill any way (not in the "
                   "standard ranges)", floor_slope=(math.radians(2.0), math.radians(5.0))),
    _training_like("soft_floor", "training on a floor that gives: contact time constant "
                   "0.03-0.045 s, feet sinking 4-11 mm standing (not in the standard ranges)",
                   floor_timeconst=(0.03, 0.045)),
    _training_like("foot_imus", "training with a foot IMU node of 30-80 g strapped to every foot "
                   "(the calf and foot weigh 194 g on the URDF's model; not in the standard "
                   "ranges)", foot_payload=(0.03, 0.08)),
    _training_like("backlash", "training with gear play of +-0.003-0.01 rad (0.3-1.1 deg in "
                   "all) on every joint, the encoders on the rotors (not in the standard "
                   "ranges)", backlash=(0.003, 0.01)),
    _training_like("body_imu", "training with the body IMU mounted 1-2 deg off about any axis "
                   "and a gyro bias of up to +-0.02 rad/s per axis (not in the standard ranges)",
                   imu_tilt_deg=(1.0, 2.0), gyro_bias=0.02),
    # a robot has all of these at once: each at the lower half of its own scenario's range,
    # the damping and armature as on Menagerie's joints (damped_joints: 2 and 0.01)
    _training_like("all_at_once", "training with every effect the standard ranges leave out, "
                   "each at the lower half of its own scenario's range, all at once: joint dry "
                   "friction 0.2-0.4 N m, damping 1-2 N m s/rad, armature 0.01 kg m^2, a floor "
                   "tilted 2-3.5 deg, foot IMU nodes of 30-55 g, gear play +-0.003-0.0065 rad, "
                   "the body IMU 1-1.5 deg off with a gyro bias up to +-0.01 rad/s",
                   joint_friction=(0.2, 0.4), joint_damping=(1.0, 2.0), armature=(0.01, 0.01),
                   floor_slope=(math.radians(2.0), math.radians(3.5)),
                   foot_payload=(0.03, 0.055), backlash=(0.003, 0.0065),
                   imu_tilt_deg=(1.0, 1.5), gyro_bias=0.01),
    # the joints of Unitree's own MuJoCo Go2 (unitree_rl_gym's sim-to-sim runner; unitree_mujoco's
    # carry damping 0.1 and dry friction 0.2): rotor inertia, next to no damping for the
    # integrator to take implicitly
    _training_like("rotor_joints", "training on the joints of Unitree's own MuJoCo Go2 "
                   "(unitree_rl_gym's sim-to-sim model): armature 0.01 kg m^2, damping 0.001 "
                   "N m s/rad, dry friction 0.1 N m (none in the standard ranges)",
                   joint_damping=(0.001, 0.001), armature=(0.01, 0.01),
                   joint_friction=(0.1, 0.1)),
    # MuJoCo's default contacts, which unitree_rl_gym's model and a plain URDF or MJCF load run
    # on: the URDF's model and Menagerie's use an elliptic cone with impratio 100
    _training_like("default_cone", "training on MuJoCo's default friction cone: pyramidal, "
                   "impratio 1 (the URDF's model and Menagerie's: elliptic, impratio 100; not "
                   "in the training)", friction_cone="pyramidal"),
    _training_like("weak_default_cone", "training, motors x0.65-0.8, on MuJoCo's default "
                   "friction cone (pyramidal, impratio 1)", motor_strength=(0.65, 0.8),
                   friction_cone="pyramidal"),
]}


@dataclass
class EpisodeResult:
    """One transfer episode. Figures over the excitation (NaN if it failed): tilt_rms_deg,
    rate_rms (rad/s), track_rmse (rad), cn. causes: what failed (empty on success).
    calf_reach_mm: for each leg whose calf touched the floor, the farthest such contact from its
    foot centre, mm (:class:`sim.free_base_run.RunHealth`). retried: why the tip guard called
    the first lift off, when the episode's figures and outcome are its second lift's.
    fall_time_s: s from the run's start to the fall (None: none). pushes: the shoves of the
    run that counts (:meth:`sim.free_base_run.PushRecord.to_dict`; the capture point's margin
    in the stance feet's polygon at each). lift_wait_s: s deploy's lift gate held the shift
    longer in the run that counts."""

    scenario: str
    leg: str
    episode: int
    success: bool
    causes: list[str] = field(default_factory=list)
    tilt_rms_deg: float = float("nan")
    rate_rms: float = float("nan")
    track_rmse: float = float("nan")
    cn: float = float("nan")
    calf_reach_mm: dict[str, float] = field(default_factory=dict)
    retried: str | None = None
    fall_time_s: float | None = None
    pushes: list[dict] = field(default_factory=list)
    lift_wait_s: float = 0.0


TOP_CAUSES = 6
"""Failure kinds shown per scenario on the page."""


def physics_rates(timestep: float, control_dt: float = 0.02) -> tuple[int, int]:
    """(command frames per policy tick, physics steps per recorded sample) at a physics step of
    ``timestep`` s under a ``control_dt`` s tick (the policy JSON's; 0.02 s, 50 Hz, for every
    policy so far). Deploy sends
    :data:`deploy.lift_schedule.COMMANDS_PER_TICK` frames a tick; a tick of fewer or other
    physics steps gets the most frames up to that which its steps divide into (4 at 5 ms, one a
    step). Samples are recorded at 500 Hz, or every step where the step is longer (the
    encoders' rate on the mock). ValueError where the step does not divide the tick."""
    from deploy.lift_schedule import COMMANDS_PER_TICK

    if not (math.isfinite(timestep) and 0.0 < timestep <= control_dt):
        raise ValueError(f"timestep must be in (0, {control_dt:g}] s, got {timestep!r}")
    n = round(control_dt / timestep)
    if abs(n * timestep - control_dt) > 1e-9:
        raise ValueError(f"timestep {timestep:g} s does not divide the policy's "
                         f"{control_dt:g} s tick")
    frames = max(k for k in range(1, COMMANDS_PER_TICK + 1) if n % k == 0)
    return frames, max(1, round(0.002 / timestep))


def _episode_seed(seed: int, scenario: str, leg: str, episode: int) -> np.random.Generator:
    key = [seed, list(SCENARIOS).index(scenario) if scenario in SCENARIOS else 99,
           LEGS.index(leg), episode]
    return np.random.default_rng(np.random.SeedSequence(key))


def run_episode(onnx_path: str, scenario: Scenario, leg: str, episode: int, seed: int = 1,
                periods: int | None = None, model_xml: str | None = None,
                max_tip=None, lift_gate=None, timestep: float = TIMESTEP_S) -> EpisodeResult:
    """One calibration of ``leg`` by the policy under ``scenario`` (its draws from ``seed``,
    the scenario, the leg and ``episode``). periods: None for the JSON's. model_xml: another
    MJCF model of the Go2 (:mod:`sim.external_model`; None: the URDF's). max_tip: deploy's
    tip guard with these limits (:class:`deploy.tip_guard.TipLimits`, a number or a (lift,
    hold) pair, deg; None: off, the policy alone). lift_gate: deploy's lift gate
    (:class:`deploy.lift_gate.GateLimits`, a margin in m or a (margin m, wait s) pair; None:
    off). A lift either calls off is lifted again as on board. timestep: the simulator's
    physics step, s (:func:`physics_rates`)."""
    from pathlib import Path

    from policy_train.policy_motion import run_policy_a2i

    control_dt = json.loads(Path(onnx_path).with_suffix(".json").read_text())["control_dt"]
    frames, record_every = physics_rates(timestep, float(control_dt))

    def attempt(extra_shift_s=0.0):
        effects, dist = scenario.draw(_episode_seed(seed, scenario.name, leg, episode))
        return run_policy_a2i(onnx_path, leg, periods=periods, effects=effects,
                              disturbance=dist, model_xml=model_xml,
                              max_tip=max_tip, lift_gate=lift_gate,
                              extra_shift_s=extra_shift_s, timestep=timestep,
                              record_every=record_every, commands_per_tick=frames)

    run, h = attempt()
    retried = None
    if h.aborted is not None and not h.fell:
        # deploy sits down, stands up and lifts the leg again with a longer shift: here from a
        # stand-up on the same draws (floor, masses, motors, pushes)
        retried = h.aborted
        run, h = attempt(RETRY_SHIFT_S)
    causes = []
    if h.aborted is not None:
        causes.append("lift called off (centre of mass)" if h.aborted.startswith(GATE_CAUSE)
                      else "lift called off (tipping)")
    if h.fell:
        causes.append("fall")
    if h.lifted_foot_touched:
        causes.append("lifted foot down")
    causes += [f"{b} on floor" for b in h.body_contacts if b != "base"]
    res = EpisodeResult(scenario.name, leg, episode, not causes, causes,
                        calf_reach_mm=dict(h.calf_reach_mm), retried=retried,
                        fall_time_s=h.fall_time_s if h.fell else None,
                        pushes=[p.to_dict() for p in h.pushes], lift_wait_s=h.lift_wait_s)
    if causes:
        return res
    ramp = 1.0  # the excitation's lead-in / lead-out (calib.excitation.ExcitationConfig.ramp)
    steady = (run.t >= run.t[0] + ramp) & (run.t <= run.t[-1] - ramp)
    track = run.tracking_rmse[model_indices(leg)]
    res.tilt_rms_deg = h.excite_tilt_rms_deg
    res.rate_rms = float(np.sqrt(np.mean(np.sum(run.base_gyro ** 2, axis=1))))
    res.track_rmse = float(np.sqrt(np.mean(track ** 2)))
    res.cn = float(condition_number(run.foot_omega[LEGS.index(leg)][steady]))
    return res


def _job(args) -> EpisodeResult:
    return run_episode(*args)


def model_identity(model_xml) -> dict | None:
    """{"path", "sha256", "mujoco"} of the model ``model_xml`` names as the simulator runs it
    (the hash of the compiled model, so that an included file or a changed adaptation changes
    it; "mujoco": the version that compiled it, since another MuJoCo saves the same model to
    other bytes); None for the URDF's. ValueError (one line) if the file cannot be made into a
    Go2 model."""
    import hashlib
    import tempfile
    from pathlib import Path

    if model_xml is None:
        return None
    import mujoco

    from sim.external_model import build_go2_spec_from_mjcf

    m = build_go2_spec_from_mjcf(model_xml).compile()
    with tempfile.TemporaryDirectory() as d:
        f = Path(d) / "model.mjb"
        mujoco.mj_saveModel(m, str(f), None)
        digest = hashlib.sha256(f.read_bytes()).hexdigest()
    return {"path": str(model_xml), "sha256": digest, "mujoco": mujoco.__version__}


def _saved_by(model: dict) -> str:
    """", MuJoCo X.Y.Z" for a :func:`model_identity` that records its MuJoCo; "" for one
    from a page written before the version was recorded."""
    return f", MuJoCo {model['mujoco']}" if "mujoco" in model else ""


def run_transfer(onnx_path, scenarios, legs=None, episodes: int = 25, seed: int = 1,
                 workers: int | None = None, periods: int | None = None,
                 progress=None, model_xml: str | None = None,
                 max_tip=None, lift_gate=None,
                 timestep: float = TIMESTEP_S) -> list[EpisodeResult]:
    """``episodes`` per leg of ``legs`` (default: the legs the policy's JSON lists) under each
    of ``scenarios`` (names of :data:`SCENARIOS`). workers: processes (None: all cores).
    progress(done, total): optional. model_xml: another MJCF model of the Go2 to run on
    (:mod:`sim.external_model`; None: the URDF's). max_tip, lift_gate: deploy's tip guard and
    lift gate, timestep: the physics step (s), as :func:`run_episode`."""
    from pathlib import Path

    max_tip = TipLimits.of(max_tip)  # a bad limit is refused before any worker starts
    lift_gate = GateLimits.of(lift_gate)
    if episodes < 1:
        raise ValueError(f"episodes must be >= 1, got {episodes}")
    unknown = [s for s in scenarios if s not in SCENARIOS]
    if unknown or not scenarios:
        raise ValueError(f"unknown scenario(s) {', '.join(unknown) or '(none given)'}; known: "
                         f"{', '.join(SCENARIOS)}")
    onnx_path = Path(onnx_path)
    meta = json.loads(onnx_path.with_suffix(".json").read_text())
    legs = [check_leg(g) for g in (legs or meta.get("legs", LEGS))]
    physics_rates(timestep, float(meta["control_dt"]))
    # a model or a scenario it cannot take is refused before any worker starts
    from sim.go2 import SimConfig, build_model_for

    model_identity(model_xml)
    for s in scenarios:
        effects, _ = SCENARIOS[s].draw(_episode_seed(seed, s, legs[0], 0))
        try:
            build_model_for(SimConfig(effects=effects, model_xml=model_xml, timestep=timestep))
        except ValueError as e:
            raise ValueError(f"scenario {s}: {str(e).splitlines()[0]}") from None
    jobs = [(str(onnx_path), SCENARIOS[s], leg, e, seed, periods, model_xml, max_tip,
             lift_gate, timestep) for s in scenarios for leg in legs for e in range(episodes)]
    out: list[EpisodeResult] = []
    with ProcessPoolExecutor(max_workers=workers or os.cpu_count() or 1) as pool:
        for i, r in enumerate(pool.map(_job, jobs), 1):
            out.append(r)
            if progress is not None:
                progress(i, len(jobs))
    return out


def _rms(xs) -> float:
    return float(np.sqrt(np.mean(np.square(xs)))) if len(xs) else float("nan")


def summarise(results: list[EpisodeResult]) -> dict:
    """{scenario: {"legs": {leg: success rate}, "success", "retried_held" (successes on a
    second lift), "tilt_rms_deg", "rate_rms",
    "track_rmse", "cn_median", "cn_p90", "causes": {cause: episodes}, "calf_reach_mm":
    {cause: mm}}}; pooled over legs, the figures over the successful episodes (RMS figures
    pooled as RMS); calf_reach_mm: for each calf cause, the farthest from its foot centre that
    calf touched, over the episodes that recorded it."""
    out = {}
    for s in dict.fromkeys(r.scenario for r in results):
        rs = [r for r in results if r.scenario == s]
        ok = [r for r in rs if r.success]
        causes: dict[str, int] = {}
        reach: dict[str, float] = {}
        for r in rs:
            for c in r.causes:
                causes[c] = causes.get(c, 0) + 1
            for g, mm in r.calf_reach_mm.items():
                c = f"{g}_calf on floor"
                reach[c] = max(reach.get(c, 0.0), mm)
        cn = [r.cn for r in ok]
        out[s] = {
            "legs": {g: float(np.mean([r.success for r in rs if r.leg == g]))
                     for g in dict.fromkeys(r.leg for r in rs)},
            "episodes": len(rs),
            "success": float(np.mean([r.success for r in rs])),
            "retried_held": sum(bool(r.success and r.retried) for r in rs),
            "tilt_rms_deg": _rms([r.tilt_rms_deg for r in ok]),
            "rate_rms": _rms([r.rate_rms for r in ok]),
            "track_rmse": _rms([r.track_rmse for r in ok]),
            "cn_median": float(np.median(cn)) if cn else float("nan"),
            "cn_p90": float(np.percentile(cn, 90)) if cn else float("nan"),
            "causes": dict(sorted(causes.items(), key=lambda kv: -kv[1])),
            "calf_reach_mm": reach,
        }
    return out


FALL_AFTER_PUSH_S = 1.5
"""s: a fall this soon after a push is put down to it (v28's shove falls on Menagerie's model
tipped past the fall threshold 0.65-0.75 s after the push)."""

TRIPOD_PHASES = ("lift", "hold", "excite", "lower")
"""The schedule's phases on three feet."""


def push_summary(results: list[EpisodeResult]) -> dict:
    """{scenario: {"pushes", "outside", "outside_fell", "falls", "falls_outside",
    "falls_inside", "falls_unpushed", "held_min_cm"}} over the scenarios whose episodes
    recorded pushes: the pushes given on three feet, how many put the capture point outside
    the stance feet's triangle (and of those, how many a fall followed within
    :data:`FALL_AFTER_PUSH_S`), the episodes that fell, split by the last push within that
    time before the fall (outside, inside, none: a push that met the centre of mass already
    outside counts as none), and the lowest capture margin, cm, of a push on three feet that
    no fall followed. Pushes after a fall are left out."""
    out = {}
    for s in dict.fromkeys(r.scenario for r in results):
        rs = [r for r in results if r.scenario == s]
        if not any(r.pushes for r in rs):
            continue
        x = {"pushes": 0, "outside": 0, "outside_fell": 0, "falls": 0, "falls_outside": 0,
             "falls_inside": 0, "falls_unpushed": 0, "held_min_cm": float("nan")}
        held = []
        for r in rs:
            ft = r.fall_time_s
            for p in r.pushes:
                if p["phase"] not in TRIPOD_PHASES or (ft is not None and p["t_s"] > ft):
                    continue  # a push given to a robot on the floor says nothing
                followed = ft is not None and ft - p["t_s"] <= FALL_AFTER_PUSH_S
                x["pushes"] += 1
                if p["capture_margin_m"] < 0:
                    x["outside"] += 1
                    x["outside_fell"] += followed
                if not followed:
                    held.append(p["capture_margin_m"])
            if ft is not None:
                x["falls"] += 1
                # a push that met the centre of mass already past an edge did not start it
                before = [p for p in r.pushes if 0 <= ft - p["t_s"] <= FALL_AFTER_PUSH_S
                          and p["com_margin_m"] >= 0]
                if not before:
                    x["falls_unpushed"] += 1
                elif before[-1]["capture_margin_m"] < 0:
                    x["falls_outside"] += 1
                else:
                    x["falls_inside"] += 1
        if held:
            x["held_min_cm"] = 100 * min(held)
        out[s] = x
    return out


def render_markdown(results: list[EpisodeResult], policy: str, seed: int,
                    elapsed_s: float | None = None, model: dict | None = None,
                    max_tip=None, lift_gate=None, timestep: float = TIMESTEP_S) -> str:
    """The page of ``a2i-train transfer`` (one row per scenario); model: the
    :func:`model_identity` of the model it ran on (None: the URDF's); max_tip, lift_gate: the
    tip guard's limits and the lift gate it ran with (:class:`deploy.tip_guard.TipLimits`,
    :class:`deploy.lift_gate.GateLimits`; None: off); timestep: its physics step, s."""
    max_tip = TipLimits.of(max_tip)
    lift_gate = GateLimits.of(lift_gate)
    summ = summarise(results)
    legs = list(dict.fromkeys(r.leg for r in results))
    n = max(1, len(results) // max(1, len(summ) * len(legs)))
    leg_arg = "" if legs == list(LEGS) else f" --legs {','.join(legs)}"
    # a run of some scenarios only names them: the line then re-runs what the page holds
    scen_arg = "" if list(summ) == list(SCENARIOS) else f" --scenarios {','.join(summ)}"
    model_arg = "" if model is None else f" --model-xml {model['path']}"
    tip_arg = "" if max_tip is None else f" --max-tip {max_tip}"
    gate_arg = "" if lift_gate is None else f" --lift-gate {lift_gate}"
    step_arg = "" if timestep == TIMESTEP_S else f" --timestep {timestep:g}"
    rate = ("1 kHz" if timestep == TIMESTEP_S else
            f"{1.0 / timestep:g} Hz, the motor PD law computed explicitly every step")
    limits = (None if max_tip is None else f"{max_tip.lift:g} deg" if max_tip.lift == max_tip.hold
              else f"{max_tip.lift:g} deg lifting, {max_tip.hold:g} deg holding")
    guard = ("the policy alone (deploy's tip guard, `deploy/tip_guard.py`, off)"
             if max_tip is None and lift_gate is None else
             "deploy's tip guard (`deploy/tip_guard.py`) off" if max_tip is None else
             f"deploy's tip guard at {limits} (`deploy/tip_guard.py`), as on board: "
             "a lift it calls off is lifted again with a longer shift, from a stand-up on the "
             "same draws (success in brackets: held on that second lift), and a second lift "
             "called off fails")
    if lift_gate is not None:
        held = sum(r.lift_wait_s > 0 for r in results)
        guard += (f"; deploy's lift gate (`deploy/lift_gate.py`): the foot leaves the floor once "
                  f"the centre of mass, estimated from the joints and the body IMU, stands "
                  f"{lift_gate.margin_m * 1e3:g} mm inside the stance triangle, the shift held "
                  f"up to {lift_gate.wait_s:g} s longer for it (held longer in {held} of "
                  f"{len(results)} episodes; a lift it calls off is lifted again as the tip "
                  "guard's)")
    on_model = ("the Go2 model built from the URDF" if model is None else
                f"the Go2 model of `{model['path']}` (compiled as the simulator runs it: sha256 "
                f"{model['sha256'][:16]}{_saved_by(model)}; `sim/external_model.py`) instead of "
                "the URDF's")
    lines = [
        "# Tripod policy transfer: a second simulator, perturbations not trained for",
        "",
        (f"Produced by `a2i-train transfer {policy}{scen_arg} --episodes {n} --seed {seed}"
        f"{leg_arg}{model_arg}{tip_arg}{gate_arg}{step_arg}` (`policy_train/transfer.py`): each "
        f"episode is one calibration of one leg by the on-board runner on `sim.go2` ({rate}, "
        "free base on the floor: the mock "
        f"robot's simulator, not the training environment) with {on_model}, and the "
        "scenario's perturbations drawn afresh. Success: no fall and no body but a foot on the "
        "floor over the whole run, and the lifted foot never down over hold and excitation; "
        f"{guard}. Figures over "
        "the excitation of the successful episodes, "
        "pooled over legs; the evaluation's targets: success 99 %, tilt 3 deg, rate 0.1 rad/s, "
        "tracking 0.05 rad, CN 1.2. Failures: in how many episodes each thing happened (an "
        "episode that tips over counts a fall and every body that touched the floor; the "
        f"commonest {TOP_CAUSES}; the `.json` beside this page has every episode). A calf's "
        "figure in brackets, where recorded: the farthest from its foot centre that it touched, "
        "mm (up to 30 mm is the calf's lower end, which wraps the top of the foot; the knee is "
        "213 mm up)."),
        "",
        (f"| scenario | what | episodes | success | {' / '.join(legs)} | tilt RMS deg | "
         "rate RMS rad/s | tracking rad | CN median (p90) | failures |"),
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for s, x in summ.items():
        per_leg = " / ".join(f"{100 * x['legs'].get(g, float('nan')):.0f}" for g in legs)
        top = list(x["causes"].items())[:TOP_CAUSES]
        causes = ", ".join(f"{c} {k}" + (f" ({x['calf_reach_mm'][c]:.0f} mm)"
                                         if c in x["calf_reach_mm"] else "")
                           for c, k in top) or "-"
        if len(x["causes"]) > TOP_CAUSES:
            causes += ", ..."
        retry = f" ({x['retried_held']} on a 2nd lift)" if x["retried_held"] else ""
        lines.append(
            f"| {s} | {SCENARIOS[s].description} | {x['episodes']} | "
            f"{100 * x['success']:.0f} %{retry} | {per_leg} % | {x['tilt_rms_deg']:.2f} | "
            f"{x['rate_rms']:.3f} | {x['track_rmse']:.3f} | {x['cn_median']:.3f} "
            f"({x['cn_p90']:.3f}) | {causes} |")
    pushes = push_summary(results)
    if pushes:
        lines += [
            "",
            ("**Pushes on three feet and the tripod's capture region.** A push's capture point "
            "is where the whole robot's centre of mass would have to stand over to stop, "
            "`c + v / sqrt(g / h)` just after the push (a linear inverted pendulum of its height "
            "h over the soles); on point feet a push that puts it outside the triangle of the "
            "three stance feet cannot be held without a step, which the lifted leg must not "
            "take (`sim.free_base_run.PushRecord`). Counted: the pushes from the lift to the "
            "end of the lowering; a fall within "
            f"{FALL_AFTER_PUSH_S:g} s of a push is put down to it, unless the centre of mass "
            "itself was already outside the triangle at the push (no push, then); held: the "
            "lowest capture margin of a push no fall followed (< 0: outside, held all the "
            "same)."),
            "",
            ("| scenario | pushes on three feet | capture point outside (a fall followed) | "
             "falls: after a push outside / inside / no push | lowest margin held, cm |"),
            "|---|---|---|---|---|",
        ]
        for s, x in pushes.items():
            lines.append(
                f"| {s} | {x['pushes']} | {x['outside']} ({x['outside_fell']}) | "
                f"{x['falls_outside']} / {x['falls_inside']} / {x['falls_unpushed']} | "
                f"{x['held_min_cm']:.1f} |")
    if elapsed_s is not None:
        lines += ["", f"Wall time: {elapsed_s:.0f} s."]
    return "\n".join(lines) + "\n"


def write_results(results: list[EpisodeResult], out_md, policy: str, seed: int,
                  elapsed_s: float | None = None, model: dict | None = None,
                  max_tip=None, lift_gate=None, timestep: float = TIMESTEP_S) -> None:
    """The markdown page at ``out_md`` and the episodes beside it (``.json``), atomically;
    model: the :func:`model_identity` of the model it ran on (None: the URDF's); timestep: its
    physics step, s."""
    from pathlib import Path

    out_md = Path(out_md)
    max_tip = TipLimits.of(max_tip)
    lift_gate = GateLimits.of(lift_gate)
    write_text_atomic(out_md, render_markdown(results, policy, seed, elapsed_s, model, max_tip,
                                              lift_gate, timestep))
    # one episode per line: a few hundred short rows stay small and diff well
    meta = {"policy": policy, "seed": seed, "elapsed_s": elapsed_s}
    if model is not None:  # pages on the URDF's model keep their earlier form
        meta["model"] = model
    if max_tip is not None:  # and those of the policy alone theirs
        meta["max_tip_deg"] = max_tip.to_json()
    if lift_gate is not None:
        meta["lift_gate"] = lift_gate.to_json()
    if timestep != TIMESTEP_S:  # and those at the mock's 1 kHz theirs
        meta["timestep_s"] = timestep
    head = json.dumps(meta)[:-1]
    rows = ",\n".join(json.dumps(dataclasses.asdict(r)) for r in results)
    write_text_atomic(out_md.with_suffix(".json"), f'{head}, "episodes": [\n{rows}\n]}}\n')


def timed_run(onnx_path, scenarios, legs, episodes, seed, workers, periods=None, log=print,
              model_xml=None, max_tip=None, lift_gate=None, timestep=TIMESTEP_S):
    """:func:`run_transfer` with a progress line every 10 % or every minute, whichever
    comes first, and the time left at the rate so far (for the CLI)."""
    t0 = time.time()
    last = [0.0, t0]  # fraction done and time at the last line

    def progress(done, total):
        now = time.time()
        # on a slow machine 10 % of a long run is many minutes: a silent run looks hung
        if done == total or done / total - last[0] >= 0.1 or now - last[1] >= 60.0:
            last[:] = [done / total, now]
            left = "" if done in (0, total) else \
                f", about {(now - t0) * (total - done) / done:.0f} s left"
            log(f"  {done}/{total} episodes, {now - t0:.0f} s{left}")

    res = run_transfer(onnx_path, scenarios, legs, episodes, seed, workers, periods, progress,
                       model_xml, max_tip, lift_gate, timestep)
    return res, time.time() - t0


def load_results(path) -> tuple[dict, list[EpisodeResult]]:
    """The episodes file :func:`write_results` wrote: ({"policy", "seed", "elapsed_s",
    "model", "max_tip", "lift_gate", "timestep"}, episodes); "model" None for the URDF's,
    "max_tip" (a :class:`deploy.tip_guard.TipLimits`) and "lift_gate" (a
    :class:`deploy.lift_gate.GateLimits`) None for the policy alone, "timestep" the physics
    step, s."""
    from pathlib import Path

    try:
        d = json.loads(Path(path).read_text())
        eps = [EpisodeResult(**e) for e in d["episodes"]]
        meta = {k: d[k] for k in ("policy", "seed", "elapsed_s")}
        meta["model"] = d.get("model")
        meta["max_tip"] = TipLimits.of(d.get("max_tip_deg"))
        meta["lift_gate"] = GateLimits.of(d.get("lift_gate"))
        meta["timestep"] = float(d.get("timestep_s", TIMESTEP_S))
    except (KeyError, TypeError, ValueError) as e:
        raise ValueError(f"{path}: not a transfer episodes file ({e})") from None
    return meta, eps


def merge_results(page: tuple[dict, list[EpisodeResult]], new: list[EpisodeResult],
                  policy: str, seed: int, legs, episodes: int,
                  model: dict | None = None,
                  max_tip=None, lift_gate=None,
                  timestep: float = TIMESTEP_S) -> list[EpisodeResult]:
    """A page's episodes (:func:`load_results`) with ``new``'s scenarios added or replaced, in
    :data:`SCENARIOS`' order: the page one command over every scenario would have written, since
    an episode's draws depend only on the seed, its scenario, leg and number. ValueError unless
    the page has this policy, seed, legs, episodes per leg and scenario, model
    (:func:`model_identity`, compared by its hash), tip guard, lift gate and physics step."""
    meta, old = page
    old_legs = list(dict.fromkeys(r.leg for r in old))
    per = {(r.scenario, r.leg) for r in old}
    old_n = len(old) // max(1, len(per))

    def _model(m):
        return "the URDF's" if m is None else f"{m['path']} ({m['sha256'][:16]}{_saved_by(m)})"

    old_model, new_model = meta.get("model"), model
    same_model = (old_model is None) == (new_model is None) and (
        old_model is None or old_model["sha256"] == new_model["sha256"])
    for what, was, now in (("policy", meta["policy"], policy), ("seed", meta["seed"], seed),
                           ("legs", ",".join(old_legs), ",".join(legs)),
                           ("episodes", old_n, episodes),
                           ("model", _model(old_model),
                            _model(old_model) if same_model else _model(new_model)),
                           ("tip guard", meta.get("max_tip"), TipLimits.of(max_tip)),
                           ("lift gate", meta.get("lift_gate"), GateLimits.of(lift_gate)),
                           ("physics step (s)", meta.get("timestep", TIMESTEP_S),
                            float(timestep))):
        if was != now:
            raise ValueError(f"the page has {what} {was}, not {now}: write a new page")
    redone = {r.scenario for r in new}
    order = {name: i for i, name in enumerate(SCENARIOS)}
    kept = [r for r in old if r.scenario not in redone]
    return sorted(kept + list(new), key=lambda r: order.get(r.scenario, len(order)))


@dataclass(frozen=True)
class PairedScenario:
    """Two policies on the same draws of one scenario. pairs: episodes both ran; both / only_a
    / only_b / neither: how many of them each held; p: the exact two-sided sign test (McNemar)
    of only_a against only_b, the chance of a split at least this uneven if the two were
    equally good."""

    scenario: str
    pairs: int
    both: int
    only_a: int
    only_b: int
    neither: int

    @property
    def success_a(self) -> float:
        return (self.both + self.only_a) / self.pairs

    @property
    def success_b(self) -> float:
        return (self.both + self.only_b) / self.pairs

    @property
    def p(self) -> float:
        n, k = self.only_a + self.only_b, min(self.only_a, self.only_b)
        return min(1.0, 2 * sum(math.comb(n, i) for i in range(k + 1)) / 2 ** n) if n else 1.0


def compare(a: list[EpisodeResult], b: list[EpisodeResult]) -> list[PairedScenario]:
    """Pair two transfer runs episode by episode (scenario, leg, episode index: the same draws
    when both ran with the same seed), per scenario in ``a``'s order and then over all
    (scenario "all"). Raises ValueError if they share no episode."""
    held_b = {(r.scenario, r.leg, r.episode): r.success for r in b}
    pairs = [(r.scenario, r.success, held_b[k]) for r in a
             if (k := (r.scenario, r.leg, r.episode)) in held_b]
    if not pairs:
        raise ValueError("the two runs share no episode (scenario, leg, episode)")

    def tally(name, rows):
        n = [sum(1 for _, x, y in rows if (x, y) == c)
             for c in ((True, True), (True, False), (False, True), (False, False))]
        return PairedScenario(name, len(rows), *n)

    out = [tally(s, [p for p in pairs if p[0] == s]) for s in dict.fromkeys(p[0] for p in pairs)]
    return out + [tally("all", pairs)]


def render_comparison(rows: list[PairedScenario], name_a: str, name_b: str) -> str:
    """The table ``a2i-train compare`` prints (markdown)."""
    head = (f"| scenario | pairs | {name_a} | {name_b} | held by both / only {name_a} / only "
            f"{name_b} / neither | sign test p |")
    lines = [head, "|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r.scenario} | {r.pairs} | {100 * r.success_a:.0f} % | "
                     f"{100 * r.success_b:.0f} % | {r.both} / {r.only_a} / {r.only_b} / "
                     f"{r.neither} | {r.p:.2g} |")
    return "\n".join(lines) + "\n"
