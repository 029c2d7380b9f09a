"""Zero-shot evaluation: the explored model + iCEM solve a task they never saw, on the real env."""
from __future__ import annotations

import functools
import hashlib
import json
import time
from pathlib import Path

import numpy as np
import torch

from torchrl_softae.envs.model_env import PROPAGATION_MODES
from torchrl_softae.modules import EnsembleWorldModel
from torchrl_softae.pipeline.builders import build_planner_policy, build_world_model
from torchrl_softae.pipeline.catalog import ENV_HELDOUT, get_env_entry, get_task, get_tasks, heldout_note, run_entry
from torchrl_softae.pipeline.config import ConfigError, ExploreConfig, apply_overrides
from torchrl_softae.pipeline.data import (ModelAccuracy, episode_seed, global_rng_states, make_real_env,
                                          seed_everything, set_global_rng_states)
from torchrl_softae.pipeline.provenance import code_identity, machine
from torchrl_softae.pipeline.runs import REFERENCES_FILE, CheckpointError, RunDir, atomic_torch_save, exit_once_after
from torchrl_softae.tasks.base import Task, TaskReward

__all__ = ["load_run", "zero_shot", "task_policy", "reference_returns", "evaluate_run", "eval_file_name",
           "evaluation_identity", "write_references", "TaskCheckpoint", "REFERENCE_POLICIES", "REFERENCES_FILE",
           "TASK_CHECKPOINT_SECONDS", "TASK_FAULT_ENV"]

#: seconds of planning between two saves of a task's progress (at most what a kill loses)
TASK_CHECKPOINT_SECONDS = 60.0
#: test hook (:func:`~torchrl_softae.pipeline.runs.exit_once_after`):
#: ``SOFTAE_EXIT_AFTER_TASK_CHECKPOINT=K`` dies right after a task's K-th progress save, like a kill
TASK_FAULT_ENV = "SOFTAE_EXIT_AFTER_TASK_CHECKPOINT"


def load_run(run_dir: str | Path) -> tuple[ExploreConfig, EnsembleWorldModel, dict]:
    """Config, trained model and checkpoint state of a run dir."""
    run = RunDir(run_dir)
    if not run.exists():
        raise CheckpointError(f"{run.path} holds no checkpoint: run `softae explore --run-dir {run.path}` first")
    state = run.load()
    cfg = ExploreConfig.from_dict(state["config"])
    observation_spec, action_spec = get_env_entry(cfg.env).specs()
    d_s, d_a = observation_spec["observation"].shape[-1], action_spec.shape[-1]
    model = build_world_model(cfg.model, d_s, d_a)
    try:
        model.load_state_dict(state["model"])
    except RuntimeError as e:
        raise CheckpointError(f"checkpoint model does not match its config ({e})") from None
    return cfg, model.eval(), state


