"""Task policies on a learned model (MBPO with TorchRL's SAC): for the ``mbpo``/``mbpo-ts`` methods
while they explore, and ``softae policy`` for any finished run (SoftAE-MBPO and friends).

Layout of ``softae policy``'s output, inside the run dir::

    policies/TASK-PROPAGATION-sSEED-epEPISODES/   (the model after that many exploration episodes)
        config.json       task, propagation, seed, updates, the policy config (checked on resume)
        checkpoint.pt     SAC networks, target networks, alpha, optimizer, imagined buffer, rounds
        eval.json         real-env returns of the trained policy over seeded episodes
"""
from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np
import torch
from tensordict import TensorDictBase
from torchrl.data import Bounded
from torchrl.envs import Compose, TransformedEnv

from torchrl_softae.envs import EnsembleModelEnv, HallucinatedControl
from torchrl_softae.envs.model_env import PROPAGATION_MODES
from torchrl_softae.modules import EnsembleWorldModel
from torchrl_softae.objectives.mbpo import MBPOTrainer, make_sac_actor_critic
from torchrl_softae.pipeline.config import ConfigError, PolicyConfig, apply_overrides
from torchrl_softae.pipeline.methods import get_method
from torchrl_softae.pipeline.runs import POLICIES_DIR, CheckpointError, RunDir, atomic_torch_save, exit_once_after
from torchrl_softae.tasks.base import Task, TaskReward

__all__ = ["PolicyLearner", "build_policy_learner", "train_policy", "evaluate_policy", "policy_dir_name",
           "stored_transitions", "POLICY_FAULT_ENV"]

#: test hook (:func:`~torchrl_softae.pipeline.runs.exit_once_after`): ``SOFTAE_EXIT_AFTER_POLICY_CHUNK=K``
#: kills ``softae policy`` right after its K-th checkpoint, once per policy dir
POLICY_FAULT_ENV = "SOFTAE_EXIT_AFTER_POLICY_CHUNK"


class PolicyLearner:
    """An :class:`~torchrl_softae.objectives.MBPOTrainer` bound to a model env with a task reward.

    The model env is ``EnsembleModelEnv(model, mode=propagation)`` (+ ``HallucinatedControl(beta)``
    for optimistic propagation) + ``TaskReward(task)``; it holds the model object, so a model
    retrained in place (each exploration episode) is what the next rollouts use.
    """

    def __init__(self, trainer: MBPOTrainer, model_env: TransformedEnv, cfg: PolicyConfig, action_dim: int):
        self.trainer, self.model_env, self.cfg, self.action_dim = trainer, model_env, cfg, action_dim

    def train(self, real: TensorDictBase, updates: int, seed: int, progress=None) -> dict:
        return self.trainer.train(self.model_env, real, self.cfg.rounds(updates), seed=seed, progress=progress)

    def policy(self, deterministic: bool = True):
        """The real-env policy: real actions only; SAC's sample while collecting, its mode to evaluate."""
        return self.trainer.policy(self.action_dim, deterministic)

    def state_dict(self) -> dict:
        return self.trainer.state_dict()

    def load_state_dict(self, state: dict) -> None:
        self.trainer.load_state_dict(state)


def build_policy_learner(cfg: PolicyConfig, model: EnsembleWorldModel, action_spec: Bounded, task: Task,
                         propagation: str, beta: float, seed: int = 0) -> PolicyLearner:
    """The SAC learner of ``task`` on ``model``; its networks are initialized from ``seed`` (the
    global RNG is left as it was)."""
    if propagation not in PROPAGATION_MODES:
        raise ConfigError(f"propagation {propagation!r}; valid: {', '.join(PROPAGATION_MODES)}")
    if task.instantiate is not None:
        raise ConfigError(f"task {task.name!r} is a family of targets: a SAC policy needs one fixed task")
    d_a = model.action_dim
    device = model.input_normalizer.loc.device
    spec = Bounded(action_spec.space.low.float().to(device), action_spec.space.high.float().to(device),
                   action_spec.shape, dtype=torch.float32, device=device)
    transforms = [HallucinatedControl(beta)] if propagation == "optimistic" else []
    model_env = TransformedEnv(EnsembleModelEnv(model, action_spec=spec, mode=propagation),
                               Compose(*transforms, TaskReward(task, action_dim=d_a)))
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed)  # SACLoss initializes its second Q network here too
        actor, qvalue = make_sac_actor_critic(model.observation_dim, model_env.action_spec, cfg.num_cells,
                                              cfg.depth, device=device)
        trainer = MBPOTrainer(
            actor, qvalue, task.reward, rollout_horizon=cfg.rollout_horizon, rollout_batch=cfg.rollout_batch,
            updates_per_rollout=cfg.updates_per_rollout, real_ratio=cfg.real_ratio,
            imagined_capacity=cfg.imagined_capacity, batch_size=cfg.batch_size, lr=cfg.lr, gamma=cfg.gamma,
            tau=cfg.tau,
        )
    return PolicyLearner(trainer, model_env, cfg, d_a)


def stored_transitions(run: RunDir, state: dict) -> TensorDictBase:
    """A run's real transitions in memory (:meth:`RunDir.read_transitions`)."""
    return run.read_transitions(state)


def policy_dir_name(task: str, propagation: str, seed: int, episodes_explored: int) -> str:
    """A policy belongs to one model: the run's after ``episodes_explored`` episodes."""
    return f"{task}-{propagation}-s{seed}-ep{episodes_explored}"


