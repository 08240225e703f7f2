"""``ssm_ms.runtime.private``: each private torch / Lightning API ssm-ms relies on answers what it should, so an
upgrade that changes one fails here, by name."""

from __future__ import annotations

import platform
import sys
from pathlib import Path

import pytest
import torch

from ssm_ms.runtime import private
from tests.conftest import rotation_model


def test_built_by_lightning_cli_is_false_from_python_and_true_under_the_cli(monkeypatch):
    import ssm_ms.module as module
    from ssm_ms.cli import main
    from tests.test_cli import CPU

    assert private.built_by_lightning_cli() is False
    model = rotation_model()
    assert "f" not in model.hparams and "g" not in model.hparams  # modules built in Python are not hyperparameters
    seen = []
    monkeypatch.setattr(
        module, "built_by_lightning_cli", lambda: seen.append(private.built_by_lightning_cli()) or seen[-1]
    )
    cli = main(["--config", str(CPU / "pendulum.yaml"), "--data.init_args.n_train", "4"], run=False)
    assert seen == [True]
    assert cli.model.hparams["f"]["class_path"].endswith("LocallyLinearTransition")  # the config, saved


def test_in_functorch_transform_sees_vmap_and_grad_only():
    x = torch.randn(3, 2)
    assert private.in_functorch_transform(x) is False
    inside = []
    torch.func.vmap(lambda row: inside.append(private.in_functorch_transform(row)) or row)(x)
    torch.func.grad(lambda v: inside.append(private.in_functorch_transform(v)) or v.sum())(x)
    assert inside == [True, True]


def test_has_forward_tangent_sees_a_dual_tensor_only():
    import torch.autograd.forward_ad as fwAD

    x = torch.randn(3)
    assert private.has_forward_tangent(x) is False
    with fwAD.dual_level():
        dual = fwAD.make_dual(x, torch.ones(3))
        assert private.has_forward_tangent(dual) is True
        assert private.has_forward_tangent(x) is False


def test_dynamo_supported_here():
    """torch.compile supports CPython 3.10-3.13 on Linux (this project's machines)."""
    expected = platform.system() == "Linux" and (3, 10) <= sys.version_info[:2] <= (3, 13)
    assert private.dynamo_supported() is expected


@pytest.mark.skipif(not Path("/proc/cpuinfo").exists(), reason="reads the CPU's flags from /proc/cpuinfo")
def test_cpu_bf16_native_agrees_with_the_cpu_flags():
    flags = set()
    for line in Path("/proc/cpuinfo").read_text().splitlines():
        if line.startswith("flags"):
            flags.update(line.split(":", 1)[1].split())
    assert private.cpu_bf16_native() is bool({"avx512_bf16", "amx_tile"} & flags)
