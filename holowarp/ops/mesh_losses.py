"""The mesh blocks' per-view image losses as one autograd op (method.md §6).

:func:`mesh_view_losses` computes, in one Warp pass forward and one backward (kernels in
``holowarp.kernels.mesh_losses``), what the geometry step compared in about twenty torch
ops: the silhouette L1 loss, the normal agreement with the frozen surfels and the
normal-map prior. ``tests/test_mesh_losses.py`` checks values and gradients against the
torch expressions they replace.
"""

from __future__ import annotations

import torch
import warp as wp

from holowarp.kernels import mesh_losses as K_
from holowarp.ops._warp import FRESH, to_wp, torch_stream, wp_device

__all__ = ["mesh_view_losses"]


def _inputs(alpha, normal, mask, ref_normal, ref_alpha, prior, c):
    has = prior is not None
    p = prior if has else c.buffer("vl.no_prior", (1, 3), torch.float32, alpha.device, zero=True)
    return [c.view("vl.alpha", alpha.reshape(-1)), c.view("vl.normal", normal.reshape(-1, 3), wp.vec3),
            c.view("vl.mask", mask.reshape(-1)), c.view("vl.ref_normal", ref_normal.reshape(-1, 3), wp.vec3h),
            c.view("vl.ref_alpha", ref_alpha.reshape(-1)), c.view("vl.prior", p.reshape(-1, 3), wp.vec3), int(has)]


class _MeshViewLosses(torch.autograd.Function):
    @staticmethod
    def forward(ctx, alpha, normal, mask, ref_normal, ref_alpha, prior, cache):
        H, W = alpha.shape
        dev, c = wp_device(alpha), cache
        rows = c.buffer("vl.rows", (H, 5), torch.float32, alpha.device)
        losses = c.buffer("vl.losses", (3,), torch.float32, alpha.device)
        scales = c.buffer("vl.scales", (3,), torch.float32, alpha.device)
        ins = _inputs(alpha, normal, mask, ref_normal, ref_alpha, prior, c)
        rows_wp = c.view("vl.rows", rows)
        with torch_stream(alpha):
            c.launch("vl.rows", K_.view_loss_rows_kernel, H, [*ins, W], [rows_wp], dev)
            c.launch("vl.total", K_.view_loss_total_kernel, 1, [rows_wp, H * W],
                     [c.view("vl.losses", losses), c.view("vl.scales", scales)], dev)
        ctx.save_for_backward(alpha, normal, scales)
        ctx.ins = ins  # the Warp views of the inputs, reused by the backward pass
        ctx.cache = c
        return losses.clone()  # the buffer is the site's again at the next step

    @staticmethod
    def backward(ctx, g_losses):
        alpha, normal, scales = ctx.saved_tensors
        c = ctx.cache
        g_alpha = torch.empty_like(alpha)
        g_normal = torch.empty_like(normal)
        g = c.buffer("vl.g_losses", (3,), torch.float32, alpha.device).copy_(g_losses)
        with torch_stream(alpha):
            c.launch("vl.backward", K_.view_loss_backward_kernel, alpha.numel(),
                     [*ctx.ins, c.view("vl.scales", scales), c.view("vl.g_losses", g)],
                     [to_wp(g_alpha.view(-1)), to_wp(g_normal.view(-1, 3), wp.vec3)], wp_device(alpha))
        return g_alpha, g_normal, None, None, None, None, None


def mesh_view_losses(alpha: torch.Tensor, normal: torch.Tensor, mask: torch.Tensor, ref_normal: torch.Tensor,
                     ref_alpha: torch.Tensor, prior: torch.Tensor | None = None, *, cache=FRESH) -> torch.Tensor:
    """``(L_mask, L_norm, L_prior)`` of one view as a (3,) float32 tensor, differentiable in
    ``alpha`` and ``normal``.

    Args:
        alpha: (H, W) float32 mesh silhouette; ``normal``: (H, W, 3) float32 mesh normals
            (:func:`holowarp.ops.rasterize_mesh`'s outputs).
        mask: (H, W) float32 target mask of the view.
        ref_normal: (H, W, 3) float16 unit normals of the frozen surfels; ``ref_alpha``:
            (H, W) float16 their coverage.
        prior: (H, W, 3) float32 normal map of the view, zero where it holds no normal, or
            None (then ``L_prior`` is 0).
        cache: a :class:`holowarp.ops._warp.StepCache` for a caller that repeats this on
            same-shaped images (the geometry step); run the backward before the next call.

    Returns:
        ``L_mask = mean |alpha - mask|``; ``L_norm``: mean ``1 - <normal, ref_normal>`` over
        the pixels with ``alpha > 0`` and ``ref_alpha > 0.5``; ``L_prior``: mean
        ``1 - cos(prior, normal)`` over the pixels with ``alpha > 0.5`` where the prior is
        longer than 0.5 (as :func:`holowarp.losses.covered_prior_loss`). A selection with no
        pixel gives 0.
    """
    if not isinstance(alpha, torch.Tensor) or alpha.ndim != 2:
        raise ValueError(f"mesh_view_losses: alpha must be an (H, W) float32 tensor, got {getattr(alpha, 'shape', type(alpha))}")
    H, W = alpha.shape
    want = {"alpha": (alpha, (H, W), torch.float32), "normal": (normal, (H, W, 3), torch.float32),
            "mask": (mask, (H, W), torch.float32), "ref_normal": (ref_normal, (H, W, 3), torch.float16),
            "ref_alpha": (ref_alpha, (H, W), torch.float16)}
    if prior is not None:
        want["prior"] = (prior, (H, W, 3), torch.float32)
    for name, (t, shape, dtype) in want.items():
        if not isinstance(t, torch.Tensor) or tuple(t.shape) != shape or t.dtype != dtype or t.device != alpha.device:
            raise ValueError(f"mesh_view_losses: {name} must be a {dtype} tensor of shape {shape} on {alpha.device}, "
                             f"got {getattr(t, 'dtype', type(t))} {tuple(getattr(t, 'shape', ()))}")
    return _MeshViewLosses.apply(alpha.contiguous(), normal.contiguous(), mask.contiguous(), ref_normal.contiguous(),
                                 ref_alpha.contiguous(), None if prior is None else prior.contiguous(), cache)
