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

import contextlib
import math
import time

import torch
from tensordict import TensorDictBase
from tensordict.utils import NestedKey
from torchrl.data import Bounded
from torchrl.envs import EnvBase, TransformedEnv
from torchrl.modules.planners.common import MPCPlannerBase

from torchrl_softae.modules.ensemble import EnsembleWorldModel, ensemble_std
from torchrl_softae.modules.planners.colored_noise import colored_noise
from torchrl_softae.modules.precision import resolve_planning_dtype

__all__ = ["ICEMPlanner"]


def _positive_int(name, value, low=1):
    if not isinstance(value, int) or isinstance(value, bool) or value < low:
        raise ValueError(f"ICEMPlanner: {name}={value!r}, expected an int >= {low}")


class ICEMPlanner(MPCPlannerBase):
    """iCEM model-predictive controller over a (model) environment.

    Args:
        env (EnvBase): a batch-unlocked env to plan in, typically
            ``TransformedEnv(EnsembleModelEnv(...), Compose(HallucinatedControl(), UncertaintyReward()))``.
        planning_horizon (int): H. Default 10.
        optim_steps (int): CEM iterations. Default 5.
        num_candidates (int): P, samples per iteration. Default 200.
        top_k (int): K, elite-set size. Default 20.
        num_particles (int): rollouts per candidate whose returns are averaged. Default 10.
            Ignored (one particle) when the env's propagation is deterministic.
        noise_beta (float): colored-noise exponent [beta]. Default 0.25.
        elite_fraction (float): xi, share of elites carried to the next iteration/step. Default 0.3.
        alpha (float): momentum of the mean/std update. Default 0.1.
        init_std (float): initial std as a fraction of the action half-range. Default 0.5.
        population_decay (float): gamma >= 1; iteration i uses ``P * gamma^-i`` samples. Default 1.
        shift_warm_start (bool): warm-start from the previous step's shifted mean and elites.
        precision (str): ``"fp32"``, ``"bf16"`` or ``"auto"`` (bf16 where the CPU has native bf16)
            for the ensemble's hidden layers while planning. Default ``"fp32"``.
        time_budget (float, optional): anytime mode: seconds per action; iterations stop when the
            next would overrun and the best sequence so far is returned (at least one iteration).
        deduplicate_particles (bool): evaluate one particle when propagation is deterministic.
        reward_key, action_key: TorchRL keys.
        seed (int): seed of the planner's own generator.

    Input: a tensordict with ``observation`` of shape ``(*B, d_s)``; output ``action`` ``(*B, d)``
    (``d`` is the planning env's action size). ``last_info`` holds the iterations run, the elapsed
    time and the best predicted return of the last call.
    """

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
        _positive_int("planning_horizon", planning_horizon)
        _positive_int("optim_steps", optim_steps)
        _positive_int("num_candidates", num_candidates, 2)
        _positive_int("top_k", top_k)
        _positive_int("num_particles", num_particles)
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
        super().__init__(env=env, action_key=action_key)
        base = env.base_env if isinstance(env, TransformedEnv) else env
        self.observation_keys = list(observation_keys) if observation_keys is not None else [
            k for k in base.observation_spec.keys(True, True) if k != "epistemic_std"
        ]
        self.in_keys = list(self.observation_keys)
        self.planning_horizon = planning_horizon
        self.optim_steps = optim_steps
        self.num_candidates = num_candidates
        self.top_k = top_k
        self.num_particles = num_particles
        self.noise_beta = float(noise_beta)
        self.elite_fraction = float(elite_fraction)
        self.alpha = float(alpha)
        self.init_std = float(init_std)
        self.population_decay = float(population_decay)
        self.shift_warm_start = shift_warm_start
        self.planning_dtype = resolve_planning_dtype(precision)
        self.precision = precision
        self.time_budget = time_budget
        self.deduplicate_particles = deduplicate_particles
        self.reward_key = reward_key
        self._base_env = base
        self._world_model = getattr(base, "world_model", None)
        self._generator = torch.Generator().manual_seed(seed)
        spec = self.action_spec
        if isinstance(spec, Bounded):
            self.register_buffer("_low", spec.space.low.detach().clone().float())
            self.register_buffer("_high", spec.space.high.detach().clone().float())
        else:  # unbounded: a unit-scale Gaussian around zero, no clipping
            d = spec.shape[-1]
            self.register_buffer("_low", torch.full((d,), -math.inf))
            self.register_buffer("_high", torch.full((d,), math.inf))
        self._mean: torch.Tensor | None = None
        self._elites: torch.Tensor | None = None
        self.last_info: dict = {}

    # ------------------------------------------------------------------ state
    def set_seed(self, seed: int) -> int:
        self._generator.manual_seed(seed)
        return seed

    def reset(self) -> None:
        """Forget the warm start (call at every episode start)."""
        self._mean = None
        self._elites = None

    def state_dict_extra(self) -> dict:
        """Warm-start state and RNG, for checkpoints that must resume bit-for-bit."""
        return {"mean": self._mean, "elites": self._elites, "rng": self._generator.get_state()}

    def load_state_dict_extra(self, state: dict) -> None:
        self._mean, self._elites = state["mean"], state["elites"]
        self._generator.set_state(state["rng"])

    @property
    def effective_particles(self) -> int:
        deterministic = bool(getattr(self._base_env, "deterministic", False))
        return 1 if (deterministic and self.deduplicate_particles) else self.num_particles

    def _centre_and_halfrange(self):
        finite = torch.isfinite(self._low) & torch.isfinite(self._high)
        mid = torch.where(finite, (self._low + self._high) / 2, torch.zeros_like(self._low))
        half = torch.where(finite, (self._high - self._low) / 2, torch.ones_like(self._low))
        return mid, half

    # ------------------------------------------------------------------ evaluation
    @contextlib.contextmanager
    def _planning_ctx(self):
        """Reduced precision in the ensemble while planning; the model env may skip re-validating
        actions, since every sample is clipped to the action spec here."""
        model, env = self._world_model, self._base_env
        prev_dtype = getattr(model, "planning_dtype", None)
        prev_check = getattr(env, "check_actions", None)
        if self.planning_dtype is not None and isinstance(model, EnsembleWorldModel):
            model.planning_dtype = self.planning_dtype
        if prev_check is not None and bool(torch.isfinite(self._low).all() and torch.isfinite(self._high).all()):
            env.check_actions = False
        try:
            yield
        finally:
            if isinstance(model, EnsembleWorldModel):
                model.planning_dtype = prev_dtype
            if prev_check is not None:
                env.check_actions = prev_check

    @torch.no_grad()
    def evaluate(self, observation_td: TensorDictBase, actions: torch.Tensor) -> torch.Tensor:
        """Predicted returns of action sequences.

        Args:
            observation_td: ``(B,)`` tensordict of initial states.
            actions: ``(B, N, H, d)`` candidate sequences.

        Returns:
            ``(B, N)`` returns averaged over particles; non-finite returns are ``-inf``.
        """
        B, N, H, _ = actions.shape
        P = self.effective_particles
        td = observation_td.reshape(B, 1, 1).expand(B, N, P).clone()
        member_key = getattr(self._base_env, "member_key", None)
        if P > 1 and member_key is not None and self._world_model is not None:
            # Trajectory sampling (TS-inf): each particle keeps one member for the whole horizon,
            # members spread evenly over a candidate's particles from a random offset.
            L = self._world_model.ensemble_size
            offset = torch.randint(L, (B, N, 1), generator=self._generator)
            td.set(member_key, (torch.arange(P) + offset) % L)
        acts = actions.unsqueeze(2).expand(B, N, P, H, actions.shape[-1])
        ret = torch.zeros(B, N, P, 1)
        alive = None
        env = self.env
        for h in range(H):
            td.set(self.action_key, acts[..., h, :])
            td = env.step(td)
            nxt = td.get("next")
            r = nxt.get(self.reward_key[1:] if isinstance(self.reward_key, tuple) else self.reward_key)
            r = r.reshape(B, N, P, -1)[..., :1].float()
            if alive is not None:
                r = r * alive
            ret = ret + r
            done = nxt.get("done", None)
            if done is not None and bool(done.any()):
                alive = (alive if alive is not None else 1.0) * (~done.reshape(B, N, P, 1)).float()
            # Carry the next state and any per-particle state (member index) to the next step.
            carried = nxt.exclude("reward", "done", "terminated", "truncated")
            if member_key is not None and member_key in td.keys():
                carried.set(member_key, td.get(member_key))
            td = carried
        ret = ret.squeeze(-1).mean(-1)
        return torch.where(torch.isfinite(ret), ret, torch.full_like(ret, -math.inf))

    # ------------------------------------------------------------------ optimization
    def _validate(self, tensordict: TensorDictBase) -> None:
        for key in self.observation_keys:
            x = tensordict.get(key, None)
            if x is None:
                raise KeyError(f"ICEMPlanner: the input tensordict has no {key!r} entry")
            expected = self._base_env.observation_spec[key].shape[-1:]
            if x.shape[-1:] != expected:
                raise ValueError(f"ICEMPlanner: {key!r} has shape {tuple(x.shape)}, expected (..., {expected[0]})")
            if not torch.isfinite(x).all():
                raise ValueError(f"ICEMPlanner: {key!r} contains NaN/inf; cannot plan from a non-finite state")

    @torch.no_grad()
    def planning(self, tensordict: TensorDictBase) -> torch.Tensor:
        self._validate(tensordict)
        t0 = time.perf_counter()
        batch = tensordict.batch_size
        obs_td = tensordict.select(*self.observation_keys).reshape(-1)
        B = obs_td.shape[0]
        H, d = self.planning_horizon, self._low.shape[-1]
        low, high = self._low, self._high
        mid, half = self._centre_and_halfrange()

        mean = mid.expand(B, H, d).clone()
        prev_elites = None
        if self.shift_warm_start and self._mean is not None and self._mean.shape == mean.shape:
            mean = self._mean.clone()
            prev_elites = self._elites
            is_init = tensordict.get("is_init", None)
            if is_init is not None:  # restart the warm start of the episodes that just began
                fresh = is_init.reshape(B, -1).any(-1)
                if bool(fresh.any()):
                    mean[fresh] = mid
                    prev_elites = None
        std = (self.init_std * half).expand(B, H, d).clone()
        n_keep = int(math.ceil(self.elite_fraction * self.top_k))

        best_ret = torch.full((B,), -math.inf)
        best_seq = mean.clone()
        elites = None
        iters_done, iter_times = 0, []
        with self._planning_ctx():
            for i in range(self.optim_steps):
                if self.time_budget is not None and i > 0:
                    spent = time.perf_counter() - t0
                    if spent + max(iter_times) > self.time_budget:
                        break
                ti = time.perf_counter()
                n = max(int(self.num_candidates * self.population_decay ** (-i)), 2 * self.top_k)
                noise = colored_noise(self.noise_beta, (B, n, d, H), generator=self._generator).transpose(-1, -2)
                samples = mean.unsqueeze(1) + std.unsqueeze(1) * noise
                extra = []
                if n_keep:
                    if i == 0 and prev_elites is not None:
                        extra.append(prev_elites[:, :n_keep])
                    elif elites is not None:
                        extra.append(elites[:, :n_keep])
                if i == self.optim_steps - 1:
                    extra.append(mean.unsqueeze(1))
                if extra:
                    samples = torch.cat([samples, *extra], 1)
                samples = torch.maximum(torch.minimum(samples, high), low)
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
