"""MBPO: TorchRL's SAC on imagined rollouts from real states (library), the mbpo methods and
``softae policy`` (pipeline)."""
import json
import os
import shutil
import subprocess
import sys

import numpy as np
import pytest
import torch
from tensordict import TensorDict
from torchrl.data import Bounded, Composite, Unbounded
from torchrl.envs import EnvBase, TransformedEnv

from torchrl_softae.envs import EnsembleModelEnv
from torchrl_softae.modules import EnsembleWorldModel
from torchrl_softae.objectives import MBPOTrainer, branched_rollouts, make_sac_actor_critic
from torchrl_softae.pipeline.cli import main
from torchrl_softae.pipeline.config import ConfigError, make_config
from torchrl_softae.pipeline.evaluate import task_rollouts, reference_returns
from torchrl_softae.pipeline.policy import POLICY_FAULT_ENV
from torchrl_softae.tasks.base import TaskReward
from torchrl_softae.tasks.pendulum import tasks as pendulum_tasks


class PendulumDynamics(EnvBase):
    """gymnasium's Pendulum-v1 dynamics (g = 10, m = l = 1, dt = 0.05) on batches of
    ``(cos th, sin th, thdot)``: the true model, as a model env that starts where it is told."""

    batch_locked = False

    def __init__(self):
        super().__init__()
        self.observation_spec = Composite(observation=Unbounded((3,)))
        self.action_spec = Bounded(-2.0, 2.0, (1,))
        self.reward_spec = Unbounded((1,))

    def _reset(self, td):
        return TensorDict({"observation": td["observation"]}, td.batch_size)

    def _step(self, td):
        o, u = td["observation"], td["action"][..., 0].clamp(-2, 2)
        th = torch.atan2(o[..., 1], o[..., 0])
        thdot = (o[..., 2] + (15.0 * torch.sin(th) + 3.0 * u) * 0.05).clamp(-8, 8)
        th = th + thdot * 0.05
        flag = torch.zeros(*td.batch_size, 1, dtype=torch.bool)
        return TensorDict({"observation": torch.stack([th.cos(), th.sin(), thdot], -1),
                           "reward": torch.zeros(*td.batch_size, 1), "done": flag, "terminated": flag}, td.batch_size)

    def _set_seed(self, seed):
        pass


def _uniform_pendulum_transitions(env, n, generator):
    th = torch.rand(n, generator=generator) * 2 * np.pi - np.pi
    s = torch.stack([th.cos(), th.sin(), torch.rand(n, generator=generator) * 16 - 8], -1)
    real = TensorDict({"observation": s, "action": torch.rand(n, 1, generator=generator) * 4 - 2}, [n])
    real["next", "observation"] = env.base_env._step(real)["observation"]
    return real


@pytest.fixture
def one_thread():
    """Networks of 64 cells: a second thread only adds synchronization."""
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


def test_sac_on_the_true_pendulum_dynamics_swings_up_far_above_random(one_thread):
    torch.manual_seed(0)
    task = pendulum_tasks()["swingup"]
    env = TransformedEnv(PendulumDynamics(), TaskReward(task))
    real = _uniform_pendulum_transitions(env, 2000, torch.Generator().manual_seed(0))
    actor, qvalue = make_sac_actor_critic(3, env.action_spec, num_cells=64, depth=2)
    trainer = MBPOTrainer(actor, qvalue, task.reward, rollout_horizon=5, rollout_batch=100, updates_per_rollout=10,
                          imagined_capacity=50_000, lr=1e-3)
    trainer.train(env, real, rounds=400, seed=0)  # seeds 0-2 of this test: -159, -115, -157
    assert trainer.updates == 4000
    ret = np.mean(task_rollouts("Pendulum-v1", task, 3, 0, lambda r, s, t: trainer.policy(1))["returns"])
    rand = np.mean(reference_returns("Pendulum-v1", "swingup", "random", episodes=3, seed=0))
    assert rand < -900 and ret > -400 and ret > rand + 700, (ret, rand)


def _model_env(task):
    torch.manual_seed(0)
    model = EnsembleWorldModel(3, 1, ensemble_size=3, num_cells=16, depth=2)
    return TransformedEnv(EnsembleModelEnv(model, action_spec=Bounded(-2.0, 2.0, (1,)), mode="sample"),
                          TaskReward(task))


def test_imagined_rollouts_start_from_real_states_and_have_the_requested_length():
    task = pendulum_tasks()["swingup"]
    env = _model_env(task)
    actor, _ = make_sac_actor_critic(3, env.action_spec, num_cells=16, depth=1)
    starts = torch.randn(7, 3)
    out = branched_rollouts(env, actor, starts, horizon=4)
    assert out.batch_size == (28,)
    assert type(out) is TensorDict  # dense: a lazy stack is indexed and stored row by row
    steps = out.reshape(7, 4)
    torch.testing.assert_close(steps[:, 0]["observation"], starts)
    torch.testing.assert_close(steps[:, 1:]["observation"], steps[:, :-1]["next", "observation"])
    # the model env set the task reward of each imagined transition
    torch.testing.assert_close(out["next", "reward"],
                               task.reward(out["observation"], out["action"], out["next", "observation"]))


