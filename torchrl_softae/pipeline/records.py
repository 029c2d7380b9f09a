"""Run records: one per run dir below a folder (its config, progress, history, evaluations and task
policies), or archived in a ``report.json``; what ``softae report`` tabulates and ``softae plot`` draws."""
from __future__ import annotations

import json
import sys
from pathlib import Path

from torchrl_softae.pipeline.runs import POLICIES_DIR, CheckpointError, RunDir, run_dirs_below

__all__ = ["collect", "read_archive", "archived_runs", "is_finished", "replication_records"]

#: the ``kind`` of a replication record (written by :mod:`torchrl_softae.pipeline.replication`)
REPLICATION_KIND = "softae-replication-record"


def _progress(history: list[dict]) -> dict:
    """What a run record derives from its per-episode history: transitions so far, last row."""
    return {"transitions": history[-1]["transitions"] if history else 0, "last": history[-1] if history else {}}


def collect(root: str | Path, warn=None) -> list[dict]:
    """One record per run dir below ``root``: config, progress, last history row, evaluations."""
    warn = warn or (lambda m: print(m, file=sys.stderr))
    root = Path(root)
    if not root.exists():
        raise FileNotFoundError(f"{root} does not exist")
    out = []
    for run_path in run_dirs_below(root):
        run = RunDir(run_path)
        try:
            stored = run.read_config()
        except CheckpointError as e:
            warn(f"softae report: skipping {run.path}: {e}")
            continue
        cfg = stored.get("config", {})
        history = run.history()
        evals = {}
        if (run.path / "eval").exists():
            for p in sorted((run.path / "eval").glob("*.json")):
                if p.stem not in ("model_accuracy",):
                    evals[p.stem] = json.loads(p.read_text())
        # task policies trained on the run's final model (``softae policy``): one per task
        policies = {}
        for p in sorted((run.path / POLICIES_DIR).glob(f"*-ep{len(history)}/eval.json")):
            res = json.loads(p.read_text())
            policies.setdefault(res["task"], res)
        out.append({"run_dir": str(run.path), "config": cfg, "env": cfg.get("env"), "method": cfg.get("method"),
                    "seed": cfg.get("seed"), "episodes_target": cfg.get("episodes"), "episodes_done": len(history),
                    **_progress(history), "history": history, "evals": evals, "policies": policies})
    return out


def read_archive(path: str | Path) -> list[dict]:
    """The ``runs`` archive of a ``report.json`` written by ``softae report``."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path} is not a file (expected a report.json written by softae report)")
    try:
        runs = json.loads(path.read_text()).get("runs")
    except (json.JSONDecodeError, UnicodeDecodeError, AttributeError):
        runs = None
    if not isinstance(runs, list):
        raise FileNotFoundError(f"{path} has no 'runs' archive (a report.json of softae report keeps one "
                                "since reports archived their runs; an older report cannot be read)")
    return runs


def archived_runs(path: str | Path, root: str | Path) -> list[dict]:
    """The runs archived in the report ``path``, as records of :func:`collect` placed below
    ``root`` by their archived path (``ENV/NAME``), each marked with the report it came from."""
    return [{**r, "run_dir": str(Path(root) / r["run_dir"]), "archived": str(path), **_progress(r["history"])}
            for r in read_archive(path)]


def is_finished(run: dict) -> bool:
    """Whether a run record (of :func:`collect`, or archived in ``report.json``) reached its
    configured number of episodes: only finished runs are averaged and plotted."""
    return bool(run["episodes_done"]) and run["episodes_done"] >= (run["episodes_target"] or 0)


def replication_records(root: str | Path) -> list[dict]:
    """Run records from the replication records below ``root`` (one JSON per run and budget,
    :mod:`~torchrl_softae.pipeline.replication`): each is a finished run of ``budget`` episodes
    whose run dir is the record (``record`` names it)."""
    out = []
    for path in sorted(Path(root).rglob("*.json")):
        try:
            rec = json.loads(path.read_text())
        except (json.JSONDecodeError, UnicodeDecodeError, OSError):
            continue
        if not isinstance(rec, dict) or rec.get("kind") != REPLICATION_KIND:
            continue
        out.append({"run_dir": str(path.with_suffix("")), "config": rec["config"], "env": rec["env"],
                    "method": rec["method"], "seed": rec["seed"], "episodes_target": rec["budget"],
                    "episodes_done": rec["budget"], "history": rec["history"],
                    "evals": {**rec["tasks"], **({"references": rec["references"]} if "references" in rec else {})},
                    "policies": {}, "record": str(path), "replication": rec, **_progress(rec["history"])})
    return out
