"""Pipeline entry of SoPrA's simulated twin: tip x-y coverage, held-out pressure-ramp rollouts."""
from __future__ import annotations

import numpy as np
import torch
from tensordict import TensorDict

from torchrl_softae.envs.robots import EnvRecord
from torchrl_softae.envs.robots.sopra.env import SoPrAEnv
from torchrl_softae.pipeline.entries.entry import EnvEntry

__all__ = ["entry"]


def _heldout(n: int, seed: int) -> TensorDict:
    """Rollouts that ramp the pressures toward random setpoints (no explored data involved)."""
    rng = np.random.default_rng(seed)
    env = SoPrAEnv("sim", seed=seed, install_signal_handlers=False, max_steps=10**9)
    obs_l, act_l, nxt_l = [], [], []
    while len(act_l) < n:
        env.set_seed(int(rng.integers(1 << 30)))
        obs = env.reset()["observation"]
        goal = rng.uniform(0, env.limits.p_max, 6) * (rng.random(6) < 0.6)
        for _ in range(40):
            a = np.clip((goal - env.safety.last_command) / env.max_step + rng.normal(0, 0.2, 6), -1, 1)
            td = env.step(TensorDict({"action": torch.as_tensor(a, dtype=torch.float32)}, []))["next"]
            if bool(td["terminated"]):
                break
            obs_l.append(obs), act_l.append(a.astype(np.float32)), nxt_l.append(td["observation"])
            obs = td["observation"]
            if len(act_l) >= n:
                break
    env.close()
    f = lambda x: torch.as_tensor(np.array(x), dtype=torch.float32)
    return TensorDict({"observation": torch.stack(obs_l), "action": f(act_l),
                       ("next", "observation"): torch.stack(nxt_l)}, [n])


def entry(record: EnvRecord, tasks: dict) -> EnvEntry:
    return EnvEntry(
        env_id=record.env_id,
        make=lambda: SoPrAEnv("sim", install_signal_handlers=False),
        tasks=tasks,
        projection=lambda obs: obs[..., 0:2],
        projection_labels=("tip x [m]", "tip y [m]"),
        heldout=_heldout,
        defaults={"planner": {"horizon": 5, "noise_beta": 1.0}},
        version="2",
        description="SoPrA pneumatic arm, simulated twin (32D state, 6 pressure deltas)",
    )
