"""Zero-copy bridges between torch tensors and Warp arrays for the autograd wrappers.

Torch and Warp share memory on both CPU and CUDA (``wp.from_torch``), so the wrappers hand
kernels views of torch storage instead of copies. Warp names devices as torch does.
"""

from __future__ import annotations

import contextlib

import torch
import warp as wp

from holowarp.device import CPU_PIECES, init_warp, run_chunks, thread_chunks
from holowarp.ops.launches import LaunchCache

__all__ = ["wp_device", "to_wp", "torch_stream", "thread_chunks", "run_chunks", "CPU_PIECES", "StepCache", "FRESH"]

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


class StepCache(LaunchCache):
    """Buffers, Warp views and recorded launches of a step repeated on same-shaped data.

    A geometry step (:class:`holowarp.stages.geometry.GeometryBlock`) launches about twenty
    small kernels, most on arrays that are the same from step to step. A fresh ``wp.launch``
    spends about 15 us packing its arguments and each ``wp.from_torch`` view about 6 us on
    this project's 2-core CPU, longer than many of those kernels run.
    Keyed by call site (a string the caller picks, one per use), a cache hands back:

    - :meth:`buffer`: the same torch tensor while the shape, dtype and device hold;
    - :meth:`view`: the same Warp view while the tensor's storage, shape and strides hold;
    - :meth:`launch` (:class:`holowarp.ops.launches.LaunchCache`): a launch recorded once; a repeat
      re-packs only the arguments that changed, so one whose arrays are all unchanged costs
      about 3 us.

    The buffers are reused: a value one step saves for its backward pass must be consumed
    before the same site runs again (one forward, then its backward, as a training step
    does). :data:`FRESH` has the same methods and makes everything anew on each call, for
    callers without a cache. Launches run on the device's current stream, as ``wp.launch``
    does, so :func:`torch_stream` orders them on CUDA.
    """

    def __init__(self):
        super().__init__()
        self._buffers: dict = {}
        self._views: dict = {}
        self._ahead: dict = {}

    def put_ahead(self, site: str, key, result) -> None:
        """Keep ``result``, work a caller ran ahead for ``site`` (e.g. on another thread),
        computed from inputs that ``key`` identifies
        (:func:`holowarp.ops.tet_energy.prepare_tet_energies`)."""
        self._ahead[site] = (key, result)

    def take_ahead(self, site: str, key):
        """The result :meth:`put_ahead` kept for ``site`` if it came from the inputs ``key``
        identifies, else None; either way the site's entry is gone (a result is taken once)."""
        hit = self._ahead.pop(site, None)
        return hit[1] if hit is not None and hit[0] == key else None

    def buffer(self, site: str, shape, dtype: torch.dtype, device, *, zero: bool = False) -> torch.Tensor:
        """A tensor of ``shape``/``dtype`` on ``device`` owned by ``site`` (zeroed when
        ``zero``, else holding whatever the site left in it)."""
        shape = tuple(int(s) for s in shape)
        t = self._buffers.get(site)
        if t is None or tuple(t.shape) != shape or t.dtype != dtype or t.device != torch.device(device):
            t = self._buffers[site] = _Fresh.buffer(site, shape, dtype, device, zero=zero)
        elif zero:
            t.zero_()
        return t

    def view(self, site: str, t: torch.Tensor, dtype=None) -> wp.array:
        """:func:`to_wp` of ``t``, the same object while ``t``'s storage, shape, strides and
        dtype are those of the last call at ``site``. One view per site is kept, holding its
        tensor: a site that sees a new tensor each step keeps only the latest alive."""
        if not t.is_contiguous():
            t = t.contiguous()
        key = (t.data_ptr(), tuple(t.shape), t.dtype, t.device, dtype)
        hit = self._views.get(site)
        if hit is not None and hit[0] == key:
            return hit[1]
        a = to_wp(t, dtype)
        self._views[site] = (key, a)
        return a


class _Fresh:
    """:class:`StepCache`'s interface without the caching: new buffers, views and launches."""

    @staticmethod
    def buffer(site, shape, dtype, device, *, zero=False):
        return (torch.zeros if zero else torch.empty)(tuple(int(s) for s in shape), dtype=dtype, device=device)

    @staticmethod
    def view(site, t, dtype=None):
        return to_wp(t, dtype)

    @staticmethod
    def launch(site, kernel, dim, inputs=(), outputs=(), device=None):
        wp.launch(kernel, dim=dim, inputs=inputs, outputs=outputs, device=device)

    @staticmethod
    def take_ahead(site, key):
        return None  # nothing is kept, so nothing was run ahead


#: The cache of callers that have none: everything made anew on each call.
FRESH = _Fresh()
