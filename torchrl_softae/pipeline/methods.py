"""The exploration methods, one record each: the table every part of the pipeline reads (CLI
choices, config validation, run-dir names, sweeps, evaluation).

Adding a method = one :class:`Method` record in :data:`METHODS` (+ its code where it needs new
behaviour, e.g. a new policy builder). Importing it is cheap (no torch), so ``softae --help``
lists the methods instantly.
"""
from __future__ import annotations

from dataclasses import dataclass

__all__ = ["Method", "METHODS", "METHOD_NAMES", "get_method"]


@dataclass(frozen=True)
class Method:
    """One way to collect data.

    Args:
        name: the ``--method`` value.
        propagation: the model env's mode while planning or imagining (one of
            :data:`torchrl_softae.envs.model_env.PROPAGATION_MODES`; a test checks it), or
            ``None`` for methods that do not use the model to act (random actions).
        reward: what the planner maximizes while exploring: ``"uncertainty"`` (||sigma||, no
            task), ``"task"`` (the ``--task`` reward) or ``None``.
        uses_beta: plans with hallucinated control of width beta (so beta is part of its identity).
        description: one line for ``--help`` and reports.
        trains_policy: collects with a SAC policy trained on the model for the task after every
            episode (MBPO) instead of planning.
    """

    name: str
    propagation: str | None
    reward: str | None
    uses_beta: bool
    description: str
    trains_policy: bool = False

    @property
    def needs_task(self) -> bool:
        return self.reward == "task"

    @property
    def ignored_settings(self) -> frozenset[str]:
        """Run settings that do not change what this method does: beta where it plans without
        hallucinated control, the task where it optimizes none. A sweep runs one trial, not one
        per value, and tables do not set its runs apart by them."""
        ignored = set() if self.uses_beta else {"beta"}
        return frozenset(ignored if self.needs_task else ignored | {"task"})

    @property
    def policy_propagation(self) -> str:
        """The propagation of task policies trained on its model (``softae policy``): its own where
        it trains one (MBPO-TS samples), else the mean."""
        return self.propagation if self.trains_policy else "mean"

    def run_name(self, seed: int, beta: float) -> str:
        """The run dir's name under ``ROOT/ENV/``: beta only where it changes the method."""
        return f"{self.name}-b{beta:g}-s{seed}" if self.uses_beta else f"{self.name}-s{seed}"


METHODS: dict[str, Method] = {m.name: m for m in (
    Method("random", None, None, False, "uniform random actions (the paper's baseline)"),
    Method("mean-ae", "mean", "uncertainty", False, "iCEM on the ensemble mean, reward ||sigma|| (Mean-AE)"),
    Method("pets-ae", "sample", "uncertainty", False, "iCEM with trajectory sampling, reward ||sigma|| (PETS-AE)"),
    Method("hucrl", "optimistic", "task", True, "iCEM with hallucinated control on a task reward (H-UCRL; needs --task)"),
    Method("mbpo", "mean", "task", False, "SAC on mean-model rollouts of the task, collects with it (MBPO; needs --task)",
           trains_policy=True),
    Method("mbpo-ts", "sample", "task", False,
           "SAC on trajectory-sampled model rollouts of the task, collects with it (MBPO-TS; needs --task)",
           trains_policy=True),
    Method("softae", "optimistic", "uncertainty", True,
           "iCEM with hallucinated control s' = mu + beta sigma eta, reward ||sigma|| (SoftAE)"),
)}  # the order of tables and plots: the baseline first, the paper's method last

METHOD_NAMES = tuple(METHODS)


def get_method(name: str) -> Method:
    try:
        return METHODS[name]
    except KeyError:
        raise ValueError(f"unknown method {name!r}; valid methods: {', '.join(METHOD_NAMES)}") from None
