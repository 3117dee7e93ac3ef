"""The ego's seat as a Gymnasium environment (one simulator) and a vector environment (N
simulators stepped together in Rust threads). The background traffic is driven in Rust: the
IDM flow, or a trained flow's frozen policy (with CoPO's coordinator, or SocialCommAdv's
adversary); Python drives only the ego (agent 0)."""

from typing import Any, Dict, Optional

import numpy as np
import gymnasium as gym
from gymnasium import spaces
from gymnasium.vector import AutoresetMode, VectorEnv
from gymnasium.vector.utils import batch_space

from . import _socialflow
from ._common import Action, Flow, Layout, ObsFormat, RenderMode, Seed, Vehicles, check_choice, make_core, observation_space, seed_arg

TERMINATIONS = tuple(_socialflow.terminations())


def split_obs(spec: Dict[str, Any], flat: np.ndarray) -> Dict[str, np.ndarray]:
    """Flat observation rows `[..., obs_len]` as a dict of their blocks (views, no copy);
    `spec` is a Core's `spec()` (`{name: (start, stop, shape)}`)."""
    lead = flat.shape[:-1]
    return {name: flat[..., a:b].reshape(lead + tuple(shape)) for name, (a, b, shape) in spec.items()}


def _check_actions(actions, n, dim):
    a = np.asarray(actions, dtype=np.float32)
    if a.size != n * dim:
        raise ValueError(f"action: {a.size} numbers given, expected {n} x {dim}")
    a = np.ascontiguousarray(a.reshape(n, dim))
    if not np.isfinite(a).all():
        raise ValueError("action: contains a NaN or an infinity")
    return a


class EgoEnv(gym.Env):
    """`make_ego(scenario, flow, vehicles, ...)`: the ego's seat in `scenario` (one of
    `socialflow.SCENARIOS`) among `flow` (`"idm"` or a trained flow's job directory),
    `vehicles` a count or a `(min, max)` range per episode. `action`: `"direct"` unless given;
    `obs_format`: `"dict"` of blocks or the `"flat"` row; `conflict_share`: the share of
    episodes drawn as conflict cases (the scenario's default unless given);
    `policy=socialflow.load_policy(...)`: observe and act as that trained policy does (its
    layout, observation caps and action).

    One simulator; Python drives the ego. Observations: a dict of the observation blocks
    (`obs_format="dict"`, masks included) or the flat row (`"flat"`). Actions in [-1, 1]:
    `direct` (the paper's `[reference speed, steer]`), `idm-residual`, `idm-accel-residual`
    (one number moving the IDM driver's acceleration: 0 drives exactly like IDM) or
    `idm-residual-lateral` (that number and a lateral target of up to one lane either side:
    zeros drive exactly like IDM, other values change lanes).

    `reset(seed=s)` draws random cases from `s`; `reset(options={"case": i})` runs stored
    evaluation case `i` (`socialflow eval`'s cases). `info` carries `success`, `termination`
    and `idm_action` (the IDM driver's choice as a `direct` action); with
    `action="idm-residual-lateral"` also `mobil_action` (IDM with MOBIL's lane changes as that
    action: a demonstrator that changes lanes, for warm-up or cloning)."""

    metadata = {"render_modes": ["rgb_array"], "render_fps": 10}

    def __init__(
        self,
        scenario: str = "merge",
        flow: Flow = "idm",
        vehicles: Vehicles = (8, 20),
        layout: Optional[Layout] = None,
        action: Optional[Action] = None,
        obs_format: ObsFormat = "dict",
        conflict_share: Optional[float] = None,
        render_mode: RenderMode = None,
        seed: Seed = 0,
        policy: Optional["_socialflow.Policy"] = None,
    ) -> None:
        if render_mode is not None:
            check_choice("render_mode", render_mode, self.metadata["render_modes"])
        self.render_mode = render_mode
        self._core = make_core(scenario, flow, vehicles, layout, action, 1, seed, conflict_share, policy=policy)
        self.obs_format = obs_format
        self.observation_space = observation_space(self._core, obs_format)
        self.action_space = spaces.Box(-1.0, 1.0, (self._core.action_dim,), np.float32)
        self._spec = self._core.spec()
        self._running = False
        self.scenario = scenario

    @property
    def num_cases(self):
        """Stored evaluation cases of the scenario (`options={"case": i}`)."""
        return self._core.num_cases

    def _format(self, row):
        row = np.array(row, dtype=np.float32, copy=True)
        return split_obs(self._spec, row) if self.obs_format == "dict" else row

    def _info(self):
        info = {"idm_action": self._core.idm_action()[0]}
        if self._core.action == "idm-residual-lateral":
            info["mobil_action"] = self._core.mobil_action()[0]
        return info

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        options = dict(options or {})
        case = options.pop("case", None)
        if options:
            raise ValueError(f"options: unknown key(s) {sorted(options)} (only 'case')")
        cases = None
        if case is not None:
            if isinstance(case, bool) or not isinstance(case, (int, np.integer)) or not 0 <= case < self.num_cases:
                raise ValueError(f"options['case']: {case!r} is not a stored case index (0..{self.num_cases - 1})")
            cases = [int(case)]
        obs, _ = self._core.reset(seed_arg(seed), cases)
        self._running = True
        return self._format(obs[0]), self._info()

    def step(self, action):
        if not self._running:
            raise RuntimeError("step() before reset() or after the episode ended: call reset()")
        a = _check_actions(action, 1, self._core.action_dim)
        obs, _, reward, terminated, truncated, success, code, final_rows, final_obs = self._core.step(a)
        ended = len(final_rows) > 0
        info = {"success": bool(success[0]), "termination": TERMINATIONS[code[0]] if code[0] >= 0 else None}
        if ended:
            self._running = False
            row = final_obs[0]
            info["idm_action"] = np.zeros(2, np.float32)
            if self._core.action == "idm-residual-lateral":
                info["mobil_action"] = np.zeros(2, np.float32)
        else:
            row = obs[0]
            info.update(self._info())
        return self._format(row), float(reward[0]), bool(terminated[0]), bool(truncated[0]), info

    def render(self, mode=None):
        mode = mode or self.render_mode
        check_choice("mode", mode, self.metadata["render_modes"])
        return self._core.render(0)


