"""`evaluate`: a Python driving policy in the ego's seat over socialflow's stored evaluation
cases x seeds, among the chosen flows, through the same Rust loop as `socialflow eval`'s cells
(so the same policy gives the same numbers). Rows have the columns of `episodes.csv`."""

import csv
import json
import math
import os
from dataclasses import dataclass, field
from typing import Any, Callable, Dict, List, Mapping, Optional, Sequence, Union, cast

import numpy as np

from . import _socialflow
from ._common import Action, Flow, Layout, ObsFormat, PathLike, check_choice, flow_arg
from .envs import split_obs

EPISODE_COLUMNS = ("experiment", "ego", "flow", "scenario", "svo_deg", "vehicles", "case", "seed", "success", "safety", "speed", "collision", "lane_change", "road_closed")
_GRID_KEYS = {"flows", "scenarios", "cases", "seeds", "envs", "vehicles", "svo_deg", "experiment", "ego"}


def zero_residual_policy(dim: int = 1) -> Callable[[np.ndarray], np.ndarray]:
    """The IDM driver as a policy: with `action="idm-accel-residual"` (`dim=1`) or
    `"idm-residual-lateral"` (`dim=2`) zeros drive exactly like IDM. Takes flat or dict
    observations."""

    def policy(obs):
        # A flat batch `[n, obs_len]`, or a dict of blocks whose arrays lead with `n`.
        n = len(next(iter(obs.values()))) if isinstance(obs, Mapping) else len(obs)
        return np.zeros((n, dim), np.float32)

    return policy


def _t95(n):
    """Two-sided 95 % Student-t quantile with n - 1 degrees of freedom (as `sf_report::Summary`)."""
    if n < 2:
        return float("nan")
    try:
        from scipy.stats import t  # optional: exact quantile

        return float(t.ppf(0.975, n - 1))
    except ImportError:
        # Cornish-Fisher expansion of the t quantile around the normal's 1.959964.
        z, df = 1.959963984540054, n - 1
        g1 = (z**3 + z) / 4
        g2 = (5 * z**5 + 16 * z**3 + 3 * z) / 96
        g3 = (3 * z**7 + 19 * z**5 + 17 * z**3 - 15 * z) / 384
        return z + g1 / df + g2 / df**2 + g3 / df**3


def _summary(xs):
    xs = np.asarray(xs, dtype=np.float64)
    n = len(xs)
    mean = float(xs.mean()) if n else float("nan")
    sd = float(xs.std(ddof=1)) if n > 1 else float("nan")
    return {"mean": mean, "ci95": _t95(n) * sd / math.sqrt(n) if n > 1 else float("nan")}


#: Outcome classes of a mined episode, worst first (`socialflow eval --mine`'s order).
OUTCOMES = ("collision", "off-road", "off-route", "wrong-lane", "road-closed", "timeout", "success")


@dataclass
class _Replay:
    """How `evaluate` ran one (flow, scenario) cell, so that `EvalResult.mine` can replay it."""

    policy: Any
    flow: Optional[str]
    layout: Optional[str]
    action: str
    vehicles: Optional[int]
    svo_deg: Optional[float]


def _safe(text: str) -> str:
    """Letters, digits, `-` and `_` kept, the rest `_` (`socialflow eval --mine`'s page names)."""
    return "".join(c if c.isascii() and (c.isalnum() or c in "-_") else "_" for c in text)


