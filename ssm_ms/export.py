"""The learned ``f`` and ``g`` for control: local linear models, and files that run without ssm-ms.

- :func:`linearize` (from :mod:`ssm_ms.analysis`, the one implementation): ``A = df/dx [N, d, d]``,
  ``B = df/du [N, d, m]`` for a system driven by inputs, and ``C = dg/dx`` (``[N, p, d]`` flattened, or
  ``[N, *obs_shape, d]``) at a batch of states (and inputs), e.g. for LQR or MPC around an operating point or the
  prediction and update of an extended Kalman filter; :func:`jacobian` for one function.
- :func:`export` writes ``f`` and ``g`` to self-contained files that need only ``torch``:

  * ``f.pt2``, ``g.pt2``: ``torch.export`` programs, batch size free; ``f`` takes ``(x, u)`` where it is driven by
    inputs (``model.json``'s ``input_dim`` > 0). Load with ``torch.export.load("f.pt2").module()``; compile for C++
    with AOTInductor if needed.
  * ``f.torchscript.pt``, ``g.torchscript.pt``: TorchScript (traced), loadable from Python with
    ``torch.jit.load`` and from C++ with libtorch's ``torch::jit::load``. TorchScript is deprecated in
    torch 2.13 but still loads; prefer ``.pt2``.
  * ONNX is not written: neither ``onnx`` nor ``onnxscript`` is among the project's dependencies (torch's
    exporter needs them). Where they are installed, ``torch.onnx.export(torch.export.load("f.pt2").module(), ...)``
    converts the ``.pt2`` program.

  Each exported file is checked against the module on a batch of another size before :func:`export`
  returns. ``model.json`` beside them says what the files are: ``state_dim``, ``obs_shape`` and, from a
  checkpoint (:func:`export_checkpoint`: ``f`` and ``g`` in the data's own units, the normalisation inside them),
  the normalisation statistics built in.

From the command line (a trained SSM's checkpoint)::

    python -m ssm_ms.export export runs/oscillator/version_0/checkpoints/last.ckpt --out exported/oscillator
"""

from __future__ import annotations

import argparse
import copy
import json
import sys
import warnings
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import torch
from torch import nn

from ssm_ms.analysis import Linearization, jacobian, linearize
from ssm_ms.nets import ConvDecoder

__all__ = ["FORMATS", "Linearization", "export", "export_checkpoint", "jacobian", "linearize", "main"]

FORMATS = ("pt2", "torchscript")
SUFFIX = {"pt2": ".pt2", "torchscript": ".torchscript.pt"}


def _standalone_copy(module: nn.Module) -> nn.Module:
    """An eval-mode copy in plain torch operations: every :class:`~ssm_ms.nets.ConvDecoder` in it runs its ``"plain"``
    backend (torch's own layers: its native kernels and channels-last path are CPU training speed that tracing
    cannot follow; same function, same parameters), and parameters and buffers are made contiguous (a channels-last
    weight makes ``torch.export.load`` warn)."""
    copy_ = copy.deepcopy(module).eval()
    for sub in copy_.modules():
        if isinstance(sub, ConvDecoder):
            sub.backend = "plain"
    with torch.no_grad():
        for tensor in list(copy_.parameters()) + list(copy_.buffers()):
            tensor.data = tensor.data.contiguous()
    for p in copy_.parameters():
        p.requires_grad_(False)
    return copy_


def _export_one(
    module: nn.Module, example: tuple[torch.Tensor, ...], fmt: str, path: Path
) -> Callable[..., torch.Tensor]:
    """Write ``module`` (called on the tensors ``example``, batch first) in format ``fmt`` to ``path``; return the
    reloaded callable (for the check)."""
    if fmt == "pt2":
        batch = torch.export.Dim("batch", min=1)
        program = torch.export.export(module, example, dynamic_shapes=tuple({0: batch} for _ in example))
        torch.export.save(program, path)
        return torch.export.load(path).module()
    with warnings.catch_warnings():  # deprecation of TorchScript; shape checks traced as constants (shapes are fixed)
        warnings.simplefilter("ignore")
        traced = torch.jit.trace(module, example, check_trace=False)
        torch.jit.save(traced, str(path))
        return torch.jit.load(str(path))