class EgoVectorEnv(VectorEnv):
    """`make_ego_vec(num_envs, scenario, ...)`: `num_envs` ego seats (the other arguments as
    `make_ego`'s), simulators of one scenario stepped together in Rust (rayon threads), one
    call per step for all of them: observations, rewards and flags come back as NumPy arrays.
    Finished episodes restart at once (Gymnasium's same-step autoreset): `infos["final_obs"]`
    holds the last observation of the simulators flagged in `infos["_final_obs"]`.
    `reset(options={"cases": [i0, i1, ...]})` runs stored cases, one per simulator, once. With
    `action="idm-residual-lateral"` the infos carry `mobil_action` `[num_envs, 2]`: IDM with
    MOBIL's lane changes as that action for each simulator's current observation (zeros where
    the ego is not alive)."""

    metadata = {"render_modes": ["rgb_array"], "autoreset_mode": AutoresetMode.SAME_STEP}

    def __init__(
        self,
        num_envs: int = 8,
        scenario: str = "merge",
        flow: Flow = "idm",
        vehicles: Vehicles = (8, 20),
        layout: Optional[Layout] = None,
        action: Optional[Action] = None,
        obs_format: ObsFormat = "dict",
        conflict_share: Optional[float] = None,
        render_mode: RenderMode = None,
        seed: Seed = 0,
        policy: Optional["_socialflow.Policy"] = None,
    ) -> None:
        if render_mode is not None:
            check_choice("render_mode", render_mode, self.metadata["render_modes"])
        if isinstance(num_envs, bool) or not isinstance(num_envs, (int, np.integer)) or num_envs < 1:
            raise ValueError(f"num_envs: {num_envs!r} is not a positive integer")
        self.render_mode = render_mode
        self._core = make_core(scenario, flow, vehicles, layout, action, num_envs, seed, conflict_share, policy=policy)
        self.num_envs = int(num_envs)
        self.obs_format = obs_format
        self.single_observation_space = observation_space(self._core, obs_format)
        self.single_action_space = spaces.Box(-1.0, 1.0, (self._core.action_dim,), np.float32)
        self.observation_space = batch_space(self.single_observation_space, self.num_envs)
        self.action_space = batch_space(self.single_action_space, self.num_envs)
        self._spec = self._core.spec()

    def _format(self, rows):
        return split_obs(self._spec, rows) if self.obs_format == "dict" else rows

    def reset(self, *, seed=None, options=None):
        options = dict(options or {})
        cases = options.pop("cases", None)
        if options:
            raise ValueError(f"options: unknown key(s) {sorted(options)} (only 'cases')")
        if cases is not None:
            cases = [int(c) for c in cases]
        if isinstance(seed, (list, tuple)):
            raise ValueError("seed: give one integer; the simulators' seeds derive from it")
        obs, alive = self._core.reset(seed_arg(seed), cases)
        return self._format(obs), self._with_mobil({"alive": alive})

    def _with_mobil(self, infos):
        if self._core.action == "idm-residual-lateral":
            infos["mobil_action"] = self._core.mobil_action()
        return infos

    def step(self, actions):
        a = _check_actions(actions, self.num_envs, self._core.action_dim)
        obs, alive, reward, terminated, truncated, success, code, final_rows, final_obs = self._core.step(a)
        infos = {"alive": alive, "success": success, "termination": code}
        if len(final_rows):
            mask = np.zeros(self.num_envs, dtype=bool)
            mask[final_rows] = True
            finals = np.empty(self.num_envs, dtype=object)
            for j, r in enumerate(final_rows):
                finals[r] = self._format(final_obs[j])
            infos["final_obs"] = finals
            infos["_final_obs"] = mask
        return self._format(obs), reward, terminated, truncated, self._with_mobil(infos)

    def render(self):
        check_choice("render_mode", self.render_mode, self.metadata["render_modes"])
        return self._core.render(0)


# The factories are the classes themselves, so their keyword lists cannot drift from the
# constructors' (and IDEs show the constructors' signatures and docs).
make_ego = EgoEnv
make_ego_vec = EgoVectorEnv
