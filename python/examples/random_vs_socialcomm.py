# A random driving policy against a trained SocialComm flow: no training, ten lines.
import sys, numpy as np, socialflow

flow = sys.argv[1] if len(sys.argv) > 1 else "runs/embedded/jobs/1-flow-socialcomm"  # socialflow train configs/flow-socialcomm.toml
rng = np.random.default_rng(0)
policy = lambda obs: rng.uniform(-1, 1, (len(obs), 2)).astype(np.float32)  # [reference speed, steer]
result = socialflow.evaluate(policy, grid={"flows": {"socialcomm": flow, "idm": "idm"}, "scenarios": ["merge"], "cases": 50, "seeds": 2})
for s in result.summary:
    print(f"{s['flow']:>10} {s['scenario']}: success {s['success']['mean']:.2f} +- {s['success']['ci95']:.2f}, collisions {s['collision']['mean']:.2f}")
result.to_csv("episodes.csv")  # the columns of `socialflow eval`'s episodes.csv
