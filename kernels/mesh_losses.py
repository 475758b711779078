"""Warp kernels of the mesh blocks' per-view image losses (method.md §6), fused.

A geometry step compares the triangle rasteriser's ``alpha`` (H, W) and ``normal``
(H, W, 3) with three images of the drawn view; in torch that was about twenty small
elementwise ops forward and as many backward, each a full pass over the image. Here it is
one pass forward and one backward (driven by ``holowarp.ops.mesh_losses``):

- ``L_mask = mean |alpha - mask|`` over all H W pixels;
- ``L_norm = sum_sel (1 - <n, r>) / max(#sel, 1)``, ``sel``: ``alpha > 0`` and the frozen
  surfels' coverage ``ref_alpha > 0.5``; ``r`` the surfels' unit normals;
- ``L_prior = sum_sel' (1 - <p, n> / max(|p| |n|, 1e-12)) / max(#sel', 1)``, ``sel'``:
  ``alpha > 0.5`` and ``|p| > 0.5`` (the normal map ``p`` holds a normal there).

The selections are masks, not weights: no gradient flows through them. The surfel images
are read in float16 (the block's per-view cache keeps them so).

Pixels are visited row by row: each thread of ``view_loss_rows_kernel`` owns one image row
and writes that row's five partial sums, so the forward has no atomics and sums in the same
order on any device; ``view_loss_total_kernel`` adds the rows. float32 only, like the
rasteriser whose outputs these read. No torch import here (style.md).
"""

from __future__ import annotations

import warp as wp

__all__ = ["view_loss_rows_kernel", "view_loss_total_kernel", "view_loss_backward_kernel"]

#: Floor of ``|p| |n|`` in the prior's cosine (as ``holowarp.losses.prior_error``).
COS_EPS = 1.0e-12


@wp.func
def _prior_cos_grad(p: wp.vec3, n: wp.vec3):
    # d/dn of <p, n> / max(|p| |n|, eps): the clamp has no gradient below eps, and the norm
    # of a zero vector none at all (as torch's norm backward).
    ln = wp.length(n)
    d = wp.length(p) * ln
    if d > COS_EPS:
        return p / d - n * (wp.dot(p, n) / (d * ln * ln))
    return p / COS_EPS


@wp.kernel(enable_backward=False)
def view_loss_rows_kernel(
    alpha: wp.array(dtype=float),  # [H W] mesh silhouette
    normal: wp.array(dtype=wp.vec3),  # [H W] mesh normals (unit, zero off the faces)
    mask: wp.array(dtype=float),  # [H W] target mask
    ref_normal: wp.array(dtype=wp.vec3h),  # [H W] frozen surfels' unit normals
    ref_alpha: wp.array(dtype=wp.float16),  # [H W] frozen surfels' coverage
    prior: wp.array(dtype=wp.vec3),  # [H W] normal map, or [1] when has_prior is 0
    has_prior: int,
    width: int,
    rows: wp.array2d(dtype=float),  # [H, 5] out: sum |a-m|, sum 1-<n,r>, #sel, sum prior err, #sel'
):
    y = wp.tid()
    s_mask = float(0.0)
    s_norm = float(0.0)
    c_norm = float(0.0)
    s_prior = float(0.0)
    c_prior = float(0.0)
    for x in range(width):
        i = y * width + x
        a = alpha[i]
        s_mask += wp.abs(a - mask[i])
        n = normal[i]
        if a > 0.0 and float(ref_alpha[i]) > 0.5:
            r = ref_normal[i]
            s_norm += 1.0 - (n[0] * float(r[0]) + n[1] * float(r[1]) + n[2] * float(r[2]))
            c_norm += 1.0
        if has_prior != 0 and a > 0.5:
            p = prior[i]
            lp = wp.length(p)
            if lp > 0.5:
                s_prior += 1.0 - wp.dot(p, n) / wp.max(lp * wp.length(n), COS_EPS)
                c_prior += 1.0
    rows[y, 0] = s_mask
    rows[y, 1] = s_norm
    rows[y, 2] = c_norm
    rows[y, 3] = s_prior
    rows[y, 4] = c_prior


@wp.kernel(enable_backward=False)
def view_loss_total_kernel(
    rows: wp.array2d(dtype=float),  # [H, 5] from view_loss_rows_kernel
    num_pixels: int,
    losses: wp.array(dtype=float),  # [3] out: L_mask, L_norm, L_prior
    scales: wp.array(dtype=float),  # [3] out: 1 / (H W), 1 / max(#sel, 1), 1 / max(#sel', 1)
):
    s_mask = float(0.0)
    s_norm = float(0.0)
    c_norm = float(0.0)
    s_prior = float(0.0)
    c_prior = float(0.0)
    for y in range(rows.shape[0]):
        s_mask += rows[y, 0]
        s_norm += rows[y, 1]
        c_norm += rows[y, 2]
        s_prior += rows[y, 3]
        c_prior += rows[y, 4]
    k_mask = 1.0 / float(num_pixels)
    k_norm = 1.0 / wp.max(c_norm, 1.0)
    k_prior = 1.0 / wp.max(c_prior, 1.0)
    scales[0] = k_mask
    scales[1] = k_norm
    scales[2] = k_prior
    losses[0] = s_mask * k_mask
    losses[1] = s_norm * k_norm
    losses[2] = s_prior * k_prior


@wp.kernel(enable_backward=False)
def view_loss_backward_kernel(
    alpha: wp.array(dtype=float),  # [H W]
    normal: wp.array(dtype=wp.vec3),  # [H W]
    mask: wp.array(dtype=float),  # [H W]
    ref_normal: wp.array(dtype=wp.vec3h),  # [H W]
    ref_alpha: wp.array(dtype=wp.float16),  # [H W]
    prior: wp.array(dtype=wp.vec3),  # [H W] or [1]
    has_prior: int,
    scales: wp.array(dtype=float),  # [3] from view_loss_total_kernel
    grad_losses: wp.array(dtype=float),  # [3] dLoss / d(L_mask, L_norm, L_prior)
    grad_alpha: wp.array(dtype=float),  # [H W] out
    grad_normal: wp.array(dtype=wp.vec3),  # [H W] out
):
    i = wp.tid()
    a = alpha[i]
    diff = a - mask[i]
    g = float(0.0)
    if diff > 0.0:
        g = grad_losses[0] * scales[0]
    elif diff < 0.0:
        g = -grad_losses[0] * scales[0]
    grad_alpha[i] = g
    gn = wp.vec3(0.0)
    if a > 0.0 and float(ref_alpha[i]) > 0.5:
        r = ref_normal[i]
        gn = gn - wp.vec3(float(r[0]), float(r[1]), float(r[2])) * (grad_losses[1] * scales[1])
    if has_prior != 0 and a > 0.5:
        p = prior[i]
        if wp.length(p) > 0.5:
            gn = gn - _prior_cos_grad(p, normal[i]) * (grad_losses[2] * scales[2])
    grad_normal[i] = gn
