"""Distil the tripod policy into one that sees a history of its noisy observations (DAgger).

The PPO policies see one 49-value frame, as the paper's, and answer every frame's sensor noise:
with the observation noise held nominal v7 holds 97 % of its FL and RL lifts instead of 87-88 %
(``docs/policy-training.md``). A student that sees the last ``history`` noisy frames is
trained to act as the teacher acts on the *clean* newest frame, which the simulator has: a
supervised problem (Ross et al. 2011, DAgger), far cheaper in samples than PPO. The student
drives the robot while the data is gathered, so it learns in the states its own mistakes lead
to; each step is labelled with the teacher's action on the clean frame (the same previous
actions, the student's).

The student starts as the teacher: the newest frame's columns of its first layer are the
teacher's weights, the older frames' zero. The environment is the teacher's training
environment (its JSON's ``train_config``: rewards unused, its randomisation, reference starts,
contact terminations, its plan pool) with every lift an excitation, lifting the legs the
teacher's network lifts itself (its graph plays the others as their mirror images; so does the
student's: ``a2i-train export`` mirrors the teacher's mirrored legs unless told otherwise).

Checkpoints (``runs/<run>/model_<it>.pt``) have the PPO checkpoints' actor layout, so
``a2i-train export`` writes the deploy contract from them (``observation.history``).
"""

from __future__ import annotations

import json
import os
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from calib.atomic import write_bytes_atomic
from deploy.observation import OBS_SIZE

__all__ = ["LABELS", "DistillConfig", "Distiller", "student_from_teacher", "widen_hidden",
           "widen_history"]


@dataclass
class DistillConfig:
    """DAgger settings. Samples are (noisy history, teacher's action on the clean frame)."""

    teacher: str = "policies/tripod_go2_v7.onnx"
    history: int = 10                 # frames the student sees (0.2 s at 50 Hz; v8, v9)
    num_envs: int = 512
    steps_per_iteration: int = 50     # policy steps of every env between updates (1 s)
    # newest samples kept (first in, first out): 4 x (49 x history + 12) bytes each, 2 GB at 10
    buffer_samples: int = 1_000_000
    updates_per_iteration: int = 25   # Adam steps per iteration
    batch_size: int = 4096
    learning_rate: float = 3e-4
    # the teacher's own lifts (v7: FL and RL; FR and RR are their mirror images in its graph,
    # and in the student's export)
    lift_leg_weights: tuple[float, float, float, float] = (3.0, 0.0, 2.0, 0.0)  # FL FR RL RR
    save_interval: int = 25
    # DRConfig fields over the teacher's (a2i-train distill --dr), e.g. noise_scale (0, 1)
    dr: dict = field(default_factory=dict)
    # which clean frame the teacher labels: "now", the state the student acts in (v8, v9);
    # "actuation", the state at which the student's action reaches the motors, its env's
    # actuation latency later (LABELS)
    labels: str = "now"
    # hidden layer widths of the student; None: the teacher's (v8-v14: 256, 128, 64). On a
    # resume they may grow (widen_hidden)
    hidden: tuple[int, ...] | None = None
    # the student's EnvConfig.calf_upper_margin (rad; None: the teacher's). The teacher labels
    # the states the student's clamp leads to, so the student learns its balance there
    calf_upper_margin: float | None = None


LABELS = ("now", "actuation")
"""``DistillConfig.labels``. With "actuation" the label is what the teacher, acting with no
latency, would command at the moment the student's command takes effect: the state there is
set by the previous command alone, so the label does not depend on the action it labels, and a
student that learns it (reading the latency from its history) plays the teacher's latency-free
closed loop."""


