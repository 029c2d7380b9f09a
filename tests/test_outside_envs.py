"""Envs and tasks the package does not know, named by reference: a gymnasium id (Reacher-v5),
``module:EnvId-v0``, ``module:callable`` (a TorchRL env), ``--task module:attr``, ``--heldout FILE``
and ``--coverage-dims``; bad references are one line, exit 2, and write nothing."""
import json
from pathlib import Path

import pytest
import torch
from tensordict import TensorDict

from torchrl_softae.pipeline.cli import main

TINY = ["--preset", "quick", "--episodes", "2", "--set", "planner.horizon=2", "--set", "planner.num_candidates=8",
        "--set", "planner.top_k=2", "--set", "train.epochs=1", "--set", "heldout_size=60", "--wandb", "disabled",
        "--quiet"]
EVAL = ["--episodes", "1", "--set", "planner.horizon=2", "--set", "planner.num_candidates=8", "--set", "planner.top_k=2"]


def _explore(run_dir, env, *extra):
    return main(["explore", "--env", env, "--run-dir", str(run_dir), *TINY, *extra])


def test_reacher_v5_explores_evaluates_and_reports(tmp_path, capsys):
    run = tmp_path / "runs" / "Reacher-v5" / "softae"
    assert _explore(run, "Reacher-v5", "--episode-length", "12") == 0
    out = capsys.readouterr().out
    assert "held-out set: random-action episodes (favours Random)" in out  # said beside the metric
    state = torch.load(run / "checkpoint.pt", weights_only=False)
    assert state["config"]["env"] == "Reacher-v5" and len(state["history"]) == 2
    assert main(["evaluate", "--run-dir", str(run), "--task", "outside_envs:reacher_tasks", *EVAL]) == 0
    out = capsys.readouterr().out
    assert "touch: mean return" in out and "[held-out set: random-action episodes (favours Random)]" in out
    res = json.loads((run / "eval" / "touch@horizon=2,num_candidates=8,top_k=2.json").read_text())
    assert len(res["returns"]) == 1 and res["success_metric"] is None
    acc = json.loads((run / "eval" / "model_accuracy.json").read_text())
    assert acc["heldout_set"].startswith("held-out set: random-action episodes")
    assert main(["report", str(tmp_path / "runs"), "--no-plots"]) == 0
    md = (tmp_path / "runs" / "report.md").read_text()
    assert "## Reacher-v5: 2 episodes" in md and "*held-out set: random-action episodes (favours Random)*" in md


def test_module_envid_env_with_module_tasks_heldout_file_and_coverage_dims(tmp_path, capsys):
    """``module:EnvId-v0`` (float64 gymnasium env registered by its module), episode length from its
    registration, the user's held-out file, the coverage grid over dims 2,3, a module:attr task."""
    heldout = TensorDict({"observation": torch.randn(40, 4, dtype=torch.float64),
                          "action": torch.rand(40, 2, dtype=torch.float64) * 2 - 1,
                          ("next", "observation"): torch.randn(40, 4, dtype=torch.float64)}, [40])
    torch.save(heldout, tmp_path / "heldout.pt")
    run = tmp_path / "runs" / "point"
    assert _explore(run, "outside_envs:OutsidePoint-v0", "--heldout", str(tmp_path / "heldout.pt"),
                    "--coverage-dims", "2,3", "--method", "hucrl", "--task", "outside_envs:reach_origin") == 0
    state = torch.load(run / "checkpoint.pt", weights_only=False)
    cfg = state["config"]
    assert cfg["episode_length"] == 25  # the env's registered max_episode_steps
    assert cfg["coverage_dims"] == "2,3" and cfg["heldout_file"] == str(tmp_path / "heldout.pt")
    assert cfg["task"] == "outside_envs:reach_origin"
    # the metric is measured on the user's 40 transitions (copied into the run dir, cast to float32)
    kept = torch.load(run / "heldout-file.pt", weights_only=False)
    assert kept.shape == (40,) and kept["observation"].dtype == torch.float32
    assert torch.equal(kept["observation"], heldout["observation"].float())
    # the coverage grid is over the velocities (dims 2, 3): the same data, another projection
    from torchrl_softae.pipeline.catalog import run_entry
    from torchrl_softae.pipeline.config import ExploreConfig

    entry = run_entry(ExploreConfig.from_dict(cfg))
    assert entry.projection_labels == ("observation[2]", "observation[3]")
    assert torch.equal(entry.project(kept), kept["observation"][:, 2:4])
    capsys.readouterr()
    assert main(["evaluate", "--run-dir", str(run), "--task", "outside_envs:point_tasks", *EVAL]) == 0
    out = capsys.readouterr().out
    assert "reach-left: mean return" in out and "reach-up: mean return" in out
    assert f"[held-out set: {tmp_path / 'heldout.pt'}]" in out
    res = json.loads((run / "eval" / "reach-up@horizon=2,num_candidates=8,top_k=2.json").read_text())
    assert res["success_metric"] == "final_distance_m" and "final_distance_m" in res["metrics"][0]


