"""Tetrahedral initialisation (method.md §4).

1. Convex hull of the stage-0 surfel centres (after dropping low-opacity ones).
2. The hull scaled by ``hull_scale`` = 1.1 about its centroid (the mean of its vertices).
3. fTetWild (pytetwild) with epsilon = 1e-3; ``edge_length_fac`` is the resolution knob.
4. One surfel per tet at its centroid, barycentric coordinates (1/4, 1/4, 1/4, 1/4): that
   binding lives in :class:`holowarp.tetgs.TetGaussians`.

The numbers live in :class:`holowarp.config.TetInitConfig`.
"""

from __future__ import annotations

import numpy as np

from holowarp.config import TetInitConfig
from holowarp.errors import InputError
from holowarp.tetmesh import TetMesh, tetrahedralize_surface

__all__ = ["HullError", "initial_tetmesh", "scaled_hull"]


class HullError(InputError):
    """The points do not span a 3D hull (too few views, too few or coplanar points)."""


def scaled_hull(points: np.ndarray, *, scale: float = TetInitConfig.hull_scale):
    """Convex hull of ``points`` (P, 3) scaled by ``scale`` about the mean of its vertices.

    Returns:
        (vertices (H, 3), faces (F, 3) int32) with outward-wound faces.

    Raises:
        HullError: fewer than 4 points, or points that are (nearly) coplanar.
    """
    from scipy.spatial import ConvexHull, QhullError

    P = np.asarray(points, dtype=np.float64)
    P = P[np.all(np.isfinite(P), axis=1)]
    if len(P) < 4:
        raise HullError(f"the convex hull needs at least 4 points, got {len(P)}")
    try:
        hull = ConvexHull(P)
    except QhullError as e:
        raise HullError(f"the points span no 3D hull (coplanar or collinear): {str(e).splitlines()[0]}") from None
    ext = P[hull.vertices].max(axis=0) - P[hull.vertices].min(axis=0)
    if hull.volume <= 1e-9 * max(float(np.prod(ext)), 1e-30) or np.min(ext) < 1e-6 * np.max(ext):
        raise HullError(f"the hull is degenerate (volume {hull.volume:.3g}, extents {ext.round(6).tolist()})")
    used, inv = np.unique(hull.simplices, return_inverse=True)
    V = P[used]
    F = inv.reshape(-1, 3).astype(np.int32)
    c = V.mean(axis=0)
    # Orient every facet outward: its normal must point away from the centroid.
    n = np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]])
    flip = np.einsum("ij,ij->i", n, V[F[:, 0]] - c) < 0
    F[flip] = F[flip][:, [0, 2, 1]]
    return c + scale * (V - c), F


def initial_tetmesh(
    centres: np.ndarray,
    opacities: np.ndarray | None = None,
    config: TetInitConfig = TetInitConfig(),
) -> TetMesh:
    """Steps 1–3 of §4: the tet mesh of the scaled convex hull of the surfel centres.

    Args:
        centres: (P, 3) stage-0 surfel centres.
        opacities: (P,) their opacities in (0, 1); low ones are dropped first.

    Raises:
        HullError: too few points survive, or they span no 3D hull.
    """
    P = np.asarray(centres, dtype=np.float64)
    if opacities is not None:
        P = P[np.asarray(opacities) >= config.min_opacity]
    if len(P) < config.min_points:
        raise HullError(
            f"only {len(P)} surfel centres with opacity >= {config.min_opacity}; at least "
            f"{config.min_points} are needed for a hull (stage 0 failed to fit the object?)"
        )
    V, F = scaled_hull(P, scale=config.hull_scale)
    return tetrahedralize_surface(V, F, edge_length_fac=config.edge_length_fac, epsilon=config.epsilon)
