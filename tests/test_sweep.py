"""Sweeps on Ray Tune (embedded) and on local processes: concurrent trials, a killed trial retried
and resumed bit for bit, reruns that do no work, `softae report`, and bad input before any trial."""
import importlib.util
import json
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from torchrl_softae.pipeline.cli import main

TINY = """
method: grid
parameters:
  method: {values: [random, softae]}
  seed: {values: [0, 1]}
  beta: {value: 2.0}
command:
  - ${program}
  - explore
  - "--env"
  - "Pendulum-v1"
  - "--preset"
  - "quick"
  - "--episodes"
  - "3"
  - "--episode-length"
  - "20"
  - "--set"
  - "planner.horizon=2"
  - "--set"
  - "planner.num_candidates=8"
  - "--set"
  - "planner.top_k=2"
  - "--set"
  - "train.epochs=1"
  - "--set"
  - "heldout_size=50"
  - "--set"
  - "train.precision=fp32"  # "auto" times both dtypes: the resumed and the reference run must train alike
  - "--wandb"
  - "disabled"
  - "--quiet"
  - ${args}
evaluate: {tasks: [swingup], episodes: 1, planner: {horizon: 2}, references: true}
"""
HAS_RAY = importlib.util.find_spec("ray") is not None
# the same sweep over an env and tasks from the user's own module (tests/outside_envs.py)
OUTSIDE_ENV = "outside_envs:OutsidePoint-v0"
OUTSIDE = TINY.replace('"Pendulum-v1"', f'"{OUTSIDE_ENV}"').replace("tasks: [swingup]", "tasks: [outside_envs:point_tasks]")


def _write(tmp_path, text=TINY, name="sweep.yaml"):
    f = tmp_path / name
    f.write_text(text)
    return f


def _model(run_dir):
    return torch.load(Path(run_dir) / "checkpoint.pt", weights_only=False)["model"]


def _check_progress(out, env="Pendulum-v1", task="swingup"):
    """One line per explored episode and per evaluation of every trial, as they happen."""
    for name in ("random-s0", "random-s1", "softae-b2-s0", "softae-b2-s1"):
        lines = [ln for ln in out.splitlines() if ln.startswith(f"trial {env}/{name}: ")]
        assert any("episode 1/3, held-out normalized MSE" in ln for ln in lines), lines
        assert any("episode 3/3, held-out normalized MSE" in ln for ln in lines), lines
        assert any(f"evaluated zero-shot (returns: {task} " in ln for ln in lines), lines


def _check_sweep(tmp_path, root, capsys, env="Pendulum-v1", tasks=("swingup",)):
    runs = sorted(p.parent for p in Path(root).rglob("checkpoint.pt"))
    assert [p.name for p in runs] == ["random-s0", "random-s1", "softae-b2-s0", "softae-b2-s1"]
    for run in runs:
        history = [json.loads(x) for x in (run / "metrics.jsonl").read_text().splitlines()]
        assert [h["episode"] for h in history] == [0, 1, 2]  # no repeated, no missing episode
        assert all((run / "eval" / f"{task}@horizon=2.json").exists() for task in tasks)
    killed = Path(root) / env / "softae-b2-s1"
    assert (killed / ".injected_exit").exists()  # it really died after episode 2
    # the same run, uninterrupted, in this process with the trial's single thread
    from torchrl_softae.pipeline import sweep
    from torchrl_softae.pipeline.sweep import expand, load_sweep, run_trial

    trials, _ = expand(load_sweep(tmp_path / "sweep.yaml"), tmp_path / "reference")
    ref = next(t for t in trials if t.run_dir.name == "softae-b2-s1")
    threads = torch.get_num_threads()
    rows = []
    try:
        with pytest.MonkeyPatch.context() as m:  # a line per step rather than every 5 minutes
            m.setattr(sweep, "TASK_PROGRESS_SECONDS", 0.0)
            run_trial(ref, threads=1, on_episode=rows.append)
    finally:
        torch.set_num_threads(threads)
    a, b = _model(killed), _model(ref.run_dir)
    assert all(torch.equal(a[k], b[k]) for k in a)  # bit for bit
    # a task in evaluation reports its steps as they go, with the time left at its pace
    steps = [r for r in rows if f"task_steps/{tasks[0]}" in r]
    done = [r[f"task_steps/{tasks[0]}"] for r in steps]
    total = steps[0]["task_total_steps"]
    assert done == list(range(2, done[-1] + 1)) and done[-1] < total  # one episode: a step at a time
    assert all(r["episode"] == 2 and r["seconds_left"] > 0 for r in steps)
    line = sweep.progress_line("T", steps[0], 3)
    assert line.startswith(f"trial T: zero-shot {tasks[0]} with the model of episode 3: 2/{total} steps (")
    assert line.endswith(" s left"), line
    # rerunning the finished sweep does no work
    capsys.readouterr()
    assert main(["sweep", str(tmp_path / "sweep.yaml"), "--root", str(root)]) == 0
    assert "4 finished, 0 to run" in capsys.readouterr().out


