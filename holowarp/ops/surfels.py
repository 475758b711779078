"""Differentiable 2D-Gaussian (surfel) rasterisation: the torch face of ``kernels/surfels.py``.

:func:`rasterize_surfels` is the public entry point (method.md §3). Two autograd functions
sit behind it, in the gsplat manner: :class:`ProjectSurfels` (per-surfel projection; its
backward is Warp's autodiff of the projection kernel) and :class:`RasterizeSurfels` (tile
binning, front-to-back compositing; its backward is the hand-written kernel). The dense
float64 reference the tests compare against is :mod:`holowarp.ops.surfels_ref`.
"""

from __future__ import annotations


import torch
import warp as wp

from holowarp.kernels import surfels as K_
from holowarp.ops._warp import run_chunks, thread_chunks, to_wp, torch_stream, wp_device

__all__ = ["rasterize_surfels", "ProjectSurfels", "RasterizeSurfels", "check_surfel_inputs"]



def _empty(shape, dtype, like: torch.Tensor) -> torch.Tensor:
    return torch.empty(shape, dtype=dtype, device=like.device)


def _zeros(shape, dtype, like: torch.Tensor) -> torch.Tensor:
    return torch.zeros(shape, dtype=dtype, device=like.device)


_PROJ_WIDTHS = (3, 2, 2, 3, 2, 2, 3)  # h2, e0, e1, pqd, centers, center_frac, normals
_VEC = {1: float, 2: wp.vec2, 3: wp.vec3}


def _mat(m: torch.Tensor, wptype):
    return wptype(*m.detach().cpu().double().reshape(-1).tolist())


class ProjectSurfels(torch.autograd.Function):
    """Surfel centres, scales, quaternions -> per-surfel splat transforms (differentiable).

    Forward returns ``h2`` [N,3], ``e0`` [N,2], ``e1`` [N,2], ``pqd`` [N,3], ``centers``
    [N,2] (projected centres, pixels), ``center_frac`` [N,2] (their fractional parts, from
    float64; not differentiable) and ``normals`` [N,3] (world, facing the camera); see
    ``kernels/surfels.py`` for their meaning. Backward runs the adjoint of the projection
    kernel. Camera arguments get no gradient.
    """

    @staticmethod
    def forward(ctx, means, quats, scales, viewmat, K):
        n = means.shape[0]
        outs = tuple(_empty((n, w), torch.float32, means) for w in _PROJ_WIDTHS)
        vm = _mat(viewmat, wp.mat44d)
        km = _mat(K, wp.mat33d)
        ins = [to_wp(means, wp.vec3), to_wp(quats, wp.vec4), to_wp(scales, wp.vec2), vm, km]
        outs_wp = [to_wp(t, _VEC[w]) for t, w in zip(outs, _PROJ_WIDTHS)]
        if n > 0:
            with torch_stream(means):
                wp.launch(K_.project_surfels, dim=n, inputs=ins, outputs=outs_wp, device=wp_device(means))
        ctx.save_for_backward(means, quats, scales)
        ctx.mark_non_differentiable(outs[5])
        ctx.cam = (vm, km)
        return outs

    @staticmethod
    def backward(ctx, *g_outs):
        means, quats, scales = ctx.saved_tensors
        vm, km = ctx.cam
        n = means.shape[0]
        d_means = _zeros((n, 3), torch.float32, means)
        d_quats = _zeros((n, 4), torch.float32, means)
        d_scales = _zeros((n, 2), torch.float32, means)
        if n > 0:
            grads = [_zeros((n, w), torch.float32, means) if g is None else g.float().contiguous()
                     for g, w in zip(g_outs, _PROJ_WIDTHS)]  # fmt: skip
            dev = wp_device(means)
            # The adjoint launch recomputes the forward into scratch outputs.
            scratch = [wp.empty(n, dtype=_VEC[w], device=dev) for w in _PROJ_WIDTHS]
            with torch_stream(means):
                wp.launch(
                    K_.project_surfels,
                    dim=n,
                    inputs=[to_wp(means, wp.vec3), to_wp(quats, wp.vec4), to_wp(scales, wp.vec2), vm, km],
                    outputs=scratch,
                    adj_inputs=[to_wp(d_means, wp.vec3), to_wp(d_quats, wp.vec4), to_wp(d_scales, wp.vec2),
                                wp.mat44d(), wp.mat33d()],
                    adj_outputs=[to_wp(g, _VEC[w]) for g, w in zip(grads, _PROJ_WIDTHS)],
                    adjoint=True,
                    device=dev,
                )  # fmt: skip
        return d_means, d_quats, d_scales, None, None


