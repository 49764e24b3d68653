"""Tripod environment throughput: env steps/s (one step = 4 physics steps of every env) with
the MuJoCo batch on 1 and 2 threads, and the ratio. Random actions on a standing robot.

  .venv/bin/python bench/bench_policy_env.py [--envs 256] [--steps 40]
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from policy_train.config import EnvConfig
from policy_train.env import TripodEnv


def measure(n_envs: int, threads: int, steps: int) -> float:
    env = TripodEnv(EnvConfig(num_envs=n_envs, plans_per_leg=1, seed=0, threads=threads))
    rng = np.random.default_rng(0)
    for _ in range(5):
        env.step(rng.normal(0, 0.1, (n_envs, 12)))
    t0 = time.perf_counter()
    for _ in range(steps):
        env.step(rng.normal(0, 0.1, (n_envs, 12)))
    return steps * n_envs / (time.perf_counter() - t0)


def main() -> None:
    p = argparse.ArgumentParser()
    p.add_argument("--envs", type=int, default=256)
    p.add_argument("--steps", type=int, default=40)
    a = p.parse_args()
    res = {th: measure(a.envs, th, a.steps) for th in (1, 2)}
    print(f"| threads | env steps/s ({a.envs} envs) | physics steps/s |")
    print("| --- | --- | --- |")
    for th, r in res.items():
        print(f"| {th} | {r:,.0f} | {4 * r:,.0f} |")
    print(f"ratio 2/1 threads: {res[2] / res[1]:.2f}")


if __name__ == "__main__":
    main()
