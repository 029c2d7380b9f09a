"""End-to-end: softae explore / evaluate / plot on real gymnasium and dm_control envs (tiny sizes)."""
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch

from torchrl_softae.pipeline.cli import main
from torchrl_softae.pipeline.config import ConfigError, make_config
from torchrl_softae.pipeline.evaluate import evaluate_run
from torchrl_softae.pipeline.explore import explore
from torchrl_softae.pipeline.runs import CheckpointError, RunDir

TINY = [
    "--set", "model.num_cells=32", "--set", "model.depth=2", "--set", "planner.horizon=5",
    "--set", "planner.num_candidates=20", "--set", "planner.top_k=4", "--set", "planner.optim_steps=2",
    "--set", "planner.num_particles=2", "--set", "train.epochs=3", "--set", "train.lr=1e-3",
    "--set", "heldout_size=200",
]
TINY_OVERRIDES = [TINY[i + 1] for i in range(0, len(TINY), 2)]


def _explore_argv(run_dir, method="softae", episodes=2, env="Pendulum-v1", length=30, extra=()):
    return ["explore", "--env", env, "--method", method, "--episodes", str(episodes), "--seed", "0",
            "--run-dir", str(run_dir), "--episode-length", str(length), "--wandb", "disabled", "--quiet",
            *TINY, *extra]


@pytest.mark.parametrize("method", ["random", "mean-ae", "pets-ae", "softae", "hucrl"])
def test_two_episode_explore_writes_buffer_checkpoint_logs(tmp_path, method):
    extra = ["--task", "swingup"] if method == "hucrl" else []
    assert main(_explore_argv(tmp_path, method, extra=extra)) == 0
    run = RunDir(tmp_path)
    state = run.load()
    assert state["episode"] == 1 and state["num_transitions"] == 60
    assert (tmp_path / "replay_ep0001").is_dir() and not (tmp_path / "replay_ep0000").exists()
    rows = [json.loads(l) for l in (tmp_path / "metrics.jsonl").read_text().splitlines()]
    assert [r["episode"] for r in rows] == [0, 1]
    assert (tmp_path / "metrics.csv").read_text().startswith("collect_seconds")
    assert all(r["heldout_nmse"] > 0 and 0 < r["coverage"] <= 1 for r in rows)
    # the dtype training ran in (train.precision=auto, resolved once) is in every row and the checkpoint
    assert {r["train_precision"] for r in rows} == {state["trainer"]["precision"]} <= {"fp32", "bf16"}
    rb = run.load_replay_buffer(state)
    assert rb.storage[:60]["observation"].shape == (60, 3)


def test_dm_control_cartpole_explores(tmp_path):
    assert main(_explore_argv(tmp_path, "softae", env="cartpole-swingup", length=20)) == 0
    state = RunDir(tmp_path).load()
    assert state["num_transitions"] == 40


def _deterministic(history):
    return [{k: v for k, v in r.items() if "seconds" not in k and "ms" not in k} for r in history]


def test_killed_run_resumes_with_identical_results(tmp_path):
    argv = _explore_argv(tmp_path / "killed", "softae", episodes=5, length=40)
    cmd = [sys.executable, "-c", "import sys; from torchrl_softae.pipeline.cli import main; sys.exit(main(sys.argv[1:]))", *argv]
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
    metrics = tmp_path / "killed" / "metrics.jsonl"
    deadline = time.time() + 120
    while time.time() < deadline:  # kill -9 once two episodes are safely on disk
        if metrics.exists() and len(metrics.read_text().splitlines()) >= 2:
            break
        time.sleep(0.05)
    os.killpg(proc.pid, signal.SIGKILL)
    proc.wait()
    done_before = len(metrics.read_text().splitlines())
    assert 2 <= done_before < 5, "the run must be interrupted mid-way for this test to mean anything"
    assert main(argv) == 0  # same command: resumes
    resumed = RunDir(tmp_path / "killed").load()
    assert main(_explore_argv(tmp_path / "straight", "softae", episodes=5, length=40)) == 0
    straight = RunDir(tmp_path / "straight").load()
    assert resumed["num_transitions"] == straight["num_transitions"] == 200
    assert _deterministic(resumed["history"]) == _deterministic(straight["history"])
    for k, v in straight["model"].items():
        torch.testing.assert_close(resumed["model"][k], v, rtol=0, atol=0)


