"""Envs and tasks from outside the package, named by reference in the tests (``outside_envs:...``):
a gymnasium env with float64 observations registered on import (``outside_envs:OutsidePoint-v0``),
a TorchRL env from a function (``outside_envs:make_torchrl_point``), tasks (one a catalog task cut
short), and bad references."""
import dataclasses

import gymnasium as gym
import numpy as np
import torch

from torchrl_softae.tasks import Task, tasks_for


class OutsidePoint(gym.Env):
    """A damped point mass on a plane: state (x, y, vx, vy) in float64, action a force in [-1, 1]^2."""

    def __init__(self, dt: float = 0.1):
        self.dt = dt
        self.observation_space = gym.spaces.Box(-np.inf, np.inf, (4,), np.float64)
        self.action_space = gym.spaces.Box(-1.0, 1.0, (2,), np.float32)
        self.state = np.zeros(4)

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        self.state = np.concatenate([self.np_random.uniform(-0.5, 0.5, 2), np.zeros(2)])
        return self.state.copy(), {}

    def step(self, action):
        x, v = self.state[:2], self.state[2:]
        v = 0.9 * v + self.dt * np.clip(action, -1, 1)
        self.state = np.concatenate([x + self.dt * v, v])
        return self.state.copy(), -float(np.linalg.norm(self.state[:2])), False, False, {}


gym.register("OutsidePoint-v0", entry_point=OutsidePoint, max_episode_steps=25)


def make_torchrl_point():
    """The same point mass as a TorchRL env (float64 observations, as GymWrapper gives them)."""
    from torchrl.envs import GymWrapper

    return GymWrapper(OutsidePoint())


def _reach(target):
    target = torch.tensor(target)
    return lambda s, a, s2: -(s2[..., :2] - target.to(s2)).norm(dim=-1)


def _final_distance(target):
    return lambda traj: {"final_distance_m": float((traj["next", "observation"][-1, :2] - torch.tensor(target)).norm())}


point_tasks = {
    "reach-left": Task("reach-left", _reach([-0.5, 0.0]), 10, _final_distance([-0.5, 0.0]), "reach x = -0.5",
                       success_metric="final_distance_m"),
    "reach-up": Task("reach-up", _reach([0.0, 0.5]), 10, _final_distance([0.0, 0.5]), "reach y = 0.5",
                     success_metric="final_distance_m"),
}


def reach_origin():
    return Task("reach-origin", _reach([0.0, 0.0]), 10, description="back to the origin")


def short_swingup():
    """Pendulum-v1's swing-up over 60 steps instead of 200: an evaluation's task in a few seconds."""
    return dataclasses.replace(tasks_for("Pendulum-v1")["swingup"], name="swingup-60", horizon=60)


# Reacher-v5's observation: cos q (2), sin q (2), target (2), joint velocities (2), fingertip - target (2)
reacher_tasks = {"touch": Task("touch", lambda s, a, s2: -s2[..., 8:10].norm(dim=-1), 10, description="fingertip to target")}

not_a_task = 3


def not_an_env():
    return 42


def unbounded_action_env():
    """A TorchRL env the planner cannot sample actions for (no action bounds)."""
    from tensordict import TensorDict
    from torchrl.data import Composite, Unbounded
    from torchrl.envs import EnvBase

    class Unbounded2D(EnvBase):
        def __init__(self):
            super().__init__(batch_size=[])
            self.observation_spec = Composite(observation=Unbounded((2,)))
            self.action_spec = Unbounded((2,))
            self.reward_spec = Unbounded((1,))

        def _reset(self, td=None, **kw):
            return TensorDict({"observation": torch.zeros(2)}, [])

        def _step(self, td):
            return TensorDict({"observation": td["observation"] + td["action"], "reward": torch.zeros(1),
                               "done": torch.zeros(1, dtype=torch.bool), "terminated": torch.zeros(1, dtype=torch.bool)}, [])

        def _set_seed(self, seed):
            return seed

    return Unbounded2D()


def lying_spec_env():
    """A TorchRL env whose observations do not match its spec: check_env_specs refuses it."""
    from tensordict import TensorDict
    from torchrl.data import Bounded, Composite, Unbounded
    from torchrl.envs import EnvBase

    class Lying(EnvBase):
        def __init__(self):
            super().__init__(batch_size=[])
            self.observation_spec = Composite(observation=Unbounded((2,)))
            self.action_spec = Bounded(-1.0, 1.0, (2,))
            self.reward_spec = Unbounded((1,))

        def _reset(self, td=None, **kw):
            return TensorDict({"observation": torch.zeros(3)}, [])

        def _step(self, td):
            return TensorDict({"observation": torch.zeros(3), "reward": torch.zeros(1),
                               "done": torch.zeros(1, dtype=torch.bool), "terminated": torch.zeros(1, dtype=torch.bool)}, [])

        def _set_seed(self, seed):
            return seed

    return Lying()


def self_signalling_env():
    """The point mass, which sends its own process SIGTERM at the 5th step it takes inside the
    pipeline's fault guard (exploration's collection, not the spec check or the held-out set): a
    stop that arrives while the guarded env steps."""
    import os
    import signal
    import sys

    def guarded() -> bool:
        frame = sys._getframe()
        while frame is not None:
            if frame.f_code.co_filename.endswith(os.path.join("envs", "guard.py")):
                return True
            frame = frame.f_back
        return False

    class SelfSignalling(OutsidePoint):
        steps = 0

        def step(self, action):
            if guarded():
                SelfSignalling.steps += 1
                if SelfSignalling.steps == 5:
                    os.kill(os.getpid(), signal.SIGTERM)
            return super().step(action)

    from torchrl.envs import GymWrapper

    return GymWrapper(SelfSignalling())