class _Binning:
    """Per-call binning state (depth order, per-block lists, packed records), kept on the
    autograd context for the backward pass. See ``kernels/surfels.py`` step 3."""

    def __init__(self, h2, e0, e1, pqd, centers, center_frac, normals, opacities, colors, width, height, near):
        dev = wp_device(h2)
        n = h2.shape[0]
        self.tiles_x = (width + K_.TILE_SIZE - 1) // K_.TILE_SIZE
        self.tiles_y = (height + K_.TILE_SIZE - 1) // K_.TILE_SIZE
        num_keys = self.tiles_x * self.tiles_y * K_.BLOCKS_PER_TILE
        self.boxes = _empty((n, 4), torch.int32, h2)
        self.counts = _empty((n,), torch.int32, h2)
        # One more list than blocks: emit_intersections files the blocks a surfel's box
        # touches but its cut-off ellipse misses under key num_keys, after every real list.
        self.list_start = _zeros((num_keys + 1,), torch.int32, h2)
        self.list_end = _zeros((num_keys + 1,), torch.int32, h2)
        self.total = 0
        if n == 0:
            return
        depth_keys = _empty((2 * n,), torch.float32, h2)
        self.order = torch.arange(2 * n, dtype=torch.int32, device=h2.device)
        boxes_wp = to_wp(self.boxes, wp.vec4i)
        wp.launch(
            K_.surfel_bounds,
            dim=n,
            inputs=[to_wp(h2, wp.vec3), to_wp(e0, wp.vec2), to_wp(e1, wp.vec2), to_wp(centers, wp.vec2),
                    to_wp(opacities), float(near), int(width), int(height)],
            outputs=[boxes_wp, to_wp(self.counts), to_wp(depth_keys)],
            device=dev,
        )  # fmt: skip
        order_wp = to_wp(self.order)
        wp.utils.radix_sort_pairs(to_wp(depth_keys), order_wp, n)
        sorted_counts = _empty((n,), torch.int32, h2)
        offsets = _empty((n,), torch.int32, h2)
        sc_wp, off_wp = to_wp(sorted_counts), to_wp(offsets)
        wp.launch(K_.gather_counts, dim=n, inputs=[order_wp, to_wp(self.counts)], outputs=[sc_wp], device=dev)
        wp.utils.array_scan(sc_wp, off_wp, inclusive=False)
        # The one host read: the number of (block, surfel) pairs sizes the list buffers.
        total = int((offsets[-1].to(torch.int64) + sorted_counts[-1]).item())
        self.total = total
        if total == 0:
            return
        self.ranked_splats = wp.empty(n, dtype=K_.splat_record, device=dev)
        wp.launch(
            K_.pack_splats,
            dim=n,
            inputs=[order_wp, to_wp(h2, wp.vec3), to_wp(e0, wp.vec2), to_wp(e1, wp.vec2),
                    to_wp(pqd, wp.vec3), to_wp(centers, wp.vec2), to_wp(center_frac, wp.vec2), to_wp(normals, wp.vec3),
                    to_wp(opacities), to_wp(colors, wp.vec3)],
            outputs=[self.ranked_splats],
            device=dev,
        )  # fmt: skip
        keys = _empty((2 * total,), torch.int32, h2)
        self.list_ranks = _empty((2 * total,), torch.int32, h2)
        keys_wp, ranks_wp = to_wp(keys), to_wp(self.list_ranks)
        # Surfels write disjoint ranges of the pairs: slices of them run on several CPU threads.
        ins = [order_wp, boxes_wp, off_wp, sc_wp, self.ranked_splats, self.tiles_x, num_keys]
        run_chunks(lambda first, cnt: wp.launch(K_.emit_intersections, dim=cnt, inputs=ins + [first],
                                                outputs=[keys_wp, ranks_wp], device=dev),
                   thread_chunks(n, dev), kernel=K_.emit_intersections, device=dev)
        # Stable sort on the key only: each list keeps the depth order of emission.
        wp.utils.radix_sort_pairs(keys_wp, ranks_wp, total, 0, max(1, int(num_keys).bit_length()))
        wp.launch(
            K_.block_ranges,
            dim=total,
            inputs=[keys_wp, total],
            outputs=[to_wp(self.list_start), to_wp(self.list_end)],
            device=dev,
        )


