"""Child seeds: one formula, so that episode ``k`` of a run and round ``k`` of an MBPO trainer are
reproducible from ``(seed, k)`` alone, whatever ran before them (a resumed run replays the seeds of
an uninterrupted one)."""
from __future__ import annotations

__all__ = ["derive_seed"]

_PRIME = 2**31 - 1  # seeds stay valid for torch, numpy and gymnasium


def derive_seed(seed: int, index: int) -> int:
    """The seed of step ``index`` (an episode, a rollout round) of a process seeded ``seed``."""
    return (int(seed) * 1_000_003 + int(index) * 7919) % _PRIME
