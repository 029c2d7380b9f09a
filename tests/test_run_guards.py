"""A run dir has one writer, stops cleanly on SIGTERM/SIGINT and loses nothing on a full disk."""
import errno
import json
import os
import resource
import signal
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from torchrl_softae.pipeline.cli import main
from torchrl_softae.pipeline.guards import LOCK_FILE, RunLock
from torchrl_softae.pipeline.runs import RunDir, atomic_write_text

sys.path.insert(0, str(Path(__file__).parent))
from test_pipeline import _deterministic, _explore_argv  # noqa: E402

EPISODES, LENGTH = 3, 30
CLI = "import sys; from torchrl_softae.pipeline.cli import main; sys.exit(main(sys.argv[1:]))"


def _argv(run_dir, episodes=EPISODES):
    return _explore_argv(run_dir, "softae", episodes=episodes, length=LENGTH)


def _cli(argv, env=None, preexec_fn=None, timeout=300):
    return subprocess.run([sys.executable, "-c", CLI, *argv], capture_output=True, text=True, timeout=timeout,
                          env={**os.environ, **(env or {})}, preexec_fn=preexec_fn)


def _snapshot(folder: Path) -> dict:
    return {str(p.relative_to(folder)): (p.stat().st_size, p.stat().st_mtime_ns) for p in folder.rglob("*")}


@pytest.fixture(scope="module")
def straight(tmp_path_factory):
    """An uninterrupted run: what every stopped-and-resumed run must equal."""
    run = tmp_path_factory.mktemp("straight")
    assert main(_argv(run)) == 0
    return RunDir(run).load()


def _assert_identical(run_dir, straight):
    resumed = RunDir(run_dir).load()
    assert resumed["num_transitions"] == straight["num_transitions"] == EPISODES * LENGTH
    assert _deterministic(resumed["history"]) == _deterministic(straight["history"])
    for k, v in straight["model"].items():
        torch.testing.assert_close(resumed["model"][k], v, rtol=0, atol=0)


def test_a_second_writer_exits_2_naming_the_holder_and_writes_nothing(tmp_path):
    assert main(_argv(tmp_path, episodes=1)) == 0
    with RunLock(tmp_path):  # this test process is the run's writer now
        before = _snapshot(tmp_path)
        out = _cli(_argv(tmp_path, episodes=2))
        assert _snapshot(tmp_path) == before
    assert out.returncode == 2
    lines = out.stderr.strip().splitlines()
    assert len(lines) == 1 and f"is being written by pid {os.getpid()}" in lines[0] and "--run-dir" in lines[0]
    assert (tmp_path / LOCK_FILE).read_text() == ""  # released: emptied
    assert main(_argv(tmp_path, episodes=2)) == 0  # and the run goes on once the writer is gone


def test_a_lock_left_by_a_dead_process_is_taken_over_with_a_note(tmp_path, capsys):
    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    (tmp_path / LOCK_FILE).write_text(json.dumps({"pid": dead.pid, "host": os.uname().nodename,
                                                  "started": "2026-12-05 10:00:00 UTC"}))
    argv = [a for a in _argv(tmp_path, episodes=1) if a != "--quiet"]
    assert main(argv) == 0
    assert f"took over the lock of pid {dead.pid}" in capsys.readouterr().out
    assert RunDir(tmp_path).load()["episode"] == 0


def test_the_lock_is_reentrant_in_a_process_and_exclusive_between_processes(tmp_path):
    with RunLock(tmp_path):
        with RunLock(tmp_path):  # a sweep trial holds it around explore, which takes it too
            pass
        holder = json.loads((tmp_path / LOCK_FILE).read_text())
        assert holder["pid"] == os.getpid()  # still held after the inner exit
        probe = subprocess.run([sys.executable, "-c", "import sys; from torchrl_softae.pipeline.guards import "
                                "RunLock, RunLocked\ntry:\n    RunLock(sys.argv[1]).__enter__()\nexcept RunLocked as e:\n"
                                "    print(e); sys.exit(3)", str(tmp_path)], capture_output=True, text=True)
        assert probe.returncode == 3 and "is being written by" in probe.stdout


@pytest.mark.parametrize("point", ["collect", "train", "checkpoint"])
def test_sigterm_stops_at_a_safe_point_with_143_and_the_resume_is_bit_identical(tmp_path, straight, point):
    out = _cli(_argv(tmp_path), env={"SOFTAE_SIGNAL_AT": f"{point}:2"})
    assert out.returncode == 143, out.stderr
    # inside the checkpoint write the signal waits for the write: episode 2 is then complete
    complete = 2 if point == "checkpoint" else 1
    expected = f"softae: stopped by SIGTERM at episode {complete + 1} of {EPISODES} ({complete} complete and saved)"
    assert out.stderr.strip().splitlines()[-1] == f"{expected}; rerun the same command to resume"
    state = RunDir(tmp_path).load()
    assert state["episode"] == complete - 1 and len(RunDir(tmp_path).history()) == complete
    assert not list(tmp_path.glob("*.tmp")) and [p.name for p in tmp_path.glob("replay_ep*")] == [state["replay_dump"]]
    assert main(_argv(tmp_path)) == 0
    _assert_identical(tmp_path, straight)


