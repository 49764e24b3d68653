"""``a2i-calib``: plan an anti-noise excitation, solve a calibration from logs, simulate one.

A thin layer over :mod:`calib` (and :mod:`sim` for the simulated subcommands, imported only
there, so ``plan`` and ``solve`` run on a robot without MuJoCo). Bad input exits 2 with a
one-line reason and writes nothing.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from pathlib import Path

import numpy as np

from calib.atomic import os_error_line, write_text_atomic
from calib.csvio import MAX_MEDIAN_STEP_S, CalibInputError, read_encoders_csv, read_imu_csv
from calib.joints import LEGS, check_leg

EXIT_BAD_INPUT = 2


class _Fail(Exception):
    """A one-line reason to exit 2."""


def _leg(s: str) -> str:
    try:
        return check_leg(s)
    except ValueError as e:
        raise argparse.ArgumentTypeError(str(e)) from None


def _number(s: str, least: float, strict: bool) -> float:
    try:
        v = float(s)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a number: {s!r}") from None
    if not (np.isfinite(v) and (v > least if strict else v >= least)):
        need = "a positive number" if strict else f"a number >= {least:g}"
        raise argparse.ArgumentTypeError(f"must be {need}, got {s!r}")
    return v


def _positive(s: str) -> float:
    return _number(s, 0.0, strict=True)


def _nonnegative(s: str) -> float:
    return _number(s, 0.0, strict=False)


def _say(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)


# ------------------------------------------------------------------------------------ plan
def cmd_plan(args) -> int:
    from calib.excitation import ExcitationConfig, plan_excitation

    try:
        cfg = ExcitationConfig(leg=args.leg, t_r=args.offset_range, periods=args.periods,
                               n_basis=args.basis, seed=args.seed,
                               **({} if args.ground_clearance is None
                                  else {"ground_clearance": args.ground_clearance}))
    except ValueError as e:
        raise _Fail(str(e)) from None
    min_rate = 1.0 / MAX_MEDIAN_STEP_S  # what the CSV readers take for seconds
    if not args.rate >= min_rate:
        raise _Fail(f"--rate must be >= {min_rate:g} Hz, got {args.rate:g}")
    t0 = time.process_time()
    try:
        plan = plan_excitation(cfg)
    except (RuntimeError, ValueError) as e:  # no motion inside the limits, a bad start pose
        raise _Fail(str(e)) from None
    cpu = time.process_time() - t0
    # what is written, checked between the optimiser's grid points too
    problems = plan.problems()
    if problems:
        raise _Fail(f"leg {args.leg}: {'; '.join(problems)}; try another --seed, a longer "
                    "--offset-range or another --basis")
    plan.to_csv(args.out, rate_hz=args.rate)
    lo, hi = plan.steady_window
    print(f"leg {plan.leg}: kappa(Sigma_FF) = {plan.kappa:.5f} reached in {cpu:.2f} s CPU; "
          f"f = {plan.f:.4f} rad/s, period {plan.period:.2f} s, {cfg.periods} periods, "
          f"duration {plan.duration:.2f} s (steady {lo:.2f}-{hi:.2f} s); "
          f"start pose (hip, thigh, calf) = {np.round(plan.q0, 4).tolist()} rad")
    print(f"wrote {args.out} at {args.rate:g} Hz")
    return 0


# ----------------------------------------------------------------------------------- solve
def _solver_config(max_offset: float):
    from calib.solver import SolverConfig

    try:
        return SolverConfig(max_offset=max_offset)
    except ValueError as e:
        raise _Fail(str(e)) from None


def cmd_solve(args) -> int:
    from calib.kinematics import LegKinematics
    from calib.pipeline import CalibrationRefused, calibrate_logs
    from calib.result import format_report

    if Path(args.out).is_dir():  # found before the solve, not after
        raise _Fail(f"--out {args.out}: is a directory")
    try:
        enc = read_encoders_csv(args.encoders, args.leg)
        imu = read_imu_csv(args.imu)
        kin = LegKinematics.from_urdf(args.urdf, leg=args.leg, foot_frame=args.foot_frame)
        result, _ = calibrate_logs(enc, imu, kin, _solver_config(args.max_offset))
    except (CalibInputError, ValueError) as e:
        raise _Fail(str(e).splitlines()[0]) from None
    except CalibrationRefused as e:
        raise _Fail("refused: " + "; ".join(e.reasons)) from None
    result.write(args.out)
    print(format_report(result))
    if enc.base_omega is None:
        print("  note: no base_w*/base_q* columns: the base was assumed still")
    print(f"wrote {args.out}")
    return 0


# ------------------------------------------------------------------------------------ demo
def _progress_printer(what: str):
    """progress(fraction) callback printing at most every 20 % to stderr."""
    last = [-1]

    def show(frac: float) -> None:
        step = int(frac * 5)
        if step != last[0]:
            last[0] = step
            _say(f"      {what} {100 * frac:3.0f} %")

    return show


def _truth_dict(leg: str, rotation: np.ndarray, offset: float) -> dict:
    return {leg: {"rotation_matrix": [[float(v) for v in r] for r in rotation],
                  "time_offset_s": float(offset)}}


def cmd_demo(args) -> int:
    from calib.csvio import write_encoders_csv, write_imu_csv
    from calib.excitation import ExcitationConfig, plan_excitation
    from calib.motions import a2i_motion
    from calib.pipeline import CalibrationRefused, calibrate_logs
    from calib.result import format_report

    try:
        from sim.calibration_run import run_motion
        from sim.sensors import random_mounting
    except ImportError as e:
        raise _Fail(f"the demo needs the simulator: pip install '.[sim]' ({e})") from None

    out = Path(args.out)
    leg = args.leg
    _say(f"[1/4] planning the anti-noise excitation for {leg} ...")
    plan = plan_excitation(ExcitationConfig(leg=leg, t_r=args.offset_range))
    _say(f"      kappa = {plan.kappa:.5f}, {plan.duration:.1f} s of motion")
    _say("[2/4] playing it on the simulated Go2 (MuJoCo, 1 kHz PD, base held) ...")
    run = run_motion(a2i_motion(plan, 200.0), progress=_progress_printer("played"))
    mount = random_mounting(args.seed, max_offset=min(0.2, 0.8 * args.offset_range),
                            gyro_noise_deg=args.noise, rate=args.imu_rate)
    imu = run.foot_imu(leg, mount)
    enc_csv, imu_csv = out / f"{leg}_encoders.csv", out / f"{leg}_imu.csv"
    write_encoders_csv(enc_csv, run.t, run.q, dq=run.dq, base_omega=run.base_gyro)
    write_imu_csv(imu_csv, imu.stamps, imu.gyro, imu.accel)
    _say(f"[3/4] logs written: {enc_csv} (500 Hz), {imu_csv} ({args.imu_rate:g} Hz, "
         f"{args.noise:g} deg/s/sqrt(Hz), hidden mounting seed {args.seed})")
    _say("[4/4] solving from the logs (the same path as `a2i-calib solve`) ...")
    try:
        result, _ = calibrate_logs(read_encoders_csv(enc_csv, leg), read_imu_csv(imu_csv),
                                   config=_solver_config(args.offset_range))
    except CalibrationRefused as e:
        raise _Fail("refused: " + "; ".join(e.reasons)) from None
    result.write(out / f"{leg}.json")
    write_text_atomic(out / "sim_truth.json",
                      json.dumps(_truth_dict(leg, mount.rotation, mount.time_offset), indent=2))
    print(format_report(result, truth=(mount.rotation, mount.time_offset)))
    print("  truth R_I^F rows: " + "  ".join(
        "[" + " ".join(f"{v:+.6f}" for v in row) + "]" for row in mount.rotation))
    print(f"  truth time offset: {mount.time_offset * 1e3:+.3f} ms")
    print(f"wrote {out / f'{leg}.json'} and {out / 'sim_truth.json'}")
    return 0


# ----------------------------------------------------------------------------------- bench
def _free_json(path: Path) -> Path:
    """Where the free-base rows live beside a held-base rows file or page: <stem>_policy.json."""
    return path.with_name(path.stem + "_policy.json")


def _read_free(path: Path):
    from sim.table1 import FreeTable

    try:
        return FreeTable.from_json(path.read_text())
    except (OSError, ValueError, TypeError, KeyError) as e:
        raise _Fail(f"cannot read free-base rows from {path}: {e}") from None


def _read_held(path: Path):
    from sim.table1 import rows_from_json

    try:
        return rows_from_json(path.read_text())
    except (OSError, ValueError, TypeError) as e:
        raise _Fail(f"cannot read rows from {path}: {e}") from None


def _held_wall_time(page: Path) -> float | None:
    """The held-base section's wall time on an existing page (kept when only the free-base
    section is re-run)."""
    try:
        text = page.read_text().split("## Free base", 1)[0]
    except OSError:
        return None
    for line in text.splitlines():
        if line.startswith("Wall time: ") and line.endswith(" s."):
            try:
                return float(line[len("Wall time: "):-3])
            except ValueError:
                return None
    return None


def _bench_policy(args, t0: float, out: Path):
    """The free-base table with A2I executed by ``args.policy``; returns (page, stdout text)."""
    import functools

    from sim.table1 import FreeTable, render_free_section, render_page, run_table1_free

    try:
        import onnxruntime  # noqa: F401
    except ImportError:
        raise _Fail("--policy needs onnxruntime: pip install onnxruntime") from None
    from deploy.policy import PolicyMeta
    from policy_train.policy_motion import load_policy, run_policy_a2i_per_leg

    legs = args.legs or list(LEGS)
    per_leg: dict[str, str] = {}  # each leg: the last given policy that serves it
    for p in args.policy:
        pol = Path(p)
        for f in (pol, pol.with_suffix(".json")):
            if not f.is_file():
                raise _Fail(f"policy file not found: {f}")
        try:
            load_policy(pol)  # fail here, once, rather than in every worker
            per_leg.update(dict.fromkeys(PolicyMeta.load(pol.with_suffix(".json")).legs, p))
        except ValueError as e:
            raise _Fail(str(e).splitlines()[0]) from None
    missing = [g for g in legs if g not in per_leg]
    if missing:
        raise _Fail(f"no given policy serves {', '.join(missing)} (its JSON's legs list)")
    per_leg = {g: per_leg[g] for g in legs}
    seeds = list(range(args.seeds))
    shown = "; ".join(f"{g} {p}" for g, p in per_leg.items())
    _say(f"Table I, free base, A2I by {shown}: {len(seeds)} seeds x {len(legs)} legs x 3 noise "
         f"levels x 4 motions, {args.workers or 'all'} worker processes")
    # each leg's A2I record: the excitation phase of its policy's lift schedule
    record_s = {g: float(PolicyMeta.load(Path(p).with_suffix(".json")).schedule.durations(g)[3])
                for g, p in per_leg.items()}
    try:
        rows, runs = run_table1_free(
            functools.partial(run_policy_a2i_per_leg, per_leg), record_s, seeds, legs,
            workers=args.workers,
            progress=lambda i, n: _say(f"  simulated {i}/{n} runs ({time.time() - t0:.0f} s)"))
    except RuntimeError as e:  # an A2I run called off or failed: no table to score it in
        raise _Fail(str(e).splitlines()[0]) from None
    free = FreeTable(rows, runs, seeds, " ".join(args.policy), time.time() - t0, record_s)
    write_text_atomic(_free_json(out), free.to_json())
    held_path = out.with_suffix(".json")
    held = _read_held(held_path) if held_path.is_file() else None
    seeds_held = sorted({r.seed for r in held}) if held else []
    page = render_page(held, seeds_held, _held_wall_time(out), free)
    return page, render_free_section(free)


def cmd_bench(args) -> int:
    try:
        from sim.table1 import render_page, run_table1
    except ImportError as e:
        raise _Fail(f"the bench needs the simulator: pip install '.[sim]' ({e})") from None
    t0 = time.time()
    out = Path(args.out)
    if args.policy and args.from_json:
        raise _Fail("--policy runs the free-base table; --from-json re-renders saved rows: "
                    "give one of them")
    shown = None
    if args.from_json:
        src = Path(args.from_json)
        rows = _read_held(src)
        seeds = sorted({r.seed for r in rows})
        free = _read_free(_free_json(src)) if _free_json(src).is_file() else None
        md = render_page(rows, seeds, _held_wall_time(src.with_suffix(".md")), free)
    elif args.policy:
        md, shown = _bench_policy(args, t0, out)
    else:
        seeds = list(range(args.seeds))
        legs = args.legs or list(LEGS)
        _say(f"Table I: {len(seeds)} seeds x {len(legs)} legs x 3 noise levels x 4 motions, "
             f"{args.workers or 'all'} worker processes")
        rows = run_table1(seeds, legs, workers=args.workers,
                          progress=lambda i, n: _say(f"  simulated {i}/{n} motions "
                                                     f"({time.time() - t0:.0f} s)"))
        # keep the free-base section of an earlier `--policy` run, and say so: it was simulated
        # by that run's code and seeds, not this one's
        free = _read_free(_free_json(out)) if _free_json(out).is_file() else None
        if free is not None:
            same = ("the same seeds" if list(free.seeds) == seeds
                    else f"{len(free.seeds)} seeds of its own")
            _say(f"kept the free-base section of {_free_json(out)} (an earlier --policy run, "
                 f"{same}; rerun with --policy to refresh it)")
        md = render_page(rows, seeds, time.time() - t0, free)
        # The raw rows beside the table, so that it can be re-rendered without re-simulating.
        write_text_atomic(out.with_suffix(".json"),
                          json.dumps([dataclasses.asdict(r) for r in rows], indent=0))
    write_text_atomic(out, md)
    print(md if shown is None else shown)
    print(f"wrote {out}" + (f" and {_free_json(out)}" if args.policy else ""))
    return 0


# ------------------------------------------------------------------------------------ main
def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="a2i-calib",
        description="Foot-IMU spatial-temporal calibration the A2I-Calib way "
                    "(R_I^F: omega_F = R omega_I; t_d = t_I - t_E).")
    sub = p.add_subparsers(dest="command", required=True, metavar="COMMAND")

    s = sub.add_parser("plan", help="optimise the anti-noise excitation for one leg",
                       description="Optimise Theorem 1's basis coefficients so that "
                                   "kappa(Sigma_FF) -> 1 within joint limits; write the joint "
                                   "trajectory as CSV (t, q_<LEG>_<JOINT>, dq_<LEG>_<JOINT>).")
    s.add_argument("--leg", type=_leg, required=True, help="FL, FR, RL or RR")
    s.add_argument("--offset-range", type=_positive, default=0.5, metavar="S",
                   help="time-offset search range t_r, s (period 8 t_r; default 0.5)")
    s.add_argument("--periods", type=int, default=4, help="steady periods (default 4)")
    s.add_argument("--basis", type=int, default=10, help="basis functions N (default 10)")
    s.add_argument("--rate", type=_positive, default=200.0, help="CSV rate, Hz (default 200)")
    s.add_argument("--seed", type=int, default=0, help="initial-guess seed (default 0)")
    s.add_argument("--ground-clearance", type=_nonnegative, metavar="M", default=None,
                   help="lowest height of the lifted foot's centre over the floor of the "
                        "stance feet, m (default: the generator's; a policy JSON's "
                        "lift_schedule names the one its lifts play, v26's 0.12)")
    s.add_argument("--out", required=True, help="output CSV")
    s.set_defaults(func=cmd_plan)

    s = sub.add_parser("solve", help="calibrate from an encoder CSV and an IMU CSV",
                       description="Calibrate one foot IMU from logs (formats: docs/formats.md). "
                                   "Writes the result JSON atomically; exits 2 with a one-line "
                                   "reason on malformed or degenerate input and writes nothing.")
    s.add_argument("--encoders", required=True, help="encoder CSV (t, q_<LEG>_<JOINT>, ...)")
    s.add_argument("--imu", required=True, help="foot IMU CSV (t, wx, wy, wz)")
    s.add_argument("--leg", type=_leg, required=True, help="FL, FR, RL or RR")
    s.add_argument("--max-offset", type=_positive, default=0.5, metavar="S",
                   help="search |t_d| up to this, s (default 0.5)")
    s.add_argument("--urdf", default=None, help="robot URDF (default: the Go2 of "
                   "example-robot-data)")
    s.add_argument("--foot-frame", default=None, help="foot frame in the URDF "
                   "(default <LEG>_foot)")
    s.add_argument("--out", required=True, help="result JSON")
    s.set_defaults(func=cmd_solve)

    s = sub.add_parser("demo", help="simulate a calibration in MuJoCo and solve it",
                       description="Plan the excitation, play it on the simulated Go2 with a "
                                   "hidden random IMU mounting, log CSVs, solve them, and print "
                                   "the result beside the truth.")
    s.add_argument("--leg", type=_leg, default="FL", help="leg (default FL)")
    s.add_argument("--seed", type=int, default=7, help="hidden mounting seed (default 7)")
    s.add_argument("--noise", type=_positive, default=0.03,
                   help="gyro noise density, deg/s/sqrt(Hz) (default 0.03)")
    s.add_argument("--imu-rate", type=_positive, default=400.0, help="IMU rate, Hz (default 400)")
    s.add_argument("--offset-range", type=_positive, default=0.5, metavar="S",
                   help="t_r, s (default 0.5)")
    s.add_argument("--out", default="calibration/demo", help="output folder")
    s.set_defaults(func=cmd_demo)

    s = sub.add_parser("bench", help="the paper's Table I in MuJoCo",
                       description="4 legs x noise {0.006, 0.03, 0.06} deg/s/sqrt(Hz) x motions "
                                   "{walk, spin, wave, A2I} x seeds; writes a markdown table. "
                                   "Base held on the motions' trajectories, or with --policy on "
                                   "the floor with A2I executed by the tripod policy.")
    s.add_argument("--seeds", type=int, default=3, help="seeds (default 3)")
    s.add_argument("--legs", type=_leg, nargs="*", default=None, help="subset of legs")
    s.add_argument("--workers", type=int, default=None, help="processes (default: all cores)")
    s.add_argument("--from-json", default=None, metavar="ROWS",
                   help="re-render the page from the rows a previous run saved (no simulation); "
                        "the free-base rows are read from ROWS' <stem>_policy.json if present")
    s.add_argument("--policy", default=None, nargs="+", metavar="ONNX",
                   help="run the free-base table instead: A2I executed by the tripod policy "
                        "(its .json beside it; with several, each leg gets the last one whose "
                        "JSON lists it, as a2i-deploy picks per leg), walk/spin open-loop, naive "
                        "wave; its rows go to <out stem>_policy.json and its section after the "
                        "held-base table")
    s.add_argument("--out", default="docs/results/table1.md", help="markdown output")
    s.set_defaults(func=cmd_bench)
    return p


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    for name in ("periods", "basis", "seeds"):
        if getattr(args, name, 1) is not None and getattr(args, name, 1) < 1:
            parser.error(f"--{name} must be >= 1")
    try:
        return args.func(args)
    except _Fail as e:
        print(f"a2i-calib {args.command}: error: {e}", file=sys.stderr)
        return EXIT_BAD_INPUT
    except OSError as e:  # an output that cannot be written, an input that cannot be read
        print(f"a2i-calib {args.command}: error: {os_error_line(e)}", file=sys.stderr)
        return EXIT_BAD_INPUT
    except KeyboardInterrupt:
        print(f"a2i-calib {args.command}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