#: Widths of the per-surfel gradients of the backward kernel: h2, e0, e1, pqd, centers,
#: normals, opacities, colors.
_GRAD_WIDTHS = (3, 2, 2, 3, 2, 3, 1, 3)


def _backward_launches(bins, bg, width: int, height: int, n: int, like: torch.Tensor, pixel_inputs: list):
    """Run the backward kernel on slices of the tiles (several CPU threads at once), each slice
    accumulating into its own zeroed gradient buffers, summed in slice order afterwards, so a
    given thread count always gives the same result. Returns the 8 gradient tensors."""
    dev = wp_device(like)
    ins = [to_wp(bins.list_start), to_wp(bins.list_ranks), to_wp(bins.order), bins.ranked_splats,
           bg, int(width), int(height), bins.tiles_x]
    total = bins.tiles_x * bins.tiles_y * K_.TILE_SIZE * K_.TILE_SIZE

    def launch(off, cnt):
        bufs = [_zeros((n, w), torch.float32, like) for w in _GRAD_WIDTHS]
        outs = [to_wp(b, _VEC[w]) if w > 1 else to_wp(b.view(n)) for b, w in zip(bufs, _GRAD_WIDTHS)]
        wp.launch(K_.rasterize_backward, dim=cnt, inputs=ins + [off] + pixel_inputs, outputs=outs, device=dev)
        return bufs

    parts = run_chunks(launch, thread_chunks(total, dev, align=K_.TILE_SIZE * K_.TILE_SIZE, always=True),
                       kernel=K_.rasterize_backward,
                       device=dev)
    out = parts[0]
    for more in parts[1:]:
        for acc, b in zip(out, more):
            acc += b
    return out


class RasterizeSurfels(torch.autograd.Function):
    """Projected surfels -> images (front-to-back compositing, hand-written backward).

    Inputs are the outputs of :class:`ProjectSurfels` plus ``opacities`` [N], ``colors``
    [N,3], ``background`` [3]; all float32 contiguous. Returns ``rgb`` [H,W,3], ``alpha``
    [H,W], ``normal`` [H,W,3], ``depth`` [H,W], ``median_depth`` [H,W], ``distortion`` [H,W]
    and (non-differentiable) ``visible`` [N] bool.
    """

    @staticmethod
    def forward(ctx, h2, e0, e1, pqd, centers, center_frac, normals, opacities, colors, background, width, height,
                near):  # fmt: skip
        bins = _Binning(h2, e0, e1, pqd, centers, center_frac, normals, opacities, colors, width, height, near)
        npix = width * height
        rgb = _empty((height, width, 3), torch.float32, h2)
        alpha = _empty((height, width), torch.float32, h2)
        normal = _empty((height, width, 3), torch.float32, h2)
        depth = _empty((height, width), torch.float32, h2)
        median = _empty((height, width), torch.float32, h2)
        dist = _empty((height, width), torch.float32, h2)
        trans = _empty((npix,), torch.float32, h2)
        last = _empty((npix,), torch.int32, h2)
        median_pos = _empty((npix,), torch.int32, h2)
        m2 = _empty((npix,), torch.float32, h2)
        bg = wp.vec3(*[float(v) for v in background.detach().cpu().tolist()])
        if bins.total == 0:
            # Nothing visible: every pixel shows the background.
            rgb[:] = background
            for t in (alpha, normal, depth, median, dist, m2):
                t.zero_()
            trans.fill_(1.0)
            last.zero_()
            median_pos.fill_(-1)
        else:
            dev = wp_device(h2)
            ins = [to_wp(bins.list_start), to_wp(bins.list_end), to_wp(bins.list_ranks), bins.ranked_splats, bg,
                   int(width), int(height), bins.tiles_x]
            outs = [to_wp(rgb.view(npix, 3), wp.vec3), to_wp(alpha.view(npix)), to_wp(normal.view(npix, 3), wp.vec3),
                    to_wp(depth.view(npix)), to_wp(median.view(npix)), to_wp(dist.view(npix)), to_wp(trans),
                    to_wp(last), to_wp(median_pos), to_wp(m2)]  # fmt: skip
            total = bins.tiles_x * bins.tiles_y * K_.TILE_SIZE * K_.TILE_SIZE
            # Pixels are independent: slices of the tiles write disjoint outputs.
            run_chunks(lambda off, cnt: wp.launch(K_.rasterize_forward, dim=cnt, inputs=ins + [off], outputs=outs,
                                                  device=dev),
                       thread_chunks(total, dev, align=K_.TILE_SIZE * K_.TILE_SIZE), kernel=K_.rasterize_forward,
                       device=dev)
        ctx.bins = bins
        ctx.size = (width, height)
        ctx.bg = bg
        ctx.save_for_backward(h2, alpha, depth, trans, last, median_pos, m2)
        visible = bins.counts > 0
        ctx.mark_non_differentiable(visible)
        return rgb, alpha, normal, depth, median, dist, visible

    @staticmethod
    def backward(ctx, g_rgb, g_alpha, g_normal, g_depth, g_median, g_dist, _g_visible):
        h2, alpha, depth, trans, last, median_pos, m2 = ctx.saved_tensors
        bins = ctx.bins
        width, height = ctx.size
        n = h2.shape[0]
        npix = width * height

        def g(t, shape):
            return _zeros(shape, torch.float32, h2) if t is None else t.float().contiguous().view(shape)

        g_rgb = g(g_rgb, (npix, 3))
        g_alpha = g(g_alpha, (npix,))
        g_normal = g(g_normal, (npix, 3))
        g_depth = g(g_depth, (npix,))
        g_median = g(g_median, (npix,))
        g_dist = g(g_dist, (npix,))
        grads = None
        if bins.total > 0:
            with torch_stream(h2):
                grads = _backward_launches(bins, ctx.bg, width, height, n, h2,
                                           [to_wp(alpha.view(npix)), to_wp(depth.view(npix)), to_wp(trans), to_wp(last),
                                            to_wp(median_pos), to_wp(m2), to_wp(g_rgb, wp.vec3), to_wp(g_alpha),
                                            to_wp(g_normal, wp.vec3), to_wp(g_depth), to_wp(g_median), to_wp(g_dist)])
        if grads is None:
            grads = [_zeros((n, w), torch.float32, h2) for w in _GRAD_WIDTHS]
        d_h2, d_e0, d_e1, d_pqd, d_centers, d_normals, d_opac, d_colors = grads
        d_opac = d_opac.view(n)
        # The background is seen through the final transmittance of every pixel.
        d_bg = (g_rgb * trans[:, None]).sum(0)
        return d_h2, d_e0, d_e1, d_pqd, d_centers, None, d_normals, d_opac, d_colors, d_bg, None, None, None


