"""Planning rollouts of the ensemble, laid out once: the model steps a planner's candidates take
over the horizon, with every step's network input written before the first step and, where the
kernels run, each step two prepared kernel calls (the whole network, then one moments pass that
also forms the next state and writes it into the next step's input).

- :class:`DeterministicRollout`: Mean-AE ``s' = mu`` and SoftAE / H-UCRL ``s' = mu + sigma * eta``,
  one particle per candidate.
- :class:`SampledRollout`: PETS-AE's trajectory sampling, ``P`` particles per candidate, each on
  one member for the whole horizon, ``s' = m_l + std_l * z``.

Built by :meth:`torchrl_softae.modules.engine.InferenceEngine.deterministic_rollout` and
:meth:`~torchrl_softae.modules.engine.InferenceEngine.sampled_rollout`; an :class:`~torchrl_softae.envs.EnsembleModelEnv`
scores a plan's candidates through them. The layouts (buffers and prepared calls) live in the
model's inference cache under keys whose first entry is one of :data:`ROLLOUT_KINDS`: one rollout
holds a layout at a time, the next rollout of the same shape takes it again. The layout functions
take the model (an :class:`~torchrl_softae.modules.EnsembleWorldModel`) as their first argument and
read its layers, normalizers, inference path and cache.
"""
from __future__ import annotations

import itertools
import threading
from collections.abc import Sequence
from types import SimpleNamespace

import torch

from torchrl_softae.modules.engine import moments_kernel, normal_kernel
from torchrl_softae.modules.engine.paths import WHOLE_NETWORK_KERNELS

__all__ = ["DeterministicRollout", "SampledRollout", "ROLLOUT_KINDS", "is_rollout_key"]

#: the first entry of a rollout layout's key in the model's inference cache, per kind of rollout
ROLLOUT_KINDS = ("rollout", "sampled rollout")


def is_rollout_key(key: tuple) -> bool:
    """Whether ``key`` of the model's inference cache holds a rollout's layout (its prepared calls
    read the addresses of this model's buffers: a copy of the model prepares its own)."""
    return key[0] in ROLLOUT_KINDS


def _same_objects(a: tuple | None, b: tuple | None) -> bool:
    """Whether two tuples hold the same objects (identity, not equality), or both are ``None``."""
    if a is None or b is None:
        return a is b
    return len(a) == len(b) and all(x is y for x, y in zip(a, b))


#: tokens of rollout objects (which one holds a layout of buffers), and the lock under
#: which a rollout takes or frees a layout
_ROLLOUT_TOKENS = itertools.count()
_ROLLOUT_LOCK = threading.Lock()


def _rollout_network(model, rows: Sequence[int], cols: int | None, device, dtype: torch.dtype) -> tuple:
    """The whole-network kernel path and packed weights for a rollout's network calls of
    ``rows`` (each call's row count), or ``(None, None)`` where its steps cannot run as prepared
    kernel calls: autograd on, not the CPU, moments by torch ops, symlog states, no moments kernel,
    or an inference path that is not a whole-network kernel for one of the row counts."""
    d, d_a = model.observation_dim, model.action_dim
    if (torch.is_grad_enabled() or torch.device(device).type != "cpu" or not model.engine.fused_moments
            or not model.engine.uses_kernels
            or model.symlog_observations or not moments_kernel.available()
            or model.ensemble_size > moments_kernel.MAX_MEMBERS):
        return None, None
    paths = tuple(model.engine._inference_path(torch.empty(r, d + d_a), dtype, cols) for r in sorted(set(rows)))
    if any(p not in WHOLE_NETWORK_KERNELS for p in paths):
        return None, None
    return paths, tuple(model.engine._packed_network(p, dtype, cols) for p in paths)


