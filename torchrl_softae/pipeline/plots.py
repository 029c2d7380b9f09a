"""Pictures of a run (or of a folder of runs), saved as PNG files.

Comparisons are made only between runs of one env and one budget (episodes x transitions):
a folder holding several budgets gets one set of figures per budget, never pooled. Methods
appear in the method table's order (random first, SoftAE last); coverage panels share their bins
and their colour scale; titles say the env, the budget and the number of seeds.
"""
from __future__ import annotations

import json
import sys
from collections import defaultdict
from pathlib import Path

import numpy as np
import torch

from torchrl_softae.pipeline.labels import label_order, row_labels
from torchrl_softae.pipeline.methods import METHOD_NAMES
from torchrl_softae.pipeline.records import is_finished, read_archive
from torchrl_softae.pipeline.runs import REFERENCES_FILE, CheckpointError, RunDir, atomic_savefig, run_dirs_below
from torchrl_softae.tasks.base import metric_label

__all__ = ["plot_run", "plot_comparison", "plot_report", "plot_path", "plot_budgets", "plot_record_coverage",
           "coverage_heatmaps"]


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _save(fig, path: Path, rect=(0, 0, 1, 1)) -> Path:
    """``rect``: the part of the figure the axes may fill (room for a figure legend below)."""
    fig.tight_layout(rect=rect)
    atomic_savefig(fig, path, dpi=120)
    _plt().close(fig)
    return path


def _projected(run: RunDir, entry) -> np.ndarray:
    state = run.load()
    rb = run.load_replay_buffer(state)
    p = entry.project(rb.storage[: len(rb)])
    return p[torch.isfinite(p).all(-1)].numpy()


def _coverage_panels(points: dict, entry, title: str, path: Path, bins: int = 40) -> Path:
    """One heatmap per label of ``points`` (``(N, 2)`` projected states), binned on one grid over
    all of them."""
    allp = np.concatenate(list(points.values()))
    lo, hi = allp.min(0), allp.max(0)
    pad = 0.02 * np.maximum(hi - lo, 1e-9)
    edges = [np.linspace(lo[i] - pad[i], hi[i] + pad[i], bins + 1) for i in range(2)]
    counts = {k: np.histogram2d(p[:, 0], p[:, 1], bins=edges)[0] for k, p in points.items()}
    return coverage_heatmaps(counts, edges, entry.projection_labels, title, path)


def coverage_heatmaps(counts: dict, edges, axis_labels, title: str, path: Path,
                      unit: str = "transitions per cell", markers: dict | None = None) -> Path:
    """One heatmap per label of ``counts`` (``(bins_x, bins_y)`` per cell, all on the grid
    ``edges = (x_edges, y_edges)``), on the same (log) colour scale, one colour bar labelled
    ``unit``; ``markers`` (``{label: (x, y)}``, e.g. task targets) are drawn on every panel."""
    from matplotlib.colors import LogNorm
    from matplotlib.ticker import MaxNLocator

    plt = _plt()
    counts = {k: np.asarray(c, dtype=float) for k, c in counts.items()}
    vmax = max(c.max() for c in counts.values())
    vmin = min((c[c > 0].min() for c in counts.values() if (c > 0).any()), default=1.0)
    n = len(counts)
    fig, axes = plt.subplots(1, n, figsize=(3.4 * n + 1.2, 3.7), squeeze=False, sharex=True, sharey=True)
    fig.subplots_adjust(top=0.82)  # room for the figure title above the panel titles
    mesh = None
    for ax, (label, c) in zip(axes[0], counts.items()):
        mesh = ax.pcolormesh(edges[0], edges[1], np.where(c > 0, c, np.nan).T, cmap="viridis",
                             norm=LogNorm(vmin=min(vmin, 1), vmax=max(vmax, 2)))
        for j, (name, (x, y)) in enumerate((markers or {}).items()):
            ax.plot(x, y, marker="*X^sD"[j % 5], ms=10, mfc="red", mec="white", ls="none", label=name)
        ax.set_title(label, fontsize=10)
        ax.set_xlabel(axis_labels[0])
    axes[0][0].set_ylabel(axis_labels[1])
    axes[0][0].xaxis.set_major_locator(MaxNLocator(5))  # shared: a wide range's labels ran into each other
    if markers:
        axes[0][0].legend(fontsize=7, loc="lower left")
    fig.suptitle(title, fontsize=11)
    fig.colorbar(mesh, ax=axes[0].tolist(), label=unit, fraction=0.04, pad=0.02)
    atomic_savefig(fig, path, dpi=120, bbox_inches="tight")
    plt.close(fig)
    return path