@dataclass
class EvalResult:
    """Per-episode `rows` (dicts with `EPISODE_COLUMNS`) and a `summary` per (flow, scenario)."""

    rows: List[Dict[str, Any]] = field(default_factory=list)
    summary: List[Dict[str, Any]] = field(default_factory=list)
    _replay: Dict[Any, _Replay] = field(default_factory=dict, repr=False, compare=False)

    def mine(self, out: PathLike, worst: int = 3) -> str:
        """Failure mining, as `socialflow eval --mine worst=N`: each (flow, scenario) cell's
        `worst` episodes (lowest success first, then most collisions, then slowest; ties by
        case and seed) replayed with the evaluated policy into self-contained browser pages in
        `out`, and `out/index.html` listing them by outcome (collision, off-road, off-route,
        wrong-lane, road-closed, timeout, success), worst first, each page linked and marked
        with whether its replay ended as the stored row says. Returns the index's path. Replays
        with the policy `evaluate` ran, so it works on a result made in this process."""
        if isinstance(worst, bool) or not isinstance(worst, (int, np.integer)) or worst < 1:
            raise ValueError(f"worst: {worst!r} is not a positive integer")
        if not self.rows:
            raise ValueError("mine: the result has no episodes")
        if not self._replay:
            raise ValueError("mine: this result has no policy to replay with (make it with socialflow.evaluate in this process)")
        os.makedirs(out, exist_ok=True)
        cells: Dict[Any, List[Dict[str, Any]]] = {}
        for r in self.rows:
            cells.setdefault((r["flow"], r["scenario"]), []).append(r)
        index = []
        for key, rows in cells.items():
            how = self._replay.get(key)
            if how is None:
                raise ValueError(f"mine: no policy recorded for flow {key[0]!r} in {key[1]!r}")
            picked = sorted(rows, key=lambda r: (r["success"], -r["collision"], r["speed"], r["case"], r["seed"]))[:worst]
            for r in picked:
                cell = "|".join("" if r[c] is None else str(r[c]) for c in ("experiment", "ego", "flow", "scenario", "svo_deg", "vehicles"))
                name = f"{_safe(cell)}-case{r['case']}-seed{r['seed']}.html"
                title = f"{cell} - case {r['case']}, seed {r['seed']}"
                html, outcome, metrics, agrees = _socialflow.view_episode(
                    how.policy, r["scenario"], int(r["case"]), int(r["seed"]), how.flow, how.layout, how.action,
                    how.vehicles, how.svo_deg, title, {k: r[k] for k in ("success", "safety", "speed", "collision", "road_closed")},
                )
                with open(os.path.join(out, name), "w", encoding="utf-8") as f:
                    f.write(html)
                index.append({
                    "href": name, "cell": cell, "experiment": r["experiment"], "ego": r["ego"], "flow": r["flow"],
                    "scenario": r["scenario"], "svo_deg": r["svo_deg"], "vehicles": r["vehicles"], "case": r["case"],
                    "seed": r["seed"], "outcome": outcome, "metrics": json.loads(metrics), "replay_agrees": agrees,
                })
        index.sort(key=lambda x: (OUTCOMES.index(x["outcome"]), x["metrics"]["success"], x["href"]))
        agree = sum(1 for x in index if x["replay_agrees"])
        title = f"{worst} worst episodes per cell ({agree} of {len(index)} replays end as stored)"
        path = os.path.join(out, "index.html")
        with open(path, "w", encoding="utf-8") as f:
            f.write(_socialflow.view_index(title, json.dumps(index)))
        return path

    def to_csv(self, path: PathLike) -> None:
        """Writes the rows as an `episodes.csv` (the format `socialflow report` reads)."""
        with open(path, "w", newline="") as f:
            w = csv.writer(f, lineterminator="\n")
            w.writerow(EPISODE_COLUMNS)
            for r in self.rows:
                w.writerow(["" if r[c] is None else r[c] for c in EPISODE_COLUMNS])


def _grid(grid, kw):
    g = dict(grid or {})
    g.update({k: v for k, v in kw.items() if v is not None})
    unknown = set(g) - _GRID_KEYS
    if unknown:
        raise ValueError(f"grid: unknown key(s) {sorted(unknown)} (expected some of {sorted(_GRID_KEYS)})")
    flows = g.get("flows", {"idm": "idm"})
    if isinstance(flows, (list, tuple)):
        flows = {("idm" if f == "idm" else str(f)): f for f in flows}
    if not isinstance(flows, dict) or not flows:
        raise ValueError("grid['flows']: give a dict {name: 'idm' | job directory} (or a list)")
    scenarios = g.get("scenarios", list(_socialflow.scenarios()))
    if isinstance(scenarios, str):
        scenarios = [scenarios]
    for key in ("cases", "seeds", "envs"):
        v = g.get(key)
        if v is not None and (isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < 1):
            raise ValueError(f"grid['{key}']: {v!r} is not a positive integer")
    return g, flows, scenarios


