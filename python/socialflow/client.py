"""`socialflow.client`: submit and follow jobs on a socialflow learner from Python.

    from socialflow.client import Client
    c = Client("http://127.0.0.1:50051")              # token: SOCIALFLOW_TOKEN, or token=/token_file=
    job = c.submit("configs/quickstart.toml")          # a path, TOML text, or a dict
    for p in c.watch(job.id):                           # progress until the job ends
        print(p.state, p.progress["env_steps"])
    done = c.wait(job.id)                               # the final Job
    c.download(job.id, "quickstart-job")               # config, actor, curves
    policy = socialflow.load_policy("quickstart-job")  # ... and act with it here

The calls are the learner's gRPC job API (`proto/socialflow/v1/socialflow.proto`) through the
package's native module, which uses the stubs generated from the proto at build time; the same
calls as `socialflow submit | status | watch | cancel | download`. Errors: `ValueError` for a
config or argument the learner or this module refuses (the message names the field),
`LookupError` for an unknown job or a file the job has not written, `PermissionError` for a
missing or wrong token, `ConnectionError` when the learner cannot be reached, `TimeoutError`
when a call outlives its 30 s deadline, `RuntimeError` otherwise.
"""

from __future__ import annotations

import csv
import io
import json
import os
from dataclasses import dataclass, field
from typing import Any, Callable, Dict, Iterator, List, Mapping, Optional, Sequence, Union

from . import _socialflow

__all__ = ["Client", "Job", "Progress", "FINAL_STATES"]

FINAL_STATES = ("succeeded", "failed", "cancelled")

PathLike = Union[str, "os.PathLike[str]"]


@dataclass(frozen=True)
class Job:
    """A job as the learner reports it. `progress` is the learner's progress record (a dict:
    `env_steps`, `updates`, `episodes`, `success`, `safety`, `speed`, the losses,
    `policy_version`, `target_env_steps`, `env_steps_per_s`, ...); `config_toml` is set by `Client.job`."""

    id: int
    name: str
    state: str
    message: str
    artifact_dir: str
    progress: Dict[str, Any] = field(default_factory=dict)
    config_toml: Optional[str] = None

    @property
    def is_final(self) -> bool:
        return self.state in FINAL_STATES

    @classmethod
    def _from_json(cls, text_or_dict: Union[str, Mapping[str, Any]]) -> "Job":
        d = json.loads(text_or_dict) if isinstance(text_or_dict, str) else text_or_dict
        return cls(
            id=int(d["job_id"]),
            name=d["name"],
            state=d["state"],
            message=d.get("message", ""),
            artifact_dir=d.get("artifact_dir", ""),
            progress=d.get("progress") or {},
            config_toml=d.get("config_toml"),
        )


@dataclass(frozen=True)
class Progress:
    """One change of a watched job: its `state` and the learner's `progress` record."""

    state: str
    progress: Dict[str, Any]

    @property
    def is_final(self) -> bool:
        return self.state in FINAL_STATES


def _toml_value(v: Any, where: str) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, (int, float)):
        return repr(v)
    if isinstance(v, str):
        return json.dumps(v)  # a JSON string is a valid TOML basic string
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_toml_value(x, where) for x in v) + "]"
    if isinstance(v, Mapping):
        return "{ " + ", ".join(f"{k} = {_toml_value(x, f'{where}.{k}')}" for k, x in v.items()) + " }"
    raise ValueError(f"config: {where} = {v!r} has no TOML form ({type(v).__name__})")


def config_to_toml(config: Mapping[str, Any]) -> str:
    """A job config given as a dict (top-level fields, and one dict per section such as
    `env`, `sac`, `train`) as TOML text."""
    top, sections = [], []
    for k, v in config.items():
        if isinstance(v, Mapping):
            lines = [f"[{k}]"] + [f"{kk} = {_toml_value(vv, f'{k}.{kk}')}" for kk, vv in v.items()]
            sections.append("\n".join(lines))
        else:
            top.append(f"{k} = {_toml_value(v, k)}")
    return "\n".join(top + [""] + sections) + "\n"


def _override_list(overrides: Union[Mapping[str, Any], Sequence[str]]) -> List[str]:
    """`section.key=value` strings from a dict of dotted keys or a list of such strings."""
    if isinstance(overrides, Mapping):
        out = []
        for k, v in overrides.items():
            if not isinstance(k, str) or not k:
                raise ValueError(f"overrides: key {k!r} is not a dotted setting name")
            out.append(f"{k}={_toml_value(v, k)}")
        return out
    if isinstance(overrides, (list, tuple)) and all(isinstance(s, str) for s in overrides):
        return list(overrides)
    raise ValueError(f"overrides: {overrides!r} is neither a dict nor a list of 'section.key=value' strings")


