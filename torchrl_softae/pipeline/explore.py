"""Episode-wise active exploration (paper, Algorithm 1).

For episode n = 1..N:
    pi_n   = iCEM on the current ensemble with the exploration reward (or random / a task for baselines)
    D_n    = D_{n-1} + rollout of pi_n on the real env (a TorchRL Collector, T steps)
    model  = retrain the ensemble on D_n (Table S6 schedule)
    -> checkpoint: model, optimizer, replay buffer, history (a killed run resumes here)
"""
from __future__ import annotations

import math
import time
import uuid
import warnings
from pathlib import Path

import numpy as np
import torch
from torchrl.collectors import Collector

from torchrl_softae.envs.guard import EnvFaultWarning
from torchrl_softae.objectives import EnsembleLoss, EnsembleTrainer
from torchrl_softae.pipeline.builders import build_exploration_policy, build_world_model
from torchrl_softae.pipeline.catalog import get_task, run_entry
from torchrl_softae.pipeline.config import ConfigError, ExploreConfig, flat_config
from torchrl_softae.pipeline.data import (ModelAccuracy, coverage, episode_seed, heldout_set, make_real_env,
                                          normalized_mse, projection_bounds, seed_everything)
from torchrl_softae.pipeline.evaluate import zero_shot
from torchrl_softae.pipeline.methods import get_method
from torchrl_softae.pipeline.policy import build_policy_learner
from torchrl_softae.pipeline.guards import RunLock, Stopped, stop_on_signals
from torchrl_softae.pipeline.runs import CheckpointError, RunDir, exit_once_after, signal_once_at

__all__ = ["Explorer", "explore", "make_real_env", "coverage", "heldout_set", "normalized_mse"]

# Keys that may change between a run and its resumption (everything else must match).
RESUMABLE_KEYS = {"episodes", "wandb", "eval_every", "eval_episodes"}


def _fixed_part(config: dict) -> dict:
    return {k: v for k, v in flat_config(config).items() if not _free_to_change(k, config)}


def _free_to_change(key: str, config: dict) -> bool:
    """Keys a resumed run may change: :data:`RESUMABLE_KEYS`, and the SAC settings of a method
    that trains no policy (they cannot have changed what it collected)."""
    if key in RESUMABLE_KEYS:
        return True
    return key.startswith("policy.") and not get_method(config.get("method", "softae")).trains_policy


