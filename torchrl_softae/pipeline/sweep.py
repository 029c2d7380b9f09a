"""Sweeps: a W&B sweep file's grid, run as many ``softae explore`` trials at once on Ray Tune
(embedded on this machine, or a cluster), or as local processes without Ray.

A trial is one exploration run in its own run dir, ``ROOT/ENV/NAME`` (the name the method table
gives); the run dir is the checkpoint. A crashed trial is retried and resumes from its last
episode; rerunning a killed sweep skips finished trials and resumes the others. Each trial
reports one result per episode to Tune and logs to its own offline W&B run (stable id).

Sweep file (W&B's format, so ``wandb sweep FILE`` works where a W&B server exists)::

    method: grid                   # or random (with run_cap); bayes needs a W&B server
    parameters:
      method: {values: [random, softae]}
      seed: {values: [0, 1, 2]}
      beta: {value: 2.0}
    command: [${program}, explore, --env, Pendulum-v1, --preset, quick, ${args}]
    evaluate:                      # optional, ours: zero-shot evaluation of each finished run
      tasks: [swingup]
      episodes: 3
      propagation: mean
      planner: {horizon: 30}
      references: true             # + model-free references on the same episodes (report rows)
    policy:                        # optional, ours: `softae policy` (SAC on the model) per task
      tasks: [swingup, spin]
      episodes: 5                  # real evaluation episodes
      propagation: mean            # default: mean, or the method's own for mbpo / mbpo-ts
"""
from __future__ import annotations

import contextlib
import functools
import io
import itertools
import json
import os
import random
import subprocess
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

from torchrl_softae.pipeline import replication
from torchrl_softae.pipeline.config import ConfigError
from torchrl_softae.pipeline.methods import get_method

__all__ = ["Trial", "load_sweep", "expand", "trial_status", "run_trial", "run_local", "run_ray", "progress_line"]

PROGRESS_PREFIX = "@softae-progress "  # a local trial's result rows on its stdout, for the driver


@dataclass
class Trial:
    """One exploration run of a sweep (+ its evaluation)."""

    name: str
    argv: list[str]  # ``softae explore`` arguments, --run-dir included
    run_dir: Path
    episodes: int
    evaluate: dict | None = None
    params: dict = field(default_factory=dict)
    policy: dict | None = None  # the sweep file's ``policy`` block
    seed: int = 0
    method: str = "softae"
    # where the driver stood: a module:attr env or task is imported from there in every worker
    # (Tune runs a trial in its own directory)
    search_path: list[str] = field(default_factory=list)
    replication: dict | None = None  # the sweep file's ``replication`` block (pipeline.replication)
    heldout_note: str = ""  # where its held-out set comes from, when not the catalog env's (catalog.heldout_note)

    def to_json(self) -> dict:
        """What a trial process (local or Ray) needs to run it."""
        return {"name": self.name, "argv": self.argv, "run_dir": str(self.run_dir), "episodes": self.episodes,
                "evaluate": self.evaluate, "policy": self.policy, "seed": self.seed, "method": self.method,
                "search_path": self.search_path, "replication": self.replication}

    @classmethod
    def from_json(cls, d: dict) -> "Trial":
        return cls(d["name"], d["argv"], Path(d["run_dir"]), d["episodes"], d["evaluate"], policy=d.get("policy"),
                   seed=d.get("seed", 0), method=d.get("method", "softae"), search_path=d.get("search_path", []),
                   replication=d.get("replication"))

    def policy_propagation(self) -> str:
        """The propagation of its task policies: the block's, else the method's own for methods that
        train a policy (MBPO-TS samples), else mean."""
        return (self.policy or {}).get("propagation") or get_method(self.method).policy_propagation


def load_sweep(path: str | Path) -> dict:
    import yaml

    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"sweep file {path} does not exist")
    try:
        spec = yaml.safe_load(path.read_text())
    except yaml.YAMLError as e:
        raise ConfigError(f"{path} is not valid YAML ({str(e).splitlines()[0]})") from None
    if not isinstance(spec, dict) or not isinstance(spec.get("parameters"), dict):
        raise ConfigError(f"{path}: a sweep file needs a 'parameters' mapping (W&B sweep format)")
    return spec


