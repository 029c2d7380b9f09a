"""The paper's model-training schedule (Table S6): after every episode, retrain on all data."""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import torch
from torch.profiler import record_function
from tensordict import TensorDictBase
from torchrl.data import ReplayBuffer

from torchrl_softae.objectives.ensemble_loss import EnsembleLoss

__all__ = ["TRAINING_PRECISIONS", "TrainingReport", "EnsembleTrainer", "transitions_from", "resolve_training_dtype"]

#: devices where ``EnsembleTrainer`` uses Adam's fused kernel by default
_FUSED_ADAM_DEVICES = ("cpu", "cuda")
#: ``EnsembleTrainer(precision=...)``: the dtype of the network's matmuls in training; ``"auto"`` is
#: bf16 where it measures faster for this model on this machine (:func:`resolve_training_dtype`)
TRAINING_PRECISIONS = ("auto", "fp32", "bf16")
_DTYPE_NAMES = {torch.float32: "fp32", torch.bfloat16: "bf16"}


@dataclass
class TrainingReport:
    """Per-epoch mean training loss and held-out normalized MSE of one :meth:`EnsembleTrainer.fit`."""

    train_loss: list = field(default_factory=list)
    val_mse: list = field(default_factory=list)
    grad_steps: int = 0
    num_train: int = 0
    num_val: int = 0
    precision: str = "fp32"  # the dtype the network's matmuls ran in ("fp32" or "bf16")

    @property
    def final_val_mse(self) -> float:
        return self.val_mse[-1] if self.val_mse else float("nan")


def transitions_from(data: ReplayBuffer | TensorDictBase, keys) -> TensorDictBase:
    """All transitions of a TorchRL replay buffer (or a tensordict) as one flat tensordict,
    with rows holding NaN/inf in any of ``keys`` dropped (a diverged step must not poison training)."""
    if isinstance(data, ReplayBuffer):
        n = len(data)
        if n == 0:
            raise ValueError("the replay buffer is empty: collect transitions before training")
        td = data.storage[:n]
    else:
        td = data
    td = td.reshape(-1).select(*keys)
    ok = torch.ones(td.shape[0], dtype=torch.bool, device=td.device)
    for key in keys:
        x = td.get(key)
        ok &= torch.isfinite(x.reshape(x.shape[0], -1)).all(-1)
    return td[ok] if not bool(ok.all()) else td


def _gradient_step_timer(model, batch_size: int, dtype: torch.dtype):
    """One gradient step of a fresh model shaped as ``model`` (random data, ``batch_size`` rows per
    member) with the matmuls in ``dtype``: what :func:`resolve_training_dtype` times. The model is
    not touched."""
    device = model.input_normalizer.loc.device
    probe = type(model)(model.observation_dim, model.action_dim, ensemble_size=model.ensemble_size,
                        num_cells=model.layers[0].out_features, depth=len(model.layers) - 1,
                        activation_class=type(model.activation), probabilistic=model.probabilistic,
                        device=device).train()
    g = torch.Generator().manual_seed(0)
    L = probe.ensemble_size
    x = torch.randn(L, batch_size, probe.observation_dim + probe.action_dim, generator=g).to(device)
    y = torch.randn(L, batch_size, probe.observation_dim, generator=g).to(device)
    loss_module = EnsembleLoss(probe)
    opt = torch.optim.Adam(probe.parameters(), lr=1e-6, fused=device.type in _FUSED_ADAM_DEVICES)

    def step():
        with torch.autocast(device.type, dtype=torch.bfloat16, enabled=dtype == torch.bfloat16):
            loss, _ = loss_module.normalized_loss(x, y)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()

    return step


def resolve_training_dtype(precision: str, model, batch_size: int = 64) -> torch.dtype:
    """The dtype of the network's matmuls in training for ``precision`` (:data:`TRAINING_PRECISIONS`).

    ``"auto"`` is bf16 only where the device has native bf16 units (:func:`.fast_bf16_available`
    on a CPU; ``torch.cuda.is_bf16_supported`` on CUDA) *and* a bf16 gradient step of this model's
    shapes measures faster than an fp32 one (timed once per machine, shapes and threads, cached on
    disk as planning's choices are: :func:`torchrl_softae.modules.engine.paths.choose`); else fp32."""
    if precision not in TRAINING_PRECISIONS:
        raise ValueError(f"precision={precision!r}, expected one of {', '.join(TRAINING_PRECISIONS)}")
    if precision != "auto":
        return torch.bfloat16 if precision == "bf16" else torch.float32
    from torchrl_softae.modules.engine import paths
    from torchrl_softae.modules.engine.precision import fast_bf16_available

    device = model.input_normalizer.loc.device
    native = torch.cuda.is_bf16_supported() if device.type == "cuda" else device.type == "cpu" and fast_bf16_available()
    if not native:
        return torch.float32
    shapes = ",".join(f"{layer.in_features}x{layer.out_features}" for layer in model.layers)
    key = (f"training step|{device.type}|ensemble {model.ensemble_size}|{shapes}|batch {batch_size}|"
           f"{type(model.activation).__name__}")
    candidates = {name: _gradient_step_timer(model, batch_size, dtype) for dtype, name in _DTYPE_NAMES.items()}
    return torch.bfloat16 if paths.choose(key, candidates) == "bf16" else torch.float32


