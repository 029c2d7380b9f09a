"""What exploration and evaluation share: the guarded real env, per-episode seeds, the held-out
set (cached) and the model-accuracy and coverage metrics."""
from __future__ import annotations

import os
import random
from pathlib import Path

import numpy as np
import torch
from tensordict import TensorDictBase
from torchrl.envs import EnvBase, StepCounter, TransformedEnv

from torchrl_softae.envs.guard import GuardedEnv
from torchrl_softae.modules import EnsembleWorldModel
from torchrl_softae.pipeline.catalog import EnvEntry
from torchrl_softae.pipeline.runs import RunDir, atomic_torch_save

__all__ = ["make_real_env", "episode_seed", "seed_everything", "heldout_set", "normalized_mse", "coverage"]


def make_real_env(entry: EnvEntry, max_steps: int) -> EnvBase:
    """The real env, guarded against faults and truncated at ``max_steps``."""
    return TransformedEnv(GuardedEnv(entry.make()), StepCounter(max_steps=max_steps))


def episode_seed(seed: int, episode: int) -> int:
    return (seed * 1_000_003 + episode * 7919) % (2**31 - 1)


def seed_everything(seed: int) -> None:
    torch.manual_seed(seed)
    np.random.seed(seed % (2**32))
    random.seed(seed)


def _cache_dir() -> Path:
    root = os.environ.get("TORCHRL_SOFTAE_CACHE") or os.path.join(
        os.environ.get("XDG_CACHE_HOME", os.path.expanduser("~/.cache")), "torchrl_softae")
    return Path(root)


def heldout_set(entry: EnvEntry, run: RunDir | None, size: int, seed: int = 12345) -> TensorDictBase:
    """The env's held-out transitions: cached in the run dir and in a per-user cache
    (``$TORCHRL_SOFTAE_CACHE``, default ``~/.cache/torchrl_softae``), since simulators are slow."""
    if run is not None and run.heldout_path.exists():
        td = torch.load(run.heldout_path, weights_only=False)
        if td.shape[0] == size:
            return td
    cached = _cache_dir() / "heldout" / f"{entry.env_id}-v{entry.version}-{size}-{seed}.pt"
    if cached.exists():
        td = torch.load(cached, weights_only=False)
    else:
        td = entry.heldout(size, seed)
        cached.parent.mkdir(parents=True, exist_ok=True)
        atomic_torch_save(td, cached)
    if run is not None:
        atomic_torch_save(td, run.heldout_path)
    return td


@torch.no_grad()
def normalized_mse(model: EnsembleWorldModel, heldout: TensorDictBase, groups: dict | None = None):
    """Next-state MSE of the ensemble mean, each dimension divided by its std over the held-out set
    (a constant dimension counts in its own units). With ``groups`` (name -> dims), returns
    ``(overall, {name: nmse over those dims})``."""
    heldout = heldout.to(model.input_normalizer.loc.device)
    obs, act, nxt = heldout["observation"], heldout["action"], heldout["next", "observation"]
    mu, *_ = model.predict(obs, act)
    std = nxt.std(0)
    std = torch.where(std > 1e-8, std, torch.ones_like(std))
    per_dim = ((mu - nxt) / std).square().mean(0)
    if groups is None:
        return float(per_dim.mean())
    return float(per_dim.mean()), {k: float(per_dim[v].mean()) for k, v in groups.items()}


def coverage(entry: EnvEntry, data: TensorDictBase, bounds: torch.Tensor, bins: int = 20) -> float:
    """Fraction of cells of a ``bins x bins`` grid over the env's projection that the data visits."""
    p = entry.project(data)
    p = p[torch.isfinite(p).all(-1)]
    if p.shape[0] == 0:
        return 0.0
    lo, hi = bounds[0], bounds[1]
    idx = ((p - lo) / (hi - lo) * bins).floor().clamp(0, bins - 1).long()
    cells = torch.unique(idx[:, 0] * bins + idx[:, 1])
    return cells.numel() / bins**2
