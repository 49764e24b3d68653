"""``a2i-sim2real``: diagnose the sim-to-real gap of a recording, or prove the diagnoser.

    a2i-sim2real diagnose RECORDING [--report out.html] [--json out.json] [--mount M] [--quiet]
    a2i-sim2real bench [--cases N] [--seed S] [--duration SEC] [--out docs/results/sim2real.md]
    a2i-sim2real synth OUT.csv|OUT.mcap [--mount M] [--effect NAME=VALUE[@JOINT]] [--seed S]

Exit status: 0 done, 2 bad input (one-line reason on stderr).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from calib.atomic import os_error_line, write_text_atomic

__all__ = ["main"]


def _diagnose(args) -> int:
    from sim2real.diagnose import DiagnoseConfig, diagnose, print_progress
    from sim2real.recording import load_recording

    for out in (args.json, args.report):
        if out and Path(out).is_dir():  # found before the diagnosis, not after
            raise ValueError(f"{out}: is a directory")
    rec = load_recording(args.recording, mount=args.mount)
    d = diagnose(rec, DiagnoseConfig(window=args.window,
                                     progress=None if args.quiet else print_progress))
    out = d.to_json()
    if args.json:
        write_text_atomic(Path(args.json), json.dumps(out, indent=2) + "\n")
    if args.report:
        from sim2real.report import render_report
        write_text_atomic(Path(args.report), render_report(d))
    verdict = "no significant gap" if not d.significant_gap else "significant gap"
    print(f"{verdict}: held-out gap {d.gap_before:.4f} -> {d.gap_after:.4f}")
    for e in d.effects[:5]:
        pv = ", ".join(f"{k}={v:.4g} [{e.ci[k][0]:.3g}, {e.ci[k][1]:.3g}]"
                       for k, v in e.parameters.items())
        mark = "*" if e.chosen else " "
        print(f" {mark} {e.name:<18} {','.join(e.location):<10} {pv}  held-out gap "
              f"{e.gap_after_heldout:.4f}")
    return 0


def _bench(args) -> int:
    from sim2real.bench import run_bench

    s = run_bench(cases=args.cases, seed=args.seed, duration=args.duration,
                  out=None if args.out == "-" else args.out)
    print(f"top-1 {100 * s['top1']:.0f} %  location {100 * s['location']:.0f} %  "
          f"param. error (median) {100 * s['param_error']:.1f} %  held-out gap reduction "
          f"(median) {100 * s['gap_reduction']:.0f} %  null cases ok {s['null_ok']}/"
          f"{s['null_cases']}  ({s['seconds']:.0f} s)")
    return 0


def _parse_effect(text: str):
    from sim import effects as fx

    name, _, rest = text.partition("=")
    value, _, where = rest.partition("@")
    try:
        v = float(value)
    except ValueError:
        raise ValueError(f"--effect {text!r}: expected NAME=VALUE[@JOINT]") from None
    joints = [where] if where else None
    table = {
        "latency": lambda: fx.ActuationLatency(v),
        "motor_strength": lambda: fx.MotorStrength(v, joints=joints),
        "coulomb_friction": lambda: fx.CoulombFriction(v, joints=joints),
        "viscous_friction": lambda: fx.ViscousFriction(v, joints=joints),
        "armature": lambda: fx.Armature(v, joints=joints),
        "backlash": lambda: fx.Backlash(v, joints=joints),
        "link_mass": lambda: fx.LinkMass(v, where or "base"),
        "foot_payload": lambda: fx.FootPayload(v, where.split("_")[0]),  # @FL or @FL_calf
        "foot_friction": lambda: fx.FootFriction(v),
        "torque_limit": lambda: fx.TorqueLimit(v, joints=joints),
        "packet_loss": lambda: fx.PacketLoss(v),
        "imu_bias": lambda: fx.ImuBias([v, v, v]),
        "imu_time_offset": lambda: fx.ImuTimeOffset(v),
        "imu_misalignment": lambda: fx.ImuMisalignment([v, 0.0, 0.0]),
    }
    if name not in table:
        raise ValueError(f"--effect: unknown effect {name!r}")
    if name == "foot_payload" and not where:
        raise ValueError(f"--effect {text!r}: a foot payload needs its leg, e.g. "
                         "foot_payload=0.06@FL")
    return table[name]()


def _synth(args) -> int:
    from sim2real.recording import write_csv
    from sim2real.synth import SynthConfig, synthesize, write_mcap_recording

    effects = [_parse_effect(e) for e in args.effect]
    rec = synthesize(effects, SynthConfig(mount=args.mount or "suspended",
                                          duration=args.duration, seed=args.seed))
    out = Path(args.out)
    if out.suffix == ".mcap":
        write_mcap_recording(rec, out)
    elif out.suffix == ".csv":
        write_csv(rec, out)
    else:
        raise ValueError(f"{out}: the output must end in .csv or .mcap")
    print(f"wrote {out} ({rec.duration:.1f} s, {rec.mount}, effects: {effects or 'none'})")
    return 0


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="a2i-sim2real", description=__doc__.split("\n")[0])
    sub = p.add_subparsers(dest="cmd", required=True)
    d = sub.add_parser("diagnose", help="diagnose a recording (.mcap or .csv)")
    d.add_argument("recording")
    d.add_argument("--report", help="write the HTML report here")
    d.add_argument("--json", help="write the JSON answer here")
    d.add_argument("--mount", choices=("suspended", "ground"),
                   help="override the mount (needed for MCAP files without it in metadata)")
    d.add_argument("--window", type=float, default=0.5, help="shooting window, s (0.5)")
    d.add_argument("--quiet", action="store_true", help="no progress on stderr")
    b = sub.add_parser("bench", help="score the diagnoser on withheld simulated effects")
    b.add_argument("--cases", type=int, default=24)
    b.add_argument("--seed", type=int, default=0)
    b.add_argument("--duration", type=float, default=8.0)
    b.add_argument("--out", default="docs/results/sim2real.md", help="'-' to skip writing")
    s = sub.add_parser("synth", help="make a recording from sim with injected effects")
    s.add_argument("out")
    s.add_argument("--mount", choices=("suspended", "ground"))
    s.add_argument("--effect", action="append", default=[],
                   help="NAME=VALUE[@JOINT], e.g. backlash=0.02@RL_thigh, foot_payload=0.06@FL "
                        "(kg; a foot IMU node's mass on that leg)")
    s.add_argument("--duration", type=float, default=8.0)
    s.add_argument("--seed", type=int, default=0)
    args = p.parse_args(argv)
    try:
        if args.cmd == "diagnose":
            return _diagnose(args)
        if args.cmd == "bench":
            if args.cases < 1:
                raise ValueError("--cases must be >= 1")
            return _bench(args)
        return _synth(args)
    except ValueError as exc:
        print(f"a2i-sim2real: error: {exc}", file=sys.stderr)
        return 2
    except OSError as exc:  # an output that cannot be written, an input that cannot be read
        print(f"a2i-sim2real: error: {os_error_line(exc)}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