def task_rollouts(env: str, task: Task, episodes: int, seed: int, policy_for, keep_trajectories: bool = False,
                  checkpoint: TaskCheckpoint | None = None, bar=None) -> dict:
    """Roll out ``policy_for(env, episode_seed, episode_task)`` for ``episodes`` seeded episodes of
    ``task`` on the real env with the task's reward: ``{"returns": [...], "metrics": [{...}, ...],
    "initial_states": [...]}``, and with ``keep_trajectories`` the episodes' ``(T,)`` rollout
    tensordicts under ``"trajectories"`` (for a study that looks inside an episode).

    The one place that fixes the evaluation episodes: zero-shot controllers and the model-free
    references see the same initial states (and, for a task family, the same targets).

    ``checkpoint``: saves the episodes done after each one, and goes on after those an earlier,
    killed attempt saved (each episode is seeded on its own, so the rest are the same). ``bar``: a
    progress bar counting steps, advanced by the episodes read back (the policy counts the rest)."""
    real = make_real_env(get_env_entry(env), task.horizon)
    reward = TaskReward(task)
    real.append_transform(reward)
    returns, metrics, starts, lengths, trajectories = [], [], [], [], []
    saved = checkpoint.saved if checkpoint is not None and not keep_trajectories else None
    done = json.loads(saved["episodes"]) if saved is not None and saved.get("kind") == "episodes" else {}
    for key, into in (("returns", returns), ("metrics", metrics), ("initial_states", starts), ("steps", lengths)):
        into.extend(done.get(key, [])[:episodes])
    if bar is not None:
        bar.update(sum(lengths))
    for i in range(len(returns), episodes):
        s = episode_seed(seed, i)
        seed_everything(s)
        reward.task = episode_task = task.for_episode(s)
        policy = policy_for(real, s, episode_task)
        if episode_task.advance is not None:
            policy = _Advancing(policy, episode_task.advance)
        real.set_seed(s)
        traj = real.rollout(task.horizon, policy, break_when_any_done=True)
        starts.append(traj[0]["observation"].tolist())
        returns.append(float(traj["next", "reward"].sum()))
        metrics.append(episode_task.metrics(traj))
        lengths.append(len(traj))
        if episode_task is not task:
            metrics[-1].update({f"target_{k}": v for k, v in episode_task.params.items()})
        if keep_trajectories:
            trajectories.append(traj)
        elif checkpoint is not None:
            # as JSON, which keeps the numbers exactly and is what the result is written as
            checkpoint.save({"kind": "episodes", "episodes": json.dumps(
                {"returns": returns, "metrics": metrics, "initial_states": starts, "steps": lengths}, default=float)})
    real.close()
    res = {"returns": returns, "metrics": metrics, "initial_states": starts}
    return res | {"trajectories": trajectories} if keep_trajectories else res


class _Advancing:
    """``policy`` that first moves a time-varying task's reference to the step it acts at."""

    def __init__(self, policy, advance):
        self.policy, self.advance, self.t = policy, advance, 0

    def __call__(self, tensordict):
        self.advance(self.t)
        self.t += 1
        return self.policy(tensordict)


def planner_overrides(planner: dict | None) -> list[str] | None:
    """Planner settings ``{key: value}`` (a sweep's ``evaluate: {planner: ...}``) as the overrides
    :func:`evaluate_run` takes (``["planner.key=value", ...]``), or ``None`` for none."""
    return [f"planner.{k}={v}" for k, v in (planner or {}).items()] or None


def eval_file_name(task: str, planner_overrides: list[str] | None = None) -> str:
    """``TASK.json``, or ``TASK@key=value,....json`` for an evaluation planned with overrides."""
    suffix = ("@" + ",".join(o.split(".", 1)[1] for o in planner_overrides)) if planner_overrides else ""
    return f"{task}{suffix}.json"


def task_policy(cfg: ExploreConfig, model: EnsembleWorldModel, task: Task, action_spec, propagation: str = "mean",
                seed: int = 0, progress=None):
    """The zero-shot controller: iCEM with ``task``'s reward on the learned model, planned with the
    run's planner settings and, for optimistic propagation, the run's beta."""
    if propagation not in PROPAGATION_MODES:
        raise ConfigError(f"propagation {propagation!r}; valid: {', '.join(PROPAGATION_MODES)}")
    return build_planner_policy(model, action_spec, cfg.planner, mode=propagation, reward=task, beta=cfg.beta,
                                seed=seed, progress=progress)


