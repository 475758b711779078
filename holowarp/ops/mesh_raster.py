"""Differentiable, tile-binned triangle rasteriser for the tet boundary (method.md §6).

``rasterize_mesh`` renders the silhouette (``alpha``), the flat world-space normal, the
camera depth and the face index of a triangle mesh seen by one OpenCV camera
(method.md §1). It is a ``torch.autograd.Function`` over the Warp kernels in
``holowarp.kernels.mesh_raster``; ``holowarp.ops.mesh_raster_ref`` holds a dense torch
reference of the same computation that the tests compare against.

Anti-aliasing choice: analytic edge distance at silhouette pixels, in the spirit of
nvdiffrast's antialias op. After a hard visibility pass, each pixel whose coverage differs
from a 4-neighbour's finds the contour edge (an edge whose neighbouring face is missing or
back-facing) crossing the segment between their centres, nearest the uncovered one; with
``d`` the distance from the pixel centre to that edge's line, covered pixels get
``min(1, 0.5 + d)`` and uncovered ones ``max(0, 0.5 - d)``. This is a one-pixel box filter
across the silhouette: straight edges get their exact covered area, and the gradient of
``alpha`` reaches the two vertices of the silhouette edge that sets it.

Only front faces are drawn (the tet boundary is closed and wound outward); faces with a
vertex closer than ``near`` to the camera plane are skipped.
"""

from __future__ import annotations

import math

import numpy as np
import torch
import warp as wp

from holowarp.kernels import mesh_raster as K_
from holowarp.ops._warp import run_chunks, thread_chunks, to_wp, wp_device, torch_stream

__all__ = ["rasterize_mesh", "mesh_face_neighbors", "DEFAULT_TILE_SIZE", "DEFAULT_NEAR"]

#: Tile edge in pixels for binning. Boundary triangles of the geometry stage cover a few
#: pixels each, so small tiles keep every pixel's face list short.
DEFAULT_TILE_SIZE = 8
#: Faces with a vertex closer than this to the camera plane (camera z, metres) are skipped.
DEFAULT_NEAR = 1.0e-3