def test_evaluation_reproduces_from_saved_run(tmp_path):
    assert main(_explore_argv(tmp_path, "softae")) == 0
    a = evaluate_run(tmp_path, tasks=["swingup"], episodes=1, progress=False)
    b = evaluate_run(tmp_path, tasks=["swingup"], episodes=1, progress=False)
    assert a["tasks"]["swingup"]["returns"] == b["tasks"]["swingup"]["returns"]
    saved = json.loads((tmp_path / "eval" / "swingup.json").read_text())
    assert saved["returns"] == b["tasks"]["swingup"]["returns"]
    assert a["heldout_nmse"] == json.loads((tmp_path / "eval" / "model_accuracy.json").read_text())["heldout_nmse"]
    assert "upright_fraction_last_half" in saved["metrics"][0]


POINT = ["--env", "outside_envs:OutsidePoint-v0", "--preset", "quick", "--set", "planner.horizon=2",
         "--set", "planner.num_candidates=8", "--set", "planner.top_k=2", "--set", "train.epochs=1"]


def test_a_resumed_evaluation_keeps_the_tasks_evaluated_for_the_same_model_code_and_machine(tmp_path, capsys):
    """``--resume``: a task saved for this model, these settings, this code and this machine is read
    back (a sentinel in its file proves it), the others are planned as an uninterrupted evaluation
    plans them; another model, other code, another setting or a file that is not JSON is planned again."""
    assert main(["explore", *POINT, "--episodes", "2", "--set", "heldout_size=40", "--wandb", "disabled", "--quiet",
                 "--run-dir", str(tmp_path)]) == 0
    tasks = ["outside_envs:point_tasks"]  # reach-left, reach-up: 10 steps each
    straight = evaluate_run(tmp_path, tasks=tasks, episodes=1, progress=False)
    done = tmp_path / "eval" / "reach-left.json"
    saved = json.loads(done.read_text())
    assert saved["code"]["version"] and saved["machine"]["cpu"] and len(saved["model_sha256"]) == 64
    assert saved["cpu_seconds"] > 0 and saved["seconds"] > 0
    sentinel = {**saved, "returns": [123.0], "mean_return": 123.0}
    done.write_text(json.dumps(sentinel))  # as a process killed in the next task left it
    (tmp_path / "eval" / "reach-up.json").unlink()
    events = []
    resumed = evaluate_run(tmp_path, tasks=tasks, episodes=1, progress=False, resume=True,
                           on_task=lambda name, res, kept: events.append((name, kept)))
    assert events == [("reach-left", True), ("reach-up", False)]
    assert resumed["tasks"]["reach-left"]["returns"] == [123.0]
    assert resumed["tasks"]["reach-up"]["returns"] == straight["tasks"]["reach-up"]["returns"]
    capsys.readouterr()
    assert main(["evaluate", "--run-dir", str(tmp_path), "--task", tasks[0], "--episodes", "1", "--resume"]) == 0
    lines = {line.split(":")[0].strip(): line for line in capsys.readouterr().out.splitlines()}
    assert "mean return 123 over 1 episodes" in lines["reach-left"] and lines["reach-left"].endswith(
        "(kept: evaluated before, --resume)") and lines["reach-up"].endswith("(kept: evaluated before, --resume)")
    assert main(["evaluate", "--run-dir", str(tmp_path), "--task", tasks[0], "--episodes", "1"]) == 0  # no --resume
    assert json.loads(done.read_text())["returns"] == straight["tasks"]["reach-left"]["returns"]
    for tampered in ({**sentinel, "model_sha256": "0" * 64}, {**sentinel, "code": {**saved["code"], "commit": "0" * 40}},
                     {**sentinel, "seed": 1}, json.dumps(sentinel)[:40]):
        done.write_text(tampered if isinstance(tampered, str) else json.dumps(tampered))
        again = evaluate_run(tmp_path, tasks=tasks, episodes=1, progress=False, resume=True)
        assert again["tasks"]["reach-left"]["returns"] == straight["tasks"]["reach-left"]["returns"], tampered


def test_swingup_task_reward_matches_gymnasium():
    """The task reward computed from observations equals Pendulum-v1's own reward."""
    from torchrl.envs import GymEnv

    from torchrl_softae.pipeline.catalog import get_env_entry

    task = get_env_entry("Pendulum-v1").tasks["swingup"]
    env = GymEnv("Pendulum-v1")
    env.set_seed(0)
    traj = env.rollout(50)
    r = task.reward(traj["observation"], traj["action"], traj["next", "observation"])
    torch.testing.assert_close(r, traj["next", "reward"], atol=1e-4, rtol=1e-4)


