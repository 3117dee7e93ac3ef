"""Stable-Baselines3 SAC in the ego's seat among IDM traffic, then `socialflow.evaluate` of the
trained policy beside the IDM driver on the same held-out stored cases.

    OMP_NUM_THREADS=1 python python/examples/sb3_sac.py --steps 80000 --out runs/sb3-sac

The action is `idm-accel-residual`: one number in [-1, 1] added to the IDM driver's
acceleration, so the zero action *is* the IDM driver and the two policies compare directly.

socialflow's `EgoVectorEnv` is a Gymnasium `VectorEnv` (same-step autoreset, `infos` a dict of
arrays), while SB3 wants its own `VecEnv` (`step_async`/`step_wait`, `dones`, a list of per-env
info dicts with `terminal_observation`). `SocialflowVecEnv` below is the thin adapter between the
two; the N simulators still step together in one Rust call. Training episodes are random draws
(`reset(seed=...)`); evaluation runs the stored cases, which training never asks for.

Writes under --out: curve.csv (env steps, wall seconds, mean return and success rate of the last
100 episodes), eval.json (both policies' summaries side by side), episodes-*.csv, model.zip.
"""

import argparse
import csv
import json
import os
import time

import numpy as np
import torch
from gymnasium import spaces
from stable_baselines3 import SAC
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.env_checker import check_env
from stable_baselines3.common.vec_env import VecEnv, VecMonitor

import socialflow

ACTION = "idm-accel-residual"


def features(obs):
    """An MLP's input from the dict observation's blocks: the ego's history, every neighbour's
    current frame (in its own frame, so its speed), its pose in the ego's frame and its mask,
    the route ahead and its mask; 360 numbers. Left out: the map segments (`seg_*`, indices
    into a map that is fixed within one scenario) and `ego_ctx` (SVO, zero among IDM)."""
    lead = obs["ego_hist"].shape[:-2]
    parts = [obs["ego_hist"], obs["agents_hist"][..., -1, :], obs["agents_ctx"], obs["agents_mask"], obs["route"], obs["route_mask"]]
    return np.concatenate([p.reshape(lead + (-1,)) for p in parts], axis=-1).astype(np.float32)


class SocialflowVecEnv(VecEnv):
    """SB3's VecEnv API over `socialflow.make_ego_vec` (dict observations -> `features`)."""

    def __init__(self, num_envs, seed, **kwargs):
        self.venv = socialflow.make_ego_vec(num_envs=num_envs, seed=seed, obs_format="dict", **kwargs)
        n = features(self.venv.single_observation_space.sample()).shape[-1]
        space = spaces.Box(-np.inf, np.inf, (n,), np.float32)
        super().__init__(num_envs, space, self.venv.single_action_space)
        self._seed, self._actions = seed, None

    def reset(self):
        obs, _ = self.venv.reset(seed=self._seed)
        self._seed = None  # later resets continue the simulators' own random streams
        return features(obs)

    def step_async(self, actions):
        self._actions = actions

    def step_wait(self):
        obs, reward, terminated, truncated, info = self.venv.step(self._actions)
        dones = terminated | truncated
        infos = [{"success": bool(info["success"][i])} for i in range(self.num_envs)]
        for i in np.flatnonzero(dones):  # same-step autoreset: obs[i] already starts the next episode
            infos[i]["terminal_observation"] = features(info["final_obs"][i])
            infos[i]["TimeLimit.truncated"] = bool(truncated[i] and not terminated[i])
        return features(obs), reward.astype(np.float32), dones, infos

    def close(self):
        pass

    def get_attr(self, name, indices=None):
        return [getattr(self.venv, name)] * len(self._get_indices(indices))

    def set_attr(self, name, value, indices=None):
        setattr(self.venv, name, value)

    def env_method(self, name, *args, indices=None, **kwargs):
        raise NotImplementedError("the simulators live in one Rust object")

    def env_is_wrapped(self, wrapper_class, indices=None):
        return [False] * len(self._get_indices(indices))


