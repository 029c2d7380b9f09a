"""Pipeline entry of an env outside the catalog (a gymnasium id, ``module:EnvId-v0``,
``module:callable``): defaults read from the env itself, no tasks of its own (``--task
module:attr``), coverage over the first two state dimensions, and a held-out set of
random-action episodes seeded apart from exploration (or the user's ``--heldout FILE``)."""
from __future__ import annotations

import torch

from torchrl_softae.envs.references import EnvReference, gym_max_episode_steps, resolve_env
from torchrl_softae.pipeline.entries.entry import EnvEntry
from torchrl_softae.references import BadReference
from torchrl_softae.seeding import derive_seed

__all__ = ["entry", "DEFAULT_EPISODE_LENGTH"]

#: the exploration horizon of an env that declares no episode limit
DEFAULT_EPISODE_LENGTH = 200


def _checked_specs(ref: EnvReference) -> tuple:
    """Build one env, run TorchRL's ``check_env_specs`` on it, and check what the pipeline needs: an
    ``"observation"`` vector and a bounded continuous action. Returns ``(observation_spec,
    action_spec, max_episode_steps)``; any failure is one :class:`BadReference` line."""
    from torchrl.data import Bounded
    from torchrl.envs.utils import check_env_specs

    env = ref.make()
    try:
        try:
            check_env_specs(env)
        except Exception as e:
            first = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
            raise BadReference(f"env {ref.text!r} fails TorchRL's check_env_specs: {first}") from None
        obs = env.observation_spec
        if "observation" not in obs.keys() or len(obs["observation"].shape) != 1:
            keys = ", ".join(map(str, obs.keys(True, True)))
            raise BadReference(f"env {ref.text!r} observes {keys}: expected one state vector named 'observation' "
                               "(a gymnasium Box observation, or wrap the env to flatten it)")
        action = env.action_spec
        if not isinstance(action, Bounded) or not action.dtype.is_floating_point or len(action.shape) != 1:
            raise BadReference(f"env {ref.text!r} has the action spec {type(action).__name__}{tuple(action.shape)} "
                               f"{action.dtype}: expected a bounded continuous action vector (the planner samples in its box)")
        return obs.clone(), action.clone(), ref.max_episode_steps or gym_max_episode_steps(env)
    finally:
        env.close()


def _random_heldout(ref: EnvReference, episode_length: int):
    """``(n, seed) -> transitions``: uniform random actions, episodes of ``episode_length`` steps
    seeded ``derive_seed(seed, i)`` (the pipeline's ``seed=12345``; exploration's episodes are
    ``derive_seed(run seed, k)``)."""

    def heldout(n: int, seed: int):
        from torchrl.envs import StepCounter
        from torchrl.envs.utils import RandomPolicy

        env = ref.make().append_transform(StepCounter(max_steps=episode_length))
        policy = RandomPolicy(env.action_spec)
        parts, count, i = [], 0, 0
        try:
            while count < n:
                s = derive_seed(seed, i)
                torch.manual_seed(s)
                env.set_seed(s)
                traj = env.rollout(episode_length, policy, break_when_any_done=True)
                parts.append(traj.select("observation", "action", ("next", "observation")).reshape(-1))
                count += parts[-1].shape[0]
                i += 1
        finally:
            env.close()
        return torch.cat(parts, 0)[:n]

    return heldout


def entry(text: str) -> EnvEntry:
    """The entry of the env ``text`` names (built once to check its specs)."""
    ref = resolve_env(text)
    obs_spec, action_spec, limit = _checked_specs(ref)
    episode_length = limit or DEFAULT_EPISODE_LENGTH
    d_s, d_a = obs_spec["observation"].shape[-1], action_spec.shape[-1]
    if d_s < 2:
        raise BadReference(f"env {text!r} has a {d_s}-dimensional state: the coverage grid needs at least 2 dimensions")
    e = EnvEntry(
        env_id=text,
        make=ref.make,
        tasks={},
        projection=lambda obs: obs[..., :2],
        projection_labels=("observation[0]", "observation[1]"),
        heldout=_random_heldout(ref, episode_length),
        defaults={"episode_length": episode_length},
        description=f"outside env ({d_s}D state, {d_a}D action, episodes of {episode_length} steps"
                    + ("" if limit else ": the env declares no limit, so the default") + ")",
        version=None,  # its physics may change under the same name: held-out sets stay in their run dir
    )
    e._specs = (obs_spec, action_spec)
    return e
