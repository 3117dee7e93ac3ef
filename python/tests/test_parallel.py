"""PettingZoo: the whole flow as a ParallelEnv."""

import numpy as np
import pytest
from pettingzoo.test import parallel_api_test

import socialflow


@pytest.mark.parametrize("obs_format", ["dict", "flat"])
def test_parallel_api(obs_format):
    env = socialflow.make_flow(scenario="roundabout", vehicles=(3, 6), obs_format=obs_format)
    parallel_api_test(env, num_cycles=200)


def test_agents_leave_and_episode_ends():
    env = socialflow.make_flow(scenario="merge", vehicles=(5, 5), obs_format="flat", action="idm-accel-residual", reward="individual")
    obs, infos = env.reset(seed=2)
    assert len(env.agents) == 5 and set(obs) == set(env.agents)
    seen_leave = False
    for _ in range(2000):
        if not env.agents:
            break
        before = set(env.agents)
        obs, rew, term, trunc, info = env.step({a: np.zeros(1, np.float32) for a in env.agents})
        assert set(obs) == before
        gone = {a for a in before if term[a] or trunc[a]}
        assert set(env.agents) == before - gone
        seen_leave |= bool(gone) and bool(env.agents)
    assert not env.agents
    with pytest.raises(ValueError, match="live agents"):
        env.reset(seed=0)
        env.step({"vehicle_99": np.zeros(1, np.float32)})
    with pytest.raises(ValueError, match="case"):
        env.reset(options={"case": -1})
    with pytest.raises(ValueError, match="reward"):
        socialflow.make_flow(reward="greedy")
