"""``--sim``: the MuJoCo mock robot started beside the deploy program, on Zenoh loopback.

The deploy code path is the robot's: it connects to the mock's endpoint and opens the mock's
pty foot-IMU ports as serial ports. ``lockstep`` runs the mock in this process (deterministic,
faster than real time); ``realtime`` runs it as a child process (``python -m hw.mock.cli``) so
that its 1 kHz physics thread does not share this process's interpreter lock with the 50 Hz loop.

MuJoCo is imported only here, and only when ``--sim`` is given (``hw.mock`` lazily).
"""

from __future__ import annotations

import json
import os
import socket
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from calib.atomic import write_text_atomic
from deploy.runtime import ImuPort

__all__ = ["SimHandle", "free_tcp_port", "start_sim", "truth_tuples", "write_sim_truth"]


def free_tcp_port() -> int:
    """A TCP port on 127.0.0.1 that was free a moment ago."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@dataclass
class SimHandle:
    """A running mock: its endpoint, foot-IMU ports, ground truth, and how to stop it."""

    connect: str
    imus: list[ImuPort]
    truth: dict
    clock: str
    mock: object = None
    proc: subprocess.Popen | None = None
    _tmp: list[Path] = field(default_factory=list)

    def stop(self) -> None:
        if self.mock is not None:
            self.mock.stop()
            self.mock = None
        if self.proc is not None:
            self.proc.terminate()
            try:
                self.proc.wait(10)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(5)
            self.proc = None
        for p in self._tmp:
            try:
                p.unlink()
            except OSError:
                pass
        self._tmp = []


def _config_dict(seed: int, clock: str, listen: str, extra: dict | None) -> dict:
    d = {"seed": int(seed), "clock": clock, "listen": [listen], "initial_pose": "lying"}
    for k, v in (extra or {}).items():
        if k in ("listen", "connect", "clock", "seed"):
            raise ValueError(f"--sim-config must not set {k!r} (use the deploy options)")
        d[k] = v
    return d


def start_sim(seed: int = 0, clock: str = "lockstep", extra_config: dict | None = None,
              in_process: bool | None = None, start_timeout_s: float = 60.0) -> SimHandle:
    """Start the mock with ``seed`` (mountings, offsets, noise) on a free loopback port.

    extra_config: more :class:`hw.mock.config.MockConfig` fields (e.g. ``{"base": "fixed"}``).
    in_process: None = lockstep in process, realtime as a child.
    """
    listen = f"tcp/127.0.0.1:{free_tcp_port()}"
    d = _config_dict(seed, clock, listen, extra_config)
    if in_process is None:
        in_process = clock == "lockstep"
    if in_process:
        from hw.mock.config import MockConfig
        from hw.mock.robot import MockRobot

        robot = MockRobot(MockConfig.from_dict(d))
        robot.start()
        truth = robot.truth()
        imus = [ImuPort(leg, port) for leg, port in robot.imu_ports.items()]
        return SimHandle(listen, imus, truth, clock, mock=robot)
    tmpdir = Path(tempfile.gettempdir())
    cfg_path = tmpdir / f"a2i-deploy-mock-{os.getpid()}.json"
    truth_path = tmpdir / f"a2i-deploy-mock-truth-{os.getpid()}.json"
    for p in (truth_path,):
        if p.exists():
            p.unlink()
    write_text_atomic(cfg_path, json.dumps(d))
    proc = subprocess.Popen(
        [sys.executable, "-m", "hw.mock.cli", "--config", str(cfg_path), "--truth",
         str(truth_path), "--progress", "0"],
        stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    handle = SimHandle(listen, [], {}, clock, proc=proc, _tmp=[cfg_path, truth_path])
    deadline = time.monotonic() + start_timeout_s
    while not truth_path.exists():
        if proc.poll() is not None:
            err = (proc.stderr.read() if proc.stderr else "").strip().splitlines()
            handle.stop()
            raise RuntimeError("the mock robot did not start: "
                               + (err[-1] if err else f"exit code {proc.returncode}"))
        if time.monotonic() > deadline:
            handle.stop()
            raise RuntimeError(f"the mock robot did not start within {start_timeout_s:g} s")
        time.sleep(0.05)
    truth = json.loads(truth_path.read_text(encoding="utf-8"))
    handle.truth = truth
    handle.imus = [ImuPort(leg, t["port"]) for leg, t in truth.items() if t.get("port")]
    return handle


def truth_tuples(truth: dict) -> dict[str, tuple[np.ndarray, float]]:
    """leg -> (R_I^F (3, 3), t_d s) from the mock's truth."""
    return {leg: (np.asarray(t["rotation_matrix"], dtype=float), float(t["time_offset_s"]))
            for leg, t in truth.items()}


def write_sim_truth(path: Path, truth: dict) -> Path:
    """``sim_truth.json``: {leg: {rotation_matrix, time_offset_s, ...}} in the result format's
    conventions (R_I^F maps IMU-frame vectors into the foot frame; t_d = t_I - t_E)."""
    keep = ("rotation_matrix", "quaternion_wxyz", "rpy_deg", "time_offset_s", "foot_frame")
    data = {leg: {k: t[k] for k in keep if k in t} for leg, t in truth.items()}
    return write_text_atomic(path, json.dumps(data, indent=2) + "\n")
