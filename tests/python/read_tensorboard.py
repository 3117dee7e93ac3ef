"""Reads a job's TensorBoard event files with the official `tensorboard` package and checks the
scalars socialflow promises are there. Usage: read_tensorboard.py <event dir> <min points>.
Prints `<tag> <points>` lines; exits non-zero (with the reason) if a tag is missing or short."""
import sys

from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

TAGS = [
    "rollout/success", "rollout/safety", "rollout/speed", "ends/collision", "ends/timeout",
    "loss/critic", "loss/actor", "sac/alpha", "sac/entropy", "rate/updates_per_s",
    "rate/transitions_per_s", "policy/version",
]

def main() -> int:
    logdir, min_points = sys.argv[1], int(sys.argv[2])
    acc = EventAccumulator(logdir, size_guidance={"scalars": 0})
    acc.Reload()
    have = set(acc.Tags()["scalars"])
    bad = []
    for tag in TAGS:
        n = len(acc.Scalars(tag)) if tag in have else 0
        print(tag, n)
        if n < min_points:
            bad.append(f"{tag}: {n} points")
    steps = [e.step for e in acc.Scalars("rollout/success")] if "rollout/success" in have else []
    if steps != sorted(steps):
        bad.append("rollout/success steps are not increasing")
    if bad:
        print("missing or short:", ", ".join(bad), file=sys.stderr)
        return 1
    return 0

if __name__ == "__main__":
    sys.exit(main())
