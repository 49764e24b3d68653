"""``a2i-deploy``: calibrate the Go2's foot IMUs on board (or against the simulated robot).

    a2i-deploy --leg FL --imu FL=/dev/ttyUSB0            # one leg, now
    a2i-deploy --leg all --imu FL=/dev/ttyUSB0#1 FR=/dev/ttyUSB0#2 ...   # four legs in turn
    a2i-deploy --imu FL=/dev/ttyUSB0 ...                 # wait for the remote
    a2i-deploy --leg FL --sim                            # the MuJoCo mock, no robot needed

Joystick mode (no --leg): L2+A stands up, then L1+Up / R1+Up / L1+Down / R1+Down calibrates
FL / FR / RL / RR; L2+B damps from any state; Ctrl-C damps and exits.

Exit codes: 0 every requested leg calibrated and written; 1 a leg was refused or failed, or a
fault damped the robot; 2 bad input or start-up failure (no robot, port, policy, conflict).
"""

from __future__ import annotations

import argparse
import json
import logging
import signal
import sys
import time
from pathlib import Path

from calib.joints import LEGS, check_leg
from deploy.lift_gate import DEFAULT_GATE, GateLimits
from deploy.tip_guard import DEFAULT_TIP_LIMITS, TipLimits

__all__ = ["main", "parse_imu"]


def parse_imu(spec: str):
    """``LEG=PORT`` or ``LEG=PORT#NODE`` -> ImuPort; ValueError (one line) otherwise."""
    from deploy.runtime import ImuPort

    if "=" not in spec:
        raise ValueError(f"--imu {spec!r}: expected LEG=PORT or LEG=PORT#NODE, "
                         "e.g. FL=/dev/ttyUSB0")
    leg, port = spec.split("=", 1)
    node = None
    if "#" in port:
        port, n = port.rsplit("#", 1)
        try:
            node = int(n)
        except ValueError:
            raise ValueError(f"--imu {spec!r}: node id {n!r} is not an integer") from None
        if not 0 <= node <= 255:
            raise ValueError(f"--imu {spec!r}: node id must be 0..255")
    if not port:
        raise ValueError(f"--imu {spec!r}: empty port")
    return ImuPort(check_leg(leg), port, node)


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="a2i-deploy",
        description="On-board foot-IMU calibration of the Unitree Go2 (A2I-Calib): stand, "
                    "lift the leg, play the anti-noise motion, lower, solve, report. "
                    "Reference: docs/deploy.md.")
    p.add_argument("--leg", action="append", metavar="LEG",
                   help="leg to calibrate now: FL, FR, RL, RR or all (repeatable, or "
                        "comma-separated); without it, wait for the remote's combos")
    p.add_argument("--sim", action="store_true",
                   help="run against the MuJoCo mock robot started here (Zenoh loopback)")
    p.add_argument("--sim-seed", type=int, default=0, metavar="N",
                   help="seed of the mock's hidden mounting rotations and offsets (default 0)")
    p.add_argument("--sim-clock", choices=("lockstep", "realtime"), default="lockstep",
                   help="mock clock: lockstep (deterministic, faster than real time; default) "
                        "or realtime")
    p.add_argument("--sim-config", metavar="PATH",
                   help="JSON of extra mock settings (docs/mock-robot.md), e.g. "
                        '{"foot_imus": {"all": {"garbage_prob": 0.1}}}')
    p.add_argument("--connect", metavar="ENDPOINT", default="tcp/127.0.0.1:7447",
                   help="Zenoh endpoint of the robot's zenoh-bridge-dds "
                        "(default tcp/127.0.0.1:7447)")
    p.add_argument("--clock", choices=("realtime", "lockstep"), default=None,
                   help="tick source and time base: realtime (robot; default) or lockstep "
                        "(a lockstep a2i-mock)")
    p.add_argument("--imu", nargs="+", action="extend", default=[], metavar="LEG=PORT[#NODE]",
                   help="foot IMU serial ports, e.g. FL=/dev/ttyUSB0 (NODE: radio node id "
                        "when several IMUs share one receiver)")
    p.add_argument("--imu-protocol", choices=("a2i", "hipnuc"), default="a2i")
    p.add_argument("--imu-baud", type=int, default=921600)
    p.add_argument("--out", metavar="DIR", default="calibration",
                   help="output folder (default calibration/)")
    p.add_argument("--policy", metavar="PATH",
                   help="policy JSON (or the ONNX beside it) for every leg (default: per leg, "
                        "the newest policies/*.json whose 'legs' list has it)")
    p.add_argument("--periods", type=int, metavar="N",
                   help="override the policy's excitation periods (shorter runs; fewer "
                        "samples)")
    p.add_argument("--no-replant", action="store_true",
                   help="lift the next leg from where the last lift left the feet, without "
                        "sitting down and standing up again in between (faster; only the first "
                        "lift then starts from the stance the policy was evaluated from)")
    p.add_argument("--max-tip", default=str(DEFAULT_TIP_LIMITS), metavar="LIFT[,HOLD]",
                   help="call a lift off, put the foot back down and lift the leg once more "
                        "with a longer shift when the body tips this many deg from its tilt "
                        "when the lift began: LIFT while the foot leaves the floor, HOLD while "
                        "the leg swings to the excitation's start (one number: both; 0: never; "
                        f"default {DEFAULT_TIP_LIMITS}; see deploy/tip_guard.py)")
    p.add_argument("--lift-gate", default=str(DEFAULT_GATE), metavar="MM[,S]",
                   help="lift the foot once the estimated centre of mass stands MM mm inside the "
                        "other three feet, the shift held up to S s longer for it, else call the "
                        f"lift off as --max-tip does (off: on time; default {DEFAULT_GATE}; "
                        "deploy/lift_gate.py)")
    p.add_argument("--record-seconds", type=float, default=180.0, metavar="S",
                   help="recorder history kept in memory and saved as MCAP (default 180)")
    p.add_argument("--force", action="store_true",
                   help="publish rt/lowcmd even though another publisher is present (DANGER)")
    p.add_argument("-v", "--verbose", action="store_true")
    return p


