"""Left-right mirror of the tripod task, for rsl-rl's symmetry data augmentation.

The Go2 is left-right symmetric, and so is the task: lifting FL mirrored through the base's
x-z plane is lifting FR. Every PPO mini-batch gets each sample's mirror image appended
(rsl-rl ``Symmetry``, Mittal et al., ICRA 2024), so that what the policy learns on one side
it learns on the other (v5 balanced FL nominally while FR still fell).

The reflection y -> -y maps
* polar vectors (linear velocity, gravity) ``(x, y, z) -> (x, -y, z)``;
* axial vectors (angular velocity, the angular-velocity command) ``(x, y, z) -> (-x, y, -z)``;
* joints: legs FR <-> FL and RR <-> RL, the hip (about x) negated, thigh and calf (about y)
  kept; the default pose is symmetric, so joint offsets, rates and ``delta_target`` actions
  mirror alike;
* the lift command: FL <-> FR and RL <-> RR.

The mirror is a signed permutation of each observation group except the lift command (a
value map), built once from the environment's term layouts.
"""

from __future__ import annotations

import numpy as np
import torch
from tensordict import TensorDict

from calib.joints import MODEL_LEGS, SDK_LEGS, check_leg
from policy_train.env import LIFT_VALUES, PRIV_TERMS

__all__ = ["ActionMirror", "Mirror", "MirroredLegsActor", "joint_mirror", "mirror_augmentation",
           "mirror_source", "policy_terms"]

_SWAP = {"FL": "FR", "FR": "FL", "RL": "RR", "RR": "RL"}
_POLAR = np.array([1.0, -1.0, 1.0])
_AXIAL = np.array([-1.0, 1.0, -1.0])


def mirror_source(leg: str) -> str:
    """The leg on the other side whose mirror image ``leg`` is (FR -> FL, ...)."""
    return _SWAP[check_leg(leg)]


def joint_mirror(legs: tuple[str, ...]) -> tuple[np.ndarray, np.ndarray]:
    """(index, sign) of a 12-joint vector in leg order ``legs``: ``mirrored = x[index] * sign``."""
    idx = np.concatenate([3 * legs.index(_SWAP[g]) + np.arange(3) for g in legs])
    return idx, np.tile([-1.0, 1.0, 1.0], 4)


def _leg_values_map() -> np.ndarray:
    """Lift-command value v -> the mirrored leg's value (0, none, stays 0)."""
    m = np.zeros(max(LIFT_VALUES.values()) + 1, dtype=int)
    for leg, v in LIFT_VALUES.items():
        m[v] = LIFT_VALUES[_SWAP.get(leg, leg)]
    return m


_TERM_MIRROR = {  # observation term name -> (index within the term, sign)
    "base_lin_vel": (np.arange(3), _POLAR),
    "base_ang_vel": (np.arange(3), _AXIAL),
    "projected_gravity": (np.arange(3), _POLAR),
    "joint_pos": joint_mirror(SDK_LEGS),
    "joint_vel": joint_mirror(SDK_LEGS),
    "previous_actions": joint_mirror(SDK_LEGS),
    "commands": (np.arange(3), _AXIAL),
    "lift_command": (np.arange(1), np.ones(1)),  # value map below
    # privileged critic terms (policy_train.env.PRIV_TERMS)
    "lin_vel": (np.arange(3), _POLAR),
    "foot_contact": (np.array([MODEL_LEGS.index(_SWAP[g]) for g in MODEL_LEGS]), np.ones(4)),
    "lift_error": (np.arange(3), np.array([-1.0, 1.0, 1.0])),  # hip, thigh, calf
}


class Mirror(torch.nn.Module):
    """The mirror of one observation group laid out as ``terms`` ((name, size) in order).
    Terms not listed in the mirror table are left-right invariant (scalars: height, gains,
    friction, phase, timers, contact flags of the whole body). A module (constant buffers, no
    in-place ops) so that an exported ONNX graph can hold it."""

    def __init__(self, terms, lift_scale: float | None = None, frames: int = 1):
        super().__init__()
        idx, sign, off = [], [], 0
        lift_at = None
        for name, size in terms:
            if name in _TERM_MIRROR:
                i, sg = _TERM_MIRROR[name]
                if len(i) != size:
                    raise ValueError(f"mirror of term {name}: size {size}, expected {len(i)}")
                idx.append(off + np.asarray(i))
                sign.append(np.asarray(sg, dtype=float))
            else:
                idx.append(off + np.arange(size))
                sign.append(np.ones(size))
            if name == "lift_command":
                if lift_scale is None:
                    raise ValueError("lift_command needs its observation scale")
                lift_at = off
            off += size
        if frames < 1:
            raise ValueError(f"frames must be >= 1, got {frames}")
        # a history of frames (newest first) mirrors frame by frame
        index = np.concatenate([np.concatenate(idx) + f * off for f in range(frames)])
        self.size = off * frames
        self.lift_at = lift_at  # in the newest frame
        self.lift_scale = float(lift_scale or 1.0)
        self.register_buffer("index", torch.from_numpy(index))
        self.register_buffer("sign", torch.from_numpy(np.tile(np.concatenate(sign), frames)).float())
        self.register_buffer("values", torch.from_numpy(_leg_values_map()).float())
        col = torch.zeros(self.size, dtype=torch.bool)
        if lift_at is not None:
            col[lift_at + off * np.arange(frames)] = True
        self.register_buffer("lift_column", col)

    def _values_of(self, x: torch.Tensor) -> torch.Tensor:
        return torch.round(x / self.lift_scale).long().clamp(0, self.values.shape[0] - 1)

    def lift_value(self, x: torch.Tensor) -> torch.Tensor:
        """The lift-command value (0 none, 1-4 legs) of observations (..., size), long: the
        newest frame's."""
        return self._values_of(x[..., self.lift_at])

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """Mirror (..., size) observations."""
        y = x[..., self.index] * self.sign.to(x.dtype)
        if self.lift_at is None:
            return y
        # every column read as a lift value; only the lift columns keep it
        lv = (self.values[self._values_of(x)] * self.lift_scale).to(x.dtype)
        return torch.where(self.lift_column, lv, y)