def test_sac_batches_mix_real_and_imagined_transitions_in_the_configured_ratio():
    task = pendulum_tasks()["swingup"]
    env = _model_env(task)
    real = _uniform_pendulum_transitions(TransformedEnv(PendulumDynamics(), TaskReward(task)), 50,
                                         torch.Generator().manual_seed(1))
    actor, qvalue = make_sac_actor_critic(3, env.action_spec, num_cells=16, depth=1)
    trainer = MBPOTrainer(actor, qvalue, task.reward, rollout_batch=10, rollout_horizon=3, batch_size=40,
                          real_ratio=0.25)
    assert trainer.num_real == 10
    before = trainer.sample_batch(real)  # nothing imagined yet: all real
    assert len(before) == 40 and _rows_in(before["observation"], real["observation"]).all()
    imagined = trainer.imagine(env, real)
    assert len(trainer.imagined) == 30 == len(imagined)
    batch = trainer.sample_batch(real)
    assert len(batch) == 40
    assert _rows_in(batch["observation"][:10], real["observation"]).all()
    assert _rows_in(batch["observation"][10:], imagined["observation"]).all()
    # real rows carry the task's reward (relabelled), whatever reward the data was collected with
    torch.testing.assert_close(batch["next", "reward"][:10],
                               task.reward(batch["observation"][:10], batch["action"][:10],
                                           batch["next", "observation"][:10]))
    losses = trainer.update(batch)
    assert all(np.isfinite(v) for v in losses.values())


def _rows_in(rows, table):
    return (rows[:, None, :] == table[None, :, :]).all(-1).any(-1)


# ---------------------------------------------------------------------------------------- pipeline
TINY = ["--env", "Pendulum-v1", "--preset", "quick", "--episode-length", "20", "--set", "planner.horizon=2",
        "--set", "planner.num_candidates=8", "--set", "planner.top_k=2", "--set", "train.epochs=1",
        "--set", "heldout_size=50", "--set", "policy.num_cells=16", "--set", "policy.rollout_batch=8",
        "--set", "policy.updates_per_step=1", "--set", "policy.batch_size=16", "--wandb", "disabled", "--quiet"]


def test_mbpo_collects_with_its_sac_policy_which_keeps_training_across_episodes(tmp_path):
    run = tmp_path / "mbpo"
    assert main(["explore", *TINY, "--method", "mbpo", "--task", "swingup", "--episodes", "1", "--run-dir", str(run)]) == 0
    state = torch.load(run / "checkpoint.pt", weights_only=False)
    assert state["policy"]["updates"] == 20  # updates_per_step x episode_length, whole rounds
    assert main(["explore", *TINY, "--method", "mbpo", "--task", "swingup", "--episodes", "2", "--run-dir", str(run)]) == 0
    state = torch.load(run / "checkpoint.pt", weights_only=False)
    assert state["policy"]["updates"] == 40 and [r["policy_updates"] for r in state["history"]] == [20, 40]
    assert len(state["policy"]["imagined"]["_storage"]["_storage"]["observation"]) > 0


def test_killed_policy_training_resumes_to_the_policy_of_an_uninterrupted_one(tmp_path):
    run = tmp_path / "random"
    assert main(["explore", *TINY, "--method", "random", "--episodes", "1", "--run-dir", str(run)]) == 0
    twin = tmp_path / "twin"
    shutil.copytree(run, twin)
    argv = ["policy", "--task", "swingup", "--updates", "60", "--checkpoint-every", "20", "--episodes", "2",
            "--set", "policy.updates_per_rollout=10", "--threads", "1", "--quiet"]
    assert main([*argv, "--run-dir", str(run)]) == 0
    killed = subprocess.run([sys.executable, "-m", "torchrl_softae.pipeline.cli", *argv, "--run-dir", str(twin)],
                            env={**os.environ, POLICY_FAULT_ENV: "2"}, capture_output=True, text=True)
    assert killed.returncode == 17, killed.stderr[-2000:]
    assert torch.load(twin / "policies/swingup-mean-s0-ep1/checkpoint.pt", weights_only=False)["updates_done"] == 40
    assert main([*argv, "--run-dir", str(twin)]) == 0
    a = torch.load(run / "policies/swingup-mean-s0-ep1/checkpoint.pt", weights_only=False)["learner"]
    b = torch.load(twin / "policies/swingup-mean-s0-ep1/checkpoint.pt", weights_only=False)["learner"]
    assert a["updates"] == b["updates"] == 60
    for k, v in a["loss"].items():
        torch.testing.assert_close(b["loss"][k], v, rtol=0, atol=0)
    ra = json.loads((run / "policies/swingup-mean-s0-ep1/eval.json").read_text())
    rb = json.loads((twin / "policies/swingup-mean-s0-ep1/eval.json").read_text())
    assert ra["returns"] == rb["returns"] and len(ra["returns"]) == 2


def _one_error_line(capsys, *needles):
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("softae: error: ") and "Traceback" not in err[0], err
    for n in needles:
        assert n in err[0], err[0]


