"""The a2i-mock command (run as ``python -m hw.mock.cli``): help, bad input, start and stop."""

from __future__ import annotations

import json
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

from loopback import free_endpoint

REPO = Path(__file__).resolve().parents[1]
CMD = [sys.executable, "-m", "hw.mock.cli"]


def run(*args: str, timeout: float = 30.0) -> subprocess.CompletedProcess:
    return subprocess.run([*CMD, *args], check=False, cwd=REPO, capture_output=True, text=True,
                          timeout=timeout)


def test_help():
    p = run("--help")
    assert p.returncode == 0
    for flag in ("--listen", "--config", "--seed", "--clock", "--truth"):
        assert flag in p.stdout


def test_bad_input_exits_2_with_one_line(tmp_path):
    p = run("--listen", "tcp/127.0.0.1")
    assert p.returncode == 2
    assert p.stderr.strip().count("\n") == 0 and "proto/host:port" in p.stderr
    cfg = tmp_path / "m.json"
    cfg.write_text(json.dumps({"clock": "lockstep", "colck": 1}))
    p = run("--config", str(cfg))
    assert p.returncode == 2 and "unknown key 'colck'" in p.stderr
    assert p.stderr.strip().count("\n") == 0
    p = run("--config", str(tmp_path / "missing.yaml"))
    assert p.returncode == 2 and "cannot read" in p.stderr
    p = run("--listen", free_endpoint(), "--truth", str(tmp_path))  # a folder: not writable
    assert p.returncode == 2 and p.stderr.strip() == f"a2i-mock: error: {tmp_path}: is a directory"


def test_endpoint_in_use_exits_2():
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen()
        p = run("--listen", f"tcp/127.0.0.1:{s.getsockname()[1]}")
    assert p.returncode == 2
    assert p.stderr.strip().count("\n") == 0 and "cannot open zenoh" in p.stderr


def test_start_prints_ports_and_truth_then_sigint_exits_0(tmp_path):
    truth = tmp_path / "truth.json"
    proc = subprocess.Popen([*CMD, "--listen", free_endpoint(), "--seed", "3", "--clock",
                             "realtime", "--truth", str(truth), "--progress", "0.5"],
                            cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        lines = []
        deadline = time.monotonic() + 30.0
        while time.monotonic() < deadline:
            line = proc.stdout.readline()
            if not line:
                break
            lines.append(line)
            if "truth:" in line:
                break
        assert any("truth:" in ln for ln in lines), lines
        ports = {ln.split()[3].rstrip(":"): ln.split()[4] for ln in lines if "foot IMU" in ln}
        assert set(ports) == {"FL", "FR", "RL", "RR"}
        assert all(p.startswith("/dev/") for p in ports.values())
        time.sleep(1.2)
        proc.send_signal(signal.SIGINT)
        _, err = proc.communicate(timeout=15)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 0, err
    assert "RTF" in err and "commands good 0" in err
    data = json.loads(truth.read_text())
    assert {leg: d["port"] for leg, d in data.items()} == ports
    assert all(abs(d["time_offset_s"]) <= 0.1 for d in data.values())
