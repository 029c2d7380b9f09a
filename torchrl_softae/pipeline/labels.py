"""Row labels of runs side by side in tables and plots: the method, plus every setting in which
runs of that method differ, so that only runs differing in the seed are averaged."""
from __future__ import annotations

from collections import defaultdict

from torchrl_softae.pipeline.config import flat_config
from torchrl_softae.pipeline.methods import METHOD_NAMES, METHODS

__all__ = ["row_labels", "label_order"]


#: config keys that never set runs apart in a table: the seed is what rows average over, the budget
#: (episodes) is a table of its own, and tracking does not change a run
_NOT_IDENTITY = ("seed", "episodes", "wandb")


def row_labels(configs: list[dict]) -> list[str]:
    """Row labels of runs side by side in a table or plot (their run configs in, one label each).

    A label is the method's name, plus every setting in which runs of that method differ (beta
    and the task only for a method they change, :attr:`Method.ignored_settings`), e.g.
    ``softae beta=1`` and ``softae beta=2``: runs are averaged only with runs that differ in
    nothing but the seed. Configs are compared as the runs
    ran (fields added since a run was written at their defaults), so an older run is not set apart
    by a field it could not store."""
    flat = [flat_config(c) for c in configs]
    differing: dict[str, set] = defaultdict(set)
    by_method = defaultdict(list)
    for f in flat:
        by_method[f.get("method")].append(f)
    for m, fs in by_method.items():
        method = METHODS.get(m)
        ignored = set(_NOT_IDENTITY) | (method.ignored_settings if method is not None else set())
        keys = set().union(*fs) - ignored
        differing[m] = {k for k in keys if len({repr(f.get(k)) for f in fs}) > 1}
    labels = []
    for f in flat:
        m = f.get("method")
        extra = [f"{k}={f.get(k):g}" if isinstance(f.get(k), float) else f"{k}={f.get(k)}"
                 for k in sorted(differing[m])]
        labels.append(" ".join([str(m), *extra]))
    return labels


def label_order(labels) -> list[str]:
    """Table order of row labels: the method table's order (the baseline first), then settings."""
    rank = {m: i for i, m in enumerate(METHOD_NAMES)}
    return sorted(set(labels), key=lambda lab: (rank.get(lab.split(" ")[0], len(rank)), lab))