def test_bad_policy_input_is_one_line(tmp_path, capsys):
    assert main(["explore", *TINY, "--method", "mbpo", "--episodes", "1", "--run-dir", str(tmp_path / "a")]) == 2
    _one_error_line(capsys, "'mbpo'", "--task", "swingup")
    assert main(["policy", "--run-dir", str(tmp_path / "nothing"), "--task", "swingup"]) == 2
    _one_error_line(capsys, "holds no checkpoint")
    run = tmp_path / "r"
    assert main(["explore", *TINY, "--method", "random", "--episodes", "1", "--run-dir", str(run)]) == 0
    capsys.readouterr()
    assert main(["policy", "--run-dir", str(run), "--task", "fly"]) == 2
    _one_error_line(capsys, "unknown task 'fly'", "swingup")
    assert main(["policy", "--run-dir", str(run), "--task", "swingup", "--propagation", "dream"]) == 2
    _one_error_line(capsys, "propagation 'dream'", "mean, sample, optimistic")
    assert main(["policy", "--run-dir", str(run), "--task", "swingup", "--set", "planner.horizon=3"]) == 2
    _one_error_line(capsys, "policy.KEY=VALUE")
    with pytest.raises(ConfigError, match="family of targets"):
        make_config("SoftArm-v1", "mbpo", task="reach-any")


def test_a_killed_mbpo_run_resumes_to_the_policy_of_an_uninterrupted_one(tmp_path):
    from torchrl_softae.pipeline.explore import FAULT_ENV

    argv = ["explore", *TINY, "--method", "mbpo", "--task", "swingup", "--episodes", "2", "--threads", "1"]
    assert main([*argv, "--run-dir", str(tmp_path / "whole")]) == 0
    killed = subprocess.run([sys.executable, "-m", "torchrl_softae.pipeline.cli", *argv, "--run-dir",
                             str(tmp_path / "killed")], env={**os.environ, FAULT_ENV: "1"}, capture_output=True, text=True)
    assert killed.returncode == 17, killed.stderr[-2000:]
    assert main([*argv, "--run-dir", str(tmp_path / "killed")]) == 0
    a, b = (torch.load(tmp_path / d / "checkpoint.pt", weights_only=False) for d in ("whole", "killed"))
    assert a["policy"]["updates"] == b["policy"]["updates"] == 40
    for k, v in a["policy"]["loss"].items():
        torch.testing.assert_close(b["policy"]["loss"][k], v, rtol=0, atol=0)
    for k, v in a["model"].items():
        torch.testing.assert_close(b["model"][k], v, rtol=0, atol=0)


def test_mbpo_presets_are_the_paper_and_quick_ones_with_a_symlog_model():
    from torchrl_softae.pipeline.arguments import PRESETS

    for mbpo, base in (("mbpo", "paper"), ("mbpo-quick", "quick")):
        a = make_config("Pendulum-hanging", "mbpo", PRESETS[mbpo], task="swingup").to_dict()
        b = make_config("Pendulum-hanging", "mbpo", PRESETS[base], task="swingup").to_dict()
        assert a["model"].pop("symlog") and not b["model"].pop("symlog") and a == b


def test_reports_and_plots_do_not_take_a_runs_task_policies_for_runs(tmp_path, capsys):
    run = tmp_path / "runs" / "random-s0"
    assert main(["explore", *TINY, "--method", "random", "--episodes", "1", "--run-dir", str(run)]) == 0
    assert main(["policy", "--run-dir", str(run), "--task", "swingup", "--updates", "10", "--episodes", "1",
                 "--set", "policy.updates_per_rollout=10", "--quiet"]) == 0
    assert (run / "policies/swingup-mean-s0-ep1/checkpoint.pt").exists()
    capsys.readouterr()
    assert main(["report", str(tmp_path / "runs"), "--no-plots"]) == 0
    assert main(["plot", "--run-dir", str(tmp_path / "runs")]) == 0
    out = capsys.readouterr()
    assert "skipping" not in out.err and "policies" not in out.out, out
    report = json.loads((tmp_path / "runs" / "report.json").read_text())
    assert [r["seeds"] for t in report["tables"] for r in t["rows"]] == [[0]] and not report["unfinished"]


def test_softae_policy_builds_the_real_env_once_for_specs_and_once_to_evaluate(tmp_path, monkeypatch):
    """Loading the run and building the learner read the specs from one instance (on SoPrA each
    instance is a valve/mocap session); the evaluation episodes use one more."""
    from torchrl_softae.pipeline.catalog import get_env_entry
    from torchrl_softae.pipeline.policy import train_policy

    run = tmp_path / "random"
    assert main(["explore", *TINY, "--method", "random", "--episodes", "1", "--run-dir", str(run)]) == 0
    entry = get_env_entry("Pendulum-v1")
    built = []
    make = entry.make
    monkeypatch.setattr(entry, "make", lambda: built.append(1) or make())
    monkeypatch.setattr(entry, "_specs", None)
    train_policy(run, "swingup", updates=2, episodes=1, progress=False, echo=None,
                 overrides=["policy.updates_per_rollout=2"])
    assert len(built) == 2
