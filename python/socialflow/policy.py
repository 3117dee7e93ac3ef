"""`load_policy`: a finished job's kept actor as a Python callable, run by socialflow's Rust
inference (the mean action `socialflow eval` drives with)."""

import os
from typing import Optional

from . import _socialflow
from ._common import PathLike

Policy = _socialflow.Policy


def load_policy(job_dir: PathLike, scenario: Optional[str] = None) -> "_socialflow.Policy":
    """The kept actor of the finished job in `job_dir` (its `config.toml` and `policy.bpk`,
    e.g. `runs/<data dir>/jobs/1-ego-idm` or a committed `docs/curves/.../jobs/...`).

    Returns a `socialflow.Policy`: `policy(obs)` maps `[n, obs_len]` float32 observations of
    the job's format to `[n, action_dim]` mean actions; `policy.action` and `policy.layout`
    say what it reads and drives with (`make_ego(scenario, policy=policy, obs_format="flat")`
    builds the environment that observes as it does), and `socialflow.evaluate(policy, ...)` needs
    nothing else. Query-centric actors read the map's segments, so calling one needs the
    scenario it acts in: `scenario`, or the job's own where it trained on one; evaluation
    binds the scenario itself. Raises `OSError` for a directory that is not a finished job's
    and `ValueError` naming the argument for anything else."""
    if not isinstance(job_dir, (str, os.PathLike)):
        raise ValueError(f"job_dir: {job_dir!r} is not a path")
    if scenario is not None and scenario not in _socialflow.scenarios():
        raise ValueError(f"scenario: unknown scenario {scenario!r} (expected one of {', '.join(_socialflow.scenarios())})")
    return _socialflow.Policy(os.fspath(job_dir), scenario)
