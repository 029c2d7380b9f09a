"""Model training per gradient step: EnsembleTrainer with Adam's fused kernel vs the per-tensor one.

    python benchmarks/training_speed.py [--dims 58 12] [--steps 250] [--rounds 7] [--threads 1]

The paper's schedule (Table S6: 5 x 4 x 256 ensemble, batch 64, lr 5e-5) on 6,000 transitions of the
given (d_s, d_a) (default the soft arm's), the two trainers' ``fit`` interleaved round by round;
median and best ms per gradient step, the ratio, and the CPU it ran on. A 50-episode arm run makes
50 fits of up to 5,000 steps, about half its wall-clock.
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
import torch
from tensordict import TensorDict

sys.path.insert(0, str(Path(__file__).parent))
from planning_speed import cpu_description  # noqa: E402

from torchrl_softae.modules import EnsembleWorldModel  # noqa: E402
from torchrl_softae.objectives import EnsembleLoss, EnsembleTrainer  # noqa: E402


def main():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--dims", type=int, nargs=2, default=[58, 12], metavar=("D_S", "D_A"))
    p.add_argument("--steps", type=int, default=250, help="gradient steps per fit")
    p.add_argument("--rounds", type=int, default=7)
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--out", default=None, help="write the result JSON here")
    args = p.parse_args()
    for name in ("steps", "rounds", "threads"):
        if getattr(args, name) < 1:
            p.error(f"--{name} {getattr(args, name)}: expected a positive integer")
    torch.set_num_threads(args.threads)
    d_s, d_a = args.dims
    n = 6000
    g = torch.Generator().manual_seed(0)
    obs = torch.randn(n, d_s, generator=g)
    data = TensorDict({"observation": obs, "action": torch.rand(n, d_a, generator=g) * 2 - 1,
                       ("next", "observation"): obs + 0.1 * torch.randn(n, d_s, generator=g)}, [n])
    trainers = {}
    for fused in (True, False):
        torch.manual_seed(0)
        trainers["fused" if fused else "per-tensor"] = EnsembleTrainer(
            EnsembleLoss(EnsembleWorldModel(d_s, d_a)), max_grad_steps=args.steps, fused=fused)
    for t in trainers.values():  # warm-up
        t.fit(data)
    ms = {k: [] for k in trainers}
    for _ in range(args.rounds):
        for k, t in trainers.items():
            t0 = time.perf_counter()
            report = t.fit(data)
            ms[k].append(1e3 * (time.perf_counter() - t0) / report.grad_steps)
    cpu = cpu_description()
    print(f"CPU: {cpu}; torch {torch.__version__}, {args.threads} thread(s); (d_s, d_a) = ({d_s}, {d_a})")
    for k, v in ms.items():
        print(f"{k:>10}: median {np.median(v):.2f} ms per gradient step, best {min(v):.2f}")
    ratio = {"median": float(np.median(ms["per-tensor"]) / np.median(ms["fused"])),
             "best": float(min(ms["per-tensor"]) / min(ms["fused"]))}
    print(f"fused is {ratio['median']:.2f}x faster (median), {ratio['best']:.2f}x (best)")
    if args.out:
        Path(args.out).write_text(json.dumps({"cpu": cpu, "torch": torch.__version__, "threads": args.threads,
                                              "dims": [d_s, d_a], "ms_per_step": ms, "speedup": ratio}, indent=1))


if __name__ == "__main__":
    main()
