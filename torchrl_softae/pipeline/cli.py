"""``softae``: explore a robot's dynamics task-agnostically, then solve tasks zero-shot.

    softae explore  --env Pendulum-v1 --method softae --episodes 10 --seed 0 --run-dir runs/pend
    softae evaluate --run-dir runs/pend --task swingup
    softae policy   --run-dir runs/pend --task swingup   (SAC on the run's model: SoftAE-MBPO)
    softae plot     --run-dir runs/pend          (a run, or a folder of runs to compare)
    softae plot     --report REPORT.json         (a report's comparison bars, without its run dirs)
    softae sweep    sweeps/pendulum.yaml         (a grid of runs, many at once on Ray Tune)
    softae report   runs                         (tables and plots from a folder of runs)
    softae demo                                  (a short exploration + evaluation + plots)

Heavy imports (torch, torchrl) happen only after the arguments parse, so ``--help`` is instant.
"""
from __future__ import annotations

import argparse
import os
import signal
import sys
from pathlib import Path

from torchrl_softae.pipeline.arguments import PRESETS, available_cores, run_dir_for  # noqa: F401 (public)
from torchrl_softae.pipeline.arguments import add_explore_args as _add_explore_args
from torchrl_softae.pipeline.arguments import config_from_args as _config

def _threads(n: int | None) -> int:
    import torch

    if n is not None and n < 1:
        from torchrl_softae.pipeline.config import ConfigError

        raise ConfigError(f"--threads={n} is invalid: expected a positive number of threads")
    n = n or available_cores()
    torch.set_num_threads(n)
    return n


def _progress_style(args) -> tuple[bool, object]:
    """Bars on a terminal; one summary line per episode in a log file; nothing with --quiet."""
    if args.quiet:
        return False, None
    return sys.stderr.isatty(), print


def cmd_explore(args) -> int:
    from torchrl_softae.pipeline.catalog import heldout_note
    from torchrl_softae.pipeline.explore import explore

    cfg = _config(args)
    note = heldout_note(cfg)
    threads = _threads(args.threads)
    run_dir = args.run_dir or run_dir_for(cfg)
    progress, echo = _progress_style(args)
    if echo is not None:
        echo(f"explore {cfg.env} with {cfg.method}: {cfg.episodes} episodes x {cfg.episode_length} steps, "
             f"{_engine(cfg.planner.precision, threads)}; run dir {run_dir}" + (f"; {note}" if note else ""))
    history = explore(cfg, run_dir, progress=progress, echo=echo)
    last = history[-1]
    print(f"{run_dir}: {last['episode'] + 1} episodes, {last['transitions']} transitions, "
          f"held-out normalized MSE {last['heldout_nmse']:.4g}{f' [{note}]' if note else ''}, coverage {last['coverage']:.3f}; "
          f"results in {run_dir}/ (metrics.csv, checkpoint.pt, replay buffer, wandb/)")
    return 0


def _engine(precision: str, threads: int) -> str:
    from torchrl_softae.modules.engine.precision import fast_bf16_available, resolve_planning_dtype

    dtype = resolve_planning_dtype(precision)
    line = f"planning in {'bf16' if dtype is not None else 'fp32'} (precision={precision}) on the CPU, {threads} torch threads"
    if dtype is not None and not fast_bf16_available():  # torch emulates bf16 there: far below fp32
        line += ("; this CPU has no native bf16 (AMX-BF16, AVX512-BF16), so bf16 planning runs far slower "
                 "than fp32: --set planner.precision=auto picks fp32 here")
    return line


def cmd_evaluate(args) -> int:
    from torchrl_softae.pipeline.catalog import ENV_HELDOUT
    from torchrl_softae.pipeline.evaluate import evaluate_run

    _threads(args.threads)
    progress, _ = _progress_style(args)
    kept = []  # the tasks --resume read back

    def on_task(name, _, was_kept):
        if was_kept:
            kept.append(name)

    res = evaluate_run(args.run_dir, tasks=args.task or None, episodes=args.episodes, seed=args.seed,
                       propagation=args.propagation, progress=progress, planner_overrides=args.overrides,
                       references=args.references, resume=args.resume, on_task=on_task)
    note = "" if res["heldout_set"] == ENV_HELDOUT else f" [{res['heldout_set']}]"
    print(f"{args.run_dir}: held-out normalized MSE {res['heldout_nmse']:.4g}{note}")
    for name, r in res["tasks"].items():
        extra = _metrics_summary(r["metrics"])
        extra = "  " + extra if extra else ""
        if name in kept:
            extra += " (kept: evaluated before, --resume)"
        elif r.get("attempts", 1) > 1:
            extra += f" (went on where a killed attempt stopped, --resume: {r['attempts']} attempts)"
        print(f"  {name:>12}: mean return {r['mean_return']:.4g} over {len(r['returns'])} episodes{extra}")
    for label, per_task in (res.get("references") or {}).get("returns", {}).items():
        print(f"  {label}: " + ", ".join(f"{t} {sum(v) / len(v):.4g}" for t, v in per_task.items() if t in res["tasks"]))
    return 0


