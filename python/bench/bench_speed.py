"""Environment steps per second from Python: socialflow's ego environment (one simulator,
and N simulators stepped together in Rust) beside highway-env's intersection and, if it
imports, MetaDrive's multi-agent intersection, each with about `--vehicles` cars and random
actions. Prints one JSON object; `run.sh` sets up the venv and writes docs/bench/python.json.

Steps differ in simulated time: socialflow's decision step is `dt_s` (0.1 s); highway-env's
intersection-v0 steps 1 / policy_frequency s (1 s at its defaults). Both are reported, with
simulated seconds per wall second."""

import argparse
import json
import platform
import time

import numpy as np


def timed(step, reset, seconds):
    reset()
    n, t0 = 0, time.perf_counter()
    while time.perf_counter() - t0 < seconds:
        n += step()
    return n / (time.perf_counter() - t0)


def bench_socialflow(vehicles, seconds, num_envs):
    import socialflow

    out = {}
    env = socialflow.make_ego(scenario="intersection", vehicles=(vehicles, vehicles), obs_format="flat")
    rng = np.random.default_rng(0)

    def step1():
        _, _, term, trunc, _ = env.step(rng.uniform(-1, 1, 2).astype(np.float32))
        if term or trunc:
            env.reset()
        return 1

    out["single"] = timed(step1, lambda: env.reset(seed=0), seconds)
    dt = env._core.dt_s
    venv = socialflow.make_ego_vec(num_envs=num_envs, scenario="intersection", vehicles=(vehicles, vehicles), obs_format="flat")
    acts = rng.uniform(-1, 1, (num_envs, 2)).astype(np.float32)

    def stepn():
        venv.step(acts)
        return num_envs

    out["vector"] = timed(stepn, lambda: venv.reset(seed=0), seconds)
    out["num_envs"] = num_envs
    out["step_s"] = dt
    out["obs_len"] = env.observation_space.shape[0]
    return out


def bench_highway(vehicles, seconds):
    import gymnasium as gym
    import highway_env  # noqa: F401  (registers the environments)

    env = gym.make("intersection-v0", config={"initial_vehicle_count": vehicles, "spawn_probability": 0.6})
    cfg = env.unwrapped.config

    def step():
        _, _, term, trunc, _ = env.step(env.action_space.sample())
        if term or trunc:
            env.reset()
        return 1

    env.action_space.seed(0)
    sps = timed(step, lambda: env.reset(seed=0), seconds)
    return {"single": sps, "step_s": 1.0 / cfg["policy_frequency"], "simulation_frequency": cfg["simulation_frequency"], "version": highway_env.__version__ if hasattr(highway_env, "__version__") else None}


def bench_metadrive(seconds):
    from metadrive.envs.marl_envs import MultiAgentIntersectionEnv

    env = MultiAgentIntersectionEnv({"num_agents": 20, "use_render": False})
    obs, _ = env.reset()

    def step():
        _, _, term, trunc, _ = env.step({a: env.action_space[a].sample() for a in env.agents})
        if term.get("__all__") or trunc.get("__all__"):
            env.reset()
        return 1

    return {"single": timed(step, lambda: None, seconds)}


def main():
    p = argparse.ArgumentParser(description=__doc__)
    p.add_argument("--vehicles", type=int, default=20)
    p.add_argument("--seconds", type=float, default=10.0)
    p.add_argument("--num-envs", type=int, default=16)
    a = p.parse_args()
    res = {"machine": platform.processor() or platform.machine(), "python": platform.python_version(), "vehicles": a.vehicles, "seconds": a.seconds}
    res["socialflow"] = bench_socialflow(a.vehicles, a.seconds, a.num_envs)
    for name, fn in (("highway_env", lambda: bench_highway(a.vehicles, a.seconds)), ("metadrive", lambda: bench_metadrive(a.seconds))):
        try:
            res[name] = fn()
        except Exception as e:  # a competitor that does not install or run here is reported, not fatal
            res[name] = {"error": f"{type(e).__name__}: {e}"[:300]}
    sf = res["socialflow"]
    for name in ("highway_env", "metadrive"):
        other = res[name].get("single")
        if other:
            res[f"ratio_single_vs_{name}"] = sf["single"] / other
            res[f"ratio_vector_vs_{name}"] = sf["vector"] / other
            step = res[name].get("step_s")
            if step:
                res[f"sim_seconds_ratio_single_vs_{name}"] = (sf["single"] * sf["step_s"]) / (other * step)
    print(json.dumps(res, indent=1))


if __name__ == "__main__":
    main()
