"""SoftAE exploration of a registered env, written with library pieces and TorchRL only.

Algorithm 1 of the paper in plain sight: per episode, a TorchRL ``Collector`` runs iCEM on the
ensemble (optimistic propagation with hallucinated control, reward ||sigma||) on the real env,
the transitions go to a TorchRL replay buffer, and the ensemble is retrained on all of them.

    python examples/softae_exploration.py                                  # Pendulum-v1, 10 episodes
    python examples/softae_exploration.py --env SoftArm-v0 --episodes 20 --out arm_model.pt

The model is saved for ``examples/zero_shot_mpc.py``. No ``torchrl_softae.pipeline`` import: the
``softae`` CLI adds checkpoints, resume, held-out metrics and plots on top of the same pieces.
"""
from __future__ import annotations

import argparse
from dataclasses import dataclass

# ----------------------------------------------------------------------------- config
@dataclass
class Config:
    env: str = "Pendulum-v1"       # a gymnasium id (ours, or e.g. Reacher-v5), module:EnvId-v0 or module:callable
    episodes: int = 10             # N
    episode_length: int = 200      # T (Table S6)
    seed: int = 0
    beta: float = 2.0              # confidence-set width (Table S6)
    ensemble_size: int = 5         # L (Table S6)
    num_cells: int = 256
    depth: int = 4
    lr: float = 5e-5
    batch_size: int = 64
    epochs: int = 50
    max_grad_steps: int = 5000
    horizon: int = 10              # iCEM (Table S7)
    num_candidates: int = 200
    top_k: int = 20
    optim_steps: int = 5
    precision: str = "fp32"        # "auto": bf16 where the CPU has native bf16
    wandb_dir: str = "runs/example-wandb"
    out: str = "softae_model.pt"


def parse_config() -> Config:
    cfg = Config()
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    for name, value in vars(cfg).items():
        p.add_argument("--" + name.replace("_", "-"), type=type(value), default=value)
    return Config(**vars(p.parse_args()))


def main(cfg: Config) -> None:
    import torch
    from torchrl.collectors import Collector
    from torchrl.data import LazyTensorStorage, ReplayBuffer
    from torchrl.envs import Compose, StepCounter, TransformedEnv
    from torchrl.record.loggers.wandb import WandbLogger

    import torchrl_softae  # registers the gymnasium ids
    from torchrl_softae.envs import EnsembleModelEnv, HallucinatedControl, UncertaintyReward
    from torchrl_softae.envs.references import make_env
    from torchrl_softae.modules import EnsembleWorldModel, ICEMPlanner
    from torchrl_softae.objectives import EnsembleLoss, EnsembleTrainer

    torch.manual_seed(cfg.seed)
    torchrl_softae.keep_freed_memory()  # process-wide: the planner's large tensors reuse memory, no page faults
    # ------------------------------------------------------------------------- the real env
    # float64 observations (gymnasium's MuJoCo envs) come out float32, as the model computes
    env = make_env(cfg.env).append_transform(StepCounter(max_steps=cfg.episode_length))
    env.set_seed(cfg.seed)
    d_s = env.observation_spec["observation"].shape[-1]
    d_a = env.action_spec.shape[-1]

    # ------------------------------------------------------------------------- model + exploration planner
    model = EnsembleWorldModel(d_s, d_a, ensemble_size=cfg.ensemble_size, num_cells=cfg.num_cells, depth=cfg.depth)
    trainer = EnsembleTrainer(EnsembleLoss(model), lr=cfg.lr, batch_size=cfg.batch_size, epochs=cfg.epochs,
                              max_grad_steps=cfg.max_grad_steps)
    hallucinate = HallucinatedControl(beta=cfg.beta)                   # action [a, eta]
    uncertainty = UncertaintyReward()                                    # reward ||sigma / state std||
    action_spec = env.action_spec.clone()
    model_env = TransformedEnv(EnsembleModelEnv(model, action_spec=action_spec, mode="optimistic"),
                               Compose(hallucinate, uncertainty))
    planner = ICEMPlanner(model_env, planning_horizon=cfg.horizon, num_candidates=cfg.num_candidates,
                          top_k=cfg.top_k, optim_steps=cfg.optim_steps, precision=cfg.precision, seed=cfg.seed)
    policy = hallucinate.policy_for_real_env(planner)                   # emits the real action only

    replay = ReplayBuffer(storage=LazyTensorStorage(cfg.episodes * cfg.episode_length))
    logger = WandbLogger(exp_name=f"example-{cfg.env}-softae", offline=True, save_dir=cfg.wandb_dir,
                         project="torchrl-softae")

    # ------------------------------------------------------------------------- Algorithm 1
    for episode in range(cfg.episodes):
        policy.reset()  # a fresh warm start
        # the planner keeps no recurrent state: the env needs no InitTracker
        collector = Collector(env, policy, frames_per_batch=cfg.episode_length, total_frames=cfg.episode_length,
                              auto_register_policy_transforms=False)
        with torch.no_grad():  # planning needs no graph
            data = next(iter(collector))
        collector.shutdown()
        replay.extend(data.reshape(-1).select("observation", "action", ("next", "observation")))
        report = trainer.fit(replay)
        # sigma per dimension relative to the data's state std, so units do not decide the norm
        uncertainty.set_scale(model.input_normalizer.scale[:d_s])
        with torch.no_grad():
            mean_sigma = float(model(data.select("observation", "action").reshape(-1))["epistemic_std"].mean())
        logger.log_scalar("train_loss", report.train_loss[-1], step=episode)
        logger.log_scalar("val_mse", report.final_val_mse, step=episode)
        logger.log_scalar("mean_sigma_on_episode", mean_sigma, step=episode)
        print(f"episode {episode + 1}/{cfg.episodes}: {len(replay)} transitions, "
              f"val MSE {report.final_val_mse:.4g}, mean sigma on the episode {mean_sigma:.4g}", flush=True)

    torch.save({"env": cfg.env, "observation_dim": d_s, "action_dim": d_a,
                "model_kwargs": dict(ensemble_size=cfg.ensemble_size, num_cells=cfg.num_cells, depth=cfg.depth),
                "state_dict": model.state_dict()}, cfg.out)
    print(f"model saved to {cfg.out}")


if __name__ == "__main__":
    main(parse_config())
