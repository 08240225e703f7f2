"""What a fit prints that a user cannot act on, dropped: :func:`quiet_lightning`.

Lightning's advertisements for its cloud services go, and torch's deprecation warning that Lightning triggers, and
nothing else of their output:

- ``💡 Tip: For seamless cloud logging ...`` (litlogger), logged by every fit, and ``💡 Tip: For seamless cloud
  uploads ...`` (litmodels), by every fit with a checkpoint callback: INFO lines of ``rank_zero_info``;
- ``isinstance(treespec, LeafSpec)`` is deprecated: torch's warning, which Lightning's own pytree helper triggers
  at the first training step.
"""

from __future__ import annotations

import logging
import warnings

# the logger rank_zero_info writes to: lightning.pytorch.utilities.rank_zero sets it (as lightning_utilities'
# rank_zero_module.log) when imported, which importing lightning.pytorch does
RANK_ZERO_LOGGER = "lightning.pytorch.utilities.rank_zero"
TIPS = "💡 Tip: For seamless cloud "  # what both advertisements start with
LEAFSPEC = r"`isinstance\(treespec, LeafSpec\)` is deprecated"


class _DropTip(logging.Filter):
    """Drops the records whose message starts with :data:`TIPS`."""

    def filter(self, record: logging.LogRecord) -> bool:
        return not str(record.msg).startswith(TIPS)


def quiet_lightning() -> None:
    """Drop Lightning's advertisements and the ``LeafSpec`` deprecation warning (see the module doc); every other line
    of Lightning and torch is left as it is. Idempotent."""
    log = logging.getLogger(RANK_ZERO_LOGGER)
    if not any(isinstance(f, _DropTip) for f in log.filters):
        log.addFilter(_DropTip())
    # any category (torch raises it as a FutureWarning); filterwarnings replaces an identical filter, adds no other
    warnings.filterwarnings("ignore", message=LEAFSPEC)
