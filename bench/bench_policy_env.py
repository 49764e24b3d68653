"""Tripod environment throughput: env steps/s (one step = 4 physics steps of every env) with
the MuJoCo batch on each thread count asked for, and the ratio to the first count. Random
actions on a standing robot. On a machine without the URDF and pinocchio, give the files of
``a2i-train pack`` (``--pack DIR``).

Where the scaling goes (docs/policy-training.md, "Stop 50" and "Stop 51"):

* ``--batch``: the MuJoCo batch's calls inside the env steps (ms a step) and the rest of the
  step (the time the batch is not stepping: with one block, the numpy on the calling thread,
  ms), and the batch alone, ``decimation`` calls of ``Batch.step`` from the state the
  environment left, on the same thread counts;
* ``--blocks K1,K2``: the environment's envs in K blocks (``EnvConfig.blocks``), whose
  commands are computed while another block's physics steps ("Stop 51"), at each thread
  count;
* ``--processes K1,K2``: K processes at once, each with its own environment of envs / K and
  its batch on T / K threads (T the largest of ``--threads``), which share nothing, so their
  numpy runs in parallel;
* ``--groups K1,K2``: K environments of envs / K in this process, each with its batch on T / K
  threads (``--group-threads N``: N each), stepped at once from K Python threads, so that one
  group's numpy may run while another's batch steps (MuJoCo's calls and numpy's array loops
  release the GIL); ``--switch-interval S`` sets how long a thread may hold the GIL while
  another waits (``sys.setswitchinterval``, Python's default 0.005 s);
* ``--parts``: where the step's numpy goes, ms a step in each part of it (the first thread
  and block count; "Stop 60");
* ``--against REF``: the environment of ``policy_train/env.py`` at git revision REF (the rest
  of the package as it is now) side by side with the current one, in this process, stepping
  alternately on the same actions: the rest of the step of each, their ratio (with one block;
  with more, the batch's calls overlap the numpy, as for ``--batch``), and whether the two gave
  the same observations, rewards and state to the last bit.

  .venv/bin/python bench/bench_policy_env.py [--envs 256] [--steps 40] [--threads 1,2]
      [--batch] [--blocks 1,2] [--processes 1,2] [--groups 1,2] [--group-threads N]
      [--switch-interval S] [--pack DIR] [--parts] [--against REF]
"""

from __future__ import annotations

import argparse
import importlib.util
import inspect
import multiprocessing as mp
import os
import queue
import subprocess
import sys
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np

import policy_train.env as env_module
from deploy.leg_dynamics import LegDynamics
from policy_train.config import EnvConfig
from policy_train.env import TripodEnv

PACK_FILES = {"model_file": "go2_train.mjb", "plan_pool_file": "pool.npz",
              "leg_dynamics_file": "leg_dynamics.npz"}  # what a2i-train pack writes
WARMUP = 5


def _env(n_envs: int, threads: int, pack: Path | None, blocks: int = 1, cls=TripodEnv):
    files = {} if pack is None else {k: str(pack / f) for k, f in PACK_FILES.items()}
    return cls(EnvConfig(num_envs=n_envs, plans_per_leg=1, seed=0, threads=threads,
                               blocks=blocks, **files))


def _run(env: TripodEnv, steps: int, rng: np.random.Generator) -> float:
    """Seconds for ``steps`` env steps of random actions."""
    t0 = time.perf_counter()
    for _ in range(steps):
        env.step(rng.normal(0, 0.1, (env.N, 12)))
    return time.perf_counter() - t0


class _TimedBatch:
    """The environment's batch, with the seconds spent in its ``step`` calls summed."""

    def __init__(self, batch):
        self._batch, self.seconds = batch, 0.0

    def step(self, *args, **kwargs):
        t0 = time.perf_counter()
        self._batch.step(*args, **kwargs)
        self.seconds += time.perf_counter() - t0

    def __getattr__(self, name):
        return getattr(self._batch, name)


def measure(n_envs: int, threads: int, steps: int, pack: Path | None = None,
            batch: bool = False, blocks: int = 1
            ) -> tuple[float, tuple[float, float, float] | None]:
    """Env steps/s of the environment; with ``batch`` also (ms a step in the batch's calls,
    ms in the rest of the step, env steps/s of the batch alone), else None."""
    env = _env(n_envs, threads, pack, blocks)
    rng = np.random.default_rng(0)
    _run(env, WARMUP, rng)
    timed = env.batch = _TimedBatch(env.batch) if batch else env.batch
    seconds = _run(env, steps, rng)
    rate = steps * n_envs / seconds
    if not batch:
        return rate, None
    env.batch = timed._batch
    in_step = 1e3 * timed.seconds / steps
    dec = env.cfg.decimation
    t0 = time.perf_counter()
    for _ in range(steps):
        for _ in range(dec):
            env.batch.step(nstep=1)
    alone = steps * n_envs / (time.perf_counter() - t0)
    return rate, (in_step, 1e3 * seconds / steps - in_step, alone)