class CurveLogger(BaseCallback):
    """Every --log-every env steps: a row of (steps, wall s, mean return, success) over the last
    `window` finished episodes (VecMonitor puts `episode` and `success` into the final info)."""

    def __init__(self, path, every, window=100):
        super().__init__()
        self.path, self.every, self.window = path, every, window
        self.returns, self.successes, self.next_log = [], [], every

    def _on_training_start(self):
        self.t0 = time.time()
        self.f = open(self.path, "w", newline="")
        self.w = csv.writer(self.f)
        self.w.writerow(["env_steps", "wall_s", "episodes", "mean_return", "success_rate"])

    def _on_step(self):
        for info in self.locals["infos"]:
            if "episode" in info:
                self.returns.append(info["episode"]["r"])
                self.successes.append(float(info["success"]))
        if self.num_timesteps >= self.next_log and self.returns:
            self.next_log += self.every
            r, s = self.returns[-self.window :], self.successes[-self.window :]
            row = [self.num_timesteps, round(time.time() - self.t0, 1), len(self.returns), round(float(np.mean(r)), 4), round(float(np.mean(s)), 4)]
            self.w.writerow(row)
            self.f.flush()
            print("steps {} wall {}s episodes {} return {} success {}".format(*row), flush=True)
        return True

    def _on_training_end(self):
        self.f.close()


def main():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--steps", type=int, default=80000, help="env steps (all envs together); 80k: 7-11 min on one core")
    p.add_argument("--envs", type=int, default=4)
    p.add_argument("--scenario", default="merge")
    p.add_argument("--vehicles", type=int, nargs=2, default=(8, 20))
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--cases", type=int, default=200, help="stored evaluation cases (held out: training draws random ones)")
    p.add_argument("--eval-seeds", type=int, default=2)
    p.add_argument("--log-every", type=int, default=1000)
    p.add_argument("--out", default="runs/sb3-sac")
    a = p.parse_args()
    torch.set_num_threads(1)
    os.makedirs(a.out, exist_ok=True)
    env_kw = dict(scenario=a.scenario, flow="idm", vehicles=tuple(a.vehicles), action=ACTION)

    check_env(socialflow.make_ego(obs_format="flat", **env_kw))  # SB3's own check of the single env
    # (the dict format passes too, with SB3's advice to flatten its 2-D blocks)
    venv = VecMonitor(SocialflowVecEnv(a.envs, a.seed, **env_kw), info_keywords=("success",))
    model = SAC(
        "MlpPolicy",
        venv,
        gamma=0.95,  # episodes last 20-100 steps of 0.1 s (socialflow's ego recipe uses 0.95 too)
        learning_starts=1000,
        train_freq=1,
        gradient_steps=1,  # one update per call, i.e. per `--envs` transitions
        batch_size=256,
        buffer_size=max(a.steps, 1000),
        seed=a.seed,
        verbose=0,
    )
    t0 = time.time()
    model.learn(total_timesteps=a.steps, callback=CurveLogger(os.path.join(a.out, "curve.csv"), a.log_every))
    train_s = time.time() - t0
    model.save(os.path.join(a.out, "model.zip"))

    def sb3_policy(obs):  # the trained actor's deterministic (mean) action, on dict blocks
        return model.predict(features(obs), deterministic=True)[0]

    grid = {"flows": {"idm": "idm"}, "scenarios": [a.scenario], "cases": a.cases, "seeds": a.eval_seeds}
    out = {"train": {"env_steps": a.steps, "wall_s": round(train_s, 1), "envs": a.envs, "updates": int(model._n_updates)}, "eval": {}}
    for name, policy, fmt in (("sb3_sac", sb3_policy, "dict"), ("idm_driver", socialflow.zero_residual_policy(1), "flat")):
        r = socialflow.evaluate(policy, grid, action=ACTION, obs_format=fmt)
        r.to_csv(os.path.join(a.out, f"episodes-{name}.csv"))
        out["eval"][name] = r.summary
    with open(os.path.join(a.out, "eval.json"), "w") as f:
        json.dump(out, f, indent=2)
    for name, summ in out["eval"].items():
        for s in summ:
            print(f"{name:>10} {s['scenario']} ({s['episodes']} episodes): success {s['success']['mean']:.3f} +- {s['success']['ci95']:.3f}, collisions {s['collision']['mean']:.3f}, speed {s['speed']['mean']:.3f}")


if __name__ == "__main__":
    main()