def _take_layout(model, key: tuple, packed, owner: int, build, dtype: torch.dtype) -> SimpleNamespace:
    """The cached layout of buffers for the rollout ``key``, taken by ``owner`` (a rollout's
    token) until that rollout has run or is dropped, or a new one from ``build()``, kept for
    the next rollout of the same shape (a planner scores its iterations' candidates with the
    same shapes: preparing the calls cost more than a step). Another rollout of the same shape
    meanwhile (nested, or from another thread) gets its own."""
    key = (*key, dtype, torch.get_num_threads())
    with _ROLLOUT_LOCK:  # taken by one rollout: the check and the taking in one step
        hit = model.engine._inference_cache.get(key)
        # packed weights rebuilt (a parameter changed): the prepared calls read the old ones
        if hit is not None and hit.owner is None and _same_objects(hit.packed, packed):
            hit.owner = owner
            return hit
    layout = build()
    layout.owner, layout.packed = owner, packed
    with _ROLLOUT_LOCK:
        hit = model.engine._inference_cache.get(key)
        if hit is None or hit.owner is None:  # a rollout still running keeps its own
            model.engine._inference_cache[key] = layout
    return layout


def deterministic_layout(model, steps: int, rows: int, with_eta: bool, device, owner: int,
                         dtype: torch.dtype = torch.float32) -> SimpleNamespace:
    """The buffers of a :class:`DeterministicRollout` of ``steps`` x ``rows`` (every step's
    network input, ``eta``, the trajectory of states from the initial ones, each step's
    ``sigma``) and, where
    :func:`_rollout_network` allows, its steps as prepared kernel calls (``compiled``:
    ``[(network call, moments call, (s', sigma)), ...]``; else ``None``), held by ``owner``
    (:func:`_take_layout`)."""
    d, d_a = model.observation_dim, model.action_dim
    cols = d if model.probabilistic else None  # the mean head only, as network_output(with_logvar=False)
    paths, packed = _rollout_network(model, [rows], cols, device, dtype)

    def build():
        layout = SimpleNamespace(
            inputs=torch.empty(steps, rows, d + d_a, device=device),
            eta=torch.empty(steps, rows, d, device=device) if with_eta else None,
            trajectory=torch.empty(steps + 1, rows, d, device=device),
            sigmas=torch.empty(steps, rows, d, device=device), compiled=None)
        if paths is None:
            return layout
        raw = torch.empty(model.ensemble_size, rows, cols or model.layers[-1].out_features)
        out, norm = model.output_normalizer, model.input_normalizer
        inputs, states, sigmas, eta = layout.inputs, layout.trajectory, layout.sigmas, layout.eta
        layout.compiled = []
        for h in range(steps):
            network, _ = WHOLE_NETWORK_KERNELS[paths[0]].prepare_forward(inputs[h], packed[0], raw.shape[-1],
                                                                          out=raw)
            moments, _ = moments_kernel.prepare_moments(
                raw, states[h], out.loc, out.scale, d,
                eta=None if eta is None else eta[h], next_input=inputs[h + 1] if h + 1 < steps else None,
                input_loc=norm.loc[:d], input_scale=norm.scale[:d], out=(states[h + 1], sigmas[h]))
            layout.compiled.append((network, moments, (states[h + 1], sigmas[h])))
        return layout

    return _take_layout(model, (ROLLOUT_KINDS[0], steps, rows, with_eta, paths, str(device)), packed, owner, build,
                        dtype)