def _evals(run: RunDir) -> dict[str, dict]:
    folder = run.path / "eval"
    if not folder.exists():
        return {}
    return {p.stem: json.loads(p.read_text()) for p in sorted(folder.glob("*.json"))
            if p.stem not in ("model_accuracy", "references")}


def _references(run: RunDir) -> dict[str, dict]:
    """The model-free references' returns of a run's evaluation (``{label: {task: [...]}}``)."""
    path = run.path / "eval" / REFERENCES_FILE
    return json.loads(path.read_text())["returns"] if path.exists() else {}


def _success_metric(entry, task: str, results=()) -> str | None:
    """The task's success metric: as its evaluation results record it, else its catalog task's."""
    for res in results:
        if "success_metric" in res:
            return res["success_metric"]
    t = None if entry is None else entry.tasks.get(task.split("@", 1)[0])
    return None if t is None else t.success_metric


def _run_entry(config: dict):
    """The entry of a run's config, or ``None`` where its env cannot be built here (an outside
    env's module is not importable where an archived report is redrawn)."""
    from torchrl_softae.pipeline.catalog import run_entry
    from torchrl_softae.pipeline.config import ExploreConfig

    try:
        return run_entry(ExploreConfig.from_dict(config))
    except ValueError:
        return None


def _heldout_title(config: dict) -> str:
    from torchrl_softae.pipeline.catalog import heldout_note

    note = heldout_note(config)
    return f"\n{note}" if note else ""


def plot_run(run_dir: str | Path) -> list[Path]:
    """Coverage heatmap, learning curves and task evaluation of one run."""
    from torchrl_softae.pipeline.catalog import run_entry
    from torchrl_softae.pipeline.config import ExploreConfig

    plt = _plt()
    run = RunDir(run_dir)
    state = run.load()
    cfg = state["config"]
    entry = run_entry(ExploreConfig.from_dict(cfg))
    history = state["history"]
    name = f"{cfg['env']} / {cfg['method']} / seed {cfg['seed']}"
    budget = f"{state['episode'] + 1} episodes, {state['num_transitions']} transitions"
    written = [_coverage_panels({cfg["method"]: _projected(run, entry)}, entry, f"{name}: coverage ({budget})",
                                run.plots / "coverage.png")]

    ep = [r["episode"] + 1 for r in history]
    fig, axes = plt.subplots(1, 2, figsize=(9, 3.5))
    axes[0].plot(ep, [r["heldout_nmse"] for r in history], "o-")
    axes[0].set_yscale("log")
    axes[0].set_xlabel("exploration episode")
    axes[0].set_ylabel("held-out normalized MSE")
    axes[1].plot(ep, [r["coverage"] for r in history], "o-", color="C1")
    axes[1].set_xlabel("exploration episode")
    axes[1].set_ylabel("coverage (fraction of cells)")
    fig.suptitle(f"{name} ({budget}){_heldout_title(cfg)}", fontsize=10)
    written.append(_save(fig, run.plots / "learning_curves.png"))

    curves = sorted({k for r in history for k in r if k.startswith("return/")})
    if curves:
        fig, ax = plt.subplots(figsize=(5, 3.5))
        for k in curves:
            pts = [(r["episode"] + 1, r[k]) for r in history if k in r]
            ax.plot(*zip(*pts), "o-", label=k.split("/", 1)[1])
        ax.set_xlabel("exploration episode")
        ax.set_ylabel("zero-shot return")
        ax.set_title(f"{name}: zero-shot return while exploring", fontsize=10)
        ax.legend()
        written.append(_save(fig, run.plots / "return_curves.png"))

    evals = _evals(run)
    if evals:
        metrics = {t: _success_metric(entry, t, [evals[t]]) for t in evals}
        with_metric = [t for t in evals if metrics[t] and metrics[t] in (evals[t]["metrics"] or [{}])[0]]
        ncols = 2 if with_metric else 1
        fig, axes = plt.subplots(1, ncols, figsize=(4.5 * ncols, 3.6), squeeze=False)
        names = list(evals)
        res = [evals[t]["returns"] for t in names]
        axes[0][0].bar(names, [np.mean(r) for r in res], yerr=[_sample_std(r) for r in res], capsize=4, color="C2")
        axes[0][0].set_ylabel(f"zero-shot return (mean +- sample std over {len(res[0])} episodes)")
        axes[0][0].tick_params(axis="x", rotation=20)
        if with_metric:
            vals = [[m[metrics[t]] for m in evals[t]["metrics"]] for t in with_metric]
            axes[0][1].bar(with_metric, [np.mean(v) for v in vals], yerr=[_sample_std(v) for v in vals], capsize=4, color="C4")
            axes[0][1].set_ylabel(" / ".join(sorted({metric_label(metrics[t]) for t in with_metric})))
            axes[0][1].set_title("success measure", fontsize=10)
        fig.suptitle(f"{name}: zero-shot evaluation after {budget}", fontsize=10)
        written.append(_save(fig, run.plots / "eval_returns.png"))
    return written


