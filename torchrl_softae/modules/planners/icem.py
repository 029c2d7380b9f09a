"""improved Cross-Entropy Method (iCEM, Pinneri et al. 2020) as a TorchRL MPC planner.

Per MPC step, for every initial state in the batch (paper, "Trajectory and Policy Optimization"):

    mean <- shift(previous mean)           (warm start, reset on episode start)
    for i in 0..I-1:
        P_i = max(P * gamma^-i, 2K)         (population decay)
        A  = clip(mean + std * colored_noise(beta), action bounds)      (P_i, H, d_a)
        A += xi*K elites kept from the previous iteration (or the previous step, shifted)
        A += mean                            (last iteration only)
        J(A) = 1/particles sum_p sum_h r_h   (model rollouts; NaN -> -inf)
        elites = top-K(J);  mean, std <- alpha * (mean, std) + (1 - alpha) * stats(elites)
    return first action of the best sequence seen
"""
from __future__ import annotations

import math
import time

import torch
from tensordict import TensorDictBase
from tensordict.utils import NestedKey
from torchrl.envs import EnvBase

from torchrl_softae.modules.ensemble import ensemble_std
from torchrl_softae.modules.planners.colored_noise import colored_noise
from torchrl_softae.modules.planners.common import SequencePlannerBase, check_positive_int

__all__ = ["ICEMPlanner"]


