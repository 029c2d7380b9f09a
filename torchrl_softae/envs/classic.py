"""Cheap real environments to test the pipeline end to end: gymnasium Pendulum-v1 and
dm_control's cartpole, both through TorchRL's own wrappers."""
from __future__ import annotations

import math

import numpy as np
import torch
from tensordict import TensorDict
from torchrl.envs import CatTensors, Compose, DoubleToFloat, GymEnv, TransformedEnv

from torchrl_softae.envs.catalog import EnvEntry, register_env_entry
from torchrl_softae.tasks.base import Task

# ---------------------------------------------------------------- Pendulum-v1
# observation = (cos th, sin th, thdot), action = torque in [-2, 2]


def _angle(obs):
    return torch.atan2(obs[..., 1], obs[..., 0])


def _swingup_reward(obs, action, next_obs):
    # gymnasium's Pendulum reward, written on the observation (it depends on s and a only)
    th, thdot = _angle(obs), obs[..., 2]
    return -(th.square() + 0.1 * thdot.square() + 0.001 * action[..., 0].square())


def _upright_metrics(traj):
    obs = traj["next", "observation"]
    up = (_angle(obs).abs() < 0.3).float()
    return {"upright_fraction_last_half": float(up[..., up.shape[-1] // 2 :].mean())}


def _spin_reward(obs, action, next_obs):
    return next_obs[..., 2]  # counter-clockwise angular velocity


def _pendulum_heldout(n: int, seed: int) -> TensorDict:
    """Uniform over the state-action box: th in [-pi, pi), thdot in [-8, 8], u in [-2, 2]."""
    import gymnasium as gym

    env = gym.make("Pendulum-v1").unwrapped
    env.reset(seed=seed)
    rng = np.random.default_rng(seed)
    th = rng.uniform(-math.pi, math.pi, n)
    thdot = rng.uniform(-8, 8, n)
    u = rng.uniform(-2, 2, n)
    obs, nxt = np.zeros((n, 3)), np.zeros((n, 3))
    for i in range(n):
        env.state = np.array([th[i], thdot[i]])
        obs[i] = [math.cos(th[i]), math.sin(th[i]), thdot[i]]
        nxt[i] = env.step(np.array([u[i]], dtype=np.float32))[0]
    f = lambda x: torch.as_tensor(x, dtype=torch.float32)
    return TensorDict({"observation": f(obs), "action": f(u[:, None]), ("next", "observation"): f(nxt)}, [n])


def _make_hanging_pendulum():
    """Pendulum-v1 whose episodes all start hanging down at rest (th = pi +- 0.05, thdot = 0).

    Random torques (|u| <= 2, below what lifting the pendulum over the top in one push needs)
    then stay near the bottom, so covering the state space takes deliberate energy pumping:
    the setting where active exploration should beat random actions.
    """
    import gymnasium as gym
    from torchrl.envs import GymWrapper

    class HangingStart(gym.Wrapper):
        def reset(self, *, seed=None, options=None):
            _, info = self.env.reset(seed=seed, options=options)
            th = math.pi + self.env.unwrapped.np_random.uniform(-0.05, 0.05)
            self.env.unwrapped.state = np.array([th, 0.0])
            return np.array([math.cos(th), math.sin(th), 0.0], dtype=np.float32), info

    return GymWrapper(HangingStart(gym.make("Pendulum-v1")))


def _pendulum_entry(env_id, make, description):
    return EnvEntry(
        env_id=env_id,
        make=make,
        tasks={
            "swingup": Task("swingup", _swingup_reward, 200, _upright_metrics, "swing up and balance (gymnasium's reward)"),
            "spin": Task("spin", _spin_reward, 200, None, "spin counter-clockwise as fast as possible"),
        },
        projection=lambda obs: torch.stack([_angle(obs), obs[..., 2]], -1),
        projection_labels=("angle [rad]", "angular velocity [rad/s]"),
        heldout=_pendulum_heldout,
        defaults={"episode_length": 200, "planner": {"horizon": 20}},
        description=description,
    )


register_env_entry(_pendulum_entry("Pendulum-v1", lambda: GymEnv("Pendulum-v1"), "gymnasium Pendulum-v1 (3D state, 1 torque)"))
register_env_entry(_pendulum_entry("Pendulum-hanging", _make_hanging_pendulum,
                                   "Pendulum-v1 starting hanging down at rest (exploration must pump energy)"))

# ---------------------------------------------------------------- dm_control cartpole
# observation = (cart x, cos phi, sin phi, x_dot, phi_dot), action = force in [-1, 1]


def _cartpole_swingup(obs, action, next_obs):
    return next_obs[..., 1] - 0.1 * next_obs[..., 0].square()


def _cartpole_move_right(obs, action, next_obs):
    return next_obs[..., 3]


def _make_cartpole():
    from torchrl.envs import DMControlEnv

    return TransformedEnv(
        DMControlEnv("cartpole", "swingup"),
        Compose(CatTensors(["position", "velocity"], "observation", del_keys=True), DoubleToFloat()),
    )


def _cartpole_heldout(n: int, seed: int) -> TensorDict:
    """Uniform states (x, phi, x_dot, phi_dot) and forces, stepped by the true dm_control physics."""
    from dm_control import suite

    env = suite.load("cartpole", "swingup", task_kwargs={"random": seed})
    rng = np.random.default_rng(seed)
    physics = env.physics
    obs, act, nxt = np.zeros((n, 5)), rng.uniform(-1, 1, (n, 1)), np.zeros((n, 5))

    def observe():
        o = env.task.get_observation(physics)
        return np.concatenate([o["position"], o["velocity"]])

    for i in range(n):
        env.reset()
        with physics.reset_context():
            physics.named.data.qpos["slider"] = rng.uniform(-1.5, 1.5)
            physics.named.data.qpos["hinge_1"] = rng.uniform(-math.pi, math.pi)
            physics.named.data.qvel["slider"] = rng.uniform(-3, 3)
            physics.named.data.qvel["hinge_1"] = rng.uniform(-8, 8)
        obs[i] = observe()
        env.step(act[i])
        nxt[i] = observe()
    f = lambda x: torch.as_tensor(x, dtype=torch.float32)
    return TensorDict({"observation": f(obs), "action": f(act), ("next", "observation"): f(nxt)}, [n])


register_env_entry(
    EnvEntry(
        env_id="cartpole-swingup",
        make=_make_cartpole,
        tasks={
            "swingup": Task("swingup", _cartpole_swingup, 200, None, "pole up, cart near the centre"),
            "move-right": Task("move-right", _cartpole_move_right, 200, None, "drive the cart to the right"),
        },
        projection=lambda obs: torch.stack([torch.atan2(obs[..., 2], obs[..., 1]), obs[..., 0]], -1),
        projection_labels=("pole angle [rad]", "cart position [m]"),
        heldout=_cartpole_heldout,
        defaults={"episode_length": 200, "planner": {"horizon": 20}},
        description="dm_control cartpole through TorchRL's DMControlEnv (5D state, 1 force)",
    )
)