def _metrics_summary(metrics: list[dict]) -> str:
    """``name=mean`` over the episodes of each numeric success metric, or ``""``."""
    if not metrics or not metrics[0]:
        return ""
    keys = [k for k, v in metrics[0].items() if isinstance(v, (int, float))]
    return ", ".join(f"{k}={sum(m[k] for m in metrics) / len(metrics):.3g}" for k in keys)


def cmd_policy(args) -> int:
    from torchrl_softae.pipeline.policy import train_policy

    _threads(args.threads)
    progress, echo = _progress_style(args)
    res = train_policy(args.run_dir, args.task, propagation=args.propagation, updates=args.updates,
                       episodes=args.episodes, seed=args.seed, overrides=args.overrides,
                       checkpoint_updates=args.checkpoint_every, progress=progress,
                       echo=echo or (lambda *_: None))
    extra = _metrics_summary(res["metrics"])
    extra = ", " + extra if extra else ""
    start = "the run's own policy + " if res["from_run_policy"] else ""
    print(f"{args.run_dir}: SAC policy for {args.task} ({start}{res['updates_done']} updates on the model, "
          f"{res['transitions']} real transitions): mean real return {res['mean_return']:.4g} over "
          f"{len(res['returns'])} episodes{extra}")
    return 0


def cmd_plot(args) -> int:
    from torchrl_softae.pipeline.plots import plot_path, plot_report

    if args.report is not None:
        written = plot_report(args.report)
        print("(the coverage heatmaps need the run dirs: not redrawn from a report)", file=sys.stderr)
    else:
        written = plot_path(args.run_dir)
    for p in written:
        print(p)
    return 0


