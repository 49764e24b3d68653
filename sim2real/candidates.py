"""Candidate unmodelled effects as parameterised changes of ``sim`` (the fitting view of
:mod:`sim.effects`).

A :class:`Candidate` is one effect name at one location with its free parameters, bounds and a
builder ``build(x) -> [Effect]``. Locations: a joint name (SDK spelling ``FR_calf``), ``all``,
``base``, ``feet`` or ``base_imu``. IMU candidates are fitted in closed form by
:mod:`sim2real.diagnose` and only carry a builder for replays and reports.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from calib.joints import EFFORT_LIMIT
from sim import effects as fx

__all__ = ["Candidate", "dynamic_candidates", "imu_candidates"]


@dataclass
class Candidate:
    """name: library effect name; location: where; params: parameter names (units in
    :data:`UNITS`); lo, hi: bounds; build(x) -> list of effects; imu: fitted in closed form;
    grid: parameter step for a grid search (a parameter only resolved to a grid, e.g. the
    physics step for latency), else None."""

    name: str
    location: str
    params: tuple[str, ...]
    lo: np.ndarray
    hi: np.ndarray
    build: Callable[[np.ndarray], list]
    nominal: np.ndarray
    imu: bool = False
    grid: float | None = None
    spec: bool = False  # changes the compiled model (no model cache across parameter values)
    log: bool = False  # coarse grid spaced logarithmically (a parameter known to a factor)
    hints: tuple[float, ...] = ()  # extra coarse-grid values read off the recording

    @property
    def key(self) -> str:
        return f"{self.name}@{self.location}"


UNITS = {
    "seconds": "s", "scale": "", "torque": "N m", "coefficient": "N m s/rad",
    "inertia": "kg m^2", "half_width": "rad", "limit": "N m", "mu": "",
    "probability": "", "gyro_bias_x": "rad/s", "gyro_bias_y": "rad/s", "gyro_bias_z": "rad/s",
    "rot_x": "rad", "rot_y": "rad", "rot_z": "rad", "gyro_scale": "",
}


def _joints(location: str):
    return None if location == "all" else [location]


def _effort(location: str) -> float:
    if location == "all":
        return float(EFFORT_LIMIT.max())
    return float(EFFORT_LIMIT[["hip", "thigh", "calf"].index(location.split("_")[1])])


def dynamic_candidates(location: str, mount: str, peak_torque: float | None = None,
                       plateau: float | None = None) -> list[Candidate]:
    """The dynamic candidates that make sense at ``location`` (a joint name or ``"all"``).

    peak_torque: the largest torque (N m) the joint at ``location`` is seen to need in the
    recording; a torque limit is searched below 1.2 times it (above, it never binds and the
    cost is flat), else up to the effort limit, on a logarithmic grid (a binding limit can be
    a tenth of the demand). plateau: the largest estimated torque (N m) the motor is recorded
    to deliver (``tau_*``), tried as a limit (a saturating motor plateaus there).

    Link masses are tried on the located joint's link and on the links it carries (thigh,
    calf of the same leg): a heavier thigh loads the hip joint most."""
    a = np.array
    j = _joints(location)
    out = [
        Candidate("motor_strength", location, ("scale",), a([0.3]), a([2.0]),
                  lambda x: [fx.MotorStrength(x[0], joints=j)], a([1.0])),
        Candidate("coulomb_friction", location, ("torque",), a([0.0]), a([3.0]),
                  lambda x: [fx.CoulombFriction(x[0], joints=j)], a([0.0]), spec=True),
        Candidate("viscous_friction", location, ("coefficient",), a([0.0]), a([2.0]),
                  lambda x: [fx.ViscousFriction(x[0], joints=j)], a([0.0]), spec=True),
        Candidate("armature", location, ("inertia",), a([0.0]), a([0.08]),
                  lambda x: [fx.Armature(x[0], joints=j)], a([0.0]), spec=True),
    ]
    if location == "all":
        out.insert(0, Candidate("latency", "all", ("seconds",), a([0.0]), a([0.06]),
                                lambda x: [fx.ActuationLatency(x[0])], a([0.0]), grid=0.001))
        if mount == "ground":
            out.append(Candidate("link_mass", "base", ("scale",), a([0.5]), a([2.0]),
                                 lambda x: [fx.LinkMass(x[0], "base")], a([1.0]), spec=True))
            out.append(Candidate("foot_friction", "feet", ("mu",), a([0.05]), a([1.5]),
                                 lambda x: [fx.FootFriction(x[0])], a([0.8]), spec=True))
    else:
        if mount == "ground":
            # standing, the contacts carry most of any torque residual to the calves: a gap
            # that looks local there may still be a command latency of every motor
            out.insert(0, Candidate("latency", "all", ("seconds",), a([0.0]), a([0.06]),
                                    lambda x: [fx.ActuationLatency(x[0])], a([0.0]),
                                    grid=0.001))
        lim = _effort(location)
        if peak_torque is not None and np.isfinite(peak_torque) and peak_torque > 0:
            lim = min(lim, 1.2 * float(peak_torque))
        lo_lim = min(0.3, 0.05 * lim)
        hints = ()
        if plateau is not None and np.isfinite(plateau) and lo_lim < plateau < lim:
            hints = (float(plateau),)
        out += [
            Candidate("backlash", location, ("half_width",), a([0.0]), a([0.08]),
                      lambda x: [fx.Backlash(x[0], joints=j)], a([0.0])),
            Candidate("torque_limit", location, ("limit",), a([lo_lim]), a([lim]),
                      lambda x: [fx.TorqueLimit(x[0], joints=j)], a([lim]), log=True,
                      hints=hints),
        ]
        leg, joint = location.split("_")
        links = [location] + [f"{leg}_{c}" for c in ("thigh", "calf")
                              if ("hip", "thigh", "calf").index(c)
                              > ("hip", "thigh", "calf").index(joint)]
        out += [Candidate("link_mass", link, ("scale",), a([0.2]), a([5.0]),
                          lambda x, lk=link: [fx.LinkMass(x[0], lk)], a([1.0]),
                          spec=True) for link in links]
    return out


def imu_candidates() -> list[Candidate]:
    a = np.array
    z3 = np.zeros(3)
    return [
        Candidate("imu_bias", "base_imu", ("gyro_bias_x", "gyro_bias_y", "gyro_bias_z"),
                  a([-1.0] * 3), a([1.0] * 3), lambda x: [fx.ImuBias(x[:3])], z3, imu=True),
        Candidate("imu_misalignment", "base_imu", ("rot_x", "rot_y", "rot_z", "gyro_scale"),
                  a([-0.5, -0.5, -0.5, 0.5]), a([0.5, 0.5, 0.5, 2.0]),
                  lambda x: [fx.ImuMisalignment(x[:3], x[3])], a([0.0, 0.0, 0.0, 1.0]),
                  imu=True),
        Candidate("imu_time_offset", "base_imu", ("seconds",), a([-0.1]), a([0.1]),
                  lambda x: [fx.ImuTimeOffset(x[0])], a([0.0]), imu=True),
    ]

