"""Losses and training schedules: the ensemble's (world model) and MBPO's (SAC on the model)."""
from torchrl_softae.objectives.ensemble_loss import EnsembleLoss
from torchrl_softae.objectives.mbpo import (MBPOTrainer, PolicyForRealEnv, branched_rollouts,
                                            make_sac_actor_critic)
from torchrl_softae.objectives.training import EnsembleTrainer, TrainingReport, transitions_from

__all__ = ["EnsembleLoss", "EnsembleTrainer", "TrainingReport", "transitions_from", "MBPOTrainer",
           "PolicyForRealEnv", "branched_rollouts", "make_sac_actor_critic"]
