"""The MuJoCo model of the Go2, built from the example-robot-data URDF.

What the URDF alone does not give MuJoCo 4.0 (FACTS.md, "Measured here"):

* meshes: ``strippath`` plus ``meshdir`` = the collision folder (the .dae visuals do not load);
* a floor, and a free joint on ``base`` (without a joint the base is fused into the world);
* contact excludes ``base`` <-> each thigh (otherwise the front legs jam on the body), and
  ``base`` <-> each hip (parent/child, but MuJoCo stops filtering those once the base is welded
  to the world, as with ``base="fixed"``: the rear hip meshes would then touch the base);
* elliptic friction cones with ``impratio`` 100 (no slow sideways creep of a standing robot);
* sites for the fixed links that the compiler fuses away: ``<LEG>_foot`` and ``<LEG>_imu`` on
  the calf, 0.213 m down the calf with the calf's orientation (the URDF ``<LEG>_foot`` frame),
  and ``imu`` on the base at (-0.02557, 0, 0.04232) (the URDF ``imu`` link, unrotated);
* a sphere (radius :data:`FOOT_RADIUS`) at each foot site replaces the URDF foot mesh for
  contact: one smooth contact point per foot instead of a handful of mesh vertices (the mesh's
  lowest point sits 0.236 m down the calf, the sphere's 0.235 m);
* torque (``motor``) actuators, gear 1, ``ctrlrange`` = effort limits: the PD law is computed by
  :mod:`sim.go2` every physics step, not by MuJoCo.

Sensors compiled into the model (read through :class:`sim.go2.Go2Sim`): ``imu_gyro`` /
``imu_acc`` at the body IMU site, ``<LEG>_imu_gyro`` / ``<LEG>_imu_acc`` at the foot IMU sites.
MuJoCo's accelerometer is a specific force (``a - g``, +9.81 m/s^2 up at rest) in the site frame.

Base modes
----------
``"free"``: free joint on ``base``. ``"fixed"``: no joint, ``base`` fixed at ``fixed_base_pos``
(hung up in the air, 0.6 m by default; the exclude pairs keep ``base`` from being fused into
the world). ``"mocap"``: the same free joint as ``"free"``; :class:`sim.go2.Go2Sim` prescribes
the base pose and velocity every step (exact, so the IMUs see the exact base angular velocity)
and applies the base wrench that gives the prescribed base acceleration, so the legs feel the
right inertial and gravity loads. The joint is named ``base_free``.
"""

from __future__ import annotations

import mujoco
import numpy as np

from calib.excitation import FOOT_RADIUS  # the foot contact sphere's radius, m: one for all
from calib.joints import EFFORT_LIMIT, JOINTS, MODEL_JOINT_NAMES, MODEL_LEGS
from calib.robot import go2_collision_mesh_dir, go2_urdf_path

__all__ = [
    "BASE_MODES",
    "BODY_IMU_OFFSET",
    "FIXED_BASE_POS",
    "FLOOR_FRICTION",
    "FOOT_OFFSET",
    "FOOT_RADIUS",
    "add_sim_parts",
    "build_go2_model",
    "build_go2_spec",
    "check_joint_order",
    "joint_names",
]

BASE_MODES = ("free", "fixed", "mocap")
FOOT_OFFSET = np.array([0.0, 0.0, -0.213])
"""Foot frame origin in the calf frame, m (URDF ``<LEG>_foot_joint``)."""
BODY_IMU_OFFSET = np.array([-0.02557, 0.0, 0.04232])
"""Body IMU origin in the base frame, m (URDF ``imu_joint``, no rotation)."""
FLOOR_FRICTION = (0.8, 0.005, 0.0001)
"""Floor (sliding, torsional, rolling) friction; MuJoCo takes the max of the two geoms."""
FIXED_BASE_POS = (0.0, 0.0, 0.6)
"""Where ``base="fixed"`` hangs the base, world frame, m."""

_FOOT_MESH = "foot_convex"