class Client:
    """A connection to a learner's job API.

    `url`: `http://host:port`, or `https://...` with `tls_ca_file` (and, for a learner that
    requires client certificates, `tls_client_cert_file` with `tls_client_key_file`). The
    bearer token: `token`, or the file `token_file`, else the `SOCIALFLOW_TOKEN` variable."""

    def __init__(
        self,
        url: str = "http://127.0.0.1:50051",
        *,
        token: Optional[str] = None,
        token_file: Optional[PathLike] = None,
        tls_ca_file: Optional[PathLike] = None,
        tls_client_cert_file: Optional[PathLike] = None,
        tls_client_key_file: Optional[PathLike] = None,
    ) -> None:
        if not isinstance(url, str):
            raise ValueError(f"url: {url!r} is not a string")
        opt = lambda p: None if p is None else os.fspath(p)  # noqa: E731
        self._c = _socialflow.JobClient(
            url,
            token,
            opt(token_file),
            opt(tls_ca_file),
            opt(tls_client_cert_file),
            opt(tls_client_key_file),
        )
        self.url = url

    def submit(
        self,
        config: Union[PathLike, str, Mapping[str, Any]],
        *,
        overrides: Optional[Union[Mapping[str, Any], Sequence[str]]] = None,
    ) -> Job:
        """Queues a job config or evaluation grid: a path to a `.toml` file, TOML text, or a
        dict (see `config_to_toml`). `overrides`: settings written over it, as the command
        line's `--set`: `{"sac.seed": 12}` or `["sac.seed=12"]`; they are recorded in the job's
        stored config. The learner validates the result; a refusal raises `ValueError` naming
        the field."""
        if isinstance(config, Mapping):
            text = config_to_toml(config)
        elif isinstance(config, os.PathLike) or (
            isinstance(config, str) and "\n" not in config and config.endswith(".toml")
        ):
            with open(os.fspath(config), encoding="utf-8") as f:
                text = f.read()
        elif isinstance(config, str):
            text = config
        else:
            raise ValueError(f"config: {config!r} is not a path, TOML text or dict")
        if overrides is not None:
            text = _socialflow.apply_overrides(text, _override_list(overrides))
        return Job._from_json(self._c.submit(text))

    def job(self, job_id: int) -> Job:
        """One job, with its config (`Job.config_toml`)."""
        return Job._from_json(self._c.job(_job_id(job_id)))

    def jobs(self) -> List[Job]:
        """Every job on the learner, newest first (without configs)."""
        return [Job._from_json(d) for d in json.loads(self._c.jobs())]

    def cancel(self, job_id: int) -> Job:
        """Cancels a queued or running job; a finished one comes back unchanged."""
        return Job._from_json(self._c.cancel(_job_id(job_id)))

    def watch(self, job_id: int) -> Iterator[Progress]:
        """The job's progress: its state now, then each change (a few per second at most),
        ending after the change that carries a final state."""
        w = self._c.watch(_job_id(job_id))
        while True:
            n = w.next()
            if n is None:
                return
            d = json.loads(n)
            yield Progress(state=d["state"], progress=d["progress"])

    def wait(self, job_id: int, on_progress: Optional[Callable[[Progress], None]] = None) -> Job:
        """Follows the job until it ends (calling `on_progress` with each change) and returns
        the final `Job`."""
        for p in self.watch(job_id):
            if on_progress is not None:
                on_progress(p)
        return self.job(job_id)

    def file(self, job_id: int, name: str) -> bytes:
        """One file of the job's artifact directory: `config.toml`, `policy.bpk`,
        `policy.json`, `best_policy.bpk`, `best_policy.json`, `curve.csv`, `curve.png`,
        `validation.csv`, `coordinator.json`, `state.json`, `episodes.csv`, `meta.json`."""
        if not isinstance(name, str):
            raise ValueError(f"name: {name!r} is not a file name")
        return self._c.file(_job_id(job_id), name)

    def curve(self, job_id: int) -> List[Dict[str, float]]:
        """The job's training curve (`curve.csv`), one dict per point."""
        return _csv_rows(self.file(job_id, "curve.csv"))

    def validation(self, job_id: int) -> List[Dict[str, float]]:
        """The job's held-out validation points (`validation.csv`), where it validates."""
        return _csv_rows(self.file(job_id, "validation.csv"))

    def policy_bytes(self, job_id: int) -> bytes:
        """The succeeded job's kept actor (`policy.bpk`, burn's format)."""
        return self.file(job_id, "policy.bpk")

    def download(self, job_id: int, dir: PathLike) -> List[str]:
        """Writes a succeeded job's files into `dir`: a training job's `config.toml`,
        `policy.bpk`, `policy.json` and its curves (a directory `socialflow.load_policy` and
        `socialflow eval` read), or an evaluation's results. Returns the names written."""
        return list(self._c.download(_job_id(job_id), os.fspath(dir)))


def _job_id(job_id: Any) -> int:
    if isinstance(job_id, bool) or not isinstance(job_id, int) or job_id < 0:
        raise ValueError(f"job_id: {job_id!r} is not a job id (a non-negative int)")
    return job_id


def _csv_rows(data: bytes) -> List[Dict[str, float]]:
    rows = []
    for r in csv.DictReader(io.StringIO(data.decode("utf-8"))):
        rows.append({k: _number(v) for k, v in r.items()})
    return rows


def _number(v: str) -> Any:
    try:
        return float(v)
    except (TypeError, ValueError):
        return v
