"""The four-leg stand a policy graph plays while no leg is lifted (lift command ``none``).

A network trained with one side's lifts and played mirrored for the other (``mirrored_legs``)
learns, with the command ``none``, a stand that already leans away from the leg it lifts most:
v26's puts the centre of mass 55-70 mm right of the feet's centre within 2 s, ready for FL and
on the wrong side for FR (``docs/policy-training.md``, "Stop 48"). A script that stands
the robot on the policy before an FR lift then starts that lift where the policy never started
it in training or evaluation, which start from the default pose with the command given at once.

``home`` replaces that stand in the graph with a fixed law: while the newest frame's command is
``none`` the actions are ``-gain / s * o_q``, ``o_q = s (q - q_default)`` the frame's
``joint_pos`` term, so each 50 Hz tick moves every joint's target by ``-scale_a * gain`` of its
error from the default pose. It integrates: the joints settle at the default pose itself, the
sag of the PD law under the body's weight taken out (v27: gain 0.2 and the action scale 0.1,
2 % of the error per tick, a time constant of about 1 s; at gain 1 the evaluation lost rear
lifts to falls after the leg was set down, and at 0.2 still some: v27 is a candidate). The
stand is then left-right symmetric and the start every lift was evaluated from. Any other
command plays the network as before.

``hold`` plays zero actions instead, from the reset until the network first acts (a lift):
the joint targets stay at the pose the robot stood up to, and the joints sag under the PD law
as far as the body's weight bends them (v26's gains: 0.23-0.25 rad at the calves, the base
32 mm lower on Menagerie's model). It is as symmetric as ``home``. The graph is stateless, so
the latch is its own output fed back: ``previous_actions`` is exactly zero after a reset and
while the hold plays, and not once the network has played a lift, so after the lowering the
network's own stand plays again, from wherever the feet were set down. Without the latch the
hold (like v27's ``home``) stood the robot on after the lowering on targets the lift left
behind, and lost rear lifts there in the evaluation (``docs/policy-training.md``, "Stop 49").

The integral needs damped joints: at the training's gains (kp 20, kd 0.5 on every joint) the
body rocks on its legs and tips over within 2-4 s at stand gains 0.1-0.5, where deploy's gains
since v20 (kd 8 on hips and thighs) settle it. So :func:`settle` plays the stand on the free-base
simulator and ``a2i-train derive --stand`` refuses a policy whose stand does not settle (the
hold's too: at the training's gains it leaves the body rocking).

The edit is made on the ONNX graph itself (nodes appended after the network's output), so the
network's weights stay byte for byte the source's and every script that runs the graph, deploy
or a checker's, gets the same stand.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

STAND_MODES = ("network", "home", "hold")
"""``network``: the graph as trained; ``home``: the integral stand at the default pose;
``hold``: zero actions, the joint targets held, until the network first acts."""

_PREFIX = "stand_"  # names of what this module adds to a graph

HOLD_LATCH = 1e-6
"""Raw action units: ``hold`` plays while the newest frame's ``previous_actions`` sum below
this in absolute value: exactly zero after a reset and while the hold plays; below it, all
twelve of a network's outputs would have to vanish at once."""


def _term_columns(obs_terms, name: str) -> tuple[int, int, float, np.ndarray | None]:
    """(first column, size, scale, offset) of term ``name`` in one observation frame."""
    off = 0
    for t in obs_terms:
        if t["name"] == name:
            offset = t.get("offset")
            return off, int(t["size"]), float(t["scale"]), \
                None if offset is None else np.asarray(offset, float)
        off += int(t["size"])
    raise ValueError(f"the observation has no {name} term")


def has_stand(model) -> bool:
    """Whether the ONNX graph (a ModelProto) already carries a stand added here."""
    return any(n.name.startswith(_PREFIX) for n in model.graph.node)


def stand_spec(mode: str, gain: float | None = None) -> dict:
    """The JSON's ``stand`` for ``mode`` (:data:`STAND_MODES`); ``home`` needs its gain (raw
    action per unit of ``joint_pos`` error, in (0, 5)), the others take none. ValueError
    otherwise."""
    if mode not in STAND_MODES:
        raise ValueError(f"unknown stand {mode!r}; known: {', '.join(STAND_MODES)}")
    if mode != "home":
        if gain is not None:
            raise ValueError(f"the {mode} stand takes no gain")
        return {"mode": mode}
    if gain is None or not (np.isfinite(gain) and 0 < gain < 5):
        raise ValueError(f"the home stand's gain must be in (0, 5), got {gain}")
    return {"mode": "home", "gain": float(gain)}