def _combinations(spec: dict) -> list[dict]:
    params = spec["parameters"]
    for name, p in params.items():
        if not isinstance(p, dict) or not ({"values", "value"} & set(p)):
            raise ConfigError(f"parameter {name!r}: expected 'values: [...]' or 'value: x' "
                              "(distributions need W&B's own controller)")
    grid = {k: p["values"] for k, p in params.items() if "values" in p}
    fixed = {k: p["value"] for k, p in params.items() if "value" in p}
    kind = spec.get("method", "grid")
    if kind == "bayes":
        raise ConfigError("sweep method 'bayes' needs W&B's sweep controller, i.e. a W&B server: run "
                          "`wandb sweep FILE` + `wandb agent` there, or use method grid or random here")
    combos = [{**fixed, **dict(zip(grid, c))} for c in itertools.product(*grid.values())]
    if kind == "random":
        cap = spec.get("run_cap")
        if not isinstance(cap, int) or cap < 1:
            raise ConfigError(f"sweep method 'random' needs run_cap (a positive integer), got {cap!r}")
        rng = random.Random(int(spec.get("seed", 0)))
        combos = [{**fixed, **{k: rng.choice(v) for k, v in grid.items()}} for _ in range(cap)]
    elif kind != "grid":
        raise ConfigError(f"sweep method {kind!r}; valid here: grid, random (bayes needs a W&B server)")
    return combos


def expand(spec: dict, root: str | Path) -> tuple[list[Trial], int]:
    """Trials of a sweep, validated (every config checked before anything runs); returns the
    trials and the number of combinations dropped as duplicates (parameters a method ignores)."""
    from torchrl_softae.pipeline.arguments import config_from_args, explore_parser, run_dir_for
    from torchrl_softae.pipeline.catalog import heldout_note

    parser = explore_parser()
    flags = {o[2:].replace("-", "_") for a in parser._actions for o in a.option_strings
             if o.startswith("--")} - {"help", "run_dir"}
    for name in spec["parameters"]:
        if name.replace("-", "_") not in flags:
            raise ConfigError(f"unknown sweep parameter {name!r}; valid: {', '.join(sorted(flags))}")
    base = [a for a in spec.get("command", []) if not str(a).startswith("${")]
    base = [str(a) for a in base[base.index("explore") + 1:]] if "explore" in base else []
    trials, seen, total = [], set(), 0
    for run in _combinations(spec):
        total += 1
        for name in get_method(str(run.get("method", "softae"))).ignored_settings:
            run.pop(name, None)  # it does not change this method: one run, not one per value
        key = tuple(sorted((k, str(v)) for k, v in run.items()))
        if key in seen:
            continue
        seen.add(key)
        argv = ["explore", *base]
        for k, v in run.items():
            if k == "set":  # --set takes a list of KEY=VALUE
                argv += [x for item in (v if isinstance(v, list) else [v]) for x in ("--set", str(item))]
            else:
                argv.append(f"--{k.replace('_', '-')}={v}")
        try:
            cfg = config_from_args(parser.parse_args(argv[1:]))
        except SystemExit:
            raise ConfigError(f"sweep run {run}: the arguments {' '.join(argv[1:])} do not parse") from None
        except ConfigError as e:
            raise ConfigError(f"sweep run {run}: {e}") from None
        run_dir = Path(run_dir_for(cfg, str(root))).resolve()
        name = f"{run_dir.parent.name}/{run_dir.name}"
        if cfg.heldout_file:  # absolute: a Ray trial runs in its own directory
            argv.append(f"--heldout={cfg.heldout_file}")
        evaluate = _evaluate_block(spec, cfg)
        trials.append(Trial(name, argv[1:] + [f"--run-dir={run_dir}"], run_dir, cfg.episodes, evaluate, dict(run),
                            policy=_policy_block(spec, cfg), seed=cfg.seed, method=cfg.method,
                            search_path=[os.getcwd()], replication=replication.check_block(spec, cfg, evaluate),
                            heldout_note=heldout_note(cfg)))
    return trials, total - len(trials)


#: what a sweep's evaluate block may say
EVALUATE_KEYS = ("tasks", "episodes", "propagation", "planner", "references")


