"""Native CPU kernels for the ConvDecoder: ``build`` compiles and loads them (ctypes), ``ops`` wraps them as a torch
autograd function. The decoder picks them through its ``backend`` argument (:class:`ssm_ms.nets.ConvDecoder`)."""

from ssm_ms.nets.native.build import cache_dir, library, threads, unavailable_reason
from ssm_ms.nets.native.ops import NATIVE_SCRATCH, applies, conv_stack

__all__ = ["NATIVE_SCRATCH", "applies", "cache_dir", "conv_stack", "library", "threads", "unavailable_reason"]