def _runs_below(folder: Path) -> list[RunDir]:
    return [RunDir(p) for p in run_dirs_below(folder, "checkpoint.pt")]


def _load_ok(runs: list[RunDir], warn) -> list[tuple[RunDir, dict]]:
    """The runs that load; each broken one costs a warning line, not the whole plot."""
    ok = []
    for run in runs:
        try:
            ok.append((run, run.load()))
        except CheckpointError as e:
            warn(f"softae plot: skipping {run.path}: {e}")
    return ok


def method_color(label: str) -> str:
    """The colour of a method (a row label's first word) in every figure: its place in the method
    table, so a method keeps its colour whichever others stand beside it."""
    name = label.split(" ")[0]
    return f"C{METHOD_NAMES.index(name)}" if name in METHOD_NAMES else "C7"


def _sample_std(values) -> float:
    """The sample std (ddof = 1) of ``values``; 0 for a single value."""
    return float(np.std(values, ddof=1)) if len(values) > 1 else 0.0


def _seed_bars(ax, labels: list[str], values: list[list[float]], color) -> None:
    """Bars of the mean over seeds with min-max whiskers (never outside what a seed reached, e.g.
    below 0 for a fraction) and every seed as a dot."""
    means = [np.mean(v) if v else np.nan for v in values]
    err = [[m - min(v) if v else 0 for m, v in zip(means, values)], [max(v) - m if v else 0 for m, v in zip(means, values)]]
    ax.bar(labels, means, yerr=err, capsize=4, color=color)
    for i, v in enumerate(values):
        ax.plot([i] * len(v), v, ".", color="k", ms=4)