def _evaluate_block(spec: dict, cfg) -> dict | None:
    """The sweep's ``evaluate`` block, checked against the run's env before anything runs."""
    from torchrl_softae.envs.model_env import PROPAGATION_MODES

    block = spec.get("evaluate")
    if block is None:
        return None
    if not isinstance(block, dict):
        raise ConfigError(f"the sweep's evaluate block: expected a mapping of {', '.join(EVALUATE_KEYS)}, got {block!r}")
    unknown = sorted(set(block) - set(EVALUATE_KEYS))
    if unknown:
        raise ConfigError(f"evaluate block: unknown key(s) {', '.join(map(repr, unknown))}; valid: {', '.join(EVALUATE_KEYS)}")
    block = dict(block)
    block["task_names"] = _task_names("evaluate", block.get("tasks") or [], cfg)
    if block.get("propagation", "mean") not in PROPAGATION_MODES:
        raise ConfigError(f"evaluate block: propagation {block['propagation']!r}; valid: {', '.join(PROPAGATION_MODES)}")
    if not isinstance(block.get("references", False), bool):
        raise ConfigError(f"evaluate block: references {block['references']!r}; expected true or false")
    return block


def _task_names(where: str, tasks: list, cfg) -> list[str]:
    """The names of the tasks a block lists (a ``module:attr`` reference may stand for several),
    checked against the run's env before anything runs."""
    from torchrl_softae.pipeline.catalog import get_env_entry, get_tasks

    try:
        entry = get_env_entry(cfg.env)
        return [name for task in tasks for name in get_tasks(entry, str(task))]
    except ValueError as e:
        raise ConfigError(f"{where} block: {e}") from None


def _policy_block(spec: dict, cfg) -> dict | None:
    """The sweep's ``policy`` block, checked against the run's env before anything runs."""
    block = spec.get("policy")
    if block is None:
        return None
    if not isinstance(block, dict) or not block.get("tasks"):
        raise ConfigError("the sweep's policy block needs 'tasks: [...]' (and optionally episodes, propagation, updates)")
    block = dict(block)
    block["task_names"] = _task_names("policy", block["tasks"], cfg)
    if len(block["task_names"]) != len(block["tasks"]):
        raise ConfigError(f"policy block: tasks {block['tasks']} name {len(block['task_names'])} tasks: a SAC policy "
                          "is trained per task, so list each task (or a reference naming exactly one)")
    return block


def _policies_trained(trial: Trial) -> bool:
    from torchrl_softae.pipeline.policy import policy_dir_name
    from torchrl_softae.pipeline.runs import POLICIES_DIR

    if not trial.policy:
        return True
    return all((trial.run_dir / POLICIES_DIR / policy_dir_name(task, trial.policy_propagation(), trial.seed,
                                                               trial.episodes) / "eval.json").exists()
               for task in trial.policy["task_names"])


def trial_status(trial: Trial) -> str:
    """``"finished"``, ``"partial k/N"`` or ``"new"`` from the run dir alone."""
    from torchrl_softae.pipeline.runs import RunDir

    history = RunDir(trial.run_dir).history()
    done = len(history)
    if trial.replication:  # finished when every budget has its record
        missing = replication.missing_budgets(trial.replication, trial.run_dir)
        if not missing and _policies_trained(trial):
            return "finished"
        return f"partial {done}/{trial.episodes}, {len(trial.replication['budgets']) - len(missing)} of " \
               f"{len(trial.replication['budgets'])} budgets recorded" if done else "new"
    if done >= trial.episodes and _evaluated(trial) and _policies_trained(trial):
        return "finished"
    return f"partial {done}/{trial.episodes}" if done else "new"


def _evaluated(trial: Trial) -> bool:
    from torchrl_softae.pipeline.evaluate import REFERENCES_FILE, eval_file_name, planner_overrides, saved_result

    if not trial.evaluate:
        return True
    eval_dir = trial.run_dir / "eval"
    tasks = trial.evaluate["task_names"]
    # what the evaluate block asks of each saved result (the planner settings are in its file name):
    # a block edited since (more episodes, another propagation) is not finished
    wanted = {"episodes_explored": trial.episodes, "episodes": int(trial.evaluate.get("episodes", 3)),
              "propagation": trial.evaluate.get("propagation", "mean")}
    overrides = planner_overrides(trial.evaluate.get("planner"))
    if any(saved_result(eval_dir / eval_file_name(task, overrides), wanted) is None for task in tasks):
        return False
    if trial.evaluate.get("references"):
        f = eval_dir / REFERENCES_FILE
        refs = json.loads(f.read_text()) if f.exists() else {}
        if refs.get("episodes") != int(trial.evaluate.get("episodes", 3)) or \
                not all(t in per_task for per_task in refs["returns"].values() for t in tasks):
            return False
    return (eval_dir / "model_accuracy.json").exists()


