"""Every private API of torch and Lightning that ssm-ms relies on, each behind one function here, where no public
one does the job (each function's docstring says which API and why). ``tests/test_private_api.py`` checks each
against what it should answer, so an upgrade of torch or Lightning that changes one fails there, by name, instead of
somewhere downstream; the pinned versions (``torch==2.13.*``, ``lightning<2.7``) are the ones checked.
"""

from __future__ import annotations

import torch


def built_by_lightning_cli() -> bool:
    """Whether a LightningModule is being built by LightningCLI right now, which hands it its configuration as
    hyperparameters (Lightning's context variable ``_given_hyperparameters``; no public equivalent): then ``f`` and
    ``g`` are saved as their config, while a module built in Python must not save them (nn.Module objects)."""
    from lightning.pytorch.core.mixins.hparams_mixin import _given_hyperparameters

    return _given_hyperparameters.get() is not None


def in_functorch_transform(t: torch.Tensor) -> bool:
    """Whether ``t`` is wrapped by a ``torch.func`` transform (vmap, grad, jacrev, ...): custom operators without a
    batching rule must not see it (``torch._C._functorch.is_functorch_wrapped_tensor``; no public equivalent)."""
    return bool(torch._C._functorch.is_functorch_wrapped_tensor(t))


def has_forward_tangent(t: torch.Tensor) -> bool:
    """Whether ``t`` carries a forward-mode AD tangent (``torch.autograd.forward_ad``'s private level counter
    tells cheaply whether any dual level is open; ``unpack_dual`` then says whether ``t`` is dual)."""
    return (
        torch.autograd.forward_ad._current_level >= 0 and torch.autograd.forward_ad.unpack_dual(t).tangent is not None
    )


def dynamo_supported() -> bool:
    """Whether ``torch.compile`` supports this Python and platform (``torch._dynamo.is_dynamo_supported``; the public
    ``torch.compiler`` has no such question: it fails at the first compiled call instead)."""
    import torch._dynamo

    return bool(torch._dynamo.is_dynamo_supported())


def cpu_bf16_native() -> bool:
    """Whether this CPU computes bfloat16 natively (AVX512-BF16 or AMX): ``torch.cpu._is_avx512_bf16_supported`` and
    ``_is_amx_tile_supported``, the checks torch's own kernels dispatch on (the public
    ``torch.backends.cpu.get_cpu_capability`` names the vector width only)."""
    return bool(torch.cpu._is_avx512_bf16_supported() or torch.cpu._is_amx_tile_supported())
