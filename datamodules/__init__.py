"""Data sets of ssm-ms: each DataModule yields ``{"index", "y", ...}`` batches of trajectories."""

from datamodules.base import TrajectoryDataModule
from datamodules.dataset import TrajectoryDataset
from datamodules.normalizer import Normalizer

__all__ = ["Normalizer", "TrajectoryDataModule", "TrajectoryDataset"]