def student_from_teacher(teacher_mlp: dict, history: int, hidden, activation: str = "elu"):
    """rsl-rl ``MLP`` over ``history`` frames, equal to the teacher on the newest frame: its
    first layer's columns for the newest frame are the teacher's, the older frames' zero.
    teacher_mlp: the teacher's MLP state dict (``0.weight`` (hidden0, 49), ...)."""
    import torch
    from rsl_rl.modules import MLP

    student = MLP(OBS_SIZE * history, 12, list(hidden), activation)
    sd = {k: v.clone() for k, v in teacher_mlp.items()}
    w0 = sd["0.weight"]
    if w0.shape[1] != OBS_SIZE:
        raise ValueError(f"teacher's first layer takes {w0.shape[1]} inputs, not {OBS_SIZE}")
    wide = torch.zeros(w0.shape[0], OBS_SIZE * history)
    wide[:, :OBS_SIZE] = w0
    sd["0.weight"] = wide
    student.load_state_dict(sd)
    return student


def widen_history(actor: dict, optimizer: dict, old: int, new: int) -> tuple[dict, dict]:
    """A checkpoint's student (``mlp.*`` state dict) and Adam state over ``old`` frames, widened
    to see ``new`` >= ``old``: the added, older frames' first-layer columns are zero, so the
    widened student acts exactly as before and starts learning what the older frames tell it.
    Their first moments are zero too; their second moments are the oldest saved frame's,
    column for column: with zero second moments Adam's first steps on the new columns are
    full learning-rate sign steps, hundreds of inputs per hidden unit moved at once (10 to 25
    frames at 3e-4: a loss of 0.24 and 10 terminations per 1 000 steps in the third iteration,
    against 0.16 and 6 with the moments filled; at 1e-4 no upset, as a plain resume;
    ``docs/policy-training.md``, v13). Returns new dicts; the inputs are not changed."""
    import torch

    if new < old:
        raise ValueError(f"the history can only grow on a resume ({old} frames saved, not {new})")
    actor = {k: v.clone() for k, v in actor.items()}
    w0 = actor["mlp.0.weight"]
    if w0.shape[1] != OBS_SIZE * old:
        raise ValueError(f"first layer takes {w0.shape[1]} inputs, not {old} frames")

    def wide(x, fill=False):
        out = torch.zeros(x.shape[0], OBS_SIZE * new, dtype=x.dtype)
        out[:, :x.shape[1]] = x
        if fill:
            out[:, x.shape[1]:] = x[:, -OBS_SIZE:].repeat(1, new - old)
        return out

    actor["mlp.0.weight"] = wide(w0)
    optimizer = {"state": {k: dict(v) for k, v in optimizer["state"].items()},
                 "param_groups": optimizer["param_groups"]}
    first = optimizer["param_groups"][0]["params"][0]  # the MLP's first parameter: 0.weight
    if first in optimizer["state"]:
        st = optimizer["state"][first]
        st["exp_avg"], st["exp_avg_sq"] = wide(st["exp_avg"]), wide(st["exp_avg_sq"], True)
    return actor, optimizer


def hidden_widths(actor: dict) -> list[int]:
    """The hidden layer widths of a student (``mlp.*`` state dict of an rsl-rl ``MLP``)."""
    n_lin = len([k for k in actor if k.startswith("mlp.") and k.endswith(".weight")])
    return [int(actor[f"mlp.{2 * i}.weight"].shape[0]) for i in range(n_lin - 1)]


