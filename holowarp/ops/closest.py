"""Point-to-surface distances: launches :mod:`holowarp.kernels.closest` on a BVH of the
surface (the same code on CPU and CUDA)."""

from __future__ import annotations

import numpy as np

from holowarp.device import init_warp, resolve_device

__all__ = ["closest_distance"]


def closest_distance(vertices, faces, points, *, device: str = "cpu") -> np.ndarray:
    """(P,) float64: the distance from each of ``points`` (P, 3) to the nearest point of the
    triangle surface ``vertices`` (V, 3) / ``faces`` (F, 3), computed in float32."""
    wp = init_warp()
    from holowarp.kernels.closest import closest_distance_kernel

    dev = resolve_device(device)
    v = np.ascontiguousarray(vertices, dtype=np.float32)
    p = np.ascontiguousarray(points, dtype=np.float32)
    if len(p) == 0:
        return np.zeros(0)
    mesh = wp.Mesh(points=wp.array(v, dtype=wp.vec3, device=dev),
                   indices=wp.array(np.ascontiguousarray(faces, dtype=np.int32).ravel(), dtype=wp.int32, device=dev))
    out = wp.empty(len(p), dtype=float, device=dev)
    both = np.concatenate([v, p])
    span = float(np.linalg.norm(both.max(0) - both.min(0))) * 2.0 + 1.0
    wp.launch(closest_distance_kernel, dim=len(p), inputs=[mesh.id, wp.array(p, dtype=wp.vec3, device=dev), span],
              outputs=[out], device=dev)
    return out.numpy().astype(np.float64)
