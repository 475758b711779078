"""Dense float64 PyTorch reference of :func:`holowarp.ops.rasterize_surfels`.

Every surfel is evaluated at every pixel with the same rules as the Warp kernels
(method.md §3) and differentiated by torch autograd; no tiles, no bounding boxes, no
hand-written backward. It is written independently of the kernels: the ray-splat
intersection uses the plain homogeneous form of 2DGS, ``h_x = x H2 - H0``,
``h_y = y H2 - H1``, ``(u, v) = (h_x x h_y)[:2] / (h_x x h_y)[2]``, with ``H = K [t_u | t_v | p]``,
and compositing is written with cumulative products over the depth-sorted surfels.

It is meant for tests and for the benchmark's speed-up figure, and costs O(N * H * W) time
and memory; ``pixel_chunk`` bounds the memory (each chunk is re-computed in backward through
``torch.utils.checkpoint``).

``means2d`` is returned as a detached leaf tensor: after ``backward()`` its ``.grad`` is the
gradient with respect to a screen-space translation of each splat, obtained here by shifting
the pixel coordinates seen by surfel i by ``-(means2d_i - means2d_i.detach())``.
"""

from __future__ import annotations

import math

import torch
from torch.utils.checkpoint import checkpoint

from holowarp.kernels.surfels import ALPHA_MAX, ALPHA_MIN, MEDIAN_T, NEAR_PLANE, T_MIN

__all__ = ["rasterize_surfels_ref", "project_surfels_ref", "quat_wxyz_to_matrix"]


def quat_wxyz_to_matrix(quats: torch.Tensor) -> torch.Tensor:
    """Rotation matrices [N, 3, 3] of wxyz quaternions [N, 4] (normalised here)."""
    q = quats / quats.norm(dim=-1, keepdim=True)
    w, x, y, z = q.unbind(-1)
    return torch.stack(
        [
            1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
            2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
            2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
        ],
        dim=-1,
    ).reshape(q.shape[:-1] + (3, 3))  # fmt: skip


def project_surfels_ref(means, quats, scales, viewmat, K):
    """Per-surfel camera quantities in the dtype of ``means``.

    Returns:
        H [N, 3, 3] (``K [t_u | t_v | p]``), centres [N, 2] (pixels), camera-space centres
        [N, 3], world normals facing the camera [N, 3].
    """
    R = quat_wxyz_to_matrix(quats)  # [N, 3, 3]
    Rcw = viewmat[:3, :3]
    tcw = viewmat[:3, 3]
    p = means @ Rcw.T + tcw  # [N, 3]
    tu = (R[:, :, 0] @ Rcw.T) * scales[:, :1]
    tv = (R[:, :, 1] @ Rcw.T) * scales[:, 1:2]
    M = torch.stack([tu, tv, p], dim=-1)  # [N, 3, 3] columns t_u, t_v, p
    H = K @ M
    centers = H[:, :2, 2] / H[:, 2:3, 2]
    nw = R[:, :, 2]
    facing = ((nw @ Rcw.T) * p).sum(-1) > 0  # pointing away from the camera
    normals = torch.where(facing[:, None], -nw, nw)
    return H, centers, p, normals


