"""Classic control systems used to test the method on something cheap: a pendulum that must pump
energy before exploration pays off. (Pendulum-v1 itself is gymnasium's; cartpole is dm_control's.)"""
from __future__ import annotations

import math

import gymnasium as gym
import numpy as np

__all__ = ["HangingStart", "make_hanging_pendulum"]


class HangingStart(gym.Wrapper):
    """Pendulum-v1 whose episodes all start hanging down at rest (th = pi +- 0.05, thdot = 0).

    Random torques (|u| <= 2, below what lifting the pendulum over the top in one push needs)
    then stay near the bottom, so covering the state space takes deliberate energy pumping:
    the setting where active exploration should beat random actions.
    """

    def reset(self, *, seed=None, options=None):
        _, info = self.env.reset(seed=seed, options=options)
        th = math.pi + self.env.unwrapped.np_random.uniform(-0.05, 0.05)
        self.env.unwrapped.state = np.array([th, 0.0])
        return np.array([math.cos(th), math.sin(th), 0.0], dtype=np.float32), info


def make_hanging_pendulum(**kwargs) -> gym.Env:
    """``Pendulum-hanging``: gymnasium's Pendulum-v1 behind :class:`HangingStart`."""
    return HangingStart(gym.make("Pendulum-v1", **kwargs).unwrapped)
