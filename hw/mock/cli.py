"""``a2i-mock``: run the MuJoCo-backed mock Go2 on a Zenoh endpoint until Ctrl-C.

Prints the foot-IMU port of each leg and the truth file on start (stdout), a progress line
every few seconds (stderr). Exit codes: 0 clean stop (SIGINT/SIGTERM), 1 the simulation
failed, 2 bad input (endpoint, config file, unknown key, value).
"""

from __future__ import annotations

import argparse
import os
import signal
import sys
import tempfile
import threading
import time

from calib.atomic import os_error_line
from hw.mock.config import CLOCKS, MockConfig, load_config

__all__ = ["main"]


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="a2i-mock",
        description="MuJoCo-backed mock Unitree Go2: rt/lowstate, rt/lowcmd and "
                    "rt/wirelesscontroller on Zenoh, foot IMUs on pty serial ports. "
                    "Reference: docs/mock-robot.md.")
    p.add_argument("--listen", metavar="ENDPOINT",
                   help="Zenoh endpoint to listen on (default tcp/127.0.0.1:7447)")
    p.add_argument("--config", metavar="PATH", help="mock config, .json or .yaml")
    p.add_argument("--seed", type=int, help="seed of every random choice (mountings, offsets, "
                   "noise)")
    p.add_argument("--clock", choices=CLOCKS, help="realtime (default) or lockstep "
                   "(one 4 ms quantum per rt/lowcmd, as a2i-deploy sends them)")
    p.add_argument("--truth", metavar="PATH", help="where to write the ground-truth JSON "
                   "(default: a2i-mock-truth-<pid>.json in the temp folder)")
    p.add_argument("--progress", type=float, default=5.0, metavar="S",
                   help="seconds between progress lines on stderr (0: none; default 5)")
    return p


class _Exit(Exception):
    def __init__(self, code: int, msg: str):
        super().__init__(msg)
        self.code = code


def _build_config(a: argparse.Namespace) -> MockConfig:
    over = {"listen": [a.listen] if a.listen else None, "seed": a.seed, "clock": a.clock,
            "truth_path": a.truth}
    try:
        if a.config:
            cfg = load_config(a.config, **over)
        else:
            cfg = MockConfig.from_dict({k: v for k, v in over.items() if v is not None})
    except (ValueError, TypeError) as e:
        raise _Exit(2, str(e).splitlines()[0]) from None
    if not cfg.truth_path:
        cfg.truth_path = os.path.join(tempfile.gettempdir(), f"a2i-mock-truth-{os.getpid()}.json")
    if not cfg.listen and not cfg.connect:
        raise _Exit(2, "no Zenoh endpoint: give --listen (e.g. tcp/127.0.0.1:7447)")
    return cfg


def _progress_line(st: dict) -> str:
    return (f"a2i-mock: sim {st['sim_time_s']:8.2f} s  RTF {st['rtf']:5.2f}  commands "
            f"good {st['commands_good']} bad-crc {st['commands_bad_crc']} "
            f"malformed {st['commands_malformed']}  lowstates {st['lowstates_published']}  "
            f"late ticks {st['late_ticks']}")


def main(argv: list[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    try:
        cfg = _build_config(args)
        # Imported here so that --help and bad input answer without loading MuJoCo.
        from hw.mock.robot import MockRobot
        from hw.transport import TransportError
        try:
            robot = MockRobot(cfg)
            robot.open()
        except ValueError as e:
            raise _Exit(2, str(e).splitlines()[0]) from None
        except TransportError as e:
            raise _Exit(2, str(e).splitlines()[0]) from None
        except OSError as e:  # --truth not writable
            raise _Exit(2, os_error_line(e)) from None
    except _Exit as e:
        print(f"a2i-mock: error: {e}", file=sys.stderr)
        return e.code

    stop = threading.Event()

    def on_signal(signum, frame):
        stop.set()

    old = {s: signal.signal(s, on_signal) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        print(f"a2i-mock: {cfg.clock} clock, listening on {', '.join(cfg.listen)}, "
              f"seed {cfg.seed}", flush=True)
        for leg, port in robot.imu_ports.items():
            ch = robot.channels[leg]
            print(f"a2i-mock: foot IMU {leg}: {port} (node {ch.node_id}, "
                  f"{ch.imu.sensor.rate:g} Hz)", flush=True)
        print(f"a2i-mock: truth: {robot.truth_path}", flush=True)
        robot.start()
        next_progress = time.monotonic() + args.progress
        while not stop.wait(0.1):
            if not robot.running:
                break
            if args.progress > 0 and time.monotonic() >= next_progress:
                next_progress += args.progress
                print(_progress_line(robot.stats()), file=sys.stderr, flush=True)
    finally:
        robot.stop()
        for s, h in old.items():
            signal.signal(s, h)
    if robot.error is not None:
        print(f"a2i-mock: error: simulation stopped: {robot.error}", file=sys.stderr)
        return 1
    print(_progress_line(robot.stats()), file=sys.stderr, flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
