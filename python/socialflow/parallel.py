"""A whole flow as a PettingZoo `ParallelEnv`: every vehicle of the episode is an agent
(`vehicle_0`, `vehicle_1`, ...), agents leave when their episode ends (collision, off road,
destination, timeout, ...). Rewards are individual or SVO-composed (the paper's Stage 1)."""

import functools
from typing import Literal, Optional

import numpy as np
from gymnasium import spaces
from pettingzoo import ParallelEnv

from . import _socialflow
from ._common import Action, Layout, ObsFormat, RenderMode, Seed, Vehicles, check_choice, make_core, observation_space, seed_arg
from .envs import _check_actions, split_obs

TERMINATIONS = tuple(_socialflow.terminations())


class FlowParallelEnv(ParallelEnv):
    """`make_flow(scenario, vehicles, ...)`: a whole flow of `scenario` with every vehicle an
    agent (a PettingZoo ParallelEnv); `reward`: each agent's own reward (`"individual"`) or
    the SVO-composed one (`"composed"`)."""

    metadata = {"name": "socialflow_flow_v0", "render_modes": ["rgb_array"], "is_parallelizable": True}

    def __init__(
        self,
        scenario: str = "roundabout",
        vehicles: Vehicles = (8, 20),
        layout: Optional[Layout] = None,
        action: Action = "direct",
        reward: Literal["individual", "composed"] = "composed",
        obs_format: ObsFormat = "dict",
        render_mode: RenderMode = None,
        seed: Seed = 0,
    ) -> None:
        if render_mode is not None:
            check_choice("render_mode", render_mode, self.metadata["render_modes"])
        check_choice("reward", reward, ("individual", "composed"))
        self.render_mode = render_mode
        self._core = make_core(scenario, None, vehicles, layout, action, 1, seed, None, multi_agent=True, reward=reward)
        self.obs_format = obs_format
        self.possible_agents = [f"vehicle_{i}" for i in range(self._core.max_agents)]
        self._index = {a: i for i, a in enumerate(self.possible_agents)}
        self._obs_space = observation_space(self._core, obs_format)
        self._act_space = spaces.Box(-1.0, 1.0, (self._core.action_dim,), np.float32)
        self._spec = self._core.spec()
        self.agents: list = []

    @functools.lru_cache(maxsize=None)
    def observation_space(self, agent):
        return self._obs_space

    @functools.lru_cache(maxsize=None)
    def action_space(self, agent):
        return self._act_space

    def _format(self, row):
        row = np.array(row, dtype=np.float32, copy=True)
        return split_obs(self._spec, row) if self.obs_format == "dict" else row

    def reset(self, seed=None, options=None):
        # Other option keys are ignored, as PettingZoo's API test expects of a ParallelEnv.
        case = (options or {}).get("case")
        cases = None if case is None else [int(case)]
        if case is not None and not 0 <= cases[0] < self._core.num_cases:
            raise ValueError(f"options['case']: {case!r} is not a stored case index (0..{self._core.num_cases - 1})")
        obs, alive = self._core.reset(seed_arg(seed), cases)
        self.agents = [a for a, i in self._index.items() if alive[i]]
        return {a: self._format(obs[self._index[a]]) for a in self.agents}, {a: {} for a in self.agents}

    def step(self, actions):
        unknown = [a for a in actions if a not in self._index or a not in self.agents]
        if unknown:
            raise ValueError(f"actions: {unknown} are not live agents")
        dim = self._core.action_dim
        batch = np.zeros((len(self.possible_agents), dim), np.float32)
        for a, act in actions.items():
            batch[self._index[a]] = _check_actions(act, 1, dim)[0]
        obs, _, reward, terminated, truncated, success, code, final_rows, final_obs = self._core.step(batch)
        finals = {int(r): final_obs[j] for j, r in enumerate(final_rows)}
        out_obs, rewards, terms, truncs, infos = {}, {}, {}, {}, {}
        for a in self.agents:
            i = self._index[a]
            out_obs[a] = self._format(finals[i] if i in finals else obs[i])
            rewards[a] = float(reward[i])
            terms[a] = bool(terminated[i])
            truncs[a] = bool(truncated[i])
            infos[a] = {"success": bool(success[i]), "termination": TERMINATIONS[code[i]] if code[i] >= 0 else None}
        self.agents = [a for a in self.agents if self._index[a] not in finals]
        return out_obs, rewards, terms, truncs, infos

    def render(self):
        check_choice("render_mode", self.render_mode, self.metadata["render_modes"])
        return self._core.render(0)

    def state(self):
        """The global view: a top-down RGB frame of the whole scene."""
        return self._core.render(0)


# The factory is the class itself, so its keyword list cannot drift from the constructor's.
make_flow = FlowParallelEnv