def run_trial(trial: Trial, threads: int, on_episode=None) -> dict:
    """Explore (resuming), evaluate and train its task policies (resuming) in this process; returns
    its last result row."""
    import torch

    from torchrl_softae.allocator import keep_freed_memory
    from torchrl_softae.pipeline.arguments import config_from_args, explore_parser
    from torchrl_softae.pipeline.guards import RunLock

    for path in trial.search_path:
        if path not in sys.path:
            sys.path.append(path)
    torch.set_num_threads(threads)
    keep_freed_memory()  # as the softae commands do (a Ray worker does not run them)
    cfg = config_from_args(explore_parser().parse_args(trial.argv))
    Path(trial.run_dir).mkdir(parents=True, exist_ok=True)
    with RunLock(trial.run_dir, note=None):  # the trial's whole life: explore, evaluate, policies
        return _run_trial(trial, cfg, on_episode)


def _run_trial(trial: Trial, cfg, on_episode) -> dict:
    from torchrl_softae.pipeline.evaluate import evaluate_run, planner_overrides
    from torchrl_softae.pipeline.explore import explore

    if trial.replication:  # the last budget is the run's episodes: nothing is left to explore
        history = replication.run_budgets(trial, cfg, on_episode, on_task=_task_events(on_episode),
                                          on_steps=_step_events(on_episode))
    else:
        history = explore(cfg, trial.run_dir, progress=False, echo=None, on_episode=on_episode)
    row = dict(history[-1])
    if trial.evaluate and not trial.replication and not _evaluated(trial):
        ev = trial.evaluate
        # a task a killed trial already evaluated for this model is kept (``resume``)
        res = evaluate_run(trial.run_dir, tasks=ev.get("tasks"), episodes=int(ev.get("episodes", 3)),
                           propagation=ev.get("propagation", "mean"), progress=False,
                           planner_overrides=planner_overrides(ev.get("planner")),
                           references=bool(ev.get("references")), resume=True, on_task=_task_events(on_episode),
                           on_steps=_step_events(on_episode, history[-1]["episode"] + 1))
        row.update({f"return/{k}": v["mean_return"] for k, v in res["tasks"].items()})
        if on_episode is not None:
            on_episode({**history[-1], **row, "evaluated": 1})
    if trial.policy and not _policies_trained(trial):
        from torchrl_softae.pipeline.policy import train_policy

        for task in trial.policy["tasks"]:
            res = train_policy(trial.run_dir, task, propagation=trial.policy_propagation(),
                               updates=trial.policy.get("updates"), episodes=int(trial.policy.get("episodes", 5)),
                               seed=trial.seed, progress=False, echo=None)
            row[f"policy_return/{res['task']}"] = res["mean_return"]
        if on_episode is not None:
            on_episode({**history[-1], **row, "policies_trained": 1})
    return row


def _task_events(on_episode):
    """``evaluate_run``'s ``on_task`` that reports each task evaluated as a trial event: a task
    planned at a long horizon is long work, and the sweep shows each as it ends."""
    if on_episode is None:
        return None

    def on_task(name, result, kept):
        on_episode({"episode": result["episodes_explored"] - 1, f"task_return/{name}": result["mean_return"],
                    "task_evaluated": 1, "kept": int(kept), "attempts": result.get("attempts", 1)})
    return on_task


#: seconds between two lines of a task in evaluation: at H = 100 a task runs for an hour on a core
#: without AMX, and its trial prints nothing else meanwhile
TASK_PROGRESS_SECONDS = 300.0


def _step_events(on_episode, explored: int | None = None):
    """``on_steps(episodes_explored, name, done, total)`` (``on_steps(name, done, total)`` for the
    model of ``explored`` episodes) that reports a task's progress as a trial event at most every
    :data:`TASK_PROGRESS_SECONDS`, with the time left at this attempt's pace (the steps read back
    from a killed attempt excluded)."""
    if on_episode is None:
        return None
    seen: dict[tuple, list] = {}  # (episodes_explored, task) -> [t0, done at t0, last report]

    def on_steps(explored, name, done, total):
        now = time.perf_counter()
        if (explored, name) not in seen:  # the pace is measured from the first count on
            seen[explored, name] = [now, done, now]
            return
        t0, done0, last = seen[explored, name]
        if now - last < TASK_PROGRESS_SECONDS or done == done0 or done >= total:
            return
        seen[explored, name][2] = now
        on_episode({"episode": explored - 1, f"task_steps/{name}": done, "task_total_steps": total,
                    "seconds_left": (total - done) * (now - t0) / (done - done0)})
    return on_steps if explored is None else functools.partial(on_steps, explored)


