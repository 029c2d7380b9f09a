"""A newcomer's mistakes: each is one line on stderr, exit code 2, no traceback, nothing written
that blocks the corrected command, which then runs in the same run dir."""
import json
import shutil

import pytest

from torchrl_softae.pipeline.cli import main

TINY = ["--env", "Pendulum-v1", "--method", "softae", "--preset", "quick", "--episode-length", "10",
        "--set", "planner.horizon=2", "--set", "planner.num_candidates=8", "--set", "planner.top_k=2",
        "--set", "train.epochs=1", "--set", "heldout_size=50", "--wandb", "disabled", "--quiet"]


def _explore(run_dir, *extra, episodes=1):
    return main(["explore", *TINY, "--episodes", str(episodes), "--run-dir", str(run_dir), *extra])


def _one_error_line(capsys, *needles):
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("softae: error: "), err
    assert "Traceback" not in err[0]
    for n in needles:
        assert n in err[0], err[0]
    return err[0]


@pytest.mark.parametrize("bad, needles", [
    ("planner.time_budget=abc", ["planner.time_budget='abc'", "expected a number or none"]),
    ("planner.time_budget=-1", ["planner.time_budget=-1.0", "expected seconds > 0"]),
    ("planner.precision=fp8", ["planner.precision='fp8'", "fp32, bf16, auto"]),
    ("planner.horizonn=3", ["planner.horizonn", "valid keys here"]),
    ("model.num_cells=big", ["model.num_cells", "expected an integer"]),
])
def test_bad_config_value_is_one_line_then_the_corrected_command_runs(tmp_path, capsys, bad, needles):
    run = tmp_path / "run"
    assert _explore(run, "--set", bad) == 2
    _one_error_line(capsys, *needles)
    assert not (run / "config.json").exists()  # nothing written before validation
    assert _explore(run) == 0


def test_bad_method_env_task_threads(tmp_path, capsys):
    assert main(["explore", "--env", "SoftArm-v9", "--run-dir", str(tmp_path / "a")]) == 2
    _one_error_line(capsys, "unknown env 'SoftArm-v9'", "catalog id")
    assert main(["explore", "--method", "sofae", "--run-dir", str(tmp_path / "a")]) == 2
    _one_error_line(capsys, "unknown method 'sofae'", "valid methods")
    assert main(["explore", "--method", "hucrl", "--run-dir", str(tmp_path / "a")]) == 2
    _one_error_line(capsys, "pass --task", "swingup")
    assert _explore(tmp_path / "b", "--threads", "0") == 2
    _one_error_line(capsys, "--threads=0")


def test_missing_or_corrupt_runs(tmp_path, capsys):
    assert main(["plot", "--run-dir", str(tmp_path / "missing")]) == 2
    _one_error_line(capsys, "does not exist")
    assert main(["evaluate", "--run-dir", str(tmp_path / "missing")]) == 2
    _one_error_line(capsys, "holds no checkpoint")

    runs = tmp_path / "runs"
    assert _explore(runs / "good") == 0
    capsys.readouterr()
    assert main(["evaluate", "--run-dir", str(runs / "good"), "--task", "swim"]) == 2
    _one_error_line(capsys, "unknown task 'swim'", "swingup")
    assert main(["evaluate", "--run-dir", str(runs / "good"), "--propagation", "optimist"]) == 2
    _one_error_line(capsys, "propagation 'optimist'", "mean, sample, optimistic")
    shutil.copytree(runs / "good", runs / "broken")
    (runs / "broken" / "checkpoint.pt").write_bytes(b"not a checkpoint")
    assert main(["plot", "--run-dir", str(runs)]) == 0  # the broken run is skipped, the rest plotted
    err = capsys.readouterr().err
    assert "skipping" in err and "broken" in err and "Traceback" not in err
    assert (runs / "plots" / "mse_bars.png").exists() and (runs / "good" / "plots" / "coverage.png").exists()


def test_resume_is_announced_even_when_quiet(tmp_path, capsys):
    run = tmp_path / "run"
    assert _explore(run) == 0
    capsys.readouterr()
    assert _explore(run, episodes=2) == 0
    out = capsys.readouterr().out
    assert f"resuming {run} at episode 2 of 2" in out
    assert _explore(run, episodes=2) == 0
    assert "already holds all 2 episodes" in capsys.readouterr().out
    history = [json.loads(line) for line in (run / "metrics.jsonl").read_text().splitlines()]
    assert [h["episode"] for h in history] == [0, 1]


def test_log_output_is_plain_lines_without_a_terminal(tmp_path, capsys):
    run = tmp_path / "run"
    argv = ["explore", *[a for a in TINY if a != "--quiet"], "--episodes", "2", "--run-dir", str(run)]
    assert main(argv) == 0
    cap = capsys.readouterr()
    lines = cap.out.splitlines()
    assert lines[0].startswith("explore Pendulum-v1 with softae: 2 episodes x 10 steps, planning in")
    assert sum(line.startswith("episode ") for line in lines) == 2
    assert "results in" in lines[-1]
    assert "\x1b[" not in cap.out + cap.err and "\r" not in cap.err  # no colour codes, no progress bars


def test_the_engine_line_warns_when_bf16_is_asked_for_without_native_bf16(monkeypatch):
    from torchrl_softae.modules.engine import precision
    from torchrl_softae.pipeline.cli import _engine

    for native in (True, False):
        monkeypatch.setattr(precision, "fast_bf16_available", lambda native=native: native)
        assert ("no native bf16" in _engine("bf16", 2)) is not native
        assert "no native bf16" not in _engine("fp32", 2)