@torch.no_grad()
def zero_shot(
    cfg: ExploreConfig,
    model: EnsembleWorldModel,
    task: Task,
    episodes: int = 3,
    seed: int = 0,
    propagation: str = "mean",
    progress: bool = True,
    batched: bool = True,
    checkpoint: TaskCheckpoint | None = None,
    on_steps=None,
) -> dict:
    """MPC with the task reward on the learned model, acting on the real env.

    ``batched``: the episodes run side by side, one env each, and the planner plans for all of
    their states in one call per step (a task family with a target per episode runs one episode
    after another). Initial states are the same either way (seeded per episode); the planner's
    random draws differ, except for a single episode, which plans alike as a batch of one. Returns
    ``{"returns": [...], "metrics": [{...}, ...]}``, one entry per episode; deterministic for a
    given seed.

    ``checkpoint``: the task's progress is saved there (:class:`TaskCheckpoint`), and what an
    earlier, killed attempt saved is continued: the same returns as one uninterrupted call.
    ``on_steps(done, total)``: called as the env steps advance (those read back from a killed
    attempt at once; ``total``: ``episodes`` x the task's horizon), for progress shown elsewhere
    than the bar ``progress`` draws.
    """
    bar = None
    if progress or on_steps is not None:
        from tqdm.auto import tqdm

        total = episodes * task.horizon
        bar = _StepCount(total, on_steps, tqdm(total=total, desc=f"zero-shot {task.name}", unit="step",
                                               leave=False) if progress else None)

    def planner(real, s, episode_task):
        return task_policy(cfg, model, episode_task, real.action_spec, propagation, seed=s, progress=bar)

    # one episode too: a batch of one plans and steps as the episode alone does, and its progress
    # saves go on mid-episode
    if batched and task.instantiate is None and task.advance is None:
        res = _task_rollouts_batched(cfg.env, task, episodes, seed, planner, checkpoint, bar)
    else:
        res = task_rollouts(cfg.env, task, episodes, seed, planner, checkpoint=checkpoint, bar=bar)
    if bar is not None:
        bar.close()
    return res


class _StepCount:
    """A task's env steps as they advance, for its progress bar and an ``on_steps(done, total)``
    listener: the planner policy and the rollouts call ``update(n)`` on it as on a tqdm bar."""

    def __init__(self, total: int, on_steps=None, bar=None):
        self.total, self.done, self.on_steps, self.bar = total, 0, on_steps, bar

    def update(self, n: int) -> None:
        self.done += n
        if self.bar is not None:
            self.bar.update(n)
        if self.on_steps is not None:
            self.on_steps(self.done, self.total)

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()


def _task_rollouts_batched(env: str, task: Task, episodes: int, seed: int, policy_for,
                           checkpoint: TaskCheckpoint | None = None, bar=None) -> dict:
    """:func:`task_rollouts` with the episodes side by side: E real envs seeded like the
    sequential episodes, one policy call per step for the ``(E,)`` batch of their states. An
    episode that ends stops stepping (its state keeps its slot in the batch).

    ``checkpoint`` (a replayable env, :attr:`~torchrl_softae.pipeline.entries.entry.EnvEntry.replayable`,
    and a policy with a ``search_state``): every ``checkpoint.every`` seconds the actions taken so
    far, the states reached, the policy's search state and the global generators are saved. A
    resumed attempt replays the actions on freshly seeded envs, checks that they reach the saved
    states (else it starts the task over), restores the rest and goes on."""
    from torchrl.envs.utils import step_mdp

    entry = get_env_entry(env)
    envs, tds = [], []
    for i in range(episodes):
        real = make_real_env(entry, task.horizon)
        real.append_transform(TaskReward(task))
        s = episode_seed(seed, i)
        seed_everything(s)
        real.set_seed(s)
        envs.append(real)
        tds.append(real.reset())
    policy = policy_for(envs[0], episode_seed(seed, 0), task)
    if not (entry.replayable and hasattr(policy, "search_state")):
        checkpoint = None
    keys = list(policy.in_keys)
    steps = [[] for _ in envs]
    alive = [True] * episodes
    taken = []  # the (E, d_a) actions of every step so far

    def act(actions):
        for i, real in enumerate(envs):
            if not alive[i]:
                continue
            out = real.step(tds[i].clone().set("action", actions[i]))
            steps[i].append(out)
            if bool(out.get(("next", "done"))):
                alive[i] = False
            tds[i] = step_mdp(out)
        taken.append(actions)

    def states():
        return torch.stack([td.get("observation") for td in tds])

    saved = checkpoint.saved if checkpoint is not None else None
    if saved is not None and saved.get("kind") == "steps":
        for actions in saved["actions"]:
            act(actions)
        if not torch.equal(states(), saved["observations"]):
            for real in envs:
                real.close()
            print(f"{checkpoint.path}: replaying its {len(taken)} steps did not reach the states it saved "
                  f"(the env is not deterministic here): {task.name} starts over")
            checkpoint.saved = None
            return _task_rollouts_batched(env, task, episodes, seed, policy_for, checkpoint, bar)
        policy.load_search_state(saved["planner"])
        set_global_rng_states(saved["rng"])
        if bar is not None:
            bar.update(sum(len(t) for t in steps))
    for _ in range(len(taken), task.horizon):
        if not any(alive):
            break
        batch = torch.stack([td.select(*keys) for td in tds])
        act(policy(batch).get("action"))
        if checkpoint is not None and checkpoint.due():
            checkpoint.save({"kind": "steps", "actions": torch.stack(taken), "observations": states(),
                             "planner": policy.search_state(), "rng": global_rng_states()})
    returns, metrics, starts = [], [], []
    for real, traj in zip(envs, steps):
        traj = torch.stack(traj)
        starts.append(traj[0]["observation"].tolist())
        returns.append(float(traj["next", "reward"].sum()))
        metrics.append(task.metrics(traj))
        real.close()
    return {"returns": returns, "metrics": metrics, "initial_states": starts}


