"""`socialflow.client` against a real learner and worker on loopback: submit (a dict, TOML
text, a file), watch, list, fetch files, download and load the trained actor, cancel, and
errors that name what is wrong."""

import os
import socket
import subprocess
import time
from pathlib import Path

import numpy as np
import pytest

import socialflow
from socialflow.client import Client, config_to_toml

from test_evaluate import REPO, socialflow_bin

TOKEN = "python-client-test-token"


def free_port():
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def tiny(name, env_steps):
    return {
        "name": name,
        "env": {"scenarios": ["roundabout"], "vehicles_min": 2, "vehicles_max": 3},
        "net": {"width": 16},
        "sac": {"batch_size": 32, "warmup_steps": 200},
        "train": {
            "env_steps": env_steps,
            "samples_per_insert": 0.1,
            "replay_capacity": 20000,
            "publish_every_updates": 5,
            "checkpoint_every_s": 1,
            "max_policy_lag": 1000,
        },
        "worker": {"envs": 4, "batch_transitions": 64},
    }


@pytest.fixture(scope="module")
def learner(tmp_path_factory):
    d = tmp_path_factory.mktemp("learner")
    grpc, admin, wadmin = free_port(), free_port(), free_port()
    env = dict(os.environ, SOCIALFLOW_TOKEN=TOKEN)
    sf = socialflow_bin()
    logs = [open(d / "learner.log", "w"), open(d / "worker.log", "w")]
    learner = subprocess.Popen(
        [sf, "learner", "--grpc-addr", f"127.0.0.1:{grpc}", "--admin-addr", f"127.0.0.1:{admin}", "--data-dir", str(d / "data"), "--scenarios-dir", "configs/scenarios", "--eval-cases-dir", "configs/cases", "--max-running-jobs", "1"],
        cwd=REPO, env=env, stdout=logs[0], stderr=subprocess.STDOUT,
    )
    url = f"http://127.0.0.1:{grpc}"
    worker = subprocess.Popen(
        [sf, "worker", "--learner", url, "--admin-addr", f"127.0.0.1:{wadmin}", "--scenarios-dir", "configs/scenarios", "--max-backoff-s", "1"],
        cwd=REPO, env=env, stdout=logs[1], stderr=subprocess.STDOUT,
    )
    client = None
    deadline = time.time() + 60
    while client is None:
        try:
            client = Client(url, token=TOKEN)
        except ConnectionError:
            if time.time() > deadline or learner.poll() is not None:
                raise
            time.sleep(0.2)
    yield client, url, d
    for p in (worker, learner):
        p.terminate()
    for p in (worker, learner):
        try:
            p.wait(timeout=30)
        except subprocess.TimeoutExpired:
            p.kill()
    for f in logs:
        f.close()


def test_a_job_submitted_as_a_dict_trains_and_its_actor_loads_here(learner, tmp_path):
    c, _, _ = learner
    job = c.submit(tiny("py-client", 600))
    assert job.name == "py-client" and job.state in ("queued", "running")
    seen = []
    done = c.wait(job.id, on_progress=seen.append)
    assert done.state == "succeeded", done.message
    assert seen and seen[-1].is_final and seen[-1].state == "succeeded"
    steps = [p.progress["env_steps"] for p in seen]
    assert steps == sorted(steps) and steps[-1] == 600, steps
    assert done.config_toml and 'name = "py-client"' in done.config_toml
    assert any(j.id == job.id and j.state == "succeeded" for j in c.jobs())
    curve = c.curve(job.id)
    assert curve and curve[-1]["env_steps"] <= 600
    files = c.download(job.id, tmp_path / "job")
    assert files[:3] == ["config.toml", "policy.bpk", "policy.json"], files
    assert (tmp_path / "job" / "policy.bpk").read_bytes() == c.policy_bytes(job.id)
    policy = socialflow.load_policy(tmp_path / "job")
    env = socialflow.make_ego(scenario="roundabout", policy=policy, obs_format="flat")
    obs, _ = env.reset(seed=0)
    a = policy(np.asarray(obs, dtype=np.float32)[None, :])
    assert a.shape == (1, policy.action_dim) and np.all(np.abs(a) <= 1.0)


def test_toml_text_and_files_submit_and_a_cancel_ends_the_job(learner, tmp_path):
    c, _, _ = learner
    text = config_to_toml(tiny("py-cancel", 10_000_000))
    path = tmp_path / "job.toml"
    path.write_text(text)
    queued = c.submit(path)
    assert queued.name == "py-cancel"
    cancelled = c.cancel(queued.id)
    assert cancelled.state == "cancelled", cancelled
    again = c.submit(text.replace("py-cancel", "py-cancel-2"))
    assert c.cancel(again.id).state == "cancelled"
    assert [p.state for p in c.watch(again.id)] == ["cancelled"]


def test_overrides_are_written_into_the_stored_config_and_refused_by_name(learner, tmp_path):
    c, _, _ = learner
    path = tmp_path / "job.toml"
    path.write_text(config_to_toml(tiny("py-set", 10_000_000)))
    job = c.submit(path, overrides={"sac.seed": 12, "name": "py-set-12", "validation.episodes": 3})
    stored = c.job(job.id).config_toml
    assert job.name == "py-set-12"
    assert "seed = 12" in stored and "episodes = 3" in stored, stored
    assert c.cancel(job.id).state == "cancelled"
    job = c.submit(path, overrides=["sac.seed=13", "name=py-set-13"])
    assert "seed = 13" in c.job(job.id).config_toml
    assert c.cancel(job.id).state == "cancelled"
    with pytest.raises(ValueError, match="seeed"):
        c.submit(path, overrides={"sac.seeed": 1})
    with pytest.raises(ValueError, match="section.key=value"):
        c.submit(path, overrides=["sac.seed"])
    with pytest.raises(ValueError, match="overrides"):
        c.submit(path, overrides=3)


def test_refusals_name_what_is_wrong(learner):
    c, url, _ = learner
    bad = tiny("py-bad", 600)
    bad["sac"]["batch_size"] = 0
    with pytest.raises(ValueError, match="batch_size"):
        c.submit(bad)
    with pytest.raises(ValueError, match="unknown_field"):
        c.submit({**tiny("py-bad", 600), "unknown_field": 1})
    with pytest.raises(LookupError, match="999999"):
        c.job(999999)
    job = c.jobs()[-1]
    with pytest.raises(ValueError, match="not a job file"):
        c.file(job.id, "../jobs.redb")
    with pytest.raises(ValueError, match="job_id"):
        c.job(-1)
    with pytest.raises(ValueError, match="config"):
        c.submit({"name": "x", "env": {"scenarios": [None]}})
    with pytest.raises(PermissionError):
        Client(url, token="a-wrong-token-of-length").jobs()
    with pytest.raises(ConnectionError):
        Client(f"http://127.0.0.1:{free_port()}", token=TOKEN)
