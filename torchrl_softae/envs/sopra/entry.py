"""Pipeline entry of SoPrA's simulated twin: reach tasks (ix)/(x), tip x-y coverage."""
from __future__ import annotations

import numpy as np
import torch
from tensordict import TensorDict

from torchrl_softae.envs.catalog import EnvEntry, register_env_entry
from torchrl_softae.envs.soft_arm import reach_reward
from torchrl_softae.envs.sopra.env import SOPRA_TARGETS, SoPrAEnv
from torchrl_softae.tasks.base import Task


def sopra_reach_task(name: str, target, horizon: int = 20) -> Task:
    tgt = torch.as_tensor(np.asarray(target), dtype=torch.float32)

    def metrics(traj):
        err = (traj["next", "observation"][..., 0:3] - tgt).norm(dim=-1) * 1e3
        return {"final_error_mm": float(err[-1]), "min_error_mm": float(err.min())}

    return Task(name, lambda s, a, s2: reach_reward((s2[..., 0:3] - tgt).norm(dim=-1)), horizon, metrics,
                f"reach {np.round(np.asarray(target), 4).tolist()}", params={"target": np.asarray(target).tolist()})


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


register_env_entry(EnvEntry(
    env_id="SoPrA-v0",
    make=lambda: SoPrAEnv("sim", install_signal_handlers=False),
    tasks={name: sopra_reach_task(name, t) for name, t in SOPRA_TARGETS.items()},
    projection=lambda obs: obs[..., 0:2],
    projection_labels=("tip x [m]", "tip y [m]"),
    heldout=_heldout,
    defaults={"episode_length": 200, "planner": {"horizon": 5, "noise_beta": 1.0}},
    version="2",
    description="SoPrA pneumatic arm, simulated twin (32D state, 6 pressure deltas)",
))
