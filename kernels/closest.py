"""Unsigned point-to-surface distance on a ``wp.Mesh`` BVH (error maps, method.md §9).

Warp + NumPy only: no torch below ``kernels/``.
"""

from __future__ import annotations

import warp as wp

__all__ = ["closest_distance_kernel"]


@wp.kernel
def closest_distance_kernel(
    mesh: wp.uint64,
    points: wp.array(dtype=wp.vec3),  # [P]
    max_dist: float,
    dist: wp.array(dtype=float),  # [P] distance to the nearest point of the surface
):
    tid = wp.tid()
    p = points[tid]
    q = wp.mesh_query_point_no_sign(mesh, p, max_dist)
    if q.result:
        dist[tid] = wp.length(wp.mesh_eval_position(mesh, q.face, q.u, q.v) - p)
    else:
        dist[tid] = max_dist
