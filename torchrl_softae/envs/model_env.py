"""A batched TorchRL environment that propagates states through the learned ensemble."""
from __future__ import annotations

import contextlib
import math

import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.data import Bounded, Categorical, Composite, Unbounded
from torchrl.envs import Compose, EnvBase, ModelBasedEnvBase, TransformedEnv

from torchrl_softae.modules.engine import normal_kernel as _normal_kernel
from torchrl_softae.modules.planners.contract import ActionSequenceEvaluator, PlanningTransform
from torchrl_softae.modules.ensemble import EnsembleWorldModel, ensemble_moments
from torchrl_softae.modules.engine.precision import resolve_planning_dtype

__all__ = ["EnsembleModelEnv", "PROPAGATION_MODES"]


def _leaves_box(x: torch.Tensor, low: torch.Tensor, high: torch.Tensor, tol: float = 1e-6) -> bool:
    """Whether an entry of ``x`` ``(..., d)`` leaves ``[low, high]`` (``(d,)`` or scalars).

    Checked once per planner call on every candidate: one pass for the whole tensor against the
    tightest bounds first (enough for the usual uniform box, and far cheaper than comparing every
    entry with its own bound), per dimension only when that is inconclusive.
    """
    lo, hi = torch.aminmax(x)
    if bool(lo >= low.max() - tol) and bool(hi <= high.min() + tol):
        return False
    flat = x.reshape(-1, x.shape[-1])
    return bool(((flat.amin(0) < low - tol) | (flat.amax(0) > high + tol)).any())

#: propagation modes of :class:`EnsembleModelEnv` (the one list; the CLI and configs read it)
PROPAGATION_MODES = ("mean", "sample", "optimistic")


