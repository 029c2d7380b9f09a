"""The robots (simulators and the real SoPrA), and the one list of environments.

``ENVS`` is the single place an environment is declared: ``torchrl_softae`` registers the
gymnasium ids from it at import (no simulator is loaded until ``gym.make``), and the pipeline's
catalog builds its entries from it. Adding an env = its simulator module, its tasks in
:mod:`torchrl_softae.tasks`, and one record here.

Nothing in this module imports a simulator or torch: importing the package stays cheap.
"""
from __future__ import annotations

from dataclasses import dataclass, field

__all__ = ["EnvRecord", "ENVS", "get_record", "register_gym_ids"]


@dataclass(frozen=True)
class EnvRecord:
    """One environment.

    Args:
        env_id: the id used by gymnasium, ``torchrl.envs.GymEnv`` and ``softae --env``.
        family: the robot (``soft_arm``, ``fish``, ``leg``, ``sopra``, ``pendulum``, ``cartpole``);
            names its task module ``torchrl_softae.tasks.FAMILY``.
        entry_point: ``"module:callable"`` of the gymnasium env, or ``None`` where the id is not
            ours to register (gymnasium's own Pendulum-v1, dm_control's cartpole).
        kwargs: keyword arguments of the entry point; the family's ``tasks(**kwargs)`` gets them too.
        max_episode_steps: the exploration horizon T (Table S6).
    """

    env_id: str
    family: str
    entry_point: str | None
    kwargs: dict = field(default_factory=dict)
    max_episode_steps: int = 200


ENVS: tuple[EnvRecord, ...] = (
    EnvRecord("SoftArm-v0", "soft_arm", "torchrl_softae.envs.robots.soft_arm:SoftArmEnv", {"observed_points": 5}, 200),
    EnvRecord("SoftArm136-v0", "soft_arm", "torchrl_softae.envs.robots.soft_arm:SoftArmEnv", {"observed_points": 11}, 200),
    # v1: 100 ms control period (H = 10 spans the step response), targets (ii) that need coordinated
    # bending, reach-any, and the workspace-volume held-out set
    EnvRecord("SoftArm-v1", "soft_arm", "torchrl_softae.envs.robots.soft_arm:SoftArmEnv",
              {"observed_points": 5, "control_period": 0.1, "target_set": "v1"}, 200),
    EnvRecord("SoftArm136-v1", "soft_arm", "torchrl_softae.envs.robots.soft_arm:SoftArmEnv",
              {"observed_points": 11, "control_period": 0.1, "target_set": "v1"}, 200),
    EnvRecord("SoftFish-v0", "fish", "torchrl_softae.envs.robots.fish:SoftFishEnv", {"with_target": False}, 200),
    EnvRecord("SoftFishTarget-v0", "fish", "torchrl_softae.envs.robots.fish:SoftFishEnv", {"with_target": True}, 200),
    EnvRecord("MSKLeg-v0", "leg", "torchrl_softae.envs.robots.msk_leg:MSKLegEnv", {}, 500),
    EnvRecord("SoPrA-v0", "sopra", "torchrl_softae.envs.robots.sopra.env:SoPrAGymEnv", {}, 200),
    EnvRecord("Pendulum-v1", "pendulum", None, {}, 200),
    EnvRecord("Pendulum-hanging", "pendulum", "torchrl_softae.envs.robots.classic:make_hanging_pendulum", {}, 200),
    EnvRecord("cartpole-swingup", "cartpole", None, {}, 200),
)

_BY_ID = {r.env_id: r for r in ENVS}


def get_record(env_id: str) -> EnvRecord:
    """The record of ``env_id``, or a ValueError listing the valid ids."""
    try:
        return _BY_ID[env_id]
    except KeyError:
        raise ValueError(f"unknown env {env_id!r}; valid envs: {', '.join(sorted(_BY_ID))}") from None


def register_gym_ids() -> None:
    """Register every record that has an entry point with gymnasium (idempotent)."""
    import gymnasium as gym

    for r in ENVS:
        if r.entry_point is not None and r.env_id not in gym.registry:
            gym.register(id=r.env_id, entry_point=r.entry_point, kwargs=dict(r.kwargs),
                         max_episode_steps=r.max_episode_steps)