def joint_names() -> tuple[str, ...]:
    """The 12 hinge joints' names in model order (FL, FR, RL, RR x hip, thigh, calf)."""
    return tuple(f"{n}_joint" for n in MODEL_JOINT_NAMES)


def build_go2_spec(
    base: str = "free",
    floor: bool = True,
    timestep: float = 0.001,
    fixed_base_pos: tuple[float, float, float] = FIXED_BASE_POS,
) -> mujoco.MjSpec:
    """The Go2 as an editable :class:`mujoco.MjSpec` (see the module docstring for what is added).

    base: ``"free"``, ``"fixed"`` or ``"mocap"``. floor: add an infinite ground plane at z = 0.
    timestep: physics step, s. fixed_base_pos: base position (world, m) for ``base="fixed"``.
    Joint order (qpos, dof, actuators) is the URDF / model order FL, FR, RL, RR.
    """
    if base not in BASE_MODES:
        raise ValueError(f"unknown base mode {base!r}: expected one of {', '.join(BASE_MODES)}")
    if not (np.isfinite(timestep) and 0.0 < timestep <= 0.05):
        raise ValueError(f"timestep must be in (0, 0.05] s, got {timestep!r}")

    spec = mujoco.MjSpec.from_file(str(go2_urdf_path()))
    spec.strippath = True
    spec.meshdir = str(go2_collision_mesh_dir())
    spec.option.timestep = float(timestep)
    # Elliptic friction cones with a high impratio (as MuJoCo Menagerie's Go2): with the
    # default pyramidal cone the splayed stance creeps sideways by ~2 mm/s under PD stand.
    spec.option.cone = mujoco.mjtCone.mjCONE_ELLIPTIC
    spec.option.impratio = 100.0

    base_body = spec.body("base")
    if base_body is None:
        raise RuntimeError("the Go2 URDF has no 'base' link")
    if base in ("free", "mocap"):
        base_body.add_freejoint(name="base_free")
    else:
        base_body.pos = np.asarray(fixed_base_pos, dtype=float)

    for leg in MODEL_LEGS:
        # base and thigh are not parent/child (the hip is between), so MuJoCo would collide them.
        spec.add_exclude(bodyname1="base", bodyname2=f"{leg}_thigh")
        # MuJoCo does not filter parent/child contacts when the parent is welded to the world:
        # with base="fixed" the rear hip meshes would collide with the base.
        spec.add_exclude(bodyname1="base", bodyname2=f"{leg}_hip")
        calf = spec.body(f"{leg}_calf")
        foot = spec.body(f"{leg}_foot")
        if calf is None or foot is None:
            raise RuntimeError(f"the Go2 URDF lacks {leg}_calf or {leg}_foot")
        if not np.allclose(foot.pos, FOOT_OFFSET) or not np.allclose(foot.quat, [1, 0, 0, 0]):
            raise RuntimeError(f"{leg}_foot is not 0.213 m straight down the calf in this URDF")
        for g in list(foot.geoms):
            if g.type == mujoco.mjtGeom.mjGEOM_MESH and g.meshname == _FOOT_MESH:
                spec.delete(g)
        calf.add_site(name=f"{leg}_foot", pos=FOOT_OFFSET, size=[0.005, 0, 0])
        calf.add_site(name=f"{leg}_imu", pos=FOOT_OFFSET, size=[0.005, 0, 0])
        calf.add_geom(
            name=f"{leg}_foot",
            type=mujoco.mjtGeom.mjGEOM_SPHERE,
            size=[FOOT_RADIUS, 0, 0],
            pos=FOOT_OFFSET,
            friction=FLOOR_FRICTION,
            # Inertia comes from the URDF <inertial> tags; the sphere must add no mass.
            mass=0.0,
        )

    imu = spec.body("imu")
    if imu is None or not np.allclose(imu.pos, BODY_IMU_OFFSET):
        raise RuntimeError("the Go2 URDF's imu link is missing or moved")
    add_sim_parts(spec, base_body, floor)
    return spec