def _composite(x, y, H, centers, shift, opac, colors, normals):
    """Composite pixels (x, y) [P] against all surfels [N], sorted front to back."""
    if H.shape[0] == 0:
        z = x.new_zeros(x.shape)
        inf = torch.full_like(z, math.inf)
        return x.new_zeros(x.shape + (3,)), z, x.new_zeros(x.shape + (3,)), z, z, z, x.new_ones(x.shape), inf
    xs = x[:, None] - shift[None, :, 0]  # [P, N]
    ys = y[:, None] - shift[None, :, 1]
    H0, H1, H2 = H[:, 0], H[:, 1], H[:, 2]  # [N, 3]
    hx = xs[..., None] * H2 - H0  # [P, N, 3]
    hy = ys[..., None] * H2 - H1
    c = torch.linalg.cross(hx, hy, dim=-1)
    ok = c[..., 2] != 0
    c2 = torch.where(ok, c[..., 2], torch.ones_like(c[..., 2]))
    u = c[..., 0] / c2
    v = c[..., 1] / c2
    rho3 = torch.where(ok, u * u + v * v, torch.full_like(u, math.inf))
    rho2 = 2.0 * ((xs - centers[:, 0]) ** 2 + (ys - centers[:, 1]) ** 2)
    use3 = rho3 <= rho2
    rho = torch.where(use3, rho3, rho2)
    z = torch.where(use3, H2[:, 0] * u + H2[:, 1] * v + H2[:, 2], H2[:, 2].expand_as(u))
    alpha_raw = torch.clamp_max(opac * torch.exp(-0.5 * rho), ALPHA_MAX)
    alpha = torch.where(alpha_raw >= ALPHA_MIN, alpha_raw, torch.zeros_like(alpha_raw))
    # Stop rule: a surfel is composited only while the transmittance after it stays >= T_MIN;
    # T is monotone, so that is one mask on the inclusive product.
    keep = torch.cumprod(1.0 - alpha, dim=1) >= T_MIN
    alpha = torch.where(keep, alpha, torch.zeros_like(alpha))
    one_minus = 1.0 - alpha
    T_incl = torch.cumprod(one_minus, dim=1)
    T_excl = torch.cat([torch.ones_like(T_incl[:, :1]), T_incl[:, :-1]], dim=1)
    w = alpha * T_excl  # [P, N]
    T_final = T_incl[:, -1]
    rgb = w @ colors
    acc = w.sum(1)
    nrm = w @ normals
    depth = (w * z).sum(1)
    # Median: last composited surfel entered with T > 0.5.
    is_med = (alpha > 0) & (T_excl > MEDIAN_T)
    idx = torch.arange(alpha.shape[1], device=alpha.device).expand_as(alpha)
    last_med = torch.where(is_med, idx, torch.full_like(idx, -1)).max(dim=1).values
    med = torch.where(
        last_med >= 0, z.gather(1, last_med.clamp_min(0)[:, None])[:, 0], torch.zeros_like(depth)
    )
    # Distortion sum_k w_k sum_{j<k} w_j (z_k - z_j)^2 via exclusive prefix sums.
    wz = w * z
    wz2 = wz * z
    A = torch.cumsum(w, 1) - w
    M1 = torch.cumsum(wz, 1) - wz
    M2 = torch.cumsum(wz2, 1) - wz2
    dist = (w * (z * z * A - 2.0 * z * M1 + M2)).sum(1)
    with torch.no_grad():
        # Relative distance of every discontinuous decision to its threshold (alpha skip,
        # transmittance stop, median choice, object-space/low-pass branch, which moves z).
        inf = torch.full_like(rho, math.inf)
        on = alpha > 0
        margin = torch.stack([
            ((alpha_raw - ALPHA_MIN).abs() / ALPHA_MIN).amin(1),
            torch.where(on, (T_excl - MEDIAN_T).abs() / MEDIAN_T, inf).amin(1),
            torch.where(on & ok, (rho3 - rho2).abs() / rho2.clamp_min(1e-300), inf).amin(1),
        ]).amin(0)  # fmt: skip
        # The stop test is on the transmittance *after* a surfel before it is dropped.
        keep_T = torch.cumprod(1.0 - alpha_raw * (alpha_raw >= ALPHA_MIN), 1)
        margin = torch.minimum(margin, ((keep_T - T_MIN).abs() / T_MIN).amin(1))
    return rgb, acc, nrm, depth, med, dist, T_final, margin