def sampled_layout(model, steps: int, rows: int, particles: int, with_noise: bool, device,
                   owner: int, dtype: torch.dtype = torch.float32) -> SimpleNamespace:
    """The buffers of a :class:`SampledRollout` of ``steps`` x ``rows`` candidates x
    ``particles`` (the first step's network input, ``rows`` rows, the later steps' ``rows *
    particles``, the candidates' initial states, members, noise, the trajectory of every
    particle's states from the initial ones, each step's ``sigma``) and,
    where :func:`_rollout_network` allows and the aleatoric std has bounds the moments kernel
    takes, its steps as prepared kernel calls (``compiled``, as :func:`deterministic_layout`'s),
    held by ``owner`` (:func:`_take_layout`)."""
    d, d_a = model.observation_dim, model.action_dim
    with_logvar = with_noise and model.probabilistic
    cols = d if (model.probabilistic and not with_logvar) else None
    bounds = model.engine._fused_logvar_bounds() if with_logvar else None
    wide = with_logvar and bounds is None  # the kernel cannot form this aleatoric std
    paths, packed = (None, None) if wide else _rollout_network(model, [rows, rows * particles], cols, device, dtype)
    n = rows * particles

    def build():
        layout = SimpleNamespace(
            first_input=torch.empty(rows, d + d_a, device=device),
            inputs=torch.empty(steps - 1, n, d + d_a, device=device), observation=torch.empty(rows, d, device=device),
            member=torch.zeros(n, dtype=torch.int64, device=device),  # valid before the first rollout fills it
            noise=torch.empty(steps, n, d, device=device) if with_noise else None,
            trajectory=torch.empty(steps + 1, n, d, device=device), sigmas=torch.empty(steps, n, d, device=device),
            compiled=None)
        if paths is None:
            return layout
        kernels = [WHOLE_NETWORK_KERNELS[p] for p in paths]
        width = cols or model.layers[-1].out_features
        first_raw = torch.empty(model.ensemble_size, rows, width)
        raw = torch.empty(model.ensemble_size, n, width)
        out, norm = model.output_normalizer, model.input_normalizer
        # without aleatoric noise s' is the member's mean: the kernel takes noise as the switch to
        # the member's next state and, without the log-variance head, never reads it
        zero_noise = None if with_noise else torch.zeros(n, d)
        states, sigmas = layout.trajectory, layout.sigmas
        layout.compiled = []
        for h in range(steps):
            # the first step's rows are the candidates' (their particles share them), then every particle's
            x, y, which = (layout.first_input, first_raw, 0) if h == 0 else (layout.inputs[h - 1], raw, -1)
            network, _ = kernels[which].prepare_forward(x, packed[which], width, out=y)
            moments, _ = moments_kernel.prepare_moments(
                y, layout.observation if h == 0 else states[h], out.loc, out.scale, d, layout.member,
                with_logvar, bounds, next_input=layout.inputs[h] if h + 1 < steps else None,
                input_loc=norm.loc[:d], input_scale=norm.scale[:d], out=(states[h + 1], sigmas[h]),
                noise=layout.noise[h] if with_noise else zero_noise, particles=particles if h == 0 else 1)
            layout.compiled.append((network, moments, (states[h + 1], sigmas[h])))
        return layout

    key = (ROLLOUT_KINDS[1], steps, rows, particles, with_noise, paths, str(device))
    return _take_layout(model, key, packed, owner, build, dtype)


class _PlanningRollout:
    """What a planning rollout's kinds share: a layout of buffers (and prepared kernel calls) taken
    from the model's cache for one run, stepped once, then given back. A subclass fills the
    layout's inputs in ``__init__`` and writes :meth:`_torch_steps` (the steps as torch ops, where
    they do not run as prepared calls)."""

    def __len__(self) -> int:
        return self._layout.sigmas.shape[0]

    @property
    def compiled(self) -> bool:
        """Whether the steps run as prepared kernel calls."""
        return self._layout.compiled is not None

    def __iter__(self):
        layout = self._layout
        if layout.owner != self._token:
            raise RuntimeError(f"{type(self).__name__}: already run (a rollout runs once; its buffers are the next's)")
        try:
            if layout.compiled is not None:
                for network, moments, step in layout.compiled:
                    network()
                    moments()
                    yield step
                return
            yield from self._torch_steps()
        finally:
            self._release()

    def run(self) -> tuple[torch.Tensor, torch.Tensor]:
        """Every step at once: the trajectory ``(H + 1, rows, d_s)`` (the initial states, then each
        step's ``s'``) and each step's ``sigma`` ``(H, rows, d_s)``, the rollout's buffers (a model
        env then scores all steps in one reward call instead of one per step between the network
        calls)."""
        for _ in self:
            pass
        return self._layout.trajectory, self._layout.sigmas

    def _torch_steps(self):
        """The steps as torch ops (where they do not run as prepared kernel calls), writing
        ``s'`` and ``sigma`` into the layout's buffers as the prepared calls do."""
        raise NotImplementedError

    def _release(self) -> None:
        with _ROLLOUT_LOCK:
            if self._layout.owner == self._token:
                self._layout.owner = None

    def __del__(self):  # dropped without running: its buffers are free for the next rollout
        if hasattr(self, "_layout"):
            self._release()


