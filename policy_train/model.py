"""The training model of the Go2: :func:`sim.model.build_go2_spec` with native PD actuators.

Python per physics step is the bottleneck of RL training, so here MuJoCo computes the PD law
itself: each motor is a ``position`` actuator (``kp``, ``kv``) with ``forcerange`` = the effort
limits (the environment scales it per env with the drawn motor strength: ``TripodEnv.torque_peak``),
so ``tau = clamp(kp * (ctrl - q) - kv * dq)``; a velocity target is folded into the
control as ``ctrl = q_des + (kd / kp) * dq_des`` (exact). ``mujoco.batch.Batch`` then steps
many copies in C on a thread pool. Differences from :class:`sim.go2.Go2Sim` (documented in
``docs/policy-training.md``): ``implicitfast`` integration (the damping term is implicit, so
kd stays stable at 5 ms), joint ``armature`` 0.01 kg m^2 (rotor inertia), and sensors used by
the rewards: foot positions / linear velocities, and ``contact`` sensors (feet and every other
collision geom against the floor).
"""

from __future__ import annotations

import mujoco
import numpy as np

from calib.excitation import base_to_foot
from calib.joints import EFFORT_LIMIT, MODEL_LEGS
from sim.model import build_go2_spec

__all__ = ["ARMATURE", "TrainModel", "build_train_model"]

ARMATURE = 0.01  # kg m^2, reflected rotor inertia per joint (as MuJoCo Menagerie's Go2)

_FOUND = 1 << int(mujoco.mjtConDataField.mjCONDATA_FOUND)
_FORCE = 1 << int(mujoco.mjtConDataField.mjCONDATA_FORCE)
_NETFORCE = 3  # reduce: net force of the matched contacts