# (label, owner, attribute): the step's parts timed by --parts; nested ones are inside the one above
PARTS = (("the substeps' commands", TripodEnv, "_command"),
         ("  of which the lifted legs' targets", TripodEnv, "_lift_targets"),
         ("    of which their feed-forward", LegDynamics, "torques_of_legs"),
         ("    of which their plan (also once after the substeps)", TripodEnv, "_plan"),
         ("rewards", env_module, "compute_rewards"),
         ("observations", TripodEnv, "observations"),
         ("contacts", TripodEnv, "_contacts"),
         ("resets", TripodEnv, "reset_idx"),
         ("state", TripodEnv, "_compute_state"))


def measure_parts(n_envs: int, threads: int, steps: int, pack: Path | None = None,
                  blocks: int = 1) -> tuple[float, float, dict[str, float]]:
    """(ms a step, ms of it in the batch's calls, {part: ms a step}) of :data:`PARTS`."""
    env = _env(n_envs, threads, pack, blocks)
    rng = np.random.default_rng(0)
    _run(env, WARMUP, rng)
    spent = dict.fromkeys([label for label, _, _ in PARTS], 0.0)
    saved = [(owner, name, inspect.getattr_static(owner, name)) for _, owner, name in PARTS]

    def timed(label, f):
        def run(*args, **kwargs):
            t0 = time.perf_counter()
            try:
                return f(*args, **kwargs)
            finally:
                spent[label] += time.perf_counter() - t0
        return run

    for (label, owner, name), (_, _, raw) in zip(PARTS, saved):
        f = timed(label, getattr(owner, name))
        setattr(owner, name, staticmethod(f) if isinstance(raw, staticmethod) else f)
    try:
        env.batch = _TimedBatch(env.batch)
        seconds = _run(env, steps, rng)
    finally:
        for owner, name, raw in saved:
            setattr(owner, name, raw)
    return (1e3 * seconds / steps, 1e3 * env.batch.seconds / steps,
            {k: 1e3 * v / steps for k, v in spent.items()})


def _env_class_at(ref: str):
    """TripodEnv of policy_train/env.py at git revision ``ref``."""
    root = Path(__file__).resolve().parents[1]
    got = subprocess.run(["git", "-C", str(root), "show", f"{ref}:policy_train/env.py"],
                         capture_output=True, text=True, check=False)
    if got.returncode != 0:
        raise SystemExit(f"bench_policy_env: --against {ref}: "
                         f"{(got.stderr.strip().splitlines() or ['git show failed'])[-1]}")
    with tempfile.TemporaryDirectory() as d:
        path = Path(d) / "env_at_ref.py"
        path.write_text(got.stdout)
        spec = importlib.util.spec_from_file_location("policy_train._env_at_ref", path)
        mod = importlib.util.module_from_spec(spec)
        sys.modules[spec.name] = mod  # dataclasses look their module up
        spec.loader.exec_module(mod)
    return mod.TripodEnv


def measure_against(old_cls, n_envs: int, threads: int, steps: int,
                    pack: Path | None = None, blocks: int = 1
                    ) -> tuple[float, float, bool]:
    """(rest of the step of ``old_cls`` (:func:`_env_class_at`), of now, ms; whether every step
    gave the same bits), the two environments stepped alternately on the same actions (the old
    one first on even steps)."""
    envs = [_env(n_envs, threads, pack, blocks, cls) for cls in (old_cls, TripodEnv)]
    for e in envs:
        e.batch = _TimedBatch(e.batch)
    rng = np.random.default_rng(0)
    total, same = [0.0, 0.0], True
    for i in range(WARMUP + steps):
        a = rng.normal(0, 0.1, (n_envs, 12))
        out = [None, None]
        for j in ((0, 1) if i % 2 == 0 else (1, 0)):
            if i == WARMUP:
                envs[j].batch.seconds = 0.0
            t0 = time.perf_counter()
            obs, rew, dones, _ = envs[j].step(a)
            if i >= WARMUP:
                total[j] += time.perf_counter() - t0
            out[j] = (*(np.asarray(v) for v in obs.values()), rew, dones, envs[j].qpos)
        same &= all(np.array_equal(x, y) for x, y in zip(*out))
    rest = [1e3 * (total[j] - envs[j].batch.seconds) / steps for j in (0, 1)]
    return rest[0], rest[1], same