class TaskCheckpoint:
    """One task's evaluation in progress, saved at ``path`` (``RUN/eval/TASK.partial.pt``) so that
    a killed evaluation goes on where it stopped rather than at the task's start.

    ``key``: what the saved progress must have been computed with to be continued (the settings,
    the model, the code, the machine: :func:`evaluate_run`'s); a file saved for another key, or
    unreadable, is ignored and replaced. ``resume``: continue what is saved (else start afresh).
    ``every``: seconds between two saves of a batch of episodes in progress (finished episodes of
    sequential ones are saved as each ends). Seconds and CPU seconds add up over the attempts.
    """

    def __init__(self, path: str | Path, key: dict, resume: bool = True, every: float = TASK_CHECKPOINT_SECONDS):
        self.path, self.every = Path(path), float(every)
        self.key = json.dumps(key, sort_keys=True, default=float)
        self.saved = self._read() if resume else None
        before = self.saved or {}
        self.attempts = int(before.get("attempts", 0)) + 1
        self.earlier_seconds = float(before.get("seconds", 0.0))
        self.earlier_cpu_seconds = float(before.get("cpu_seconds", 0.0))
        self._t0, self._cpu0 = time.perf_counter(), time.process_time()
        self._last_save, self.saves = self._t0, 0

    def _read(self) -> dict | None:
        if not self.path.exists():
            return None
        try:
            saved = torch.load(self.path, map_location="cpu", weights_only=True)
        except Exception:  # cut short or not ours: the task starts over
            return None
        return saved if isinstance(saved, dict) and saved.get("key") == self.key else None

    def seconds(self) -> float:
        """Wall seconds over every attempt so far."""
        return self.earlier_seconds + time.perf_counter() - self._t0

    def cpu_seconds(self) -> float:
        return self.earlier_cpu_seconds + time.process_time() - self._cpu0

    def due(self) -> bool:
        return time.perf_counter() - self._last_save >= self.every

    def save(self, progress: dict) -> None:
        atomic_torch_save({**progress, "key": self.key, "attempts": self.attempts, "seconds": self.seconds(),
                           "cpu_seconds": self.cpu_seconds()}, self.path)
        self._last_save = time.perf_counter()
        self.saves += 1
        exit_once_after(TASK_FAULT_ENV, self.saves, self.path.parent, "task checkpoint")

    def provenance(self) -> dict:
        """What a finished task's result records of its attempts: their seconds, and how many
        processes computed it with the seconds of the earlier ones (when more than one)."""
        out = {"seconds": self.seconds(), "cpu_seconds": self.cpu_seconds()}
        if self.attempts > 1:
            out.update(attempts=self.attempts, earlier_seconds=self.earlier_seconds,
                       earlier_cpu_seconds=self.earlier_cpu_seconds)
        return out

    def discard(self) -> None:
        self.path.unlink(missing_ok=True)


#: the model-free references a zero-shot controller is put next to, and their table labels
REFERENCE_POLICIES = {"random": "random actions, no model", "zero": "no control (zero action)"}


