"""Runs the reference benchmark's SAC update (../shared/bench/sac_torch.py, unchanged) on a CUDA
device: the batches are drawn on the CPU with the script's own generator, moved to the GPU, and
the networks are built there. Each update ends in .item(), so wall-clock timing is synchronised.

    PYTHONPATH=../shared/bench python3 crates/lab/scripts/results/bench/sac_torch_cuda.py paper:50 compact:100 small:100
"""
import json
import statistics
import sys
import time

import sac_torch as m
import torch


def to_cuda(x):
    if isinstance(x, dict):
        return {k: to_cuda(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return type(x)(to_cuda(v) for v in x)
    return x.cuda()

def bench(size, iters, warmup):
    cfg = m.SIZES[size]
    torch.manual_seed(0)
    gen = torch.Generator().manual_seed(0)
    batches = [to_cuda(m.make_batch(cfg, gen)) for _ in range(2)]
    torch.set_default_device("cuda")
    sac = m.SAC(cfg)
    for i in range(warmup):
        sac.update(batches[i % 2])
    times = []
    for i in range(iters):
        t0 = time.perf_counter()
        sac.update(batches[i % 2])
        times.append(time.perf_counter() - t0)
    torch.set_default_device("cpu")
    med = statistics.median(times)
    return {"size": size, "updates_per_s": 1.0 / med, "median_s": med, "min_s": min(times), "n": iters}

if __name__ == "__main__":
    out = {"impl": f"pytorch {torch.__version__} cuda", "gpu": torch.cuda.get_device_name(0)}
    out["runs"] = [bench(s, int(n), 5) for s, n in (a.split(":") for a in sys.argv[1:])]
    print(json.dumps(out, indent=1))
