"""The LightningCLI behind ``cli.py`` (importable, so that tests can run it in-process)."""

from __future__ import annotations

import lightning.pytorch as pl
from lightning.pytorch.cli import LightningCLI

from ssm_ms.perf import configure_allocator


def main(args: list[str] | None = None, run: bool = True) -> LightningCLI:
    """Parse ``args`` (default: ``sys.argv``) and run the subcommand.

    Subclass mode for model and data (configs name them by ``class_path``) and the omegaconf parser
    (configs may interpolate, e.g. ``state_dim: ${model.init_args.state_dim}``).
    """
    configure_allocator()  # large CPU tensors: reuse freed memory instead of page-faulting it back
    return LightningCLI(
        pl.LightningModule,
        pl.LightningDataModule,
        subclass_mode_model=True,
        subclass_mode_data=True,
        parser_kwargs={"parser_mode": "omegaconf"},
        save_config_kwargs={"overwrite": True},
        args=args,
        run=run,
    )
