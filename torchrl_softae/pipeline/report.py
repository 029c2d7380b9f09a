"""``softae report ROOT``: any folder of runs (a sweep, or runs made by hand) as the paper's tables.

Per env and budget (episodes x transitions; runs of different budgets are never averaged
together): one row per method with mean +- sample std over seeds of the held-out normalized MSE (and
by group of state dimensions where the env defines groups), the coverage and each evaluated
task's zero-shot return (and its success measure where the task has one), the real returns of the SAC task policies trained on the run's final model (``softae
policy``, ``RUN/policies/``), plus the model-free reference rows where a run dir holds
``eval/references.json`` (``softae evaluate --references``, a sweep's ``evaluate: {references:
true}``). Runs that
have not reached their configured number of episodes are listed as unfinished, never averaged.
Markdown and JSON go to ``ROOT/report.md`` and ``ROOT/report.json``; comparison plots to
``ROOT/plots/``. ``report.json`` also keeps every run's config, per-episode history and
evaluations (``runs``), so a committed report outlives the run dirs it was made from, and
``softae report ROOT --merge OLD/report.json`` adds the runs of such a report to the runs below
``ROOT`` (a baseline run later beside runs whose dirs are gone): one table, every run's record kept.
"""
from __future__ import annotations

import json
import sys
from collections import defaultdict
from pathlib import Path

import numpy as np

from torchrl_softae.pipeline.labels import label_order, row_labels
from torchrl_softae.pipeline.records import (archived_runs, collect, is_finished, read_archive,  # noqa: F401 (public)
                                              replication_records)
from torchrl_softae.pipeline.runs import atomic_write_text
from torchrl_softae.tasks.base import metric_label

__all__ = ["archived_runs", "collect", "is_finished", "read_archive", "report"]


def _fmt(values, digits: int = 4) -> str:
    v = np.asarray([x for x in values if x is not None and np.isfinite(x)], dtype=float)
    if not len(v):
        return "-"
    m = f"{v.mean():.{digits}g}"
    return m + (f" ± {v.std(ddof=1):.2g}" if len(v) > 1 else "")  # the sample std over the seeds


