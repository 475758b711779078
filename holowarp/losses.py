"""Image and geometry losses shared by the Gaussian stages (method.md §3 and §5).

All functions are plain differentiable torch. Images are ``[H, W, C]`` (channels last, as the
rasterisers return them) or ``[B, C, H, W]``; colours in [0, 1].

- :func:`l1_dssim_loss`: the photometric loss ``(1 - 0.2) L1 + 0.2 (1 - SSIM)`` (method.md
  §3), with the SSIM of :func:`holowarp.metrics.image.ssim`.
- :func:`mask_loss`: L1 between rendered opacity and the foreground mask.
- :func:`depth_to_normal`: world-space normals of the surface a depth map describes.
- :func:`normal_consistency_loss` and :func:`distortion_loss`: the 2DGS regularisers.
- :func:`ranked_loss` / :func:`ranked_normal_loss`: the large-error-focused normal loss R(.)
  of method.md §5 (mean of the largest fraction of per-pixel errors).
"""

from __future__ import annotations

import math

import torch

from holowarp.metrics.image import ssim

__all__ = [
    "LAMBDA_DSSIM",
    "l1_dssim_loss",
    "mask_loss",
    "depth_to_normal",
    "normal_consistency_loss",
    "distortion_loss",
    "prior_error",
    "covered_prior_loss",
    "ranked_loss",
    "ranked_normal_loss",
]

#: Weight of the D-SSIM term in the photometric loss (method.md §3, §5).
LAMBDA_DSSIM = 0.2
def l1_dssim_loss(pred: torch.Tensor, target: torch.Tensor, *, lambda_dssim: float = LAMBDA_DSSIM) -> torch.Tensor:
    """``(1 - lambda) L1 + lambda (1 - SSIM)`` (method.md §3; lambda = 0.2)."""
    l1 = (pred - target).abs().mean()
    return (1.0 - lambda_dssim) * l1 + lambda_dssim * (1.0 - ssim(pred, target))


