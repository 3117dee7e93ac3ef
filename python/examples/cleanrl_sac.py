"""A single-file SAC in PyTorch (CleanRL's style: one script, no framework) in the ego's seat among
IDM traffic, on socialflow's Gymnasium vector env as it is; then `socialflow.evaluate` of the
trained actor's mean action beside the IDM driver on the same held-out stored cases.

    OMP_NUM_THREADS=1 python python/examples/cleanrl_sac.py --steps 80000 --out runs/cleanrl-sac

Action `idm-accel-residual`: zero is the IDM driver. Same settings and outputs as sb3_sac.py
(curve.csv, eval.json, episodes-*.csv, actor.pt).
"""

import argparse
import csv
import json
import os
import time

import numpy as np
import torch
import torch.nn as nn
import torch.nn.functional as F

import socialflow

ACTION = "idm-accel-residual"


def features(obs):
    """The MLP's input (as in sb3_sac.py): the ego's history, each neighbour's current frame (its
    speed), pose and mask, the route and its mask; the map segments and ego_ctx are left out."""
    lead = obs["ego_hist"].shape[:-2]
    parts = [obs["ego_hist"], obs["agents_hist"][..., -1, :], obs["agents_ctx"], obs["agents_mask"], obs["route"], obs["route_mask"]]
    return np.concatenate([p.reshape(lead + (-1,)) for p in parts], axis=-1).astype(np.float32)


def mlp(i, o, h=256):
    return nn.Sequential(nn.Linear(i, h), nn.ReLU(), nn.Linear(h, h), nn.ReLU(), nn.Linear(h, o))


class Actor(nn.Module):
    def __init__(self, n_obs, n_act):
        super().__init__()
        self.net = mlp(n_obs, 2 * n_act)

    def forward(self, x):
        mean, log_std = self.net(x).chunk(2, dim=-1)
        return mean, log_std.clamp(-5, 2)

    def sample(self, x):
        """A tanh-squashed Gaussian action and its log-probability."""
        mean, log_std = self(x)
        u = mean + log_std.exp() * torch.randn_like(mean)
        a = torch.tanh(u)
        logp = (-0.5 * ((u - mean) / log_std.exp()) ** 2 - log_std - 0.5 * np.log(2 * np.pi)).sum(-1)
        logp -= (2 * (np.log(2) - u - F.softplus(-2 * u))).sum(-1)  # log |d tanh(u) / du|
        return a, logp

    def act(self, x):
        return torch.tanh(self(x)[0])


