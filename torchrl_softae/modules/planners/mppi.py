"""Model-predictive path integral control (MPPI; Williams et al. 2017) over sampled sequences.

A second planner on the same scoring path as :class:`~torchrl_softae.modules.planners.ICEMPlanner`
(:meth:`SequencePlannerBase.evaluate`): where iCEM refits a Gaussian to the top-K elites, MPPI
averages *all* samples weighted by ``softmax(J / lambda)``::

    for i in 0..I-1:
        A = clip(mean + std * noise)              (N, H, d)
        w = softmax((J(A) - max J) / temperature)
        mean <- sum_n w_n A_n
    return mean[0]  (then shift the mean by one step for the next call)

Unlike TorchRL's ``MPPIPlanner`` it needs no value network: the return is the sum of the model
env's rewards over the horizon.
"""
from __future__ import annotations

import math

import torch
from tensordict import TensorDictBase
from tensordict.utils import NestedKey
from torchrl.envs import EnvBase

from torchrl_softae.modules.planners.colored_noise import colored_noise
from torchrl_softae.modules.planners.common import SequencePlannerBase, check_positive_int

__all__ = ["MPPIPlanner"]


class MPPIPlanner(SequencePlannerBase):
    """MPPI over a (model) environment.

    Args:
        env (EnvBase): a batch-unlocked env (an ``EnsembleModelEnv`` behind its transforms, or any
            TorchRL env).
        planning_horizon (int): H. Default 10.
        optim_steps (int): refinement iterations per action. Default 3.
        num_candidates (int): N, samples per iteration. Default 200.
        temperature (float): lambda of the exponential weights (in reward units). Default 1.
        noise_std (float): sampling std as a fraction of the action half-range. Default 0.5.
        noise_beta (float): colored-noise exponent (0 = white noise, as classic MPPI). Default 0.
        num_particles, precision, deduplicate_particles, seed, keys: as in
            :class:`~torchrl_softae.modules.planners.common.SequencePlannerBase`.

    Examples:
        >>> planner = MPPIPlanner(env, planning_horizon=5, num_candidates=64)
        >>> planner(TensorDict({"observation": torch.zeros(3)}, []))["action"]
    """

    _warm_start = ("_mean",)  # (B, H, d) shifted mean

    def __init__(
        self,
        env: EnvBase,
        planning_horizon: int = 10,
        optim_steps: int = 3,
        num_candidates: int = 200,
        temperature: float = 1.0,
        noise_std: float = 0.5,
        noise_beta: float = 0.0,
        num_particles: int = 10,
        precision: str = "fp32",
        deduplicate_particles: bool = True,
        reward_key: NestedKey = ("next", "reward"),
        action_key: NestedKey = "action",
        observation_keys: list | None = None,
        seed: int = 0,
    ):
        check_positive_int("MPPIPlanner", "optim_steps", optim_steps)
        check_positive_int("MPPIPlanner", "num_candidates", num_candidates)
        for name, value in (("temperature", temperature), ("noise_std", noise_std)):
            if not value > 0:
                raise ValueError(f"MPPIPlanner: {name}={value!r}, expected > 0")
        if not noise_beta >= 0:
            raise ValueError(f"MPPIPlanner: noise_beta={noise_beta!r}, expected >= 0")
        super().__init__(
            env, planning_horizon, num_particles=num_particles, precision=precision,
            deduplicate_particles=deduplicate_particles, action_key=action_key, reward_key=reward_key,
            observation_keys=observation_keys, seed=seed,
        )
        self.optim_steps = optim_steps
        self.num_candidates = num_candidates
        self.temperature = float(temperature)
        self.noise_std = float(noise_std)
        self.noise_beta = float(noise_beta)
        self._mean: torch.Tensor | None = None
        self.last_info: dict = {}

    @torch.no_grad()
    def planning(self, tensordict: TensorDictBase) -> torch.Tensor:
        obs_td = self.validate_input(tensordict)
        batch = tensordict.batch_size
        B, H, d = obs_td.shape[0], self.planning_horizon, self._low.shape[-1]
        mid, half = self.centre_and_halfrange()
        mean = mid.expand(B, H, d).clone()
        if self._mean is not None and self._mean.shape == mean.shape:
            mean = self._mean.clone()
        std = self.noise_std * half
        best_ret = torch.full((B,), -math.inf, device=self.env_device)
        for _ in range(self.optim_steps):
            noise = colored_noise(self.noise_beta, (B, self.num_candidates, d, H), generator=self._generator)
            samples = self.sample_candidates(mean.unsqueeze(1), std, noise.transpose(-1, -2))
            returns = self.evaluate(obs_td, samples)  # (B, N), -inf where non-finite
            best_ret = torch.maximum(best_ret, returns.max(1).values)
            weights = torch.softmax(returns / self.temperature, dim=1)  # softmax subtracts the max
            weights = torch.nan_to_num(weights, nan=1.0 / self.num_candidates)  # all -inf: plain mean
            mean = (weights[..., None, None] * samples).sum(1)
        self._mean = torch.cat([mean[:, 1:], mid.expand(B, 1, d)], 1)
        self.last_info = {"best_return": best_ret.reshape(batch)}
        return mean[:, 0].reshape(*batch, d)