@pytest.mark.skipif(not HAS_RAY, reason="Ray is not installed (pip install 'torchrl-softae[ray]')")
def test_ray_sweep_runs_trials_concurrently_resumes_a_killed_one_and_prints_only_our_lines(tmp_path, capsys):
    """`softae sweep` as a user runs it, over an env and tasks of the user's own module in the folder
    they run it from (Tune runs each trial in a folder of its own): its terminal shows our lines only
    (one per episode, evaluation, failed attempt and trial), Ray's output lands in ROOT/ray.log, and
    no dashboard process starts."""
    import os
    import time

    f = _write(tmp_path, OUTSIDE)
    project = tmp_path / "project"
    project.mkdir()
    shutil.copy(Path(__file__).parent / "outside_envs.py", project)
    root = tmp_path / "runs"
    env = {**os.environ, "SOFTAE_EXIT_AFTER_EPISODE": "2:softae-b2-s1",
           "HOME": str(tmp_path / "home")}  # nothing may be left in the real home folder
    env.pop("PYTHONPATH", None)
    proc = subprocess.Popen([sys.executable, "-m", "torchrl_softae.pipeline.cli", "sweep", str(f), "--root", str(root),
                             "--cpus-per-trial", "1"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            env=env, cwd=project)
    dashboards = set()
    while proc.poll() is None:  # Ray's dashboard, if anything started it, is a process of its own
        ps = subprocess.run(["ps", "-eo", "pid,args"], capture_output=True, text=True).stdout
        dashboards |= {ln for ln in ps.splitlines() if "dashboard/dashboard.py" in ln}
        time.sleep(0.5)
    out, err = proc.communicate()
    assert proc.returncode == 0, err
    assert not dashboards, dashboards
    assert err == ""
    assert "engine: Ray" in out and "embedded, 2 CPUs" in out and f"Ray's own output in {root / 'ray.log'}" in out
    _check_progress(out, OUTSIDE_ENV, "reach-left")
    ours = ("sweep ", "softae explore ", "engine: ", f"trial {OUTSIDE_ENV}/", "note: ")
    assert "note: held-out set: random-action episodes (favours Random)" in out
    assert all(ln.startswith(ours) for ln in out.splitlines() if ln.strip()), out
    # Ray knows the worker died, not its exit code: the line gives Ray's last line on it
    failed = [ln for ln in out.splitlines() if ln.startswith(f"trial {OUTSIDE_ENV}/softae-b2-s1 failed")]
    assert len(failed) == 1 and ("worker process has died" in failed[0] or "Worker exit" in failed[0]), out
    assert failed[0].endswith("(attempt 1); retrying: it resumes from its run dir"), failed
    assert "Traceback" not in out and (root / "ray.log").stat().st_size > 0
    _check_sweep(tmp_path, root, capsys, OUTSIDE_ENV, ("reach-left", "reach-up"))
    assert not (tmp_path / "home" / ".ray").exists() or not any((tmp_path / "home" / ".ray").rglob("*token*"))


def test_bad_ray_targets_are_one_line_before_any_trial(tmp_path, capsys):
    f = _write(tmp_path)
    assert main(["sweep", str(f), "--root", str(tmp_path / "runs"), "--address", "not an address",
                 "--storage", str(tmp_path / "s")]) == 2
    assert capsys.readouterr().err.strip() == ("softae: error: --address 'not an address': expected HOST:PORT, "
                                               "ray://HOST:PORT or auto")
    blocked = tmp_path / "file"
    blocked.write_text("")
    assert main(["sweep", str(f), "--root", str(tmp_path / "runs"), "--storage", str(blocked / "sub")]) == 2
    assert capsys.readouterr().err.strip().startswith(f"softae: error: --storage '{blocked / 'sub'}': expected a "
                                                      "folder this process can write")
    assert not (tmp_path / "runs").exists()


def test_local_processes_sweep_resumes_a_killed_trial(tmp_path, capsys, monkeypatch):
    monkeypatch.setenv("SOFTAE_EXIT_AFTER_EPISODE", "2:softae-b2-s1")
    f = _write(tmp_path)
    root = tmp_path / "runs"
    assert main(["sweep", str(f), "--root", str(root), "--jobs", "2"]) == 0
    out = capsys.readouterr().out
    assert "engine: local processes (2 at a time" in out and "exited with code 17" in out
    _check_progress(out)
    monkeypatch.delenv("SOFTAE_EXIT_AFTER_EPISODE")
    _check_sweep(tmp_path, root, capsys)
    # an evaluate block edited since the runs were evaluated leaves them to evaluate again
    from torchrl_softae.pipeline.sweep import expand, load_sweep, trial_status

    for edit in ("episodes: 2,", "episodes: 1, propagation: sample,"):
        edited = _write(tmp_path, TINY.replace("episodes: 1,", edit), name="edited.yaml")
        assert {trial_status(t) for t in expand(load_sweep(edited), root)[0]} == {"partial 3/3"}, edit
    assert {trial_status(t) for t in expand(load_sweep(f), root)[0]} == {"finished"}

    # a run that died and was not resumed is reported as unfinished, never averaged
    unfinished = root / "Pendulum-v1" / "random-s7"
    argv = ["explore", "--env", "Pendulum-v1", "--method", "random", "--seed", "7", "--preset", "quick",
            "--episodes", "3", "--episode-length", "20", "--set", "heldout_size=50", "--set", "train.epochs=1",
            "--wandb", "disabled", "--quiet", "--run-dir", str(unfinished)]
    env = {**__import__("os").environ, "SOFTAE_EXIT_AFTER_EPISODE": "1"}
    rc = subprocess.run([sys.executable, "-m", "torchrl_softae.pipeline.cli", *argv], env=env,
                        capture_output=True).returncode
    assert rc == 17
    capsys.readouterr()
    assert main(["report", str(root)]) == 0
    out = capsys.readouterr().out
    assert "## Pendulum-v1: 3 episodes = 60 transitions per run" in out
    assert "| random | 2 |" in out and "| softae | 2 |" in out and "swingup@horizon=2 return" in out
    assert "random seed 7, 1 of 3 episodes" in out
    # its plots show the finished runs the tables average, not the unfinished one as a budget of its own
    plots = sorted(p.name for p in (root / "plots").glob("*.png"))
    assert "mse_bars.png" in plots and not any(p.startswith("Pendulum-v1_") for p in plots), plots
    # the model-free references on the same evaluation episode, one row each
    assert "| *random actions, no model* | - | - | - |" in out and "| *no control (zero action)* |" in out
    data = json.loads((root / "report.json").read_text())
    assert [r["method"] for r in data["tables"][0]["rows"]] == ["random", "softae"]
    assert data["unfinished"][0]["episodes_done"] == 1
    # the report keeps every run's history and evaluations (what survives the run dirs)
    archived = {r["run_dir"]: r for r in data["runs"]}
    assert len(archived["Pendulum-v1/random-s7"]["history"]) == 1
    finished = [r for r in data["runs"] if r["episodes_done"] == 3]
    assert len(finished) == 4 and all([h["episode"] for h in r["history"]] == [0, 1, 2] for r in finished)
    assert all(r["evals"]["swingup@horizon=2"]["returns"] for r in finished)

    # the committed report alone redraws the same comparison bars once the run dirs are gone
    drawn = {name: (root / "plots" / name).read_bytes() for name in ("mse_bars.png", "task_returns.png")}
    archive = tmp_path / "committed"
    archive.mkdir()
    (archive / "report.json").write_bytes((root / "report.json").read_bytes())
    shutil.rmtree(root)
    assert main(["plot", "--report", str(archive / "report.json")]) == 0
    assert "coverage heatmaps need the run dirs" in capsys.readouterr().err
    assert {name: (archive / "plots" / name).read_bytes() for name in drawn} == drawn
    assert main(["plot", "--report", str(root / "report.json")]) == 2
    assert "is not a file" in capsys.readouterr().err


def test_row_labels_keep_apart_runs_of_a_method_that_differ_in_more_than_the_seed():
    from torchrl_softae.pipeline.labels import label_order, row_labels

    def cfg(method, seed, beta=2.0, horizon=10, episodes=5):
        return {"method": method, "seed": seed, "beta": beta, "episodes": episodes, "wandb": "disabled",
                "planner": {"horizon": horizon}}

    configs = [cfg("softae", 0, 1.0), cfg("softae", 1, 1.0, episodes=8), cfg("softae", 0, 2.0),
               cfg("random", 0, 1.0), cfg("random", 1, 2.0),  # beta does not change random actions
               cfg("mean-ae", 0, horizon=5), cfg("mean-ae", 1, horizon=20)]
    labels = row_labels(configs)
    assert labels == ["softae beta=1", "softae beta=1", "softae beta=2", "random", "random",
                      "mean-ae planner.horizon=5", "mean-ae planner.horizon=20"]
    assert label_order(labels) == ["random", "mean-ae planner.horizon=20", "mean-ae planner.horizon=5",
                                   "softae beta=1", "softae beta=2"]
    # a run written before a config field existed ran at its default: it is not set apart by it
    older, newer = cfg("softae", 0), cfg("softae", 1)
    older["model"], newer["model"] = {"depth": 4}, {"depth": 4, "symlog": False}
    assert row_labels([older, newer]) == ["softae", "softae"]
    newer["model"]["symlog"] = True
    assert row_labels([older, newer]) == ["softae model.symlog=False", "softae model.symlog=True"]


def test_report_and_plots_never_average_runs_of_different_beta(tmp_path, capsys):
    tiny = ["--env", "Pendulum-v1", "--preset", "quick", "--episodes", "1", "--episode-length", "20",
            "--set", "planner.horizon=2", "--set", "planner.num_candidates=8", "--set", "planner.top_k=2",
            "--set", "train.epochs=1", "--set", "heldout_size=50", "--wandb", "disabled", "--quiet"]
    root = tmp_path / "runs"
    for method, beta, seed in [("softae", 1, 0), ("softae", 2, 0), ("softae", 2, 1), ("random", 2, 0)]:
        assert main(["explore", *tiny, "--method", method, "--beta", str(beta), "--seed", str(seed),
                     "--run-dir", str(root / f"{method}-b{beta}-s{seed}")]) == 0
    assert main(["report", str(root)]) == 0
    rows = json.loads((root / "report.json").read_text())["tables"][0]["rows"]
    assert [(r["method"], r["seeds"]) for r in rows] == [("random", [0]), ("softae beta=1", [0]),
                                                          ("softae beta=2", [0, 1])]
    assert "| softae beta=2 | 2 |" in capsys.readouterr().out
    assert (root / "plots" / "mse_bars.png").exists()


@pytest.mark.parametrize("text, args, needle", [
    (TINY.replace("seed: {values", "sed: {values"), [], "unknown sweep parameter 'sed'"),
    (TINY.replace("beta: {value: 2.0}", "set: {value: planner.precision=fp8}"), [], "planner.precision='fp8'"),
    (TINY.replace("method: grid", "method: bayes"), [], "needs W&B's sweep controller"),
    (TINY, ["--address", "auto"], "--storage"),
    (TINY.replace("episodes: 1,", "episodez: 1,"), [], "evaluate block: unknown key(s) 'episodez'"),
    (TINY.replace("tasks: [swingup]", "tasks: [swingdown]"), [], "evaluate block: unknown task 'swingdown'"),
])
def test_bad_sweep_input_is_one_line_before_any_trial(tmp_path, capsys, text, args, needle):
    f = _write(tmp_path, text)
    assert main(["sweep", str(f), "--root", str(tmp_path / "runs"), *args]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and needle in err[0], err
    assert not (tmp_path / "runs").exists()


def test_random_search_with_run_cap(tmp_path, capsys):
    text = TINY.replace("method: grid", "method: random\nrun_cap: 3").replace("seed: {values: [0, 1]}",
                                                                              "seed: {values: [0, 1, 2, 3, 4, 5]}")
    f = _write(tmp_path, text)
    assert main(["sweep", str(f), "--root", str(tmp_path / "runs"), "--dry-run"]) == 0
    lines = [x for x in capsys.readouterr().out.splitlines() if x.startswith("softae explore")]
    assert 1 <= len(lines) <= 3


def test_a_sweep_policy_block_trains_task_policies_and_the_report_shows_them(tmp_path, capsys):
    """The MBPO comparison as a sweep: a ``policy`` block runs ``softae policy`` per task on every
    finished run (the method's own propagation for mbpo-ts), and ``softae report`` has a column per task."""
    text = TINY.replace("method: {values: [random, softae]}", "method: {values: [random, mbpo-ts]}").replace(
        "seed: {values: [0, 1]}", "seed: {values: [3]}\n  task: {value: swingup}").replace(
        '"3"\n', '"1"\n').replace(
        "evaluate: {tasks: [swingup], episodes: 1, planner: {horizon: 2}, references: true}",
        "policy: {tasks: [swingup, spin], episodes: 1, updates: 10}")
    text = text.replace('  - "--quiet"', '  - "--set"\n  - "policy.num_cells=16"\n  - "--set"\n  - "policy.rollout_batch=8"\n'
                        '  - "--set"\n  - "policy.updates_per_rollout=10"\n  - "--set"\n  - "policy.updates_per_step=1"\n'
                        '  - "--quiet"')
    f, root = _write(tmp_path, text), tmp_path / "runs"
    assert main(["sweep", str(f), "--root", str(root), "--jobs", "1"]) == 0
    out = capsys.readouterr().out
    assert "sweep done: 2 of 2 trials finished" in out, out
    for name, prop in (("random-s3", "mean"), ("mbpo-ts-s3", "sample")):
        for task in ("swingup", "spin"):
            res = json.loads((root / "Pendulum-v1" / name / "policies" / f"{task}-{prop}-s3-ep1" / "eval.json").read_text())
            assert len(res["returns"]) == 1 and res["seed"] == 3
    assert main(["sweep", str(f), "--root", str(root), "--jobs", "1"]) == 0  # nothing left to do
    assert "0 to run" in capsys.readouterr().out
    assert main(["report", str(root), "--no-plots"]) == 0
    md = capsys.readouterr().out
    assert "spin SAC policy return" in md and "swingup SAC policy return" in md
    rows = json.loads((root / "report.json").read_text())["tables"][0]["rows"]
    assert [r["method"] for r in rows] == ["random", "mbpo-ts"]
    assert all(len(r["policy/spin/return"]) == 1 and r["policy/spin/return"][0] is not None for r in rows)


def test_report_shows_the_heldout_error_by_group_where_runs_logged_groups(tmp_path):
    """The arm logs its held-out error per group of state dimensions; the report keeps those
    columns (mean over seeds, in logged order) beside the overall error."""
    from torchrl_softae.pipeline.config import ExploreConfig
    from torchrl_softae.pipeline.report import report

    for seed, (overall, tip, vel) in enumerate([(2.0, 0.1, 5.0), (4.0, 0.3, 7.0)]):
        run = tmp_path / "SoftArm-v0" / f"random-s{seed}"
        run.mkdir(parents=True)
        cfg = ExploreConfig(env="SoftArm-v0", method="random", episodes=1, seed=seed).to_dict()
        (run / "config.json").write_text(json.dumps({"config": cfg}))
        row = {"episode": 0, "transitions": 200, "coverage": 0.1, "heldout_nmse": overall,
               "heldout_nmse/tip": tip, "heldout_nmse/velocities": vel}
        (run / "metrics.jsonl").write_text(json.dumps(row) + "\n")
    text, json_path, _, _ = report(tmp_path, plots=False)
    table = json.loads(json_path.read_text())["tables"][0]
    assert table["columns"] == ["method", "seeds", "held-out normalized MSE", "nMSE tip", "nMSE velocities",
                                "coverage"]
    (row,) = table["rows"]
    assert row["heldout_nmse/tip"] == [0.1, 0.3] and row["heldout_nmse/velocities"] == [5.0, 7.0]
    assert "| random | 2 | 3 ± 1.4 | 0.2 ± 0.14 | 6 ± 1.4 | 0.1 ± 0 |" in text  # sample std (ddof = 1)


def test_a_sweep_drops_the_settings_a_method_ignores(tmp_path):
    """A grid of methods with a task and a beta: the task reaches only the methods that optimize
    one, beta only the methods that plan with hallucinated control, so the exploration-only
    methods keep their run names and configs (one trial each, no duplicate per task)."""
    from torchrl_softae.pipeline.sweep import expand, load_sweep

    text = TINY.replace("method: {values: [random, softae]}", "method: {values: [random, hucrl, softae]}").replace(
        "beta: {value: 2.0}", "beta: {value: 2.0}\n  task: {values: [swingup, spin]}")
    trials, dropped = expand(load_sweep(_write(tmp_path, text)), tmp_path / "runs")
    names = sorted({t.name for t in trials})
    assert names == ["Pendulum-v1/hucrl-b2-s0", "Pendulum-v1/hucrl-b2-s1", "Pendulum-v1/random-s0",
                     "Pendulum-v1/random-s1", "Pendulum-v1/softae-b2-s0", "Pendulum-v1/softae-b2-s1"]
    assert dropped == 2 * 2 * 3 - 8  # random and softae: one trial per seed, not one per task
    for t in trials:
        flags = {a.split("=")[0] for a in t.argv if a.startswith("--")}
        assert ("--task" in flags) == (t.method == "hucrl") and ("--beta" in flags) == (t.method != "random"), t.argv


def _hand_made_run(root, name, method, seed, nmse, returns, refs=None):
    """A finished one-episode run dir as ``softae explore`` + ``softae evaluate`` leave it."""
    from torchrl_softae.pipeline.config import ExploreConfig

    run = root / "Pendulum-v1" / name
    (run / "eval").mkdir(parents=True)
    cfg = ExploreConfig(env="Pendulum-v1", method=method, episodes=1, seed=seed,
                        task="swingup" if method == "hucrl" else None).to_dict()
    (run / "config.json").write_text(json.dumps({"config": cfg}))
    (run / "metrics.jsonl").write_text(json.dumps({"episode": 0, "transitions": 200, "coverage": 0.5,
                                                   "heldout_nmse": nmse}) + "\n")
    metrics = [{"upright_fraction_last_half": 0.5}] * len(returns)  # swingup's success measure
    (run / "eval" / "swingup.json").write_text(json.dumps({"returns": returns, "metrics": metrics}))
    if refs is not None:
        (run / "eval" / "references.json").write_text(json.dumps({"episodes": 1, "returns": refs}))


def test_report_merges_the_runs_archived_in_an_earlier_report(tmp_path, capsys):
    """A baseline run later beside runs whose dirs are gone: ``--merge`` puts the committed
    report's archived runs and the new run dirs in one table; a new run dir of the same
    ENV/NAME replaces its archived record; bad input is one line."""
    old, new = tmp_path / "old", tmp_path / "new"
    _hand_made_run(old, "random-s0", "random", 0, 0.4, [1.0], refs={"no control (zero action)": {"swingup": [0.5]}})
    _hand_made_run(old, "random-s1", "random", 1, 0.6, [3.0])
    assert main(["report", str(old), "--no-plots"]) == 0
    committed = tmp_path / "committed" / "report.json"
    committed.parent.mkdir()
    committed.write_bytes((old / "report.json").read_bytes())
    shutil.rmtree(old)
    _hand_made_run(new, "hucrl-b2-s0", "hucrl", 0, 0.2, [5.0])
    _hand_made_run(new, "hucrl-b2-s1", "hucrl", 1, 0.3, [7.0])
    _hand_made_run(new, "random-s1", "random", 1, 0.8, [2.0])  # rerun: replaces the archived seed 1
    capsys.readouterr()
    assert main(["report", str(new), "--merge", str(committed)]) == 0
    captured = capsys.readouterr()
    table = json.loads((new / "report.json").read_text())
    (t,) = table["tables"]
    assert [(r["method"], r["seeds"], r["heldout_nmse"], r["swingup/return"]) for r in t["rows"]] == [
        ("random", [0, 1], [0.4, 0.8], [1.0, 2.0]), ("hucrl", [0, 1], [0.2, 0.3], [5.0, 7.0])]
    assert t["references"] == {"no control (zero action)": {"swingup": [0.5]}}
    assert sorted(r["run_dir"] for r in table["runs"]) == ["Pendulum-v1/hucrl-b2-s0", "Pendulum-v1/hucrl-b2-s1",
                                                           "Pendulum-v1/random-s0", "Pendulum-v1/random-s1"]
    assert f"- {committed}: Pendulum-v1/random-s0" in captured.out
    # the bars come from the merged records; the heatmaps would need every run's collected states
    assert (new / "plots" / "mse_bars.png").exists() and (new / "plots" / "task_returns.png").exists()
    assert "without their collected states: no coverage heatmaps" in captured.err
    # the merged report is itself an archive: merging it into an empty root gives the same table
    again = tmp_path / "again"
    assert main(["report", str(again), "--merge", str(new / "report.json"), "--no-plots"]) == 0
    assert json.loads((again / "report.json").read_text())["tables"] == table["tables"]
    capsys.readouterr()
    assert main(["report", str(new), "--merge", str(tmp_path / "nope.json")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "nope.json is not a file (expected a report.json" in err[0], err


REPLICATION = TINY.replace("evaluate: {tasks: [swingup], episodes: 1, planner: {horizon: 2}, references: true}",
             "evaluate: {tasks: [swingup, spin], episodes: 1, planner: {horizon: 2}, references: true}\n"
             "replication: {budgets: [1, 3], results: RESULTS, task_episodes: {spin: 2}}")


def test_a_replication_sweep_records_every_run_at_every_budget_and_reports_them(tmp_path, capsys, monkeypatch):
    """The sweep's replication block: each run is evaluated at each budget, one self-contained
    record per (run, budget); a rerun does no work; ``softae report RESULTS`` tables each budget."""
    results = tmp_path / "results" / "Pendulum-v1"
    f = _write(tmp_path, REPLICATION.replace("RESULTS", str(results)))
    root = tmp_path / "runs"
    assert main(["sweep", str(f), "--root", str(root), "--jobs", "2"]) == 0
    names = sorted(p.name for p in results.glob("*.json"))
    assert names == [f"{run}-ep{b}.json" for run in ("random-s0", "random-s1", "softae-b2-s0", "softae-b2-s1")
                     for b in (1, 3)]
    rec = json.loads((results / "softae-b2-s1-ep1.json").read_text())
    assert rec["budget"] == 1 and rec["transitions"] == 20 and len(rec["history"]) == 1
    assert rec["config"]["episodes"] == 1 and rec["config"]["method"] == "softae"
    assert set(rec["code"]) == {"commit", "dirty"} and rec["machine"]["cpu"] and "torch" in rec["machine"]
    assert rec["accuracy"]["heldout_nmse"] == rec["history"][-1]["heldout_nmse"]
    assert "heldout_nmse_identity" in rec["accuracy"] and rec["coverage"] == rec["history"][-1]["coverage"]
    assert len(rec["tasks"]["swingup"]["returns"]) == 1 and len(rec["tasks"]["spin"]["returns"]) == 2
    assert rec["tasks"]["swingup"]["planner_horizon"] == 2
    # the CPU seconds beside the wall clock's: the exploration's are its episodes' sum
    cpu = rec["cpu_seconds"]
    assert cpu["explore"] == pytest.approx(sum(r["cpu_seconds"] for r in rec["history"])) and cpu["explore"] > 0
    assert cpu["evaluate"] > 0 and set(cpu) == set(rec["seconds"])
    # the model-free references on the same episodes, with the record
    from torchrl_softae.pipeline.evaluate import reference_returns

    refs = rec["references"]["returns"]
    assert sorted(refs) == ["no control (zero action)", "random actions, no model"]
    assert refs["no control (zero action)"]["swingup"] == reference_returns("Pendulum-v1", "swingup", "zero", 1, 0)
    assert len(refs["random actions, no model"]["spin"]) == 2 and rec["references"]["task_episodes"] == {"spin": 2}
    # the explored data's histogram on the coverage grid pools back to the recorded coverage, and one
    # of other data is refused
    from torchrl_softae.pipeline.replication import HISTOGRAM_BINS, check_histogram, pooled_coverage

    hist = rec["coverage_histogram"]
    assert hist["bins"] == HISTOGRAM_BINS and sum(map(sum, hist["counts"])) == 20 == hist["transitions"]
    assert pooled_coverage(hist) == rec["coverage"] > 0
    moved = {**hist, "counts": [[0] * HISTOGRAM_BINS for _ in range(HISTOGRAM_BINS)]}
    moved["counts"][0][0] = 20  # the same transitions, other cells
    with pytest.raises(ValueError, match="not the same data"):
        check_histogram(moved, rec["history"])
    assert rec["tasks"]["swingup"]["success_metric"] == "upright_fraction_last_half"
    # the budget-3 record continues the budget-1 run: same first episode
    late = json.loads((results / "softae-b2-s1-ep3.json").read_text())
    assert late["history"][0] == rec["history"][0] and len(late["history"]) == 3
    # killed in the budget-3 evaluation after swingup: the rerun keeps swingup (a sentinel proves it),
    # evaluates spin, counts both tasks' seconds and says so
    (results / "softae-b2-s1-ep3.json").unlink()
    evals = root / "Pendulum-v1" / "softae-b2-s1" / "eval"
    (evals / "spin@horizon=2.json").unlink()
    swingup = json.loads((evals / "swingup@horizon=2.json").read_text())
    assert swingup["episodes_explored"] == 3
    (evals / "swingup@horizon=2.json").write_text(json.dumps({**swingup, "returns": [7.0], "mean_return": 7.0,
                                                               "cpu_seconds": 1000.0}))
    # and killed again right after spin's third progress save (a save every step, then the process
    # stops): the partial's 500 CPU seconds stand for what a long killed attempt spent
    from torchrl_softae.pipeline import sweep
    from torchrl_softae.pipeline.evaluate import TaskCheckpoint
    from torchrl_softae.pipeline.sweep import expand, load_sweep, run_trial

    class Killed(Exception):
        pass

    def save_then_die(self, progress, save=TaskCheckpoint.save):
        save(self, progress)
        if self.saves == 3:
            raise Killed

    trial = next(t for t in expand(load_sweep(f), root)[0] if t.name == "Pendulum-v1/softae-b2-s1")
    threads = torch.get_num_threads()
    rows = []
    with monkeypatch.context() as m:
        m.setattr(TaskCheckpoint, "due", lambda self: True)
        m.setattr(TaskCheckpoint, "save", save_then_die)
        m.setattr(sweep, "TASK_PROGRESS_SECONDS", 0.0)  # a progress line per step
        with pytest.raises(Killed):
            run_trial(trial, threads=1, on_episode=rows.append)  # the sweep's threads: the machine is in the key
    torch.set_num_threads(threads)
    # spin's two episodes side by side, 2 env steps a step, with the budget-3 model
    assert [(r["episode"], r["task_steps/spin"]) for r in rows if "task_steps/spin" in r] == [(2, 4), (2, 6)]
    partial = evals / "spin@horizon=2.partial.pt"
    torch.save({**torch.load(partial, weights_only=True), "cpu_seconds": 500.0}, partial)
    capsys.readouterr()
    assert main(["sweep", str(f), "--root", str(root), "--jobs", "1"]) == 0
    out = capsys.readouterr().out
    assert "3 finished, 1 to run" in out
    assert "trial Pendulum-v1/softae-b2-s1: zero-shot swingup with the model of episode 3: mean return 7 " \
           "(kept from an earlier attempt)" in out, out
    assert "trial Pendulum-v1/softae-b2-s1: zero-shot spin with the model of episode 3: mean return" in out
    assert "(went on where a killed attempt stopped: 2 attempts)" in out, out
    again = json.loads((results / "softae-b2-s1-ep3.json").read_text())
    spin = again["tasks"]["spin"]  # the same returns as the uninterrupted evaluation
    assert spin["attempts"] == 2 and spin["earlier_cpu_seconds"] == 500.0 and not partial.exists()
    assert again["tasks"]["swingup"]["returns"] == [7.0] and spin == late["tasks"]["spin"] | {
        k: spin[k] for k in ("seconds", "cpu_seconds", "attempts", "earlier_seconds", "earlier_cpu_seconds")}
    # the record's evaluation counts the kept task wholly and the resumed one's killed part
    assert again["cpu_seconds"]["evaluate"] > 1500.0
    (results / "softae-b2-s1-ep3.json").write_text(json.dumps(late))  # the real record again, for the report
    assert main(["sweep", str(f), "--root", str(root)]) == 0
    assert "4 finished, 0 to run" in capsys.readouterr().out
    assert main(["report", str(results.parent)]) == 0
    md = (results.parent / "report.md").read_text()
    assert "## Pendulum-v1: 1 episodes = 20 transitions per run" in md
    assert "## Pendulum-v1: 3 episodes = 60 transitions per run" in md
    assert "| softae | 2 |" in md and "swingup@horizon=2 return" not in md and "swingup return" in md
    # the held-out baselines the records measured, as reference rows of each budget's table
    identity = f"| *s' = s* | - | {rec['accuracy']['heldout_nmse_identity']:.3g} |"
    assert md.count(identity) == 2 and md.count("| *predict the mean* | - |") == 2
    spin = refs["random actions, no model"]["spin"]
    assert md.count(f"| *random actions, no model* | - | - | - | {np.mean(spin):.3g} ± ") == 2, md
    assert (results.parent / "plots" / "Pendulum-v1_60tr_mse_bars.png").exists()  # one figure per budget
    assert (results.parent / "plots" / "Pendulum-v1_budgets.png").stat().st_size > 10_000  # every budget, every seed
    assert (results.parent / "plots" / "Pendulum-v1_coverage_3ep.png").exists()  # from the records' histograms


def test_a_replication_block_is_checked_before_any_run(tmp_path, capsys):
    f = _write(tmp_path, REPLICATION.replace("RESULTS", str(tmp_path / "r")).replace("budgets: [1, 3]",
                                                                                     "budgets: [1, 2]"))
    assert main(["sweep", str(f), "--root", str(tmp_path / "runs")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("softae: error: "), err
    assert "replication block: the budgets end at 2 episodes but the runs explore 3: set --episodes 2" in err[0]
    assert not (tmp_path / "runs").exists()


def test_the_budget_plot_keeps_no_change_in_view_and_labels_the_lowest_error(tmp_path, monkeypatch):
    """The held-out error's log axis reaches the decade below a line that ends just above one, and
    still shows the s' = s line when every model's error lies far below it."""
    import matplotlib.pyplot as plt

    from torchrl_softae.pipeline import plots

    leg = Path(__file__).resolve().parents[1] / "benchmarks" / "results" / "replication" / "MSKLeg-v0"
    recs = [json.loads(p.read_text()) for p in sorted(leg.glob("random-s*-ep*.json"))]
    for rec, err in zip(recs, np.geomspace(0.03, 0.0115, len(recs))):  # all below s' = s (0.1)
        rec["accuracy"]["heldout_nmse"] = float(err)
    figs = []
    monkeypatch.setattr(plots, "_save", lambda fig, path, rect=None: figs.append(fig) or path)
    plots.plot_budgets(recs, tmp_path)
    ax = next(a for a in figs[0].axes if "MSE" in a.get_title())
    low, high = ax.get_ylim()
    assert low <= 0.01 < 0.0115 and high >= recs[0]["accuracy"]["heldout_nmse_identity"]
    plt.close("all")
