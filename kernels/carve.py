"""Visual-hull carving: the silhouette-consistency field on a regular grid.

For every grid node (:func:`carve_kernel`) or given point (:func:`carve_points_kernel`) p
the field is ``min over views of mask_v(project_v(p))``, the mask
sampled bilinearly at the projection (OpenCV camera, pixel centres at ``x + 0.5``). A node
behind a camera gets 0; a node projecting outside an image gets 0 when
``outside_is_empty`` (every view sees the whole object, as in the synthetic protocol) and
is otherwise left to the other views. The visual hull is the 0.5 super-level set: a node is
kept iff it projects inside every mask (mask > 0.5), and marching cubes at 0.5 on this field
places the surface between nodes with sub-voxel accuracy from the soft mask edges.

A *tolerant* carve (``outliers = k > 0``) takes the (k+1)-th smallest value instead of the
minimum: a node is kept when all but k views see it inside (real captures: masks and poses
that disagree by a few pixels in some views).

Warp + NumPy only: no torch below ``kernels/``.
"""

from __future__ import annotations

import warp as wp

__all__ = ["carve_kernel", "carve_points_kernel", "carve_value", "sample_mask_bilinear", "MAX_OUTLIERS"]


@wp.func
def sample_mask_bilinear(masks: wp.array3d(dtype=float), view: int, x: float, y: float):
    """Bilinear mask value at continuous pixel coordinates (x, y) (pixel centres at +0.5),
    clamped to the border."""
    h = masks.shape[1]
    w = masks.shape[2]
    fx = wp.clamp(x - 0.5, 0.0, float(w - 1))
    fy = wp.clamp(y - 0.5, 0.0, float(h - 1))
    x0 = int(wp.floor(fx))
    y0 = int(wp.floor(fy))
    x1 = wp.min(x0 + 1, w - 1)
    y1 = wp.min(y0 + 1, h - 1)
    ax = fx - float(x0)
    ay = fy - float(y0)
    top = masks[view, y0, x0] * (1.0 - ax) + masks[view, y0, x1] * ax
    bot = masks[view, y1, x0] * (1.0 - ax) + masks[view, y1, x1] * ax
    return top * (1.0 - ay) + bot * ay


#: Most views a tolerant carve may let reject a point it keeps (:func:`carve_value`).
MAX_OUTLIERS = 7
_lowest = wp.types.vector(length=MAX_OUTLIERS + 1, dtype=float)


@wp.func
def carve_value(
    p: wp.vec3,
    viewmats: wp.array(dtype=wp.mat44),
    Ks: wp.array(dtype=wp.mat33),
    masks: wp.array3d(dtype=float),
    outside_is_empty: int,
    outliers: int,
):
    """(the (outliers+1)-th smallest over views of the bilinear mask at p's projection, the
    number of views that see p). ``outliers = 0`` is the plain minimum (the visual hull);
    ``outliers = k`` keeps a point that all but k views see inside, so a few masks that are
    too tight (or poses that are slightly off) cannot carve a notch through the object.
    A view that p lies behind or (with ``outside_is_empty``) projects outside of gives 0."""
    h = float(masks.shape[1])
    w = float(masks.shape[2])
    lo = _lowest()
    for j in range(MAX_OUTLIERS + 1):
        lo[j] = 1.0
    seen = int(0)
    for v in range(viewmats.shape[0]):
        M = viewmats[v]
        pc = wp.vec3(
            M[0, 0] * p[0] + M[0, 1] * p[1] + M[0, 2] * p[2] + M[0, 3],
            M[1, 0] * p[0] + M[1, 1] * p[1] + M[1, 2] * p[2] + M[1, 3],
            M[2, 0] * p[0] + M[2, 1] * p[1] + M[2, 2] * p[2] + M[2, 3],
        )
        val = float(1.0)
        counted = int(1)
        if pc[2] <= 1.0e-6:
            val = 0.0
        else:
            K = Ks[v]
            x = K[0, 0] * pc[0] / pc[2] + K[0, 1] * pc[1] / pc[2] + K[0, 2]
            y = K[1, 1] * pc[1] / pc[2] + K[1, 2]
            if x < 0.0 or y < 0.0 or x > w or y > h:
                val = 0.0
                if outside_is_empty == 0:
                    counted = 0
            else:
                seen += 1
                val = sample_mask_bilinear(masks, v, x, y)
        if counted != 0 and val < lo[outliers]:
            # insert into the sorted list of the outliers+1 smallest values
            j = outliers
            while j > 0 and lo[j - 1] > val:
                lo[j] = lo[j - 1]
                j -= 1
            lo[j] = val
            if lo[outliers] <= 0.0:
                break
    return lo[outliers], seen


@wp.kernel
def carve_kernel(
    origin: wp.vec3,  # world position of node (0, 0, 0)
    spacing: float,  # node spacing (cubic cells)
    viewmats: wp.array(dtype=wp.mat44),  # [V] world-to-camera, OpenCV
    Ks: wp.array(dtype=wp.mat33),  # [V]
    masks: wp.array3d(dtype=float),  # [V, H, W] in [0, 1]
    outside_is_empty: int,
    outliers: int,  # views that may reject a kept node (0: the plain visual hull)
    field: wp.array3d(dtype=float),  # [NX, NY, NZ] (outliers+1)-th smallest mask value over views
):
    i, j, k = wp.tid()
    p = origin + wp.vec3(float(i), float(j), float(k)) * spacing
    val, seen = carve_value(p, viewmats, Ks, masks, outside_is_empty, outliers)
    field[i, j, k] = val


@wp.kernel
def carve_points_kernel(
    points: wp.array(dtype=wp.vec3),  # [P] world positions
    viewmats: wp.array(dtype=wp.mat44),  # [V] world-to-camera, OpenCV
    Ks: wp.array(dtype=wp.mat33),  # [V]
    masks: wp.array3d(dtype=float),  # [V, H, W] in [0, 1]
    outside_is_empty: int,
    outliers: int,  # views that may reject a kept point (0: the plain visual hull)
    field: wp.array(dtype=float),  # [P] (outliers+1)-th smallest mask value over views
    seen: wp.array(dtype=wp.int32),  # [P] views in front of which the point projects in frame
):
    i = wp.tid()
    val, n = carve_value(points[i], viewmats, Ks, masks, outside_is_empty, outliers)
    field[i] = val
    seen[i] = n
