"""Data sets of ssm-ms: each DataModule yields ``{"index", "y", ...}`` batches of trajectories."""

from datamodules.base import Normalizer, TrajectoryDataModule, TrajectoryDataset

__all__ = ["Normalizer", "TrajectoryDataModule", "TrajectoryDataset"]
