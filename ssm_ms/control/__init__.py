"""Control with a learned model: sampling model-predictive control (:mod:`.mppi`) on ``f(x, u)``, the swing-up
cost (:mod:`.cost`) on angles read from images (:mod:`.goals`), and the closed loop run by ``cli.py test``
(:class:`ClosedLoop`)."""

from ssm_ms.control.module import ClosedLoop
from ssm_ms.control.plant import TruePendulum

__all__ = ["ClosedLoop", "TruePendulum"]
