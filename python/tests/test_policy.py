"""`socialflow.load_policy`: a committed job's actor loads, acts in a Gymnasium loop, and scores
in `socialflow.evaluate` exactly what `socialflow eval` scores for it, episode by episode."""

import csv
import subprocess
import sys

import numpy as np
import pytest

import socialflow
from test_evaluate import REPO, socialflow_bin

# paper-small's RL/IDM ego (replicate s25): the acceleration residual, query-centric, four
# scenarios. A copy of docs/curves/paper-small-s25/jobs/1-ego-idm (its config and actor): tests
# read fixtures, never docs/, so results can move or leave docs/ without breaking a test.
EGO = REPO / "tests/fixtures/paper-small-s25/jobs/1-ego-idm"


def test_a_committed_actor_loads_and_acts_in_an_env():
    p = socialflow.load_policy(EGO, scenario="merge")
    assert (p.kind, p.action, p.layout, p.action_dim, p.scenario) == ("ego", "idm-accel-residual", "query-centric", 1, "merge")
    assert "1-ego-idm" in repr(p)
    env = socialflow.make_ego(scenario="merge", policy=p, obs_format="flat")
    obs, _ = env.reset(seed=3)
    assert obs.shape == (p.obs_len,)
    total = 0
    for _ in range(40):
        a = p(obs[None, :])
        assert a.shape == (1, 1) and a.dtype == np.float32 and np.all(np.abs(a) <= 1)
        obs, _, terminated, truncated, _ = env.step(a[0])
        total += 1
        if terminated or truncated:
            break
    assert total > 0
    # Deterministic: the same rows give the same actions, batched or not.
    rows = np.stack([obs, obs, obs])
    assert np.array_equal(p(rows), np.repeat(p(obs[None, :]), 3, axis=0))


def test_bad_arguments_name_themselves(tmp_path):
    with pytest.raises(OSError, match="job_dir"):
        socialflow.load_policy(tmp_path)
    with pytest.raises(ValueError, match="scenario"):
        socialflow.load_policy(EGO, scenario="moon")
    unbound = socialflow.load_policy(EGO)
    assert unbound.scenario is None
    with pytest.raises(ValueError, match="scenario"):
        unbound(np.zeros((1, unbound.obs_len), np.float32))
    bound = socialflow.load_policy(EGO, scenario="merge")
    with pytest.raises(ValueError, match="obs"):
        bound(np.zeros((2, bound.obs_len + 1), np.float32))
    with pytest.raises(ValueError, match="action"):
        socialflow.make_ego(scenario="merge", policy=bound, action="direct")
    with pytest.raises(ValueError, match="policy"):
        socialflow.make_ego(scenario="merge", policy="not a policy")
    with pytest.raises(ValueError, match="action"):
        socialflow.evaluate(bound, action="idm-residual-lateral", scenarios=["merge"], cases=1, seeds=1)
    (tmp_path / "config.toml").write_text("name = 3\n")
    with pytest.raises(ValueError, match="job_dir"):
        socialflow.load_policy(tmp_path)


def test_evaluate_scores_what_the_cli_scores(tmp_path):
    cases, seeds, envs = 8, 2, 8
    grid = tmp_path / "grid.toml"
    grid.write_text(
        f'kind = "eval"\nname = "python-policy"\nruns = "{EGO.parent.parent}"\nout = "{tmp_path / "out"}"\n'
        f'scenarios = ["merge", "roundabout"]\ncases = {cases}\nseeds = {seeds}\nenvs = {envs}\n'
        'flows = [{ name = "IDM", job = "idm" }]\negos = [{ name = "RL/IDM", job = "ego-idm", trained_in = "IDM" }]\n'
        '[experiments]\ncross_validation = ["IDM"]\n'
    )
    subprocess.run([socialflow_bin(), "eval", str(grid)], cwd=REPO, check=True, capture_output=True, text=True)
    with open(tmp_path / "out" / "episodes.csv") as f:
        cli = {
            (r["scenario"], int(r["case"]), int(r["seed"])): tuple(float(r[c]) for c in ("success", "safety", "speed", "collision"))
            for r in csv.DictReader(f)
            if r["ego"] == "RL/IDM" and r["flow"] == "IDM"
        }
    res = socialflow.evaluate(socialflow.load_policy(EGO), scenarios=["merge", "roundabout"], cases=cases, seeds=seeds, envs=envs)
    mine = {(r["scenario"], r["case"], r["seed"]): tuple(float(r[c]) for c in ("success", "safety", "speed", "collision")) for r in res.rows}
    assert len(mine) == 2 * cases * seeds
    assert mine.keys() == cli.keys()
    for k in sorted(mine):
        assert mine[k] == pytest.approx(cli[k], abs=1e-6), k


def test_python_m_socialflow_lists_the_entry_points():
    out = subprocess.run([sys.executable, "-m", "socialflow", "--help"], check=True, capture_output=True, text=True).stdout
    for name in ("make_ego", "make_ego_vec", "make_flow", "load_policy", "evaluate"):
        assert f"socialflow.{name}" in out, out
    bad = subprocess.run([sys.executable, "-m", "socialflow", "--nope"], capture_output=True, text=True)
    assert bad.returncode != 0 and "--nope" in bad.stderr