class ICEMPlanner(SequencePlannerBase):
    """iCEM model-predictive controller over a (model) environment.

    Args:
        env (EnvBase): a batch-unlocked env to plan in, typically
            ``TransformedEnv(EnsembleModelEnv(...), Compose(HallucinatedControl(), UncertaintyReward()))``.
            Candidates are scored by the env's ``evaluate_action_sequences`` when it offers the
            :class:`~torchrl_softae.modules.planners.contract.ActionSequenceEvaluator` contract, by TorchRL's
            ``env.rollout`` otherwise.
        planning_horizon (int): H. Default 10.
        optim_steps (int): CEM iterations. Default 5.
        num_candidates (int): P, samples per iteration. Default 200.
        top_k (int): K, elite-set size. Default 20.
        num_particles (int): rollouts per candidate whose returns are averaged. Default 10.
            The model env asks for one when its propagation is deterministic.
        noise_beta (float): colored-noise exponent [beta]. Default 0.25.
        elite_fraction (float): xi, share of elites carried to the next iteration/step. Default 0.3.
        alpha (float): momentum of the mean/std update. Default 0.1.
        init_std (float): initial std as a fraction of the action half-range. Default 0.5.
        population_decay (float): gamma >= 1; iteration i uses ``P * gamma^-i`` samples. Default 1.
        shift_warm_start (bool): warm-start from the previous step's shifted mean and elites.
        precision (str): ``"fp32"``, ``"bf16"`` or ``"auto"`` (bf16 where the device has native
            bf16) for the ensemble's hidden layers while planning. Default ``"fp32"``.
        time_budget (float, optional): anytime mode: seconds per action; iterations stop when the
            next would overrun and the best sequence so far is returned (at least one iteration).
        deduplicate_particles (bool): evaluate one particle when propagation is deterministic.
        reward_key, action_key: TorchRL keys.
        seed (int): seed of the planner's own generator.

    Input: a tensordict with ``observation`` of shape ``(*B, d_s)``; output ``action`` ``(*B, d)``
    (``d`` is the planning env's action size). ``last_info`` holds the iterations run, the elapsed
    time and the best predicted return of the last call. Every tensor is created on the env's device.

    Examples:
        >>> model = EnsembleWorldModel(3, 1, num_cells=32, depth=2)
        >>> env = TransformedEnv(EnsembleModelEnv(model, mode="mean"), UncertaintyReward())
        >>> planner = ICEMPlanner(env, planning_horizon=5, num_candidates=20, top_k=4)
        >>> planner(TensorDict({"observation": torch.zeros(3)}, []))["action"].shape
        torch.Size([1])
    """

    _warm_start = ("_mean", "_elites")  # (B, H, d) shifted mean, (B, K, H, d) shifted elites

    def __init__(
        self,
        env: EnvBase,
        planning_horizon: int = 10,
        optim_steps: int = 5,
        num_candidates: int = 200,
        top_k: int = 20,
        num_particles: int = 10,
        noise_beta: float = 0.25,
        elite_fraction: float = 0.3,
        alpha: float = 0.1,
        init_std: float = 0.5,
        population_decay: float = 1.0,
        shift_warm_start: bool = True,
        precision: str = "fp32",
        time_budget: float | None = None,
        deduplicate_particles: bool = True,
        reward_key: NestedKey = ("next", "reward"),
        action_key: NestedKey = "action",
        observation_keys: list | None = None,
        seed: int = 0,
    ):
        check_positive_int("ICEMPlanner", "optim_steps", optim_steps)
        check_positive_int("ICEMPlanner", "num_candidates", num_candidates, 2)
        check_positive_int("ICEMPlanner", "top_k", top_k)
        if top_k > num_candidates:
            raise ValueError(f"ICEMPlanner: top_k={top_k} must not exceed num_candidates={num_candidates}")
        if not 0.0 <= elite_fraction <= 1.0:
            raise ValueError(f"ICEMPlanner: elite_fraction={elite_fraction!r}, expected in [0, 1]")
        if not 0.0 <= alpha < 1.0:
            raise ValueError(f"ICEMPlanner: alpha={alpha!r}, expected in [0, 1)")
        if not noise_beta >= 0:
            raise ValueError(f"ICEMPlanner: noise_beta={noise_beta!r}, expected >= 0")
        if not init_std > 0:
            raise ValueError(f"ICEMPlanner: init_std={init_std!r}, expected > 0")
        if not population_decay >= 1.0:
            raise ValueError(f"ICEMPlanner: population_decay={population_decay!r}, expected >= 1")
        if time_budget is not None and not time_budget > 0:
            raise ValueError(f"ICEMPlanner: time_budget={time_budget!r}, expected > 0 seconds or None")
        super().__init__(
            env, planning_horizon, num_particles=num_particles, precision=precision,
            deduplicate_particles=deduplicate_particles, action_key=action_key, reward_key=reward_key,
            observation_keys=observation_keys, seed=seed,
        )
        self.optim_steps = optim_steps
        self.num_candidates = num_candidates
        self.top_k = top_k
        self.noise_beta = float(noise_beta)
        self.elite_fraction = float(elite_fraction)
        self.alpha = float(alpha)
        self.init_std = float(init_std)
        self.population_decay = float(population_decay)
        self.shift_warm_start = shift_warm_start
        self.time_budget = time_budget
        self._mean: torch.Tensor | None = None
        self._elites: torch.Tensor | None = None
        self.last_info: dict = {}

    # ------------------------------------------------------------------ optimization
    @torch.no_grad()
    def planning(self, tensordict: TensorDictBase) -> torch.Tensor:
        obs_td = self.validate_input(tensordict)
        t0 = time.perf_counter()
        batch = tensordict.batch_size
        B = obs_td.shape[0]
        H, d = self.planning_horizon, self._low.shape[-1]
        mid, half = self.centre_and_halfrange()

        mean = mid.expand(B, H, d).clone()
        prev_elites = None
        if self.shift_warm_start and self._mean is not None and self._mean.shape == mean.shape:
            mean = self._mean.clone()
            prev_elites = self._elites
            is_init = tensordict.get("is_init", None)
            if is_init is not None:  # restart the warm start of the episodes that just began
                fresh = is_init.reshape(B, -1).any(-1).to(self.env_device)
                if bool(fresh.any()):
                    mean[fresh] = mid
                    prev_elites = None
        std = (self.init_std * half).expand(B, H, d).clone()
        n_keep = int(math.ceil(self.elite_fraction * self.top_k))

        best_ret = torch.full((B,), -math.inf, device=self.env_device)
        best_seq = mean.clone()
        elites = None
        iters_done, iter_times = 0, []
        for i in range(self.optim_steps):
            if self.time_budget is not None and i > 0:
                spent = time.perf_counter() - t0
                if spent + max(iter_times) > self.time_budget:
                    break
            ti = time.perf_counter()
            n = max(int(self.num_candidates * self.population_decay ** (-i)), 2 * self.top_k)
            noise = colored_noise(self.noise_beta, (B, n, d, H), generator=self._generator).transpose(-1, -2)
            extra = []
            if n_keep:
                if i == 0 and prev_elites is not None:
                    extra.append(prev_elites[:, :n_keep])
                elif elites is not None:
                    extra.append(elites[:, :n_keep])
            if i == self.optim_steps - 1:
                extra.append(mean.unsqueeze(1))
            samples = self.sample_candidates(mean.unsqueeze(1), std.unsqueeze(1), noise, tuple(extra))
            returns = self.evaluate(obs_td, samples)  # (B, n')
            top_ret, top_idx = returns.topk(self.top_k, dim=1)  # sorted, best first
            elites = samples.gather(1, top_idx[..., None, None].expand(B, self.top_k, H, d))
            better = top_ret[:, 0] > best_ret
            best_ret = torch.where(better, top_ret[:, 0], best_ret)
            best_seq = torch.where(better[:, None, None], elites[:, 0], best_seq)
            e_mean = elites.mean(1)
            e_std = ensemble_std(elites.transpose(0, 1), e_mean)
            mean = self.alpha * mean + (1 - self.alpha) * e_mean
            std = self.alpha * std + (1 - self.alpha) * e_std
            iters_done += 1
            iter_times.append(time.perf_counter() - ti)

        if self.shift_warm_start:
            # Shift by one step; the new last step restarts from the centre of the action box.
            self._mean = torch.cat([mean[:, 1:], mid.expand(B, 1, d)], 1)
            self._elites = torch.cat([elites[:, :, 1:], mid.expand(B, self.top_k, 1, d)], 2)
        self.last_info = {
            "iterations": iters_done,
            "elapsed": time.perf_counter() - t0,
            "best_return": best_ret.reshape(batch),
        }
        return best_seq[:, 0].reshape(*batch, d)
