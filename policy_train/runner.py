"""PPO training of the tripod policy with rsl-rl (its ``PPO`` and ``MLPModel``; our own loop).

The loop is rsl-rl's ``OnPolicyRunner.learn`` reduced to what we need, so that we control the
progress line, the checkpoints (``runs/<name>/model_<it>.pt``; ``runs/`` is gitignored), resume,
and the two training phases of the paper (tripod stance first, then calibration motions:
``EnvConfig.p_excite`` is 0 for the first ``PPOConfig.stage1_fraction`` of the iterations).

The actor sees the 49-dim observation (``base_lin_vel`` zero-filled); the critic additionally
sees privileged simulator state (true base velocity, height, contacts, randomised parameters,
schedule phase): asymmetric actor-critic.
"""

from __future__ import annotations

import json
import os
import time
from pathlib import Path

import numpy as np
import torch
from rsl_rl.algorithms import PPO
from rsl_rl.env import VecEnv
from tensordict import TensorDict

from policy_train.config import TrainConfig
from policy_train.env import TripodEnv
from policy_train.symmetry import mirror_augmentation

__all__ = ["TorchVecEnv", "Trainer", "check_device", "rsl_train_cfg"]


class TorchVecEnv(VecEnv):
    """rsl-rl ``VecEnv`` over a numpy :class:`TripodEnv`: tensors on ``device`` (the
    simulation stays on the CPU; only the observations, rewards and actions cross)."""

    def __init__(self, env: TripodEnv, device: str = "cpu"):
        self.env = env
        self.num_envs = env.N
        self.num_actions = 12
        self.max_episode_length = env.max_episode_length
        self.device = device
        self.cfg = {}

    @property
    def episode_length_buf(self) -> torch.Tensor:
        return torch.from_numpy(self.env.episode_length_buf)

    @episode_length_buf.setter
    def episode_length_buf(self, v) -> None:
        self.env.episode_length_buf[:] = np.asarray(v)

    def _tensor(self, x: np.ndarray) -> torch.Tensor:
        return torch.from_numpy(x).to(self.device)

    def _td(self, obs: dict) -> TensorDict:
        return TensorDict({k: self._tensor(v) for k, v in obs.items()}, batch_size=[self.num_envs],
                          device=self.device)

    def get_observations(self) -> TensorDict:
        return self._td(self.env.observations())

    def step(self, actions: torch.Tensor):
        obs, rew, dones, extras = self.env.step(actions.detach().cpu().numpy())
        ex = {"time_outs": self._tensor(extras["time_outs"])}
        # the step's numpy results, for the progress line without a copy back from the device
        self.last_extras, self.last_rewards, self.last_dones = extras, rew, dones.astype(bool)
        return (self._td(obs), self._tensor(rew.astype(np.float32)),
                self._tensor(dones.astype(np.int64)), ex)


def rsl_train_cfg(cfg: TrainConfig) -> dict:
    p = cfg.ppo
    return {
        "num_steps_per_env": p.num_steps_per_env,
        "save_interval": p.save_interval,
        "obs_groups": {"actor": ["policy"], "critic": ["critic"]},
        "algorithm": {
            "class_name": "PPO", "num_learning_epochs": p.num_learning_epochs,
            "num_mini_batches": p.num_mini_batches, "clip_param": p.clip_param,
            "gamma": p.gamma, "lam": p.lam, "value_loss_coef": 1.0,
            "entropy_coef": p.entropy_coef, "learning_rate": p.learning_rate,
            "max_grad_norm": p.max_grad_norm, "use_clipped_value_loss": True,
            "schedule": "adaptive", "desired_kl": p.desired_kl,
            "symmetry_cfg": {"use_data_augmentation": True, "use_mirror_loss": False,
                             "data_augmentation_func": mirror_augmentation}
            if p.mirror_augmentation else None,
        },
        "actor": {
            "class_name": "MLPModel", "hidden_dims": list(p.actor_hidden), "activation": "elu",
            "obs_normalization": False,
            "distribution_cfg": {"class_name": "GaussianDistribution", "init_std": p.init_std},
        },
        "critic": {
            "class_name": "MLPModel", "hidden_dims": list(p.critic_hidden), "activation": "elu",
            "obs_normalization": True,
        },
        "multi_gpu": None,
    }