def test_module_callable_torchrl_env_resumes_and_plots(tmp_path, capsys):
    run = tmp_path / "runs" / "torchrl-point"
    assert _explore(run, "outside_envs:make_torchrl_point", "--episode-length", "10") == 0
    assert main(["explore", "--env", "outside_envs:make_torchrl_point", "--run-dir", str(run), *TINY,
                 "--episode-length", "10", "--episodes", "3"]) == 0  # resumes: one more episode
    history = [json.loads(x) for x in (run / "metrics.jsonl").read_text().splitlines()]
    assert [h["episode"] for h in history] == [0, 1, 2]
    assert history[-1]["transitions"] == 30
    assert main(["plot", "--run-dir", str(run)]) == 0
    assert (run / "plots" / "coverage.png").exists() and (run / "plots" / "learning_curves.png").exists()
    assert main(["evaluate", "--run-dir", str(run), "--task", "outside_envs:reach_origin", *EVAL]) == 0
    assert json.loads((run / "eval" / "reach-origin@horizon=2,num_candidates=8,top_k=2.json").read_text())["returns"]
    assert main(["report", str(tmp_path / "runs")]) == 0
    md = (tmp_path / "runs" / "report.md").read_text()
    assert "## outside_envs:make_torchrl_point: 3 episodes" in md and "reach-origin@horizon=2,num_candidates=8,top_k=2 return" in md
    assert (tmp_path / "runs" / "plots" / "mse_bars.png").exists()