def widen_hidden(actor: dict, optimizer: dict | None, hidden, seed: int = 0
                 ) -> tuple[dict, dict | None]:
    """A student (``mlp.*`` state dict of an rsl-rl ``MLP``: Linear layers ``mlp.0``, ``mlp.2``,
    ...) and its Adam state widened to the hidden layer widths ``hidden``, each >= the saved
    one, acting exactly as before (Net2Net's function-preserving widening, Chen et al. 2016):
    an added unit's incoming weights are random (the spread of its layer's existing rows), its
    bias zero, and its outgoing weights zero, so it changes nothing until the outgoing weights
    learn. Adam's first moments of the added entries are zero, their second moments the mean
    of the tensor's saved ones, so that the first steps on them are not full learning-rate
    sign steps (the upset ``widen_history`` measured). ``optimizer`` may be None (a fresh
    student). Returns new dicts; the inputs are not changed."""
    import torch

    old = hidden_widths(actor)
    n_lin = len(old) + 1
    hidden = [int(h) for h in hidden]
    if len(hidden) != len(old):
        raise ValueError(f"the student has {len(old)} hidden layers, not {len(hidden)}")
    if any(h < o for h, o in zip(hidden, old, strict=True)):
        raise ValueError(f"hidden layers can only grow ({', '.join(map(str, old))} saved, "
                         f"not {', '.join(map(str, hidden))})")
    gen = torch.Generator().manual_seed(seed)
    actor = {k: v.clone() for k, v in actor.items()}
    shapes = {}  # the parameter's position in the MLP -> its shape before and after
    for i in range(n_lin):
        w, b = actor[f"mlp.{2 * i}.weight"], actor[f"mlp.{2 * i}.bias"]
        rows = hidden[i] if i < n_lin - 1 else w.shape[0]
        cols = w.shape[1] if i == 0 else hidden[i - 1]
        nw = torch.zeros(rows, cols, dtype=w.dtype)
        nw[:w.shape[0], :w.shape[1]] = w
        if rows > w.shape[0]:  # the added units' inputs: all of the (widened) layer below
            nw[w.shape[0]:] = torch.randn(rows - w.shape[0], cols, generator=gen) * w.std()
        nb = torch.zeros(rows, dtype=b.dtype)
        nb[:b.shape[0]] = b
        actor[f"mlp.{2 * i}.weight"], actor[f"mlp.{2 * i}.bias"] = nw, nb
        shapes[2 * i] = (tuple(w.shape), tuple(nw.shape))
        shapes[2 * i + 1] = (tuple(b.shape), tuple(nb.shape))
    if optimizer is None:
        return actor, None
    state = {k: dict(v) for k, v in optimizer["state"].items()}
    params = optimizer["param_groups"][0]["params"]  # in the MLP's order: 0.weight, 0.bias, ...
    for pos, pid in enumerate(params):
        if pid not in state:
            continue
        old_shape, new_shape = shapes[pos]
        st = state[pid]
        for key, fill in (("exp_avg", False), ("exp_avg_sq", True)):
            x = st[key]
            out = torch.full(new_shape, float(x.mean()) if fill else 0.0, dtype=x.dtype)
            out[tuple(slice(0, n) for n in old_shape)] = x
            st[key] = out
    return actor, {"state": state, "param_groups": optimizer["param_groups"]}