def _comparison_bars(by_method: dict[str, list[dict]], entry, title: str, budget: str, seed_text: str,
                     out_dir: Path, prefix: str) -> list[Path]:
    """The held-out MSE bars and the zero-shot task bars of one (env, budget) group. A record is
    one run's ``history`` (per episode), ``evals`` (task -> evaluation) and ``references``
    (label -> task -> model-free returns)."""
    plt = _plt()
    first_config = next(iter(by_method.values()))[0]["config"]
    env = entry.env_id if entry is not None else first_config["env"]
    methods = label_order(by_method)
    colors = [method_color(m) for m in methods]  # a method's colour in every panel and figure
    written = []
    fig, ax = plt.subplots(figsize=(1.3 * len(methods) + 2.5, 4.0))
    vals = [np.array([rec["history"][-1]["heldout_nmse"] for rec in by_method[m]]) for m in methods]
    # min-max whiskers: never below a log axis, unlike mean - std
    _seed_bars(ax, methods, [list(v) for v in vals], colors)
    ax.set_yscale("log")
    allv = np.concatenate(vals)
    ax.set_ylim(allv.min() / 3, allv.max() * 3)  # a decade of room: bar heights stay comparable
    ax.set_ylabel("held-out normalized MSE")
    # the env on a line of its own: a figure this narrow cut the one-line title off
    note = _heldout_title(first_config)
    ax.set_title(f"{env}\n{budget}, {seed_text}\nbar: mean, whiskers: min-max, dots: seeds{note}", fontsize=9)
    written.append(_save(fig, out_dir / f"{prefix}mse_bars.png"))

    tasks = sorted({t for m in methods for rec in by_method[m] for t in rec["evals"]})
    if not tasks:
        return written
    metric_of = {t: _success_metric(entry, t, [rec["evals"][t] for m in methods for rec in by_method[m]
                                                if t in rec["evals"]]) for t in tasks}
    rows = 2 if any(metric_of.values()) else 1
    fig, axes = plt.subplots(rows, len(tasks), figsize=(max(3.4 * len(tasks) + 1, 6.5), 3.2 * rows),
                             squeeze=False)  # wide enough for the title
    refs = next((rec["references"] for m in methods for rec in by_method[m] if rec["references"]), {})
    for j, task in enumerate(tasks):
        per_method = {m: [rec["evals"][task] for rec in by_method[m] if task in rec["evals"]] for m in methods}
        ret = [[np.mean(e["returns"]) for e in per_method[m]] for m in methods]
        _seed_bars(axes[0][j], methods, ret, colors)
        for k, (label, per_task) in enumerate(refs.items()):  # the same episodes without a model
            if per_task.get(task.split("@")[0]):
                axes[0][j].axhline(np.mean(per_task[task.split("@")[0]]), color="k", lw=1,
                                   ls=("--", ":")[k % 2], label=label)
        axes[0][j].set_title(task, fontsize=10)
        axes[0][j].tick_params(axis="x", rotation=30)
        if rows == 2:
            metric = metric_of[task]
            if metric:
                vals = [[np.mean([x[metric] for x in e["metrics"]]) for e in per_method[m]] for m in methods]
                _seed_bars(axes[1][j], methods, vals, colors)
                axes[1][j].set_ylabel(metric_label(metric), fontsize=9)
                axes[1][j].tick_params(axis="x", rotation=30)
            else:
                axes[1][j].axis("off")
    axes[0][0].set_ylabel("zero-shot return")
    fig.suptitle(f"{title}\nbar: mean over seeds, whiskers: min-max, dots: seeds", fontsize=10)
    handles, labels = axes[0][-1].get_legend_handles_labels()
    if handles:  # below the panels: inside one, it covered a bar
        fig.legend(handles, labels, loc="lower center", ncol=len(handles), fontsize=8, frameon=False)
    written.append(_save(fig, out_dir / f"{prefix}task_returns.png", rect=(0, 0.07 if handles else 0, 1, 1)))
    return written


def _budget_groups(records: list[dict], warn, where: Path):
    """Per (env, budget) of ``records``, in order: the runs by row label (runs of a method that
    differ in more than the seed apart, ``row_labels``), the env entry, the title and its parts,
    and the file-name prefix. Never pooled across budgets."""
    budgets: dict[tuple, list] = defaultdict(list)
    for rec in records:
        budgets[(rec["config"]["env"], rec["episodes"], rec["transitions"])].append(rec)
    if len(budgets) > 1:
        warn(f"softae plot: {where} holds {len(budgets)} (env, budget) groups; plotting each on its own, never pooled")
    for (env, episodes, transitions), rs in sorted(budgets.items()):
        by_method = defaultdict(list)
        for rec, label in zip(rs, row_labels([rec["config"] for rec in rs])):
            by_method[label].append(rec)
        seeds = sorted({len(v) for v in by_method.values()})
        budget = f"{episodes} episodes = {transitions} transitions per run"
        seed_text = (f"{seeds[0]} seed{'s' * (seeds[0] != 1)}" if len(seeds) == 1
                     else f"{min(seeds)}-{max(seeds)} seeds")
        prefix = f"{env}_{transitions}tr_" if len(budgets) > 1 else ""
        yield by_method, _run_entry(rs[0]["config"]), (f"{env}, {budget}, {seed_text}", budget, seed_text), prefix


