"""Warp kernels of the vertex optimiser's step (:class:`holowarp.optim.UniformAdam`, method.md §6).

A geometry step moves every tet vertex once; in torch the update was about a dozen small
elementwise ops over the (N, 3) positions, each a pass and a dispatch, which cost more than
the arithmetic (issue 17). Here it is two passes, driven by ``holowarp.ops.adam``:

- ``uniform_adam_moments_kernel``: Adam's moments ``m = b1 m + (1 - b1) g`` and
  ``v = b2 v + (1 - b2) g * g`` per element, and the largest ``v`` of all (``atomic_max``:
  the order does not change a maximum, so the result is the same on any device);
- ``uniform_adam_apply_kernel``: ``x -= lr (m / bc1) / (sqrt(v_max / bc2) + eps)`` with the
  bias corrections ``bc1 = 1 - b1^t``, ``bc2 = 1 - b2^t``, each row's displacement scaled
  down to length ``cap`` when longer (``cap <= 0``: no cap).

Generic over float32 and float64 (``vec3f`` / ``vec3d`` rows). No torch import here (style.md).
"""

from __future__ import annotations

from typing import Any

import warp as wp

__all__ = ["uniform_adam_moments_kernel", "uniform_adam_apply_kernel"]


@wp.kernel(enable_backward=False)
def uniform_adam_moments_kernel(
    grad: wp.array(dtype=Any),  # [N] vec3 gradient
    b1: Any,
    b2: Any,
    m: wp.array(dtype=Any),  # [N] vec3 first moment, updated in place
    v: wp.array(dtype=Any),  # [N] vec3 second moment, updated in place
    v_max: wp.array(dtype=Any),  # [1] max over every element of v (zeroed by the caller)
):
    i = wp.tid()
    g = grad[i]
    one = type(b1)(1.0)
    mi = m[i] * b1 + g * (one - b1)
    vi = v[i] * b2 + wp.cw_mul(g, g) * (one - b2)
    m[i] = mi
    v[i] = vi
    wp.atomic_max(v_max, 0, wp.max(vi))


@wp.kernel(enable_backward=False)
def uniform_adam_apply_kernel(
    m: wp.array(dtype=Any),  # [N] vec3 first moment
    v_max: wp.array(dtype=Any),  # [1] max of the second moment
    bc1: Any,  # 1 - b1^t
    bc2: Any,  # 1 - b2^t
    lr: Any,
    eps: Any,
    cap: Any,  # largest row displacement; <= 0 for none
    x: wp.array(dtype=Any),  # [N] vec3 parameter, updated in place
):
    i = wp.tid()
    denom = wp.sqrt(v_max[0] / bc2) + eps
    upd = (m[i] / bc1) * (lr / denom)
    zero = type(cap)(0.0)
    if cap > zero:
        n = wp.length(upd)
        if n > cap:
            upd = upd * (cap / n)
    x[i] = x[i] - upd


def _register_overloads():
    for T, V in ((wp.float32, wp.vec3f), (wp.float64, wp.vec3d)):
        aV, aT = wp.array(dtype=V), wp.array(dtype=T)
        wp.overload(uniform_adam_moments_kernel, [aV, T, T, aV, aV, aT])
        wp.overload(uniform_adam_apply_kernel, [aV, aT, T, T, T, T, T, aV])


_register_overloads()