def _shape_error(name, t, expected):
    return ValueError(f"rasterize_surfels: {name} must have shape {expected}, got {tuple(t.shape)}")


def check_surfel_inputs(means, quats, scales, opacities, colors, viewmat, K, width, height, background):
    """Validate :func:`rasterize_surfels` arguments; raise ``ValueError`` naming the bad one.

    Returns ``(N, width, height, background)`` with ``background`` a tensor [3] (zeros if None).
    """
    for name, t in (("means", means), ("quats", quats), ("scales", scales), ("opacities", opacities),
                    ("colors", colors), ("viewmat", viewmat), ("K", K)):  # fmt: skip
        if not isinstance(t, torch.Tensor):
            raise TypeError(f"rasterize_surfels: {name} must be a torch.Tensor, got {type(t).__name__}")
        if not t.is_floating_point():
            raise TypeError(f"rasterize_surfels: {name} must be floating point, got {t.dtype}")
    if means.ndim != 2 or means.shape[1] != 3:
        raise _shape_error("means", means, "[N, 3]")
    n = means.shape[0]
    if n > K_.MAX_SURFELS:
        raise ValueError(f"rasterize_surfels: at most {K_.MAX_SURFELS} surfels per call (the lists pack a depth rank "
                         f"into 23 bits), got {n}")
    for name, t, shape in (("quats", quats, (n, 4)), ("scales", scales, (n, 2)), ("opacities", opacities, (n,)),
                           ("colors", colors, (n, 3)), ("viewmat", viewmat, (4, 4)), ("K", K, (3, 3))):  # fmt: skip
        if tuple(t.shape) != shape:
            raise _shape_error(name, t, list(shape))
    for name, t in (("quats", quats), ("scales", scales), ("opacities", opacities), ("colors", colors)):
        if t.device != means.device:
            raise ValueError(f"rasterize_surfels: {name} is on {t.device} but means is on {means.device}")
    k = K.detach().double().cpu()
    if not (torch.allclose(k[2], torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)) and float(k[1, 0]) == 0.0):
        raise ValueError(
            "rasterize_surfels: K must be a pinhole matrix [[fx, s, cx], [0, fy, cy], [0, 0, 1]], "
            f"got {k.tolist()}"
        )
    try:
        width, height = int(width), int(height)
    except (TypeError, ValueError) as e:
        raise ValueError(f"rasterize_surfels: width and height must be integers, got {width!r}, {height!r}") from e
    if width <= 0 or height <= 0:
        raise ValueError(f"rasterize_surfels: width and height must be positive, got {width}x{height}")
    if background is None:
        background = torch.zeros(3, dtype=torch.float32, device=means.device)
    elif not isinstance(background, torch.Tensor) or tuple(background.shape) != (3,):
        shape = tuple(background.shape) if isinstance(background, torch.Tensor) else type(background).__name__
        raise ValueError(f"rasterize_surfels: background must be a tensor of shape [3], got {shape}")
    return n, width, height, background