@torch.no_grad()
def reference_returns(env: str, task: str | Task, policy: str = "random", episodes: int = 3, seed: int = 0) -> list[float]:
    """Task returns without a model, on the same episodes (seeds) as :func:`zero_shot`.

    ``policy="random"``: uniform random actions from the action spec (what random exploration
    does); ``"zero"``: the centre of the action space at every step (no control). They tell a
    zero-shot controller that solves a task from one that does no better than not trying.
    """
    if policy not in REFERENCE_POLICIES:
        raise ValueError(f"reference policy {policy!r}: expected one of {', '.join(REFERENCE_POLICIES)}")
    if isinstance(task, str):
        try:
            task = get_task(get_env_entry(env), task)
        except ValueError as e:
            raise ConfigError(str(e)) from None

    def reference_policy(real, s, episode_task):
        if policy == "random":
            return None  # TorchRL's rollout samples from the action spec
        spec = real.action_spec
        centre = (spec.space.low + spec.space.high) / 2
        return lambda td: td.set("action", centre.expand(*td.batch_size, *centre.shape).clone())

    return task_rollouts(env, task, episodes, seed, reference_policy)["returns"]


def evaluate_run(
    run_dir: str | Path, tasks: list[str] | None = None, episodes: int = 3, seed: int = 0,
    propagation: str = "mean", progress: bool = True, planner_overrides: list[str] | None = None,
    references: bool = False, task_episodes: dict[str, int] | None = None, resume: bool = False,
    on_task=None, checkpoint_seconds: float = TASK_CHECKPOINT_SECONDS, on_steps=None,
) -> dict:
    """Zero-shot returns on ``tasks`` (names of the env's tasks or ``module:attr`` references;
    default: all of the env's) and held-out normalized MSE.

    ``episodes`` per task, or ``task_episodes[name]`` for the tasks that map names there.

    ``planner_overrides`` (``["planner.horizon=30", ...]``) plan the tasks differently from the
    exploration. Results are written to ``RUN/eval/TASK.json`` (``TASK@key=value,...json`` with
    overrides) and ``RUN/eval/model_accuracy.json``. ``references``: also the returns of the
    model-free references (:data:`REFERENCE_POLICIES`) on the same episodes, to
    ``RUN/eval/references.json`` (``softae report`` adds them as rows).

    ``resume``: a task whose saved result was computed for this checkpoint's model with these
    settings, by the same code on the same machine (:func:`evaluation_identity`), is read
    back instead of planned again, and a task a killed evaluation was in goes on from its last
    progress save (``RUN/eval/TASK.partial.pt``, every ``checkpoint_seconds`` of planning:
    :class:`TaskCheckpoint`), to the same result. Progress is saved with or without ``resume``.
    ``on_task(name, result, kept)`` is called after each task (``kept``: read back; its
    ``seconds`` and ``cpu_seconds`` are those of the processes that planned it, ``earlier_*``
    the part of them spent by killed attempts). ``on_steps(name, done, total)``: as a task's env
    steps advance (:func:`zero_shot`'s), for progress shown elsewhere than a bar.
    """
    cfg, model, state = load_run(run_dir)
    if planner_overrides:
        bad = [o for o in planner_overrides if not o.strip().startswith("planner.")]
        if bad:
            raise ConfigError(f"evaluate only overrides planner settings (planner.KEY=VALUE), got {bad}")
        apply_overrides(cfg, planner_overrides).validate()
    run = RunDir(run_dir)
    entry = run_entry(cfg)
    try:
        chosen = {k: t for name in (tasks or sorted(entry.tasks)) for k, t in get_tasks(entry, name).items()}
    except ValueError as e:
        raise ConfigError(str(e)) from None
    out = {"env": cfg.env, "method": cfg.method, "seed": cfg.seed, "episodes_explored": state["episode"] + 1,
           "transitions": state["num_transitions"], "heldout_set": heldout_note(cfg) or ENV_HELDOUT}
    accuracy = ModelAccuracy(entry, run, cfg.heldout_size, announce=print if progress else None)
    out.update(accuracy(model))
    out.update(accuracy.baselines)
    run.write_json(run.eval_dir / "model_accuracy.json", dict(out))
    out["tasks"] = {}
    identity = evaluation_identity(state)
    for name, task in chosen.items():
        n = (task_episodes or {}).get(name, episodes)
        path = run.eval_dir / eval_file_name(name, planner_overrides)
        # which model was evaluated and how: a resumed, longer exploration makes this result stale
        settings = {"propagation": propagation, "beta": cfg.beta, "seed": seed, "episodes": n,
                    "planner": dict(vars(cfg.planner)), "episodes_explored": out["episodes_explored"],
                    "success_metric": task.success_metric, **identity}
        res = saved_result(path, settings) if resume else None
        kept = res is not None
        checkpoint = TaskCheckpoint(path.with_suffix(".partial.pt"), settings, resume and not kept, checkpoint_seconds)
        if not kept:
            res = zero_shot(cfg, model, task, episodes=n, seed=seed, propagation=propagation, progress=progress,
                            checkpoint=checkpoint, on_steps=None if on_steps is None else functools.partial(on_steps, name))
            res["mean_return"] = float(np.mean(res["returns"]))
            res.update(settings, **checkpoint.provenance())
            run.write_json(path, res)
        checkpoint.discard()  # (also what a process killed between the two writes left beside a result)
        out["tasks"][name] = res
        if on_task is not None:
            on_task(name, res, kept)
    if references:
        out["references"] = write_references(run, cfg.env, chosen, episodes, seed, task_episodes)
    return out