def add_stand(onnx_bytes: bytes, observation: dict, lift_none_value: float, default_pose,
              stand: dict) -> bytes:
    """The graph ``onnx_bytes`` playing ``stand`` (:func:`stand_spec`; module docstring) where
    the newest frame's ``lift_command`` is ``lift_none_value``. observation: the JSON's
    ``observation`` (terms, in frame order; the newest frame first); default_pose: the JSON's
    (12, rad), which ``home`` needs the ``joint_pos`` term measured from. ValueError on a graph
    that already has a stand, on terms without ``lift_command`` (or, for ``home``, without a
    ``joint_pos`` measured from the default pose)."""
    import onnx
    from onnx import TensorProto, helper, numpy_helper

    stand = stand_spec(stand.get("mode"), stand.get("gain"))
    if stand["mode"] == "network":
        return onnx_bytes
    terms = observation["terms"]
    c_at, _, c_scale, _ = _term_columns(terms, "lift_command")
    if stand["mode"] == "home":
        q_at, q_size, q_scale, q_offset = _term_columns(terms, "joint_pos")
        if q_size != 12:
            raise ValueError(f"joint_pos has {q_size} values, expected 12")
        if q_offset is None or not np.allclose(q_offset, default_pose, atol=1e-9):
            raise ValueError("joint_pos is not measured from the default pose: the stand would "
                             "hold another one")
    model = onnx.load_from_string(onnx_bytes)
    if has_stand(model):
        raise ValueError("the graph already has a stand; derive from its source instead")
    g = model.graph
    if len(g.output) != 1:
        raise ValueError(f"expected one graph output, got {len(g.output)}")
    out = g.output[0].name
    net_out = _PREFIX + "network_actions"
    for n in g.node:
        n.output[:] = [net_out if o == out else o for o in n.output]
    obs = g.input[0].name

    def const(name, value, dtype=np.float32):
        g.initializer.append(numpy_helper.from_array(np.asarray(value, dtype), _PREFIX + name))
        return _PREFIX + name

    def node(op, inputs, name, **attrs):
        g.node.append(helper.make_node(op, inputs, [_PREFIX + name], name=_PREFIX + name,
                                       **attrs))
        return _PREFIX + name

    axis1 = const("axis1", [1], np.int64)
    if stand["mode"] == "home":
        q = node("Slice", [obs, const("q_lo", [q_at], np.int64),
                           const("q_hi", [q_at + 12], np.int64), axis1], "joint_pos")
        actions = node("Mul", [q, const("gain", -stand["gain"] / q_scale)], "home_actions")
    else:  # hold: a constant, so a non-finite network output cannot leak into it
        actions = const("hold_actions", np.zeros((1, 12)))
    c = node("Slice", [obs, const("c_lo", [c_at], np.int64),
                       const("c_hi", [c_at + 1], np.int64), axis1], "lift_command")
    # the command's values are c_scale apart: nearer than half of that is the value
    dist = node("Abs", [node("Sub", [c, const("none", lift_none_value * c_scale)], "c_minus")],
                "c_dist")
    play = none = node("Less", [dist, const("half_step", 0.5 * abs(c_scale))], "no_lift")
    if stand["mode"] == "hold":
        # the latch: the graph's own last output comes back as previous_actions, all zero from
        # the reset for as long as the hold plays; once the network has acted (a lift) it is
        # not, and the network's stand plays on. A sum by MatMul needs no opset-specific Reduce.
        p_at, _, p_scale, _ = _term_columns(terms, "previous_actions")
        prev = node("Abs", [node("Slice", [obs, const("p_lo", [p_at], np.int64),
                                           const("p_hi", [p_at + 12], np.int64), axis1],
                                 "previous_actions")], "previous_abs")
        moved = node("MatMul", [prev, const("ones", np.ones((12, 1)))], "previous_sum")
        fresh = node("Less", [moved, const("at_rest", HOLD_LATCH * abs(p_scale))], "not_acted")
        play = node("And", [none, fresh], "hold_plays")
    g.node.append(helper.make_node("Where", [play, actions, net_out], [out],
                                   name=_PREFIX + "select"))
    g.value_info.append(helper.make_tensor_value_info(net_out, TensorProto.FLOAT,
                                                      ["batch", 12]))
    onnx.checker.check_model(model)
    return model.SerializeToString()


