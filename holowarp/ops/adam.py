"""The vertex optimiser's update in two Warp passes (kernels in ``holowarp.kernels.optim``).

:class:`holowarp.optim.UniformAdam` uses :func:`uniform_adam_rows_` for a group whose one
parameter is an (N, 3) array of positions (the geometry stage's vertices); other shapes take
its torch path. ``tests/test_optim.py`` checks both against a NumPy transcription of the
documented update.
"""

from __future__ import annotations

import torch
import warp as wp

from holowarp.kernels import optim as K_
from holowarp.ops._warp import FRESH, torch_stream, wp_device

__all__ = ["uniform_adam_rows_", "rows_supported"]

_TYPES = {torch.float32: (wp.float32, wp.vec3f), torch.float64: (wp.float64, wp.vec3d)}


def rows_supported(p: torch.Tensor) -> bool:
    """Whether :func:`uniform_adam_rows_` takes ``p``: (N, 3), float32 or float64, contiguous,
    with a dense gradient of its own layout."""
    g = p.grad
    return (p.ndim == 2 and p.shape[1] == 3 and p.dtype in _TYPES and p.is_contiguous() and g is not None
            and not g.is_sparse and g.dtype == p.dtype and g.shape == p.shape)


def uniform_adam_rows_(p: torch.Tensor, m: torch.Tensor, v: torch.Tensor, t: int, *, lr: float, betas, eps: float,
                       max_step: float | None, cache=FRESH) -> None:
    """One UniformAdam step of the (N, 3) rows ``p`` in place (its ``.grad`` the gradient),
    ``m`` and ``v`` (N, 3) its moments (updated in place), ``t`` the step's number from 1:
    ``p -= lr m_hat / (max sqrt(v_hat) + eps)``, each row's move capped at ``max_step``
    (``None``: no cap). ``cache``: a :class:`holowarp.ops._warp.StepCache` of a caller that
    steps the same tensors again and again."""
    T, V = _TYPES[p.dtype]
    b1, b2 = (float(b) for b in betas)
    dev, c = wp_device(p), cache
    n = p.shape[0]
    grad = p.grad.contiguous()
    v_max = c.buffer("adam.v_max", (1,), p.dtype, p.device, zero=True)
    vmax_wp = c.view("adam.v_max", v_max)
    m_wp, x_wp = c.view("adam.m", m, V), c.view("adam.x", p.detach(), V)
    with torch_stream(p):
        c.launch("adam.moments", K_.uniform_adam_moments_kernel, n,
                 [c.view("adam.grad", grad, V), T(b1), T(b2)], [m_wp, c.view("adam.v", v, V), vmax_wp], dev)
        cap = -1.0 if max_step is None else float(max_step)
        c.launch("adam.apply", K_.uniform_adam_apply_kernel, n,
                 [m_wp, vmax_wp, T(1.0 - b1**t), T(1.0 - b2**t), T(float(lr)), T(float(eps)), T(cap)], [x_wp], dev)
