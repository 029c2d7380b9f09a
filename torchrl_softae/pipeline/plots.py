"""Pictures of a run (or of a folder of runs), saved as PNG files."""
from __future__ import annotations

import json
from collections import defaultdict
from pathlib import Path

import numpy as np
import torch

from torchrl_softae.pipeline.runs import RunDir

__all__ = ["plot_run", "plot_comparison", "plot_path"]


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _transitions(run: RunDir):
    state = run.load()
    rb = run.load_replay_buffer(state)
    return rb.storage[: len(rb)]


def plot_coverage(run: RunDir, entry, ax=None, bins: int = 40):
    plt = _plt()
    p = entry.project(_transitions(run))
    p = p[torch.isfinite(p).all(-1)].numpy()
    own = ax is None
    if own:
        fig, ax = plt.subplots(figsize=(5, 4))
    h = ax.hist2d(p[:, 0], p[:, 1], bins=bins, cmap="viridis", cmin=1)
    ax.set_xlabel(entry.projection_labels[0])
    ax.set_ylabel(entry.projection_labels[1])
    if own:
        fig.colorbar(h[3], ax=ax, label="transitions")
        return fig
    return ax


def plot_run(run_dir: str | Path) -> list[Path]:
    """Coverage heatmap, learning curves and task-return curves/bars of one run."""
    from torchrl_softae.pipeline.catalog import get_env_entry

    plt = _plt()
    run = RunDir(run_dir)
    state = run.load()
    cfg = state["config"]
    entry = get_env_entry(cfg["env"])
    history = state["history"]
    written = []

    fig = plot_coverage(run, entry)
    fig.axes[0].set_title(f"{cfg['env']} coverage, {cfg['method']} ({state['num_transitions']} transitions)")
    out = run.plots / "coverage.png"
    fig.tight_layout()
    fig.savefig(out, dpi=120)
    plt.close(fig)
    written.append(out)

    ep = [r["episode"] + 1 for r in history]
    fig, axes = plt.subplots(1, 2, figsize=(9, 3.5))
    axes[0].plot(ep, [r["heldout_nmse"] for r in history], "o-")
    axes[0].set_yscale("log")
    axes[0].set_xlabel("episode")
    axes[0].set_ylabel("held-out normalized MSE")
    axes[1].plot(ep, [r["coverage"] for r in history], "o-", color="C1")
    axes[1].set_xlabel("episode")
    axes[1].set_ylabel("coverage (fraction of cells)")
    fig.suptitle(f"{cfg['env']} / {cfg['method']} / seed {cfg['seed']}")
    fig.tight_layout()
    out = run.plots / "learning_curves.png"
    fig.savefig(out, dpi=120)
    plt.close(fig)
    written.append(out)

    curves = sorted({k for r in history for k in r if k.startswith("return/")})
    if curves:
        fig, ax = plt.subplots(figsize=(5, 3.5))
        for k in curves:
            pts = [(r["episode"] + 1, r[k]) for r in history if k in r]
            ax.plot(*zip(*pts), "o-", label=k.split("/", 1)[1])
        ax.set_xlabel("episode")
        ax.set_ylabel("zero-shot return")
        ax.legend()
        fig.tight_layout()
        out = run.plots / "return_curves.png"
        fig.savefig(out, dpi=120)
        plt.close(fig)
        written.append(out)

    evals = sorted(p for p in (run.path / "eval").glob("*.json") if p.stem != "model_accuracy") if (run.path / "eval").exists() else []
    if evals:
        fig, ax = plt.subplots(figsize=(5, 3.5))
        names = [p.stem for p in evals]
        res = [json.loads(p.read_text())["returns"] for p in evals]
        ax.bar(names, [np.mean(r) for r in res], yerr=[np.std(r) for r in res], capsize=4)
        ax.set_ylabel("zero-shot return")
        ax.set_title("evaluation")
        fig.tight_layout()
        out = run.plots / "eval_returns.png"
        fig.savefig(out, dpi=120)
        plt.close(fig)
        written.append(out)
    return written