def apply_stand(onnx_bytes: bytes, meta: dict) -> bytes:
    """The graph with the stand the policy JSON ``meta`` names (its ``stand``; absent or
    ``network``: unchanged): for a graph rebuilt from a policy's network (``a2i-train refine``),
    so that its JSON's stand is the one it plays."""
    return add_stand(onnx_bytes, meta["observation"], meta["lift_command"]["none"],
                     meta["default_pose"], meta.get("stand") or {"mode": "network"})


SETTLE_S = 4.0
"""s of standing :func:`settle` plays."""
MAX_SETTLED_ERROR = 0.02
"""rad: for ``home``, the joints' largest distance from the default pose at the end of
:func:`settle` (``hold`` leaves them where the PD law sags to under the body's weight)."""
MAX_SETTLED_DRIFT = 0.01
"""rad: the joints' largest motion over the last second of :func:`settle` (at rest)."""
MAX_SETTLE_TILT_DEG = 10.0
"""deg: the body's largest tilt during :func:`settle`."""


@dataclass(frozen=True)
class Settle:
    """How a policy's stand (lift command none) stands the robot: after :data:`SETTLE_S` s
    from the default pose on the level floor of the URDF's model, nothing else perturbing it.
    mode: the stand's (:data:`STAND_MODES`); error_rad: the joints' largest distance from the
    default pose at the end; drift_rad: their largest motion over the last second; tilt_deg:
    the body's largest tilt on the way."""

    mode: str
    error_rad: float
    drift_rad: float
    tilt_deg: float

    @property
    def settled(self) -> bool:
        return (self.tilt_deg <= MAX_SETTLE_TILT_DEG and self.drift_rad <= MAX_SETTLED_DRIFT
                and (self.mode != "home" or self.error_rad <= MAX_SETTLED_ERROR))

    def why_not(self) -> str:
        """One line on what :attr:`settled` found wrong ('' when settled)."""
        bad = []
        if self.mode == "home" and self.error_rad > MAX_SETTLED_ERROR:
            bad.append(f"the joints end {self.error_rad:.3f} rad from the default pose (at most "
                       f"{MAX_SETTLED_ERROR})")
        if self.drift_rad > MAX_SETTLED_DRIFT:
            bad.append(f"they still moved {self.drift_rad:.3f} rad in the last second (at most "
                       f"{MAX_SETTLED_DRIFT})")
        if self.tilt_deg > MAX_SETTLE_TILT_DEG:
            bad.append(f"the body tilted {self.tilt_deg:.1f} deg (at most "
                       f"{MAX_SETTLE_TILT_DEG:g})")
        return "; ".join(bad)


def settle(json_path, seconds: float = SETTLE_S) -> Settle:
    """Play the policy at ``json_path`` (its ONNX beside it) with no lift command, as on board
    (50 Hz, the JSON's gains, 1 kHz physics), from the default pose; seconds: at least 1."""
    from calib.joints import model_to_sdk, sdk_to_model
    from deploy.observation import build_observation
    from deploy.policy import PolicyMeta, PolicyRunner
    from policy_train.policy_motion import policy_signals
    from sim.free_base_run import free_base_sim

    if not seconds >= 1.0:
        raise ValueError(f"settle needs at least 1 s, got {seconds}")
    pm = PolicyMeta.load(json_path)
    mode = (json.loads(Path(json_path).read_text()).get("stand") or {}).get("mode", "network")
    runner = PolicyRunner(pm)
    dt = 0.001
    n_ctrl = round(pm.control_dt / dt)
    n = round(seconds / dt)
    sim = free_base_sim(dt, sdk_to_model(pm.default_pose))
    runner.reset(model_to_sdk(sim.q))
    kp, kd = sdk_to_model(pm.kp), sdk_to_model(pm.kd)
    tilt = 0.0
    lo = hi = None  # the joints' range over the last second (SDK order)
    for k in range(n):
        if k % n_ctrl == 0:
            signals = policy_signals(sim, runner, pm.lift_value(None))
            runner.step(runner.act(build_observation(pm.observation, signals)), sim.q_sdk)
            sim.set_command(sdk_to_model(runner.target), np.zeros(12), kp, kd, 0.0)
        sim.step()
        tilt = max(tilt, sim.base_tilt)
        if k >= n - round(1.0 / dt):
            q = sim.q_sdk
            lo = q if lo is None else np.minimum(lo, q)
            hi = q if hi is None else np.maximum(hi, q)
    return Settle(mode, float(np.abs(sim.q_sdk - pm.default_pose).max()),
                  float((hi - lo).max()), float(np.degrees(tilt)))