class ActionMirror(torch.nn.Module):
    """The mirror of 12 joint actions (SDK order): legs swapped, hips negated."""

    def __init__(self):
        super().__init__()
        idx, sign = joint_mirror(SDK_LEGS)
        self.register_buffer("index", torch.from_numpy(idx))
        self.register_buffer("sign", torch.from_numpy(sign).float())

    def forward(self, a: torch.Tensor) -> torch.Tensor:
        return a[..., self.index] * self.sign.to(a.dtype)


class MirroredLegsActor(torch.nn.Module):
    """An actor whose lifts of the legs in ``mirror_legs`` (leg -> source leg on the other
    side) are played as the mirror image of its own lifts of the source leg:
    ``a = M_a(actor(M_o(obs)))`` when the lift command names such a leg, ``actor(obs)``
    otherwise (the newest frame's command, over a history of ``frames`` frames). Valid because
    the robot and the task are left-right symmetric (``tests/test_symmetry.py``); used when PPO
    learnt one side better than the other."""

    def __init__(self, actor: torch.nn.Module, obs_terms, mirror_legs: dict, frames: int = 1):
        super().__init__()
        for leg, src in mirror_legs.items():
            if _SWAP.get(leg) != src:
                raise ValueError(f"{leg} can only mirror {_SWAP.get(leg, '?')}, not {src}")
        terms, scale = policy_terms(obs_terms)
        self.actor = actor
        self.obs_mirror = Mirror(terms, scale, frames)
        if self.obs_mirror.lift_at is None:
            raise ValueError("the observation has no lift_command term")
        self.action_mirror = ActionMirror()
        self.register_buffer("mirrored_values", torch.tensor(
            [LIFT_VALUES[g] for g in mirror_legs], dtype=torch.long))

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        a = self.actor(obs)
        am = self.action_mirror(self.actor(self.obs_mirror(obs)))
        v = self.obs_mirror.lift_value(obs)
        use = (v.unsqueeze(-1) == self.mirrored_values).any(-1, keepdim=True)
        return torch.where(use, am, a)


def policy_terms(obs_terms) -> tuple[list[tuple[str, int]], float | None]:
    """(name, size) of each observation term (the JSON's ``observation.terms``) and the
    ``lift_command`` term's scale (None without one)."""
    terms = [(t["name"], int(t["size"])) for t in obs_terms]
    lift = [t for t in obs_terms if t["name"] == "lift_command"]
    scale = float(np.ravel(lift[0]["scale"])[0]) if lift else None
    return terms, scale


class _Mirrors:
    def __init__(self, env, device):
        terms, scale = policy_terms(env.obs_terms)
        # a policy that sees a history mirrors frame by frame; the critic sees one frame
        self.policy = Mirror(terms, scale, env.cfg.obs_history).to(device)
        self.critic = Mirror(terms + list(PRIV_TERMS), scale).to(device)
        self.action = ActionMirror().to(device)
        self.device = torch.device(device)


def mirror_augmentation(env=None, obs: TensorDict | None = None, actions: torch.Tensor | None = None):
    """rsl-rl ``data_augmentation_func``: (obs, actions) with the mirrored samples appended
    along the batch dimension (either may be None). ``env``: the rsl-rl VecEnv
    (:class:`policy_train.runner.TorchVecEnv`) whose :class:`TripodEnv` gives the layouts."""
    if obs is None and actions is None:
        return None, None
    tripod = getattr(env, "env", env)
    device = (obs["policy"] if obs is not None else actions).device
    m = getattr(tripod, "_mirrors", None)
    if m is None or m.device != device:  # the update's device (policy_train.runner)
        m = tripod._mirrors = _Mirrors(tripod, device)
    out_obs = out_act = None
    if obs is not None:
        n = obs.batch_size[0]
        out_obs = TensorDict({"policy": torch.cat([obs["policy"], m.policy(obs["policy"])]),
                              "critic": torch.cat([obs["critic"], m.critic(obs["critic"])])},
                             batch_size=[2 * n])
    if actions is not None:
        out_act = torch.cat([actions, m.action(actions)])
    return out_obs, out_act
