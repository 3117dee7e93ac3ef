"""Gymnasium environments: API conformance, determinism, stored cases, rendering, bad input."""

import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

import socialflow


@pytest.mark.parametrize("obs_format", ["dict", "flat"])
@pytest.mark.parametrize("action", ["direct", "idm-accel-residual", "idm-residual-lateral"])
def test_check_env(obs_format, action):
    env = socialflow.make_ego(scenario="merge", vehicles=(4, 8), obs_format=obs_format, action=action)
    check_env(env, skip_render_check=True)


def test_dict_blocks_match_the_flat_row():
    flat = socialflow.make_ego(scenario="intersection", obs_format="flat")
    blocks = socialflow.make_ego(scenario="intersection", obs_format="dict")
    a, _ = flat.reset(seed=3)
    b, _ = blocks.reset(seed=3)
    assert sum(v.size for v in b.values()) == a.size
    assert set(b) >= {"ego_hist", "agents_mask", "route_mask", "seg_mask"}
    assert np.array_equal(np.concatenate([b[k].ravel() for k in b]), a)
    assert blocks.observation_space.contains(b)
    assert set(np.unique(b["agents_mask"])) <= {0.0, 1.0}


def rollout(env, seed, steps=80):
    obs, _ = env.reset(seed=seed)
    rng = np.random.default_rng(0)
    trace = [obs.copy()]
    for _ in range(steps):
        obs, r, term, trunc, info = env.step(rng.uniform(-1, 1, env.action_space.shape).astype(np.float32))
        trace.append(np.append(obs, [r, term, trunc]))
        if term or trunc:
            obs, _ = env.reset()
    return np.concatenate(trace)


def test_same_seed_same_trajectory():
    env = socialflow.make_ego(scenario="roundabout", obs_format="flat")
    a, b = rollout(env, 7), rollout(env, 7)
    assert np.array_equal(a, b)
    assert not np.array_equal(a, rollout(env, 8))


def test_stored_case_and_idm_zero_residual_end_the_episode():
    env = socialflow.make_ego(scenario="merge", action="idm-accel-residual", obs_format="flat")
    assert env.num_cases == 200
    obs, info = env.reset(options={"case": 5})
    steps, done = 0, False
    while not done:
        obs, r, term, trunc, info = env.step(np.zeros(1, np.float32))
        done = term or trunc
        steps += 1
        assert steps < 2000
    assert info["termination"] in socialflow.TERMINATIONS
    # The same stored case replays identically.
    env.reset(options={"case": 5})
    with pytest.raises(RuntimeError):
        fresh = socialflow.make_ego(scenario="merge")
        fresh.step(np.zeros(2, np.float32))


def test_the_mobil_driver_is_a_lateral_demonstrator_that_changes_lanes():
    env = socialflow.make_ego(scenario="bottleneck", action="idm-residual-lateral", obs_format="flat")
    lateral = set()
    for case in range(10):
        obs, info = env.reset(options={"case": case})
        done = False
        while not done:
            a = info["mobil_action"]
            assert a.shape == (2,) and a.dtype == np.float32
            assert -1.0 <= a[0] <= 0.0, "the residual only brakes, while it changes lanes"
            lateral.add(float(a[1]))
            obs, r, term, trunc, info = env.step(a)
            done = term or trunc
        assert info["termination"] != "wrong-lane", "never the opposite carriageway"
    assert lateral <= {-1.0, 0.0, 1.0} and len(lateral) > 1, f"lane targets {lateral}"
    # Only the lateral action carries it.
    _, info = socialflow.make_ego(scenario="bottleneck", action="idm-accel-residual").reset(seed=0)
    assert "mobil_action" not in info
    # The vector environment carries one per simulator, for the observations it returns.
    vec = socialflow.make_ego_vec(num_envs=3, scenario="bottleneck", action="idm-residual-lateral")
    _, infos = vec.reset(seed=1)
    for _ in range(30):
        a = infos["mobil_action"]
        assert a.shape == (3, 2) and a.dtype == np.float32
        assert np.all(np.isin(a[:, 1], [-1.0, 0.0, 1.0]))
        _, _, _, _, infos = vec.step(a)
    _, infos = socialflow.make_ego_vec(num_envs=2, action="idm-accel-residual").reset(seed=1)
    assert "mobil_action" not in infos


def test_render_rgb_array():
    env = socialflow.make_ego(scenario="bottleneck", render_mode="rgb_array")
    env.reset(seed=0)
    frame = env.render()
    assert frame.dtype == np.uint8 and frame.ndim == 3 and frame.shape[2] == 3
    assert max(frame.shape[:2]) == 480 and frame.std() > 0


def test_vector_env_steps_all_simulators_and_autoresets():
    venv = socialflow.make_ego_vec(num_envs=6, scenario="intersection", obs_format="flat", action="idm-accel-residual")
    obs, info = venv.reset(seed=1)
    assert obs.shape == (6, venv.single_observation_space.shape[0]) and info["alive"].all()
    ended = 0
    for _ in range(300):
        obs, r, term, trunc, info = venv.step(np.zeros((6, 1), np.float32))
        assert obs.shape[0] == 6 and r.shape == (6,) and term.dtype == bool
        if "_final_obs" in info:
            done = term | trunc
            assert np.array_equal(info["_final_obs"], done)
            ended += done.sum()
            assert all(info["final_obs"][i].shape == obs[i].shape for i in np.flatnonzero(done))
    assert ended > 0
    assert venv.observation_space.contains(obs)


@pytest.mark.parametrize(
    "kwargs, names",
    [
        ({"scenario": "highway"}, "scenario"),
        ({"action": "fly"}, "action"),
        ({"layout": "polar"}, "layout"),
        ({"vehicles": (5, 2)}, "vehicles"),
        ({"vehicles": (1, 500)}, "vehicles"),
        ({"obs_format": "xml"}, "obs_format"),
        ({"conflict_share": 2.0}, "conflict_share"),
        ({"render_mode": "human"}, "render_mode"),
        ({"seed": -1}, "seed"),
    ],
)
def test_bad_arguments_name_themselves(kwargs, names):
    with pytest.raises(ValueError, match=names):
        socialflow.make_ego(**kwargs)


def test_bad_flow_directory_and_actions():
    with pytest.raises(OSError, match="flow"):
        socialflow.make_ego(flow="/nonexistent/job")
    env = socialflow.make_ego(scenario="merge")
    env.reset(seed=0)
    with pytest.raises(ValueError, match="action"):
        env.step(np.zeros(3, np.float32))
    with pytest.raises(ValueError, match="action"):
        env.step(np.array([np.nan, 0.0], np.float32))
    with pytest.raises(ValueError, match="case"):
        env.reset(options={"case": 10_000})
    with pytest.raises(ValueError, match="options"):
        env.reset(options={"level": 3})
