"""A batched TorchRL environment that propagates states through the learned ensemble."""
from __future__ import annotations

import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.data import Bounded, Categorical, Composite, Unbounded
from torchrl.envs import ModelBasedEnvBase

from torchrl_softae.modules.ensemble import EnsembleWorldModel, ensemble_std

__all__ = ["EnsembleModelEnv", "PROPAGATION_MODES"]

PROPAGATION_MODES = ("mean", "sample", "optimistic")


class EnsembleModelEnv(ModelBasedEnvBase):
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

    Args:
        world_model (EnsembleWorldModel): the trained ensemble.
        action_spec (Bounded, optional): the real env's action spec; default ``[-1, 1]^{d_a}``.
        mode (str): one of ``"mean"``, ``"sample"``, ``"optimistic"``.
        aleatoric_noise (bool, optional): add the aleatoric noise [w_t]; default ``True`` for
            ``"sample"`` and ``False`` otherwise (deterministic propagation lets planners skip
            identical particles).
        initial_states (Tensor, optional): ``(N, d_s)`` states that :meth:`reset` draws from.
    """

    member_key = "member_index"

    def __init__(
        self,
        world_model: EnsembleWorldModel,
        action_spec: Bounded | None = None,
        mode: str = "mean",
        aleatoric_noise: bool | None = None,
        initial_states: torch.Tensor | None = None,
        device="cpu",
        batch_size=None,
    ):
        if not isinstance(world_model, EnsembleWorldModel):
            raise TypeError(f"world_model must be an EnsembleWorldModel, got {type(world_model).__name__}")
        if mode not in PROPAGATION_MODES:
            raise ValueError(f"mode={mode!r}, expected one of {PROPAGATION_MODES}")
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
        self.observation_spec = Composite(
            observation=Unbounded((d_s,)), epistemic_std=Unbounded((d_s,)), shape=self.batch_size
        )
        actions = {"action": action_spec.clone()}
        if mode == "optimistic":
            actions["eta"] = Unbounded((d_s,))
        self.full_action_spec = Composite(actions, shape=self.batch_size)
        if mode == "sample":
            self.state_spec = Composite(
                {self.member_key: Categorical(world_model.ensemble_size, (), dtype=torch.int64)},
                shape=self.batch_size,
            )
        self.reward_spec = Unbounded((1,))
        self._generator = torch.Generator().manual_seed(0)
        self.initial_states = None if initial_states is None else initial_states.detach().reshape(-1, d_s).clone()

    @property
    def deterministic(self) -> bool:
        """``True`` when identical (state, action) particles always give identical next states."""
        return self.mode != "sample" and not self.aleatoric_noise

    def _set_seed(self, seed: int | None) -> None:
        self._generator.manual_seed(int(seed) if seed is not None else 0)

    def _randn(self, shape, like: torch.Tensor) -> torch.Tensor:
        return torch.randn(shape, generator=self._generator, dtype=like.dtype).to(like.device)

    def _reset(self, tensordict: TensorDictBase | None = None, **kwargs) -> TensorDictBase:
        d_s = self.world_model.observation_dim
        shape = self.batch_size
        if tensordict is not None and "observation" in tensordict.keys():
            obs = tensordict.get("observation")
            shape = obs.shape[:-1]
        elif self.initial_states is not None:
            idx = torch.randint(self.initial_states.shape[0], shape, generator=self._generator)
            obs = self.initial_states[idx]
        else:  # states distributed like the data the model was fit on
            norm = self.world_model.input_normalizer
            obs = norm.loc[:d_s] + norm.scale[:d_s] * self._randn((*shape, d_s), norm.loc)
        out = TensorDict(
            {"observation": obs, "epistemic_std": torch.zeros_like(obs)}, batch_size=shape, device=self.device
        )
        if self.mode == "sample":
            out.set(self.member_key, torch.randint(self.world_model.ensemble_size, shape, generator=self._generator))
        return out

    def propagate(
        self,
        observation: torch.Tensor,
        action: torch.Tensor,
        eta: torch.Tensor | None = None,
        member_index: torch.Tensor | None = None,
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """One model step on plain tensors: returns ``(s', sigma)``, both ``(*B, d_s)``."""
        model = self.world_model
        if self.mode == "sample" and member_index is None:
            member_index = torch.randint(model.ensemble_size, observation.shape[:-1], generator=self._generator)
        members, ale = model.predict_members(
            observation, action, with_aleatoric=self.aleatoric_noise,
            member_index=member_index if self.mode == "sample" else None,
        )
        mu = members.mean(0)
        sigma = ensemble_std(members, mu)
        if self.mode == "mean":
            nxt = mu
            noise_std = ale.square().mean(0).sqrt() if ale is not None else None
        elif self.mode == "optimistic":
            if eta is None:
                raise KeyError("mode='optimistic' needs the hallucinated control 'eta' in the tensordict")
            if eta.shape != mu.shape:
                raise ValueError(f"'eta' has shape {tuple(eta.shape)}, expected {tuple(mu.shape)}")
            nxt = torch.addcmul(mu, sigma, eta)
            noise_std = ale.square().mean(0).sqrt() if ale is not None else None
        else:  # trajectory sampling: ``ale`` is already the assigned member's
            idx = member_index.reshape(1, *mu.shape[:-1], 1).expand(1, *mu.shape)
            nxt = members.gather(0, idx).squeeze(0)
            noise_std = ale
        if noise_std is not None:
            nxt = nxt + noise_std * self._randn(nxt.shape, nxt)
        return nxt, sigma

    #: validate every action against the spec (a planner that clips its samples may switch it off)
    check_actions: bool = True

    def _check_action(self, action: torch.Tensor) -> None:
        if not self.check_actions:
            return
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
        self._check_action(action)
        member = tensordict.get(self.member_key, None) if self.mode == "sample" else None
        nxt, sigma = self.propagate(obs, action, tensordict.get("eta", None), member)
        batch = tensordict.batch_size
        out = TensorDict(
            {
                "observation": nxt,
                "epistemic_std": sigma,
                "reward": torch.zeros(*batch, 1, dtype=nxt.dtype, device=nxt.device),
                "done": torch.zeros(*batch, 1, dtype=torch.bool, device=nxt.device),
                "terminated": torch.zeros(*batch, 1, dtype=torch.bool, device=nxt.device),
            },
            batch_size=batch,
        )
        if member is not None:
            out.set(self.member_key, member)
        return out
