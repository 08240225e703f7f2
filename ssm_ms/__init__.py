"""ssm-ms: neural state-space models learned by multiple shooting.

The Python API (:mod:`ssm_ms.api`, docs/python.md)::

    from ssm_ms import Recordings, SSM, fit

    data = Recordings(y=y, u=u, dt=0.05)
    model = SSM(data, state_dim=8)
    fit(model, data, epochs=300)
    y_sim = model.simulate(u_new, y_init=y_init, u_init=u_init)

The names are imported on first use, so that ``import ssm_ms`` (and the tools that only read results files) does
not pay for torch and Lightning.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from ssm_ms.api import SSM, Recordings, fit

__all__ = ["SSM", "Recordings", "fit"]


def __getattr__(name: str) -> Any:
    if name in __all__:
        from ssm_ms import api

        return getattr(api, name)
    raise AttributeError(f"module 'ssm_ms' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted([*globals(), *__all__])
