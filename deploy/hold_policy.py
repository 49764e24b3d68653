"""A stand-in policy that follows the exact file contract (``docs/policy-format.md``).

Its network outputs a constant action (zero: every joint holds the target it had when the
policy started; NaN: a broken network, for the supervisor's fault test). Useful for tests, for
benchmarks of the loop, and for bring-up on a robot hanging in a harness or a fixed-base mock,
where the lifted leg plays its schedule and the other legs just hold. It does not balance a
free robot on three legs: that is the trained policy's job.

Needs the ``onnx`` package (the ``train`` and ``dev`` extras), imported when called.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from calib.atomic import write_bytes_atomic, write_text_atomic
from calib.joints import SDK_JOINT_NAMES, SDK_LEGS, STAND_POSE_LEG, full_pose, position_limits
from deploy.lift_schedule import LiftSchedule
from deploy.observation import OBS_SIZE, default_terms

__all__ = ["hold_policy_metadata", "write_hold_policy"]


def hold_policy_metadata(name: str = "hold", kp: float = 40.0, kd: float = 1.0,
                         schedule: LiftSchedule | None = None) -> dict:
    """Metadata (schema_version 1) of a hold policy: default pose = stand pose, soft limits =
    joint limits minus 0.05 rad, the default lift schedule unless given."""
    default = full_pose(STAND_POSE_LEG, order="sdk")
    lo = np.concatenate([position_limits(leg)[0] for leg in SDK_LEGS])
    hi = np.concatenate([position_limits(leg)[1] for leg in SDK_LEGS])
    sched = schedule or LiftSchedule()
    return {
        "schema_version": 1,
        "name": name,
        "onnx": f"{name}.onnx",
        "created_utc": "1970-01-01T00:00:00+00:00",
        "commit": "",
        "seed": 0,
        "iterations": 0,
        "train_config": {"kind": "hold (constant action), not trained"},
        "control_dt": 0.02,
        "physics_dt": 0.005,
        "decimation": 4,
        "joint_order": list(SDK_JOINT_NAMES),
        "default_pose": [float(v) for v in default],
        "kp": [float(kp)] * 12,
        "kd": [float(kd)] * 12,
        "action": {"size": 12, "scale": 0.25, "clip": 100.0, "mode": "delta_target"},
        "soft_limits": {"lower": [float(v) + 0.05 for v in lo],
                        "upper": [float(v) - 0.05 for v in hi]},
        "observation": {"size": OBS_SIZE, "clip": 100.0, "terms": default_terms(default)},
        "lift_command": {"none": 0.0, "FL": 1.0, "FR": 2.0, "RL": 3.0, "RR": 4.0},
        "lift_schedule": sched.to_metadata(),
        "evaluation": {},
    }


def _constant_graph(value: float) -> bytes:
    import onnx
    from onnx import TensorProto, helper, numpy_helper

    w = numpy_helper.from_array(np.zeros((OBS_SIZE, 12), np.float32), "W")
    b = numpy_helper.from_array(np.full((12,), value, np.float32), "b")
    nodes = [helper.make_node("MatMul", ["obs", "W"], ["mm"]),
             helper.make_node("Add", ["mm", "b"], ["actions"])]
    graph = helper.make_graph(
        nodes, "hold",
        [helper.make_tensor_value_info("obs", TensorProto.FLOAT, ["batch", OBS_SIZE])],
        [helper.make_tensor_value_info("actions", TensorProto.FLOAT, ["batch", 12])],
        initializer=[w, b])
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])
    model.ir_version = 8
    onnx.checker.check_model(model)
    return model.SerializeToString()


def write_hold_policy(folder: str | Path, name: str = "hold", action_value: float = 0.0,
                      **meta_kwargs) -> Path:
    """Write ``<name>.onnx`` and ``<name>.json`` into ``folder``; returns the JSON path."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    write_bytes_atomic(folder / f"{name}.onnx", _constant_graph(float(action_value)))
    meta = hold_policy_metadata(name, **meta_kwargs)
    return write_text_atomic(folder / f"{name}.json", json.dumps(meta, indent=2) + "\n")