def export(
    f: nn.Module,
    g: nn.Module,
    state_dim: int,
    out_dir: str | Path,
    formats: Sequence[str] = FORMATS,
    metadata: dict[str, Any] | None = None,
    rtol: float = 1e-5,
    atol: float = 1e-6,
) -> dict[str, Path]:
    """Write ``f`` (``[N, d] -> [N, d]``, or ``([N, d], [N, m]) -> [N, d]`` where ``f.input_dim = m > 0``) and ``g``
    (``[N, d] -> [N, *obs_shape]``) to ``out_dir``.

    Args:
        f, g: the SSM's networks (any ``nn.Module`` with those shapes; ``model.f``, ``model.g``).
        state_dim: ``d``.
        out_dir: created if missing; existing files of the same names are replaced.
        formats: among ``"pt2"`` (``torch.export``) and ``"torchscript"``.
        metadata: written into ``model.json`` beside ``state_dim``, ``obs_shape`` and the file names.
        rtol, atol: each reloaded file must reproduce the module on a fresh batch of states this closely
            (else ``RuntimeError``: the network does something the format cannot capture).

    Returns:
        ``{"f.pt2": path, "g.pt2": path, ..., "model.json": path}``.
    """
    unknown = [fmt for fmt in formats if fmt not in FORMATS]
    if unknown or not formats:
        raise ValueError(f"export formats must be among {list(FORMATS)} (ONNX: see ssm_ms.export), got {list(formats)}")
    if int(state_dim) != state_dim or state_dim < 1:
        raise ValueError(f"state_dim must be a positive integer, got {state_dim!r}")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    dtype = next(iter(f.parameters()), torch.zeros(())).dtype
    generator = torch.Generator().manual_seed(0)
    m = int(getattr(f, "input_dim", 0))
    example = torch.randn(2, state_dim, generator=generator, dtype=dtype)
    check = torch.randn(5, state_dim, generator=generator, dtype=dtype)  # another batch size than the example
    inputs = {
        "f": (
            (example, torch.randn(2, m, generator=generator, dtype=dtype)),
            (check, torch.randn(5, m, generator=generator, dtype=dtype)),
        )
        if m
        else ((example,), (check,)),
        "g": ((example,), (check,)),
    }
    written: dict[str, Path] = {}
    obs_shape = None
    for name, module in (("f", f), ("g", g)):
        module = _standalone_copy(module)
        examples, checks = inputs[name]
        with torch.no_grad():
            expected = module(*checks)
        if name == "g":
            obs_shape = list(expected.shape[1:])
        for fmt in formats:
            path = out / f"{name}{SUFFIX[fmt]}"
            loaded = _export_one(module, examples, fmt, path)
            with torch.no_grad():
                got = loaded(*checks)
            if got.shape != expected.shape or not torch.allclose(got, expected, rtol=rtol, atol=atol):
                raise RuntimeError(
                    f"the {fmt} export of {name} ({type(module).__name__}) does not reproduce the module"
                )
            written[path.name] = path
    info = {
        "state_dim": int(state_dim),
        "input_dim": m,
        "obs_shape": obs_shape,
        "dtype": str(dtype).removeprefix("torch."),
        "files": sorted(written),
        "load": {"pt2": "torch.export.load('f.pt2').module()", "torchscript": "torch.jit.load('f.torchscript.pt')"},
        "torch": torch.__version__,
        **(metadata or {}),
    }
    (out / "model.json").write_text(json.dumps(info, indent=2) + "\n")
    written["model.json"] = out / "model.json"
    return written


def export_checkpoint(checkpoint: str | Path, out_dir: str | Path, formats: Sequence[str] = FORMATS) -> dict[str, Path]:
    """:func:`export` the ``f`` and ``g`` of a trained ``MultipleShootingModule`` checkpoint in the data's own units
    (:meth:`~ssm_ms.module.MultipleShootingModule.in_units`): the exported ``f`` takes the inputs and ``g`` returns the
    measurements as the training files held them, the normalisation built in. ``model.json`` records it
    (``normalization``: ``mean``, ``std`` of the measurements, ``input_normalization`` of the inputs; ``null`` where
    the data were not normalised)."""
    from ssm_ms.loading import load_ssm

    model, _ = load_ssm(checkpoint)  # a missing, truncated or foreign file: ValueError / OSError naming it
    data = model.data_state or {}

    def statistics(key: str, applies_to: str) -> dict[str, Any] | None:
        norm = data.get(key)
        if norm is None or (bool((norm["mean"] == 0).all()) and bool((norm["std"] == 1).all())):
            return None
        return {"mean": norm["mean"].tolist(), "std": norm["std"].tolist(), "applies_to": applies_to}

    metadata = {
        "checkpoint": str(checkpoint),
        "f_class": type(model.f).__name__,
        "g_class": type(model.g).__name__,
        "units": "the data's own: inputs into f and measurements out of g as the training files held them",
        "normalization": statistics("normalizer", "inside g: g(x) = g_normalised(x) * std + mean per channel"),
        "input_normalization": statistics("input_normalizer", "inside f: f(x, u) = f_normalised(x, (u - mean) / std)"),
    }
    f, g = model.in_units()
    return export(f, g, model.state_dim, out_dir, formats, metadata)


def main(argv: list[str] | None = None) -> int:
    """``python -m ssm_ms.export export CKPT --out DIR [--format pt2 torchscript]``."""
    parser = argparse.ArgumentParser(
        prog="python -m ssm_ms.export",
        description="Export the learned f and g of an SSM checkpoint to files that run with torch alone.",
    )
    sub = parser.add_subparsers(dest="command", required=True)
    exp = sub.add_parser("export", help="write f and g as torch.export (.pt2) and TorchScript files, and model.json")
    exp.add_argument("checkpoint", help="the last.ckpt of an SSM run (python cli.py fit --config ...)")
    exp.add_argument("--out", required=True, help="output folder (created)")
    exp.add_argument(
        "--format",
        nargs="+",
        default=list(FORMATS),
        choices=FORMATS,
        dest="formats",
        help="formats to write (default: both)",
    )
    args = parser.parse_args(argv)
    try:
        written = export_checkpoint(args.checkpoint, args.out, args.formats)
    except (ValueError, OSError) as err:  # a user's mistake: one message, no traceback
        print(f"error: {err}", file=sys.stderr)
        return 1
    print(f"wrote {', '.join(sorted(written))} to {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