def main():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--steps", type=int, default=80000, help="env steps (all envs together); 80k: 7-11 min on one core")
    p.add_argument("--envs", type=int, default=4)
    p.add_argument("--scenario", default="merge")
    p.add_argument("--vehicles", type=int, nargs=2, default=(8, 20))
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--gamma", type=float, default=0.95)
    p.add_argument("--tau", type=float, default=0.005)
    p.add_argument("--lr", type=float, default=3e-4)
    p.add_argument("--batch", type=int, default=256)
    p.add_argument("--learning-starts", type=int, default=1000)
    p.add_argument("--cases", type=int, default=200)
    p.add_argument("--eval-seeds", type=int, default=2)
    p.add_argument("--log-every", type=int, default=1000)
    p.add_argument("--window", type=int, default=100, help="episodes in the curve's means")
    p.add_argument("--out", default="runs/cleanrl-sac")
    a = p.parse_args()
    torch.set_num_threads(1)
    torch.manual_seed(a.seed)
    rng = np.random.default_rng(a.seed)
    os.makedirs(a.out, exist_ok=True)

    # socialflow's vector env is a Gymnasium VectorEnv: same-step autoreset, final obs in infos.
    envs = socialflow.make_ego_vec(num_envs=a.envs, scenario=a.scenario, flow="idm", vehicles=tuple(a.vehicles), action=ACTION, obs_format="dict", seed=a.seed)
    obs = features(envs.reset(seed=a.seed)[0])
    n_obs, n_act = obs.shape[1], envs.single_action_space.shape[0]

    actor = Actor(n_obs, n_act)
    qs, q_targets = nn.ModuleList([mlp(n_obs + n_act, 1) for _ in range(2)]), nn.ModuleList([mlp(n_obs + n_act, 1) for _ in range(2)])
    q_targets.load_state_dict(qs.state_dict())
    q_opt, pi_opt = torch.optim.Adam(qs.parameters(), lr=a.lr), torch.optim.Adam(actor.parameters(), lr=a.lr)
    log_alpha = torch.zeros(1, requires_grad=True)
    alpha_opt, target_entropy = torch.optim.Adam([log_alpha], lr=a.lr), -float(n_act)

    cap = a.steps + a.envs
    buf = {"o": np.zeros((cap, n_obs), np.float32), "a": np.zeros((cap, n_act), np.float32), "r": np.zeros(cap, np.float32), "o2": np.zeros((cap, n_obs), np.float32), "d": np.zeros(cap, np.float32)}
    size = 0

    def q(nets, o, act):
        x = torch.cat([o, act], -1)
        return torch.stack([n(x).squeeze(-1) for n in nets])

    f = open(os.path.join(a.out, "curve.csv"), "w", newline="")
    log = csv.writer(f)
    log.writerow(["env_steps", "wall_s", "episodes", "mean_return", "success_rate"])
    ep_ret, returns, successes = np.zeros(a.envs), [], []
    t0, step, updates, next_log = time.time(), 0, 0, a.log_every
    while step < a.steps:
        if step < a.learning_starts:
            act = rng.uniform(-1, 1, (a.envs, n_act)).astype(np.float32)
        else:
            with torch.no_grad():
                act = actor.sample(torch.from_numpy(obs))[0].numpy()
        raw, reward, terminated, truncated, info = envs.step(act)
        next_obs = features(raw)
        real_next = next_obs.copy()  # the next state of each transition: the final obs where one ended
        ep_ret += reward
        for i in np.flatnonzero(terminated | truncated):
            real_next[i] = features(info["final_obs"][i])
            returns.append(ep_ret[i])
            successes.append(float(info["success"][i]))
            ep_ret[i] = 0
        j = slice(size, size + a.envs)
        buf["o"][j], buf["a"][j], buf["r"][j], buf["o2"][j], buf["d"][j] = obs, act, reward, real_next, terminated  # truncation bootstraps
        size += a.envs
        obs = next_obs
        step += a.envs

        if step >= a.learning_starts:  # one update per vector step, as sb3_sac.py
            idx = rng.integers(0, size, a.batch)
            o, ac, r, o2, d = (torch.from_numpy(buf[k][idx]) for k in ("o", "a", "r", "o2", "d"))
            alpha = log_alpha.exp().detach()
            with torch.no_grad():
                a2, logp2 = actor.sample(o2)
                target = r + a.gamma * (1 - d) * (q(q_targets, o2, a2).min(0).values - alpha * logp2)
            q_loss = F.mse_loss(q(qs, o, ac), target.expand(2, -1))
            q_opt.zero_grad()
            q_loss.backward()
            q_opt.step()

            pi, logp = actor.sample(o)
            pi_loss = (alpha * logp - q(qs, o, pi).min(0).values).mean()
            pi_opt.zero_grad()
            pi_loss.backward()
            pi_opt.step()
            alpha_loss = -(log_alpha * (logp.detach() + target_entropy)).mean()
            alpha_opt.zero_grad()
            alpha_loss.backward()
            alpha_opt.step()

            with torch.no_grad():
                for pt, pq in zip(q_targets.parameters(), qs.parameters()):
                    pt.lerp_(pq, a.tau)
            updates += 1

        if step >= next_log and returns:
            next_log += a.log_every
            row = [step, round(time.time() - t0, 1), len(returns), round(float(np.mean(returns[-a.window :])), 4), round(float(np.mean(successes[-a.window :])), 4)]
            log.writerow(row)
            f.flush()
            print("steps {} wall {}s episodes {} return {} success {}".format(*row), f"alpha {alpha.item() if updates else 1.0:.3f}", flush=True)
    f.close()
    train_s = time.time() - t0
    torch.save(actor.state_dict(), os.path.join(a.out, "actor.pt"))

    def policy(blocks):  # the actor's mean action on a batch of dict observations
        with torch.no_grad():
            return actor.act(torch.from_numpy(features(blocks))).numpy()

    grid = {"flows": {"idm": "idm"}, "scenarios": [a.scenario], "cases": a.cases, "seeds": a.eval_seeds}
    out = {"train": {"env_steps": a.steps, "wall_s": round(train_s, 1), "envs": a.envs, "updates": updates}, "eval": {}}
    for name, pol, fmt in (("cleanrl_sac", policy, "dict"), ("idm_driver", socialflow.zero_residual_policy(1), "flat")):
        r = socialflow.evaluate(pol, grid, action=ACTION, obs_format=fmt)
        r.to_csv(os.path.join(a.out, f"episodes-{name}.csv"))
        out["eval"][name] = r.summary
    with open(os.path.join(a.out, "eval.json"), "w") as fh:
        json.dump(out, fh, indent=2)
    for name, summ in out["eval"].items():
        for s in summ:
            print(f"{name:>11} {s['scenario']} ({s['episodes']} episodes): success {s['success']['mean']:.3f} +- {s['success']['ci95']:.3f}, collisions {s['collision']['mean']:.3f}, speed {s['speed']['mean']:.3f}")


if __name__ == "__main__":
    main()
