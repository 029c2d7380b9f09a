"""Held-out sets from scripted controllers on gymnasium robots (no explored data), and TorchRL
envs that report an ``info`` entry (e.g. the fish's world position) for coverage plots."""
from __future__ import annotations

import numpy as np
import torch
from tensordict import TensorDict
from torchrl.data import Unbounded


__all__ = ["gym_env_with_info", "scripted_rollouts"]


def gym_env_with_info(env_id: str, info_key: str, size: int):
    from torchrl.envs import GymEnv
    from torchrl.envs.libs.gym import default_info_dict_reader

    env = GymEnv(env_id)
    env.set_info_dict_reader(default_info_dict_reader([info_key], spec={info_key: Unbounded((size,), dtype=torch.float32)}))
    return env


def scripted_rollouts(make_env, policy_factory, n: int, seed: int, info_key: str, horizon: int) -> TensorDict:
    """Transitions of scripted episodes until ``n`` are collected."""
    rng = np.random.default_rng(seed)
    env = make_env()
    obs_l, act_l, nxt_l, info_l, ninfo_l = [], [], [], [], []
    ep = 0
    while len(act_l) < n:
        obs, info = env.reset(seed=int(seed * 1000 + ep))
        policy = policy_factory(rng)
        for k in range(horizon):
            a = policy(k)
            nxt, _, term, _, ninfo = env.step(a)
            if term:
                break
            obs_l.append(obs), act_l.append(a), nxt_l.append(nxt)
            info_l.append(np.asarray(info[info_key], dtype=np.float32)), ninfo_l.append(np.asarray(ninfo[info_key], dtype=np.float32))
            obs, info = nxt, ninfo
            if len(act_l) >= n:
                break
        ep += 1
    f = lambda x: torch.as_tensor(np.array(x), dtype=torch.float32)
    return TensorDict({"observation": f(obs_l), "action": f(act_l), info_key: f(info_l),
                       ("next", "observation"): f(nxt_l), ("next", info_key): f(ninfo_l)}, [n])