def _check_rollout_actions(kind: str, model, observation: torch.Tensor,
                           normalized_actions: torch.Tensor) -> tuple[int, int]:
    """``(H, M)`` of a rollout's ``(H, M, d_a)`` actions from ``(M, d_s)`` states, or one clear error."""
    if normalized_actions.dim() != 3 or normalized_actions.shape[-1] != model.action_dim:
        raise ValueError(f"{kind}: normalized_actions has shape {tuple(normalized_actions.shape)}, "
                         f"expected (H, M, {model.action_dim})")
    H, M, _ = normalized_actions.shape
    if observation.shape != (M, model.observation_dim):
        raise ValueError(f"{kind}: observation has shape {tuple(observation.shape)}, "
                         f"expected ({M}, {model.observation_dim})")
    return H, M


class DeterministicRollout(_PlanningRollout):
    """The model steps of a deterministic planning rollout of ``M`` candidates, laid out once.

    Mean-AE propagates ``s' = mu``, SoftAE and H-UCRL ``s' = mu + sigma * eta`` [the optimistic
    mean, eta the hallucinated control with beta applied]. A planner knows its candidates' actions
    for the whole horizon: every step's network input is written before the first step, its action
    columns at once, and each step writes the next input's state columns in the same pass that
    computes ``mu`` and ``sigma``. Where the inference path is a whole-network kernel
    (:mod:`.amx_network`, :mod:`.fma_network`) and the moments kernel applies
    (:mod:`.moments_kernel`), a step is two compiled calls, prepared once per shape: right after a
    network call every torch op and line of Python runs on cache-cold code and data, several times
    slower than the same op in a loop (``benchmarks/studies/cold_ops.py``).
    Elsewhere each step runs :meth:`EnsembleWorldModel.network_output` and the torch ops of the
    moments, with the same values (``test_deterministic_rollout_matches_the_torch_ops``).

    Inference only (``torch.no_grad()``), the hidden layers in ``dtype`` (``None``: fp32); the parameters must
    not change while it runs. Iterating yields ``(s', sigma)``, ``(M, d_s)`` each, step by step,
    once. The yielded tensors are buffers that the model's next rollout of the same shape writes
    again (preallocated, as a planner's iterations reuse them): copy them to keep them. A rollout
    built while another of its shape has not run yet (nested, another thread) gets its own.

    Args:
        model: the ensemble.
        observation: ``(M, d_s)`` the initial states.
        normalized_actions: ``(H, M, d_a)`` (:meth:`EnsembleWorldModel.normalized_actions`).
        eta: ``(H, M, d_s)`` or ``None``.
        dtype: the hidden layers' dtype (``torch.bfloat16`` to plan in bf16; ``None``: fp32).

    Examples:
        >>> import torch
        >>> from torchrl_softae.modules import EnsembleWorldModel
        >>> model = EnsembleWorldModel(3, 1).eval()
        >>> acts = model.normalized_actions(torch.zeros(4, 2, 1))  # H = 4 steps of 2 candidates
        >>> with torch.no_grad():
        ...     rollout = model.engine.deterministic_rollout(torch.zeros(2, 3), acts)
        ...     steps = [(s.clone(), sigma.clone()) for s, sigma in rollout]
        >>> len(steps), steps[-1][0].shape  # (s', sigma) per step
        (4, torch.Size([2, 3]))
    """

    def __init__(self, model, observation: torch.Tensor, normalized_actions: torch.Tensor,
                 eta: torch.Tensor | None = None, dtype: torch.dtype | None = None):
        d = model.observation_dim
        H, M = _check_rollout_actions("DeterministicRollout", model, observation, normalized_actions)
        if eta is not None and eta.shape != (H, M, d):
            raise ValueError(f"DeterministicRollout: eta has shape {tuple(eta.shape)}, expected ({H}, {M}, {d})")
        self.model, self.dtype = model, dtype
        self._token = next(_ROLLOUT_TOKENS)
        self._layout = layout = deterministic_layout(model, H, M, eta is not None, observation.device, self._token,
                                                     dtype or torch.float32)
        # every step's network input: the actions' columns at once, the first state's now, each
        # next state's by the step before
        layout.inputs[..., d:] = normalized_actions
        layout.inputs[0] = model.network_input(observation, normalized_actions[0], action_normalized=True)
        layout.trajectory[0].copy_(observation)
        if eta is not None:
            layout.eta.copy_(eta)

    @property
    def network_calls(self) -> list[tuple[tuple[int, int], bool]]:
        """Each step's network call: its input's shape and whether it computes the log-variance."""
        return [(tuple(x.shape), False) for x in self._layout.inputs]

    def _torch_steps(self):
        model, layout = self.model, self._layout
        inputs, eta, states, sigmas = layout.inputs, layout.eta, layout.trajectory, layout.sigmas
        H = inputs.shape[0]
        for h in range(H):
            raw = model.network_output(inputs[h], with_logvar=False, dtype=self.dtype)
            state, sigma, _, _ = model.moments_from_output(
                raw, states[h], eta=None if eta is None else eta[h], next_input=inputs[h + 1] if h + 1 < H else None)
            states[h + 1].copy_(state)
            sigmas[h].copy_(sigma)
            yield states[h + 1], sigmas[h]


