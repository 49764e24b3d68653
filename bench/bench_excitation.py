"""Benchmark of the anti-noise excitation generator and the baseline motions (Table I style).

Per leg: kappa reached by the optimiser, objective evaluations, restarts, process time on one
core, kappa of the steady part resampled at 100 and 1000 Hz, then kappa of walk, spin, wave
and A2I for the same leg, two ways: ``rel`` = foot angular velocity relative to the base
(closed form, what the optimiser controls); ``abs`` = what a foot gyro sees (base rotation
included, via calib.kinematics).

Run: .venv/bin/python bench/bench_excitation.py [--seed N] [--duration S] [--rate HZ]
"""

from __future__ import annotations

import argparse

from calib.excitation import ExcitationConfig, foot_omega, plan_excitation
from calib.joints import LEGS
from calib.kinematics import LegKinematics
from calib.metrics import condition_number
from calib.motions import a2i_motion, baseline_motions


def _abs_kappa(motion, leg: str, kin: LegKinematics) -> float:
    q, dq = motion.leg(leg)
    t0, t1 = motion.steady_window
    keep = (motion.t >= t0) & (motion.t < t1)
    w = kin.foot_angular_velocity(q[keep], dq[keep], base_omega=motion.base_omega[keep])
    return condition_number(w)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--duration", type=float, default=20.0, help="baseline duration, s")
    ap.add_argument("--rate", type=float, default=200.0, help="sample rate of the motions, Hz")
    args = ap.parse_args()

    print("A2I excitation (t_r = 0.5 s, 10 basis terms, 4 periods of 4 s, ramps 1 s)")
    hdr = f"{'leg':4} {'kappa':>8} {'evals':>6} {'restarts':>8} {'cpu s':>7} "
    hdr += f"{'k@100Hz':>9} {'k@1kHz':>9} {'w_rms rad/s':>12} {'hip range rad':>14}"
    print(hdr)
    print("-" * len(hdr))
    plans = {}
    for leg in LEGS:
        p = plan_excitation(ExcitationConfig(leg=leg, seed=args.seed))
        plans[leg] = p
        t, q, dq = p.sample(1000.0)
        steady = (t >= p.steady_window[0]) & (t < p.steady_window[1])

        rms = foot_omega(q[steady], dq[steady]).std(0).mean()
        print(f"{leg:4} {p.kappa:8.6f} {p.iterations:6d} {p.restarts:8d} {p.process_time:7.3f} "
              f"{p.steady_kappa(100.0):9.6f} {p.steady_kappa(1000.0):9.6f} {rms:12.3f} "
              f"{q[:, 0].min():6.2f}..{q[:, 0].max():5.2f}")
    cpu = [p.process_time for p in plans.values()]
    print(f"worst cpu time per leg: {max(cpu):.3f} s (target < 2 s); "
          f"worst kappa: {max(p.kappa for p in plans.values()):.5f} (target <= 1.02)")

    print(f"\nkappa of Sigma_FF on the steady part ({args.duration:g} s baselines, "
          f"{args.rate:g} Hz, seed {args.seed})")
    names = ("walk", "spin", "wave", "a2i")
    hdr = f"{'leg':4} " + " ".join(f"{n + ' rel':>11} {n + ' abs':>11}" for n in names)
    hdr += f" {'walk/a2i rel':>13}"
    print(hdr)
    print("-" * len(hdr))
    for leg in LEGS:
        kin = LegKinematics.from_urdf(leg=leg)
        ms = baseline_motions(leg, args.duration, args.rate, args.seed)
        ms["a2i"] = a2i_motion(plans[leg], args.rate)
        rel = {n: ms[n].kappa(leg) for n in names}
        ab = {n: _abs_kappa(ms[n], leg, kin) for n in names}
        cells = " ".join(f"{rel[n]:11.4g} {ab[n]:11.4g}" for n in names)
        ratio = rel["walk"] / rel["a2i"]
        print(f"{leg:4} {cells} {ratio:13.4g}")
    print("(wave: hip still, the foot turns about one axis only, so Sigma_FF is singular: inf)")


if __name__ == "__main__":
    main()
