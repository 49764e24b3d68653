"""Where a tripod policy's base angular rate comes from, and how much of its action is sensor
noise: a diagnosis over the evaluation's episodes (``policy_train.evaluate.evaluation_env``),
for one or more exported policies side by side.

For each policy and randomisation setting (``full``, ``nominal``, or groups of
``config.DR_GROUPS`` held nominal, e.g. ``latency,obs_noise``):

* the base angular rate RMS per axis (roll, pitch, yaw; rad/s) over the excitation, and the
  share of its power in 0-1, 1-3, 3-8 and 8-25 Hz;
* the action's answer to the observation noise alone: RMS over joints and steps of
  pi(clean + delta) - pi(clean), delta drawn from the training's noise for one group of
  observation terms at a time (gyro, gravity, joint positions, joint velocities) and for all
  (actions are clipped to +-1; one unit is 0.1 rad of target per 20 ms step). A policy that
  sees a history of frames gets the clean history, each frame with its own noise draw.

  .venv/bin/python bench/bench_policy_noise.py policies/tripod_go2_v7.onnx [OTHER.onnx ...]
      [--episodes 32] [--legs FL,RL] [--settings full,latency,latency+obs_noise,nominal]
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from calib.joints import check_leg
from deploy.lift_schedule import PHASES, LiftSchedule
from deploy.observation import OBS_SIZE, ObservationHistory, history_length
from policy_train.config import DR_GROUPS, TrainConfig
from policy_train.env import noise_amplitude
from policy_train.evaluate import evaluation_env

BANDS_HZ = ((0.0, 1.0), (1.0, 3.0), (3.0, 8.0), (8.0, 25.1))
NOISE_GROUPS = {"gyro": "base_ang_vel", "gravity": "projected_gravity",
                "joint pos": "joint_pos", "joint vel": "joint_vel"}


def term_slices(terms: list[dict]) -> dict[str, slice]:
    out, i = {}, 0
    for t in terms:
        out[t["name"]] = slice(i, i + int(t["size"]))
        i += int(t["size"])
    return out


def diagnose(onnx_path: Path, legs, episodes: int, setting: str, seed: int = 5) -> dict:
    import onnxruntime as ort

    meta = json.loads(onnx_path.with_suffix(".json").read_text())
    sess = ort.InferenceSession(str(onnx_path), providers=["CPUExecutionProvider"])
    name_in = sess.get_inputs()[0].name

    def policy(x):
        return sess.run(None, {name_in: x.astype(np.float32)})[0]

    nominal = setting == "nominal"
    dr_off = () if setting in ("full", "nominal") else tuple(setting.split("+"))
    env, _ = evaluation_env(meta, legs, episodes, seed, nominal=nominal, dr_off=dr_off)
    sched = LiftSchedule.from_metadata(meta["lift_schedule"])
    # the training's noise, also where this setting holds it nominal
    amp = noise_amplitude(meta["observation"]["terms"],
                          TrainConfig.from_dict(meta["train_config"]).env.dr)
    sl = term_slices(env.obs_terms)
    frames = history_length(meta["observation"])
    clean_hist = ObservationHistory(frames, OBS_SIZE, (env.N,))  # evaluation episodes never reset
    rng = np.random.default_rng(seed)
    excite = PHASES.index("excite")
    n_steps = int(np.ceil(float(sched.total(legs[0])) / env.dt))
    rates, phases, answer = [], [], {k: [] for k in [*NOISE_GROUPS, "all"]}
    obs = env.observations()
    clean_hist.push(obs["critic"][:, :OBS_SIZE])
    for k in range(n_steps):
        ob, _, _, _ = env.step(policy(obs["policy"]))
        obs = ob
        rates.append(env.ang_vel_b.copy())
        phases.append(env.phase.copy())
        clean = clean_hist.push(obs["critic"][:, :OBS_SIZE]).reshape(env.N, frames, OBS_SIZE)
        if k % 5 == 0 and (env.phase == excite).any():
            base = policy(clean.reshape(env.N, -1))
            for g, out in answer.items():
                s = slice(0, OBS_SIZE) if g == "all" else sl[NOISE_GROUPS[g]]
                x = clean.copy()
                x[..., s] += rng.uniform(-1, 1, x[..., s].shape) * amp[s]
                out.append(policy(x.reshape(env.N, -1)) - base)
    rates, phases = np.array(rates), np.array(phases)
    # the steps every episode spends in the excitation, and the episodes that stayed there
    steps = np.flatnonzero((phases == excite).sum(1) > 0.9 * env.N)
    w = rates[steps][:, (phases[steps] == excite).all(0)]
    spec = np.abs(np.fft.rfft(w - w.mean(0), axis=0)) ** 2
    f = np.fft.rfftfreq(w.shape[0], env.dt)
    return {"rate_axes": np.sqrt(np.mean(w ** 2, (0, 1))),
            "rate": float(np.sqrt(np.mean(np.sum(w ** 2, 2)))),
            "bands": [float(spec[(f >= lo) & (f < hi)].sum() / spec.sum()) for lo, hi in BANDS_HZ],
            "answer": {g: float(np.sqrt(np.mean(np.square(v)))) for g, v in answer.items()}}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("onnx", nargs="+")
    p.add_argument("--episodes", type=int, default=32, help="per leg")
    p.add_argument("--legs", default="FL,RL")
    p.add_argument("--settings", default="full,latency,latency+obs_noise,nominal",
                   help="comma-separated: full, nominal, or DR groups held nominal joined by +")
    a = p.parse_args(argv)
    try:
        legs = tuple(check_leg(x.strip()) for x in a.legs.split(","))
    except ValueError as e:
        p.error(str(e))
    if a.episodes < 1:
        p.error("--episodes must be >= 1")
    for setting in a.settings.split(","):
        if setting not in ("full", "nominal") and not set(setting.split("+")) <= set(DR_GROUPS):
            p.error(f"setting {setting!r}: full, nominal, or groups of {', '.join(DR_GROUPS)} "
                    "joined by +")
    for path in a.onnx:
        if not Path(path).is_file() or not Path(path).with_suffix(".json").is_file():
            p.error(f"{path}: no such policy (ONNX and JSON)")
    print("| policy | held nominal | rate RMS rad/s | roll / pitch / yaw | power 0-1 / 1-3 / 3-8 / "
          "8-25 Hz | action answer to noise: gyro / gravity / joint pos / joint vel / all |")
    print("| --- | --- | --- | --- | --- | --- |")
    for path in a.onnx:
        for setting in a.settings.split(","):
            print(f"  {Path(path).stem}: {setting} ...", file=sys.stderr, flush=True)
            r = diagnose(Path(path), legs, a.episodes, setting)
            ans = r["answer"]
            print(f"| {Path(path).stem} | {setting if setting != 'full' else 'nothing'} | "
                  f"{r['rate']:.3f} | {' / '.join(f'{x:.3f}' for x in r['rate_axes'])} | "
                  f"{' / '.join(f'{100 * x:.0f} %' for x in r['bands'])} | "
                  + " / ".join(f"{ans[g]:.3f}" for g in [*NOISE_GROUPS, "all"]) + " |", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