def plot_comparison(folder: str | Path, warn=None, only: list | None = None) -> list[Path]:
    """Per env and budget: bars of held-out normalized MSE and zero-shot returns per method over the
    seeds, and one coverage heatmap per method (all its seeds' data), below ``folder/plots``.
    ``only``: plot just these run dirs (``softae report`` passes its finished runs, so its plots
    show what its tables average)."""
    warn = warn or (lambda msg: print(msg, file=sys.stderr))
    folder = Path(folder)
    runs = _runs_below(folder)
    if only is not None:
        keep = {Path(p).resolve() for p in only}
        runs = [r for r in runs if r.path.resolve() in keep]
    loaded = _load_ok(runs, warn)
    if not loaded:
        raise FileNotFoundError(f"no readable run (checkpoint.pt) below {folder}")
    records = [{"config": state["config"], "episodes": state["episode"] + 1, "transitions": state["num_transitions"],
                "history": state["history"], "evals": _evals(run), "references": _references(run), "run": run}
               for run, state in loaded]
    out_dir = folder / "plots"
    out_dir.mkdir(exist_ok=True)
    written = []
    for by_method, entry, (title, budget, seed_text), prefix in _budget_groups(records, warn, folder):
        written += _comparison_bars(by_method, entry, title, budget, seed_text, out_dir, prefix)
        if entry is None:
            warn(f"softae plot: {title}: the env cannot be built here, so no coverage heatmap")
            continue
        methods = label_order(by_method)
        points = {f"{m} ({len(by_method[m])} seed{'s' * (len(by_method[m]) != 1)}, cov. "
                  f"{np.mean([rec['history'][-1]['coverage'] for rec in by_method[m]]):.2f})":
                  np.concatenate([_projected(rec["run"], entry) for rec in by_method[m]]) for m in methods}
        written.append(_coverage_panels(points, entry, f"coverage by method: {title}",
                                        out_dir / f"{prefix}coverage_by_method.png"))
    return written


def plot_report(report_json: str | Path, warn=None) -> list[Path]:
    """The comparison bars (held-out MSE, zero-shot returns) redrawn from a ``softae report``
    JSON alone, into ``plots/`` beside it: a committed report keeps every run's config, history
    and evaluations, so its figures outlive the run dirs. The coverage heatmaps need the runs'
    collected states and are not redrawn (the report's own are kept)."""
    warn = warn or (lambda msg: print(msg, file=sys.stderr))
    path = Path(report_json)
    runs = read_archive(path)
    finished = [r for r in runs if is_finished(r)]
    if not finished:
        raise FileNotFoundError(f"{path} holds no finished run: nothing to plot")
    refs = Path(REFERENCES_FILE).stem  # the report archives eval/references.json among the evaluations
    records = [{"config": r["config"], "episodes": r["episodes_done"], "transitions": r["history"][-1]["transitions"],
                "history": r["history"], "evals": {t: e for t, e in r["evals"].items() if t != refs},
                "references": r["evals"].get(refs, {}).get("returns", {})}
               for r in finished]
    out_dir = path.parent / "plots"
    out_dir.mkdir(exist_ok=True)
    written = []
    for by_method, entry, (title, budget, seed_text), prefix in _budget_groups(records, warn, path):
        written += _comparison_bars(by_method, entry, title, budget, seed_text, out_dir, prefix)
    return written