class Explorer:
    """Runs (or resumes) ``softae explore`` for one config into one run dir.

    Args:
        cfg: a validated :class:`ExploreConfig`.
        run_dir: where everything is written; an existing run with the same config resumes.
        progress: tqdm bars for episodes, planning steps and training (for a terminal).
        echo: where one-line messages go (resuming, a summary per episode when there are no bars,
            where the results are); ``None`` for silence. The resume line is printed even then
            when ``announce_resume`` is true.
    """

    def __init__(self, cfg: ExploreConfig, run_dir: str | Path, progress: bool = True, echo=print,
                 announce_resume: bool = True, on_episode=None):
        self.cfg = cfg.validate()
        self.run = RunDir(run_dir)
        self.run.path.mkdir(parents=True, exist_ok=True)
        self.progress = progress
        self.echo = echo
        self.announce_resume = announce_resume
        self.on_episode = on_episode  # called with each finished (checkpointed) episode's row
        self.entry = run_entry(self.cfg)
        self.task = get_task(self.entry, cfg.task) if cfg.task else None

    # ------------------------------------------------------------------ set-up / resume
    def _check_config(self) -> str | None:
        """Returns the W&B id of an existing run after checking its config matches."""
        stored = self.run.read_config()
        if stored is None:
            return None
        old, new = flat_config(stored.get("config", {})), flat_config(self.cfg.to_dict())
        diff = [f"{k}: stored {old.get(k)!r} != requested {new.get(k)!r}"
                for k in sorted(set(old) | set(new))
                if not _free_to_change(k, self.cfg.to_dict()) and old.get(k) != new.get(k)]
        if diff:
            raise ConfigError(
                f"{self.run.path} holds a run with a different configuration ({'; '.join(diff)}); "
                "use another --run-dir or the original settings"
            )
        return stored.get("wandb_id")

    def _logger(self, wandb_id: str):
        if self.cfg.wandb == "disabled":
            return None
        from torchrl.record.loggers.wandb import WandbLogger

        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            return WandbLogger(
                exp_name=f"{self.cfg.env}-{self.cfg.method}-s{self.cfg.seed}", offline=self.cfg.wandb == "offline",
                save_dir=str(self.run.path), id=wandb_id, project="torchrl-softae", resume="allow",
                config=self.cfg.to_dict(), log_env_packages=False,
            )

    def run_exploration(self) -> list[dict]:
        """Explore into the run dir as its only writer (:class:`~.guards.RunLock`); SIGTERM or
        SIGINT stop it at once, leaving the last complete episode (:class:`~.guards.Stopped`, with
        ``done`` and ``total`` episodes set), and the same command resumes it."""
        with RunLock(self.run.path, note=self.echo or print), stop_on_signals():
            try:
                return self._run_exploration()
            except Stopped as e:
                e.done, e.total = self.run.saved_episodes, self.cfg.episodes
                raise

    def _run_exploration(self) -> list[dict]:
        cfg = self.cfg
        wandb_id = self._check_config() or uuid.uuid4().hex[:12]
        self.run.write_json(self.run.config_path, {"config": cfg.to_dict(), "wandb_id": wandb_id})
        env = make_real_env(self.entry, cfg.episode_length)
        d_s = env.observation_spec["observation"].shape[-1]
        d_a = env.action_spec.shape[-1]
        capacity = cfg.episodes * cfg.episode_length + 1
        seed_everything(cfg.seed)
        model = build_world_model(cfg.model, d_s, d_a)
        trainer = EnsembleTrainer(
            EnsembleLoss(model), lr=cfg.train.lr, batch_size=cfg.train.batch_size, epochs=cfg.train.epochs,
            max_grad_steps=cfg.train.max_grad_steps, val_fraction=cfg.train.val_fraction,
            precision=cfg.train.precision, progress=self.progress,
        )
        method = get_method(cfg.method)
        learner = (build_policy_learner(cfg.policy, model, env.action_spec, self.task, method.propagation, cfg.beta,
                                        cfg.seed)
                   if method.trains_policy else None)
        history: list[dict] = []
        start = 0
        if self.run.exists():
            state = self.run.load()
            if _fixed_part(state["config"]) != _fixed_part(cfg.to_dict()):
                raise CheckpointError(f"{self.run.checkpoint_path} belongs to another configuration than config.json")
            try:
                model.load_state_dict(state["model"])
                trainer.load_state_dict(state["trainer"])
                if learner is not None:
                    learner.load_state_dict(state["policy"])
            except (RuntimeError, KeyError, ValueError) as e:
                raise CheckpointError(f"checkpoint does not fit this model ({e})") from None
            history = state["history"]
            start = state["episode"] + 1
            self.run.write_logs(history)  # logs a full disk left behind the checkpoint catch up
            rb = self.run.load_replay_buffer(state, capacity)
            if self.announce_resume or self.echo is not None:
                what = (f"resuming {self.run.path} at episode {start + 1} of {cfg.episodes}" if start < cfg.episodes
                        else f"{self.run.path} already holds all {cfg.episodes} episodes: nothing to do")
                (self.echo or print)(what)
        else:
            rb = self.run.new_replay_buffer(capacity)
        accuracy = ModelAccuracy(self.entry, self.run, cfg.heldout_size,
                                 announce=self.echo or (print if self.progress else None))
        bounds = projection_bounds(self.entry, accuracy.heldout)
        logger = self._logger(wandb_id)

        bar = None
        if self.progress and start < cfg.episodes:
            from tqdm.auto import tqdm

            bar = tqdm(total=cfg.episodes, initial=start, desc=f"explore {cfg.env} [{cfg.method}]", unit="episode")
        try:
            for n in range(start, cfg.episodes):
                row = self._episode(n, env, model, trainer, rb, accuracy, bounds, learner)
                history.append(row)
                # No RNG state: every episode reseeds from (seed, episode), so a resumed run draws the
                # same numbers as an uninterrupted one.
                state = {
                    "episode": n, "config": cfg.to_dict(), "model": model.state_dict(), "trainer": trainer.state_dict(),
                    "history": history, "wandb_id": wandb_id,
                }
                if learner is not None:  # the SAC policy, its optimizer and imagined data (MBPO methods)
                    state["policy"] = learner.state_dict()
                self.run.save(state, rb)
                if self.on_episode is not None:
                    self.on_episode(row)
                exit_once_after(FAULT_ENV, n + 1, self.run.path, "episode")
                if logger is not None:
                    for k, v in row.items():
                        if isinstance(v, (int, float)) and k != "episode" and math.isfinite(v):
                            logger.log_scalar(k, v, step=n)
                if bar is not None:
                    bar.update(1)
                    bar.set_postfix(nmse=f"{row['heldout_nmse']:.3g}", cov=f"{row['coverage']:.2f}")
                elif self.echo is not None:
                    self.echo(f"episode {n + 1}/{cfg.episodes}: {row['transitions']} transitions, held-out normalized MSE "
                              f"{row['heldout_nmse']:.4g}, coverage {row['coverage']:.3f}, collect {row['collect_seconds']:.0f} s, "
                              f"train {row['train_seconds']:.0f} s ({row['train_precision']})"
                              + (f", SAC {row['policy_seconds']:.0f} s" if "policy_seconds" in row else ""))
            if bar is not None:
                bar.close()
            if logger is not None:
                import wandb

                wandb.finish()
        finally:  # a failed episode still closes the env: a real robot vents
            env.close()
        self.model, self.replay_buffer, self.history = model, rb, history
        return history

    # ------------------------------------------------------------------ one episode
    def _episode(self, n, env, model, trainer, rb, accuracy, bounds, learner=None) -> dict:
        cfg = self.cfg
        s = episode_seed(cfg.seed, n)
        seed_everything(s)
        t0, cpu0 = time.perf_counter(), time.process_time()
        step_bar = None
        if self.progress:
            from tqdm.auto import tqdm

            step_bar = tqdm(total=cfg.episode_length, desc=f"episode {n} (plan+act)", leave=False, unit="step")
        policy = build_exploration_policy(cfg, model, env, self.task, seed=s, progress=step_bar, learner=learner)
        if hasattr(policy, "reset"):
            policy.reset()
        env.set_seed(s)
        faults_before = env.base_env.num_faults
        with warnings.catch_warnings():
            warnings.simplefilter("always", EnvFaultWarning)
            # One batch of one episode. The env lives across episodes: a real robot's safety layer
            # never re-arms once closed, and a Collector closes its env when it reaches
            # total_frames, so it gets no total (-1) and is shut down keeping the env open.
            collector = Collector(
                env, policy, frames_per_batch=cfg.episode_length, total_frames=-1,
                auto_register_policy_transforms=False,
            )
            data = next(iter(collector))
            collector.shutdown(close_env=False)
        if step_bar is not None:
            step_bar.close()
        signal_once_at("collect", n + 1, self.run.path)
        data = data.reshape(-1)
        keys = {"observation", *self.entry.projection_keys}
        rb.extend(data.select(*keys, "action", *(("next", k) for k in keys), ("next", "reward"),
                              ("next", "done"), ("next", "env_fault"), strict=False).cpu())
        t_collect = time.perf_counter() - t0

        signal_once_at("train", n + 1, self.run.path)
        t1 = time.perf_counter()
        report = trainer.fit(rb, generator=torch.Generator().manual_seed(s))
        t_train = time.perf_counter() - t1
        # this process's CPU time (every thread) over collect and train: unlike the wall clock,
        # it costs nothing while the run is paused or waits for a shared core
        cpu_seconds = time.process_time() - cpu0

        stored = rb.storage[: len(rb)]
        policy_row = {}
        if learner is not None:  # MBPO: the task policy keeps training on the retrained model
            t2 = time.perf_counter()
            info = learner.train(stored, cfg.policy.updates_per_step * cfg.episode_length, seed=s)
            policy_row = {"policy_seconds": time.perf_counter() - t2, "policy_updates": learner.trainer.updates,
                          **{f"sac/{k}": v for k, v in info.items()}}
        row = {
            "episode": n,
            "transitions": len(rb),
            "env_faults": int(env.base_env.num_faults - faults_before),
            "collect_seconds": t_collect,
            "train_seconds": t_train,
            "cpu_seconds": cpu_seconds,
            "plan_ms_per_step": 1e3 * getattr(policy, "seconds", 0.0) / max(getattr(policy, "calls", 0), 1),
            "train_loss": report.train_loss[-1] if report.train_loss else float("nan"),
            "val_mse": report.final_val_mse,
            "grad_steps": report.grad_steps,
            "train_precision": report.precision,
            "coverage": coverage(self.entry, stored, bounds),
            "episode_env_reward": float(data["next", "reward"].sum()),
            **accuracy(model),
            **policy_row,
        }
        if cfg.eval_every and ((n + 1) % cfg.eval_every == 0 or n + 1 == cfg.episodes):
            for name, task in self.entry.tasks.items():
                res = zero_shot(cfg, model, task, episodes=cfg.eval_episodes, seed=10_000 + n, progress=False)
                row[f"return/{name}"] = float(np.mean(res["returns"]))
        return row


def explore(cfg: ExploreConfig, run_dir: str | Path, progress: bool = True, echo=print, on_episode=None) -> list[dict]:
    """Run or resume an exploration; returns the per-episode history."""
    return Explorer(cfg, run_dir, progress=progress, echo=echo, on_episode=on_episode).run_exploration()


#: test hook (:func:`~torchrl_softae.pipeline.runs.exit_once_after`): ``SOFTAE_EXIT_AFTER_EPISODE=K``
#: (or ``K:NAME``) makes a run die right after checkpointing episode K, once per run dir, to test
#: that sweeps retry and resume killed runs
FAULT_ENV = "SOFTAE_EXIT_AFTER_EPISODE"