class EnsembleTrainer:
    """Retrains an ensemble on all collected data with the paper's schedule.

    Args:
        loss_module (EnsembleLoss): the loss (holds the model).
        lr (float): Adam learning rate. Default 5e-5.
        batch_size (int): minibatch per member. Default 64.
        epochs (int): passes over the data per :meth:`fit`. Default 50.
        max_grad_steps (int): cap on gradient steps per :meth:`fit`. Default 5000.
        val_fraction (float): share of transitions held out for the validation MSE. Default 0.1.
        bootstrap (bool): members sample with replacement (bootstrap) instead of each walking
            its own random permutation. Default ``False``.
        weight_decay (float): Adam weight decay. Default 0.
        fused (bool, optional): Adam's fused kernel (one pass over each parameter instead of
            one per elementwise op; the same update up to float rounding). ``None`` (default):
            fused where torch has it for the model's device (CPU, CUDA).
        precision (str): the dtype of the network's matmuls, one of :data:`TRAINING_PRECISIONS`:
            ``"fp32"`` (default), ``"bf16"`` (``torch.autocast``: the hidden layers' matmuls in bf16;
            the output head, master weights, loss, normalizers and optimizer state in fp32) or
            ``"auto"`` (bf16 where it measures faster for this model here,
            :func:`resolve_training_dtype`). Resolved once, at the first
            :meth:`fit`, and kept in :meth:`state_dict`, so a resumed run trains as it began.
        progress (bool): show a tqdm bar.

    The optimizer lives across calls (its state is part of :meth:`state_dict`, for resuming).

    Examples:
        >>> model = EnsembleWorldModel(3, 1, num_cells=32, depth=2)
        >>> obs = torch.randn(500, 3)
        >>> data = TensorDict({"observation": obs, "action": torch.randn(500, 1),
        ...                    ("next", "observation"): obs + 0.1}, [500])
        >>> report = EnsembleTrainer(EnsembleLoss(model), lr=1e-3, epochs=2).fit(data)
        >>> report.grad_steps, report.precision
        (16, 'fp32')
    """

    def __init__(
        self,
        loss_module: EnsembleLoss,
        lr: float = 5e-5,
        batch_size: int = 64,
        epochs: int = 50,
        max_grad_steps: int = 5000,
        val_fraction: float = 0.1,
        bootstrap: bool = False,
        weight_decay: float = 0.0,
        fused: bool | None = None,
        precision: str = "fp32",
        progress: bool = False,
    ):
        for name, v in (("lr", lr), ("batch_size", batch_size), ("epochs", epochs), ("max_grad_steps", max_grad_steps)):
            if not v > 0:
                raise ValueError(f"EnsembleTrainer: {name}={v!r}, expected > 0")
        if not 0.0 <= val_fraction < 1.0:
            raise ValueError(f"EnsembleTrainer: val_fraction={val_fraction!r}, expected in [0, 1)")
        if precision not in TRAINING_PRECISIONS:
            raise ValueError(f"EnsembleTrainer: precision={precision!r}, expected one of {', '.join(TRAINING_PRECISIONS)}")
        self.loss_module = loss_module
        self.model = loss_module.world_model
        self.batch_size = batch_size
        self.epochs = epochs
        self.max_grad_steps = max_grad_steps
        self.val_fraction = val_fraction
        self.bootstrap = bootstrap
        self.progress = progress
        self.precision = precision
        self._dtype: torch.dtype | None = None  # resolved at the first fit (or read from a checkpoint)
        if fused is None:
            fused = self.model.input_normalizer.loc.device.type in _FUSED_ADAM_DEVICES
        self.fused = bool(fused)
        self.optimizer = torch.optim.Adam(self.model.parameters(), lr=lr, weight_decay=weight_decay, fused=self.fused)

    @property
    def dtype(self) -> torch.dtype:
        """The dtype of the network's matmuls in training (``precision`` resolved on first use)."""
        if self._dtype is None:
            self._dtype = resolve_training_dtype(self.precision, self.model, self.batch_size)
        return self._dtype

    def state_dict(self) -> dict:
        return {"optimizer": self.optimizer.state_dict(), "precision": _DTYPE_NAMES[self.dtype]}

    def load_state_dict(self, state: dict) -> None:
        self.optimizer.load_state_dict(state["optimizer"])
        # the dtype the run trained in: a checkpoint from before the choice existed trained in fp32
        resolved = state.get("precision", "fp32")
        if self.precision != "auto" and self.precision != resolved:
            raise ValueError(f"EnsembleTrainer: precision={self.precision!r}, but the checkpoint trained in {resolved}")
        self._dtype = torch.bfloat16 if resolved == "bf16" else torch.float32

    def fit(self, data: ReplayBuffer | TensorDictBase, generator: torch.Generator | None = None) -> TrainingReport:
        """Refit normalizers and train on every transition in ``data``, on the model's device.

        ``generator`` (a CPU generator) draws the split and minibatch order, so a seeded fit gives
        the same minibatches on every device. The network's inputs and targets are normalized once
        per fit (the normalizers are fixed within it) and each step gathers its rows from them: the
        same values as normalizing each minibatch, without per-step tensordict work."""
        k = self.loss_module.tensor_keys
        keys = [k.observation, k.action, k.next_observation]
        model = self.model
        device = model.input_normalizer.loc.device
        # a replay buffer's storage may live elsewhere, and hold another float dtype (gymnasium's
        # MuJoCo envs give float64): the data takes the model's device and dtype, once
        td = transitions_from(data, keys).to(device).to(model.layers[0].weight.dtype)
        n = td.shape[0]
        if n < 2:
            raise ValueError(f"EnsembleTrainer.fit needs at least 2 finite transitions, got {n}")
        dtype = self.dtype
        g = generator if generator is not None else torch.Generator().manual_seed(0)
        perm = torch.randperm(n, generator=g).to(device)
        n_val = int(round(self.val_fraction * n)) if n >= 10 else 0
        val, train = td[perm[:n_val]], td[perm[n_val:]]
        n_train = train.shape[0]
        with record_function("softae.train.normalizers"):
            obs, act, nxt = train.get(k.observation), train.get(k.action), train.get(k.next_observation)
            model.fit_normalizers(obs, act, nxt)  # checks the data's shapes and dtype once, for every step
            with torch.no_grad():
                inputs, targets = model.network_input(obs, act), model.normalized_target(obs, nxt)

        L = model.ensemble_size
        bs = min(self.batch_size, n_train)
        steps_per_epoch = math.ceil(n_train / bs)
        total = min(self.epochs * steps_per_epoch, self.max_grad_steps)
        report = TrainingReport(num_train=n_train, num_val=n_val, precision=_DTYPE_NAMES[dtype])
        bar = None
        if self.progress:
            from tqdm.auto import tqdm

            bar = tqdm(total=total, desc=f"train model ({report.precision})", leave=False, unit="step")
        model.train()
        autocast = torch.autocast(device.type, dtype=torch.bfloat16, enabled=dtype == torch.bfloat16)
        step = 0
        while step < total:
            with record_function("softae.train.batch"):
                if self.bootstrap:
                    order = torch.randint(n_train, (L, steps_per_epoch * bs), generator=g)
                else:  # every member walks its own permutation: one argsort, no loop over members
                    order = torch.rand(L, n_train, generator=g).argsort(dim=1)
                order = order.to(device)
            epoch_steps = min(steps_per_epoch, total - step)
            epoch_loss = torch.zeros((), dtype=torch.float64, device=device)  # as a Python float sum
            for j in range(epoch_steps):
                with record_function("softae.train.batch"):
                    idx = order[:, j * bs : (j + 1) * bs]  # (L, bs): one gather per tensor, all members
                    x, y = inputs[idx], targets[idx]
                with record_function("softae.train.forward"), autocast:
                    loss, _ = self.loss_module.normalized_loss(x, y)
                with record_function("softae.train.backward"):
                    self.optimizer.zero_grad(set_to_none=True)
                    loss.backward()
                with record_function("softae.train.optimizer"):
                    self.optimizer.step()
                epoch_loss += loss.detach()
                if bar is not None:
                    bar.update(1)
            step += epoch_steps
            report.train_loss.append(float(epoch_loss) / max(epoch_steps, 1))
            if n_val:
                with record_function("softae.train.validation"):
                    report.val_mse.append(self.validation_mse(val))
        if bar is not None:
            bar.close()
        model.eval()
        report.grad_steps = step
        return report

    @torch.no_grad()
    def validation_mse(self, td: TensorDictBase) -> float:
        """Normalized squared error of the ensemble mean on ``td`` (per-dimension output scale)."""
        k = self.loss_module.tensor_keys
        obs, act, nxt = td.get(k.observation), td.get(k.action), td.get(k.next_observation)
        mu, *_ = self.model.predict(obs, act)
        scale = self.model.output_normalizer.scale
        return float(((mu - nxt) / scale).square().mean())