class TrainModel:
    """Compiled model plus the sensor slices the environment reads."""

    def __init__(self, physics_dt: float = 0.005, kp: float = 20.0, kd: float = 0.5,
                 model_file: str | None = None):
        if model_file is not None:
            # a model saved by save() (mj_saveModel): no URDF / meshes package needed
            self.spec = None
            self.model = mujoco.MjModel.from_binary_path(str(model_file))
            if abs(self.model.opt.timestep - physics_dt) > 1e-12:
                raise ValueError(f"{model_file}: timestep {self.model.opt.timestep} != {physics_dt}")
            self._index()
            return
        spec = build_go2_spec(base="free", floor=True, timestep=physics_dt)
        spec.option.integrator = mujoco.mjtIntegrator.mjINT_IMPLICITFAST
        lim = np.tile(np.asarray(EFFORT_LIMIT, dtype=float), len(MODEL_LEGS))
        for act, tau in zip(spec.actuators, lim, strict=True):
            act.set_to_position(kp=kp, kv=kd)
            act.ctrllimited = mujoco.mjtLimited.mjLIMITED_FALSE
            act.forcelimited = mujoco.mjtLimited.mjLIMITED_TRUE
            act.forcerange = [-tau, tau]
        for j in spec.joints:
            if j.type == mujoco.mjtJoint.mjJNT_HINGE:
                j.armature = ARMATURE
        # name the unnamed collision geoms, so that contact sensors can match them
        other = []
        for b in spec.bodies:
            for k, g in enumerate(b.geoms):
                if b.name == "world" or g.name.endswith("_foot"):
                    continue
                if not g.name:
                    g.name = f"{b.name}_col{k}"
                other.append(g.name)
        site = mujoco.mjtObj.mjOBJ_SITE
        geom = mujoco.mjtObj.mjOBJ_GEOM
        for leg in MODEL_LEGS:
            spec.add_sensor(name=f"{leg}_foot_pos", type=mujoco.mjtSensor.mjSENS_FRAMEPOS,
                            objtype=site, objname=f"{leg}_foot")
            spec.add_sensor(name=f"{leg}_foot_vel", type=mujoco.mjtSensor.mjSENS_FRAMELINVEL,
                            objtype=site, objname=f"{leg}_foot")
        for leg in MODEL_LEGS:
            spec.add_sensor(name=f"{leg}_foot_contact", type=mujoco.mjtSensor.mjSENS_CONTACT,
                            objtype=geom, objname=f"{leg}_foot", reftype=geom, refname="floor",
                            intprm=[_FOUND | _FORCE, _NETFORCE, 1])
        for name in other:
            spec.add_sensor(name=f"{name}_contact", type=mujoco.mjtSensor.mjSENS_CONTACT,
                            objtype=geom, objname=name, reftype=geom, refname="floor",
                            intprm=[_FOUND | _FORCE, _NETFORCE, 1])
        self.spec = spec
        self.model = spec.compile()
        self._index()

    def save(self, path) -> None:
        """Write the compiled model (MuJoCo binary .mjb), for machines without the URDF."""
        mujoco.mj_saveModel(self.model, str(path), None)

    def _index(self) -> None:
        m = self.model
        other = [m.sensor(i).name.removesuffix("_contact") for i in range(m.nsensor)
                 if m.sensor(i).name.endswith("_contact")
                 and not m.sensor(i).name.endswith("_foot_contact")]
        self.collision_geoms = tuple(other)
        self.base_geoms = tuple(n for n in other if n.startswith("base"))

        def adr(name: str) -> int:
            return int(m.sensor(name).adr[0])

        self.foot_pos = np.array([adr(f"{leg}_foot_pos") for leg in MODEL_LEGS])
        self.foot_vel = np.array([adr(f"{leg}_foot_vel") for leg in MODEL_LEGS])
        self.foot_contact = np.array([adr(f"{leg}_foot_contact") for leg in MODEL_LEGS])
        self.other_contact = np.array([adr(f"{n}_contact") for n in other])
        self.base_contact = np.array([adr(f"{n}_contact") for n in self.base_geoms])
        self.base_body = m.body("base").id
        self.calf_hull = self._calf_hulls()
        self.hinge_qadr = int(m.jnt_qposadr[m.joint("FL_hip_joint").id])
        self.hinge_dadr = int(m.jnt_dofadr[m.joint("FL_hip_joint").id])

    def _calf_hulls(self) -> np.ndarray:
        """(4, V, 3) m: the points of each calf's collision geoms, in the calf frame relative to
        the foot site (mesh hull vertices, or the bounding-box corners of other geoms), padded
        by repetition to a common V; per leg of ``MODEL_LEGS``."""
        m = self.model
        d = mujoco.MjData(m)
        mujoco.mj_kinematics(m, d)
        corners = np.array(np.meshgrid([-1, 1], [-1, 1], [-1, 1])).reshape(3, -1).T
        hulls = []
        for leg in MODEL_LEGS:
            b = m.body(f"{leg}_calf").id
            rb, pb = d.xmat[b].reshape(3, 3), d.xpos[b]
            foot = rb.T @ (d.site_xpos[m.site(f"{leg}_foot").id] - pb)
            pts = []
            for g in np.flatnonzero((m.geom_bodyid == b) & (m.geom_contype | m.geom_conaffinity)):
                if m.geom(g).name.endswith("_foot"):
                    continue
                if m.geom_type[g] == mujoco.mjtGeom.mjGEOM_MESH:
                    mid, a = m.geom_dataid[g], m.mesh_vertadr[m.geom_dataid[g]]
                    local = m.mesh_vert[a:a + m.mesh_vertnum[mid]]
                else:
                    local = m.geom_aabb[g, :3] + corners * m.geom_aabb[g, 3:]
                world = d.geom_xpos[g] + local @ d.geom_xmat[g].reshape(3, 3).T
                pts.append((world - pb) @ rb - foot)
            if not pts:
                raise ValueError(f"{leg}_calf has no collision geom")
            hulls.append(np.concatenate(pts))
        n = max(len(h) for h in hulls)
        return np.stack([np.concatenate([h, np.repeat(h[-1:], n - len(h), 0)]) for h in hulls])

    def calf_low_z(self, gravity_b: np.ndarray, q: np.ndarray, foot_z: np.ndarray) -> np.ndarray:
        """Height (m, world) of each calf's lowest collision point, (N, 4), model leg order.

        A stance calf is what touches the floor first when its leg inclines: the hull near the
        foot reaches within 6-10 mm of the floor in v7's tripod. gravity_b (N, 3) projected
        gravity (unit, base frame); q (N, 12) joint angles rad; foot_z (N, 4) foot-site
        heights m. World up is carried into each calf frame
        (:func:`calib.excitation.base_to_foot`); the lowest point is the foot's height plus the
        most negative projection of :attr:`calf_hull` on it."""
        up = -gravity_b
        out = np.empty(foot_z.shape)
        for leg in range(4):
            u = base_to_foot(up, q[:, 3 * leg:3 * leg + 3])
            # elementwise, not a matmul: used inside a rollout, idle BLAS threads spin and
            # starve MuJoCo's thread pool (a 16-core training run fell from 30 k to 10 k steps/s)
            h = self.calf_hull[leg].T
            proj = u[:, :1] * h[0] + u[:, 1:2] * h[1] + u[:, 2:] * h[2]
            out[:, leg] = foot_z[:, leg] + np.min(proj, -1)
        return out


def build_train_model(physics_dt: float = 0.005, kp: float = 20.0, kd: float = 0.5) -> TrainModel:
    """:class:`TrainModel` with the nominal gains (per-environment gains are set by the env)."""
    return TrainModel(physics_dt, kp, kd)