def _duration(seconds: float) -> str:
    return f"{seconds:.0f} s" if seconds < 90 else f"{seconds / 60:.0f} min" if seconds < 5400 else f"{seconds / 3600:.1f} h"


# ---------------------------------------------------------------------------- engines
def _result(row: dict) -> dict:
    """What a trial reports per event (to Tune, or to the local driver): the row's finite numbers."""
    return {k: v for k, v in row.items() if isinstance(v, (int, float)) and v == v}


def progress_line(name: str, row: dict, episodes: int) -> str:
    """The sweep's one line per trial event: an explored episode, a task's progress and its end, the
    evaluation, the task policies."""
    if row.get("policies_trained"):
        what = ", ".join(f"{k.split('/', 1)[1]} {v:.3g}" for k, v in row.items() if k.startswith("policy_return/"))
        return f"trial {name}: task policies trained (real returns: {what})"
    if row.get("evaluated"):
        what = ", ".join(f"{k.split('/', 1)[1]} {v:.3g}" for k, v in row.items() if k.startswith("return/"))
        return f"trial {name}: evaluated zero-shot (returns: {what})"
    steps = [(k.split("/", 1)[1], int(v)) for k, v in row.items() if k.startswith("task_steps/")]
    if steps:
        (task, done), total = steps[0], int(row["task_total_steps"])
        return (f"trial {name}: zero-shot {task} with the model of episode {int(row['episode']) + 1}: "
                f"{done}/{total} steps ({done / total:.0%}), about {_duration(row['seconds_left'])} left")
    if row.get("task_evaluated"):
        what = ", ".join(f"{k.split('/', 1)[1]} with the model of episode {int(row['episode']) + 1}: mean return "
                         f"{v:.4g}" for k, v in row.items() if k.startswith("task_return/"))
        if row.get("kept"):
            what += " (kept from an earlier attempt)"
        elif row.get("attempts", 1) > 1:
            what += f" (went on where a killed attempt stopped: {int(row['attempts'])} attempts)"
        return f"trial {name}: zero-shot {what}"
    return (f"trial {name}: episode {int(row['episode']) + 1}/{episodes}, held-out normalized MSE "
            f"{row.get('heldout_nmse', float('nan')):.4g}, coverage {row.get('coverage', float('nan')):.3f}")


def run_local(trials: list[Trial], jobs: int, threads: int, max_failures: int, echo=print) -> dict:
    """Each trial as a ``softae`` subprocess, ``jobs`` at a time; a failed one is retried
    ``max_failures`` times (it resumes from its run dir). Each trial's episodes are echoed as they
    finish (:func:`progress_line`). Returns {trial name: status}."""
    import tempfile

    status: dict[str, str] = {}
    lock = threading.Lock()
    pending = list(trials)

    def attempt(trial: Trial) -> tuple[int, str]:
        cmd = [sys.executable, "-m", "torchrl_softae.pipeline.sweep", "--trial", json.dumps(trial.to_json()),
               "--threads", str(threads)]
        # stderr to a file, not a pipe: nothing blocks while stdout is read line by line
        with tempfile.TemporaryFile("w+") as err:
            proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=err, text=True)
            for line in proc.stdout:
                if line.startswith(PROGRESS_PREFIX):
                    with lock:
                        echo(progress_line(trial.name, json.loads(line[len(PROGRESS_PREFIX):]), trial.episodes))
            rc = proc.wait()
            err.seek(0)
            last = [ln.strip() for ln in err.read().splitlines() if ln.strip()]
        return rc, last[-1] if last else ""

    def worker():
        while True:
            with lock:
                if not pending:
                    return
                trial = pending.pop(0)
            for n in range(max_failures + 1):
                rc, last_error = attempt(trial)
                if rc == 0:
                    break
                with lock:
                    echo(f"trial {trial.name} exited with code {rc} (attempt {n + 1})"
                         + (f": {last_error}" if last_error else "") + "; "
                         + ("retrying: it resumes from its run dir" if n < max_failures else "giving up"))
            with lock:
                status[trial.name] = trial_status(trial)
                echo(f"trial {trial.name}: {status[trial.name]}")

    threads_ = [threading.Thread(target=worker) for _ in range(max(1, jobs))]
    for t in threads_:
        t.start()
    for t in threads_:
        t.join()
    return status


