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
from holowarp.ops._warp import to_wp, torch_stream, wp_device

__all__ = ["mesh_view_losses"]


def _inputs(alpha, normal, mask, ref_normal, ref_alpha, prior):
    has = prior is not None
    p = prior if has else torch.zeros((1, 3), dtype=torch.float32, device=alpha.device)
    return [to_wp(alpha.reshape(-1)), to_wp(normal.reshape(-1, 3), wp.vec3), to_wp(mask.reshape(-1)),
            to_wp(ref_normal.reshape(-1, 3), wp.vec3h), to_wp(ref_alpha.reshape(-1)),
            to_wp(p.reshape(-1, 3), wp.vec3), int(has)]


class _MeshViewLosses(torch.autograd.Function):
    @staticmethod
    def forward(ctx, alpha, normal, mask, ref_normal, ref_alpha, prior):
        H, W = alpha.shape
        dev = wp_device(alpha)
        rows = torch.empty((H, 5), dtype=torch.float32, device=alpha.device)
        losses = torch.empty(3, dtype=torch.float32, device=alpha.device)
        scales = torch.empty(3, dtype=torch.float32, device=alpha.device)
        ins = _inputs(alpha, normal, mask, ref_normal, ref_alpha, prior)
        with torch_stream(alpha):
            wp.launch(K_.view_loss_rows_kernel, dim=H, inputs=[*ins, W], outputs=[to_wp(rows)], device=dev)
            wp.launch(K_.view_loss_total_kernel, dim=1, inputs=[to_wp(rows), H * W],
                      outputs=[to_wp(losses), to_wp(scales)], device=dev)
        ctx.save_for_backward(alpha, normal, scales)
        ctx.ins = ins  # the Warp views of the inputs, reused by the backward pass
        return losses

    @staticmethod
    def backward(ctx, g_losses):
        alpha, normal, scales = ctx.saved_tensors
        g_alpha = torch.empty_like(alpha)
        g_normal = torch.empty_like(normal)
        with torch_stream(alpha):
            wp.launch(K_.view_loss_backward_kernel, dim=alpha.numel(),
                      inputs=[*ctx.ins, to_wp(scales), to_wp(g_losses.to(torch.float32).contiguous())],
                      outputs=[to_wp(g_alpha.view(-1)), to_wp(g_normal.view(-1, 3), wp.vec3)], device=wp_device(alpha))
        return g_alpha, g_normal, None, None, None, None


def mesh_view_losses(alpha: torch.Tensor, normal: torch.Tensor, mask: torch.Tensor, ref_normal: torch.Tensor,
                     ref_alpha: torch.Tensor, prior: torch.Tensor | None = None) -> torch.Tensor:
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
                                 ref_alpha.contiguous(), None if prior is None else prior.contiguous())