@pytest.mark.parametrize(
    "kwargs, overrides, match",
    [
        (dict(env="Pendulum-v1", method="ucb"), [], "valid methods: random, mean-ae, pets-ae, hucrl, mbpo, mbpo-ts, softae"),
        (dict(env="Acrobot-v7", method="softae"), [], "unknown env .Acrobot-v7.: expected a catalog id .*Pendulum-v1.*, a registered gymnasium id"),
        (dict(env="Pendulum-v1", method="hucrl"), [], "pass --task, one of spin, swingup"),
        (dict(env="Pendulum-v1", method="softae", task="fly"), [], "unknown task .fly. for env .Pendulum-v1.: expected one of spin, swingup, or module:attr"),
        (dict(env="Pendulum-v1", method="softae"), ["planner.horizon=-3"], "planner.horizon=-3"),
        (dict(env="Pendulum-v1", method="softae"), ["planner.horizn=3"], "valid keys here: horizon"),
        (dict(env="Pendulum-v1", method="softae"), ["beta=-1"], "beta=-1"),
    ],
)
def test_config_validation(kwargs, overrides, match):
    with pytest.raises(ConfigError, match=match):
        make_config(kwargs.pop("env"), kwargs.pop("method"), overrides, **kwargs)


def test_cli_reports_config_errors(tmp_path, capsys):
    assert main(["explore", "--method", "nope", "--run-dir", str(tmp_path), "--wandb", "disabled"]) == 2
    assert "valid methods" in capsys.readouterr().err


def test_corrupt_and_mismatched_checkpoints_are_refused(tmp_path):
    assert main(_explore_argv(tmp_path, "random")) == 0
    # a different config in the same run dir is refused, naming the difference
    with pytest.raises(ConfigError, match="planner.horizon: stored 5 != requested 6"):
        cfg = make_config("Pendulum-v1", "random", TINY_OVERRIDES + ["planner.horizon=6"], episodes=2,
                          episode_length=30, wandb="disabled")
        explore(cfg, tmp_path, progress=False)
    (tmp_path / "checkpoint.pt").write_bytes(b"not a checkpoint")
    with pytest.raises(CheckpointError, match="corrupt"):
        cfg = make_config("Pendulum-v1", "random", TINY_OVERRIDES, episodes=3, episode_length=30, wandb="disabled")
        explore(cfg, tmp_path, progress=False)
    with pytest.raises(CheckpointError, match="corrupt"):
        evaluate_run(tmp_path)


def test_more_episodes_extend_a_finished_run(tmp_path):
    assert main(_explore_argv(tmp_path, "random", episodes=1)) == 0
    assert main(_explore_argv(tmp_path, "random", episodes=2)) == 0
    assert RunDir(tmp_path).load()["num_transitions"] == 60


def test_plots_are_written(tmp_path):
    for m in ("random", "softae"):
        assert main(_explore_argv(tmp_path / m, m)) == 0
    assert main(["plot", "--run-dir", str(tmp_path)]) == 0
    for name in ("mse_bars.png", "coverage_by_method.png"):
        assert (tmp_path / "plots" / name).stat().st_size > 1000
    assert (tmp_path / "softae" / "plots" / "coverage.png").stat().st_size > 1000


def test_sweep_file_expands_to_grid(capsys):
    root = Path(__file__).resolve().parents[1]
    assert main(["sweep", str(root / "sweeps" / "pendulum.yaml"), "--dry-run"]) == 0
    out = capsys.readouterr().out
    lines = [line for line in out.splitlines() if line.startswith("softae explore")]
    # beta only multiplies the method that uses it: 3 methods x 3 seeds + softae x 3 seeds x 2 betas
    assert len(lines) == 3 * 3 + 3 * 2 and len(set(lines)) == len(lines)
    assert "15 runs" in out and "9 duplicates dropped" in out
    assert "--method=softae --seed=0 --beta=1.0" in out
    assert not any("--beta" in line for line in lines if "--method=softae" not in line)


def test_every_committed_sweep_file_is_valid(tmp_path, capsys):
    """Each sweep under sweeps/ expands and passes every check a run would make first (config, the
    evaluate and replication blocks): a typo costs a test, not hours of replication runs."""
    root = Path(__file__).resolve().parents[1]
    files = sorted((root / "sweeps").rglob("*.yaml"))
    assert len(files) >= 12
    for f in files:
        assert main(["sweep", str(f), "--root", str(tmp_path / f.stem), "--dry-run"]) == 0, f
        assert "softae explore" in capsys.readouterr().out, f


