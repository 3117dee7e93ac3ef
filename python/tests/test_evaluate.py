"""`socialflow.evaluate` gives the Rust CLI's numbers for the same policy."""

import json
import os
import subprocess
from pathlib import Path

import numpy as np
import pytest

import socialflow

REPO = Path(__file__).resolve().parents[2]


def socialflow_bin():
    path = os.environ.get("SOCIALFLOW_BIN")
    if not path:
        target = Path(os.environ.get("CARGO_TARGET_DIR", REPO / "target"))
        for profile in ("debug", "release"):
            if (target / profile / "socialflow").exists():
                path = str(target / profile / "socialflow")
                break
    if not path:
        pytest.fail("set SOCIALFLOW_BIN to the socialflow binary (cargo build --bins)")
    return path


@pytest.mark.parametrize("scenario", ["roundabout", "intersection"])
def test_idm_as_policy_equals_the_cli(scenario):
    cases, seeds = 24, 2
    out = subprocess.run(
        [socialflow_bin(), "eval-flow", "--flow", "idm", "--ego", "idm", "--scenario", scenario, "--cases", str(cases), "--seeds", str(seeds), "--json"],
        cwd=REPO,
        check=True,
        capture_output=True,
        text=True,
    )
    cli = json.loads(out.stdout)
    res = socialflow.evaluate(socialflow.zero_residual_policy(), grid={"flows": {"idm": "idm"}, "scenarios": [scenario], "cases": cases, "seeds": seeds}, action="idm-accel-residual")
    assert len(res.rows) == len(cli["episodes"]) == cases * seeds
    for mine, theirs in zip(res.rows, cli["episodes"]):
        assert (mine["case"], mine["seed"]) == (theirs["case"], theirs["seed"])
        for k in ("success", "safety", "speed", "collision"):
            assert mine[k] == pytest.approx(theirs[k], abs=1e-6), (k, mine, theirs)
    (s,) = res.summary
    assert s["success"]["mean"] == pytest.approx(cli["success"]["mean"], abs=1e-9)
    assert s["collision"]["mean"] == pytest.approx(cli["collision"]["mean"], abs=1e-9)
    assert s["success"]["ci95"] == pytest.approx(cli["success"]["ci95"], rel=1e-3)


def test_the_idm_driver_takes_dict_observations_too():
    grid = {"flows": {"idm": "idm"}, "scenarios": ["merge"], "cases": 6, "seeds": 1}
    flat = socialflow.evaluate(socialflow.zero_residual_policy(), grid=grid, action="idm-accel-residual")
    blocks = socialflow.evaluate(socialflow.zero_residual_policy(), grid=grid, action="idm-accel-residual", obs_format="dict")
    assert [r["success"] for r in blocks.rows] == [r["success"] for r in flat.rows]
    assert len(blocks.rows) == 6


def test_direct_policy_and_dict_observations(tmp_path):
    seen = []

    def brake(obs):
        seen.append(obs["ego_hist"].shape)
        return np.tile(np.array([-1.0, 0.0], np.float32), (len(obs["ego_hist"]), 1))

    res = socialflow.evaluate(brake, flows=["idm"], scenarios=["merge"], cases=4, seeds=1, obs_format="dict")
    assert len(res.rows) == 4 and seen and len(seen[0]) == 3
    # A car that never moves never succeeds, nor leaves its lane.
    assert all(r["success"] == 0.0 and r["lane_change"] == 0.0 for r in res.rows)
    # Every episode records whether standing cars closed the road ahead at its timeout.
    assert all(r["road_closed"] in (0.0, 1.0) for r in res.rows)
    res.to_csv(tmp_path / "episodes.csv")
    header = (tmp_path / "episodes.csv").read_text().splitlines()[0]
    assert header == "experiment,ego,flow,scenario,svo_deg,vehicles,case,seed,success,safety,speed,collision,lane_change,road_closed"


def test_bad_policy_and_grid():
    with pytest.raises(ValueError, match="policy"):
        socialflow.evaluate(lambda obs: np.zeros((len(obs), 5), np.float32), scenarios=["merge"], cases=2, seeds=1)
    with pytest.raises(ZeroDivisionError):
        socialflow.evaluate(lambda obs: 1 / 0, scenarios=["merge"], cases=2, seeds=1)
    with pytest.raises(ValueError, match="grid"):
        socialflow.evaluate(lambda obs: obs, grid={"casez": 3})
    with pytest.raises(ValueError, match="cases"):
        socialflow.evaluate(lambda obs: obs, scenarios=["merge"], cases=100_000)
    with pytest.raises(ValueError, match="policy"):
        socialflow.evaluate(42)


def test_mining_replays_the_worst_episodes_into_pages(tmp_path):
    """`EvalResult.mine`, the Python side of `socialflow eval --mine`: each cell's worst
    episodes replayed with the evaluated policy into pages that end as the stored rows say, and
    an index sorted by outcome."""

    def crawl(obs):
        # Barely moving: many episodes time out, some with the road closed behind.
        return np.tile(np.array([-0.9, 0.0], np.float32), (len(obs), 1))

    res = socialflow.evaluate(crawl, flows=["idm"], scenarios=["merge", "roundabout"], cases=6, seeds=2)
    index = res.mine(tmp_path / "mined", worst=2)
    assert index == os.path.join(tmp_path / "mined", "index.html")
    text = Path(index).read_text()
    rows = json.loads(text.split('id="data">', 1)[1].split("</script>", 1)[0])
    pages = sorted(p.name for p in (tmp_path / "mined").glob("*.html") if p.name != "index.html")
    assert len(pages) == 4 and sorted(r["href"] for r in rows) == pages, (pages, rows)
    for name in pages:
        page = (tmp_path / "mined" / name).read_text()
        assert '"agrees":true' in page, f"{name}: the replay does not end as the stored row"
    assert "4 of 4 replays end as stored" in text and all(r["replay_agrees"] for r in rows)
    # Sorted by outcome, worst first; each cell's picks are its worst episodes.
    order = [socialflow.evaluation.OUTCOMES.index(r["outcome"]) for r in rows]
    assert order == sorted(order), rows
    for scenario in ("merge", "roundabout"):
        picked = [r for r in rows if r["scenario"] == scenario]
        keys = {(r["case"], r["seed"]) for r in picked}
        left = [r["success"] for r in res.rows if r["scenario"] == scenario and (r["case"], r["seed"]) not in keys]
        assert len(picked) == 2 and max(r["metrics"]["success"] for r in picked) <= min(left)


def test_mining_refuses_bad_arguments(tmp_path):
    res = socialflow.evaluate(socialflow.zero_residual_policy(), flows=["idm"], scenarios=["merge"], cases=2, seeds=1, action="idm-accel-residual")
    for worst in (0, -1, 1.5, True):
        with pytest.raises(ValueError, match="worst"):
            res.mine(tmp_path, worst=worst)
    with pytest.raises(ValueError, match="mine"):
        socialflow.EvalResult(rows=res.rows).mine(tmp_path)
