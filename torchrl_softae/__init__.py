"""torchrl_softae: active exploration of soft-robot dynamics (SoftAE) as TorchRL components.

Importing the package registers its gymnasium ids (cheap: simulators load on first ``make``):
``SoftArm-v0`` (58D), ``SoftArm136-v0`` (136D), ``SoftFish-v0`` (15D), ``SoftFishTarget-v0`` (18D),
``MSKLeg-v0`` (10D), ``SoPrA-v0`` (32D, the simulated twin).
"""
__version__ = "0.1.0"


def _register_gym_ids() -> None:
    import gymnasium as gym

    ids = {
        "SoftArm-v0": ("torchrl_softae.envs.soft_arm:SoftArmEnv", {"observed_points": 5}, 200),
        "SoftArm136-v0": ("torchrl_softae.envs.soft_arm:SoftArmEnv", {"observed_points": 11}, 200),
        "SoftFish-v0": ("torchrl_softae.envs.fish:SoftFishEnv", {"with_target": False}, 200),
        "SoftFishTarget-v0": ("torchrl_softae.envs.fish:SoftFishEnv", {"with_target": True}, 200),
        "MSKLeg-v0": ("torchrl_softae.envs.msk_leg:MSKLegEnv", {}, 500),
        "SoPrA-v0": ("torchrl_softae.envs.sopra.env:SoPrAGymEnv", {}, 200),
    }
    for env_id, (entry_point, kwargs, steps) in ids.items():
        if env_id not in gym.registry:
            gym.register(id=env_id, entry_point=entry_point, kwargs=kwargs, max_episode_steps=steps)


_register_gym_ids()