def evaluate_policy(env_id: str, task: Task, learner: PolicyLearner, episodes: int, seed: int) -> dict:
    """Real-env returns of the learner's deterministic policy on the evaluation episodes every
    zero-shot controller sees (same seeds, same initial states)."""
    from torchrl_softae.pipeline.evaluate import task_rollouts

    res = task_rollouts(env_id, task, episodes, seed, lambda real, s, t: learner.policy(deterministic=True))
    res["mean_return"] = float(np.mean(res["returns"]))
    return res


def train_policy(
    run_dir: str | Path,
    task: str,
    *,
    propagation: str = "mean",
    updates: int | None = None,
    episodes: int = 5,
    seed: int = 0,
    overrides: list[str] | None = None,
    checkpoint_updates: int = 1000,
    progress: bool = True,
    echo=print,
) -> dict:
    """Train (or resume) a SAC policy for ``task`` on a run's model and data; evaluate it on the real env.

    ``updates``: SAC updates in all, rounded up to whole rollout rounds (default ``policy.updates_per_step`` x the run's real
    transitions: what an MBPO run on the same data gets). A run that trained its own policy for
    this task (``mbpo``, ``mbpo-ts``) with this propagation starts from it, and then defaults to
    no further updates. ``overrides``: ``policy.KEY=VALUE``. Checkpoints every
    ``checkpoint_updates`` updates; rerunning the same command after a kill resumes and gives the
    numbers of an uninterrupted run. Returns the evaluation (also written to ``eval.json``).
    """
    from torchrl_softae.pipeline.catalog import get_env_entry, get_task
    from torchrl_softae.pipeline.evaluate import load_run

    cfg, model, state = load_run(run_dir)
    bad = [o for o in overrides or [] if not o.strip().startswith("policy.")]
    if bad:
        raise ConfigError(f"softae policy only overrides policy settings (policy.KEY=VALUE), got {bad}")
    apply_overrides(cfg, list(overrides or [])).validate()
    entry = get_env_entry(cfg.env)
    try:
        the_task = get_task(entry, task)
        run_task = None if cfg.task is None else get_task(entry, cfg.task)
    except ValueError as e:
        raise ConfigError(str(e)) from None
    task = the_task.name  # a module:attr reference stands for its Task's name in folders and results
    if episodes < 1 or (updates is not None and updates < 0) or checkpoint_updates < 1:
        raise ConfigError(f"--episodes={episodes}, --updates={updates}, --checkpoint-every={checkpoint_updates}: "
                          "expected episodes >= 1, updates >= 0, checkpoint-every >= 1")
    run = RunDir(run_dir)
    real = stored_transitions(run, state)
    learner = build_policy_learner(cfg.policy, model, entry.specs()[1], the_task, propagation, cfg.beta, seed)
    own = (get_method(cfg.method).trains_policy and run_task is not None and run_task.name == task
           and get_method(cfg.method).propagation == propagation
           and "policy" in state)
    if own:
        learner.load_state_dict(state["policy"])
    start_updates = learner.trainer.updates
    if updates is None:
        updates = 0 if own else cfg.policy.updates_per_step * len(real)
    out = run.path / POLICIES_DIR / policy_dir_name(task, propagation, seed, state["episode"] + 1)
    out.mkdir(parents=True, exist_ok=True)
    setup = {"task": task, "propagation": propagation, "seed": seed, "updates": updates, "from_run_policy": own,
             "policy": vars(cfg.policy), "episodes_explored": state["episode"] + 1, "transitions": len(real)}
    cfg_path, ckpt = out / "config.json", out / "checkpoint.pt"
    if cfg_path.exists():
        stored, requested = json.loads(cfg_path.read_text()), json.loads(json.dumps(setup, default=float))
        if stored != requested:
            diff = [f"{k}: stored {stored.get(k)!r} != requested {v!r}" for k, v in requested.items()
                    if stored.get(k) != v]
            raise ConfigError(f"{out} holds a policy trained otherwise ({'; '.join(diff)}); pass another --seed "
                              "or delete that folder")
    run.write_json(cfg_path, setup)
    done = 0
    if ckpt.exists():
        try:
            saved = torch.load(ckpt, map_location="cpu", weights_only=False)
            learner.load_state_dict(saved["learner"])
        except Exception as e:  # noqa: BLE001
            raise CheckpointError(f"policy checkpoint {ckpt} is unreadable ({type(e).__name__}: {e}); delete it "
                                  "to retrain") from None
        done = saved["updates_done"]
        if echo is not None:
            echo(f"resuming {out} at update {done} of {updates}")
    bar = None
    if progress and done < updates:
        from tqdm.auto import tqdm

        bar = tqdm(total=updates, initial=done, desc=f"SAC {task} on the model [{propagation}]", unit="update")
    t0 = time.perf_counter()
    chunk = max(checkpoint_updates // cfg.policy.updates_per_rollout, 1) * cfg.policy.updates_per_rollout
    while done < updates:
        n = min(chunk, updates - done)
        learner.train(real, n, seed=seed, progress=bar)
        done = learner.trainer.updates - start_updates
        atomic_torch_save({"learner": learner.state_dict(), "updates_done": done}, ckpt)
        exit_once_after(POLICY_FAULT_ENV, -(-done // chunk), out, "checkpoint")
        if bar is None and echo is not None:
            echo(f"{out.name}: {done}/{updates} SAC updates")
    if bar is not None:
        bar.close()
    seconds = time.perf_counter() - t0
    res = evaluate_policy(cfg.env, the_task, learner, episodes, seed)
    res.update(setup, updates_done=done, train_seconds=seconds, run_method=cfg.method, env=cfg.env,
               run_seed=cfg.seed)
    res.pop("policy")
    res["policy_config"] = vars(cfg.policy)
    run.write_json(out / "eval.json", res)
    return res

