"""`python -m socialflow [--help | --version]`: the package's entry points, one line each, and
where the Rust command line takes over (training, job graphs, evaluation grids, reports)."""

import argparse
import sys

import socialflow

ENTRY_POINTS = (
    ("make_ego", "the ego's seat among a flow: a gymnasium.Env"),
    ("make_ego_vec", "N ego seats stepped together in Rust: a gymnasium.vector.VectorEnv"),
    ("make_flow", "every vehicle of a scenario: a PettingZoo ParallelEnv"),
    ("load_policy", "a trained job's actor as a callable (Rust inference)"),
    ("evaluate", "a policy in the ego's seat over the stored cases, as `socialflow eval` scores it"),
)


def main(argv=None):
    epilog = "entry points:\n" + "\n".join(f"  socialflow.{name:<13} {what}" for name, what in ENTRY_POINTS)
    epilog += "\n\ntraining, job graphs, evaluation grids and reports: the `socialflow` command (`socialflow --help`)"
    p = argparse.ArgumentParser(prog="python -m socialflow", description=__doc__.splitlines()[0], epilog=epilog, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--version", action="version", version=f"socialflow {socialflow.__version__}")
    p.parse_args(argv)
    p.print_help()
    return 0


if __name__ == "__main__":
    sys.exit(main())