def rasterize_surfels(
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
    near_plane: float = K_.NEAR_PLANE,
) -> dict:
    """Render 2D Gaussian surfels into one view, differentiably (method.md §3).

    Args:
        means: surfel centres in world coordinates (metres). [N, 3]
        quats: rotations as wxyz quaternions, not necessarily normalised; the surfel's normal
            is the rotation's third axis. [N, 4]
        scales: linear, positive extents (standard deviations, metres) along the rotation's
            first two axes. [N, 2]
        opacities: in (0, 1). [N]
        colors: RGB per surfel. [N, 3]
        viewmat: world-to-camera matrix, OpenCV axes (x right, y down, z forward). [4, 4]
        K: pinhole intrinsics in pixels; pixel centres at (x + 0.5, y + 0.5). [3, 3]
        width, height: image size in pixels.
        background: colour seen through the final transmittance; black if None. [3]
        near_plane: surfels whose cut-off disk (alpha >= 1/255) comes closer to the camera
            than this (metres) are culled.

    Returns:
        dict of float32 tensors on the inputs' device:

        - ``rgb`` [H, W, 3]: sum_k w_k c_k + T_final * background, w_k = alpha_k T_k.
        - ``alpha`` [H, W]: sum_k w_k.
        - ``normal`` [H, W, 3]: sum_k w_k n_k, n_k the world normal flipped to face the camera.
        - ``depth`` [H, W]: sum_k w_k z_k, z_k the camera depth of the ray-splat intersection.
        - ``median_depth`` [H, W]: z of the contributor where the transmittance crosses 0.5.
        - ``distortion`` [H, W]: sum_k w_k sum_{j<k} w_j (z_k - z_j)^2 (2DGS).
        - ``means2d`` [N, 2]: projected centres in pixels. When gradients flow, its ``.grad``
          after ``backward()`` is the loss gradient with respect to a screen-space translation
          of each splat (the densification signal), as in gsplat.
        - ``visible`` [N] bool: the surfel touched at least one tile.

        Gradients flow to means, quats, scales, opacities, colors and background (and to
        anything upstream of them). Inputs of any float dtype are computed in float32.

    Example:
        >>> out = rasterize_surfels(means, quats, scales, opac, rgb, viewmat, K, 128, 128)
        >>> loss = (out["rgb"] - target).abs().mean(); loss.backward()
    """
    n, width, height, background = check_surfel_inputs(
        means, quats, scales, opacities, colors, viewmat, K, width, height, background
    )
    f32 = torch.float32
    means = means.to(f32).contiguous()
    quats = quats.to(f32).contiguous()
    scales = scales.to(f32).contiguous()
    opacities = opacities.to(f32).contiguous()
    colors = colors.to(f32).contiguous()
    background = background.to(device=means.device, dtype=f32).contiguous()
    with torch_stream(means):
        h2, e0, e1, pqd, centers, center_frac, normals = ProjectSurfels.apply(means, quats, scales, viewmat, K)
        rgb, alpha, normal, depth, median, dist, visible = RasterizeSurfels.apply(
            h2, e0, e1, pqd, centers, center_frac, normals, opacities, colors, background, width, height, float(near_plane)
        )
    if centers.requires_grad:
        centers.retain_grad()
    return {
        "rgb": rgb,
        "alpha": alpha,
        "normal": normal,
        "depth": depth,
        "median_depth": median,
        "distortion": dist,
        "means2d": centers,
        "visible": visible,
    }
