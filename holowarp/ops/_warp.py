"""Zero-copy bridges between torch tensors and Warp arrays for the autograd wrappers.

Torch and Warp share memory on both CPU and CUDA (``wp.from_torch``), so the wrappers hand
kernels views of torch storage instead of copies. Warp names devices as torch does.
"""

from __future__ import annotations

import contextlib

import torch
import warp as wp

from holowarp.device import CPU_PIECES, init_warp, run_chunks, thread_chunks

__all__ = ["wp_device", "to_wp", "torch_stream", "thread_chunks", "run_chunks", "CPU_PIECES"]

init_warp()


def wp_device(t: torch.Tensor) -> str:
    """Warp device string of a torch tensor (``"cpu"`` or ``"cuda:N"``)."""
    if t.device.type == "cuda":
        return f"cuda:{t.device.index or 0}"
    return "cpu"


def to_wp(t: torch.Tensor, dtype=None) -> wp.array:
    """A Warp view of ``t`` (made contiguous first), optionally as a vector dtype.

    Args:
        t: tensor to share. Its dtype must match ``dtype``'s scalar type.
        dtype: e.g. ``wp.vec3`` to view a (N, 3) float32 tensor as N vec3s.
    """
    t = t.detach()
    if not t.is_contiguous():
        t = t.contiguous()
    return wp.from_torch(t, dtype=dtype, requires_grad=False)


def torch_stream(t: torch.Tensor):
    """Context that runs Warp launches on torch's current CUDA stream of ``t``'s device, so
    they order with torch's work without an extra sync (a no-op on CPU)."""
    if t.device.type == "cuda":
        return wp.ScopedStream(wp.stream_from_torch(t.device))
    return contextlib.nullcontext()

