"""Pipeline entries of the MuJoCo robots: fish tasks (iii)-(vi), leg tasks (vii)-(viii).

Held-out sets come from scripted controllers that use no explored data: travelling-wave gaits
with random frequency/phase/amplitude/bias for the fish, random periodic muscle patterns with a
random roll for the leg.
"""
from __future__ import annotations

import math

import numpy as np
import torch
from tensordict import TensorDict
from torchrl.data import Unbounded

from torchrl_softae.envs.catalog import EnvEntry, register_env_entry
from torchrl_softae.tasks.base import Task


def _gym_env(env_id: str, info_key: str, size: int):
    from torchrl.envs import GymEnv
    from torchrl.envs.libs.gym import default_info_dict_reader

    env = GymEnv(env_id)
    env.set_info_dict_reader(default_info_dict_reader([info_key], spec={info_key: Unbounded((size,), dtype=torch.float32)}))
    return env


def _rollouts(make_env, policy_factory, n: int, seed: int, info_key: str, horizon: int) -> TensorDict:
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


# ---------------------------------------------------------------- fish
def _wave_policy(rng):
    freq, phase, amp = rng.uniform(0.5, 4.0), rng.uniform(-1.2, 1.2), rng.uniform(0.2, 1.0)
    bias = rng.uniform(-0.5, 0.5) * (rng.random() < 0.5)

    def policy(k):
        t = 0.02 * k
        a = [amp * math.sin(2 * math.pi * freq * t - phase * i) + bias for i in range(4)]
        return np.clip(np.array(a, dtype=np.float32), -1, 1)

    return policy


def _fish_heldout(with_target: bool):
    from torchrl_softae.envs.fish import SoftFishEnv

    def make(n: int, seed: int) -> TensorDict:
        return _rollouts(lambda: SoftFishEnv(with_target=with_target), _wave_policy, n, seed, "position", 200)

    return make


def _fish_entry(env_id: str, with_target: bool) -> EnvEntry:
    o = 3 if with_target else 0
    if with_target:
        tasks = {
            "to-target": Task("to-target", lambda s, a, s2: -s2[..., 0:3].norm(dim=-1), 200, None,
                              "(v) swim to the target: -||p - p_target||"),
            "from-target": Task("from-target", lambda s, a, s2: s2[..., 0:3].norm(dim=-1), 200, None,
                                "(vi) swim away from the target: +||p - p_target||"),
        }
    else:
        tasks = {
            "forward": Task("forward", lambda s, a, s2: s2[..., o], 200, None, "(iii) swim along +x: v_x"),
            "backward": Task("backward", lambda s, a, s2: -s2[..., o], 200, None, "(iv) turn and swim along -x: -v_x"),
        }
    return EnvEntry(
        env_id=env_id,
        make=lambda: _gym_env(env_id, "position", 2),
        tasks=tasks,
        projection=lambda pos: pos,
        projection_keys=("position",),
        projection_labels=("x [m]", "y [m]"),
        heldout=_fish_heldout(with_target),
        defaults={"episode_length": 200, "train": {"max_grad_steps": 7500},
                  "planner": {"horizon": 100 if with_target else 10}},
        description=f"MuJoCo articulated fish in fluid, {18 if with_target else 15}D state, 4 joint torques",
    )


# ---------------------------------------------------------------- leg
def _muscle_pattern_policy(rng):
    freq, duty, roll = rng.uniform(2.0, 7.0), rng.uniform(0.2, 0.6), rng.uniform(-1, 1)
    levels = rng.uniform(-1, 1, 4)

    def policy(k):
        stance = (0.01 * k * freq) % 1.0 < duty
        hip = levels[:2] if stance else levels[:2][::-1]
        knee = np.array([-1.0, 1.0]) if stance else np.array([1.0, -1.0])
        return np.clip(np.r_[roll, hip, knee * abs(levels[2])], -1, 1).astype(np.float32)

    return policy


def _leg_heldout(n: int, seed: int) -> TensorDict:
    from torchrl_softae.envs.msk_leg import MSKLegEnv

    return _rollouts(MSKLegEnv, _muscle_pattern_policy, n, seed, "foot_height", 500)


register_env_entry(_fish_entry("SoftFish-v0", False))
register_env_entry(_fish_entry("SoftFishTarget-v0", True))
register_env_entry(
    EnvEntry(
        env_id="MSKLeg-v0",
        make=lambda: _gym_env("MSKLeg-v0", "foot_height", 1),
        tasks={
            "ccw": Task("ccw", lambda s, a, s2: s2[..., 5], 500, None, "(vii) hop counter-clockwise: +yaw rate"),
            "cw": Task("cw", lambda s, a, s2: -s2[..., 5], 500, None, "(viii) hop clockwise: -yaw rate"),
        },
        projection=lambda obs, foot: torch.stack([obs[..., 0], foot[..., 0]], -1),
        projection_keys=("observation", "foot_height"),
        projection_labels=("boom yaw [rad]", "foot height [m]"),
        heldout=_leg_heldout,
        defaults={"episode_length": 500, "planner": {"horizon": 100}},
        description="MuJoCo hopping leg on a boom, HASEL muscles + DC motor, 10D state, 5 actions",
    )
)