class EnsembleModelEnv(ModelBasedEnvBase, ActionSequenceEvaluator):
    """Imagined rollouts through an :class:`EnsembleWorldModel`.

    Propagation modes (paper, "Active Exploration of State-Space Models"):

    * ``"mean"`` (Mean-AE): ``s' = mu(s, a)``.
    * ``"sample"`` (PETS-AE, trajectory sampling): ``s' = NN_l(s, a) + aleatoric noise`` where each
      particle follows the member ``l = td["member_index"]`` for its whole trajectory (TS-inf); a
      missing ``member_index`` draws a member per step (TS-1).
    * ``"optimistic"`` (SoftAE / H-UCRL): ``s' = mu(s, a) + sigma(s, a) * eta`` with the
      hallucinated control ``eta`` in ``[-beta, beta]^{d_s}`` read from the ``"eta"`` action entry;
      :class:`~torchrl_softae.envs.transforms.HallucinatedControl` maps a planner's ``[-1, 1]``
      action onto it.

    Every step writes the epistemic std [sigma] at ``("next", "epistemic_std")``. The model has no
    reward of its own: ``reward`` is zero until a transform (``UncertaintyReward`` or a task reward)
    sets it. The env never terminates.

    Planners score candidates through :meth:`evaluate_action_sequences` (the
    :class:`~torchrl_softae.modules.planners.contract.ActionSequenceEvaluator` contract).

    Args:
        world_model (EnsembleWorldModel): the trained ensemble.
        action_spec (Bounded, optional): the real env's action spec; default ``[-1, 1]^{d_a}``.
        mode (str): one of :data:`PROPAGATION_MODES`.
        aleatoric_noise (bool, optional): add the aleatoric noise [w_t]; default ``True`` for
            ``"sample"`` and ``False`` otherwise (deterministic propagation lets planners skip
            identical particles).
        initial_states (Tensor, optional): ``(N, d_s)`` states that :meth:`reset` draws from.
        device: where the env and the model live; default the model's device (the model is
            moved there, as TorchRL's ``ModelBasedEnvBase`` does).

    Examples:
        >>> env = EnsembleModelEnv(EnsembleWorldModel(3, 1), mode="mean")
        >>> td = env.reset(TensorDict({"observation": torch.zeros(4, 3)}, [4]))
        >>> env.step(td.set("action", torch.zeros(4, 1)))["next", "epistemic_std"].shape
        torch.Size([4, 3])
    """

    member_key = "member_index"

    #: score deterministic one-particle plans (Mean-AE, SoftAE) through the model's

    def __init__(
        self,
        world_model: EnsembleWorldModel,
        action_spec: Bounded | None = None,
        mode: str = "mean",
        aleatoric_noise: bool | None = None,
        initial_states: torch.Tensor | None = None,
        device=None,
        batch_size=None,
    ):
        if not isinstance(world_model, EnsembleWorldModel):
            raise TypeError(f"world_model must be an EnsembleWorldModel, got {type(world_model).__name__}")
        if mode not in PROPAGATION_MODES:
            raise ValueError(f"mode={mode!r}, expected one of {PROPAGATION_MODES}")
        if device is None:
            device = world_model.input_normalizer.loc.device
        super().__init__(world_model, device=device, batch_size=batch_size)
        d_s, d_a = world_model.observation_dim, world_model.action_dim
        self.mode = mode
        self.aleatoric_noise = (mode == "sample") if aleatoric_noise is None else bool(aleatoric_noise)
        if aleatoric_noise and not world_model.probabilistic:
            raise ValueError("aleatoric_noise=True needs a probabilistic EnsembleWorldModel")
        if action_spec is None:
            action_spec = Bounded(-1.0, 1.0, (d_a,))
        if action_spec.shape[-1:] != (d_a,):
            raise ValueError(f"action_spec has shape {tuple(action_spec.shape)}, expected ({d_a},) to match the world model")
        dev = self.device
        self.observation_spec = Composite(
            observation=Unbounded((d_s,), device=dev), epistemic_std=Unbounded((d_s,), device=dev),
            shape=self.batch_size, device=dev,
        )
        actions = {"action": action_spec.clone().to(dev)}
        if mode == "optimistic":
            actions["eta"] = Unbounded((d_s,), device=dev)
        self.full_action_spec = Composite(actions, shape=self.batch_size, device=dev)
        if mode == "sample":
            self.state_spec = Composite(
                {self.member_key: Categorical(world_model.ensemble_size, (), dtype=torch.int64, device=dev)},
                shape=self.batch_size, device=dev,
            )
        self.reward_spec = Unbounded((1,), device=dev)
        self._generator = torch.Generator(device=dev).manual_seed(0)
        self.initial_states = (None if initial_states is None
                               else initial_states.detach().reshape(-1, d_s).to(dev).clone())
        self._check_actions = True
        self._plan_dtype: torch.dtype | None = None  # the hidden layers' dtype while a plan is scored
        self._propagate = {"mean": self._propagate_mean, "sample": self._propagate_sample,
                           "optimistic": self._propagate_optimistic}[mode]

    @property
    def deterministic(self) -> bool:
        """``True`` when identical (state, action) particles always give identical next states."""
        return self.mode != "sample" and not self.aleatoric_noise

    def _set_seed(self, seed: int | None) -> None:
        self._generator.manual_seed(int(seed) if seed is not None else 0)

    def generator_state(self) -> torch.Tensor:
        # trajectory sampling draws its aleatoric noise from this env's generator
        return self._generator.get_state()

    def set_generator_state(self, state: torch.Tensor) -> None:
        self._generator.set_state(state)

    def _randn(self, shape, like: torch.Tensor, generator: torch.Generator | None = None) -> torch.Tensor:
        return torch.randn(shape, generator=generator or self._generator, dtype=like.dtype, device=like.device)

    def _reset(self, tensordict: TensorDictBase | None = None, **kwargs) -> TensorDictBase:
        d_s = self.world_model.observation_dim
        shape = self.batch_size
        if tensordict is not None and "observation" in tensordict.keys():
            obs = tensordict.get("observation")
            shape = obs.shape[:-1]
        elif self.initial_states is not None:
            idx = torch.randint(self.initial_states.shape[0], shape, generator=self._generator, device=self.device)
            obs = self.initial_states[idx]
        else:  # states distributed like the data the model was fit on
            norm = self.world_model.input_normalizer
            obs = norm.loc[:d_s] + norm.scale[:d_s] * self._randn((*shape, d_s), norm.loc)
        out = TensorDict(
            {"observation": obs, "epistemic_std": torch.zeros_like(obs)}, batch_size=shape, device=self.device
        )
        if self.mode == "sample":
            out.set(self.member_key, torch.randint(self.world_model.ensemble_size, shape, generator=self._generator,
                                                   device=self.device))
        return out

    # ------------------------------------------------------------------ propagation
    def propagate(
        self,
        observation: torch.Tensor,
        action: torch.Tensor,
        eta: torch.Tensor | None = None,
        member_index: torch.Tensor | None = None,
        particles: int = 1,
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """One model step on plain tensors: returns ``(s', sigma)``, both ``(*B, d_s)``.

        ``particles`` > 1: ``observation``, ``action`` (and ``eta``) are ``(*B, 1, d)``, shared by
        that many particles (``member_index`` ``(*B, particles)``), and the outputs are ``(*B,
        particles, d_s)``: the ensemble runs once for them all; what differs between the particles
        (their member, their noise) is applied after. The same values as ``particles`` copies of
        the inputs, at ``1 / particles`` of the network's cost."""
        return self._propagate(observation, self.world_model.normalized_actions(action), eta, member_index, particles)

    def _moments(self, observation, model_action, member_index=None, particles=1):
        """``(mu, sigma, member_mean, aleatoric_std)``, each ``(*B, d_s)`` (see
        :meth:`EnsembleWorldModel.predict_moments`) at the normalized actions ``model_action``
        (:meth:`EnsembleWorldModel.normalized_actions`); with ``particles`` > 1 the inputs are
        shared by that many particles and the outputs ``(*B, particles, d_s)``."""
        model = self.world_model
        if particles == 1:
            return model.predict_moments(observation, model_action, self.aleatoric_noise, member_index,
                                         action_normalized=True, dtype=self._plan_dtype)
        # shared rows: every member's mean, then each particle's member picked from them
        members, ale = model.predict_members(observation, model_action, with_aleatoric=self.aleatoric_noise,
                                             action_normalized=True, dtype=self._plan_dtype)
        mu, sigma = ensemble_moments(members)
        shape = (*mu.shape[:-2], particles, mu.shape[-1])
        mu, sigma = mu.expand(shape), sigma.expand(shape)
        member_mean = None
        if member_index is not None:
            idx = member_index.reshape(1, *shape[:-1], 1).expand(1, *shape)
            member_mean = members.expand(members.shape[0], *shape).gather(0, idx).squeeze(0)
            if ale is not None:
                ale = ale.expand(members.shape[0], *shape).gather(0, idx).squeeze(0)
        elif ale is not None:
            ale = ale.square().mean(0).sqrt().expand(shape)
        return mu, sigma, member_mean, ale

    def _with_noise(self, nxt, noise_std):
        if noise_std is None:
            return nxt
        # the counter-based draws where they apply (the model's kernels), else torch.randn's
        engine = self.world_model.engine
        return _normal_kernel.add_scaled_randn(nxt, noise_std, self._generator,
                                               kernel=engine.uses_kernels and engine.kernel_noise)

    def _propagate_mean(self, observation, action, eta, member_index, particles=1):
        mu, sigma, _, ale = self._moments(observation, action, particles=particles)
        return self._with_noise(mu, ale), sigma

    @staticmethod
    def _check_eta(eta, expected_shape) -> None:
        if eta is None:
            raise KeyError("mode='optimistic' needs the hallucinated control 'eta' in the tensordict")
        if eta.shape != expected_shape:  # eta perturbs the state it comes with
            raise ValueError(f"'eta' has shape {tuple(eta.shape)}, expected {tuple(expected_shape)}")

    def _propagate_optimistic(self, observation, action, eta, member_index, particles=1):
        self._check_eta(eta, observation.shape)
        mu, sigma, _, ale = self._moments(observation, action, particles=particles)
        return self._with_noise(self.world_model.optimistic_step(mu, sigma, eta), ale), sigma

    def _propagate_sample(self, observation, action, eta, member_index, particles=1):
        if member_index is None:
            shape = observation.shape[:-1] if particles == 1 else (*observation.shape[:-2], particles)
            member_index = torch.randint(self.world_model.ensemble_size, shape,
                                         generator=self._generator, device=observation.device)
        # trajectory sampling: the particle's own member, with that member's aleatoric noise
        _, sigma, member_mean, ale = self._moments(observation, action, member_index, particles)
        return self._with_noise(member_mean, ale), sigma

    # ------------------------------------------------------------------ stepping
    def _check_action(self, action: torch.Tensor) -> None:
        d_a = self.world_model.action_dim
        if action.shape[-1:] != (d_a,):
            raise ValueError(f"EnsembleModelEnv: 'action' has shape {tuple(action.shape)}, expected (..., {d_a})")
        spec = self.full_action_spec["action"]
        if isinstance(spec, Bounded):
            low, high = spec.space.low, spec.space.high
            bad = (action < low - 1e-6) | (action > high + 1e-6)
            if bool(bad.any()):
                i = bad.nonzero()[0].tolist()
                raise ValueError(
                    f"EnsembleModelEnv: action value {float(action[tuple(i)]):.4g} at index {i} is outside the "
                    f"action spec [{float(low[i[-1]]):.4g}, {float(high[i[-1]]):.4g}]"
                )

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        obs = tensordict.get("observation")
        action = tensordict.get("action")
        if self._check_actions:
            self.world_model.check_dtype("observation", obs)
            self._check_action(action)
        member = tensordict.get(self.member_key, None) if self.mode == "sample" else None
        nxt, sigma = self.propagate(obs, action, tensordict.get("eta", None), member)
        batch = tensordict.batch_size
        flag = torch.zeros(*batch, 1, dtype=torch.bool, device=nxt.device)
        out = TensorDict(
            {"observation": nxt, "epistemic_std": sigma,
             "reward": torch.zeros(*batch, 1, dtype=nxt.dtype, device=nxt.device), "done": flag, "terminated": flag},
            batch_size=batch, device=self.device,
        )
        if member is not None:
            out.set(self.member_key, member)
        return out

    # ------------------------------------------------------------------ the planner contract
    @property
    def state_keys(self) -> list:
        return ["observation"]

    def particles_needed(self, requested: int) -> int:
        return 1 if self.deterministic else requested

    @contextlib.contextmanager
    def _planning(self, precision: str):
        """The model's hidden layers in ``precision`` for this env's model calls (an argument of
        each call, not state on the shared model); per-step action checks off (the sequences were
        checked once, as a whole)."""
        engine = self.world_model.engine
        prev_dtype, prev_check = self._plan_dtype, self._check_actions
        # "auto": bf16 only where it measures faster for this ensemble on this machine
        self._plan_dtype = engine.auto_planning_dtype() if precision == "auto" else resolve_planning_dtype(precision)
        self._check_actions = False
        try:
            yield
        finally:
            self._plan_dtype, self._check_actions = prev_dtype, prev_check

    @torch.no_grad()
    def evaluate_action_sequences(
        self,
        initial_state: TensorDictBase,
        action_sequences: torch.Tensor,
        *,
        num_particles: int,
        env: EnvBase | None = None,
        precision: str = "fp32",
        generator: torch.Generator | None = None,
    ) -> torch.Tensor:
        """Returns of ``(B, N, H, d)`` action sequences from ``(B,)`` initial states, ``(B, N)``.

        ``env`` is this env or a ``TransformedEnv`` over it (its transforms split the action,
        e.g. :class:`~torchrl_softae.envs.transforms.HallucinatedControl`, and set the reward,
        e.g. :class:`~torchrl_softae.envs.transforms.UncertaintyReward`). With ``num_particles``
        > 1 in ``"sample"`` mode every particle keeps one member for the whole horizon (TS-inf),
        members spread evenly over a candidate's particles from a random offset. Plans the engine
        has a rollout for (deterministic with one particle: Mean-AE, SoftAE, H-UCRL; trajectory
        sampling with particles: PETS-AE) are scored by it on plain tensors (at the first step a
        candidate's particles share its state and action, so the ensemble runs once for them);
        every other plan by stepping ``env`` (TorchRL's ``step``).
        """
        env = self if env is None else env
        B, N, H, d = action_sequences.shape
        P = num_particles
        spec = env.full_action_spec[env.action_key]
        if isinstance(spec, Bounded):
            low, high = spec.space.low, spec.space.high
            if _leaves_box(action_sequences, low, high):
                raise ValueError(f"EnsembleModelEnv.evaluate_action_sequences: action sequences leave the action "
                                 f"spec [{float(low.min()):.4g}, {float(high.max()):.4g}]")
        self.world_model.check_dtype("observation", initial_state.get("observation"))  # e.g. a float64 real env
        obs = initial_state.get("observation").reshape(B, 1, 1, -1).expand(B, N, P, -1)
        member = None
        if self.mode == "sample" and P > 1:
            L = self.world_model.ensemble_size
            offset = torch.randint(L, (B, N, 1), generator=generator, device=action_sequences.device)
            member = (torch.arange(P, device=action_sequences.device) + offset) % L
        stack = self._tensor_stack(env)
        kind = self._rollout_kind(P, member) if stack is not None else None
        with self._planning(precision):
            if kind is not None:
                ret = self._returns_by_rollout(kind, stack, obs, action_sequences, member)
            else:
                acts = action_sequences.unsqueeze(2).expand(B, N, P, H, d)
                ret = self._returns_through_step(env, obs, acts, member)
        ret = ret.squeeze(-1).mean(-1)
        return torch.where(torch.isfinite(ret), ret, torch.full_like(ret, -math.inf))

    def _tensor_stack(self, env: EnvBase) -> list | None:
        """The transforms between ``env`` and this env, if every one can act on plain tensors."""
        if env is self:
            return []
        if not (isinstance(env, TransformedEnv) and env.base_env is self):
            return None
        transforms = list(env.transform) if isinstance(env.transform, Compose) else [env.transform]
        return transforms if all(isinstance(t, PlanningTransform) for t in transforms) else None

    def _rollout_kind(self, particles: int, member) -> str | None:
        """The engine's rollout that scores this plan (``"deterministic"``: one particle, no noise;
        ``"sampled"``: trajectory sampling with particles), or ``None``: TorchRL's step path."""
        engine = self.world_model.engine
        if not engine.rollouts:
            return None
        if self.deterministic and particles == 1:
            return "deterministic"
        return "sampled" if self.mode == "sample" and member is not None else None

    def _returns_by_rollout(self, kind, stack, obs, action_sequences, member) -> torch.Tensor:
        """The returns of a plan scored by the engine's rollout ``kind`` on plain tensors (no
        TensorDict, no spec work per step): the same values as stepping the TorchRL stack
        (``test_rollouts_match_the_torchrl_stack``).

        Args:
            kind: :meth:`_rollout_kind`.
            stack: the transforms (:meth:`_tensor_stack`).
            obs: ``(B, N, P, d_s)`` the initial states of each candidate's ``P`` particles (the same
                state for all of them).
            action_sequences: ``(B, N, H, d)``, a candidate's actions, shared by its particles.
            member: ``(B, N, P)`` each particle's member (trajectory sampling) or ``None``.

        Returns:
            ``(B, N, P, 1)`` returns.
        """
        # The action transforms map each step's action alone: once for the whole horizon (not once
        # per step), laid out step by step so that a step's entries are contiguous, (B, N, 1, k);
        # so are the actions as the network takes them.
        entries = {"action": action_sequences}
        for t in reversed(stack):  # inverse transforms run outermost first, as in TorchRL
            entries = t.plan_action(entries)
        entries = {k: v.movedim(-2, 0).unsqueeze(-2).contiguous() for k, v in entries.items()}
        model_actions = self.world_model.normalized_actions(entries["action"])
        if kind == "deterministic":
            return self._deterministic_returns(stack, obs, entries, model_actions)
        return self._sampled_returns(stack, obs, entries, model_actions, member)

    def _deterministic_returns(self, stack, obs, entries, model_actions) -> torch.Tensor:
        """:meth:`_returns_by_rollout` with deterministic propagation and one particle per candidate
        (``obs`` ``(B, N, 1, d_s)``; ``entries`` and ``model_actions`` step-major, ``(H, B, N, 1,
        k)``): the model's steps laid out once (:meth:`torchrl_softae.modules.engine.InferenceEngine.deterministic_rollout`),
        on flat ``(B * N, k)`` rows; the rewards of all steps at once (:meth:`_rollout_returns`)."""
        B, N, _, d_s = obs.shape
        H = model_actions.shape[0]
        eta = None
        if self.mode == "optimistic":
            eta = entries.get("eta")
            self._check_eta(eta, (H, *obs.shape))
            eta = eta.reshape(H, B * N, d_s)
        rollout = self.world_model.engine.deterministic_rollout(
            obs.reshape(B * N, d_s), model_actions.reshape(H, B * N, -1), eta, dtype=self._plan_dtype)
        return self._rollout_returns(stack, rollout, entries["action"], (B, N, 1))

    def _sampled_returns(self, stack, obs, entries, model_actions, member) -> torch.Tensor:
        """:meth:`_returns_by_rollout` with trajectory sampling, each particle following its member
        (``obs`` ``(B, N, P, d_s)``, ``member`` ``(B, N, P)``; ``entries`` and ``model_actions``
        step-major, ``(H, B, N, 1, k)``): the model's steps laid out once
        (:meth:`torchrl_softae.modules.engine.InferenceEngine.sampled_rollout`, the network once for a candidate's particles
        at the first step), the noise drawn from this env's generator as stepping draws it; the
        rewards of all steps at once (:meth:`_rollout_returns`)."""
        B, N, P, d_s = obs.shape
        H = model_actions.shape[0]
        rollout = self.world_model.engine.sampled_rollout(
            obs[:, :, 0].reshape(B * N, d_s), model_actions.reshape(H, B * N, -1), member.reshape(B * N, P),
            self.aleatoric_noise, self._generator, dtype=self._plan_dtype)
        action = entries["action"]
        return self._rollout_returns(stack, rollout, action.expand(H, B, N, P, action.shape[-1]), (B, N, P))

    @staticmethod
    def _rollout_returns(stack, rollout, actions, batch: tuple[int, ...]) -> torch.Tensor:
        """The returns ``(*batch, 1)`` of a planning rollout's rows (``batch``: their shape) under
        the actions ``(H, *batch, k)``: every step run first, then each
        transform's reward for all steps in one call (its steps' arguments stacked, ``(H, *batch,
        ...)``; :meth:`~torchrl_softae.modules.planners.PlanningTransform.plan_reward`), summed over
        the horizon. One call instead of one per step between the network calls, where every op ran
        cache-cold (``benchmarks/studies/cold_ops.py``)."""
        trajectory, sigmas = rollout.run()
        H = sigmas.shape[0]
        trajectory = trajectory.view(H + 1, *batch, -1)
        sigmas = sigmas.view(H, *batch, -1)
        # the model env's own reward, zero: one read-only value for every step and row
        reward = torch.zeros((1,) * (len(batch) + 2), device=sigmas.device).expand(H, *batch, 1)
        for t in stack:
            reward = t.plan_reward(trajectory[:-1], actions, trajectory[1:], sigmas, reward)
        return reward.reshape(H, *batch, 1).sum(0, dtype=torch.float32)

    def _returns_through_step(self, env, obs, acts, member) -> torch.Tensor:
        """Any transform stack: TorchRL's ``env.step`` on a tensordict per horizon step."""
        B, N, P, H, _ = acts.shape
        td = TensorDict({"observation": obs}, [B, N, P], device=obs.device)
        if member is not None:
            td.set(self.member_key, member)
        ret = torch.zeros(B, N, P, 1, device=obs.device)
        for h in range(H):
            td.set(env.action_key, acts[..., h, :])
            nxt = env.step(td).get("next")
            ret += nxt.get("reward").reshape(B, N, P, -1)[..., :1].float()
            # carry the next state and the particle's member (TS-inf) to the next step
            carried = nxt.select(*self.state_keys)
            if member is not None:
                carried.set(self.member_key, member)
            td = carried
        return ret