def plot_budgets(records: list[dict], out_dir: str | Path) -> list[Path]:
    """One figure per env of replication records (:mod:`~torchrl_softae.pipeline.replication`):
    against the exploration budget, the held-out normalized MSE, the coverage and each task's
    zero-shot return and success metric; a thin line per seed (every seed visible), a thick one
    for the mean over the seeds at each budget, one colour per method; s' = s on the error and the
    model-free references (records with ``references``) on the returns as grey lines."""
    plt = _plt()
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    written = []
    by_env = defaultdict(list)
    for rec in records:
        by_env[rec["env"]].append(rec)
    for env, recs in sorted(by_env.items()):
        labels = row_labels([r["config"] for r in recs])
        runs = defaultdict(lambda: defaultdict(dict))  # label -> seed -> budget -> record
        for rec, label in zip(recs, labels):
            runs[label][rec["seed"]][rec["budget"]] = rec
        tasks = sorted({t for r in recs for t in r["tasks"]})
        refs = next((r["references"]["returns"] for r in recs if "references" in r), {})
        reference_panels = {f"{t} return": t for t in tasks} if refs else {}
        metric = {t: next((r["tasks"][t].get("success_metric") for r in recs if t in r["tasks"]), None) for t in tasks}
        # row 0: the model; row 1: each task's return; row 2: its success metric, under its return
        cols = max(2, len(tasks))
        grid = [[("held-out normalized MSE", lambda r: r["accuracy"]["heldout_nmse"]),
                 ("coverage", lambda r: r["coverage"])],
                [(f"{t} return", lambda r, t=t: r["tasks"][t]["mean_return"]) for t in tasks]]
        if any(metric.values()):
            grid.append([(f"{t} {metric_label(metric[t])}", lambda r, t=t: float(np.mean(
                [m[metric[t]] for m in r["tasks"][t]["metrics"]]))) if metric[t] else None for t in tasks])
        fig, axes = plt.subplots(len(grid), cols, figsize=(3.4 * cols, 2.8 * len(grid) + 0.6), squeeze=False)
        placed = [(axes[i][j], panel) for i, row in enumerate(grid) for j, panel in enumerate(row) if panel]
        for ax in axes.flat:
            if not any(ax is a for a, _ in placed):
                ax.axis("off")
        for ax, (name, value) in placed:
            for label in label_order(runs):
                color = method_color(label)
                means = {}  # budget -> every seed's value there
                for seed, per_budget in sorted(runs[label].items()):
                    values = {b: v for b, r in sorted(per_budget.items()) if (v := _value(value, r)) is not None}
                    # a marker too: a seed evaluated at one budget so far is a point, not a line
                    ax.plot(list(values), list(values.values()), ".-", color=color, lw=0.8, ms=3, alpha=0.35)
                    for b, v in values.items():
                        means.setdefault(b, []).append(v)
                budgets = sorted(means)
                counts = sorted({len(means[b]) for b in budgets}) or [0]  # seeds per budget can differ
                n = str(counts[0]) if len(counts) == 1 else f"{counts[0]}-{counts[-1]}"
                ax.plot(budgets, [np.mean(means[b]) for b in budgets], "o-", color=color, lw=2, ms=4,
                        label=f"{label} (n={n})")
            ax.set_title(name, fontsize=9)
            ax.set_xlabel("exploration episodes")
            if "MSE" in name:
                ax.set_yscale("log")
                identity = next((r["accuracy"]["heldout_nmse_identity"] for r in recs
                                 if "heldout_nmse_identity" in r["accuracy"]), None)
                if identity is not None:  # the same held-out set for every record of the env
                    ax.axhline(identity, color="0.4", ls="--", lw=1, label="s' = s (no change)")
                # after every line: set_ylim ends autoscaling, and s' = s may lie above the data
                low = ax.get_ylim()[0]
                decade = 10 ** np.floor(np.log10(low))
                if low < 2 * decade:  # show the decade's label: the lowest line would end unlabelled
                    ax.set_ylim(bottom=decade / 1.1)
            elif name in reference_panels:  # the same evaluation episodes for every record
                for (ref, per_task), ls in zip(sorted(refs.items()), (":", "-.")):
                    if per_task.get(reference_panels[name]):
                        ax.axhline(np.mean(per_task[reference_panels[name]]), color="0.3", ls=ls, lw=1, label=ref)
        legend = {}  # every panel's entries once: the methods, s' = s and the references
        for ax, _ in placed:
            for handle, label in zip(*ax.get_legend_handles_labels()):
                legend.setdefault(label, handle)
        ncol = min(len(legend), 2 * cols)  # about 1.7 inches per entry: the figure's width
        fig.legend(list(legend.values()), list(legend), loc="lower center", ncol=ncol, fontsize=8)
        bottom = (0.15 + 0.25 * -(-len(legend) // ncol)) / fig.get_figheight()  # the legend's rows
        # two lines: one would outgrow a two-column figure with a long env id
        fig.suptitle(f"{env} against the exploration budget\nthin lines: each seed; thick: the mean over seeds",
                     fontsize=10)
        written.append(_save(fig, out_dir / f"{env}_budgets.png", rect=(0, bottom, 1, 0.95)))
    return written


def plot_record_coverage(records: list[dict], out_dir: str | Path) -> list[Path]:
    """Per env and budget of replication records that carry a coverage histogram: one heatmap per
    method (transitions per cell, averaged over its seeds so methods with different seed counts
    compare) on the env's grid, one colour scale; drawn from the records alone."""
    out_dir = Path(out_dir)
    groups = defaultdict(list)
    for rec in records:
        if "coverage_histogram" in rec:
            groups[(rec["env"], rec["budget"], rec["transitions"])].append(rec)
    written = []
    for (env, budget, transitions), recs in sorted(groups.items()):
        first = recs[0]["coverage_histogram"]
        if any(r["coverage_histogram"]["bounds"] != first["bounds"] for r in recs):
            raise ValueError(f"{env}, {budget} episodes: coverage histograms on different grids (other held-out sets)")
        by_label = defaultdict(list)
        for rec, label in zip(recs, row_labels([r["config"] for r in recs])):
            by_label[label].append(rec)
        counts = {}
        for label in label_order(by_label):
            rs = sorted(by_label[label], key=lambda r: r["seed"])
            counts[f"{label} (seed{'s' * (len(rs) > 1)} {','.join(str(r['seed']) for r in rs)}; "
                   f"cov. {np.mean([r['coverage'] for r in rs]):.2f})"] = np.mean(
                [np.asarray(r["coverage_histogram"]["counts"]) for r in rs], 0)
        (x0, y0), (x1, y1) = first["bounds"]
        edges = [np.linspace(x0, x1, first["bins"] + 1), np.linspace(y0, y1, first["bins"] + 1)]
        out_dir.mkdir(parents=True, exist_ok=True)
        written.append(coverage_heatmaps(
            counts, edges, first["labels"], f"{env}: where the explored data lies after {budget} episodes "
            f"({transitions} transitions per seed)\ngrid: the held-out set's range; edge cells also hold what "
            "lies beyond", out_dir / f"{env}_coverage_{budget}ep.png", unit="transitions per cell (mean over seeds)"))
    return written


def _value(value, record):
    """``value(record)``, or ``None`` where the record lacks it (a task it did not evaluate)."""
    try:
        return value(record)
    except KeyError:
        return None


def plot_path(path: str | Path, warn=None) -> list[Path]:
    """A run dir gets its own plots; a folder of runs gets the comparison plus each run's plots
    (a broken run is skipped with a warning line)."""
    warn = warn or (lambda msg: print(msg, file=sys.stderr))
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"--run-dir {path} does not exist")
    if RunDir(path).exists():
        return plot_run(path)
    runs = _runs_below(path)
    if not runs:
        raise FileNotFoundError(f"{path} holds no run: nothing to plot (run `softae explore --run-dir {path}`)")
    written = plot_comparison(path, warn)
    for run in runs:
        try:
            written += plot_run(run.path)
        except CheckpointError as e:
            warn(f"softae plot: skipping {run.path}: {e}")
    return written
