"""Model-based policy optimization (MBPO, Janner et al. 2019) with TorchRL's SAC, on any model env.

Paper, supplement "SoftAE with Model-Based Policy Optimization" (Table S8): a SAC policy is trained
on short imagined rollouts branched from real states:

    repeat
        s_0 ~ D_env                                  (``rollout_batch`` real start states)
        s_{h+1} = f(s_h, a_h),  a_h ~ pi(.|s_h)      (``rollout_horizon`` model steps, the model
                                                      env's propagation: mean = MBPO, sample = MBPO-TS)
        D_model <- D_model + {(s_h, a_h, r_h, s_{h+1})}
        ``updates_per_rollout`` SAC updates on batches of ``real_ratio`` real + the rest imagined

The model env is any TorchRL env that starts from the ``"observation"`` of the tensordict given to
``reset`` and sets the task reward (e.g. ``TransformedEnv(EnsembleModelEnv(model), TaskReward(task))``).
Real transitions are relabelled with the same task reward, so a data set collected for another
purpose (exploration) trains a policy for any task.
"""
from __future__ import annotations

from typing import Callable

import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.nn import TensorDictModule, TensorDictModuleBase
from torch import nn
from torchrl.data import Bounded, LazyTensorStorage, ReplayBuffer
from torchrl.envs import EnvBase
from torchrl.envs.utils import ExplorationType, set_exploration_type
from torchrl.modules import MLP, NormalParamExtractor, ProbabilisticActor, TanhNormal, ValueOperator
from torchrl.objectives import SACLoss, SoftUpdate

from torchrl_softae.envs.transforms.hallucinated_control import RealActionPolicy
from torchrl_softae.seeding import derive_seed

__all__ = ["make_sac_actor_critic", "branched_rollouts", "MBPOTrainer", "PolicyForRealEnv", "TRANSITION_KEYS"]

#: what one transition holds for SAC (real and imagined alike)
TRANSITION_KEYS = ("observation", "action", ("next", "observation"), ("next", "reward"), ("next", "done"),
                   ("next", "terminated"))


def make_sac_actor_critic(observation_dim: int, action_spec: Bounded, num_cells: int = 1024, depth: int = 3,
                          device=None) -> tuple[ProbabilisticActor, ValueOperator]:
    """SAC's actor (tanh-squashed Gaussian on ``action_spec``'s box) and Q network, ``depth`` x
    ``num_cells`` SiLU MLPs each (Table S8: 3 x 1024), as TorchRL's SAC example builds them.

    Examples:
        >>> actor, q = make_sac_actor_critic(3, Bounded(-2.0, 2.0, (1,)), num_cells=32, depth=2)
        >>> td = actor(TensorDict({"observation": torch.zeros(5, 3)}, [5]))
        >>> td["action"].shape, q(td)["state_action_value"].shape
        (torch.Size([5, 1]), torch.Size([5, 1]))
    """
    d_a = action_spec.shape[-1]
    low = action_spec.space.low.to(device=device, dtype=torch.float32)
    high = action_spec.space.high.to(device=device, dtype=torch.float32)
    cells = [num_cells] * depth
    actor_net = nn.Sequential(
        MLP(in_features=observation_dim, out_features=2 * d_a, num_cells=cells, activation_class=nn.SiLU,
            device=device),
        NormalParamExtractor(scale_mapping="biased_softplus_1.0", scale_lb=1e-4),
    )
    actor = ProbabilisticActor(
        TensorDictModule(actor_net, in_keys=["observation"], out_keys=["loc", "scale"]),
        in_keys=["loc", "scale"], spec=Bounded(low, high, (d_a,), device=device),
        distribution_class=TanhNormal, distribution_kwargs={"low": low, "high": high, "tanh_loc": False},
        default_interaction_type=ExplorationType.RANDOM, return_log_prob=False,
    )
    qvalue = ValueOperator(
        MLP(in_features=observation_dim + d_a, out_features=1, num_cells=cells, activation_class=nn.SiLU,
            device=device),
        in_keys=["observation", "action"],
    )
    return actor, qvalue


@torch.no_grad()
def branched_rollouts(env: EnvBase, policy, start_observations: torch.Tensor, horizon: int) -> TensorDictBase:
    """``horizon`` steps of ``policy`` on ``env`` from each of ``(B, d_s)`` start states.

    Returns the ``(B * horizon,)`` transitions (:data:`TRANSITION_KEYS`), row ``b * horizon + h``
    being step ``h`` of the rollout from ``start_observations[b]``. The policy samples (SAC's
    exploration). Rollouts start from the given states without a reset, so ``"sample"``
    propagation draws a member per transition (TS-1, as MBPO does).
    """
    B = start_observations.shape[0]
    td = TensorDict({"observation": start_observations.to(env.device)}, [B], device=env.device)
    with set_exploration_type(ExplorationType.RANDOM):
        traj = env.rollout(horizon, policy, tensordict=td, auto_reset=False, break_when_any_done=False)
    # the rollout is a lazy stack of its steps (not return_contiguous=True: the first step, not
    # reset, lacks the done keys the others have); made dense once here, on the transition keys
    # every step has, because indexing, moving and storing a lazy (B * horizon,) stack goes row by
    # row (far slower than on a dense tensordict)
    return traj.select(*TRANSITION_KEYS).contiguous().reshape(-1)


