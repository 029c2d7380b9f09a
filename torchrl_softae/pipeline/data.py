"""What exploration and evaluation share: the guarded real env, per-episode seeds, the held-out
set (cached) and the model-accuracy and coverage metrics."""
from __future__ import annotations

import functools
import os
import random
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch
from tensordict import TensorDictBase
from torchrl.envs import EnvBase, StepCounter, TransformedEnv

from torchrl_softae.envs.guard import GuardedEnv
from torchrl_softae.modules import EnsembleWorldModel
from torchrl_softae.pipeline.entries.entry import EnvEntry
from torchrl_softae.pipeline.runs import RunDir, atomic_torch_save
from torchrl_softae.seeding import derive_seed

__all__ = ["make_real_env", "episode_seed", "load_transitions", "TRANSITION_KEYS", "seed_everything", "global_rng_states", "set_global_rng_states", "heldout_set", "reference_set", "reference_scale",
           "normalized_mse", "trivial_nmse", "legacy_normalized_mse", "coverage", "coverage_counts", "projection_bounds", "COVERAGE_BINS", "ModelAccuracy"]


def make_real_env(entry: EnvEntry, max_steps: int) -> EnvBase:
    """The real env, guarded against faults and truncated at ``max_steps``."""
    return TransformedEnv(GuardedEnv(entry.make()), StepCounter(max_steps=max_steps))


def episode_seed(seed: int, episode: int) -> int:
    """The seed of a run's episode ``episode`` (:func:`~torchrl_softae.seeding.derive_seed`)."""
    return derive_seed(seed, episode)


def seed_everything(seed: int) -> None:
    torch.manual_seed(seed)
    np.random.seed(seed % (2**32))
    random.seed(seed)


def global_rng_states() -> dict:
    """The states of the generators :func:`seed_everything` seeds (torch's, numpy's, Python's),
    as tensors and numbers (``torch.load(weights_only=True)`` reads them back)."""
    kind, keys, pos, has_gauss, gauss = np.random.get_state()
    version, internal, gauss_next = random.getstate()
    return {"torch": torch.get_rng_state(), "numpy": [kind, torch.from_numpy(keys.astype(np.int64)), pos, has_gauss, gauss],
            "python": [version, torch.tensor(internal, dtype=torch.int64), gauss_next]}


def set_global_rng_states(states: dict) -> None:
    """Restore :func:`global_rng_states`."""
    torch.set_rng_state(states["torch"])
    kind, keys, pos, has_gauss, gauss = states["numpy"]
    np.random.set_state((kind, keys.numpy().astype(np.uint32), pos, has_gauss, gauss))
    version, internal, gauss_next = states["python"]
    random.setstate((version, tuple(internal.tolist()), gauss_next))


def _cache_dir() -> Path:
    root = os.environ.get("TORCHRL_SOFTAE_CACHE") or os.path.join(
        os.environ.get("XDG_CACHE_HOME", os.path.expanduser("~/.cache")), "torchrl_softae")
    return Path(root)


def _cached(entry: EnvEntry, kind: str, make, size: int, seed: int, run: RunDir | None,
            announce: Callable[[str], None] | None = None) -> TensorDictBase:
    """``make(size, seed)``, cached in the run dir and in a per-user cache (``$TORCHRL_SOFTAE_CACHE``,
    default ``~/.cache/torchrl_softae``), keyed by env, physics version, size and seed: simulators
    are slow, and runs of another physics version never share a set. ``announce`` gets one line
    before and one after a build (the arm's held-out set takes minutes)."""
    name = f"{entry.env_id.replace(':', '-').replace('/', '-')}-v{entry.version}-{kind}-{size}-{seed}.pt"
    local = None if run is None else run.path / name
    if local is not None and local.exists():
        return torch.load(local, weights_only=False)
    cached = _cache_dir() / kind / name
    if entry.version is not None and cached.exists():
        td = torch.load(cached, weights_only=False)
    else:
        if announce is not None:
            announce(f"building the {kind} set of {entry.env_id} (size {size}, seed {seed}) once; "
                     + (f"later runs read {cached}" if entry.version is not None else "the run dir keeps it"))
        t0 = time.perf_counter()
        td = make(size, seed)
        if announce is not None:
            announce(f"{kind} set built: {td.shape[0]} transitions in {time.perf_counter() - t0:.0f} s")
        if entry.version is not None:
            cached.parent.mkdir(parents=True, exist_ok=True)
            atomic_torch_save(td, cached)
    if local is not None:
        atomic_torch_save(td, local)
    return td