def test_softae_covers_more_than_random(tmp_path):
    """From a hanging start, active exploration visits far more of the (angle, velocity) plane
    than random torques, which cannot pump the pendulum over the top."""
    settings = ["model.num_cells=64", "model.depth=2", "planner.horizon=10", "planner.num_candidates=40",
                "planner.top_k=5", "planner.optim_steps=3", "planner.num_particles=2", "train.lr=3e-3",
                "train.epochs=20", "heldout_size=200"]
    cov = {}
    for m in ("random", "softae"):
        cfg = make_config("Pendulum-hanging", m, settings, episodes=3, episode_length=100, wandb="disabled")
        cov[m] = explore(cfg, tmp_path / m, progress=False)[-1]["coverage"]
    assert cov["softae"] > 2 * cov["random"], cov


def test_wandb_offline_logging_needs_no_network(tmp_path, monkeypatch):
    monkeypatch.delenv("WANDB_MODE", raising=False)
    argv = _explore_argv(tmp_path, "random", episodes=1)
    argv[argv.index("--wandb") + 1] = "offline"
    assert main(argv) == 0
    runs = list((tmp_path / "wandb").glob("offline-run-*"))
    assert len(runs) == 1 and any(runs[0].glob("*.wandb"))


def test_evaluate_with_planner_overrides(tmp_path, capsys):
    assert main(_explore_argv(tmp_path, "softae", episodes=1)) == 0
    assert main(["evaluate", "--run-dir", str(tmp_path), "--task", "spin", "--episodes", "1", "--quiet",
                 "--set", "planner.horizon=3"]) == 0
    res = json.loads((tmp_path / "eval" / "spin@horizon=3.json").read_text())
    assert res["planner"]["horizon"] == 3
    assert main(["evaluate", "--run-dir", str(tmp_path), "--task", "spin", "--set", "train.lr=1"]) == 2
    assert "only overrides planner settings" in capsys.readouterr().err


def test_reference_returns_are_seeded_and_tell_random_from_no_control():
    from torchrl_softae.pipeline.evaluate import reference_returns

    rand = reference_returns("Pendulum-v1", "swingup", "random", episodes=2, seed=3)
    assert rand == reference_returns("Pendulum-v1", "swingup", "random", episodes=2, seed=3)
    zero = reference_returns("Pendulum-v1", "swingup", "zero", episodes=2, seed=3)
    assert len(zero) == 2 and zero != rand
    with pytest.raises(ValueError, match="'greedy'"):
        reference_returns("Pendulum-v1", "swingup", "greedy")


def test_batched_zero_shot_evaluation_sees_the_same_episodes(tmp_path):
    """E episodes side by side with one planner call per step: the same seeded initial states as
    one after another, reproducible, and per-episode returns and metrics."""
    from torchrl_softae.pipeline.evaluate import load_run, zero_shot

    run = tmp_path / "run"
    cfg = make_config("Pendulum-hanging", "softae", ["model.num_cells=32", "model.depth=2", "train.epochs=2",
                                                    "planner.num_candidates=16", "planner.top_k=4",
                                                    "planner.optim_steps=2", "planner.horizon=3", "heldout_size=50"],
                      episodes=1, episode_length=20, wandb="disabled")
    explore(cfg, run, progress=False, echo=None)
    cfg, model, _ = load_run(run)
    task = __import__("torchrl_softae.tasks", fromlist=["tasks_for"]).tasks_for("Pendulum-hanging")["swingup"]
    task = type(task)(**{**task.__dict__, "horizon": 15})
    a = zero_shot(cfg, model, task, episodes=3, seed=5, progress=False, batched=True)
    b = zero_shot(cfg, model, task, episodes=3, seed=5, progress=False, batched=True)
    c = zero_shot(cfg, model, task, episodes=3, seed=5, progress=False, batched=False)
    assert a == b and len(a["returns"]) == 3 and "upright_fraction_last_half" in a["metrics"][0]
    assert len(set(a["returns"])) == 3  # three different episodes, not one repeated
    assert a["initial_states"] == c["initial_states"]  # the same seeded episodes as one after another