def _worker(n_envs: int, threads: int, steps: int, pack: Path | None, seed: int, barrier,
            out) -> None:
    env = _env(n_envs, threads, pack)
    rng = np.random.default_rng(seed)
    _run(env, WARMUP, rng)
    barrier.wait()
    t0 = time.perf_counter()
    _run(env, steps, rng)
    out.put((t0, time.perf_counter()))


def measure_processes(n_envs: int, k: int, threads: int, steps: int,
                      pack: Path | None = None) -> float:
    """Env steps/s of ``k`` processes with ``n_envs // k`` envs each (batch threads
    ``threads // k``), stepping at once: all envs' steps over the span from the first start
    to the last finish."""
    ctx = mp.get_context("spawn")  # a forked MuJoCo thread pool is not safe
    barrier, out = ctx.Barrier(k), ctx.Queue()
    per = n_envs // k
    procs = [ctx.Process(target=_worker, args=(per, max(1, threads // k), steps, pack, i, barrier,
                                                    out))
             for i in range(k)]
    for p in procs:
        p.start()
    spans = []
    while len(spans) < k:
        try:
            spans.append(out.get(timeout=1.0))
        except queue.Empty:
            failed = [p.exitcode for p in procs if p.exitcode]
            if failed:  # the others wait at the barrier for it
                for p in procs:
                    p.terminate()
                raise SystemExit(f"bench_policy_env: a worker exited with {failed[0]}")
    for p in procs:
        p.join()
    return k * per * steps / (max(e for _, e in spans) - min(s for s, _ in spans))


def measure_groups(n_envs: int, k: int, threads: int, steps: int,
                   pack: Path | None = None) -> float:
    """Env steps/s of ``k`` environments of ``n_envs // k``, each with its batch on
    ``threads`` threads, stepped at once from ``k`` Python threads."""
    envs = [_env(n_envs // k, threads, pack) for _ in range(k)]
    rngs = [np.random.default_rng(i) for i in range(k)]
    with ThreadPoolExecutor(k) as pool:
        list(pool.map(lambda i: _run(envs[i], WARMUP, rngs[i]), range(k)))
        t0 = time.perf_counter()
        list(pool.map(lambda i: _run(envs[i], steps, rngs[i]), range(k)))
        return k * (n_envs // k) * steps / (time.perf_counter() - t0)


def _counts(text: str, flag: str) -> list[int]:
    try:
        counts = [int(t) for t in text.split(",")]
    except ValueError:
        raise SystemExit(f"bench_policy_env: {flag} {text!r}: comma-separated integers")
    if not counts or min(counts) < 1:
        raise SystemExit(f"bench_policy_env: {flag} counts must be >= 1")
    return counts


def main() -> None:
    p = argparse.ArgumentParser(description=" ".join(__doc__.split("\n\n")[0].split()))
    p.add_argument("--envs", type=int, default=256)
    p.add_argument("--steps", type=int, default=40)
    p.add_argument("--threads", default="1,2", help="thread counts, e.g. 1,2,4,8,16")
    p.add_argument("--batch", action="store_true",
                   help="also time the MuJoCo batch in the steps and alone")
    p.add_argument("--blocks", default="1", help="block counts, e.g. 1,2 (EnvConfig.blocks)")
    p.add_argument("--processes", help="process counts, e.g. 1,2,4: the largest thread count split among them")
    p.add_argument("--groups", help="group counts, e.g. 1,2,4: the largest thread count split "
                   "among them")
    p.add_argument("--group-threads", type=int, help="batch threads of each group")
    p.add_argument("--switch-interval", type=float,
                   help="seconds a thread may hold the GIL while another waits")
    p.add_argument("--pack", type=Path, help="a2i-train pack's folder instead of the URDF")
    p.add_argument("--parts", action="store_true",
                   help="also time each part of the step's numpy")
    p.add_argument("--against", metavar="REF",
                   help="also run policy_train/env.py at git revision REF side by side")
    a = p.parse_args()
    counts = _counts(a.threads, "--threads")
    procs = _counts(a.processes, "--processes") if a.processes else []
    groups = _counts(a.groups, "--groups") if a.groups else []
    blocks = _counts(a.blocks, "--blocks")
    if a.envs < 1 or a.steps < 1:
        raise SystemExit("bench_policy_env: --envs and --steps must be >= 1")
    if a.envs < max(procs + groups + blocks):
        raise SystemExit(f"bench_policy_env: --envs {a.envs} is fewer than "
                         f"{max(procs + groups + blocks)} processes, groups or blocks")
    if a.group_threads is not None and a.group_threads < 1:
        raise SystemExit("bench_policy_env: --group-threads must be >= 1")
    if a.switch_interval is not None:
        if not a.switch_interval > 0:
            raise SystemExit("bench_policy_env: --switch-interval must be > 0")
        sys.setswitchinterval(a.switch_interval)
    missing = [f for f in PACK_FILES.values() if a.pack and not (a.pack / f).is_file()]
    if missing:
        raise SystemExit(f"bench_policy_env: {a.pack} lacks {', '.join(missing)} "
                         "(write it with a2i-train pack)")
    old_cls = _env_class_at(a.against) if a.against else None  # a bad REF fails first
    print(f"{os.cpu_count()} CPUs; {a.envs} envs, {a.steps} steps per count; GIL switch "
          f"interval {sys.getswitchinterval() * 1e3:g} ms", flush=True)
    res = {}
    for th in counts:
        for k in blocks:
            res[th, k] = measure(a.envs, th, a.steps, a.pack, a.batch, k)
            print(f"  {th} thread(s), {k} block(s) done", flush=True)
    base, bbase = res[counts[0], blocks[0]]
    print(f"| threads | blocks | env steps/s | physics steps/s | ratio to {counts[0]} thread(s), "
          f"{blocks[0]} block(s) |"
          + (" batch in the step, ms | rest of the step, ms | batch alone, env steps/s | "
             "batch-alone ratio |" if a.batch else ""))
    print("| --- | --- | --- | --- | --- |" + (" --- | --- | --- | --- |" if a.batch else ""))
    for (th, k), (r, b) in res.items():
        extra = (f" {b[0]:.1f} | {b[1]:.1f} | {b[2]:,.0f} | {b[2] / bbase[2]:.2f} |"
                 if b is not None else "")
        print(f"| {th} | {k} | {r:,.0f} | {4 * r:,.0f} | {r / base:.2f} |" + extra)
    if procs:
        th = max(counts)
        rp = {}
        for k in procs:
            rp[k] = measure_processes(a.envs, k, th, a.steps, a.pack)
            print(f"  {k} process(es) done", flush=True)
        print(f"\n| processes ({th} threads in all) | env steps/s | ratio to {procs[0]} |")
        print("| --- | --- | --- |")
        for k, r in rp.items():
            print(f"| {k} | {r:,.0f} | {r / rp[procs[0]]:.2f} |")

    if a.parts:
        th, k = counts[0], blocks[0]
        step, in_batch, parts = measure_parts(a.envs, th, a.steps, a.pack, k)
        print(f"\n{th} thread(s), {k} block(s): a step {step:.1f} ms, {in_batch:.1f} in the "
              f"batch's calls, {step - in_batch:.1f} the rest; of the rest:")
        print("| part | ms a step |\n| --- | --- |")
        for label, ms in parts.items():
            print(f"| {label} | {ms:.2f} |")
    if a.against:
        th, k = counts[0], blocks[0]
        old, new, same = measure_against(old_cls, a.envs, th, a.steps, a.pack, k)
        print(f"\npolicy_train/env.py at {a.against} against now, {th} thread(s), {k} "
              f"block(s), side by side: rest of the step {old:.2f} ms against {new:.2f} "
              f"(ratio {new / old:.3f}); the same bits every step: {'yes' if same else 'no'}")

    if groups:
        th = max(counts)
        rg = {}
        for k in groups:
            gt = a.group_threads or max(1, th // k)
            rg[k] = measure_groups(a.envs, k, gt, a.steps, a.pack)
            print(f"  {k} group(s) done", flush=True)
        each = f"{a.group_threads} threads each" if a.group_threads else f"{th} threads in all"
        print(f"\n| groups ({each}) | env steps/s | ratio to {groups[0]} |")
        print("| --- | --- | --- |")
        for k, r in rg.items():
            print(f"| {k} | {r:,.0f} | {r / rg[groups[0]]:.2f} |")


if __name__ == "__main__":
    main()
