"""Benchmark of the on-board loop: real-time mode against the mock robot for a long run.

The mock runs in its own process (realtime clock, 1 kHz physics); this process is the deploy
program, calibrating the four legs in turn, over and over, for ``--seconds`` (default 600).
Printed: tick period error p50 / p99 / max against the absolute 20 ms deadlines, missed
deadlines, compute time per tick, calibrations done, and this process's resident memory at
the start of the loop, after the warm-up (the recorder's rings fill once, ``--record-seconds``)
and at the end: it must not grow after the warm-up, the recorder's memory being fixed by its
configuration.

    .venv/bin/python bench/bench_deploy.py                 # 10 minutes
    .venv/bin/python bench/bench_deploy.py --seconds 60    # a quick look

With a trained policy in ``policies/`` the robot stands on the floor; without one (or with
``--hold``) it is hung up (``base: fixed``) and driven by the hold policy.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from deploy.hold_policy import write_hold_policy
from deploy.policy import PolicyMeta, default_policy_path
from deploy.runtime import DeployConfig, DeployRunner, rss_bytes
from deploy.session import SessionConfig, State
from deploy.simulate import start_sim, truth_tuples
from deploy.supervisor import SupervisorConfig


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=600.0)
    ap.add_argument("--record-seconds", type=float, default=60.0,
                    help="recorder history; RSS is compared after this warm-up (default 60)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--hold", action="store_true", help="hold policy on a hung robot")
    ap.add_argument("--stale-ticks", type=int, default=3,
                    help="supervisor's stale-LowState limit (default 3 = the product's); a "
                         "starved mock on a loaded machine may need more")
    args = ap.parse_args()

    tmp = Path(tempfile.mkdtemp(prefix="a2i-bench-deploy-"))
    policy = None
    if not args.hold:
        try:
            policy = default_policy_path()
        except ValueError:
            policy = None
    extra = {}
    if policy is None:
        policy = write_hold_policy(tmp / "policies")
        extra = {"base": "fixed"}
    meta = PolicyMeta.load(policy)
    print(f"policy {meta.name} ({policy}); mock {'hung up' if extra else 'on the floor'}; "
          f"{args.seconds:g} s real time", flush=True)
    sim = start_sim(args.seed, "realtime", extra)
    n_ticks = round(args.seconds / meta.control_dt)
    # Every ring full (the slowest, the 400 Hz foot IMUs in 500 Hz slots, after 1.1 x 1.25 x
    # record_seconds) and the first SOLVE done (its imports, the allocator's arena).
    warm_s = max(args.record_seconds * 1.5, 60.0)
    warm_tick = round(warm_s / meta.control_dt)
    rss = {}
    quiet: list[tuple[float, int]] = []  # RSS when a leg is lifted: no SOLVE in flight
    prev_state = [None]

    def on_tick(r: DeployRunner) -> None:
        st = r.session.state
        if st is State.TRIPOD and prev_state[0] is not State.TRIPOD:
            quiet.append((r.ticks * meta.control_dt, rss_bytes()))
        prev_state[0] = st
        if r.ticks == 1:
            rss["loop start"] = rss_bytes()
        elif r.ticks == warm_tick:
            rss[f"after warm-up ({warm_s:g} s)"] = rss_bytes()
        elif r.ticks % 3000 == 0:
            s = r.stats.summary()
            print(f"  {r.ticks * meta.control_dt:6.0f} s: {r.session.state.value:<9} "
                  f"period error p99 {s.period_error_p99 * 1e3:6.3f} ms, missed {s.missed}, "
                  f"RSS {rss_bytes() / 2**20:7.1f} MiB", flush=True)

    cfg = DeployConfig(legs=["FL", "FR", "RL", "RR"] * 1000, out_dir=tmp / "out",
                       connect=[sim.connect], imus=sim.imus, clock="realtime",
                       record_seconds=args.record_seconds, truth=truth_tuples(sim.truth),
                       write_mcap=False, max_ticks=n_ticks,
                       # hung up, the body cannot move over the tripod: no lift gate
                       session=SessionConfig(lift_gate=None) if extra else SessionConfig(),
                       supervisor=SupervisorConfig(stale_ticks=args.stale_ticks))
    t0 = time.monotonic()
    try:
        runner = DeployRunner(cfg, meta, on_tick=on_tick)
        result = runner.run()
    finally:
        sim.stop()
    wall = time.monotonic() - t0
    rss["end"] = result.rss_end_bytes
    s = result.timing
    done = [o for o in result.outcomes if o.payload is not None]
    ok = sum(o.ok for o in result.outcomes)
    print()
    print("| figure | value |\n| --- | --- |")
    print(f"| wall time | {wall:.1f} s |")
    print(f"| ticks | {s.ticks} (expected {n_ticks}) |")
    print(f"| missed deadlines | {s.missed} |")
    print(f"| LowCmd_ frames skipped (a successor already due) | {s.frames_skipped} of "
          f"{s.ticks * (runner.n_cmd - 1)} |")
    print(f"| ticks started > 1 ms late | {s.late} ({100 * s.late / max(1, s.ticks):.2f} %) |")
    print(f"| period error p50 / p99 / max | {s.period_error_p50 * 1e3:.3f} / "
          f"{s.period_error_p99 * 1e3:.3f} / {s.period_error_max * 1e3:.3f} ms |")
    print(f"| compute per tick p50 / p99 / max | {s.compute_p50 * 1e3:.3f} / "
          f"{s.compute_p99 * 1e3:.3f} / {s.compute_max * 1e3:.3f} ms |")
    print(f"| compute p99 / period | {s.compute_p99 / meta.control_dt:.3f} |")
    print(f"| calibrations solved / accepted | {len(done)} / {ok} |")
    print(f"| recorder memory (fixed by config) | {result.recorder_bytes / 2**20:.1f} MiB |")
    print(f"| RSS before the loop | {result.rss_start_bytes / 2**20:.1f} MiB |")
    for k, v in rss.items():
        print(f"| RSS {k} | {v / 2**20:.1f} MiB |")
    keys = list(rss)
    if len(keys) >= 3:
        grow = rss["end"] - rss[keys[1]]
        print(f"| RSS growth after warm-up | {grow / 2**20:+.1f} MiB |")
    late = [(t, v) for t, v in quiet if t >= warm_s]
    if len(late) >= 2:
        vals = np.array([v for _, v in late]) / 2**20
        print(f"| RSS at each lift after warm-up (no SOLVE in flight): first / min / max / "
              f"last | {vals[0]:.1f} / {vals.min():.1f} / {vals.max():.1f} / {vals[-1]:.1f} MiB "
              f"({len(vals)} lifts, {late[0][0]:.0f}-{late[-1][0]:.0f} s) |")
    print(f"| final state / fault | {result.final_state.value} / {result.fault} |")
    print()
    for o in result.outcomes:
        if o.payload is not None and not o.ok:
            print(f"{o.leg}: not accepted: {o.error}")
        elif o.ok and o.payload.errors_vs_truth() is not None:
            rot, off = o.payload.errors_vs_truth()
            print(f"{o.leg}: accepted: rotation error {rot:.3f} deg, offset error "
                  f"{off * 1e3:.3f} ms")
    return 0


if __name__ == "__main__":
    sys.exit(main())
