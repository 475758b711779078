"""Zero-copy bridges between torch tensors and Warp arrays for the autograd wrappers.

Torch and Warp share memory on both CPU and CUDA (``wp.from_torch``), so the wrappers hand
kernels views of torch storage instead of copies. Warp names devices as torch does.
"""

from __future__ import annotations

import contextlib
from concurrent.futures import ThreadPoolExecutor

import torch
import warp as wp

from holowarp.device import cpu_threads, init_warp

__all__ = ["wp_device", "to_wp", "torch_stream", "thread_chunks", "run_chunks"]

_POOL: ThreadPoolExecutor | None = None
_POOL_SIZE = 0

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


def thread_chunks(total: int, device: str, *, align: int = 256, per_thread: int = 4) -> list[tuple[int, int]]:
    """``[(offset, count), ...]`` covering ``range(total)`` in pieces of whole ``align``-thread
    blocks: one piece on CUDA or with one CPU thread, else ``per_thread`` pieces per thread
    (several per thread balance tiles of unequal cost)."""
    n = cpu_threads()
    if device != "cpu" or n == 1 or total <= align:
        return [(0, total)]
    blocks = -(-total // align)
    pieces = min(blocks, n * per_thread)
    edges = [round(blocks * k / pieces) * align for k in range(pieces + 1)]
    edges[-1] = total
    return [(a, b - a) for a, b in zip(edges[:-1], edges[1:]) if b > a]


def run_chunks(fn, chunks, *, kernel=None, device: str = "cpu") -> list:
    """``[fn(offset, count) for each chunk]``, run on the CPU thread pool when there are
    several (Warp releases the GIL while a CPU kernel runs); results in chunk order.
    ``kernel``'s module is loaded first, so no two threads ever compile or load it."""
    global _POOL, _POOL_SIZE
    if len(chunks) == 1:
        return [fn(*chunks[0])]
    if kernel is not None:
        kernel.module.load(wp.get_device(device))
    n = cpu_threads()
    if _POOL is None or _POOL_SIZE != n:
        if _POOL is not None:
            _POOL.shutdown(wait=True)
        _POOL, _POOL_SIZE = ThreadPoolExecutor(max_workers=n, thread_name_prefix="holowarp-kernel"), n
    return [f.result() for f in [_POOL.submit(fn, *c) for c in chunks]]
