"""``softae``: explore a robot's dynamics task-agnostically, then solve tasks zero-shot.

    softae explore  --env Pendulum-v1 --method softae --episodes 10 --seed 0 --run-dir runs/pend
    softae evaluate --run-dir runs/pend --task swingup
    softae plot     --run-dir runs/pend          (a run, or a folder of runs to compare)
    softae sweep    sweeps/pendulum.yaml         (a grid of runs, many at once on Ray Tune)
    softae report   runs                         (tables and plots from a folder of runs)
    softae demo                                  (a short exploration + evaluation + plots)

Heavy imports (torch, torchrl) happen only after the arguments parse, so ``--help`` is instant.
"""
from __future__ import annotations

import argparse
import os
import sys

from torchrl_softae.pipeline.methods import METHOD_NAMES, get_method

PRESETS = {
    "paper": [],
    # Small enough for a laptop-minute demo; the method is unchanged, only sizes/steps shrink.
    "quick": [
        "model.num_cells=128", "model.depth=3", "planner.num_candidates=100", "planner.top_k=10",
        "planner.optim_steps=3", "planner.num_particles=5", "train.lr=1e-3", "train.epochs=20",
        "train.max_grad_steps=600", "heldout_size=1000",
    ],
}


def available_cores() -> int:
    """Cores this process may run on (its CPU affinity, e.g. under ``taskset``), not the machine's."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        return os.cpu_count() or 1


def _threads(n: int | None) -> int:
    import torch

    if n is not None and n < 1:
        from torchrl_softae.pipeline.config import ConfigError

        raise ConfigError(f"--threads={n} is invalid: expected a positive number of threads")
    n = n or available_cores()
    torch.set_num_threads(n)
    return n


def _add_explore_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--env", default="Pendulum-v1", help="environment id (see `softae envs`); default Pendulum-v1")
    p.add_argument("--method", default="softae", help=f"one of {', '.join(METHOD_NAMES)}; default softae")
    p.add_argument("--episodes", type=int, default=None, help="exploration episodes N (default 10)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--run-dir", default=None, help="output folder; an existing run with the same settings resumes "
                                                   "(default runs/ENV/METHOD-bBETA-sSEED)")
    p.add_argument("--episode-length", type=int, default=None, help="exploration horizon T (env default)")
    p.add_argument("--beta", type=float, default=None,
                   help="optimism beta for the methods that use it (default: the paper's, Table S6)")
    p.add_argument("--task", default=None, help="task optimized by hucrl (and nothing else)")
    p.add_argument("--eval-every", type=int, default=None, help="zero-shot evaluate all tasks every K episodes (0 = never)")
    p.add_argument("--preset", choices=sorted(PRESETS), default="paper",
                   help="paper: Table S6/S7 sizes; quick: small model/planner for demos and tests")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                   help="override any config field, e.g. --set planner.horizon=5 --set train.lr=1e-4 (repeatable)")
    p.add_argument("--wandb", choices=["offline", "online", "disabled"], default="offline",
                   help="W&B tracking (default offline: no network needed; `wandb sync RUN/wandb/...` later)")
    p.add_argument("--threads", type=int, default=None,
                   help="torch threads (default: the cores this process may use). Two runs side by side on "
                        "2 cores: give each --threads 1 (or taskset -c 0 / -c 1), else both slow down 10x+")
    p.add_argument("--quiet", action="store_true",
                   help="no progress output (a resumed run still says so in one line)")


def _progress_style(args) -> tuple[bool, object]:
    """Bars on a terminal; one summary line per episode in a log file; nothing with --quiet."""
    if args.quiet:
        return False, None
    return sys.stderr.isatty(), print


def _config(args):
    from torchrl_softae.pipeline.config import make_config

    overrides = PRESETS[args.preset] + list(args.overrides)
    return make_config(
        args.env, args.method, overrides, episodes=args.episodes, seed=args.seed, episode_length=args.episode_length,
        beta=args.beta, task=args.task, eval_every=args.eval_every, wandb=args.wandb,
    )


def run_dir_for(cfg, root: str = "runs") -> str:
    """``ROOT/ENV/NAME`` with the name the method table gives (beta only where the method uses it)."""
    return os.path.join(root, cfg.env, get_method(cfg.method).run_name(cfg.seed, cfg.beta))


def cmd_explore(args) -> int:
    from torchrl_softae.pipeline.explore import explore

    cfg = _config(args)
    threads = _threads(args.threads)
    run_dir = args.run_dir or run_dir_for(cfg)
    progress, echo = _progress_style(args)
    if echo is not None:
        echo(f"explore {cfg.env} with {cfg.method}: {cfg.episodes} episodes x {cfg.episode_length} steps, "
             f"{_engine(cfg.planner.precision, threads)}; run dir {run_dir}")
    history = explore(cfg, run_dir, progress=progress, echo=echo)
    last = history[-1]
    print(f"{run_dir}: {last['episode'] + 1} episodes, {last['transitions']} transitions, "
          f"held-out normalized MSE {last['heldout_nmse']:.4g}, coverage {last['coverage']:.3f}; "
          f"results in {run_dir}/ (metrics.csv, checkpoint.pt, replay buffer, wandb/)")
    return 0


def _engine(precision: str, threads: int) -> str:
    from torchrl_softae.modules.precision import resolve_planning_dtype

    dtype = resolve_planning_dtype(precision)
    return f"planning in {'bf16' if dtype is not None else 'fp32'} (precision={precision}) on the CPU, {threads} torch threads"


def cmd_evaluate(args) -> int:
    from torchrl_softae.pipeline.evaluate import evaluate_run

    _threads(args.threads)
    progress, _ = _progress_style(args)
    res = evaluate_run(args.run_dir, tasks=args.task or None, episodes=args.episodes, seed=args.seed,
                       propagation=args.propagation, progress=progress, planner_overrides=args.overrides)
    print(f"{args.run_dir}: held-out normalized MSE {res['heldout_nmse']:.4g}")
    for name, r in res["tasks"].items():
        extra = ""
        if r["metrics"] and r["metrics"][0]:
            keys = [k for k, v in r["metrics"][0].items() if isinstance(v, (int, float))]
            extra = "  " + ", ".join(f"{k}={sum(m[k] for m in r['metrics']) / len(r['metrics']):.3g}" for k in keys)
        print(f"  {name:>12}: mean return {r['mean_return']:.4g} over {len(r['returns'])} episodes{extra}")
    return 0


def cmd_plot(args) -> int:
    from torchrl_softae.pipeline.plots import plot_path

    for p in plot_path(args.run_dir):
        print(p)
    return 0


def cmd_sweep(args) -> int:
    from torchrl_softae.pipeline.config import ConfigError
    from torchrl_softae.pipeline.sweep import expand, load_sweep, run_local, run_ray, trial_status

    if args.address and not args.storage:
        raise ConfigError("--address joins a Ray cluster: pass --storage PATH on a filesystem every node shares "
                          "(run dirs and Tune's results must be visible to all of them)")
    if args.cpus_per_trial < 1 or (args.jobs is not None and args.jobs < 1) or args.max_failures < 0:
        raise ConfigError("--cpus-per-trial and --jobs take a positive number, --max-failures a number >= 0")
    spec = load_sweep(args.file)
    root = args.root or (os.path.join(args.storage, "runs") if args.storage else "runs")
    trials, dropped = expand(spec, root)
    status = {t.name: trial_status(t) for t in trials}
    todo = [t for t in trials if status[t.name] != "finished"]
    keys = ", ".join(spec["parameters"])
    print(f"sweep {args.file}: {len(trials)} runs over {keys}"
          + (f" ({dropped} duplicates dropped: parameters a method ignores)" if dropped else "")
          + f"; {len(trials) - len(todo)} finished, {len(todo)} to run, under {root}")
    for t in trials:
        print(f"softae explore {' '.join(t.argv)}   [{status[t.name]}]", flush=True)
    if args.dry_run or not todo:
        return 0
    use_ray = args.jobs is None and _ray_available()
    if args.address and not use_ray:
        raise ConfigError("--address needs Ray: pip install 'torchrl-softae[ray]' (and no --jobs)")
    if use_ray:
        final = run_ray(todo, args.cpus_per_trial, args.max_failures, address=args.address, storage=args.storage,
                        num_cpus=None if args.address else max(available_cores(), args.cpus_per_trial))
    else:
        jobs = args.jobs or max(1, available_cores() // args.cpus_per_trial)
        print(f"engine: local processes ({'Ray is not installed; ' if args.jobs is None else ''}{jobs} at a time, "
              f"{args.cpus_per_trial} torch thread(s) each)", flush=True)
        final = run_local(todo, jobs, args.cpus_per_trial, args.max_failures)
    unfinished = [n for n, st in final.items() if st != "finished"]
    print(f"sweep done: {len(final) - len(unfinished)} of {len(final)} trials finished"
          + (f"; unfinished: {', '.join(unfinished)} (rerun the same command to resume them)" if unfinished else "")
          + f". Tables: softae report {root}")
    return 1 if unfinished else 0


def _ray_available() -> bool:
    import importlib.util

    return importlib.util.find_spec("ray") is not None


def cmd_report(args) -> int:
    from torchrl_softae.pipeline.report import report

    md, json_path, md_path, plots = report(args.root, plots=not args.no_plots)
    print(md)
    print(f"\nwrote {md_path} and {json_path}" + (f"; plots: {', '.join(str(p) for p in plots)}" if plots else ""))
    return 0


def cmd_demo(args) -> int:
    run_dir = args.run_dir
    steps = [
        ["explore", "--env", "Pendulum-v1", "--method", "softae", "--preset", "quick", "--episodes", str(args.episodes),
         "--run-dir", run_dir, "--wandb", args.wandb],
        ["evaluate", "--run-dir", run_dir, "--task", "swingup", "--episodes", "1"],
        ["plot", "--run-dir", run_dir],
    ]
    for argv in steps:
        print("\n$ softae " + " ".join(argv), flush=True)
        rc = main(argv)
        if rc:
            return rc
    print(f"\nplots in {os.path.join(run_dir, 'plots')}")
    return 0


def cmd_envs(args) -> int:
    from torchrl_softae.pipeline.catalog import env_ids, get_env_entry

    for env_id in env_ids():
        e = get_env_entry(env_id)
        print(f"{env_id:>20}  tasks: {', '.join(sorted(e.tasks)):<30} {e.description}")
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="softae", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    sub = parser.add_subparsers(dest="command", required=True)

    p = sub.add_parser("explore", help="explore an env task-agnostically and learn its dynamics",
                       description="Episode-wise active exploration (paper, Algorithm 1). Writes checkpoint, "
                                   "replay buffer, logs; rerunning the same command resumes a killed run.")
    _add_explore_args(p)
    p.set_defaults(func=cmd_explore)

    p = sub.add_parser("evaluate", help="zero-shot task returns and model accuracy of a run")
    p.add_argument("--run-dir", required=True)
    p.add_argument("--task", action="append", default=[], help="task name (repeatable; default: all tasks of the env)")
    p.add_argument("--episodes", type=int, default=3)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--propagation", default="mean",
                   help="how the planner propagates the model for the task: a mode of EnsembleModelEnv "
                        "(default mean); optimistic plans with the run's beta")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="planner.KEY=VALUE",
                   help="plan the task differently from exploration, e.g. --set planner.horizon=30 (repeatable)")
    p.add_argument("--threads", type=int, default=None)
    p.add_argument("--quiet", action="store_true")
    p.set_defaults(func=cmd_evaluate)

    p = sub.add_parser("plot", help="coverage heatmaps, curves and bars as PNG files")
    p.add_argument("--run-dir", required=True, help="a run dir, or a folder of runs to compare methods")
    p.set_defaults(func=cmd_plot)

    p = sub.add_parser("sweep", help="run a W&B sweep file's grid as many runs at once (Ray Tune, or local processes)",
                       description="Each run is one `softae explore` in its own run dir ROOT/ENV/NAME; a killed run "
                                   "is retried and resumes; rerunning the same command skips finished runs. On a "
                                   "cluster: `ray start --head` on one node, `ray start --address=HEAD:6379` on the "
                                   "others, then `softae sweep FILE --address auto --storage /shared/path`.")
    p.add_argument("file", help="sweep YAML (W&B format: method grid|random, parameters with values/value, command)")
    p.add_argument("--root", default=None, help="runs go to ROOT/ENV/NAME (default runs, or STORAGE/runs)")
    p.add_argument("--dry-run", action="store_true", help="list the runs and their state only")
    p.add_argument("--cpus-per-trial", type=int, default=1,
                   help="CPUs Tune reserves for a run, and its torch threads (default 1: no oversubscription)")
    p.add_argument("--jobs", type=int, default=None,
                   help="run as N local processes instead of Ray (default: Ray if installed, else cores / cpus-per-trial)")
    p.add_argument("--max-failures", type=int, default=2, help="retries of a crashed run (it resumes); default 2")
    p.add_argument("--address", default=None, help="join a Ray cluster (HOST:PORT or auto) instead of an embedded Ray")
    p.add_argument("--storage", default=None, help="a path every cluster node shares (required with --address)")
    p.set_defaults(func=cmd_sweep)

    p = sub.add_parser("report", help="the paper's tables and plots from a folder of runs (a sweep or runs by hand)")
    p.add_argument("root", help="a folder of run dirs")
    p.add_argument("--no-plots", action="store_true")
    p.set_defaults(func=cmd_report)

    p = sub.add_parser("demo", help="a short Pendulum exploration, evaluation and plots (a few minutes)")
    p.add_argument("--run-dir", default=os.path.join("runs", "demo"))
    p.add_argument("--episodes", type=int, default=6)
    p.add_argument("--wandb", choices=["offline", "online", "disabled"], default="offline")
    p.set_defaults(func=cmd_demo)

    p = sub.add_parser("envs", help="list environments and their tasks")
    p.set_defaults(func=cmd_envs)
    return parser


def _plain_output() -> None:
    """W&B without its banner, TorchRL without INFO lines (and their colour codes)."""
    import logging

    os.environ.setdefault("WANDB_SILENT", "true")
    os.environ.setdefault("RL_LOGGING_LEVEL", "WARNING")  # read when torchrl is first imported
    logging.getLogger("torchrl").setLevel(os.environ["RL_LOGGING_LEVEL"])  # in case it already was


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    _plain_output()
    from torchrl_softae.envs.robots.rendering import RenderingUnavailable
    from torchrl_softae.pipeline.config import ConfigError
    from torchrl_softae.pipeline.runs import CheckpointError

    try:
        return args.func(args)
    except (ConfigError, CheckpointError, FileNotFoundError, RenderingUnavailable) as e:
        print(f"softae: error: {e}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
