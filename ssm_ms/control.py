"""The earlier name of :mod:`ssm_ms.export` (linearisation of ``f`` and ``g`` for control, export to .pt2 /
TorchScript): ``from ssm_ms.control import export, linearize`` and ``python -m ssm_ms.control export ...`` keep
working."""

from ssm_ms.export import FORMATS, export, export_checkpoint, jacobian, linearize, main

__all__ = ["FORMATS", "export", "export_checkpoint", "jacobian", "linearize", "main"]

if __name__ == "__main__":
    main()