@pytest.fixture(scope="module")
def pets_run(tmp_path_factory):
    """A tiny PETS-AE run (2 episodes of Pendulum-v1) for the tests that evaluate it again and again."""
    run = tmp_path_factory.mktemp("pets_run")
    assert main(_explore_argv(run, "pets-ae", length=20)) == 0
    return run


def test_a_task_killed_mid_episode_goes_on_from_its_last_progress_save_to_the_same_result(pets_run, capsys):
    """A batch of episodes killed between two planner calls (``TASK_FAULT_ENV``: ``os._exit``
    right after the 25th progress save) goes on there with ``--resume``: the actions replayed, the
    planner's search state and the generators restored, the same returns as an uninterrupted
    evaluation (trajectory sampling with aleatoric noise, so every generator counts). A save for
    other settings is ignored; a replay that does not reach the saved states starts over."""
    from torchrl_softae.pipeline.evaluate import TASK_FAULT_ENV, TaskCheckpoint

    tmp_path = pets_run
    kwargs = dict(tasks=["outside_envs:short_swingup"], episodes=2, propagation="sample", progress=False)
    straight = evaluate_run(tmp_path, **kwargs)["tasks"]["swingup-60"]
    result, partial = tmp_path / "eval" / "swingup-60.json", tmp_path / "eval" / "swingup-60.partial.pt"
    assert straight["returns"][0] != straight["returns"][1] and "attempts" not in straight and not partial.exists()
    result.unlink()
    code = (f"import torch; torch.set_num_threads({torch.get_num_threads()}); "  # the machine is in the key
            f"from torchrl_softae.pipeline.evaluate import evaluate_run; "
            f"evaluate_run({str(tmp_path)!r}, **{kwargs!r}, resume=True, checkpoint_seconds=0)")
    proc = subprocess.run([sys.executable, "-c", code], env={**os.environ, TASK_FAULT_ENV: "25"},
                          cwd=Path(__file__).parent, capture_output=True, text=True)  # where outside_envs is
    assert proc.returncode == 17, proc.stderr[-2000:]
    assert partial.exists() and not result.exists()
    saved = torch.load(partial, weights_only=True)
    assert saved["actions"].shape == (25, 2, 1) and saved["attempts"] == 1 and saved["seconds"] > 0
    key = json.loads(saved["key"])
    assert TaskCheckpoint(partial, key).saved is not None
    assert TaskCheckpoint(partial, {**key, "seed": 1}).saved is None
    assert TaskCheckpoint(partial, key, resume=False).saved is None

    # a replay that misses the saved states (as a non-deterministic env would) starts the task over
    kept = partial.read_bytes()
    torch.save({**saved, "observations": saved["observations"] + 1}, partial)
    capsys.readouterr()
    over = evaluate_run(tmp_path, **kwargs, resume=True)["tasks"]["swingup-60"]
    assert "replaying its 25 steps did not reach the states it saved" in capsys.readouterr().out
    assert over["returns"] == straight["returns"] and not partial.exists()

    partial.write_bytes(kept)
    result.unlink()
    assert main(["evaluate", "--run-dir", str(tmp_path), "--task", kwargs["tasks"][0], "--episodes", "2",
                 "--propagation", "sample", "--resume"]) == 0
    assert "(went on where a killed attempt stopped, --resume: 2 attempts)" in capsys.readouterr().out
    resumed = json.loads(result.read_text())
    assert resumed["returns"] == straight["returns"] and resumed["metrics"] == straight["metrics"]
    assert resumed["attempts"] == 2 and 0 < resumed["earlier_seconds"] < resumed["seconds"]
    assert not partial.exists()
    partial.write_bytes(kept)  # as a kill between writing the result and removing the progress leaves it
    assert evaluate_run(tmp_path, **kwargs, resume=True)["tasks"]["swingup-60"] == resumed
    assert not partial.exists()


@pytest.mark.parametrize("propagation", ["mean", "sample"])
def test_one_episode_as_a_batch_of_one_is_the_episode_alone(pets_run, propagation):
    """A single episode runs as a batch of one (so its progress saves go on mid-episode), with the
    returns, metrics and initial state of the same episode run alone."""
    from outside_envs import short_swingup
    from torchrl_softae.pipeline.evaluate import load_run, zero_shot

    cfg, model, _ = load_run(pets_run)
    alone, batch = (zero_shot(cfg, model, short_swingup(), episodes=1, seed=3, propagation=propagation,
                              progress=False, batched=batched) for batched in (False, True))
    assert batch == alone