def test_sigterm_and_sigint_sent_from_outside_stop_the_run_and_it_resumes(tmp_path, straight):
    for sig, code in ((signal.SIGINT, 130), (signal.SIGTERM, 143)):
        proc = subprocess.Popen([sys.executable, "-c", CLI, *_argv(tmp_path)], stderr=subprocess.PIPE, text=True)
        metrics = tmp_path / "metrics.jsonl"
        start = len(RunDir(tmp_path).history())
        while proc.poll() is None and len(RunDir(tmp_path).history()) <= start:
            pass  # an episode more on disk: then stop it wherever it is
        proc.send_signal(sig)
        _, err = proc.communicate(timeout=120)
        assert proc.returncode == code, err
        assert "rerun the same command to resume" in err.strip().splitlines()[-1] and metrics.exists()
        assert "Traceback" not in err
    assert main(_argv(tmp_path)) == 0
    _assert_identical(tmp_path, straight)


def test_a_file_size_limit_during_the_checkpoint_loses_nothing_and_the_run_resumes(tmp_path, straight):
    assert main(_argv(tmp_path, episodes=1)) == 0
    checkpoint = tmp_path / "checkpoint.pt"
    limit = checkpoint.stat().st_size // 2  # every other file of the run is smaller than this
    assert all(p.stat().st_size < limit for p in tmp_path.rglob("*") if p.is_file() and p != checkpoint)
    before = {p: p.read_bytes() for p in (checkpoint, tmp_path / "metrics.jsonl", tmp_path / "metrics.csv")}

    def small_disk():
        resource.setrlimit(resource.RLIMIT_FSIZE, (limit, limit))

    out = _cli(_argv(tmp_path), preexec_fn=small_disk)
    assert out.returncode == 1, out.stderr
    lines = out.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"softae: error: cannot write {checkpoint}: File too large;")
    assert {p: p.read_bytes() for p in before} == before  # the previous checkpoint and metrics, untouched
    state = RunDir(tmp_path).load()
    assert state["episode"] == 0 and len(RunDir(tmp_path).load_replay_buffer(state)) == LENGTH
    assert not list(tmp_path.glob("*.tmp")) and [p.name for p in tmp_path.glob("replay_ep*")] == ["replay_ep0000"]
    assert main(_argv(tmp_path)) == 0  # space freed: the same command resumes
    _assert_identical(tmp_path, straight)


def test_a_failed_atomic_write_keeps_the_old_file_and_names_the_path(tmp_path):
    from torchrl_softae.pipeline.runs import _atomic_write

    path = tmp_path / "report.json"
    atomic_write_text(path, "good")

    def half_then_full(f):
        f.write(b"partial")
        raise OSError(errno.ENOSPC, "No space left on device")

    with pytest.raises(OSError) as e:
        _atomic_write(path, half_then_full)
    assert e.value.errno == errno.ENOSPC and e.value.filename == str(path)
    assert path.read_text() == "good" and sorted(p.name for p in tmp_path.iterdir()) == ["report.json"]


def test_a_stop_that_arrives_while_the_env_steps_is_not_taken_for_an_env_fault(tmp_path):
    """SIGTERM inside ``env.step`` stops the run (exit 143, nothing of the episode kept), instead of
    the env's fault guard ending the episode early and the run carrying on with a shorter one."""
    env = {**os.environ, "PYTHONPATH": str(Path(__file__).parent)}
    run = tmp_path / "run"
    out = subprocess.run([sys.executable, "-m", "torchrl_softae.pipeline.cli", "explore", "--env",
                          "outside_envs:self_signalling_env", "--run-dir", str(run), "--preset", "quick",
                          "--episodes", "2", "--episode-length", "10", "--set", "heldout_size=20",
                          "--wandb", "disabled", "--quiet"], capture_output=True, text=True, env=env, timeout=300)
    assert out.returncode == 143, out.stderr[-2000:]
    assert out.stderr.strip().splitlines()[-1].startswith("softae: stopped by SIGTERM at episode 1 of 2")
    assert "EnvFaultWarning" not in out.stderr and "Traceback" not in out.stderr
    assert RunDir(run).history() == []  # the interrupted episode is not on disk

