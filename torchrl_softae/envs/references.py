"""Any env by name: a registered gymnasium id, ``module:EnvId-v0`` or ``module:callable``, as a
TorchRL env with float32 observations and actions.

    >>> from torchrl_softae.envs.references import make_env
    >>> env = make_env("Reacher-v5")            # gymnasium's MuJoCo reacher, float64 -> float32
    >>> env.observation_spec["observation"].dtype
    torch.float32

``module:EnvId-v0`` imports ``module`` (which registers the id with gymnasium), as
``gymnasium.make`` does; ``module:callable`` calls ``module.callable()``, which returns a gymnasium
env or a TorchRL :class:`~torchrl.envs.EnvBase`.
"""
from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import torch

from torchrl_softae.references import BadReference, import_reference_module, split_reference

__all__ = ["EnvReference", "resolve_env", "make_env", "float32_env", "gym_max_episode_steps"]

FORMS = "a registered gymnasium id (e.g. Reacher-v5), module:EnvId-v0 or module:callable"


@dataclass(frozen=True)
class EnvReference:
    """An env named by ``text``: a gymnasium id (``gym_id``) or a zero-argument ``factory``.

    ``max_episode_steps``: gymnasium's registered episode limit, where the id has one."""

    text: str
    gym_id: str | None = None
    factory: Callable[[], object] | None = None
    max_episode_steps: int | None = None

    def make(self):
        """A new TorchRL env (float32 observations and actions, :func:`float32_env`)."""
        from torchrl.envs import GymEnv

        if self.gym_id is not None:
            return float32_env(GymEnv(self.gym_id))
        try:
            made = self.factory()
        except Exception as e:  # the user's factory failed: one line naming it
            raise BadReference(f"env {self.text!r}: calling it raised {type(e).__name__}: {e}") from None
        return float32_env(as_torchrl_env(made, self.text))


def as_torchrl_env(obj, text: str = "env"):
    """A TorchRL env from a gymnasium env (wrapped) or a TorchRL env (as is)."""
    import gymnasium as gym
    from torchrl.envs import EnvBase, GymWrapper

    if isinstance(obj, EnvBase):
        return obj
    if isinstance(obj, gym.Env):
        return GymWrapper(obj)
    raise BadReference(f"env {text!r} gave a {type(obj).__name__}: expected a gymnasium.Env or a TorchRL EnvBase")


def float32_env(env):
    """``env``, behind TorchRL's ``DoubleToFloat`` where any observation or action entry is float64
    (gymnasium's MuJoCo envs): the world model and the planners compute in float32."""
    from torchrl.envs import DoubleToFloat, TransformedEnv

    specs = (env.full_observation_spec, env.full_action_spec, env.full_state_spec)
    if any(leaf.dtype == torch.float64 for spec in specs for leaf in spec.values(True, True)):
        return TransformedEnv(env, DoubleToFloat())
    return env


def gym_max_episode_steps(env) -> int | None:
    """The episode limit of a TorchRL env that wraps a gymnasium env with a registered spec."""
    base = getattr(env, "base_env", env)
    spec = getattr(getattr(base, "_env", None), "spec", None)
    return getattr(spec, "max_episode_steps", None)


def _registered(gym_id: str):
    import gymnasium as gym

    try:
        return gym.spec(gym_id)
    except gym.error.Error:
        return None


def resolve_env(text: str) -> EnvReference:
    """The env ``text`` names (imports its module; builds nothing), or a :class:`BadReference`."""
    parts = split_reference(text)
    if parts is None:
        spec = _registered(text)
        if spec is None:
            raise BadReference(f"unknown env {text!r}: expected {FORMS}")
        return EnvReference(text, gym_id=text, max_episode_steps=spec.max_episode_steps)
    module_name, attr = parts
    module = import_reference_module(module_name, text)
    if attr.isidentifier() and hasattr(module, attr):
        factory = getattr(module, attr)
        if not callable(factory):
            raise BadReference(f"env {text!r} is a {type(factory).__name__}: expected a callable returning an env, "
                               "or a gymnasium id the module registers")
        return EnvReference(text, factory=factory)
    spec = _registered(attr)  # gymnasium's module:EnvId form: importing the module registered the id
    if spec is None:
        raise BadReference(f"env {text!r}: module {module_name!r} has no attribute {attr!r} and registers no "
                           f"gymnasium id {attr!r}; expected module:EnvId-v0 or module:callable")
    return EnvReference(text, gym_id=attr, max_episode_steps=spec.max_episode_steps)


def make_env(text: str):
    """``resolve_env(text).make()``: a new TorchRL env with float32 observations and actions."""
    return resolve_env(text).make()
