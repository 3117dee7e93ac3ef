"""socialflow from Python: Gymnasium and PettingZoo environments over socialflow's Rust
simulator, with the background traffic (IDM, or a trained flow's frozen policy) driven in Rust.

    import socialflow
    env = socialflow.make_ego(scenario="merge", flow="idm")        # gymnasium.Env
    venv = socialflow.make_ego_vec(num_envs=16, scenario="merge")   # gymnasium.vector.VectorEnv
    flow = socialflow.make_flow(scenario="roundabout")              # pettingzoo ParallelEnv
    result = socialflow.evaluate(policy, grid={"flows": {"idm": "idm"}, "scenarios": ["merge"]})
    actor = socialflow.load_policy("runs/quickstart/jobs/1-quickstart")   # a trained job's actor
    jobs = socialflow.client.Client("http://127.0.0.1:50051")             # submit and follow jobs

Rust is the only implementation: this package wraps `crates/sim` and `crates/sac` (module
`socialflow._socialflow`); nothing here steps a vehicle.
"""

from importlib.metadata import PackageNotFoundError, version

from . import _socialflow, client
from .envs import EgoEnv, EgoVectorEnv, make_ego, make_ego_vec, split_obs
from .evaluation import EvalResult, evaluate, zero_residual_policy
from .parallel import FlowParallelEnv, make_flow
from .policy import Policy, load_policy

SCENARIOS = tuple(_socialflow.scenarios())
TERMINATIONS = tuple(_socialflow.terminations())

try:
    __version__ = version("socialflow")
except PackageNotFoundError:  # pragma: no cover - running from a source tree
    __version__ = "0+unknown"

__all__ = [
    "EgoEnv",
    "EgoVectorEnv",
    "EvalResult",
    "FlowParallelEnv",
    "Policy",
    "SCENARIOS",
    "TERMINATIONS",
    "client",
    "evaluate",
    "load_policy",
    "make_ego",
    "make_ego_vec",
    "make_flow",
    "split_obs",
    "zero_residual_policy",
]