def heldout_set(entry: EnvEntry, run: RunDir | None, size: int, seed: int = 12345,
                announce: Callable[[str], None] | None = None) -> TensorDictBase:
    """The env's held-out transitions (``entry.heldout``), cached; or all of the user's
    ``entry.heldout_file``, copied into the run dir at first use (the run keeps what it measured on)."""
    if entry.heldout_file is None:
        return _cached(entry, "heldout", entry.heldout, size, seed, run, announce)
    local = None if run is None else run.path / "heldout-file.pt"
    if local is not None and local.exists():
        return torch.load(local, weights_only=False)
    obs_spec, action_spec = entry.specs()
    td = load_transitions(entry.heldout_file, obs_spec["observation"].shape[-1], action_spec.shape[-1])
    if local is not None:
        atomic_torch_save(td, local)
    return td


#: the entries a file of transitions must hold (``--heldout FILE``)
TRANSITION_KEYS = ("observation", "action", ("next", "observation"))


def load_transitions(path: str | Path, state_dim: int, action_dim: int) -> TensorDictBase:
    """Transitions from ``path`` (a TensorDict saved with ``torch.save``, or a memmap directory
    written by ``TensorDict.memmap``), flattened to ``(N,)`` and cast to float32; a ValueError
    names what is missing or mis-shaped. Read once per process while the file is unchanged: a run
    validates its config and measures on the same file."""
    path = Path(path)
    if not path.exists():
        raise ValueError(f"--heldout {str(path)!r}: no such file or directory")
    stat = path.stat()
    return _load_transitions(path.resolve(), stat.st_mtime_ns, stat.st_size, state_dim, action_dim)


@functools.lru_cache(maxsize=4)
def _load_transitions(path: Path, mtime_ns: int, size: int, state_dim: int, action_dim: int) -> TensorDictBase:
    from tensordict import TensorDict

    try:
        td = TensorDict.load_memmap(path) if path.is_dir() else torch.load(path, weights_only=False)
    except Exception as e:  # noqa: BLE001 (any unreadable file is the same one-line error)
        raise ValueError(f"--heldout {str(path)!r}: cannot read it ({type(e).__name__}: {e}); expected a TensorDict "
                         "saved with torch.save or a memmap directory") from None
    if not isinstance(td, TensorDictBase):
        raise ValueError(f"--heldout {str(path)!r} holds a {type(td).__name__}: expected a TensorDict with "
                         "observation, action and ('next', 'observation')")
    if td.batch_dims == 0:  # saved without a batch size: the leading dimension is the transitions'
        td = td.auto_batch_size_(batch_dims=1)
    want = {"observation": state_dim, "action": action_dim, ("next", "observation"): state_dim}
    for key, dim in want.items():
        if key not in td.keys(True):
            raise ValueError(f"--heldout {str(path)!r} has no {key!r} entry: expected observation, action and "
                             "('next', 'observation')")
        shape = tuple(td.get(key).shape[td.batch_dims:])
        if shape != (dim,):
            raise ValueError(f"--heldout {str(path)!r}: {key!r} has per-transition shape {shape}, expected ({dim},) "
                             "for this env")
    out = td.select(*TRANSITION_KEYS).reshape(-1).to_tensordict()
    if out.shape[0] == 0:
        raise ValueError(f"--heldout {str(path)!r} holds no transitions")
    return out.apply(lambda x: x.float())


def reference_set(entry: EnvEntry, run: RunDir | None, heldout: TensorDictBase, seed: int = 54321,
                  announce: Callable[[str], None] | None = None) -> TensorDictBase:
    """The fixed, broad set whose per-dimension std normalizes the model error: the held-out set,
    plus as many of the env's extra reference transitions where it has some (the arm: i.i.d.
    random-action motion, so that dimensions the reaching rollouts barely move -- twist, axial
    velocity -- are not divided by ~0, while the positions keep the workspace's spread)."""
    if entry.reference is None:
        return heldout
    extra = _cached(entry, "reference", entry.reference, heldout.shape[0], seed, run, announce)[: heldout.shape[0]]
    keys = ["observation", "action", ("next", "observation")]
    return torch.cat([heldout.select(*keys), extra.select(*keys)], 0)


def reference_scale(reference: TensorDictBase, eps: float = 1e-6) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """``(mean, std, kept)`` of the reference next states: population statistics per dimension,
    ``kept`` excludes the constant dimensions (std <= eps), which carry no information."""
    nxt = reference["next", "observation"]
    std = nxt.std(0, unbiased=False)
    return nxt.mean(0), std, std > eps


def _nmse_report(pred: torch.Tensor, heldout: TensorDictBase, scale, groups: dict | None):
    mean, std, kept = (x.to(pred.device) for x in scale)
    nxt = heldout["next", "observation"]
    per_dim = ((pred - nxt) / torch.where(kept, std, torch.ones_like(std))).square().mean(0)
    overall = float(per_dim[kept].mean())
    if groups is None:
        return overall
    out = {}
    for name, dims in groups.items():
        dims = torch.as_tensor(dims, device=per_dim.device)
        dims = dims[kept[dims]]
        out[name] = float(per_dim[dims].mean()) if dims.numel() else float("nan")
    return overall, out


