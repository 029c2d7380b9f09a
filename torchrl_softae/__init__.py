"""torchrl_softae: active exploration of soft-robot dynamics (SoftAE) as TorchRL components.

The library -- :mod:`~torchrl_softae.modules` (ensemble world model, planners),
:mod:`~torchrl_softae.objectives` (loss, training schedule), :mod:`~torchrl_softae.envs` (the
model env, its transforms, and the robots under ``envs.robots``) and :mod:`~torchrl_softae.tasks`
-- never imports :mod:`~torchrl_softae.pipeline` (CLI, configs, runs, sweeps, plots).

Importing the package registers the gymnasium ids of ``torchrl_softae.envs.robots.ENVS`` (cheap:
simulators load on first ``make``): ``SoftArm-v0`` (58D), ``SoftArm136-v0`` (136D),
``SoftFish-v0`` (15D), ``SoftFishTarget-v0`` (18D), ``MSKLeg-v0`` (10D), ``SoPrA-v0`` (32D, the
simulated twin), ``Pendulum-hanging``.

:func:`~torchrl_softae.allocator.keep_freed_memory` (process-wide, so opt-in; the ``softae``
commands call it) spares planners the page faults of glibc handing large tensors back to the kernel.
"""
__version__ = "0.1.0"

from torchrl_softae.allocator import keep_freed_memory  # noqa: F401 (public)
from torchrl_softae.envs.robots import register_gym_ids as _register_gym_ids

_register_gym_ids()
