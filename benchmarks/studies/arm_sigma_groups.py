"""Which state dimensions drive the exploration reward ||sigma|| on the soft arm?

    python benchmarks/studies/arm_sigma_groups.py benchmarks/results/runs/arm_v1/softae-s0

Loads a run's model and replay buffer, evaluates the epistemic std sigma(s, a) on its visited
states with uniform random actions, and reports each state group's share of sum(sigma^2), in
original units and after the per-dimension scaling the pipeline applies (sigma / state std of the
data, ``normalize_uncertainty``, the same for SoftAE, Mean-AE and PETS-AE). Writes
benchmarks/results/arm_sigma_groups.json.
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

import torch

from torchrl_softae.envs.robots.soft_arm import arm_layout
from torchrl_softae.pipeline.evaluate import load_run
from torchrl_softae.pipeline.runs import RunDir


def main():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("run_dir", help="a soft-arm run dir")
    run_dir = Path(p.parse_args().run_dir)
    cfg, model, state = load_run(run_dir)
    rb = RunDir(run_dir).load_replay_buffer(state)
    obs = rb.storage[: len(rb)]["observation"]
    g = torch.Generator().manual_seed(0)
    act = torch.rand(obs.shape[0], model.action_dim, generator=g) * 2 - 1
    with torch.no_grad():
        _, sigma, _, _ = model.predict(obs, act)
    scale = model.input_normalizer.scale[: model.observation_dim]
    points = 5 if model.observation_dim == 58 else 11
    out = {"run": str(run_dir), "episodes": state["episode"] + 1, "groups": {}}
    for label, s in (("original units", sigma), ("scaled by state std", sigma / scale)):
        total = s.square().sum(-1).mean()
        shares = {name: float(s[:, sl].square().sum(-1).mean() / total) for name, sl in arm_layout(points).items()}
        out["groups"][label] = shares
        print(f"{label}: " + ", ".join(f"{k} {100 * v:.1f}%" for k, v in shares.items()))
    top = (sigma.square().mean(0) / sigma.square().mean(0).sum()).topk(5)
    out["top_dims_original"] = {int(i): float(v) for v, i in zip(*top)}
    print("top dims (original units):", {int(i): round(float(v), 3) for v, i in zip(*top)})
    Path(__file__).parents[1].joinpath("results", "arm_sigma_groups.json").write_text(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