# "all" lifts the rear legs first. After a tripod the feet stay where its shift left them, and
# the front lifts shift the body ~8 cm (rear ~2.4 cm): measured on the mock (seed 101), a rear
# lift after both front ones tipped past 30 deg, while rear-first calibrated all four. REPLANT
# (deploy/session.py) now starts every lift from a stand-up; the order stays for --no-replant.
ALL_LEGS_ORDER: tuple[str, ...] = ("RL", "RR", "FL", "FR")


def _legs(values: list[str] | None) -> list[str]:
    out: list[str] = []
    for v in values or []:
        for part in v.split(","):
            part = part.strip()
            if not part:
                continue
            if part.lower() == "all":
                out.extend(leg for leg in ALL_LEGS_ORDER if leg not in out)
            else:
                leg = check_leg(part)
                if leg not in out:
                    out.append(leg)
    return out


def _say(line: str) -> None:
    print(line, flush=True)


def main(argv: list[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    logging.basicConfig(level=logging.DEBUG if args.verbose else logging.WARNING,
                        format="a2i-deploy: %(levelname)s %(name)s: %(message)s")
    try:
        legs = _legs(args.leg)
        imus = [parse_imu(s) for s in args.imu]
        try:
            max_tip = TipLimits.parse(args.max_tip)
        except ValueError as e:
            raise ValueError(f"--max-tip: {e}") from None
        try:
            lift_gate = GateLimits.parse(args.lift_gate)
        except ValueError as e:
            raise ValueError(f"--lift-gate: {e}") from None
    except ValueError as e:
        print(f"a2i-deploy: error: {e}", file=sys.stderr)
        return 2
    try:
        from deploy.policy import default_policy_path, policies_for_legs

        want = legs
        if not want and not args.policy:  # joystick: every leg some policy serves
            want = []
            for g in LEGS:
                try:
                    default_policy_path(leg=g)
                    want.append(g)
                except ValueError:
                    pass
        metas = policies_for_legs(want or LEGS, args.policy)
        if args.periods is not None:
            from dataclasses import replace

            for m in {id(m): m for m in metas.values()}.values():
                m.schedule = replace(m.schedule, periods=int(args.periods))
        extra = None
        if args.sim_config:
            extra = json.loads(Path(args.sim_config).read_text(encoding="utf-8"))
            if not isinstance(extra, dict):
                raise ValueError("--sim-config must hold a JSON object")
    except (ValueError, OSError) as e:
        print(f"a2i-deploy: error: {e}", file=sys.stderr)
        return 2

    from deploy.report import results_table
    from deploy.runtime import DeployConfig, DeployError, DeployRunner
    from deploy.session import SessionConfig

    out_dir = Path(args.out)
    sim = None
    truth = None
    session_meta: dict = {}
    if args.sim:
        from deploy.simulate import start_sim, truth_tuples, write_sim_truth

        _say(f"a2i-deploy: starting the mock robot (seed {args.sim_seed}, "
             f"{args.sim_clock} clock)...")
        try:
            sim = start_sim(args.sim_seed, args.sim_clock, extra)
        except (ValueError, RuntimeError, OSError) as e:
            print(f"a2i-deploy: error: {e}", file=sys.stderr)
            return 2
        out_dir.mkdir(parents=True, exist_ok=True)
        write_sim_truth(out_dir / "sim_truth.json", sim.truth)
        truth = truth_tuples(sim.truth)
        connect = sim.connect
        clock = args.sim_clock
        given = {i.leg for i in imus}
        imus = imus + [i for i in sim.imus if i.leg not in given]
        session_meta = {"sim_seed": args.sim_seed, "sim_clock": args.sim_clock}
    else:
        connect = args.connect
        clock = args.clock or "realtime"
    cfg = DeployConfig(legs=legs, joystick=not legs, out_dir=out_dir, connect=[connect],
                       imus=imus, imu_protocol=args.imu_protocol, imu_baud=args.imu_baud,
                       clock=clock, record_seconds=args.record_seconds, force=args.force,
                       truth=truth, session_metadata=session_meta, progress=_say,
                       session=SessionConfig(replant=not args.no_replant,
                                             max_tip=max_tip, lift_gate=lift_gate))
    runner = None
    try:
        try:
            runner = DeployRunner(cfg, metas)
        except (DeployError, ValueError) as e:
            print(f"a2i-deploy: error: {e}", file=sys.stderr)
            return 2
        by_file: dict = {}
        for g, m in metas.items():
            by_file.setdefault(m.path, []).append(g)
        names = "; ".join(f"{', '.join(g)}: {p}" for p, g in by_file.items())
        _say(f"a2i-deploy: policies {names}; legs "
             f"{', '.join(legs) if legs else 'from the remote (L2+A stand, L1/R1+Up/Down)'}; "
             f"{clock} clock; robot {connect}")

        def on_signal(signum, frame):
            runner.request_stop()

        old = signal.signal(signal.SIGINT, on_signal)
        t0 = time.monotonic()
        try:
            result = runner.run()
        except DeployError as e:
            print(f"a2i-deploy: error: {e}", file=sys.stderr)
            return 2
        finally:
            signal.signal(signal.SIGINT, old)
    finally:
        if sim is not None:
            sim.stop()
    wall = time.monotonic() - t0
    _say("")
    _say(results_table(result.outcomes) if result.outcomes else "no leg was calibrated")
    _say("")
    if result.fault:
        _say(f"FAULT: the robot was damped: {result.fault}")
    for leg, err in sorted(result.imu_errors.items()):
        _say(f"foot IMU {leg}: {err}")
    _say(f"loop: {result.ticks} ticks in {wall:.1f} s wall; " + "; ".join(result.timing.lines()))
    if result.mcap_path is not None:
        _say(f"session recording: {result.mcap_path}")
    if sim is not None:
        _say(f"simulated truth: {out_dir / 'sim_truth.json'}")
    return 0 if result.ok else 1


if __name__ == "__main__":
    sys.exit(main())
