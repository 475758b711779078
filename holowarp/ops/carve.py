"""Silhouette carving driver: launches :mod:`holowarp.kernels.carve` on a grid or on points.

The field at a point is the minimum over views of the mask sampled bilinearly at its
projection (0 behind a camera; 0 outside an image when ``outside_is_empty``), or with
``outliers = k`` the (k+1)-th smallest value; ``margin_px`` first dilates every mask by that
many pixels (a disk). Inputs are plain arrays so this layer knows nothing of datasets;
:mod:`holowarp.carve` is the domain API on top.
"""

from __future__ import annotations

import numpy as np

from holowarp.device import init_warp, resolve_device

__all__ = ["carve_grid", "carve_points"]


def _dilate(masks: np.ndarray, r: int) -> np.ndarray:
    """Grey-value dilation of every mask (V, H, W) by a disk of radius ``r`` pixels."""
    if r <= 0:
        return masks
    from scipy.ndimage import grey_dilation

    y, x = np.mgrid[-r:r + 1, -r:r + 1]
    disk = (x * x + y * y) <= r * r
    return np.stack([grey_dilation(m, footprint=disk) for m in masks])


def _check(outliers: int, margin_px: int):
    from holowarp.kernels.carve import MAX_OUTLIERS

    if not 0 <= int(outliers) <= MAX_OUTLIERS:
        raise ValueError(f"carve: outliers must lie in [0, {MAX_OUTLIERS}], got {outliers}")
    if int(margin_px) < 0:
        raise ValueError(f"carve: margin_px must be >= 0, got {margin_px}")


def _views(viewmats, Ks, masks, dev, margin_px: int = 0):
    wp = init_warp()
    masks = _dilate(np.asarray(masks, dtype=np.float32), int(margin_px))
    vm = wp.array(np.ascontiguousarray(viewmats, dtype=np.float32), dtype=wp.mat44, device=dev)
    K = wp.array(np.ascontiguousarray(Ks, dtype=np.float32), dtype=wp.mat33, device=dev)
    m = wp.array(np.ascontiguousarray(masks, dtype=np.float32), dtype=float, device=dev)
    return wp, vm, K, m


def carve_grid(viewmats, Ks, masks, origin, spacing: float, shape, *, outside_is_empty: bool = True,
               outliers: int = 0, margin_px: int = 0, device: str = "cpu") -> np.ndarray:
    """The carve field (NX, NY, NZ) float32 at nodes ``origin + (i, j, k) * spacing``.

    Args:
        viewmats: (V, 4, 4) world-to-camera (OpenCV); Ks: (V, 3, 3); masks: (V, H, W) in [0, 1].
        origin: (3,) world position of node (0, 0, 0); spacing: node spacing (world units).
        shape: (NX, NY, NZ) node counts.
        outliers: views that may reject a node that is kept (0: the plain visual hull).
        margin_px: dilate the masks by this many pixels first.
    """
    from holowarp.kernels.carve import carve_kernel

    _check(outliers, margin_px)
    dev = resolve_device(device)
    wp, vm, K, m = _views(viewmats, Ks, masks, dev, margin_px)
    field = wp.empty(tuple(int(s) for s in shape), dtype=float, device=dev)
    wp.launch(carve_kernel, dim=field.shape,
              inputs=[wp.vec3(*np.asarray(origin, np.float32)), float(spacing), vm, K, m, int(outside_is_empty),
                      int(outliers)],
              outputs=[field], device=dev)
    return field.numpy()


def carve_points(viewmats, Ks, masks, points, *, outside_is_empty: bool = True, outliers: int = 0,
                 margin_px: int = 0, device: str = "cpu") -> tuple[np.ndarray, np.ndarray]:
    """The carve field (P,) float32 at world ``points`` (P, 3), and (P,) int32 the number of
    views that see each point (in front of the camera, inside its image). The carve stops
    once ``outliers + 1`` views reject a point, so that count is exact wherever the field
    is > 0. ``outliers`` and ``margin_px`` as in :func:`carve_grid`."""
    from holowarp.kernels.carve import carve_points_kernel

    _check(outliers, margin_px)
    dev = resolve_device(device)
    pts = np.ascontiguousarray(points, dtype=np.float32).reshape(-1, 3)
    if len(pts) == 0:
        return np.zeros(0, np.float32), np.zeros(0, np.int32)
    wp, vm, K, m = _views(viewmats, Ks, masks, dev, margin_px)
    field = wp.empty(len(pts), dtype=float, device=dev)
    seen = wp.empty(len(pts), dtype=wp.int32, device=dev)
    wp.launch(carve_points_kernel, dim=len(pts),
              inputs=[wp.array(pts, dtype=wp.vec3, device=dev), vm, K, m, int(outside_is_empty), int(outliers)],
              outputs=[field, seen], device=dev)
    return field.numpy(), seen.numpy()