def test_sequential_episodes_go_on_after_those_a_killed_attempt_finished(pets_run, tmp_path):
    """One episode after another (a task family, or ``batched=False``): each finished episode is
    saved, and a resumed attempt goes on after them (a sentinel return proves the first is read
    back); the others are those of an uninterrupted evaluation."""
    from outside_envs import short_swingup
    from torchrl_softae.pipeline.evaluate import TaskCheckpoint, load_run, zero_shot

    cfg, model, _ = load_run(pets_run)
    task = short_swingup()
    path, key = tmp_path / "task.partial.pt", {"what": "this test"}
    straight = zero_shot(cfg, model, task, episodes=2, seed=2, progress=False, batched=False,
                         checkpoint=TaskCheckpoint(path, key))
    saved = torch.load(path, weights_only=True)
    assert json.loads(saved["episodes"])["returns"] == straight["returns"]
    first = {k: v[:1] for k, v in json.loads(saved["episodes"]).items()}
    torch.save({**saved, "episodes": json.dumps({**first, "returns": [123.0]})}, path)
    resumed = zero_shot(cfg, model, task, episodes=2, seed=2, progress=False, batched=False,
                        checkpoint=TaskCheckpoint(path, key))
    assert resumed["returns"] == [123.0, *straight["returns"][1:]]
    assert resumed["initial_states"] == straight["initial_states"]


def test_episodes_read_back_advance_the_progress_bar_by_their_steps(tmp_path):
    """A resumed sequential evaluation's progress bar starts at the steps of the episodes it read
    back (the policy counts only the steps it plans)."""
    import io

    from outside_envs import short_swingup
    from torchrl.envs.utils import RandomPolicy
    from tqdm import tqdm
    from torchrl_softae.pipeline.evaluate import TaskCheckpoint, task_rollouts

    task, path, key = short_swingup(), tmp_path / "task.partial.pt", {"what": "this test"}

    def rollouts(bar=None):
        return task_rollouts("Pendulum-v1", task, 2, 0, lambda real, s, t: RandomPolicy(real.action_spec),
                             checkpoint=TaskCheckpoint(path, key), bar=bar)

    straight = rollouts()
    saved = torch.load(path, weights_only=True)
    assert json.loads(saved["episodes"])["steps"] == [task.horizon, task.horizon]
    torch.save({**saved, "episodes": json.dumps({k: v[:1] for k, v in json.loads(saved["episodes"]).items()})}, path)
    bar = tqdm(total=2 * task.horizon, file=io.StringIO())
    assert rollouts(bar) == straight and bar.n == task.horizon


def test_a_run_from_before_a_new_config_field_resumes(tmp_path):
    """Config fields added later (e.g. model.symlog) take their defaults for older runs."""
    run = tmp_path / "run"
    argv = ["explore", "--env", "Pendulum-v1", "--preset", "quick", "--episode-length", "10", "--set", "heldout_size=50",
            "--set", "train.epochs=1", "--set", "planner.horizon=2", "--wandb", "disabled", "--quiet", "--run-dir", str(run)]
    assert main([*argv, "--episodes", "1"]) == 0
    stored = json.loads((run / "config.json").read_text())
    del stored["config"]["model"]["symlog"]  # as written before the field existed
    (run / "config.json").write_text(json.dumps(stored))
    state = torch.load(run / "checkpoint.pt", weights_only=False)
    del state["config"]["model"]["symlog"]
    torch.save(state, run / "checkpoint.pt")
    assert main([*argv, "--episodes", "2"]) == 0
    assert len(RunDir(run).history()) == 2


def test_heldout_set_is_built_once_and_says_so(tmp_path, monkeypatch):
    """A build (minutes on the arm) is announced with its size and cache path; a cached read is silent
    and returns the same transitions."""
    from torchrl_softae.pipeline.catalog import get_env_entry
    from torchrl_softae.pipeline.data import heldout_set

    monkeypatch.setenv("TORCHRL_SOFTAE_CACHE", str(tmp_path))
    entry, lines = get_env_entry("Pendulum-v1"), []
    first = heldout_set(entry, None, 40, announce=lines.append)
    assert len(lines) == 2 and "size 40" in lines[0] and str(tmp_path) in lines[0]
    assert lines[1].startswith("heldout set built: 40 transitions")
    again = heldout_set(entry, None, 40, announce=lines.append)
    assert len(lines) == 2 and torch.equal(first["next", "observation"], again["next", "observation"])