class MBPOTrainer:
    """SAC (TorchRL's :class:`~torchrl.objectives.SACLoss`) on imagined rollouts from real states.

    Args:
        actor, qvalue: from :func:`make_sac_actor_critic` (the actor's action space is the model
            env's, e.g. ``[a, eta]`` behind a :class:`~torchrl_softae.envs.HallucinatedControl`).
        reward_fn: ``(s, a, s') -> r`` (``(*B,)`` or ``(*B, 1)``), the task reward, used to
            relabel real transitions (the model env computes the imagined ones' itself).
        rollout_horizon: imagined steps per branch [H, Table S8: 5].
        rollout_batch: real start states per rollout round (MBPO: 400).
        updates_per_rollout: SAC updates between two rollout rounds (MBPO: 20 per env step).
        real_ratio: fraction of real transitions in every SAC batch (MBPO: 0.05).
        imagined_capacity: imagined transitions kept (oldest dropped first).
        batch_size, lr: Table S8 (256, 3e-4); ``gamma``, ``tau``: MBPO's 0.99 and 0.005.

    Construction draws from torch's global RNG (TorchRL's ``SACLoss`` initializes the second Q
    network), so seed it before building for reproducible networks.

    A round (rollouts, then updates) reseeds torch from ``(seed, round)``, so training in pieces
    with checkpoints in between (:meth:`state_dict`) gives the numbers of one uninterrupted call.
    """

    def __init__(
        self,
        actor: ProbabilisticActor,
        qvalue: ValueOperator,
        reward_fn: Callable[[torch.Tensor, torch.Tensor, torch.Tensor], torch.Tensor],
        *,
        rollout_horizon: int = 5,
        rollout_batch: int = 400,
        updates_per_rollout: int = 20,
        real_ratio: float = 0.05,
        imagined_capacity: int = 200_000,
        batch_size: int = 256,
        lr: float = 3e-4,
        gamma: float = 0.99,
        tau: float = 0.005,
    ):
        if not 0 <= real_ratio <= 1:
            raise ValueError(f"real_ratio={real_ratio!r}, expected in [0, 1]")
        for name, v in (("rollout_horizon", rollout_horizon), ("rollout_batch", rollout_batch),
                        ("updates_per_rollout", updates_per_rollout), ("batch_size", batch_size),
                        ("imagined_capacity", imagined_capacity)):
            if not (isinstance(v, int) and v > 0):
                raise ValueError(f"{name}={v!r}, expected a positive integer")
        self.actor, self.qvalue, self.reward_fn = actor, qvalue, reward_fn
        self.rollout_horizon, self.rollout_batch = rollout_horizon, rollout_batch
        self.updates_per_rollout, self.batch_size = updates_per_rollout, batch_size
        self.num_real = int(round(real_ratio * batch_size))
        self.loss = SACLoss(actor, qvalue, num_qvalue_nets=2, loss_function="l2", delay_actor=False,
                            delay_qvalue=True, alpha_init=1.0)
        self.loss.make_value_estimator(gamma=gamma)
        self.target_update = SoftUpdate(self.loss, tau=tau)
        self.optimizer = torch.optim.Adam([
            {"params": list(self.loss.actor_network_params.flatten_keys().values())},
            {"params": list(self.loss.qvalue_network_params.flatten_keys().values())},
            {"params": [self.loss.log_alpha]},
        ], lr=lr)
        self.imagined = ReplayBuffer(storage=LazyTensorStorage(imagined_capacity))
        self.rounds = 0  # rollout rounds done (what the seeds and a resumed run count from)
        self.updates = 0

    @property
    def action_dim(self) -> int:
        return self.actor.spec["action"].shape[-1]

    # ------------------------------------------------------------------ data
    def real_transitions(self, real: TensorDictBase, index: torch.Tensor) -> TensorDictBase:
        """Real transitions ``real[index]`` with the task reward, actions padded with zeros to the
        policy's action size (``eta = 0``: the model's mean, what a real step is closest to)."""
        t = real[index]
        s, a, s2 = t["observation"], t["action"], t["next", "observation"]
        r = self.reward_fn(s, a, s2)
        r = r.unsqueeze(-1) if r.shape == s.shape[:-1] else r
        if a.shape[-1] < self.action_dim:
            a = torch.cat([a, a.new_zeros(*a.shape[:-1], self.action_dim - a.shape[-1])], -1)
        done = torch.zeros(*s.shape[:-1], 1, dtype=torch.bool, device=s.device)
        return TensorDict({"observation": s, "action": a, "next": {
            "observation": s2, "reward": r.to(s.dtype), "done": done, "terminated": done}}, [len(index)])

    def sample_batch(self, real: TensorDictBase) -> TensorDictBase:
        """One SAC batch: the first :attr:`num_real` rows real, the rest imagined (all real while
        nothing is imagined yet)."""
        n_real = self.num_real if len(self.imagined) else self.batch_size
        parts = []
        if n_real:
            parts.append(self.real_transitions(real, torch.randint(len(real), (n_real,))))
        if self.batch_size - n_real:
            parts.append(self.imagined.sample(self.batch_size - n_real).select(*TRANSITION_KEYS))
        return torch.cat(parts) if len(parts) > 1 else parts[0]

    def imagine(self, model_env: EnvBase, real: TensorDictBase) -> TensorDictBase:
        """One rollout round into the imagined buffer; returns the new transitions."""
        starts = real["observation"][torch.randint(len(real), (self.rollout_batch,))]
        new = branched_rollouts(model_env, self.actor, starts, self.rollout_horizon)
        # a model that diverges must not poison the critic: keep finite transitions only
        finite = torch.isfinite(new["next", "observation"]).all(-1) & torch.isfinite(new["next", "reward"]).all(-1)
        new = new[finite].cpu()
        if len(new):
            self.imagined.extend(new)
        return new

    # ------------------------------------------------------------------ SAC
    def update(self, batch: TensorDictBase) -> dict:
        losses = self.loss(batch)
        total = losses["loss_actor"] + losses["loss_qvalue"] + losses["loss_alpha"]
        self.optimizer.zero_grad(set_to_none=True)
        total.backward()
        self.optimizer.step()
        self.target_update.step()
        self.updates += 1
        return {k: float(losses[k].detach()) for k in ("loss_actor", "loss_qvalue", "loss_alpha", "alpha", "entropy")}

    def train(self, model_env: EnvBase, real: TensorDictBase, rounds: int, seed: int = 0, progress=None) -> dict:
        """``rounds`` rollout rounds, each followed by ``updates_per_rollout`` SAC updates.

        ``real``: the ``(N,)`` real transitions (``observation``, ``action``, ``("next",
        "observation")``). Returns the last update's losses and the imagined buffer's size.
        """
        if len(real) == 0:
            raise ValueError("MBPOTrainer.train needs at least one real transition")
        last = {}
        for _ in range(rounds):
            round_seed = derive_seed(seed, self.rounds)
            torch.manual_seed(round_seed)
            model_env.set_seed(round_seed)
            self.imagine(model_env, real)
            for _ in range(self.updates_per_rollout):
                last = self.update(self.sample_batch(real))
            self.rounds += 1
            if progress is not None:
                progress.update(self.updates_per_rollout)
                progress.set_postfix(q=f"{last['loss_qvalue']:.3g}", alpha=f"{last['alpha']:.3g}")
        last["imagined"] = len(self.imagined)
        return last

    def policy(self, action_dim: int | None = None, deterministic: bool = True) -> TensorDictModuleBase:
        """The actor as a real-env policy: its mode (or a sample). ``action_dim``: the real env's
        action size when the actor also emits hallucinated control (``[a, eta]``): only ``a``
        reaches the env (:class:`~torchrl_softae.envs.RealActionPolicy`)."""
        policy = PolicyForRealEnv(self.actor, deterministic)
        if action_dim is not None and action_dim < self.action_dim:
            policy = RealActionPolicy(policy, action_dim)
        return policy

    # ------------------------------------------------------------------ checkpoint
    def state_dict(self) -> dict:
        return {"loss": self.loss.state_dict(), "optimizer": self.optimizer.state_dict(),
                "imagined": self.imagined.state_dict(), "rounds": self.rounds, "updates": self.updates}

    def load_state_dict(self, state: dict) -> None:
        self.loss.load_state_dict(state["loss"])
        self.optimizer.load_state_dict(state["optimizer"])
        self.imagined.load_state_dict(state["imagined"])
        self.rounds, self.updates = int(state["rounds"]), int(state["updates"])


class PolicyForRealEnv(TensorDictModuleBase):
    """A SAC actor acting on a real env: its mode (``deterministic``) or a sample, without
    gradients, in the observation's dtype. Wrap it in
    :class:`~torchrl_softae.envs.RealActionPolicy` when the actor also emits hallucinated control."""

    def __init__(self, actor: ProbabilisticActor, deterministic: bool = True):
        super().__init__()
        self.actor, self.deterministic = actor, deterministic
        self.in_keys, self.out_keys = ["observation"], ["action"]

    @torch.no_grad()
    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        kind = ExplorationType.DETERMINISTIC if self.deterministic else ExplorationType.RANDOM
        with set_exploration_type(kind):
            out = self.actor(tensordict.select("observation").float())
        return tensordict.set("action", out["action"].to(tensordict.get("observation").dtype))