def _ray_trainable(config: dict) -> None:
    """A Tune function trainable: one trial (``config["trial"]``), one result per event (an episode,
    a task's progress, a task, the evaluation)."""
    from ray import tune

    t = config["trial"]
    trial = Trial.from_json(t)

    run_trial(trial, t["threads"], on_episode=lambda row: tune.report(_result(row)))


def check_ray_target(address: str | None, storage: str | None) -> None:
    """``--address`` (``HOST:PORT``, ``ray://HOST:PORT`` or ``auto``) and ``--storage`` (a folder this
    process can write, made if missing), checked before any trial starts: one line each."""
    import re

    if address is not None and not re.fullmatch(r"auto|(ray://)?[A-Za-z0-9._\-]+:\d{1,5}", address):
        raise ConfigError(f"--address {address!r}: expected HOST:PORT, ray://HOST:PORT or auto")
    if storage is not None:
        path = Path(storage)
        try:
            path.mkdir(parents=True, exist_ok=True)
            probe = path / f".softae-write-test-{os.getpid()}"
            probe.write_text("")
            probe.unlink()
        except OSError as e:
            raise ConfigError(f"--storage {storage!r}: expected a folder this process can write ({e.strerror})") from None


#: where :func:`_to_terminal` writes while :func:`ray_output_to` redirects everything else (a module
#: global, not a closure: Tune pickles its callbacks, and an open file cannot be pickled)
_TERMINAL: dict = {}


def _to_terminal(line: str) -> None:
    print(line, file=_TERMINAL.get("stream", sys.stdout), flush=True)


@contextlib.contextmanager
def ray_output_to(log_file: Path | None, echo=print):
    """Inside the block, everything this process and the processes it starts print (Ray's logs,
    Tune's tables, worker stack traces) goes to ``log_file``; the block gets the ``echo`` for our own
    lines, which still reach the terminal. ``log_file=None``: nothing is redirected."""
    if log_file is None:
        yield echo
        return
    log_file.parent.mkdir(parents=True, exist_ok=True)
    log = open(log_file, "a", buffering=1)  # noqa: SIM115 (closed below)
    for stream in (sys.stdout, sys.stderr):
        stream.flush()
    try:  # our lines go where stdout went: the terminal's descriptor, or a Python-level capture
        terminal = os.fdopen(os.dup(sys.stdout.fileno()), "w", buffering=1) if sys.stdout.fileno() == 1 else sys.stdout
    except (AttributeError, OSError, ValueError, io.UnsupportedOperation):
        terminal = sys.stdout
    saved_fds, saved_streams = (os.dup(1), os.dup(2)), (sys.stdout, sys.stderr)
    os.dup2(log.fileno(), 1)
    os.dup2(log.fileno(), 2)
    sys.stdout = sys.stderr = log
    _TERMINAL["stream"] = terminal
    try:
        yield _to_terminal
    finally:
        _TERMINAL.pop("stream", None)
        sys.stdout, sys.stderr = saved_streams
        for fd, saved in zip((1, 2), saved_fds):
            os.dup2(saved, fd)
            os.close(saved)
        if terminal is not saved_streams[0]:
            terminal.close()
        log.close()


def _error_line(trial) -> str:
    """The exit code (where the error names one) and last line of a failed Tune trial's latest
    failure, from its error file, without Ray's advice on common causes."""
    import re

    text = ""
    path = getattr(trial, "error_file", None)
    if path and os.path.exists(path):
        text = Path(path).read_text().rsplit("Failure # ", 1)[-1]
    text = text.split(" Some common causes", 1)[0]
    code = re.search(r"exit(?:ed with)? code:? (-?\d+)", text, re.IGNORECASE)
    last = [ln.strip() for ln in text.splitlines()[1:] if ln.strip()]
    return (f"failed with exit code {code.group(1)}" if code else "failed") + (f": {last[-1][:300]}" if last else "")


def _tune_name(trial) -> str:
    """A Tune trial's name and folder: ours without the characters a path or URI would parse."""
    return trial.config["trial"]["name"].replace("/", "_").replace(":", "_")