def mask_loss(alpha: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """Mean ``|alpha - mask|`` of rendered opacity [H, W] against the foreground mask [H, W]."""
    return (alpha - mask).abs().mean()


def depth_to_points(depth: torch.Tensor, K: torch.Tensor, viewmat: torch.Tensor) -> torch.Tensor:
    """World points [H, W, 3] of a camera-z depth map [H, W]: each pixel centre unprojected
    to ``z K^-1 (x + 0.5, y + 0.5, 1)`` (skew ``K[0, 1]`` included), then moved to world
    coordinates by the world-to-camera ``viewmat`` [4, 4]."""
    h, w = depth.shape
    K = K.to(depth)
    viewmat = viewmat.to(depth)
    ys, xs = torch.meshgrid(
        torch.arange(h, dtype=depth.dtype, device=depth.device) + 0.5,
        torch.arange(w, dtype=depth.dtype, device=depth.device) + 0.5,
        indexing="ij",
    )
    y_cam = (ys - K[1, 2]) / K[1, 1]
    x_cam = (xs - K[0, 2] - K[0, 1] * y_cam) / K[0, 0]
    pts_cam = torch.stack([x_cam, y_cam, torch.ones_like(xs)], dim=-1) * depth[..., None]
    R = viewmat[:3, :3]
    t = viewmat[:3, 3]
    return (pts_cam - t) @ R  # R^T (p - t)


def nearest_box(points: torch.Tensor, boxes: torch.Tensor) -> torch.Tensor:
    """Index (int64, ``points``' shape without the last axis) of the axis-aligned box nearest
    each point [..., 3]; ``boxes`` (P, 2, 3) as ``(lo, hi)`` rows. A point inside a box is at
    distance 0 from it (the first such box wins)."""
    p = points[..., None, :]
    gap = (boxes[:, 0] - p).clamp_min(0) + (p - boxes[:, 1]).clamp_min(0)
    return (gap * gap).sum(-1).argmin(-1)


def depth_to_normal(depth: torch.Tensor, K: torch.Tensor, viewmat: torch.Tensor) -> torch.Tensor:
    """World-space unit normals of the surface described by a camera-z depth map.

    Each pixel centre is unprojected to ``z K^-1 (x + 0.5, y + 0.5, 1)`` and moved to world
    coordinates; the normal is the cross product of the central differences along y and x,
    oriented towards the camera (OpenCV axes). Border pixels, and pixels whose neighbours
    have no depth (``<= 0``), get a zero normal.

    Args:
        depth: camera z in metres (not ray length). [H, W]
        K: intrinsics. [3, 3]
        viewmat: world-to-camera. [4, 4]

    Returns:
        normals [H, W, 3] in world coordinates.
    """
    h, w = depth.shape
    pts = depth_to_points(depth, K, viewmat)
    d_dy = pts[2:, 1:-1] - pts[:-2, 1:-1]
    d_dx = pts[1:-1, 2:] - pts[1:-1, :-2]
    n = torch.linalg.cross(d_dy, d_dx, dim=-1)  # faces the camera for OpenCV axes
    n = n / n.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    valid = (depth[2:, 1:-1] > 0) & (depth[:-2, 1:-1] > 0) & (depth[1:-1, 2:] > 0) & (depth[1:-1, :-2] > 0)
    out = torch.zeros(h, w, 3, dtype=depth.dtype, device=depth.device)
    out[1:-1, 1:-1] = n * valid[..., None]
    return out


def normal_consistency_loss(
    rendered_normal: torch.Tensor, surface_normal: torch.Tensor, *, weight: torch.Tensor | None = None
) -> torch.Tensor:
    """2DGS normal consistency: mean over pixels of ``weight * (1 - <n_rendered, n_surface>)``.

    Args:
        rendered_normal: alpha-weighted sum of surfel normals (as rendered). [H, W, 3]
        surface_normal: normals from the rendered depth (:func:`depth_to_normal`), usually
            multiplied by the detached rendered opacity as in 2DGS. [H, W, 3]
        weight: optional per-pixel weight. [H, W]
    """
    err = 1.0 - (rendered_normal * surface_normal).sum(-1)
    if weight is not None:
        err = err * weight
    return err.mean()


def prior_error(prior: torch.Tensor, *normals: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The normal-map prior's per-pixel error: ``sum_k 1 - cos(prior, normals[k])`` (H, W), and
    where the prior holds a normal (H, W) bool (length > 0.5; the maps are zero elsewhere).

    Every map is [H, W, 3] and need not be unit length. The prior's lengths are computed once
    for all the maps compared with it (stage 0, the Gaussian phases and the mesh blocks each
    compare one or two maps with it on every step)."""
    length = prior.norm(dim=-1)
    err = None
    for n in normals:
        e = 1.0 - (prior * n).sum(-1) / (length * n.norm(dim=-1)).clamp_min(1e-12)
        err = e if err is None else err + e
    return err, length > 0.5


def covered_prior_loss(prior: torch.Tensor, normal: torch.Tensor, alpha: torch.Tensor, *,
                       chord: bool = False) -> torch.Tensor:
    """Mean ``1 - cos`` between a rendered ``normal`` map (H, W, 3) and the normal map
    ``prior`` (H, W, 3) over the pixels the render covers (``alpha`` (H, W) > 0.5) where the
    prior holds a normal; 0 where there is no such pixel. Written without a boolean gather
    (a data-dependent shape is a host sync); the mesh blocks and the polish use it.

    ``chord``: the mean chord ``|n/|n| - p/|p|| = sqrt(2 (1 - cos))`` instead (plus 1e-6
    under the root, so that it is smooth where the normals agree). It grows linearly with the
    angle between them, so a surface tilted by a hundredth of a radian is still pulled back
    (``1 - cos`` is 5e-5 there, and its gradient vanishes with the tilt)."""
    err, has = prior_error(prior, normal)
    if chord:
        err = torch.sqrt(2.0 * err.clamp_min(0.0) + 1e-6)
    sel = ((alpha > 0.5) & has).to(err.dtype)
    return (err * sel).sum() / sel.sum().clamp_min(1.0)


def distortion_loss(distortion: torch.Tensor, *, weight: torch.Tensor | None = None) -> torch.Tensor:
    """Mean of the rendered 2DGS depth-distortion map [H, W] (optionally weighted)."""
    return (distortion if weight is None else distortion * weight).mean()


def ranked_loss(errors: torch.Tensor, *, mask: torch.Tensor | None = None, top_fraction: float = 0.5,
                groups: tuple[torch.Tensor, int] | None = None) -> torch.Tensor:
    """Large-error-focused mean: the mean of the largest ``top_fraction`` of ``errors``.

    This is the ranking operator R(.) of method.md §5: small errors (already fitted pixels,
    noise) are ignored and the gradient concentrates on the worst pixels. ``top_fraction=1``
    is the plain mean. Pixels outside ``mask`` are ignored; no valid pixel gives 0.

    ``groups``: ``(labels, count)``, labels in ``[0, count)`` of ``errors``' shape. Each
    group ranks its own valid pixels: the loss averages the largest ``top_fraction`` of every
    group's errors (one sum over all taken pixels). A scene's objects (method.md §11) are
    the groups, so one object with large errors does not push another's out of the ranking.
    """
    if not 0.0 < top_fraction <= 1.0:
        raise ValueError(f"ranked_loss: top_fraction must be in (0, 1], got {top_fraction}")
    if groups is not None:
        return _grouped_ranked_loss(errors, mask, top_fraction, *groups)
    e = errors.reshape(-1)
    if mask is None:
        k = max(1, int(math.ceil(top_fraction * e.numel())))
        return torch.topk(e, k, sorted=False).values.mean() if e.numel() else errors.sum() * 0.0
    # With a mask the count is data dependent. Rather than gather the valid pixels (a host
    # read of their number, a device sync on CUDA), sort all of them with the invalid ones
    # last and average the first k = ceil(top_fraction * valid) of that order.
    valid = mask.reshape(-1).bool()
    order = torch.sort(torch.where(valid, e.detach(), torch.full_like(e, -torch.inf)), descending=True).indices
    n = valid.sum()
    k = torch.ceil(top_fraction * n.to(e.dtype))
    take = torch.arange(e.numel(), device=e.device) < k
    return (e[order] * take).sum() / k.clamp_min(1.0)


def _grouped_ranked_loss(errors, mask, top_fraction: float, labels: torch.Tensor, count: int) -> torch.Tensor:
    """:func:`ranked_loss` within each group of ``labels``: one sort by error (invalid pixels
    last), a stable sort by group, and each pixel's rank is its place after its group's start."""
    e = errors.reshape(-1)
    g = labels.reshape(-1).long()
    valid = torch.ones_like(g, dtype=torch.bool) if mask is None else mask.reshape(-1).bool()
    order = torch.sort(torch.where(valid, e.detach(), torch.full_like(e, -torch.inf)), descending=True,
                       stable=True).indices
    order = order[torch.sort(g[order], stable=True).indices]
    # index_add_ into ``count`` slots, not bincount: its length would need a read of max(g).
    total = torch.zeros(count, dtype=torch.long, device=e.device).index_add_(0, g, torch.ones_like(g))
    start = torch.cumsum(total, 0) - total
    n_valid = torch.zeros(count, dtype=e.dtype, device=e.device).index_add_(0, g, valid.to(e.dtype))
    k = torch.ceil(top_fraction * n_valid)
    gs = g[order]
    take = (torch.arange(e.numel(), device=e.device) - start[gs]) < k[gs]
    return (e[order] * take).sum() / k.sum().clamp_min(1.0)


def ranked_normal_loss(
    n1: torch.Tensor,
    n2: torch.Tensor,
    *,
    mask: torch.Tensor | None = None,
    top_fraction: float = 0.5,
    groups: tuple[torch.Tensor, int] | None = None,
) -> torch.Tensor:
    """``R(1 - cos(n1, n2))`` over pixels [H, W, 3] (method.md §5 L_normal / L_prior);
    ``groups`` as in :func:`ranked_loss`.

    Normals need not be unit length (rendered normals are alpha-weighted); the cosine
    normalises them. Pixels where either normal is zero count as valid only if ``mask``
    says so; by default they are skipped.
    """
    l1 = n1.norm(dim=-1)
    l2 = n2.norm(dim=-1)
    cos = (n1 * n2).sum(-1) / (l1 * l2).clamp_min(1e-12)
    valid = (l1 > 1e-8) & (l2 > 1e-8)
    if mask is not None:
        valid = valid & mask.bool()
    return ranked_loss(1.0 - cos, mask=valid, top_fraction=top_fraction, groups=groups)