class SampledRollout(_PlanningRollout):
    """The model steps of a trajectory-sampling planning rollout (PETS-AE, TS-inf) of ``M``
    candidates with ``P`` particles each, laid out once.

    Every particle follows one member ``l`` for the whole horizon and propagates ``s' = m_l +
    std_l * z`` [m_l that member's mean, std_l its aleatoric std, z standard normal; ``s' = m_l``
    without aleatoric noise], while ``sigma`` [the epistemic std over all members, which the
    exploration reward needs] is computed at every particle's state. At the first step a
    candidate's particles share its state and action: the network runs once for them (``M`` rows,
    then ``M * P``). As in :class:`DeterministicRollout` every step's network input is written
    before the first step, each step writes the next input's state columns in the same pass that
    draws the next state, and where the inference path is a whole-network kernel and the moments
    kernel applies a step is two prepared kernel calls; elsewhere torch ops with the same values
    (``test_sampled_rollout_matches_the_torch_ops``). The noise of every step is drawn before the
    first one, one draw per step from ``generator`` in step order, as
    :meth:`~torchrl_softae.envs.EnsembleModelEnv.propagate` draws it step by step: the same
    generator state gives the same noise.

    Inference only, the hidden layers in ``dtype`` (``None``: fp32). Iterating yields ``(s', sigma)``, ``(M * P,
    d_s)`` each (row ``m * P + p``: candidate ``m``'s particle ``p``), step by step, once: buffers
    that the next rollout of the same shape writes again (copy them to keep them).

    Args:
        model: the ensemble.
        observation: ``(M, d_s)`` the initial states.
        normalized_actions: ``(H, M, d_a)`` (:meth:`EnsembleWorldModel.normalized_actions`).
        member_index: ``(M, P)`` each particle's member.
        aleatoric_noise: draw the members' aleatoric noise.
        generator: the noise's source (torch's default generator if ``None``).
        dtype: the hidden layers' dtype (``None``: fp32).

    Examples:
        >>> import torch
        >>> from torchrl_softae.modules import EnsembleWorldModel
        >>> model = EnsembleWorldModel(3, 1).eval()
        >>> acts = model.normalized_actions(torch.zeros(4, 2, 1))  # H = 4 steps of 2 candidates
        >>> members = torch.tensor([[0, 1, 2], [3, 4, 0]])  # 3 particles each
        >>> with torch.no_grad():
        ...     steps = [s.clone() for s, _ in model.engine.sampled_rollout(torch.zeros(2, 3), acts, members)]
        >>> len(steps), steps[-1].shape  # s' of every particle, step by step
        (4, torch.Size([6, 3]))
    """

    def __init__(self, model, observation: torch.Tensor, normalized_actions: torch.Tensor,
                 member_index: torch.Tensor, aleatoric_noise: bool = True, generator: torch.Generator | None = None,
                 dtype: torch.dtype | None = None):
        d = model.observation_dim
        H, M = _check_rollout_actions("SampledRollout", model, observation, normalized_actions)
        if member_index.dim() != 2 or member_index.shape[0] != M or member_index.dtype.is_floating_point:
            raise ValueError(f"SampledRollout: member_index is {tuple(member_index.shape)} {member_index.dtype}, "
                             f"expected ({M}, P) integers")
        L = model.ensemble_size
        lo, hi = torch.aminmax(member_index) if member_index.numel() else (0, 0)
        if not (0 <= int(lo) and int(hi) < L):
            raise ValueError(f"SampledRollout: member_index outside [0, {L})")
        P = member_index.shape[1]
        self.model, self.particles, self.dtype = model, P, dtype
        self._token = next(_ROLLOUT_TOKENS)
        self._layout = layout = sampled_layout(model, H, M, P, aleatoric_noise, observation.device, self._token,
                                               dtype or torch.float32)
        layout.first_input.copy_(model.network_input(observation, normalized_actions[0], action_normalized=True))
        if H > 1:  # the later steps' action columns, each candidate's repeated for its particles
            layout.inputs.view(H - 1, M, P, -1)[..., d:] = normalized_actions[1:].unsqueeze(2)
        layout.observation.copy_(observation)
        layout.trajectory[0].view(M, P, d).copy_(observation.unsqueeze(1))  # every particle's initial state
        layout.member.copy_(member_index.reshape(-1))
        if aleatoric_noise:
            # one draw per step, in step order, as stepping draws them: with autograd on, stepping's
            # states need a gradient and it draws by torch.randn (add_scaled_randn), so does this
            grad = torch.is_grad_enabled() and any(p.requires_grad for p in model.parameters())
            for noise in layout.noise:
                if grad:
                    noise.copy_(torch.randn(noise.shape, generator=generator, device=noise.device))
                else:
                    normal_kernel.normal_(noise, generator, kernel=model.engine.uses_kernels and model.engine.kernel_noise)

    @property
    def network_calls(self) -> list[tuple[tuple[int, int], bool]]:
        """Each step's network call: its input's shape and whether it computes the log-variance."""
        with_logvar = self._layout.noise is not None and self.model.probabilistic
        return [(tuple(x.shape), with_logvar) for x in (self._layout.first_input, *self._layout.inputs)]

    def _torch_steps(self):
        model, layout, P = self.model, self._layout, self.particles
        states, sigmas = layout.trajectory, layout.sigmas
        d, H = model.observation_dim, sigmas.shape[0]
        with_noise = layout.noise is not None
        for h in range(H):
            x = layout.first_input if h == 0 else layout.inputs[h - 1]
            raw = model.network_output(x, with_logvar=with_noise, dtype=self.dtype)
            if h == 0:  # the candidates' rows, each repeated for its particles
                raw = raw.repeat_interleave(P, dim=1)
            _, sigma, picked, ale = model.moments_from_output(raw, states[h], with_noise, layout.member)
            states[h + 1].copy_(picked if not with_noise else torch.addcmul(picked, ale, layout.noise[h]))
            sigmas[h].copy_(sigma)
            if h + 1 < H:
                layout.inputs[h, :, :d] = model._normalized_states(states[h + 1])
            yield states[h + 1], sigmas[h]