def evaluation_identity(state: dict) -> dict:
    """What a saved task result must share with a new evaluation to be kept by ``resume``, beside
    its settings: the model (a digest of the checkpoint's weights), the code
    (:func:`~torchrl_softae.pipeline.provenance.code_identity`) and the machine (CPU, instruction
    sets, torch, threads, kernels), since each of them changes the planner's arithmetic."""
    digest = hashlib.sha256()
    for key in sorted(state["model"]):
        tensor = state["model"][key].detach().cpu().contiguous()
        digest.update(key.encode())
        digest.update(tensor.reshape(-1).view(torch.uint8).numpy().tobytes())
    return {"model_sha256": digest.hexdigest(), "code": code_identity(), "machine": machine()}


def saved_result(path: Path, settings: dict) -> dict | None:
    """The result saved at ``path`` if it was computed with ``settings`` (as JSON reads them back;
    any subset of a result's settings), else ``None``."""
    if not path.exists():
        return None
    try:
        saved = json.loads(path.read_text())
    except json.JSONDecodeError:  # not a result (written elsewhere, or cut short): evaluate again
        return None
    expected = json.loads(json.dumps(settings, default=float))
    return saved if all(saved.get(k) == v for k, v in expected.items()) and "returns" in saved else None


def write_references(run: RunDir, env: str, tasks: dict[str, Task], episodes: int, seed: int,
                     task_episodes: dict[str, int] | None = None) -> dict:
    """The model-free references' returns on ``tasks`` (the evaluation's episodes: ``episodes``, or
    ``task_episodes[name]``), merged into ``RUN/eval/references.json``:
    ``{"episodes", "seed", "task_episodes", "returns": {label: {task: [...]}}}``."""
    path = run.eval_dir / REFERENCES_FILE
    want = {name: (task_episodes or {}).get(name, episodes) for name in tasks}
    known = json.loads(path.read_text()) if path.exists() else {}
    if known.get("episodes") != episodes or known.get("seed") != seed:
        known = {"episodes": episodes, "seed": seed, "returns": {}}
    counts = known.setdefault("task_episodes", {})  # only the tasks that differ from ``episodes``
    for policy, label in REFERENCE_POLICIES.items():
        per_task = known["returns"].setdefault(label, {})
        for name, task in tasks.items():
            if name not in per_task or counts.get(name, episodes) != want[name]:
                per_task[name] = reference_returns(env, task, policy, want[name], seed)
    for name, n in want.items():
        if n == episodes:
            counts.pop(name, None)
        else:
            counts[name] = n
    run.write_json(path, known)
    return known