def add_sim_parts(spec: mujoco.MjSpec, base_body, floor: bool) -> None:
    """What every model :class:`sim.go2.Go2Sim` drives gets, whatever file it came from: the
    body IMU site ``imu`` on ``base_body`` (at :data:`BODY_IMU_OFFSET`, unless the spec has
    one), the floor (unless the spec has a world geom ``floor``; removed if ``floor`` is
    false), torque actuators in model order capped at the effort limits, and the IMU sensors.
    The feet's ``<LEG>_foot`` / ``<LEG>_imu`` sites must be there already."""
    if spec.site("imu") is None:
        base_body.add_site(name="imu", pos=BODY_IMU_OFFSET, size=[0.005, 0, 0])

    own = [g for g in spec.worldbody.geoms if g.name == "floor"]
    if not floor:
        for g in own:
            spec.delete(g)
    elif not own:
        spec.worldbody.add_geom(
            name="floor",
            type=mujoco.mjtGeom.mjGEOM_PLANE,
            size=[0.0, 0.0, 0.05],
            friction=FLOOR_FRICTION,
        )

    limits = np.tile(np.asarray(EFFORT_LIMIT, dtype=float), len(MODEL_LEGS))
    for name, lim in zip(joint_names(), limits, strict=True):
        spec.add_actuator(
            name=name.removesuffix("_joint"),
            target=name,
            trntype=mujoco.mjtTrn.mjTRN_JOINT,
            gear=[1, 0, 0, 0, 0, 0],
            ctrllimited=mujoco.mjtLimited.mjLIMITED_TRUE,
            ctrlrange=[-lim, lim],
        )

    site = mujoco.mjtObj.mjOBJ_SITE
    for prefix in ("",) + tuple(f"{leg}_" for leg in MODEL_LEGS):
        spec.add_sensor(
            name=f"{prefix}imu_gyro",
            type=mujoco.mjtSensor.mjSENS_GYRO,
            objtype=site,
            objname=f"{prefix}imu",
        )
        spec.add_sensor(
            name=f"{prefix}imu_acc",
            type=mujoco.mjtSensor.mjSENS_ACCELEROMETER,
            objtype=site,
            objname=f"{prefix}imu",
        )


def build_go2_model(
    base: str = "free",
    floor: bool = True,
    timestep: float = 0.001,
    fixed_base_pos: tuple[float, float, float] = FIXED_BASE_POS,
) -> mujoco.MjModel:
    """Compiled :func:`build_go2_spec` (same arguments)."""
    model = build_go2_spec(base, floor, timestep, fixed_base_pos).compile()
    check_joint_order(model)
    return model


def check_joint_order(model: mujoco.MjModel) -> None:
    """Raise RuntimeError unless the model's hinge joints and actuators are in model order.

    Model order = ``calib.joints.MODEL_JOINT_NAMES`` (FL, FR, RL, RR x hip, thigh, calf), with
    contiguous qpos / dof addresses, so that ``qpos[a:a+12]`` is the joint vector.
    """
    hinges = [
        i for i in range(model.njnt) if model.jnt_type[i] == mujoco.mjtJoint.mjJNT_HINGE
    ]
    names = tuple(model.joint(i).name for i in hinges)
    if names != joint_names():
        raise RuntimeError(f"unexpected joint order in the Go2 model: {names}")
    qadr = model.jnt_qposadr[hinges]
    dadr = model.jnt_dofadr[hinges]
    if np.any(np.diff(qadr) != 1) or np.any(np.diff(dadr) != 1):
        raise RuntimeError("Go2 joint qpos/dof addresses are not contiguous")
    acts = tuple(model.actuator(i).name for i in range(model.nu))
    if acts != MODEL_JOINT_NAMES:
        raise RuntimeError(f"unexpected actuator order in the Go2 model: {acts}")
    if len(JOINTS) * len(MODEL_LEGS) != model.nu:
        raise RuntimeError("the Go2 model must have 12 actuators")
