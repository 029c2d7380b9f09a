"""Replications: one exploration evaluated at several budgets, as a sweep file's ``replication``
block says; one JSON record per (env, method, seed, budget) that holds everything a reader needs
later without the run dir: the run's full config, the commit and machine that ran it, held-out
accuracy overall and by group (with the s' = s and predict-the-mean baselines), coverage and the
histogram of the explored data on the env's coverage grid (heatmaps drawn from the records alone),
the per-episode history, per task the returns, success metrics and the planner horizon used, and
with ``evaluate: {references: true}`` the model-free references' returns on the same episodes.

Sweep file::

    replication:
      budgets: [10, 25, 50]                         # exploration episodes at which to evaluate
      results: benchmarks/results/replication/SoftArm-v1   # where the records go
      task_episodes: {reach-any: 3}                 # evaluation episodes where not the evaluate block's
    evaluate: {tasks: [reach-close, reach-far, reach-any], episodes: 1, planner: {horizon: 10}}

``softae report RESULTS`` tabulates the records (one table per budget, mean +- sample std over
seeds, n) and draws them.
"""
from __future__ import annotations

import dataclasses
import functools
import json
import time
from pathlib import Path

from torchrl_softae.pipeline.config import ConfigError
from torchrl_softae.pipeline.data import COVERAGE_BINS
from torchrl_softae.pipeline.provenance import code_version, machine
from torchrl_softae.pipeline.records import REPLICATION_KIND

__all__ = ["REPLICATION_KIND", "REPLICATION_KEYS", "HISTOGRAM_BINS", "check_block", "record_path", "missing_budgets",
           "run_budgets", "code_version", "machine", "coverage_histogram", "pooled_coverage", "check_histogram"]

REPLICATION_KEYS = ("budgets", "results", "task_episodes")
#: cells per axis of a record's coverage histogram: twice the coverage metric's, so pooling 2 x 2
#: cells gives back the recorded coverage (checked before a record is written)
HISTOGRAM_BINS = 2 * COVERAGE_BINS


def check_block(spec: dict, cfg, evaluate: dict | None) -> dict | None:
    """The sweep's ``replication`` block, checked before anything runs; ``results`` made absolute
    (a Ray trial runs in a folder of its own)."""
    block = spec.get("replication")
    if block is None:
        return None
    if not isinstance(block, dict) or sorted(set(block) - set(REPLICATION_KEYS)):
        raise ConfigError(f"the sweep's replication block: expected a mapping of {', '.join(REPLICATION_KEYS)}, "
                          f"got {block!r}")
    budgets = block.get("budgets")
    if (not isinstance(budgets, list) or not budgets or not all(isinstance(b, int) and b > 0 for b in budgets)
            or budgets != sorted(set(budgets))):
        raise ConfigError(f"replication block: budgets {budgets!r}: expected increasing positive episode counts")
    if budgets[-1] != cfg.episodes:
        raise ConfigError(f"replication block: the budgets end at {budgets[-1]} episodes but the runs explore "
                          f"{cfg.episodes}: set --episodes {budgets[-1]} in the command")
    if not isinstance(block.get("results"), str):
        raise ConfigError("replication block: results: expected the folder the records go to")
    if not evaluate or not evaluate.get("task_names"):
        raise ConfigError("replication block: needs an evaluate block naming the tasks to evaluate at each budget")
    episodes = block.get("task_episodes") or {}
    if not isinstance(episodes, dict) or not all(isinstance(n, int) and n > 0 for n in episodes.values()):
        raise ConfigError(f"replication block: task_episodes {episodes!r}: expected task -> positive episode count")
    unknown = sorted(set(episodes) - set(evaluate["task_names"]))
    if unknown:
        raise ConfigError(f"replication block: task_episodes names {', '.join(unknown)}, not among the evaluated "
                          f"tasks ({', '.join(evaluate['task_names'])})")
    return {"budgets": budgets, "results": str(Path(block["results"]).resolve()), "task_episodes": episodes}


def record_path(block: dict, run_dir: Path, budget: int) -> Path:
    """``RESULTS/RUN-epBUDGET.json``, ``RUN`` the run dir's name (method, beta where used, seed)."""
    return Path(block["results"]) / f"{Path(run_dir).name}-ep{budget}.json"


def missing_budgets(block: dict, run_dir: Path) -> list[int]:
    return [b for b in block["budgets"] if not record_path(block, run_dir, b).exists()]


def coverage_histogram(cfg, run_dir: Path) -> dict:
    """Transitions per cell of the env's coverage grid (its projection, e.g. the arm's tip x-z) of
    every transition ``run_dir`` holds, at :data:`HISTOGRAM_BINS` cells per axis."""
    from torchrl_softae.pipeline.catalog import run_entry
    from torchrl_softae.pipeline.data import coverage_counts, heldout_set, projection_bounds
    from torchrl_softae.pipeline.runs import RunDir

    entry, run = run_entry(cfg), RunDir(run_dir)
    rb = run.load_replay_buffer(run.load())
    bounds = projection_bounds(entry, heldout_set(entry, run, cfg.heldout_size))
    counts = coverage_counts(entry, rb.storage[: len(rb)], bounds, HISTOGRAM_BINS)
    return {"bins": HISTOGRAM_BINS, "bounds": bounds.tolist(), "labels": list(entry.projection_labels),
            "transitions": len(rb), "counts": counts.tolist()}