def _runs_below(folder: Path) -> list[RunDir]:
    return sorted((RunDir(p.parent) for p in folder.rglob("checkpoint.pt")), key=lambda r: str(r.path))


def plot_comparison(folder: str | Path) -> list[Path]:
    """Bars of held-out normalized MSE and zero-shot returns per method over the runs below ``folder``,
    and one coverage heatmap per method (first seed)."""
    from torchrl_softae.pipeline.catalog import get_env_entry

    plt = _plt()
    folder = Path(folder)
    runs = _runs_below(folder)
    if not runs:
        raise FileNotFoundError(f"no run (checkpoint.pt) below {folder}")
    by_method: dict[str, list] = defaultdict(list)
    for run in runs:
        state = run.load()
        by_method[state["config"]["method"]].append((run, state))
    methods = sorted(by_method)
    out_dir = folder / "plots"
    out_dir.mkdir(exist_ok=True)
    written = []

    fig, ax = plt.subplots(figsize=(1.2 * len(methods) + 2, 3.5))
    vals = [[s["history"][-1]["heldout_nmse"] for _, s in by_method[m]] for m in methods]
    ax.bar(methods, [np.mean(v) for v in vals], yerr=[np.std(v) for v in vals], capsize=4, color="C0")
    ax.set_ylabel("held-out normalized MSE")
    ax.set_yscale("log")
    fig.tight_layout()
    out = out_dir / "mse_bars.png"
    fig.savefig(out, dpi=120)
    plt.close(fig)
    written.append(out)

    tasks = sorted({p.stem for r in runs if (r.path / "eval").exists() for p in (r.path / "eval").glob("*.json")} - {"model_accuracy"})
    if tasks:
        fig, axes = plt.subplots(1, len(tasks), figsize=(3.2 * len(tasks) + 1, 3.5), squeeze=False)
        for ax, task in zip(axes[0], tasks):
            means = []
            for m in methods:
                rs = [np.mean(json.loads((r.path / "eval" / f"{task}.json").read_text())["returns"])
                      for r, _ in by_method[m] if (r.path / "eval" / f"{task}.json").exists()]
                means.append((np.mean(rs) if rs else np.nan, np.std(rs) if rs else 0))
            ax.bar(methods, [m[0] for m in means], yerr=[m[1] for m in means], capsize=4, color="C2")
            ax.set_title(task)
            ax.tick_params(axis="x", rotation=30)
        axes[0][0].set_ylabel("zero-shot return")
        fig.tight_layout()
        out = out_dir / "task_returns.png"
        fig.savefig(out, dpi=120)
        plt.close(fig)
        written.append(out)

    entry = get_env_entry(by_method[methods[0]][0][1]["config"]["env"])
    fig, axes = plt.subplots(1, len(methods), figsize=(3.6 * len(methods), 3.3), squeeze=False, sharex=True, sharey=True)
    for ax, m in zip(axes[0], methods):
        run, state = by_method[m][0]
        plot_coverage(run, entry, ax=ax)
        ax.set_title(f"{m} (cov. {state['history'][-1]['coverage']:.2f})")
    fig.tight_layout()
    out = out_dir / "coverage_by_method.png"
    fig.savefig(out, dpi=120)
    plt.close(fig)
    written.append(out)
    return written


def plot_path(path: str | Path) -> list[Path]:
    """A run dir gets its own plots; a folder of runs gets the comparison plus each run's plots."""
    path = Path(path)
    if RunDir(path).exists():
        return plot_run(path)
    runs = _runs_below(path)
    if not runs:
        raise FileNotFoundError(f"{path} holds no run: nothing to plot (run `softae explore --run-dir {path}`)")
    written = plot_comparison(path)
    for run in runs:
        written += plot_run(run.path)
    return written