def mesh_face_neighbors(faces: torch.Tensor) -> torch.Tensor:
    """Face across each edge of each triangle.

    Args:
        faces: (F, 3) integer vertex indices.

    Returns:
        (F, 3) int32: entry ``[f, k]`` is the face sharing edge ``faces[f, k] ->
        faces[f, (k + 1) % 3]``, or -1 when that edge is on the mesh boundary or shared by
        more than two faces (both are treated as potential silhouette edges).
    """
    faces = torch.as_tensor(faces)
    F = faces.shape[0]
    dev = faces.device
    if F == 0:
        return torch.empty((0, 3), dtype=torch.int32, device=dev)
    f64 = faces.to(torch.int64)
    a = f64[:, [0, 1, 2]].reshape(-1)  # [3F] edge k of face f at 3 f + k
    b = f64[:, [1, 2, 0]].reshape(-1)
    n = int(f64.max().item()) + 1
    key = torch.minimum(a, b) * n + torch.maximum(a, b)
    skey, order = torch.sort(key, stable=True)
    _, counts = torch.unique_consecutive(skey, return_counts=True)
    group = torch.repeat_interleave(counts, counts)  # size of each sorted entry's group
    pos = torch.arange(skey.numel(), device=dev)
    first = torch.repeat_interleave(torch.cumsum(counts, 0) - counts, counts)
    partner_sorted = torch.where(pos == first, pos + 1, pos - 1).clamp_max(skey.numel() - 1)
    nbr_sorted = torch.where(group == 2, order[partner_sorted] // 3, torch.full_like(order, -1))
    out = torch.empty(3 * F, dtype=torch.int64, device=dev)
    out[order] = nbr_sorted
    return out.view(F, 3).to(torch.int32)


_NEIGHBOR_CACHE: list = []  # [(faces copy, neighbors)], most recent last
_NEIGHBOR_CACHE_SIZE = 4


def _cached_face_neighbors(faces: torch.Tensor) -> torch.Tensor:
    # The geometry stage draws the same boundary faces every iteration until a topology
    # change; comparing contents is microseconds, rebuilding the adjacency is milliseconds.
    for i, (f, n) in enumerate(_NEIGHBOR_CACHE):
        if f.shape == faces.shape and f.device == faces.device and torch.equal(f, faces):
            _NEIGHBOR_CACHE.append(_NEIGHBOR_CACHE.pop(i))
            return n
    n = mesh_face_neighbors(faces)
    _NEIGHBOR_CACHE.append((faces.clone(), n))
    del _NEIGHBOR_CACHE[:-_NEIGHBOR_CACHE_SIZE]
    return n


def _as_matrix(m, shape, name) -> np.ndarray:
    if isinstance(m, torch.Tensor):
        m = m.detach().cpu().numpy()
    m = np.asarray(m, dtype=np.float64)
    if m.shape != shape:
        raise ValueError(f"rasterize_mesh: {name} must have shape {shape}, got {m.shape}")
    if not np.all(np.isfinite(m)):
        raise ValueError(f"rasterize_mesh: {name} has non-finite entries")
    return m


def _setup_faces(x_wp, faces_wp, R, t, Kmat, V: int, F: int, near: float, dev):
    """Project the vertices and set up every face's screen triangle, edge equations, 1/z
    and normal (kernels ``project_vertices_kernel`` and ``face_setup_kernel``)."""
    pc = wp.empty(V, dtype=wp.vec3, device=dev)
    uv = wp.empty(V, dtype=wp.vec2, device=dev)
    wp.launch(K_.project_vertices_kernel, dim=V, inputs=[x_wp, R, t, Kmat], outputs=[pc, uv], device=dev)
    f = {k: wp.empty(F, dtype=d, device=dev) for k, d in (
        ("p0", wp.vec2), ("p1", wp.vec2), ("p2", wp.vec2), ("edge_len", wp.vec3), ("inv_z", wp.vec3),
        ("inv_area2", float), ("front", wp.int32), ("fnormal", wp.vec3), ("edge_eq", wp.mat33))}  # fmt: skip
    wp.launch(K_.face_setup_kernel, dim=F, inputs=[faces_wp, x_wp, pc, uv, float(near)],
              outputs=[f["p0"], f["p1"], f["p2"], f["edge_len"], f["inv_z"], f["inv_area2"], f["front"], f["fnormal"],
                       f["edge_eq"]], device=dev)
    return pc, uv, f


def _bin_faces(f: dict, nbr_wp, F: int, W: int, H: int, tile_size: int, tiles_x: int, T: int, dev):
    """Silhouette flags and per-tile face lists: (contour, tile_offsets, tile_counts, tile_faces)."""
    contour = wp.empty(F, dtype=wp.int32, device=dev)
    tile_rect = wp.empty(F, dtype=wp.vec4i, device=dev)
    tile_counts = wp.zeros(T, dtype=wp.int32, device=dev)
    wp.launch(K_.face_bin_count_kernel, dim=F, inputs=[f["front"], nbr_wp, f["p0"], f["p1"], f["p2"], W, H, tile_size,
                                                       tiles_x], outputs=[contour, tile_rect, tile_counts], device=dev)
    tile_offsets = wp.empty(T, dtype=wp.int32, device=dev)
    wp.utils.array_scan(tile_counts, tile_offsets, inclusive=False)
    # one host read to size the face lists (a device sync on CUDA)
    total = int(wp.to_torch(tile_offsets)[-1].item()) + int(wp.to_torch(tile_counts)[-1].item())
    tile_faces = wp.empty(max(total, 1), dtype=wp.int32, device=dev)
    tile_fill = wp.zeros(T, dtype=wp.int32, device=dev)
    wp.launch(K_.tile_fill_kernel, dim=F, inputs=[tile_rect, tiles_x, tile_offsets, tile_fill], outputs=[tile_faces],
              device=dev)
    return contour, tile_offsets, tile_counts, tile_faces


class _RasterizeMesh(torch.autograd.Function):
    @staticmethod
    def forward(ctx, vertices, faces, neighbors, R, t, Kmat, width, height, tile_size, near):
        dev = wp_device(vertices)
        tdev = vertices.device
        V, F, H, W = vertices.shape[0], faces.shape[0], height, width
        tiles_x = (W + tile_size - 1) // tile_size
        tiles_y = (H + tile_size - 1) // tile_size
        x_wp = to_wp(vertices, wp.vec3)
        pc, uv, f = _setup_faces(x_wp, to_wp(faces, wp.vec3i), R, t, Kmat, V, F, near, dev)
        contour, tile_offsets, tile_counts, tile_faces = _bin_faces(
            f, to_wp(neighbors, wp.vec3i), F, W, H, tile_size, tiles_x, tiles_x * tiles_y, dev)
        alpha = torch.empty((H, W), dtype=torch.float32, device=tdev)
        depth = torch.empty((H, W), dtype=torch.float32, device=tdev)
        face_id = torch.empty((H, W), dtype=torch.int32, device=tdev)
        winner = torch.empty((H, W), dtype=torch.int32, device=tdev)
        normal = torch.empty((H, W, 3), dtype=torch.float32, device=tdev)
        face_id_wp = to_wp(face_id.view(-1))
        bands = thread_chunks(H, dev, align=tile_size)
        r_in = [tile_offsets, tile_counts, tile_faces, f["edge_eq"], f["inv_z"], f["inv_area2"], f["fnormal"], W,
                tile_size, tiles_x]
        r_out = [to_wp(depth.view(-1)), face_id_wp, to_wp(normal.view(-1, 3), wp.vec3)]
        run_chunks(lambda r0, n: wp.launch(K_.raster_kernel, dim=(n, W), inputs=r_in + [r0], outputs=r_out, device=dev),
                   bands, kernel=K_.raster_kernel, device=dev)
        # Anti-aliasing reads the 4-neighbours' coverage: it starts once every band is rasterised.
        a_in = [tile_offsets, tile_counts, tile_faces, f["p0"], f["p1"], f["p2"], f["edge_len"], contour, face_id_wp,
                W, H, tile_size, tiles_x]
        a_out = [to_wp(alpha.view(-1)), to_wp(winner.view(-1))]
        run_chunks(lambda r0, n: wp.launch(K_.antialias_kernel, dim=(n, W), inputs=a_in + [r0], outputs=a_out,
                                           device=dev), bands, kernel=K_.antialias_kernel, device=dev)
        ctx.mark_non_differentiable(depth, face_id)
        ctx.save_for_backward(vertices, faces, winner, face_id)
        ctx.raster = (pc, uv, R, Kmat, W, H)
        return alpha, normal, depth, face_id

    @staticmethod
    def backward(ctx, g_alpha, g_normal, _g_depth, _g_face_id):
        with torch_stream(ctx.saved_tensors[0]):
            return _RasterizeMesh._backward(ctx, g_alpha, g_normal)

    @staticmethod
    def _backward(ctx, g_alpha, g_normal):
        vertices, faces, winner, face_id = ctx.saved_tensors
        pc, uv, R, Kmat, W, H = ctx.raster
        dev = wp_device(vertices)
        V = vertices.shape[0]
        F = faces.shape[0]
        if g_alpha is None:
            g_alpha = torch.zeros((H, W), dtype=torch.float32, device=vertices.device)
        if g_normal is None:
            g_normal = torch.zeros((H, W, 3), dtype=torch.float32, device=vertices.device)
        g_alpha = g_alpha.to(torch.float32).contiguous()
        g_normal = g_normal.to(torch.float32).contiguous()
        faces_wp = to_wp(faces, wp.vec3i)
        x_wp = to_wp(vertices, wp.vec3)
        b_in = [faces_wp, uv, to_wp(winner.view(-1)), to_wp(face_id.view(-1)), to_wp(g_alpha.view(-1)),
                to_wp(g_normal.view(-1, 3), wp.vec3), W]

        def band(r0, n):
            # Each band accumulates into its own buffers; summed in band order (deterministic).
            g_uv, g_fn = wp.zeros(V, dtype=wp.vec2, device=dev), wp.zeros(F, dtype=wp.vec3, device=dev)
            wp.launch(K_.raster_backward_kernel, dim=(n, W), inputs=b_in + [r0], outputs=[g_uv, g_fn], device=dev)
            return wp.to_torch(g_uv), wp.to_torch(g_fn)

        parts = run_chunks(band, thread_chunks(H, dev, align=8, always=True), kernel=K_.raster_backward_kernel,
                           device=dev)
        g_uv_t, g_fn_t = parts[0]
        for a, b in parts[1:]:
            g_uv_t += a
            g_fn_t += b
        grad_uv, grad_fn = to_wp(g_uv_t, wp.vec2), to_wp(g_fn_t, wp.vec3)
        grad_x = torch.zeros((V, 3), dtype=torch.float32, device=vertices.device)
        gx_wp = to_wp(grad_x, wp.vec3)
        wp.launch(K_.face_normal_backward_kernel, dim=F, inputs=[faces_wp, x_wp, grad_fn], outputs=[gx_wp], device=dev)
        wp.launch(K_.project_backward_kernel, dim=V, inputs=[pc, R, Kmat, grad_uv], outputs=[gx_wp], device=dev)
        return grad_x, None, None, None, None, None, None, None, None, None


def _check_inputs(vertices, faces, viewmat, K, width, height, neighbors, tile_size, near):
    """Validated, converted inputs of :func:`rasterize_mesh` (ValueError naming the argument)."""
    if not isinstance(vertices, torch.Tensor):
        vertices = torch.as_tensor(np.asarray(vertices), dtype=torch.float32)
    if vertices.ndim != 2 or vertices.shape[1] != 3 or not vertices.is_floating_point():
        raise ValueError(f"rasterize_mesh: vertices must be a (V, 3) float tensor, got {tuple(vertices.shape)} {vertices.dtype}")
    dev = vertices.device
    faces = torch.as_tensor(faces, device=dev)
    if faces.ndim != 2 or faces.shape[1] != 3 or faces.is_floating_point():
        raise ValueError(f"rasterize_mesh: faces must be a (F, 3) integer tensor, got {tuple(faces.shape)} {faces.dtype}")
    width, height, tile_size = int(width), int(height), int(tile_size)
    if width <= 0 or height <= 0:
        raise ValueError(f"rasterize_mesh: width and height must be positive, got {width}x{height}")
    if tile_size <= 0:
        raise ValueError(f"rasterize_mesh: tile_size must be positive, got {tile_size}")
    if not (math.isfinite(near) and near > 0):
        raise ValueError(f"rasterize_mesh: near must be a positive number, got {near}")
    Vn = vertices.shape[0]
    if faces.numel():
        fmin, fmax = (int(v) for v in torch.aminmax(faces))
        if fmin < 0 or fmax >= Vn:
            raise ValueError(f"rasterize_mesh: faces index vertices outside [0, {Vn}) (min {fmin}, max {fmax})")
    vm = _as_matrix(viewmat, (4, 4), "viewmat")
    Km = _as_matrix(K, (3, 3), "K")
    faces = faces.to(torch.int32).contiguous()
    if neighbors is None:
        neighbors = _cached_face_neighbors(faces)
    else:
        neighbors = torch.as_tensor(neighbors, device=dev)
        if neighbors.shape != faces.shape:
            raise ValueError(f"rasterize_mesh: neighbors must have shape {tuple(faces.shape)}, got {tuple(neighbors.shape)}")
        neighbors = neighbors.to(torch.int32).contiguous()

    return vertices, faces, neighbors, vm, Km, width, height, tile_size


def rasterize_mesh(
    vertices: torch.Tensor,
    faces: torch.Tensor,
    viewmat,
    K,
    width: int,
    height: int,
    *,
    neighbors: torch.Tensor | None = None,
    tile_size: int = DEFAULT_TILE_SIZE,
    near: float = DEFAULT_NEAR,
) -> dict:
    """Rasterise a triangle mesh (the tet boundary) into one OpenCV camera.

    Args:
        vertices: (V, 3) world positions, metres. Gradients flow back to it through
            ``alpha`` and ``normal``. Computed in float32 (a float64 input gets a float64
            gradient of the float32 computation).
        faces: (F, 3) integer vertex indices, wound so the normal points outward.
        viewmat: (4, 4) world-to-camera matrix (tensor or array; not differentiated).
        K: (3, 3) intrinsics (not differentiated). Pixel centres at ``(x + 0.5, y + 0.5)``.
        width, height: image size in pixels.
        neighbors: optional (F, 3) int32 from :func:`mesh_face_neighbors`. Without it the
            adjacency is computed and kept in a small cache keyed on the faces' contents.
        tile_size: binning tile edge in pixels.
        near: faces with a vertex at camera depth <= ``near`` are not drawn.

    Returns:
        dict with
        ``alpha`` (H, W) float32 anti-aliased coverage in [0, 1] (differentiable),
        ``normal`` (H, W, 3) float32 unit world-space normal of the visible face, zero where
        no face covers the pixel centre (differentiable),
        ``depth`` (H, W) float32 camera z of the visible surface, 0 where empty (not
        differentiable), and
        ``face_id`` (H, W) int32 visible face, -1 where empty.
        Note ``alpha`` can be positive where ``face_id`` is -1 (outer half of the
        anti-aliasing band), so normal losses should mask with ``face_id >= 0``.

    Example:
        >>> out = rasterize_mesh(V, F, viewmat, K, 256, 256)
        >>> loss = (out["alpha"] - mask).abs().mean()
    """
    vertices, faces, neighbors, vm, Km, width, height, tile_size = _check_inputs(
        vertices, faces, viewmat, K, width, height, neighbors, tile_size, near)
    dev, Vn = vertices.device, vertices.shape[0]
    # float32 kernels; .to() routes a float64 input's gradient back as float64
    x = vertices.to(torch.float32)
    R = wp.mat33(*vm[:3, :3].reshape(-1).tolist())
    t = wp.vec3(*vm[:3, 3].tolist())
    Kw = wp.mat33(*Km.reshape(-1).tolist())
    if faces.shape[0] == 0 or Vn == 0:
        z = x.sum() * 0.0  # keeps the graph connected for callers that backprop anyway
        return {
            "alpha": torch.zeros((height, width), dtype=torch.float32, device=dev) + z,
            "normal": torch.zeros((height, width, 3), dtype=torch.float32, device=dev) + z,
            "depth": torch.zeros((height, width), dtype=torch.float32, device=dev),
            "face_id": torch.full((height, width), -1, dtype=torch.int32, device=dev),
        }
    with torch_stream(x):
        alpha, normal, depth, face_id = _RasterizeMesh.apply(
            x.contiguous(), faces, neighbors, R, t, Kw, width, height, tile_size, float(near)
        )
    return {"alpha": alpha, "normal": normal, "depth": depth, "face_id": face_id}
