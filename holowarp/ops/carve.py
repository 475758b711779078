"""Silhouette carving driver: launches :mod:`holowarp.kernels.carve` on a grid or on points.

The field at a point is the minimum over views of the mask sampled bilinearly at its
projection (0 behind a camera; 0 outside an image when ``outside_is_empty``). Inputs are
plain arrays so this layer knows nothing of datasets; :mod:`holowarp.carve` is the domain
API on top.
"""

from __future__ import annotations

import numpy as np

from holowarp.device import init_warp, resolve_device

__all__ = ["carve_grid", "carve_points"]


def _views(viewmats, Ks, masks, dev):
    wp = init_warp()
    vm = wp.array(np.ascontiguousarray(viewmats, dtype=np.float32), dtype=wp.mat44, device=dev)
    K = wp.array(np.ascontiguousarray(Ks, dtype=np.float32), dtype=wp.mat33, device=dev)
    m = wp.array(np.ascontiguousarray(masks, dtype=np.float32), dtype=float, device=dev)
    return wp, vm, K, m


def carve_grid(viewmats, Ks, masks, origin, spacing: float, shape, *, outside_is_empty: bool = True,
               device: str = "cpu") -> np.ndarray:
    """The carve field (NX, NY, NZ) float32 at nodes ``origin + (i, j, k) * spacing``.

    Args:
        viewmats: (V, 4, 4) world-to-camera (OpenCV); Ks: (V, 3, 3); masks: (V, H, W) in [0, 1].
        origin: (3,) world position of node (0, 0, 0); spacing: node spacing (world units).
        shape: (NX, NY, NZ) node counts.
    """
    from holowarp.kernels.carve import carve_kernel

    dev = resolve_device(device)
    wp, vm, K, m = _views(viewmats, Ks, masks, dev)
    field = wp.empty(tuple(int(s) for s in shape), dtype=float, device=dev)
    wp.launch(carve_kernel, dim=field.shape,
              inputs=[wp.vec3(*np.asarray(origin, np.float32)), float(spacing), vm, K, m, int(outside_is_empty)],
              outputs=[field], device=dev)
    return field.numpy()


def carve_points(viewmats, Ks, masks, points, *, outside_is_empty: bool = True,
                 device: str = "cpu") -> tuple[np.ndarray, np.ndarray]:
    """The carve field (P,) float32 at world ``points`` (P, 3), and (P,) int32 the number of
    views that see each point (in front of the camera, inside its image). The carve stops at
    the first view that rejects a point, so that count is exact wherever the field is > 0."""
    from holowarp.kernels.carve import carve_points_kernel

    dev = resolve_device(device)
    pts = np.ascontiguousarray(points, dtype=np.float32).reshape(-1, 3)
    if len(pts) == 0:
        return np.zeros(0, np.float32), np.zeros(0, np.int32)
    wp, vm, K, m = _views(viewmats, Ks, masks, dev)
    field = wp.empty(len(pts), dtype=float, device=dev)
    seen = wp.empty(len(pts), dtype=wp.int32, device=dev)
    wp.launch(carve_points_kernel, dim=len(pts),
              inputs=[wp.array(pts, dtype=wp.vec3, device=dev), vm, K, m, int(outside_is_empty)],
              outputs=[field, seen], device=dev)
    return field.numpy(), seen.numpy()
