"""Argument checks and observation spaces shared by the environments (internal)."""

import os
from typing import Literal, Optional, Tuple, Union

import numpy as np
from gymnasium import spaces

from . import _socialflow

OBS_FORMATS = ("dict", "flat")

# Argument types of the public functions (for IDEs and type checkers).
PathLike = Union[str, "os.PathLike[str]"]
Flow = Union[Literal["idm"], PathLike, None]
"""`"idm"` (or None) for the rule-based flow, or a finished flow job's directory."""
Vehicles = Union[int, Tuple[int, int]]
"""A vehicle count, or an inclusive range drawn per episode."""
Action = Literal["direct", "idm-residual", "idm-accel-residual", "idm-residual-lateral"]
Layout = Literal["ego-frame", "query-centric"]
ObsFormat = Literal["dict", "flat"]
RenderMode = Optional[Literal["rgb_array"]]
Seed = Optional[int]


def check_choice(name, value, choices):
    if value not in choices:
        raise ValueError(f"{name}: {value!r} is not one of {', '.join(map(repr, choices))}")
    return value


def flow_arg(flow):
    """`"idm"` / None, or a finished flow job's artifact directory (str or PathLike)."""
    if flow is None or flow == "idm":
        return None
    if isinstance(flow, (str, os.PathLike)):
        return os.fspath(flow)
    raise ValueError(f"flow: {flow!r} is neither 'idm' nor a job's artifact directory")


def vehicles_arg(vehicles):
    if isinstance(vehicles, int) and not isinstance(vehicles, bool):
        vehicles = (vehicles, vehicles)
    try:
        lo, hi = (int(v) for v in vehicles)
    except (TypeError, ValueError):
        raise ValueError(f"vehicles: {vehicles!r} is not a count or a (min, max) pair") from None
    return lo, hi


def seed_arg(seed):
    if seed is None:
        return None
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise ValueError(f"seed: {seed!r} is not a non-negative integer")
    return int(seed)


def observation_space(core, obs_format):
    """The space of one observation row: a Dict of its blocks (masks in [0, 1]) or a flat Box."""
    check_choice("obs_format", obs_format, OBS_FORMATS)
    if obs_format == "flat":
        return spaces.Box(-np.inf, np.inf, (core.obs_len,), np.float32)
    parts = {}
    for name, (_, _, shape) in core.spec().items():
        shape = tuple(shape)
        if name.endswith("_mask"):
            parts[name] = spaces.Box(0.0, 1.0, shape, np.float32)
        elif name == "seg_id":
            parts[name] = spaces.Box(0.0, float(max(core.segments - 1, 0)), shape, np.float32)
        else:
            parts[name] = spaces.Box(-np.inf, np.inf, shape, np.float32)
    return spaces.Dict(parts)


def make_core(scenario, flow, vehicles, layout, action, num_envs, seed, conflict_share, multi_agent=False, reward="individual", policy=None):
    if not isinstance(scenario, str):
        raise ValueError(f"scenario: {scenario!r} is not a scenario name")
    if policy is not None:
        if not isinstance(policy, _socialflow.Policy):
            raise ValueError(f"policy: {policy!r} is not a socialflow.Policy (socialflow.load_policy)")
        # The env observes and acts as the loaded policy does.
        action = policy.action if action is None else action
    action = "direct" if action is None else action
    seed = seed_arg(seed)
    return _socialflow.Core(
        scenario,
        flow_arg(flow),
        vehicles_arg(vehicles),
        layout,
        action,
        int(num_envs),
        0 if seed is None else seed,
        conflict_share,
        multi_agent,
        reward,
        policy,
    )
