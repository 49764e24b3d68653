"""Speed of the simulated Go2: physics steps per second in the ways the project uses it.

Run: ``.venv/bin/python bench/bench_sim.py [--steps N]``. One thread unless stated. Prints a
table; ``vs mj_step`` is the ratio to a bare ``mujoco.mj_step`` loop on the same model and state
with sensors disabled (no PD law, no Python per step beyond the call): the ceiling for a
Python-driven loop. Timings on a shared machine vary by +-30 %; compare ratios.
"""

from __future__ import annotations

import argparse
import time

import mujoco
import numpy as np

from calib.joints import EFFORT_LIMIT, default_crouch
from sim.go2 import Go2BatchSim, Go2Sim, SimConfig, rotation_about_axis_trajectory, stand_pose
from sim.model import build_go2_model
from sim.sensors import FootImuModel, random_mounting


def _standing(cfg: SimConfig) -> Go2Sim:
    sim = Go2Sim(cfg)
    sim.set_command(stand_pose(), 0.0, 60.0, 5.0, 0.0)
    sim.step(300)
    return sim


def _rate(fn, n: int, repeats: int = 3) -> float:
    """Best of ``repeats`` runs of ``fn(n)``: n / seconds."""
    best = np.inf
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn(n)
        best = min(best, time.perf_counter() - t0)
    return n / best


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--steps", type=int, default=4000, help="physics steps per measurement")
    args = ap.parse_args()
    n = args.steps
    rows: list[tuple[str, float, str]] = []

    t0 = time.perf_counter()
    for _ in range(10):
        Go2Sim(SimConfig())
    rows.append(("Go2Sim() construction (model compile)", 10 / (time.perf_counter() - t0),
                 "per s"))

    # Ceiling: the same PD law inside MuJoCo (affine position actuators), bare mj_step loop.
    m = build_go2_model("free")
    m.actuator_gainprm[:, 0] = 60.0
    m.actuator_biastype[:] = mujoco.mjtBias.mjBIAS_AFFINE
    m.actuator_biasprm[:, :3] = [0.0, -60.0, -5.0]
    m.actuator_ctrllimited[:] = 0
    m.actuator_forcelimited[:] = 1
    m.actuator_forcerange[:] = np.stack([-np.tile(EFFORT_LIMIT, 4), np.tile(EFFORT_LIMIT, 4)], 1)
    ref = _standing(SimConfig())
    d = mujoco.MjData(m)
    d.qpos[:], d.qvel[:] = ref.data.qpos, ref.data.qvel
    d.ctrl[:] = stand_pose()

    def raw(k):
        for _ in range(k):
            mujoco.mj_step(m, d)

    rows.append(("bare mj_step, PD in MuJoCo, sensors on", _rate(raw, n), "steps/s"))
    # Go2Sim.run skips the sensor stage (the accelerometers cost an extra RNE pass); the
    # accessors compute it when asked. The fair ceiling is mj_step without sensors:
    m.opt.disableflags |= mujoco.mjtDisableBit.mjDSBL_SENSOR
    base = _rate(raw, n)
    rows.append(("bare mj_step, PD in MuJoCo, sensors off (= 1.00)", base, "steps/s"))
    assert d.qpos[2] > 0.3, "the reference loop must keep standing to be a fair ceiling"

    sim = _standing(SimConfig())
    rows.append(("Go2Sim.run, standing, PD every step", _rate(sim.run, n), "steps/s"))

    sim = _standing(SimConfig())
    imu = FootImuModel(random_mounting(0))

    def streaming(k):
        for _ in range(k):
            imu.update(sim.time, sim.foot_angular_velocity("FL"), sim.foot_specific_force("FL"))
            sim.step()

    rows.append(("step(1) + foot truth + FootImuModel.update", _rate(streaming, n), "steps/s"))

    sim = Go2Sim(SimConfig(base="mocap"))
    sim.set_base_trajectory(rotation_about_axis_trajectory([0, 1, 0], 0.3, 1.0))
    sim.reset()
    sim.set_command(stand_pose(), 0.0, 25.0, 0.5, 0.0)
    rows.append(("mocap base (trajectory), run", _rate(sim.run, n), "steps/s"))

    # RL setting (FACTS.md): kp 20, kd 0.5 at dt 0.005 around the default crouch. (kd 5 at
    # dt 0.005 is unstable on this model: explicit PD, zero rotor armature in the URDF.)
    sim = Go2Sim(SimConfig(timestep=0.005))
    sim.reset(q=default_crouch())
    sim.set_command(default_crouch(), 0.0, 20.0, 0.5, 0.0)
    sim.step(100)

    def policy_loop(k):
        q0 = default_crouch()
        for _ in range(k // 4):
            sim.set_command(q0, 0.0, 20.0, 0.5, 0.0)
            _ = sim.q, sim.dq, sim.base_ang_vel, sim.base_quat_wxyz
            sim.step(4)

    r = _rate(policy_loop, n)
    assert not sim.body_contacts(), "the policy-loop robot fell: the measurement is not standing"
    rows.append(("50 Hz loop over dt 0.005 (decimation 4)", r, "steps/s"))
    rows.append(("  = real-time factor", r * 0.005, "x"))

    for threads in (1, 2):
        batch = Go2BatchSim(SimConfig(), 4, threads=threads)
        batch.set_commands(stand_pose(), 0.0, 60.0, 5.0, 0.0)
        batch.step(100)
        rb = _rate(batch.step, n // 4, repeats=2) * len(batch)
        batch.close()
        rows.append((f"Go2BatchSim 4 envs, {threads} thread(s)", rb, "env-steps/s"))

    width = max(len(r[0]) for r in rows)
    print(f"{'measurement':<{width}}  {'rate':>12}  unit        vs mj_step")
    for name, val, unit in rows:
        ratio = f"{val / base:9.2f}" if unit in ("steps/s", "env-steps/s") else ""
        print(f"{name:<{width}}  {val:12.0f}  {unit:<10}  {ratio}")


if __name__ == "__main__":
    main()
