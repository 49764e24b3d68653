"""The import arrows of ARCHITECTURE.md, checked on the source (AST), and the on-board path's
independence from the training and simulation extras, checked by importing it in a fresh
interpreter where torch and mujoco cannot be imported."""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PROJECT = ("calib", "sim", "hw", "policy_train", "deploy", "sim2real", "cli", "tests", "bench")


def _imports(path: Path) -> set[str]:
    """Top-level names and 'pkg.sub' prefixes imported anywhere in the file."""
    tree = ast.parse(path.read_text(encoding="utf-8"))
    out = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            out.add(node.module)
    return out


def _files(pkg: str):
    return sorted((ROOT / pkg).rglob("*.py"))


def _violations(pkg: str, forbidden, allowed=()) -> list[str]:
    bad = []
    for f in _files(pkg):
        for mod in _imports(f):
            top = mod.split(".")[0]
            if any(mod == a or mod.startswith(a + ".") for a in allowed):
                continue
            if top in forbidden:
                bad.append(f"{f.relative_to(ROOT)} imports {mod}")
    return bad


def test_calib_imports_nothing_of_the_project():
    assert _violations("calib", set(PROJECT) - {"calib"}) == []


def test_sim_never_imports_hw_or_deploy():
    assert _violations("sim", {"hw", "deploy", "policy_train", "sim2real", "cli", "tests",
                               "bench"}) == []


def test_hw_outside_mock_never_imports_sim():
    bad = [v for v in _violations("hw", {"sim", "deploy", "policy_train", "sim2real", "cli",
                                         "tests", "bench"})
           if not v.startswith("hw/mock/")]
    assert bad == []
    # and of calib only the pure utilities (docs/architecture-notes.md)
    assert [v for v in _violations("hw", {"calib"}, allowed=("calib.joints", "calib.atomic"))
            if not v.startswith("hw/mock/")] == []


def test_policy_train_takes_only_the_shared_contract_from_deploy():
    assert _violations("policy_train", {"hw", "sim2real", "cli", "tests", "bench", "deploy"},
                       allowed=("deploy.observation", "deploy.lift_schedule", "deploy.action",
                                "deploy.tracking_adapter", "deploy.tip_guard", "deploy.lift_gate",
                                "deploy.policy")) == []


def test_nothing_imports_tests_or_bench():
    for pkg in ("calib", "sim", "hw", "policy_train", "deploy", "sim2real", "cli"):
        assert _violations(pkg, {"tests", "bench"}) == [], pkg


BLOCKER = """
import importlib.abc, sys
class Block(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path=None, target=None):
        if name.split('.')[0] in ('torch', 'mujoco', 'rsl_rl'):
            raise ImportError('blocked for this test: ' + name)
sys.meta_path.insert(0, Block())
"""


@pytest.mark.parametrize("module", [
    "calib.pipeline", "calib.excitation", "calib.motions", "cli.calib", "hw.transport",
    "hw.go2_msgs", "hw.recorder", "hw.mcap_io", "hw.imu_serial", "hw.joystick",
])
def test_on_board_path_imports_without_torch_and_mujoco(module):
    code = BLOCKER + f"import importlib; importlib.import_module({module!r})"
    r = subprocess.run([sys.executable, "-c", code], check=False, capture_output=True,
                       text=True, cwd=ROOT)
    assert r.returncode == 0, r.stderr[-2000:]


def test_deploy_imports_without_torch_and_mujoco():
    mods = [f"deploy.{p.stem}" for p in _files("deploy") if p.stem not in ("__init__",)]
    # --sim starts the mock lazily: only that path may need mujoco
    mods = [m for m in mods if m not in ("deploy.simulate",)]
    if not mods:
        pytest.skip("no deploy modules yet")
    code = BLOCKER + "import importlib\n" + "\n".join(
        f"importlib.import_module({m!r})" for m in mods)
    r = subprocess.run([sys.executable, "-c", code], check=False, capture_output=True,
                       text=True, cwd=ROOT)
    assert r.returncode == 0, r.stderr[-2000:]