@pytest.mark.parametrize("args, needle", [
    (["--env", "no_such_module:Thing-v0"], "cannot import module 'no_such_module'"),
    (["--env", "outside_envs:nothing"], "module 'outside_envs' has no attribute 'nothing' and registers no gymnasium id"),
    (["--env", "outside_envs:not_an_env"], "gave a int: expected a gymnasium.Env or a TorchRL EnvBase"),
    (["--env", "outside_envs:not_a_task"], "is a int: expected a callable returning an env"),
    (["--env", "outside_envs:unbounded_action_env"], "expected a bounded continuous action vector"),
    (["--env", "outside_envs:lying_spec_env"], "env 'outside_envs:lying_spec_env' fails TorchRL's check_env_specs: "),
    (["--env", "NoSuchEnv-v9"], "unknown env 'NoSuchEnv-v9': expected a catalog id (MSKLeg-v0"),
    (["--env", "outside_envs:OutsidePoint-v0", "--task", "outside_envs:nope"],
     "module 'outside_envs' has no attribute 'nope'"),
    (["--env", "outside_envs:OutsidePoint-v0", "--method", "hucrl", "--task", "outside_envs:not_a_task"],
     "is a int: expected a torchrl_softae Task"),
    (["--env", "outside_envs:OutsidePoint-v0", "--method", "hucrl", "--task", "outside_envs:point_tasks"],
     "names 2 tasks (reach-left, reach-up): expected exactly one here"),
    (["--env", "outside_envs:OutsidePoint-v0", "--method", "hucrl", "--task", "swingup"],
     "unknown task 'swingup' for env 'outside_envs:OutsidePoint-v0': expected module:attr"),
    (["--env", "outside_envs:OutsidePoint-v0", "--heldout", "WRONG"], "observation' has per-transition shape (3,), expected (4,)"),
    (["--env", "outside_envs:OutsidePoint-v0", "--heldout", "MISSING"], "no such file or directory"),
    (["--env", "outside_envs:OutsidePoint-v0", "--coverage-dims", "0,7"], "coverage_dims='0,7': expected two distinct"),
])
def test_a_bad_reference_is_one_line_exit_2_and_nothing_written(tmp_path, capsys, args, needle):
    wrong = TensorDict({"observation": torch.zeros(5, 3), "action": torch.zeros(5, 2),
                        ("next", "observation"): torch.zeros(5, 3)}, [5])
    torch.save(wrong, tmp_path / "wrong.pt")
    args = [str(tmp_path / "wrong.pt") if a == "WRONG" else str(tmp_path / "missing.pt") if a == "MISSING" else a
            for a in args]
    run = tmp_path / "run"
    assert main(["explore", *args, "--run-dir", str(run), *TINY]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("softae: error: ") and needle in err[0], err
    assert not run.exists()


def test_library_make_env_casts_float64_and_load_tasks_reads_every_form():
    from torchrl_softae.envs.references import make_env, resolve_env
    from torchrl_softae.tasks import load_tasks

    env = make_env("outside_envs:OutsidePoint-v0")
    assert env.observation_spec["observation"].dtype == torch.float32
    assert env.rollout(3)["observation"].dtype == torch.float32
    assert resolve_env("outside_envs:OutsidePoint-v0").max_episode_steps == 25
    assert make_env("outside_envs:make_torchrl_point").rollout(2)["next", "observation"].dtype == torch.float32
    assert list(load_tasks("outside_envs:point_tasks")) == ["reach-left", "reach-up"]
    assert list(load_tasks("outside_envs:reach_origin")) == ["reach-origin"]  # a function returning a Task


def test_model_env_refuses_float64_states_with_the_fix():
    """The library's boundary: a float64 state reaching the model env names the dtype and the fix."""
    from torchrl.data import Bounded

    from torchrl_softae.envs import EnsembleModelEnv
    from torchrl_softae.modules import EnsembleWorldModel

    model = EnsembleWorldModel(4, 2, ensemble_size=2, num_cells=8, depth=1)
    env = EnsembleModelEnv(model, action_spec=Bounded(-1.0, 1.0, (2,)))
    td = TensorDict({"observation": torch.zeros(3, 4, dtype=torch.float64), "action": torch.zeros(3, 2)}, [3])
    with pytest.raises(TypeError, match="torch.float64.*DoubleToFloat"):
        env.step(td)


def test_examples_accept_references_and_collect_without_torchrl_warnings(tmp_path):
    """The example script explores an outside env by reference with no FutureWarning from the
    collector (the planner needs no InitTracker: it keeps no recurrent state)."""
    import os
    import subprocess
    import sys

    root = Path(__file__).parents[1]
    env = {**os.environ, "PYTHONPATH": str(Path(__file__).parent), "PYTHONWARNINGS": "error::FutureWarning"}
    proc = subprocess.run([sys.executable, str(root / "examples" / "softae_exploration.py"), "--env",
                           "outside_envs:OutsidePoint-v0", "--episodes", "2", "--episode-length", "8", "--horizon", "2",
                           "--num-candidates", "8", "--top-k", "2", "--epochs", "1", "--num-cells", "16",
                           "--wandb-dir", str(tmp_path), "--out", str(tmp_path / "model.pt")],
                          capture_output=True, text=True, env=env, cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert "FutureWarning" not in proc.stderr and (tmp_path / "model.pt").exists()
