"""Typed run configuration with the paper's defaults (Tables S6, S7), per-env overrides and validation."""
from __future__ import annotations

import dataclasses
import json
from dataclasses import asdict, dataclass, field
from typing import Any

__all__ = [
    "METHODS",
    "DEFAULT_BETA",
    "ModelConfig",
    "TrainConfig",
    "PlannerConfig",
    "PolicyConfig",
    "ExploreConfig",
    "ConfigError",
    "make_config",
    "apply_overrides",
    "flat_config",
]

from torchrl_softae.modules.engine.kernels import KERNEL_CHOICES
from torchrl_softae.modules.planners.contract import PLANNING_PRECISIONS
from torchrl_softae.objectives.training import TRAINING_PRECISIONS
from torchrl_softae.envs.transforms.hallucinated_control import DEFAULT_BETA
from torchrl_softae.pipeline.methods import METHOD_NAMES as METHODS, get_method


class ConfigError(ValueError):
    """A configuration value is invalid; the message names it and the valid options."""


@dataclass
class ModelConfig:
    """Ensemble world model [L, 4 x 256] (Table S6)."""

    ensemble_size: int = 5
    num_cells: int = 256
    depth: int = 4
    probabilistic: bool = True
    symlog: bool = False  # model the state in symlog space (on in the MBPO presets)
    kernels: str = "auto"  # "torch": never our compiled kernels (EnsembleWorldModel(kernels=...))


@dataclass
class TrainConfig:
    """Training schedule after every episode (Table S6)."""

    lr: float = 5e-5
    batch_size: int = 64
    epochs: int = 50
    max_grad_steps: int = 5000
    val_fraction: float = 0.1
    # the network's matmuls: bf16 where it measures faster here (EnsembleTrainer's precision)
    precision: str = "auto"


@dataclass
class PlannerConfig:
    """iCEM settings (Table S7)."""

    horizon: int = 10
    num_candidates: int = 200
    top_k: int = 20
    optim_steps: int = 5
    num_particles: int = 10
    noise_beta: float = 0.25
    elite_fraction: float = 0.3
    precision: str = "fp32"
    time_budget: float | None = None