def evaluate(
    policy: Union["_socialflow.Policy", Callable[[Any], Any]],
    grid: Optional[Mapping[str, Any]] = None,
    *,
    action: Action = "direct",
    layout: Optional[Layout] = None,
    obs_format: ObsFormat = "flat",
    cases: Optional[int] = None,
    seeds: Optional[int] = None,
    envs: Optional[int] = None,
    scenarios: Optional[Sequence[str]] = None,
    flows: Optional[Mapping[str, Flow]] = None,
) -> EvalResult:
    """Runs `policy` in the ego's seat over the grid: for every flow and scenario, the first
    `cases` stored cases (200) x `seeds` (10), `envs` (16) simulators stepped together.

    `policy` is a job's actor from `load_policy` (run in Rust with its own action and layout,
    as `socialflow eval` runs it), or any callable: `policy(obs)` gets a batch of observations (`[n, obs_len]` float32, or a dict of blocks with
    `obs_format="dict"`) and returns `[n, action_dim]` actions in [-1, 1] of the kind `action`.
    `grid`: `{"flows": {name: "idm" | flow job dir}, "scenarios": [...], "cases", "seeds",
    "envs", "vehicles", "svo_deg", "experiment", "ego"}`; keyword arguments override it.
    Every random draw of an episode (learned flows' sampled actions, noise) is the episode's
    own, keyed by (case, seed, step, agent), and learned policies run in Rust infer in calls of
    a fixed number of rows, as in `socialflow eval`: an episode ends the same at any `envs`
    (a Python callable's own batching is its own). Returns an `EvalResult`."""
    if not callable(policy):
        raise ValueError(f"policy: {policy!r} is not callable")
    check_choice("obs_format", obs_format, ("flat", "dict"))
    # A job's actor (`load_policy`) drives in Rust with its own action and layout.
    loaded = policy if isinstance(policy, _socialflow.Policy) else None
    if loaded is not None:
        if action not in ("direct", loaded.action):
            raise ValueError(f"action: {action!r} given, but the policy drives with {loaded.action!r}")
        if layout not in (None, loaded.layout):
            raise ValueError(f"layout: {layout!r} given, but the policy reads {loaded.layout!r}")
        if obs_format != "flat":
            raise ValueError("obs_format: a loaded policy reads flat observations")
        action, layout = cast(Action, loaded.action), cast(Layout, loaded.layout)
    g, flow_map, scenario_list = _grid(grid, {"cases": cases, "seeds": seeds, "envs": envs, "scenarios": scenarios, "flows": flows})
    n_cases, n_seeds, n_envs = int(g.get("cases", 200)), int(g.get("seeds", 10)), int(g.get("envs", 16))
    vehicles, svo = g.get("vehicles"), g.get("svo_deg")
    experiment, ego = g.get("experiment", "python"), g.get("ego", "python")
    result = EvalResult()
    for name, flow in flow_map.items():
        for scenario in scenario_list:
            call = policy
            if obs_format == "dict":
                spec = _socialflow.Core(scenario, flow_arg(flow), (1, 1), layout, action).spec()

                def call(obs, _spec=spec):
                    return policy(split_obs(_spec, obs))

            def wrapped(obs, _call=call):
                a = np.ascontiguousarray(np.asarray(_call(obs), dtype=np.float32))
                return a.reshape(len(obs), -1) if a.ndim == 1 else a

            acting = loaded if loaded is not None else wrapped
            rows = _socialflow.evaluate(acting, scenario, flow_arg(flow), layout, action, n_cases, n_seeds, n_envs, vehicles, svo)
            result._replay[(name, scenario)] = _Replay(acting, flow_arg(flow), layout, action, vehicles, svo)
            mine = [
                dict(zip(EPISODE_COLUMNS, (experiment, ego, name, scenario, None if svo is None else int(svo), vehicles, case, seed, success, safety, speed, collision, lane_change, road_closed)))
                for case, seed, success, safety, speed, collision, lane_change, road_closed in rows
            ]
            result.rows.extend(mine)
            s = {"flow": name, "scenario": scenario, "episodes": len(mine)}
            for col in ("success", "safety", "speed", "collision"):
                s[col] = _summary([r[col] for r in mine])
            result.summary.append(s)
    return result
