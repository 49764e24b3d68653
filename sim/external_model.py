"""The Go2 from another MJCF file, made into the model :class:`sim.go2.Go2Sim` drives.

A sim-to-sim check: the policy, the mock robot or the transfer check run on someone else's
model of the robot (MuJoCo Menagerie's ``unitree_go2``, or a checker's own) instead of the one
:mod:`sim.model` builds from the URDF, so that what they measure does not rest on our geometry,
masses, joint model or contact settings.

Kept from the file: bodies, inertias, joints (damping, armature, dry friction, limits),
collision geoms with their contact settings (``solref``, ``solimp``, ``priority``, ``condim``,
friction, margin), the options (integrator, cone, ``impratio``), and its floor where it has a
world geom named ``floor`` (Menagerie's ``scene.xml``).

Replaced or added, so that ``Go2Sim`` finds what it reads:

* the timestep (the caller's: ``Go2Sim`` computes the motor PD law every physics step);
* the free joint on ``base`` is named ``base_free`` (``"fixed"``: removed, the base placed);
* actuators: the file's are removed and torque motors added in model order with the effort
  limits, as :func:`sim.model.build_go2_spec` does (``Go2Sim`` writes torques);
* the feet: each calf's collision sphere nearest the URDF foot frame (0.213 m down the calf)
  is named ``<LEG>_foot``, and the sites ``<LEG>_foot`` / ``<LEG>_imu`` are put at that frame;
* the body IMU site ``imu`` on ``base`` where the file has none (at the URDF's offset);
* sensors: the file's are removed, and the body and foot IMUs' gyros and accelerometers added;
* keyframes are removed (their sizes no longer match), and so are geoms that collide with
  nothing and show a mesh (visual meshes, whose files a checker's copy may not carry; only on
  bodies with an explicit ``<inertial>``, whose mass they therefore do not carry);
* a floor (:func:`sim.model.build_go2_spec`'s) where the file has none and one is asked for.
"""

from __future__ import annotations

from pathlib import Path

import mujoco
import numpy as np

from calib.joints import MODEL_LEGS
from sim.model import BASE_MODES, FIXED_BASE_POS, FOOT_OFFSET, add_sim_parts, joint_names

__all__ = ["FOOT_MATCH_TOL", "build_go2_spec_from_mjcf"]

FOOT_MATCH_TOL = 0.01
"""m: how far from the URDF foot frame a calf's collision sphere may sit to be taken for the
foot (Menagerie's are 2 mm behind it); farther, the calibration's foot kinematics would not hold."""


def _fail(path: Path, why: str):
    raise ValueError(f"{path}: {why}")


def build_go2_spec_from_mjcf(
    path,
    base: str = "free",
    floor: bool = True,
    timestep: float = 0.001,
    fixed_base_pos: tuple[float, float, float] = FIXED_BASE_POS,
) -> mujoco.MjSpec:
    """The Go2 of the MJCF at ``path`` as :func:`sim.model.build_go2_spec` would give it (same
    arguments; see the module docstring for what is kept and what replaced). ValueError (one
    line, naming the file) when the file is missing or malformed, or lacks what the simulator
    needs: the Unitree joint names in model order (FL, FR, RL, RR x hip, thigh, calf), a body
    ``base``, a body ``<LEG>_calf`` with a collision sphere at its foot."""
    path = Path(path)
    if base not in BASE_MODES:
        raise ValueError(f"unknown base mode {base!r}: expected one of {', '.join(BASE_MODES)}")
    if not (np.isfinite(timestep) and 0.0 < timestep <= 0.05):
        raise ValueError(f"timestep must be in (0, 0.05] s, got {timestep!r}")
    if not path.is_file():
        raise ValueError(f"model file not found: {path}")
    try:
        spec = mujoco.MjSpec.from_file(str(path))
    except ValueError as e:  # MuJoCo's parse errors run over several lines: keep the first
        _fail(path, f"not a MuJoCo model ({(str(e).splitlines() or ['?'])[0]})")
    spec.option.timestep = float(timestep)

    base_body = spec.body("base")
    if base_body is None:
        _fail(path, "no body named 'base'")
    names = [j.name for j in spec.joints if j.type == mujoco.mjtJoint.mjJNT_HINGE]
    if tuple(names) != joint_names():
        _fail(path, f"hinge joints {names} are not the Go2's in model order ({', '.join(joint_names())})")
    free = [j for j in spec.joints if j.type == mujoco.mjtJoint.mjJNT_FREE]
    if len(free) > 1 or (free and free[0].parent.name != "base"):
        _fail(path, "a free joint on a body other than 'base'")
    if base in ("free", "mocap"):
        if free:
            free[0].name = "base_free"
        else:
            base_body.add_freejoint(name="base_free")
    else:
        for j in free:
            spec.delete(j)
        base_body.pos = np.asarray(fixed_base_pos, dtype=float)
        for leg in MODEL_LEGS:  # as build_go2_spec: welded to the world, no parent/child filter
            spec.add_exclude(bodyname1="base", bodyname2=f"{leg}_hip")

    for g in list(spec.geoms):
        if g.type == mujoco.mjtGeom.mjGEOM_MESH and g.contype == 0 and g.conaffinity == 0:
            if not g.parent.explicitinertial:
                _fail(path, f"body {g.parent.name!r} takes its inertia from its geoms: give it an "
                            "<inertial> so that its visual meshes can be dropped")
            spec.delete(g)
    used = {g.meshname for g in spec.geoms if g.type == mujoco.mjtGeom.mjGEOM_MESH}
    for m in list(spec.meshes):
        if m.name not in used:
            spec.delete(m)
    for e in list(spec.actuators) + list(spec.sensors) + list(spec.keys):
        spec.delete(e)

    for leg in MODEL_LEGS:
        calf = spec.body(f"{leg}_calf")
        if calf is None:
            _fail(path, f"no body named '{leg}_calf'")
        spheres = [g for g in calf.geoms if g.type == mujoco.mjtGeom.mjGEOM_SPHERE
                   and (g.contype or g.conaffinity)]
        off = [float(np.linalg.norm(np.asarray(g.pos) - FOOT_OFFSET)) for g in spheres]
        if not spheres or min(off) > FOOT_MATCH_TOL:
            _fail(path, f"'{leg}_calf' has no collision sphere within {FOOT_MATCH_TOL * 1000:.0f} mm "
                        f"of its foot frame {tuple(FOOT_OFFSET)} m")
        spheres[int(np.argmin(off))].name = f"{leg}_foot"
        for s in list(calf.sites):
            if s.name in (f"{leg}_foot", f"{leg}_imu"):
                spec.delete(s)
        calf.add_site(name=f"{leg}_foot", pos=FOOT_OFFSET, size=[0.005, 0, 0])
        calf.add_site(name=f"{leg}_imu", pos=FOOT_OFFSET, size=[0.005, 0, 0])

    add_sim_parts(spec, base_body, floor)
    return spec
