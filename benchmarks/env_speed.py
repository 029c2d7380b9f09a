"""Control steps per second of every environment we ship, on one core, next to gymnasium Pendulum.

    python benchmarks/env_speed.py [--steps 400]

Random actions, raw gymnasium API (no TorchRL wrapper overhead), one thread. Simulator start-up
(and numba compilation on the very first run) is excluded by a warm-up episode.
"""
from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import gymnasium as gym
import torch

import torchrl_softae  # noqa: F401  (registers the ids)

ENVS = [("Pendulum-v1", {}), ("SoftArm-v0", {}), ("SoftArm136-v0", {}), ("SoftFish-v0", {}),
        ("SoftFishTarget-v0", {}), ("MSKLeg-v0", {})]


def steps_per_second(env_id: str, kwargs: dict, steps: int) -> float:
    env = gym.make(env_id, **kwargs)
    env.reset(seed=0)
    for _ in range(5):  # warm-up (JIT, caches)
        env.step(env.action_space.sample())
    env.reset(seed=0)
    t = time.perf_counter()
    n = 0
    while n < steps:
        _, _, term, trunc, _ = env.step(env.action_space.sample())
        n += 1
        if term or trunc:
            env.reset()
    dt = time.perf_counter() - t
    env.close()
    return n / dt


def main():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--steps", type=int, default=400)
    p.add_argument("--out", default=str(Path(__file__).parent / "results" / "env_speed.json"))
    args = p.parse_args()
    torch.set_num_threads(1)
    rows = {}
    print("| env | control steps / s (1 core) |\n|---|---|")
    for env_id, kwargs in ENVS:
        if env_id not in gym.registry:
            continue
        sps = steps_per_second(env_id, kwargs, args.steps)
        rows[env_id] = sps
        print(f"| {env_id} | {sps:,.0f} |", flush=True)
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