@dataclass
class PolicyConfig:
    """SAC on the learned model (MBPO). Table S8: networks 3 x 1024, batch 256, lr 3e-4, rollout
    horizon 5; the rest is MBPO's (Janner et al. 2019), our choice where the paper is silent."""

    num_cells: int = 1024
    depth: int = 3
    batch_size: int = 256
    lr: float = 3e-4
    gamma: float = 0.99
    tau: float = 0.005
    rollout_horizon: int = 5
    rollout_batch: int = 400  # real start states per rollout round
    updates_per_rollout: int = 20  # SAC updates between rollout rounds
    updates_per_step: int = 20  # SAC updates per real transition (MBPO's G)
    real_ratio: float = 0.05
    imagined_capacity: int = 200_000

    def rounds(self, updates: int) -> int:
        """Rollout rounds that give ``updates`` SAC updates (rounded up)."""
        return -(-updates // self.updates_per_rollout)


@dataclass
class ExploreConfig:
    """One exploration run (``softae explore``).

    ``env``: a catalog id, a registered gymnasium id, ``module:EnvId-v0`` or ``module:callable``;
    ``task``: one of the env's tasks or ``module:attr``; ``method``: a name of
    :data:`torchrl_softae.pipeline.methods.METHODS`; ``beta`` matters only for methods that use it.
    """

    env: str = "Pendulum-v1"
    method: str = "softae"
    episodes: int = 10
    seed: int = 0
    episode_length: int = 200
    beta: float = DEFAULT_BETA
    task: str | None = None
    normalize_uncertainty: bool = True
    heldout_size: int = 2000
    heldout_file: str | None = None  # the user's held-out transitions (--heldout FILE) instead of the env's set
    coverage_dims: str | None = None  # "I,J": the state dimensions of the coverage grid (default: the env's)
    eval_every: int = 0
    eval_episodes: int = 1
    wandb: str = "offline"
    model: ModelConfig = field(default_factory=ModelConfig)
    train: TrainConfig = field(default_factory=TrainConfig)
    planner: PlannerConfig = field(default_factory=PlannerConfig)
    policy: PolicyConfig = field(default_factory=PolicyConfig)

    # ------------------------------------------------------------------ (de)serialization
    def to_dict(self) -> dict:
        return asdict(self)

    def to_json(self) -> str:
        return json.dumps(self.to_dict(), indent=1, sort_keys=True)

    @classmethod
    def from_dict(cls, d: dict) -> "ExploreConfig":
        d = dict(d)
        sub = {"model": ModelConfig, "train": TrainConfig, "planner": PlannerConfig, "policy": PolicyConfig}
        for k, t in sub.items():
            if k in d:
                d[k] = t(**d[k])
        return cls(**d)

    # ------------------------------------------------------------------ validation
    def validate(self) -> "ExploreConfig":
        """Check every field (types, ranges, names); a :class:`ConfigError` names the first bad one."""
        from torchrl_softae.pipeline.catalog import get_env_entry, get_task, run_entry
        from torchrl_softae.pipeline.data import load_transitions

        _check_types(self)
        try:
            entry = get_env_entry(self.env)
            method = get_method(self.method)
            task = None if self.task is None else get_task(entry, self.task)
            if self.heldout_file is not None or self.coverage_dims is not None:
                obs_spec, action_spec = run_entry(self).specs()
            if self.heldout_file is not None:
                load_transitions(self.heldout_file, obs_spec["observation"].shape[-1], action_spec.shape[-1])
        except ValueError as e:
            raise ConfigError(str(e)) from None
        tasks = sorted(entry.tasks)
        if method.needs_task and self.task is None:
            choices = f"one of {', '.join(tasks)}, or module:attr" if tasks else "module:attr naming your Task"
            raise ConfigError(f"method {method.name!r} optimizes a task reward: pass --task, {choices}")
        positive = {
            "episodes": self.episodes, "episode_length": self.episode_length, "heldout_size": self.heldout_size,
            "eval_episodes": self.eval_episodes,
            "model.ensemble_size": self.model.ensemble_size - 1, "model.num_cells": self.model.num_cells,
            "model.depth": self.model.depth, "train.batch_size": self.train.batch_size,
            "train.epochs": self.train.epochs, "train.max_grad_steps": self.train.max_grad_steps,
            "train.lr": self.train.lr, "planner.horizon": self.planner.horizon,
            "planner.num_candidates": self.planner.num_candidates, "planner.top_k": self.planner.top_k,
            "planner.optim_steps": self.planner.optim_steps, "planner.num_particles": self.planner.num_particles,
            **{f"policy.{k}": getattr(self.policy, k) for k in (
                "num_cells", "depth", "batch_size", "lr", "gamma", "tau", "rollout_horizon", "rollout_batch",
                "updates_per_rollout", "updates_per_step", "imagined_capacity")},
        }
        for k, v in positive.items():
            if not v > 0:
                shown = v + 1 if k == "model.ensemble_size" else v
                extra = " (at least 2 members)" if k == "model.ensemble_size" else ""
                raise ConfigError(f"{k}={shown!r} is invalid: expected a positive value{extra}")
        if self.planner.top_k > self.planner.num_candidates:
            raise ConfigError(f"planner.top_k={self.planner.top_k} exceeds planner.num_candidates={self.planner.num_candidates}")
        if not self.beta >= 0:
            raise ConfigError(f"beta={self.beta!r} is invalid: expected >= 0")
        if self.eval_every < 0:
            raise ConfigError(f"eval_every={self.eval_every!r} is invalid: expected >= 0 (0 = never)")
        if self.wandb not in ("offline", "online", "disabled"):
            raise ConfigError(f"wandb={self.wandb!r}; valid: offline, online, disabled")
        if self.planner.precision not in PLANNING_PRECISIONS:
            raise ConfigError(f"planner.precision={self.planner.precision!r}; valid: {', '.join(PLANNING_PRECISIONS)}")
        if self.planner.time_budget is not None and not self.planner.time_budget > 0:
            raise ConfigError(f"planner.time_budget={self.planner.time_budget!r} is invalid: expected seconds > 0, "
                              "or none for no deadline")
        if not 0 <= self.planner.elite_fraction <= 1:
            raise ConfigError(f"planner.elite_fraction={self.planner.elite_fraction!r}; expected in [0, 1]")
        if self.planner.noise_beta < 0:
            raise ConfigError(f"planner.noise_beta={self.planner.noise_beta!r}; expected >= 0")
        if not 0 <= self.policy.real_ratio <= 1:
            raise ConfigError(f"policy.real_ratio={self.policy.real_ratio!r}; expected in [0, 1]")
        if not 0 < self.policy.gamma <= 1 or not 0 < self.policy.tau <= 1:
            raise ConfigError(f"policy.gamma={self.policy.gamma!r} and policy.tau={self.policy.tau!r}: expected in (0, 1]")
        if method.needs_task and task is not None and task.instantiate is not None:
            # the family's own reward is a placeholder: only its per-episode tasks have a target
            raise ConfigError(f"task {self.task!r} is a family of targets (one per evaluation episode): "
                              f"{self.method} explores on one fixed task "
                              f"(choose one of {', '.join(t for t in tasks if entry.tasks[t].instantiate is None)})")
        if self.model.kernels not in KERNEL_CHOICES:
            raise ConfigError(f"model.kernels={self.model.kernels!r}; valid: {', '.join(KERNEL_CHOICES)}")
        if self.train.precision not in TRAINING_PRECISIONS:
            raise ConfigError(f"train.precision={self.train.precision!r}; valid: {', '.join(TRAINING_PRECISIONS)}")
        if not 0 <= self.train.val_fraction < 1:
            raise ConfigError(f"train.val_fraction={self.train.val_fraction!r}; expected in [0, 1)")
        return self


def _flatten(d: dict, prefix: str = "") -> dict:
    out = {}
    for k, v in d.items():
        out.update(_flatten(v, f"{prefix}{k}.") if isinstance(v, dict) else {f"{prefix}{k}": v})
    return out


def flat_config(config: dict) -> dict:
    """A run's stored config as flat ``section.key`` items, with every field added since it was
    written at its default: what the run ran with. Runs from before a new field (e.g. ``model.symlog``)
    compare equal to new runs at its default, on resume and in tables."""
    return {**_flatten(ExploreConfig().to_dict()), **_flatten(config)}


def _check_types(cfg: Any, prefix: str = "") -> None:
    """Every field holds a value of its annotated type (an int is accepted for a float)."""
    for f in dataclasses.fields(cfg):
        v = getattr(cfg, f.name)
        if dataclasses.is_dataclass(v):
            _check_types(v, prefix + f.name + ".")
            continue
        kinds = {"int": (int,), "float": (int, float), "str": (str,), "bool": (bool,)}
        ann = str(f.type).replace(" ", "")
        optional = ann.endswith("|None")
        want = kinds.get(ann[: -len("|None")] if optional else ann)
        if want is None or (optional and v is None):
            continue
        if not isinstance(v, want) or (isinstance(v, bool) and bool not in want):
            expected = {"int": "an integer", "float": "a number", "str": "a string", "bool": "true or false"}[
                ann[: -len("|None")] if optional else ann]
            raise ConfigError(f"{prefix}{f.name}={v!r} is invalid: expected {expected}" + (" or none" if optional else ""))


def _merge(target: Any, overrides: dict, prefix: str = "") -> None:
    names = {f.name: f for f in dataclasses.fields(target)}
    for k, v in overrides.items():
        if k not in names:
            raise ConfigError(f"unknown config key {prefix + k!r}; valid keys: {', '.join(prefix + n for n in names)}")
        cur = getattr(target, k)
        if dataclasses.is_dataclass(cur):
            if not isinstance(v, dict):
                raise ConfigError(f"{prefix + k} is a section; set its fields as {prefix + k}.FIELD=VALUE")
            _merge(cur, v, prefix + k + ".")
        else:
            setattr(target, k, v)


def _parse_value(text: str, current: Any) -> Any:
    if isinstance(current, bool):
        if text.lower() in ("1", "true", "yes", "on"):
            return True
        if text.lower() in ("0", "false", "no", "off"):
            return False
        raise ConfigError(f"expected a boolean, got {text!r}")
    if text.lower() in ("none", "null"):
        return None
    if isinstance(current, int):
        try:
            return int(text)
        except ValueError:
            raise ConfigError(f"expected an integer, got {text!r}") from None
    if isinstance(current, float) or current is None:
        try:
            return float(text)
        except ValueError:
            if current is None:
                return text  # an optional string field (task); _check_types refuses it elsewhere
            raise ConfigError(f"expected a number, got {text!r}") from None
    return text


def apply_overrides(cfg: ExploreConfig, assignments: list[str]) -> ExploreConfig:
    """Apply ``KEY=VALUE`` strings (``planner.horizon=5``, ``train.lr=1e-4``) to ``cfg`` in place."""
    for item in assignments:
        if "=" not in item:
            raise ConfigError(f"override {item!r} must look like KEY=VALUE (e.g. planner.horizon=5)")
        key, text = item.split("=", 1)
        parts = key.strip().split(".")
        obj = cfg
        for p in parts[:-1]:
            if not hasattr(obj, p) or not dataclasses.is_dataclass(getattr(obj, p)):
                raise ConfigError(f"unknown config section {p!r} in {key!r}; sections: model, train, planner, policy")
            obj = getattr(obj, p)
        leaf = parts[-1]
        if leaf not in {f.name for f in dataclasses.fields(obj)}:
            valid = ", ".join(f.name for f in dataclasses.fields(obj))
            raise ConfigError(f"unknown config key {key!r}; valid keys here: {valid}")
        try:
            setattr(obj, leaf, _parse_value(text.strip(), getattr(obj, leaf)))
        except ConfigError as e:
            raise ConfigError(f"{key}: {e}") from None
    return cfg


def make_config(env: str, method: str = "softae", overrides: list[str] | None = None, **fields) -> ExploreConfig:
    """Paper defaults, then the env's defaults, then explicit ``fields``, then ``KEY=VALUE`` overrides."""
    from torchrl_softae.pipeline.catalog import get_env_entry

    cfg = ExploreConfig(env=env, method=method)
    try:
        entry = get_env_entry(env)
    except ValueError as e:
        raise ConfigError(str(e)) from None
    _merge(cfg, entry.defaults)
    _merge(cfg, {k: v for k, v in fields.items() if v is not None})
    apply_overrides(cfg, overrides or [])
    return cfg.validate()
