"""The IDM driver as a Python policy in the ego's seat among a trained flow (a job directory:
SocialComm, CoPO, FailMaker or SocialCommAdv with its adversary), through the socialflow package;
also steps the Gymnasium environment among that flow. Prints one JSON object with the episodes,
for the Rust test to compare with `socialflow eval-flow --policy <dir> --ego idm`.
Usage: flow_ego_equality.py JOB_DIR SCENARIO CASES SEEDS"""

import json
import sys

import numpy as np

import socialflow


def main():
    flow, scenario, cases, seeds = sys.argv[1], sys.argv[2], int(sys.argv[3]), int(sys.argv[4])
    res = socialflow.evaluate(socialflow.zero_residual_policy(), grid={"flows": {"flow": flow}, "scenarios": [scenario], "cases": cases, "seeds": seeds}, action="idm-accel-residual")
    env = socialflow.make_ego(scenario=scenario, flow=flow, vehicles=(3, 5), action="idm-accel-residual", obs_format="dict")
    obs, _ = env.reset(seed=0)
    steps = 0
    for _ in range(60):
        obs, r, term, trunc, info = env.step(np.zeros(1, np.float32))
        steps += 1
        assert env.observation_space.contains(obs)
        if term or trunc:
            obs, _ = env.reset()
    print(json.dumps({"episodes": res.rows, "env_steps": steps}))


if __name__ == "__main__":
    main()