def report(root: str | Path, plots: bool = True, warn=None, merge: list | tuple = (),
           write: bool = True) -> tuple[str, Path | None, Path | None, list]:
    """Build the tables (markdown + JSON) and plots; returns ``(markdown, json path, md path, plots)``.

    ``merge``: earlier ``report.json`` files whose archived runs join the runs below ``root``; a
    run dir below ``root`` replaces an archived run of the same ``ENV/NAME`` (it is newer).
    ``write=False``: only the markdown, nothing written below ``root`` (no JSON, no plots)."""
    from torchrl_softae.pipeline.catalog import env_ids, get_env_entry, heldout_note

    warn = warn or (lambda m: print(m, file=sys.stderr))
    root = Path(root)
    runs = collect(root, warn) if root.exists() or not merge else []
    runs += replication_records(root) if root.exists() else []
    seen = {Path(r["run_dir"]).resolve() for r in runs}
    for path in merge:
        for r in archived_runs(path, root):
            where = Path(r["run_dir"]).resolve()
            if where not in seen:
                seen.add(where)
                runs.append(r)
    if not runs:
        raise FileNotFoundError(f"no run (config.json) or replication record below {root}")
    finished = [r for r in runs if is_finished(r)]
    unfinished = [r for r in runs if r not in finished]
    budgets = defaultdict(list)
    for r in finished:
        budgets[(r["env"], r["episodes_done"], r["transitions"])].append(r)
    md, tables = [f"# Report of {root}", ""], []
    for (env, episodes, transitions), rs_of_budget in sorted(budgets.items()):
        # one row per method (and setting, where runs of a method differ in more than the seed)
        by_method = defaultdict(list)
        for r, label in zip(rs_of_budget, row_labels([r["config"] for r in rs_of_budget])):
            by_method[label].append(r)
        catalog_tasks = get_env_entry(env).tasks if env in env_ids() else {}
        # evaluations planned with overrides keep their own column (TASK@key=value)
        tasks = sorted({t for rs in by_method.values() for r in rs for t in r["evals"] if t != "references"})
        # the success metric as the evaluation recorded it (older results: the catalog task's)
        recorded = {t: r["evals"][t]["success_metric"] for rs in by_method.values() for r in rs for t in tasks
                    if t in r["evals"] and "success_metric" in r["evals"][t]}
        metric_of = {t: recorded[t] if t in recorded else getattr(catalog_tasks.get(t.split("@")[0]), "success_metric", None)
                     for t in tasks}
        # the held-out error by group of state dimensions where the env defines groups (the arm:
        # tip, positions, velocities, ...), in the order the runs logged them
        groups = list(dict.fromkeys(k.split("/", 1)[1] for rs in by_method.values() for r in rs
                                    for k in r["last"] if k.startswith("heldout_nmse/")))
        head = ["method", "seeds", "held-out normalized MSE", *(f"nMSE {g.replace('_', ' ')}" for g in groups),
                "coverage"]
        for t in tasks:
            head.append(f"{t} return")
            if metric_of[t]:
                head.append(f"{t} {metric_label(metric_of[t])}")
        policy_tasks = sorted({t for rs in by_method.values() for r in rs for t in r["policies"]})
        head += [f"{t} SAC policy return" for t in policy_tasks]
        rows = []
        for m in label_order(by_method):
            rs = sorted(by_method[m], key=lambda r: r["seed"])  # every per-seed list in the order of "seeds"
            row = {"method": m, "seeds": [r["seed"] for r in rs],
                   "heldout_nmse": [r["last"].get("heldout_nmse") for r in rs],
                   "coverage": [r["last"].get("coverage") for r in rs]}
            cells = [m, str(len(rs)), _fmt(row["heldout_nmse"])]
            for g in groups:
                row[f"heldout_nmse/{g}"] = [r["last"].get(f"heldout_nmse/{g}") for r in rs]
                cells.append(_fmt(row[f"heldout_nmse/{g}"], 3))
            cells.append(_fmt(row["coverage"], 3))
            for t in tasks:
                ret = [np.mean(r["evals"][t]["returns"]) if t in r["evals"] else None for r in rs]
                row[f"{t}/return"] = ret
                cells.append(_fmt(ret, 3))
                if metric_of[t]:
                    mv = [np.mean([x[metric_of[t]] for x in r["evals"][t]["metrics"]]) if t in r["evals"] else None
                          for r in rs]
                    row[f"{t}/{metric_of[t]}"] = mv
                    cells.append(_fmt(mv, 3))
            for t in policy_tasks:
                ret = [r["policies"][t]["mean_return"] if t in r["policies"] else None for r in rs]
                row[f"policy/{t}/return"] = ret
                cells.append(_fmt(ret, 3))
            rows.append(row)
            md_row = "| " + " | ".join(cells) + " |"
            row["markdown"] = md_row
        # model-free reference rows: the same evaluation episodes for every run, so one run's say
        refs = next((r["evals"]["references"]["returns"] for rs in by_method.values() for r in rs
                     if "references" in r["evals"]), {})
        md += [f"## {env}: {episodes} episodes = {transitions} transitions per run", "",
               "| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
        md += [row["markdown"] for row in rows]
        # the held-out baselines the records measured on the same set (s' = s, the set's mean): one
        # value per set, so the first run's
        accuracy = next((r["replication"]["accuracy"] for rs in by_method.values() for r in rs
                         if "heldout_nmse_identity" in r.get("replication", {}).get("accuracy", {})), None)
        for name, suffix in (("s' = s", "_identity"), ("predict the mean", "_mean")) if accuracy else ():
            values = [accuracy.get(f"heldout_nmse{suffix}"), *(accuracy.get(f"heldout_nmse{suffix}/{g}") for g in groups)]
            cells = [f"*{name}*", "-", *(_fmt([v], 3) for v in values), "-"]
            cells += ["-"] * (len(tasks) + sum(1 for t in tasks if metric_of[t]) + len(policy_tasks))
            md.append("| " + " | ".join(cells) + " |")
        for name, per_task in sorted(refs.items()):  # one order whichever run's file was read
            cells = [f"*{name}*", "-", "-", *["-"] * len(groups), "-"]
            for t in tasks:
                cells.append(_fmt(per_task.get(t.split("@")[0], []), 3))
                if metric_of[t]:
                    cells.append("-")
            cells += ["-"] * len(policy_tasks)
            md.append("| " + " | ".join(cells) + " |")
        notes = sorted({heldout_note(r["config"]) for rs in by_method.values() for r in rs} - {""})
        md += [""] + [f"*{note}*" for note in notes] if notes else []
        md.append("")
        tables.append({"env": env, "episodes": episodes, "transitions": transitions, "columns": head,
                       "heldout_set": notes,
                       "rows": [{k: v for k, v in row.items() if k != "markdown"} for row in rows],
                       "references": refs})
    archived = defaultdict(list)
    for r in runs:
        if r.get("archived"):
            archived[r["archived"]].append(Path(r["run_dir"]).relative_to(root))
    if archived:
        md += ["## Runs from earlier reports (their run dirs are not below the root)", ""]
        md += [f"- {path}: {', '.join(map(str, names))}" for path, names in archived.items()]
        md.append("")
    if unfinished:
        md += ["## Unfinished runs (not averaged)", ""]
        md += [f"- {r['run_dir']}: {r['method']} seed {r['seed']}, {r['episodes_done']} of {r['episodes_target']} "
               "episodes" for r in unfinished]
        md.append("")
    text = "\n".join(md)
    if not write:
        return text, None, None, []
    root.mkdir(parents=True, exist_ok=True)
    md_path, json_path = root / "report.md", root / "report.json"
    atomic_write_text(md_path, text)
    summary = ("run_dir", "method", "seed", "episodes_done", "episodes_target")
    # every run's history and evaluations too: a committed report keeps what each run measured
    # when its run dir (checkpoints, replay dumps) is gone
    archive = [{**{k: r[k] for k in summary}, "run_dir": str(Path(r["run_dir"]).relative_to(root)),
                "env": r["env"], "config": r["config"], "history": r["history"], "evals": r["evals"],
                "policies": r["policies"]} for r in runs]
    atomic_write_text(json_path, json.dumps({"tables": tables, "unfinished": [{k: r[k] for k in summary}
                                                                             for r in unfinished],
                                             "runs": archive}, indent=1, default=float))
    written = []
    if plots and finished and any(r.get("archived") or r.get("record") for r in finished):
        from torchrl_softae.pipeline.plots import plot_report

        # archived runs keep their histories and evaluations, not their collected states
        written = plot_report(json_path, warn)
        n_archived = sum(1 for r in finished if r.get("archived"))
        if n_archived:  # (replication records carry a histogram of their data instead)
            warn(f"softae report: {n_archived} runs come from earlier reports, without their collected states: "
                 "no coverage heatmaps")
        records = [r["replication"] for r in finished if "replication" in r]
        if records:  # several budgets of one exploration: the curves against the budget, every seed
            from torchrl_softae.pipeline.plots import plot_budgets, plot_record_coverage

            written += plot_budgets(records, root / "plots") + plot_record_coverage(records, root / "plots")
    elif plots and finished:
        from torchrl_softae.pipeline.plots import plot_comparison

        # the runs the tables average; unfinished ones would be a budget of their own
        written = plot_comparison(root, warn, only=[r["run_dir"] for r in finished])
    return text, json_path, md_path, written