def run_ray(trials: list[Trial], cpus_per_trial: int, max_failures: int, address: str | None = None,
            storage: str | None = None, num_cpus: int | None = None, echo=print, log_file: Path | None = None,
            dashboard: bool = False) -> dict:
    """The trials on Ray Tune: an embedded local Ray (no dashboard unless ``dashboard``) or the cluster
    at ``address`` (``storage``: Tune's results on a filesystem all nodes share). Only our lines reach
    the terminal (a line per finished episode and evaluation, per failed attempt with Ray's last line
    on it and the exit code where Ray names one); Ray's own output goes to ``log_file`` (``None``: to the terminal too)."""
    os.environ.setdefault("RAY_AUTH_MODE", "disabled")  # no token file under the home folder for a local Ray
    os.environ.setdefault("RAY_DEDUP_LOGS", "0")
    with ray_output_to(log_file, echo) as say:
        return _run_ray(trials, cpus_per_trial, max_failures, address, storage, num_cpus, say, log_file, dashboard)


def _run_ray(trials, cpus_per_trial, max_failures, address, storage, num_cpus, echo, log_file, dashboard) -> dict:
    import ray
    from ray import tune

    t0 = time.perf_counter()
    quiet = log_file is not None
    if address is None:
        ray.init(num_cpus=num_cpus, include_dashboard=dashboard, log_to_driver=not quiet, configure_logging=False,
                 ignore_reinit_error=True)
    else:
        try:
            ray.init(address=address, log_to_driver=not quiet, ignore_reinit_error=True)
        except (ConnectionError, RuntimeError, ValueError) as e:
            raise ConfigError(f"--address {address!r}: cannot join that Ray cluster ({str(e).splitlines()[0]})") from None
    echo(f"engine: Ray {ray.__version__} ({'embedded, ' + str(int(ray.cluster_resources().get('CPU', 0))) + ' CPUs' if address is None else 'cluster at ' + address}), "
         f"{cpus_per_trial} CPU(s) and torch thread(s) per trial; started in {time.perf_counter() - t0:.1f} s"
         + (f"; Ray's own output in {log_file}" if quiet else ""))
    storage_path = str(Path(storage).resolve()) if storage else str((trials[0].run_dir.parents[1] / ".tune").resolve())
    attempts: dict[str, int] = {}

    class Progress(tune.Callback):
        """The driver's one line per trial result and per failed attempt (the trials run quietly)."""

        def on_trial_result(self, iteration, trials, trial, result, **info):
            t = trial.config["trial"]
            echo(progress_line(t["name"], result, t["episodes"]))

        def on_trial_recover(self, iteration, trials, trial, **info):  # failed, and Tune retries it
            self._failed(trial, "retrying: it resumes from its run dir")

        def on_trial_error(self, iteration, trials, trial, **info):  # failed for the last time
            self._failed(trial, "giving up")

        def _failed(self, trial, what: str) -> None:
            name = trial.config["trial"]["name"]
            attempts[name] = attempts.get(name, 0) + 1
            echo(f"trial {name} {_error_line(trial)} (attempt {attempts[name]}); {what}")

    tuner = tune.Tuner(
        tune.with_resources(_ray_trainable, {"cpu": cpus_per_trial}),
        param_space={"trial": tune.grid_search([{**t.to_json(), "threads": cpus_per_trial} for t in trials])},
        tune_config=tune.TuneConfig(trial_name_creator=_tune_name, trial_dirname_creator=_tune_name),
        run_config=tune.RunConfig(name=f"softae-sweep-{int(time.time())}", storage_path=storage_path,
                                  failure_config=tune.FailureConfig(max_failures=max_failures),
                                  verbose=0 if quiet else 2, callbacks=[Progress()]),
    )
    tuner.fit()
    if address is None:
        ray.shutdown()
    status = {t.name: trial_status(t) for t in trials}
    for name, st in status.items():
        echo(f"trial {name}: {st}")
    return status


def main(argv=None) -> int:
    """Entry of a local trial subprocess (``--trial JSON``)."""
    import argparse

    p = argparse.ArgumentParser()
    p.add_argument("--trial", required=True)
    p.add_argument("--threads", type=int, default=1)
    args = p.parse_args(argv)

    run_trial(Trial.from_json(json.loads(args.trial)), args.threads,
              on_episode=lambda row: print(PROGRESS_PREFIX + json.dumps(_result(row)), flush=True))
    return 0


if __name__ == "__main__":
    sys.exit(main())
