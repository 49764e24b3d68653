"""Tripod environment throughput: env steps/s (one step = 4 physics steps of every env) with
the MuJoCo batch on each thread count asked for, and the ratio to one thread. Random actions on
a standing robot. On a machine without the URDF and pinocchio, give the files of
``a2i-train pack`` (``--pack DIR``).

  .venv/bin/python bench/bench_policy_env.py [--envs 256] [--steps 40] [--threads 1,2] [--pack DIR]
"""

from __future__ import annotations

import argparse
import os
import time
from pathlib import Path

import numpy as np

from policy_train.config import EnvConfig
from policy_train.env import TripodEnv

PACK_FILES = {"model_file": "go2_train.mjb", "plan_pool_file": "pool.npz",
              "leg_dynamics_file": "leg_dynamics.npz"}  # what a2i-train pack writes


def measure(n_envs: int, threads: int, steps: int, pack: Path | None = None) -> float:
    files = {} if pack is None else {k: str(pack / f) for k, f in PACK_FILES.items()}
    env = TripodEnv(EnvConfig(num_envs=n_envs, plans_per_leg=1, seed=0, threads=threads, **files))
    rng = np.random.default_rng(0)
    for _ in range(5):
        env.step(rng.normal(0, 0.1, (n_envs, 12)))
    t0 = time.perf_counter()
    for _ in range(steps):
        env.step(rng.normal(0, 0.1, (n_envs, 12)))
    return steps * n_envs / (time.perf_counter() - t0)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--envs", type=int, default=256)
    p.add_argument("--steps", type=int, default=40)
    p.add_argument("--threads", default="1,2", help="thread counts, e.g. 1,2,4,8,16")
    p.add_argument("--pack", type=Path, help="a2i-train pack's folder instead of the URDF")
    a = p.parse_args()
    try:
        counts = [int(t) for t in a.threads.split(",")]
    except ValueError:
        raise SystemExit(f"bench_policy_env: --threads {a.threads!r}: comma-separated integers")
    if not counts or min(counts) < 1 or a.envs < 1 or a.steps < 1:
        raise SystemExit("bench_policy_env: --threads, --envs and --steps must be >= 1")
    missing = [f for f in PACK_FILES.values() if a.pack and not (a.pack / f).is_file()]
    if missing:
        raise SystemExit(f"bench_policy_env: {a.pack} lacks {', '.join(missing)} "
                         "(write it with a2i-train pack)")
    res = {th: measure(a.envs, th, a.steps, a.pack) for th in counts}
    base = res[counts[0]]
    print(f"{os.cpu_count()} CPUs; {a.envs} envs, {a.steps} steps per thread count")
    print(f"| threads | env steps/s | physics steps/s | ratio to {counts[0]} thread(s) |")
    print("| --- | --- | --- | --- |")
    for th, r in res.items():
        print(f"| {th} | {r:,.0f} | {4 * r:,.0f} | {r / base:.2f} |")


if __name__ == "__main__":
    main()