def pooled_coverage(histogram: dict) -> float:
    """The coverage metric (the share of visited cells of the ``COVERAGE_BINS`` grid) of a histogram."""
    import numpy as np

    c = np.asarray(histogram["counts"])
    k = histogram["bins"] // COVERAGE_BINS
    pooled = c.reshape(COVERAGE_BINS, k, COVERAGE_BINS, k).sum((1, 3))
    return float((pooled > 0).sum()) / COVERAGE_BINS**2


def check_histogram(histogram: dict, history: list[dict]) -> None:
    """A histogram belongs to a run's history only if it holds its transitions and gives back its
    recorded coverage."""
    want = history[-1]
    if histogram["transitions"] != want["transitions"] or abs(pooled_coverage(histogram) - want["coverage"]) > 1e-9:
        raise ValueError(f"coverage histogram of {histogram['transitions']} transitions with coverage "
                         f"{pooled_coverage(histogram):.4f}, the run's history {want['transitions']} with "
                         f"{want['coverage']:.4f}: not the same data")


def run_budgets(trial, cfg, on_episode=None, on_task=None, on_steps=None) -> list[dict]:
    """Explore ``trial``'s run to each budget that has no record yet, evaluate it there and write
    its record; returns the run's history (the last budget's). A budget the run already went past cannot be
    evaluated any more (its model is gone): one clear error. A task a killed process evaluated for
    the budget's model is kept (:func:`~torchrl_softae.pipeline.evaluate.evaluate_run`'s ``resume``),
    and its seconds count in the record's. ``on_task``: as ``evaluate_run``'s; ``on_steps``: as
    ``evaluate_run``'s, called with the budget first."""
    from torchrl_softae.pipeline.evaluate import evaluate_run, planner_overrides
    from torchrl_softae.pipeline.explore import explore
    from torchrl_softae.pipeline.runs import RunDir, atomic_write_text

    block, ev = trial.replication, trial.evaluate
    for budget in missing_budgets(block, trial.run_dir):
        done = len(RunDir(trial.run_dir).history())
        if done > budget:
            raise ConfigError(f"{trial.run_dir} explored {done} episodes, past the budget {budget} whose record "
                              f"{record_path(block, trial.run_dir, budget)} is missing: that model is gone; "
                              "explore a new run dir to evaluate it")
        cfg_b = dataclasses.replace(cfg, episodes=budget)
        history = explore(cfg_b, trial.run_dir, progress=False, echo=None, on_episode=on_episode)
        t0, cpu0 = time.perf_counter(), time.process_time()
        earlier = {"seconds": 0.0, "cpu_seconds": 0.0}  # spent on these tasks by earlier, killed processes

        def count_earlier(name, result, was_kept, earlier=earlier):
            for key in earlier:  # a kept task wholly, a resumed one its part before the kill
                earlier[key] += result.get(key, 0.0) if was_kept else result.get(f"earlier_{key}", 0.0)
            if on_task is not None:
                on_task(name, result, was_kept)

        res = evaluate_run(trial.run_dir, tasks=ev["task_names"], episodes=int(ev.get("episodes", 3)),
                           task_episodes=block["task_episodes"], propagation=ev.get("propagation", "mean"),
                           progress=False, planner_overrides=planner_overrides(ev.get("planner")),
                           references=bool(ev.get("references")), resume=True, on_task=count_earlier,
                           on_steps=None if on_steps is None else functools.partial(on_steps, budget))
        accuracy = {k: v for k, v in res.items() if k.startswith("heldout_")}
        tasks = {name: {**r, "planner_horizon": r["planner"]["horizon"]} for name, r in res["tasks"].items()}
        histogram = coverage_histogram(cfg_b, trial.run_dir)
        check_histogram(histogram, history)
        record = {
            "kind": REPLICATION_KIND, "env": cfg.env, "method": cfg.method, "seed": cfg.seed, "budget": budget,
            "transitions": history[-1]["transitions"], "config": cfg_b.to_dict(), "code": code_version(),
            "machine": machine(), "accuracy": accuracy, "coverage": history[-1]["coverage"],
            "coverage_histogram": histogram, "tasks": tasks,
            # the model-free returns on the same evaluation episodes (``evaluate: {references: true}``)
            **({"references": res["references"]} if "references" in res else {}),
            "seconds": {"explore": sum(r["collect_seconds"] + r["train_seconds"] for r in history),
                        "evaluate": time.perf_counter() - t0 + earlier["seconds"]},
            # CPU seconds of the same work; a pause costs none. Episodes explored by code older than
            # the field have none, and then neither has the record's exploration.
            "cpu_seconds": {"explore": (sum(r["cpu_seconds"] for r in history)
                                        if all("cpu_seconds" in r for r in history) else None),
                            "evaluate": time.process_time() - cpu0 + earlier["cpu_seconds"]},
            "history": history,
        }
        path = record_path(block, trial.run_dir, budget)
        path.parent.mkdir(parents=True, exist_ok=True)
        atomic_write_text(path, json.dumps(record, indent=1, default=float))
        if on_episode is not None:
            on_episode({**history[-1], **{f"return/{k}": v["mean_return"] for k, v in tasks.items()}, "evaluated": 1})
    return RunDir(trial.run_dir).history()
