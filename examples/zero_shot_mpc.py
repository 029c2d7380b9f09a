"""Zero-shot MPC: the explored model + iCEM solve a task they never saw, on the real env.

    python examples/softae_exploration.py --out model.pt
    python examples/zero_shot_mpc.py --model model.pt --task swingup

Library pieces and TorchRL only: the saved ensemble in an ``EnsembleModelEnv`` (mean propagation)
with the task's reward (``TaskReward``) planned by ``ICEMPlanner``; the real env reports the same
task reward.
"""
from __future__ import annotations

import argparse
from dataclasses import dataclass


# ----------------------------------------------------------------------------- config
@dataclass
class Config:
    model: str = "softae_model.pt"   # written by examples/softae_exploration.py
    task: str = "swingup"            # a task of the env (tasks_for(env)), or module:attr naming your own Task
    episodes: int = 3
    seed: int = 0
    horizon: int = 20                # iCEM (Table S7; longer than exploration's where a task needs it)
    num_candidates: int = 200
    top_k: int = 20
    optim_steps: int = 5
    precision: str = "fp32"


def parse_config() -> Config:
    cfg = Config()
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    for name, value in vars(cfg).items():
        p.add_argument("--" + name.replace("_", "-"), type=type(value), default=value)
    return Config(**vars(p.parse_args()))


def main(cfg: Config) -> list[float]:
    import torch
    from torchrl.envs import TransformedEnv

    import torchrl_softae  # registers the gymnasium ids
    from torchrl_softae.envs import EnsembleModelEnv
    from torchrl_softae.envs.references import make_env
    from torchrl_softae.modules import EnsembleWorldModel, ICEMPlanner
    from torchrl_softae.tasks import TaskReward, load_tasks, tasks_for

    torchrl_softae.keep_freed_memory()  # process-wide: the planner's large tensors reuse memory, no page faults

    saved = torch.load(cfg.model, weights_only=False)
    model = EnsembleWorldModel(saved["observation_dim"], saved["action_dim"], **saved["model_kwargs"])
    model.load_state_dict(saved["state_dict"])
    model.eval()
    if ":" in cfg.task:  # your own task (module:attr); the first, where it names several
        task = next(iter(load_tasks(cfg.task).values()))
    else:
        tasks = tasks_for(saved["env"])
        if cfg.task not in tasks:
            raise SystemExit(f"unknown task {cfg.task!r} for {saved['env']}; valid tasks: {', '.join(sorted(tasks))}")
        task = tasks[cfg.task]

    real = TransformedEnv(make_env(saved["env"]), TaskReward(task))
    model_env = TransformedEnv(EnsembleModelEnv(model, action_spec=real.action_spec.clone(), mode="mean"),
                               TaskReward(task))
    planner = ICEMPlanner(model_env, planning_horizon=cfg.horizon, num_candidates=cfg.num_candidates,
                          top_k=cfg.top_k, optim_steps=cfg.optim_steps, precision=cfg.precision, seed=cfg.seed)
    returns = []
    for episode in range(cfg.episodes):
        planner.reset()
        real.set_seed(cfg.seed + episode)
        with torch.no_grad():
            traj = real.rollout(task.horizon, planner, break_when_any_done=True)
        returns.append(float(traj["next", "reward"].sum()))
        metrics = task.metrics(traj)
        print(f"episode {episode + 1}: return {returns[-1]:.4g}"
              + "".join(f", {k} {v:.3g}" for k, v in metrics.items()), flush=True)
    print(f"{cfg.task}: mean return {sum(returns) / len(returns):.4g} over {len(returns)} episodes")
    return returns


if __name__ == "__main__":
    main(parse_config())
