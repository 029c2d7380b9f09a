"""Losses and training schedules."""
from torchrl_softae.objectives.ensemble_loss import EnsembleLoss
from torchrl_softae.objectives.training import EnsembleTrainer, TrainingReport, transitions_from

__all__ = ["EnsembleLoss", "EnsembleTrainer", "TrainingReport", "transitions_from"]