@torch.no_grad()
def normalized_mse(model: EnsembleWorldModel, heldout: TensorDictBase, groups: dict | None = None, scale=None):
    """Held-out next-state MSE of the ensemble mean, per dimension divided by the variance of a
    fixed reference set (``scale`` from :func:`reference_scale`; default the held-out set itself),
    constant dimensions excluded, averaged over dimensions. With ``groups`` (name -> dims), returns
    ``(overall, {name: nmse over those dims})``. Predicting the reference mean on the reference set
    scores 1.0."""
    heldout = heldout.to(model.input_normalizer.loc.device)
    mu, *_ = model.predict(heldout["observation"], heldout["action"])
    return _nmse_report(mu, heldout, scale if scale is not None else reference_scale(heldout), groups)


def trivial_nmse(heldout: TensorDictBase, scale, groups: dict | None = None) -> dict:
    """The same metric for two predictors that know nothing: ``s' = s`` and the reference mean."""
    obs = heldout["observation"]
    mean = scale[0].to(obs.device).expand_as(obs)
    return {"identity": _nmse_report(obs, heldout, scale, groups), "mean": _nmse_report(mean, heldout, scale, groups)}


@torch.no_grad()
def legacy_normalized_mse(model: EnsembleWorldModel, heldout: TensorDictBase) -> float:
    """The metric before the reference set (kept so old numbers stay comparable): each dimension
    divided by its own sample std over the held-out set, a constant dimension in its own units."""
    heldout = heldout.to(model.input_normalizer.loc.device)
    obs, act, nxt = heldout["observation"], heldout["action"], heldout["next", "observation"]
    mu, *_ = model.predict(obs, act)
    std = nxt.std(0)
    std = torch.where(std > 1e-8, std, torch.ones_like(std))
    return float(((mu - nxt) / std).square().mean())


#: cells per axis of the coverage grid (the ``coverage`` in every run's history)
COVERAGE_BINS = 20


def projection_bounds(entry: EnvEntry, heldout: TensorDictBase) -> torch.Tensor:
    """``(2, 2)``: low and high corners of the coverage grid, the held-out set's projection padded
    by 5 % (fixed per env, so every run of the env is binned on the same grid)."""
    p = entry.project(heldout)
    lo, hi = p.min(0).values, p.max(0).values
    pad = 0.05 * (hi - lo).clamp_min(1e-6)
    return torch.stack([lo - pad, hi + pad])


def coverage_counts(entry: EnvEntry, data: TensorDictBase, bounds: torch.Tensor, bins: int = COVERAGE_BINS) -> torch.Tensor:
    """``(bins, bins)`` int64: transitions per cell of a grid over the env's projection between
    ``bounds`` (axis 0 the projection's first coordinate); points outside count in the edge cells."""
    p = entry.project(data)
    p = p[torch.isfinite(p).all(-1)]
    lo, hi = bounds[0], bounds[1]
    idx = ((p - lo) / (hi - lo) * bins).floor().clamp(0, bins - 1).long()
    return torch.bincount(idx[:, 0] * bins + idx[:, 1], minlength=bins * bins).reshape(bins, bins)


def coverage(entry: EnvEntry, data: TensorDictBase, bounds: torch.Tensor, bins: int = COVERAGE_BINS) -> float:
    """Fraction of cells of a ``bins x bins`` grid over the env's projection that the data visits."""
    return int((coverage_counts(entry, data, bounds, bins) > 0).sum()) / bins**2


class ModelAccuracy:
    """The held-out metric of one env, set up once per run: ``accuracy(model)`` returns the row
    ``{"heldout_nmse": ..., "heldout_nmse/GROUP": ..., "heldout_nmse_legacy": ...}``;
    :attr:`baselines` holds the same metric for ``s' = s`` and the reference mean. ``announce``
    gets a line where a set is built rather than read from the cache."""

    def __init__(self, entry: EnvEntry, run: RunDir | None, size: int, announce: Callable[[str], None] | None = None):
        self.entry = entry
        self.heldout = heldout_set(entry, run, size, announce=announce)
        self.scale = reference_scale(reference_set(entry, run, self.heldout, announce=announce))
        self.groups = entry.accuracy_groups
        self.baselines = {}
        for name, (overall, groups) in trivial_nmse(self.heldout, self.scale, self.groups).items():
            self.baselines[f"heldout_nmse_{name}"] = overall
            self.baselines.update({f"heldout_nmse_{name}/{k}": v for k, v in groups.items()})

    def __call__(self, model: EnsembleWorldModel) -> dict:
        overall, groups = normalized_mse(model, self.heldout, self.groups, self.scale)
        return {"heldout_nmse": overall, **{f"heldout_nmse/{k}": v for k, v in groups.items()},
                "heldout_nmse_legacy": legacy_normalized_mse(model, self.heldout)}
