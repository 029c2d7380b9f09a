"""Zero-shot evaluation of E episodes as one batch (one planner call per step for all E states)
vs one episode after another, same model, same planner settings, same seeded episodes.

    python benchmarks/eval_batch_speed.py           # Pendulum-hanging and SoftFish-v0, E = 8

The model is a paper-sized ensemble (5 x 4 x 256) with normalizers fitted on random transitions
(speed does not depend on training); the planner is the paper's iCEM (P=200, K=20, 5 iterations)
with mean propagation (one particle), H from the env's defaults, fp32; episodes are cut to
``--steps`` control steps (the ratio does not depend on it). Both modes run twice, interleaved,
and the best of each is kept. Results: stdout and benchmarks/results/eval_batch_speed.json.
"""
from __future__ import annotations

import argparse
import json
import time
from dataclasses import replace
from pathlib import Path

import torch

from torchrl_softae.pipeline.builders import build_world_model
from torchrl_softae.pipeline.catalog import get_env_entry
from torchrl_softae.pipeline.config import make_config
from torchrl_softae.pipeline.data import make_real_env
from torchrl_softae.pipeline.evaluate import zero_shot


def model_for(env_id: str, cfg):
    env = make_real_env(get_env_entry(env_id), 50)
    data = env.rollout(300, break_when_any_done=False)
    env.close()
    obs, act, nxt = data["observation"], data["action"], data["next", "observation"]
    model = build_world_model(cfg.model, obs.shape[-1], act.shape[-1])
    model.fit_normalizers(obs, act, nxt)
    return model.eval()


def main():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--envs", nargs="+", default=["Pendulum-hanging", "SoftFish-v0"])
    p.add_argument("--episodes", type=int, default=8)
    p.add_argument("--steps", type=int, default=50)
    p.add_argument("--threads", type=int, default=2)
    args = p.parse_args()
    torch.set_num_threads(args.threads)
    results = {}
    for env_id in args.envs:
        cfg = make_config(env_id, "softae", wandb="disabled")
        model = model_for(env_id, cfg)
        task = next(iter(get_env_entry(env_id).tasks.values()))
        task = replace(task, horizon=args.steps)
        times = {"batched": [], "sequential": []}
        for _ in range(2):
            for mode in ("batched", "sequential"):
                t = time.perf_counter()
                res = zero_shot(cfg, model, task, episodes=args.episodes, seed=0, progress=False,
                                batched=mode == "batched")
                times[mode].append(time.perf_counter() - t)
                results.setdefault(env_id, {})[f"{mode}_initial_states"] = res["initial_states"]
        b, s = min(times["batched"]), min(times["sequential"])
        same = results[env_id].pop("batched_initial_states") == results[env_id].pop("sequential_initial_states")
        results[env_id].update({"task": task.name, "episodes": args.episodes, "steps": args.steps,
                                "horizon": cfg.planner.horizon, "batched_s": b, "sequential_s": s,
                                "speedup": s / b, "same_initial_states": same})
        print(f"{env_id} ({task.name}, {args.episodes} episodes x {args.steps} steps, H={cfg.planner.horizon}): "
              f"one after another {s:.1f} s, as one batch {b:.1f} s -> {s / b:.2f}x; same initial states: {same}",
              flush=True)
    out = Path(__file__).parent / "results" / "eval_batch_speed.json"
    out.write_text(json.dumps(results, indent=1))


if __name__ == "__main__":
    main()