def check_device(device: str) -> str:
    """``device`` as torch names it (``cpu``, ``cuda``, ``cuda:1``); ValueError with one line
    where torch does not know it or this machine has no such GPU."""
    try:
        dev = torch.device(device)
    except (RuntimeError, TypeError) as e:
        raise ValueError(f"unknown device {device!r} ({str(e).splitlines()[0]})") from None
    if dev.type == "cuda":
        n = torch.cuda.device_count() if torch.cuda.is_available() else 0
        if (dev.index or 0) >= n:
            raise ValueError(f"device {device!r}: this machine has {n} CUDA GPU(s)"
                             + ("" if n else f" (torch {torch.__version__})"))
    elif dev.type != "cpu":
        raise ValueError(f"device {device!r}: cpu or cuda")
    return str(dev)


class Trainer:
    """Builds env + PPO; ``learn(iterations)`` with a progress line per iteration.

    device: where the networks and PPO's update run (``cpu``, ``cuda``); the simulation and
    the rewards run on the CPU either way. On a machine with a GPU the update moves there
    (measured on a lent 16-core machine: docs/policy-training.md, "Training throughput on a
    lent machine")."""

    def __init__(self, cfg: TrainConfig, run_dir: str | Path, seed: int = 0, log=print,
                 device: str = "cpu"):
        self.cfg = cfg
        self.device = check_device(device)
        cfg.env.seed = seed
        torch.manual_seed(seed)
        np.random.seed(seed)
        # the update's threads, as many as the simulation's (EnvConfig.threads, 0: all CPUs)
        torch.set_num_threads(cfg.env.threads or max(1, os.cpu_count() or 1))
        self.run_dir = Path(run_dir)
        self.log = log
        self.env = TripodEnv(cfg.env)
        self.venv = TorchVecEnv(self.env, self.device)
        self.train_cfg = rsl_train_cfg(cfg)
        obs = self.venv.get_observations()
        self.alg = PPO.construct_algorithm(obs, self.venv, self.train_cfg, self.device)
        self.iteration = 0
        self.seed = seed
        self.history: list[dict] = []
        self.total_iterations = 0
        self.resumed_from_average: list[int] | None = None  # iterations whose mean it started from
        self.warm_start: dict | None = None  # the exported policy it started from, if any

    def save(self, path: Path) -> None:
        d = self.alg.save()
        groups = d["optimizer_state_dict"]["param_groups"]
        if len(groups) > 1:  # during a critic warm-up: saved as the one group PPO builds
            one = {**groups[-1], "params": [i for g in groups for i in g["params"]]}
            d["optimizer_state_dict"] = {**d["optimizer_state_dict"], "param_groups": [one]}
        d["iter"] = self.iteration
        d["train_config"] = self.cfg.to_dict()
        d["seed"] = self.seed
        d["history"] = self.history
        if self.resumed_from_average:
            d["resumed_from_average"] = self.resumed_from_average
        if self.warm_start:
            d["warm_start"] = self.warm_start
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_suffix(".tmp")
        torch.save(d, tmp)
        os.replace(tmp, path)

    def load(self, checkpoint: str | Path | dict) -> None:
        """Continue from a checkpoint file, or one already loaded (``export.average_checkpoints``)."""
        d = checkpoint if isinstance(checkpoint, dict) else torch.load(
            checkpoint, weights_only=False, map_location="cpu")
        self.alg.load(d, None, True)
        self.iteration = int(d["iter"])
        self.history = list(d.get("history", []))
        # a start from averaged weights is part of how later checkpoints came about
        self.resumed_from_average = d.get("averaged_iterations", d.get("resumed_from_average"))
        self.warm_start = d.get("warm_start")

    def set_learning_rate(self, lr: float) -> None:
        """PPO's learning rate from now on (the adaptive schedule moves it from there)."""
        self.alg.learning_rate = float(lr)
        for group in self.alg.optimizer.param_groups:
            group["lr"] = float(lr)

    def load_policy(self, start: dict, std: float) -> None:
        """Start from an exported policy (:func:`policy_train.warm_start.policy_start`): its
        actor weights exactly, every action's exploration std set to ``std`` (the export keeps
        only the mean), a fresh critic and optimiser (train it first: ``learn(...,
        critic_only=True)``), the policy's iteration and stage."""
        if not (np.isfinite(std) and std > 0):
            raise ValueError(f"the exploration std must be > 0, got {std}")
        actor = self.alg.get_policy()
        try:
            actor.mlp.load_state_dict(start["actor_mlp"])
        except RuntimeError as e:  # layer names or shapes other than the configuration's
            raise ValueError(f"the policy's weights do not fit its configuration's actor: "
                             f"{str(e).splitlines()[0]}") from e
        with torch.no_grad():
            dist = actor.distribution
            if hasattr(dist, "std_param"):
                dist.std_param.fill_(std)
            else:
                dist.log_std_param.fill_(float(np.log(std)))
        self.iteration = int(start["iter"])
        self.history = list(start["history"])
        self.warm_start = {**start["warm_start"], "std": float(std)}

    def learn(self, iterations: int, max_seconds: float | None = None,
              critic_only: bool = False) -> None:
        """Run PPO iterations (a progress line each, checkpoints every ``save_interval``).

        critic_only: the warm-up after :meth:`load_policy`. Only the critic moves: the actor's
        parameters (mean and std) sit in their own optimiser group at learning rate 0, so
        Adam still gathers their gradient moments, and the rate is fixed (the unmoved actor's
        KL of 0 would raise it). Without the moments PPO's first updates move every weight a
        full step at once (Adam's first steps are sign steps): from v7, FL's success fell from
        78 to 42 % in 50 iterations (docs/policy-training.md)."""
        if not critic_only:
            self._learn(iterations, max_seconds, False)
            return
        alg = self.alg
        actor, critic = alg.get_policy(), alg.critic
        old = alg.optimizer
        schedule, lr = alg.schedule, alg.learning_rate
        alg.optimizer = type(old)([{"params": list(actor.parameters()), "lr": 0.0},
                                   {"params": list(critic.parameters()), "lr": lr}],
                                  **old.defaults)
        alg.optimizer.state.update(old.state)
        alg.schedule = "fixed"
        try:
            self._learn(iterations, max_seconds, True)
        finally:
            # one group again, as rsl-rl builds it (checkpoints must load into a fresh PPO),
            # keeping the moments gathered
            warm = alg.optimizer
            alg.optimizer = type(old)(
                [{"params": list(actor.parameters()) + list(critic.parameters()), "lr": lr}],
                **old.defaults)
            alg.optimizer.state.update(warm.state)
            alg.schedule, alg.learning_rate = schedule, lr

    def _step_calf_margin(self) -> None:
        """One iteration of the calf-clamp curriculum (``EnvConfig.calf_margin_target``)."""
        e = self.cfg.env
        if e.calf_margin_target is None:
            return
        now = e.soft_limit_margin if e.calf_upper_margin is None else e.calf_upper_margin
        gap = e.calf_margin_target - now
        if gap:
            self.env.set_calf_upper_margin(now + float(np.clip(gap, -e.calf_margin_step,
                                                               e.calf_margin_step)))

    def _learn(self, iterations: int, max_seconds: float | None, critic_only: bool) -> None:
        ppo = self.cfg.ppo
        start = self.iteration
        if self.total_iterations <= start:  # not planned by the caller: this call's end
            self.total_iterations = start + iterations
        stage1_end = int(ppo.stage1_fraction * self.total_iterations)
        if self.history and self.history[-1].get("stage") == 2:
            # resumed in phase 2: never back to tripod-only training, whatever the planned
            # total (a resume with a total below the checkpoint's iteration once re-planned
            # phase 1 and trained 476 iterations without calibration motions)
            stage1_end = min(stage1_end, start)
        obs = self.venv.get_observations()
        self.alg.train_mode()
        ep_rew = np.zeros(self.env.N)
        t_start = time.time()
        for it in range(start, start + iterations):
            if max_seconds is not None and time.time() - t_start > max_seconds:
                self.log(f"time limit reached after {self.iteration - start} iterations")
                break
            self.env.p_excite = 0.0 if it < stage1_end else self.cfg.env.p_excite
            if not critic_only:  # the warm-up's critic learns the policy as it stands
                self._step_calf_margin()
            t0 = time.time()
            finished_r, finished_len, falls = [], [], 0
            with torch.inference_mode():
                for _ in range(ppo.num_steps_per_env):
                    actions = self.alg.act(obs)
                    obs, rew, dones, extras = self.venv.step(actions)
                    self.alg.process_env_step(obs, rew, dones, extras)
                    ex = self.venv.last_extras
                    ep_rew += self.venv.last_rewards
                    d = self.venv.last_dones
                    if d.any():
                        finished_r.extend(ep_rew[d].tolist())
                        finished_len.extend(ex["episode_length"].tolist())
                        falls += int(ex["terminated"].sum())
                        ep_rew[d] = 0.0
                self.alg.compute_returns(obs)
            t1 = time.time()
            losses = self.alg.update()
            t2 = time.time()
            self.iteration = it + 1
            steps = ppo.num_steps_per_env * self.env.N
            rec = {
                "iteration": self.iteration,
                "mean_step_reward": float(self.alg.storage.rewards.mean()),
                "mean_episode_reward": float(np.mean(finished_r)) if finished_r else None,
                "mean_episode_length_s": (float(np.mean(finished_len)) * self.env.dt
                                          if finished_len else None),
                "falls": falls, "episodes": len(finished_r),
                "steps_per_s": steps / (t1 - t0), "collect_s": t1 - t0, "learn_s": t2 - t1,
                "value_loss": float(losses.get("value", losses.get("value_function", 0.0))),
                "std": float(self.alg.get_policy().output_std.detach().mean()),
                "learning_rate": float(self.alg.learning_rate),
                "stage": 1 if it < stage1_end else 2,
            }
            if self.cfg.env.calf_upper_margin is not None:
                rec["calf_upper_margin"] = self.cfg.env.calf_upper_margin
            if critic_only:
                rec["critic_only"] = True
            self.history.append(rec)
            er = rec["mean_episode_reward"]
            el = rec["mean_episode_length_s"]
            self.log(
                f"it {self.iteration:5d}  stage {rec['stage']}{' critic' if critic_only else ''}"
                f"  step_rew {rec['mean_step_reward']:+.4f}"
                f"  ep_rew {'   -   ' if er is None else f'{er:+8.2f}'}"
                f"  ep_len {'  -  ' if el is None else f'{el:5.1f}'} s  falls {falls:4d}/"
                f"{len(finished_r):<4d}  std {rec['std']:.3f}  {rec['steps_per_s']:7.0f} steps/s"
                f"  ({rec['collect_s']:.1f}+{rec['learn_s']:.1f} s)", )
            if self.iteration % ppo.save_interval == 0:
                self.save(self.run_dir / f"model_{self.iteration}.pt")
        self.save(self.run_dir / f"model_{self.iteration}.pt")
        (self.run_dir / "history.json").write_text(json.dumps(self.history, indent=1))
