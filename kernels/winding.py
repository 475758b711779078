"""Inside/outside classification of points against a closed triangle surface (method.md §9).

Uses Warp's generalised winding number (``wp.mesh_query_point_sign_winding_number``, a
Barnes-Hut fast winding number on the mesh BVH): robust to small holes, self-intersections
and inconsistent tessellation, which ray parity is not. The ``wp.Mesh`` must be built with
``support_winding_number=True``.

Warp + NumPy only: no torch below ``kernels/``.
"""

from __future__ import annotations

import warp as wp

__all__ = ["winding_inside_kernel", "WINDING_ACCURACY", "WINDING_THRESHOLD"]

#: Barnes-Hut accuracy of the fast winding number (Warp's default; larger = more exact).
WINDING_ACCURACY = wp.constant(2.0)
#: A point is inside when its winding number exceeds this (0.5: half-way between 0 and 1).
WINDING_THRESHOLD = wp.constant(0.5)


@wp.kernel
def winding_inside_kernel(
    mesh: wp.uint64,
    points: wp.array(dtype=wp.vec3),  # [P]
    max_dist: float,
    inside: wp.array(dtype=wp.int32),  # [P] 1 inside, 0 outside
):
    tid = wp.tid()
    q = wp.mesh_query_point_sign_winding_number(mesh, points[tid], max_dist, WINDING_ACCURACY, WINDING_THRESHOLD)
    if q.result and q.sign < 0.0:
        inside[tid] = 1
    else:
        inside[tid] = 0
