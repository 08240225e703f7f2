"""Opt-in speed paths: the compiled rollout against a plain loop, bf16-mixed against float32, and their errors."""

import shutil

import pytest
import torch

from ssm_ms.module import MultipleShootingModule
from ssm_ms.nets import ConvDecoder, LocallyLinearTransition, Projection
from ssm_ms.runtime import perf
from ssm_ms.training.shooting import (
    CompiledRollout,
    compile_unavailable_reason,
    multiple_shooting_loss,
    shooting_residuals,
)
from tests.conftest import fast_trainer, rotation_model

NATIVE_BF16 = perf.bf16_support("cpu")[0]
BF16_RTOL = 1e-2  # the README's stated tolerance of bf16-mixed against float32 (measured: ~2e-4)


@pytest.mark.slow  # inductor's C++ build is ~40 s of make test's 10 minutes on the slowest CPUs; make test-slow runs it
@pytest.mark.skipif(compile_unavailable_reason("default") is not None, reason="torch.compile unavailable here")
def test_compiled_rollout_matches_a_plain_loop_with_gradients():
    torch.manual_seed(0)
    f = LocallyLinearTransition(3, n_matrices=4, hidden=16).double()
    x0 = torch.randn(5, 3, dtype=torch.float64, requires_grad=True)
    states = CompiledRollout(f)(x0, 4)  # inductor (C++ on CPU): one graph for the 3 calls of f
    xs = [x0]
    for _ in range(3):
        xs.append(f(xs[-1]))
    loop = torch.stack(xs, 1)
    torch.testing.assert_close(states, loop)
    weight = torch.randn_like(loop)
    got = torch.autograd.grad((states * weight).sum(), [x0, *f.parameters()])
    want = torch.autograd.grad((loop * weight).sum(), [x0, *f.parameters()])
    for a, b in zip(got, want):
        torch.testing.assert_close(a, b)


def test_compile_rollout_bad_mode_and_missing_compiler(monkeypatch):
    with pytest.raises(ValueError, match="unknown torch.compile mode 'fastest'"):
        rotation_model(compile_rollout="fastest")
    monkeypatch.setattr(shutil, "which", lambda name: None)
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    with pytest.raises(ValueError, match="needs a C\\+\\+ compiler .* use the eager rollout"):
        rotation_model(compile_rollout="default")


@pytest.mark.skipif(not NATIVE_BF16, reason="this CPU has no native bfloat16")
def test_bf16_mixed_loss_is_within_the_stated_tolerance_of_float32():
    torch.manual_seed(0)
    f, g = LocallyLinearTransition(10, 32, 1024), ConvDecoder(10, "pendulum")
    nodes = torch.randn(3, 4, 10)
    y = torch.rand(3, 4 * 25, 1, 24, 24).round()
    fit32, gap32 = multiple_shooting_loss(f, g, nodes, y)
    with torch.autocast("cpu", dtype=torch.bfloat16):  # what trainer.precision: bf16-mixed does
        fit16, gap16 = multiple_shooting_loss(f, g, nodes, y)
    assert fit16.dtype == gap16.dtype == torch.float32  # the losses themselves are reduced in float32
    assert abs(fit16.item() - fit32.item()) <= BF16_RTOL * fit32.item()
    assert abs(gap16.item() - gap32.item()) <= BF16_RTOL * gap32.item()
    assert fit16.item() != fit32.item()  # bfloat16 really ran
    grads = torch.autograd.grad(fit16 + gap16, [*f.parameters(), *g.parameters()])  # as Lightning: outside autocast
    assert all(gr.dtype == torch.float32 and torch.isfinite(gr).all() for gr in grads)


@pytest.mark.skipif(not NATIVE_BF16, reason="this CPU has no native bfloat16")
def test_bf16_mixed_trains_through_lightning(tmp_path, rotation_dm):
    model = rotation_model()
    fast_trainer(tmp_path, max_epochs=1, precision="bf16-mixed").fit(model, datamodule=rotation_dm)
    assert torch.isfinite(model.nodes.weight).all() and model.nodes.weight.abs().sum() > 0


def test_bf16_refused_where_the_cpu_lacks_it(tmp_path, rotation_dm, monkeypatch):
    monkeypatch.setattr(torch.cpu, "_is_avx512_bf16_supported", lambda: False)
    monkeypatch.setattr(torch.cpu, "_is_amx_tile_supported", lambda: False)
    with pytest.raises(ValueError, match="no native bfloat16 instructions.*use trainer.precision: 32"):
        fast_trainer(tmp_path, max_epochs=1, precision="bf16-mixed").fit(rotation_model(), datamodule=rotation_dm)
    perf.check_precision("32-true", "cpu")  # float32 is always fine


def test_module_rollout_uses_the_compiled_function_when_asked():
    """The module routes its rollouts through CompiledRollout (here checked without compiling: the
    object is replaced by a counting wrapper of the eager rollout)."""
    model = MultipleShootingModule(
        LocallyLinearTransition(2, 4, 8), Projection([0]), state_dim=2, num_trajectories=3, n_nodes=2
    )
    calls = []

    def counting(x0, steps, u=None):
        calls.append(steps)
        xs = [x0]
        for _ in range(steps - 1):
            xs.append(model.f(xs[-1]))
        return torch.stack(xs, 1)

    plain = model.shooting_loss({"index": torch.arange(3), "y": torch.randn(3, 6, 1)})
    model._rollout_fn = counting
    routed = model.shooting_loss({"index": torch.arange(3), "y": torch.randn(3, 6, 1)})
    model(torch.zeros(2, 2), 5)
    assert calls == [4, 5]
    assert plain[1].item() == routed[1].item()  # same nodes, same f: same gap
    # the augmented Lagrangian's gaps come from the same rollout
    calls.clear()
    nodes, y = torch.randn(3, 3, 2), torch.randn(3, 6, 1)
    fit, residual = shooting_residuals(model.f, model.g, nodes, y, rollout_fn=counting)
    assert calls == [3]
    naive = torch.stack([nodes[:, i + 1] - model.f(model.f(nodes[:, i])) for i in range(2)], dim=1)
    torch.testing.assert_close(residual, naive)