def cmd_sweep(args) -> int:
    from torchrl_softae.pipeline.config import ConfigError
    from torchrl_softae.pipeline.sweep import check_ray_target, expand, load_sweep, run_local, run_ray, trial_status

    if args.address and not args.storage:
        raise ConfigError("--address joins a Ray cluster: pass --storage PATH on a filesystem every node shares "
                          "(run dirs and Tune's results must be visible to all of them)")
    if args.cpus_per_trial < 1 or (args.jobs is not None and args.jobs < 1) or args.max_failures < 0:
        raise ConfigError("--cpus-per-trial and --jobs take a positive number, --max-failures a number >= 0")
    check_ray_target(args.address, args.storage)
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
    for note in sorted({t.heldout_note for t in trials} - {""}):
        print(f"note: {note}", flush=True)
    if args.dry_run or not todo:
        return 0
    use_ray = args.jobs is None and _ray_available()
    if args.address and not use_ray:
        raise ConfigError("--address needs Ray: pip install 'torchrl-softae[ray]' (and no --jobs)")
    if use_ray:
        final = run_ray(todo, args.cpus_per_trial, args.max_failures, address=args.address, storage=args.storage,
                        num_cpus=None if args.address else max(available_cores(), args.cpus_per_trial),
                        log_file=None if args.verbose else Path(root) / "ray.log", dashboard=args.dashboard)
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

    md, json_path, md_path, plots = report(args.root, plots=not args.no_plots, merge=args.merge)
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
    print("and any registered gymnasium id (Reacher-v5), module:EnvId-v0 or module:callable; tasks by module:attr")
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
    p.add_argument("--task", action="append", default=[],
                   help="a task of the env, or module:attr naming your own Task, a dict of them or a function "
                        "returning either (repeatable; default: all tasks of the env)")
    p.add_argument("--episodes", type=int, default=3)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--propagation", default="mean",
                   help="how the planner propagates the model for the task: a mode of EnsembleModelEnv "
                        "(default mean); optimistic plans with the run's beta")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="planner.KEY=VALUE",
                   help="plan the task differently from exploration, e.g. --set planner.horizon=30 (repeatable)")
    p.add_argument("--references", action="store_true",
                   help="also the returns of model-free references (random actions, no control) on the same episodes")
    p.add_argument("--resume", action="store_true",
                   help="keep each task already evaluated for this model with these settings, by the same code "
                        "on the same machine (a killed evaluation goes on from the task it was in)")
    p.add_argument("--threads", type=int, default=None)
    p.add_argument("--quiet", action="store_true")
    p.set_defaults(func=cmd_evaluate)

    p = sub.add_parser("policy", help="train a SAC policy for a task on a run's model and data (MBPO), then evaluate it",
                       description="SAC on imagined rollouts of the run's model, branched from its real states "
                                   "(SoftAE-MBPO for a SoftAE run). Writes RUN/policies/TASK-PROPAGATION-sSEED-epEPISODES/; "
                                   "rerunning the same command resumes a killed training.")
    p.add_argument("--run-dir", required=True)
    p.add_argument("--task", required=True, help="a task of the run's env (see `softae envs`), or module:attr naming your own")
    p.add_argument("--propagation", default="mean", help="the model env's mode in the rollouts (default mean = MBPO; "
                                                          "sample = MBPO-TS)")
    p.add_argument("--updates", type=int, default=None,
                   help="SAC updates (default policy.updates_per_step x the run's real transitions)")
    p.add_argument("--episodes", type=int, default=5, help="real evaluation episodes (default 5)")
    p.add_argument("--checkpoint-every", type=int, default=1000, help="SAC updates between checkpoints (default 1000)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="policy.KEY=VALUE",
                   help="override a SAC setting, e.g. --set policy.num_cells=256 (repeatable)")
    p.add_argument("--threads", type=int, default=None)
    p.add_argument("--quiet", action="store_true")
    p.set_defaults(func=cmd_policy)

    p = sub.add_parser("plot", help="coverage heatmaps, curves and bars as PNG files")
    what = p.add_mutually_exclusive_group(required=True)
    what.add_argument("--run-dir", help="a run dir, or a folder of runs to compare methods")
    what.add_argument("--report", help="a report.json of softae report: its comparison bars redrawn without the run dirs")
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
    p.add_argument("--verbose", action="store_true",
                   help="Ray's own logs, tables and stack traces on the terminal too (default: in ROOT/ray.log)")
    p.add_argument("--dashboard", action="store_true", help="start Ray's dashboard (embedded Ray only; default none)")
    p.set_defaults(func=cmd_sweep)

    p = sub.add_parser("report", help="the paper's tables and plots from a folder of runs (a sweep or runs by hand)")
    p.add_argument("root", help="a folder of run dirs")
    p.add_argument("--merge", action="append", default=[], metavar="REPORT.json",
                   help="also the runs archived in an earlier report (their run dirs gone); a run dir below "
                        "ROOT replaces an archived run of the same ENV/NAME (repeatable)")
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


def plain_output() -> None:
    """W&B without its banner, TorchRL without INFO lines (and their colour codes): what the CLI
    and the long benchmarks print goes to log files."""
    import logging

    os.environ.setdefault("WANDB_SILENT", "true")
    os.environ.setdefault("RL_LOGGING_LEVEL", "WARNING")  # read when torchrl is first imported
    logging.getLogger("torchrl").setLevel(os.environ["RL_LOGGING_LEVEL"])  # in case it already was


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    plain_output()
    from torchrl_softae.allocator import keep_freed_memory

    keep_freed_memory()  # planners allocate large tensors at every model step: reuse, not page faults
    from torchrl_softae.envs.robots.rendering import RenderingUnavailable
    from torchrl_softae.pipeline.config import ConfigError
    from torchrl_softae.pipeline.guards import RunLocked, Stopped, write_failure
    from torchrl_softae.pipeline.runs import CheckpointError
    from torchrl_softae.references import BadReference

    # past a file-size limit (RLIMIT_FSIZE) a write fails with EFBIG instead of killing the process
    signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
    try:
        return args.func(args)
    except (ConfigError, BadReference, CheckpointError, FileNotFoundError, RenderingUnavailable, RunLocked) as e:
        print(f"softae: error: {e}", file=sys.stderr)
        return 2
    except Stopped as e:
        where = (f" at episode {e.done + 1} of {e.total} ({e.done} complete and saved)"
                 if e.total is not None and e.done < e.total else "")
        print(f"softae: stopped by {e}{where}; rerun the same command to resume", file=sys.stderr)
        return e.exit_code
    except OSError as e:
        line = write_failure(e)
        if line is None:
            raise
        print(f"softae: error: {line}", file=sys.stderr)
        return 1


if __name__ == "__main__":
    sys.exit(main())