def rasterize_surfels_ref(
    means: torch.Tensor,  # [N, 3]
    quats: torch.Tensor,  # [N, 4]
    scales: torch.Tensor,  # [N, 2]
    opacities: torch.Tensor,  # [N]
    colors: torch.Tensor,  # [N, 3]
    viewmat: torch.Tensor,  # [4, 4]
    K: torch.Tensor,  # [3, 3]
    width: int,
    height: int,
    background: torch.Tensor | None = None,  # [3]
    *,
    near_plane: float = NEAR_PLANE,
    pixel_chunk: int | None = None,
    dtype: torch.dtype = torch.float64,
) -> dict:
    """Same contract and outputs as :func:`holowarp.ops.rasterize_surfels`, densely.

    Computes in ``dtype`` (float64 by default) and returns tensors of that dtype.
    ``pixel_chunk`` pixels are composited at a time (all at once if None).

    One extra output, ``decision_margin`` [H, W]: per pixel, the smallest relative distance
    of any discontinuous decision to its threshold (alpha vs 1/255, transmittance vs 1e-4,
    transmittance vs 0.5 for the median, object-space vs low-pass term). Where it is tiny, a
    float32 implementation may legitimately decide the other way; tests mask such pixels.
    """
    dev = means.device
    means, quats, scales, opacities, colors = (t.to(dtype) for t in (means, quats, scales, opacities, colors))
    viewmat = viewmat.to(device=dev, dtype=dtype)
    K = K.to(device=dev, dtype=dtype)
    if background is None:
        background = torch.zeros(3, dtype=dtype, device=dev)
    background = background.to(dtype)
    H, centers, p, normals = project_surfels_ref(means, quats, scales, viewmat, K)
    means2d = centers.detach().clone().requires_grad_(torch.is_grad_enabled())

    # Culling is per surfel and independent of the pixel: opacity below ALPHA_MIN never
    # shows, and a cut-off disk (rho <= 2 ln(255 o)) reaching the near plane is dropped.
    with torch.no_grad():
        o = opacities.detach()
        r2 = 2.0 * torch.log(torch.clamp_min(o * 255.0, 1e-30))
        tz2 = H[:, 2, 0] ** 2 + H[:, 2, 1] ** 2
        pz = H[:, 2, 2]
        valid = (o * 255.0 >= 1.0) & (pz > near_plane) & ((pz - near_plane) ** 2 > r2 * tz2)
        sel = torch.nonzero(valid).squeeze(1)
        sel = sel[torch.sort(pz[sel], stable=True).indices]

    Hs, cs, op, col, nrm = H[sel], centers[sel], opacities[sel], colors[sel], normals[sel]
    shift = (means2d - means2d.detach())[sel]
    ys, xs = torch.meshgrid(
        torch.arange(height, dtype=dtype, device=dev) + 0.5,
        torch.arange(width, dtype=dtype, device=dev) + 0.5,
        indexing="ij",
    )
    xs, ys = xs.reshape(-1), ys.reshape(-1)
    npix = width * height
    chunk = npix if pixel_chunk is None else max(1, int(pixel_chunk))
    parts = []
    for s in range(0, npix, chunk):
        args = (xs[s : s + chunk], ys[s : s + chunk], Hs, cs, shift, op, col, nrm)
        if chunk < npix and torch.is_grad_enabled():
            # Reentrant checkpointing: the non-reentrant variant kept each chunk's activations
            # alive here (6 GB for a quarter of a 10k-surfel 128^2 image).
            parts.append(checkpoint(_composite, *args, use_reentrant=True))
        else:
            parts.append(_composite(*args))
    rgb, acc, nrm_img, depth, med, dist, T_final, margin = (torch.cat(t, 0) for t in zip(*parts))
    rgb = rgb + T_final[:, None] * background
    return {
        "rgb": rgb.reshape(height, width, 3),
        "alpha": acc.reshape(height, width),
        "normal": nrm_img.reshape(height, width, 3),
        "depth": depth.reshape(height, width),
        "median_depth": med.reshape(height, width),
        "distortion": dist.reshape(height, width),
        "means2d": means2d,
        "visible": valid,
        "decision_margin": margin.reshape(height, width),
    }