class Distiller:
    """The teacher (onnxruntime, its JSON), the environment, the student and its optimiser."""

    def __init__(self, cfg: DistillConfig, run_dir: str | Path, seed: int = 0, threads: int = 0,
                 log=print, resume: dict | None = None):
        import onnxruntime as ort
        import torch
        from rsl_rl.modules import MLP

        from policy_train.config import TrainConfig
        from policy_train.env import PlanPool, TripodEnv
        from policy_train.warm_start import policy_start

        if cfg.labels not in LABELS:
            raise ValueError(f"labels must be one of {', '.join(LABELS)}, not {cfg.labels!r}")
        self.cfg, self.log, self.seed = cfg, log, seed
        self.run_dir = Path(run_dir)
        n_threads = threads or max(1, os.cpu_count() or 1)
        torch.set_num_threads(n_threads)
        torch.manual_seed(seed)
        teacher = Path(cfg.teacher)
        start = policy_start(teacher)  # ValueError unless an exported tripod policy
        self.meta = json.loads(teacher.with_suffix(".json").read_text())
        opts = ort.SessionOptions()
        opts.intra_op_num_threads = n_threads
        self.teacher = ort.InferenceSession(str(teacher), opts, providers=["CPUExecutionProvider"])
        self.teacher_in = self.teacher.get_inputs()[0].name
        tc = TrainConfig.from_dict(self.meta["train_config"])
        e = tc.env
        e.obs_history = cfg.history
        e.num_envs, e.seed, e.threads = cfg.num_envs, seed, threads
        e.model_file = e.plan_pool_file = None
        e.p_excite = 1.0  # phase 2: every lift plays an excitation
        e.lift_leg_weights = tuple(cfg.lift_leg_weights)
        e.dr = e.dr.with_settings(cfg.dr)
        if cfg.calf_upper_margin is not None:
            e.calf_upper_margin = float(cfg.calf_upper_margin)
        sched = self.meta["lift_schedule"]
        if float(sched.get("excitation_seen", 1.0)) != 1.0 or e.excitation_seen != 1.0:
            # the labels are the teacher's actions on frames of the leg as measured
            raise ValueError(f"the teacher {teacher.name} is shown only part of its lifted "
                             "leg's excursion while it excites (excitation_seen): distil from "
                             "one that observes it as measured")
        e.lift_kp, e.lift_kd = float(sched["kp"]), float(sched["kd"])
        e.lift_feedforward = bool(sched.get("feedforward", False))  # as deploy plays it
        e.lift_adapt = bool(sched.get("adapt", False))
        self.train_config = tc
        # the teacher's plans: a policy learns its pool (warm_start.policy_plan_pool)
        pool = PlanPool(e.plans_per_leg, e.t_r_range, e.n_basis, e.train_periods, e.physics_dt,
                        np.random.default_rng(int(start["seed"]) + 1), e.ground_clearance)
        self.env = TripodEnv(e, plan_pool=pool)
        self.env.obs_terms = self.meta["observation"]["terms"]  # the teacher's, as on board
        if cfg.labels == "actuation":
            self.env.actuation_frames = np.zeros((e.num_envs, OBS_SIZE), dtype=np.float32)
        self.iteration = 0
        self.history: list[dict] = []
        if resume is None:
            first = student_from_teacher(start["actor_mlp"], cfg.history, tc.ppo.actor_hidden)
            actor = {f"mlp.{k}": v for k, v in first.state_dict().items()}
            opt_state = None
        else:
            actor, opt_state = widen_history(resume["actor_state_dict"],
                                             resume["optimizer_state_dict"],
                                             int(resume["distill"]["history"]), cfg.history)
            self.iteration = int(resume["iter"])
            self.history = list(resume.get("history", []))
        hidden = tuple(cfg.hidden or hidden_widths(actor))
        actor, opt_state = widen_hidden(actor, opt_state, hidden, seed)
        tc.ppo.actor_hidden = hidden  # export builds the student's network from this
        self.student = MLP(OBS_SIZE * cfg.history, 12, list(hidden), "elu")
        self.student.load_state_dict({k[len("mlp."):]: v for k, v in actor.items()})
        self.opt = torch.optim.Adam(self.student.parameters(), lr=cfg.learning_rate)
        if opt_state is not None:
            self.opt.load_state_dict(opt_state)
            for group in self.opt.param_groups:  # the state carries the rate it was saved with
                group["lr"] = cfg.learning_rate
        n_in = OBS_SIZE * cfg.history
        self.buf_x = np.zeros((cfg.buffer_samples, n_in), dtype=np.float32)
        self.buf_y = np.zeros((cfg.buffer_samples, 12), dtype=np.float32)
        self.buf_n = self.buf_at = 0
        self.rng = np.random.default_rng(seed + 7)

    def _store(self, x: np.ndarray, y: np.ndarray) -> None:
        n, cap = len(x), self.cfg.buffer_samples
        idx = (self.buf_at + np.arange(n)) % cap
        self.buf_x[idx], self.buf_y[idx] = x, y
        self.buf_at = (self.buf_at + n) % cap
        self.buf_n = min(cap, self.buf_n + n)

    def _collect(self, obs: dict) -> tuple[dict, dict]:
        """One iteration's steps with the student acting; returns the last observations and
        statistics (episodes ended, of them by falls or contacts, mean length s)."""
        import torch

        ended = fell = 0
        lengths = []
        for _ in range(self.cfg.steps_per_iteration):
            x = obs["policy"]
            clean = obs["critic"][:, :OBS_SIZE]
            with torch.no_grad():
                act = self.student(torch.from_numpy(x)).numpy()
            obs, _, dones, extras = self.env.step(act)
            if self.cfg.labels == "actuation":
                clean = self.env.actuation_frames
            self._store(x, self.teacher.run(None, {self.teacher_in: clean})[0])
            ended += int(dones.sum())
            fell += int(extras["terminated"].sum())
            if "episode_length" in extras:
                lengths.extend(extras["episode_length"] * self.env.dt)
        return obs, {"episodes_ended": ended, "terminated": fell,
                     "mean_episode_length_s": float(np.mean(lengths)) if lengths else None}

    def _update(self) -> float:
        import torch

        losses = []
        for _ in range(self.cfg.updates_per_iteration):
            i = self.rng.integers(0, self.buf_n, min(self.cfg.batch_size, self.buf_n))
            x, y = torch.from_numpy(self.buf_x[i]), torch.from_numpy(self.buf_y[i])
            loss = torch.mean((self.student(x) - y) ** 2)
            self.opt.zero_grad()
            loss.backward()
            self.opt.step()
            losses.append(loss.item())
        return float(np.mean(losses))

    def checkpoint(self) -> dict:
        return {
            "actor_state_dict": {f"mlp.{k}": v for k, v in self.student.state_dict().items()},
            "optimizer_state_dict": self.opt.state_dict(),
            "train_config": self.train_config.to_dict(),
            "iter": self.iteration,
            "seed": self.seed,
            "history": self.history,
            "distill": {**asdict(self.cfg), "teacher_name": Path(self.cfg.teacher).name,
                        "teacher_commit": self.meta.get("commit"),
                        "lift_schedule": self.meta["lift_schedule"],
                        # the student lifts only the teacher's own legs: export mirrors the rest
                        "mirrored_legs": self.meta.get("mirrored_legs") or {}},
        }

    def save(self) -> Path:
        import io

        import torch

        path = self.run_dir / f"model_{self.iteration}.pt"
        buf = io.BytesIO()
        torch.save(self.checkpoint(), buf)
        write_bytes_atomic(path, buf.getvalue())
        return path

    def learn(self, iterations: int, max_minutes: float | None = None) -> Path:
        """Run ``iterations`` (or until ``max_minutes``), one progress line each; save every
        ``save_interval`` and at the end; return the last checkpoint's path."""
        self.run_dir.mkdir(parents=True, exist_ok=True)
        t_start = time.time()
        obs = self.env.observations()
        last = None
        for _ in range(iterations):
            t0 = time.time()
            obs, stats = self._collect(obs)
            t1 = time.time()
            loss = self._update()
            self.iteration += 1
            steps = self.cfg.steps_per_iteration * self.env.N
            rec = {"iteration": self.iteration, "loss": loss, "stage": 2,
                   "ended_per_1k_steps": 1e3 * stats["episodes_ended"] / steps,
                   "terminated_per_1k_steps": 1e3 * stats["terminated"] / steps,
                   "mean_episode_length_s": stats["mean_episode_length_s"]}
            self.history.append(rec)
            self.log(f"it {self.iteration:5d}  loss {loss:.5f}  ended/1k steps "
                     f"{rec['ended_per_1k_steps']:.2f} (terminated "
                     f"{rec['terminated_per_1k_steps']:.2f})  buffer {self.buf_n}  "
                     f"{steps / (t1 - t0):.0f} steps/s  collect {t1 - t0:.1f}s "
                     f"learn {time.time() - t1:.1f}s")
            if self.iteration % self.cfg.save_interval == 0:
                last = self.save()
            if max_minutes is not None and time.time() - t_start > 60 * max_minutes:
                self.log(f"stopping after {max_minutes} min")
                break
        if last is None or not last.name.endswith(f"_{self.iteration}.pt"):
            last = self.save()
        return last
