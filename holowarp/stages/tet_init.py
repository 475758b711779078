"""Tetrahedral initialisation (method.md §4).

1. Convex hull of the stage-0 surfel centres (after dropping low-opacity ones).
2. The hull scaled by ``hull_scale`` = 1.1 about its centroid (the mean of its vertices).
3. fTetWild (pytetwild) with epsilon = 1e-3; ``edge_length_fac`` is the resolution knob.
   In a scene of several objects it is relative to each object (:func:`object_sizing`).
4. One surfel per tet at its centroid, barycentric coordinates (1/4, 1/4, 1/4, 1/4): that
   binding lives in :class:`holowarp.tetgs.TetGaussians`.

The numbers live in :class:`holowarp.config.TetInitConfig`.
"""

from __future__ import annotations

import numpy as np

from holowarp.config import TetInitConfig
from holowarp.errors import InputError
from holowarp.tetmesh import TetMesh, tetrahedralize_surface

__all__ = ["HullError", "initial_tetmesh", "object_sizing", "scaled_hull"]

#: Cells along the longest side of :func:`object_sizing`'s background grid.
SIZING_CELLS = 24
#: Grid nodes this many cells or nearer to an object's box take its edge length.
SIZING_MARGIN = 1.5
#: fTetWild meets a sizing field more closely than its global ideal edge length: a cube
#: meshed with the field has 0.90x the mean edge it has alone at the same value (1.4x the
#: tets), so the field's values are this much longer to give an object the tets it has alone.
SIZING_GAIN = 1.1


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


def object_sizing(pieces, lo, hi, *, edge_length_fac: float, hull_scale: float = TetInitConfig.hull_scale,
                  cells: int = SIZING_CELLS):
    """fTetWild's sizing field for a scene of several objects: in and around each object
    the ideal edge length it would get alone, ``edge_length_fac`` x ``hull_scale`` x the
    diagonal of its bounding box (alone, the hull around it is about that box, inflated by
    ``hull_scale``); in the empty space between them, which the carve removes, the largest
    of those or ``edge_length_fac`` x the diagonal of the box ``lo``-``hi`` (the hull's: one
    edge length for the whole scene), whichever is longer.

    A scene's hull spans all objects, so one edge length relative to its diagonal meshes
    every object coarser the more the scene spreads, and no one factor suits objects of
    different shapes: in the three-object test scene, with that edge length divided by the
    scene's width in objects (2.5), the box (a cube, whose diagonal is long for its side)
    got 76k tets against 34k alone.

    Args:
        pieces: the objects' bounding boxes, ``[(lo (3,), hi (3,)), ...]`` (at least one;
            :func:`holowarp.stages.objects.hull_pieces`).
        lo, hi: (3,) corners of the box the field must cover (the hull's bounding box).
        cells: grid cells along the longest side of that box.

    Returns:
        ``(bg_vertices (B, 3), bg_tets (T, 4), bg_values (B,))`` for
        :func:`holowarp.tetmesh.tetrahedralize_surface`'s ``sizing``: a Kuhn-split grid over
        the box grown by one cell; a node within :data:`SIZING_MARGIN` cells of an object's
        box (Euclidean distance; 0 inside) takes the value of the nearest such object,
        others the empty space's value; world units.
    """
    from holowarp.primitives import box_tetmesh

    if len(pieces) == 0:
        raise ValueError("object_sizing: no objects")
    box_lo = np.asarray([p[0] for p in pieces], dtype=np.float64).reshape(-1, 3)
    box_hi = np.asarray([p[1] for p in pieces], dtype=np.float64).reshape(-1, 3)
    edge = SIZING_GAIN * edge_length_fac * hull_scale * np.linalg.norm(box_hi - box_lo, axis=1)
    lo, hi = np.asarray(lo, dtype=np.float64), np.asarray(hi, dtype=np.float64)
    step = float((hi - lo).max()) / cells
    n = np.maximum(1, np.ceil((hi - lo) / step).astype(int)) + 2
    grid = box_tetmesh(tuple(n), tuple(n * step), tuple(0.5 * (lo + hi) - 0.5 * n * step))
    X = grid.vertices
    gap = np.maximum(box_lo[None] - X[:, None], 0.0) + np.maximum(X[:, None] - box_hi[None], 0.0)  # (B, K, 3)
    dist = np.linalg.norm(gap, axis=2)
    nearest = np.argmin(dist, axis=1)
    # Empty space between the objects is carved away: mesh it no finer than the coarsest
    # object, nor than one edge length for the whole hull would.
    far = max(float(edge.max()), edge_length_fac * float(np.linalg.norm(hi - lo)))
    values = np.where(dist[np.arange(len(X)), nearest] <= SIZING_MARGIN * step, edge[nearest], far)
    return X, grid.tets, values


def initial_tetmesh(
    centres: np.ndarray,
    opacities: np.ndarray | None = None,
    config: TetInitConfig = TetInitConfig(),
    *,
    pieces=None,
    seed: int = 0,
) -> TetMesh:
    """Steps 1–3 of §4: the tet mesh of the scaled convex hull of the surfel centres.

    Args:
        centres: (P, 3) stage-0 surfel centres.
        opacities: (P,) their opacities in (0, 1); low ones are dropped first.
        pieces: a scene's objects as bounding boxes ``[(lo (3,), hi (3,)), ...]``
            (:func:`holowarp.stages.objects.hull_pieces`): each is meshed at the edge length
            it would get alone (:func:`object_sizing`). None: one object, the edge length
            relative to the hull's diagonal.
        seed: the run's seed, which fTetWild's random choices are drawn from
            (:func:`holowarp.tetmesh.tetrahedralize_surface`).

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
    if not pieces:
        return tetrahedralize_surface(V, F, edge_length_fac=config.edge_length_fac, epsilon=config.epsilon, seed=seed)
    sizing = object_sizing(pieces, V.min(0), V.max(0), edge_length_fac=config.edge_length_fac,
                           hull_scale=config.hull_scale)
    return tetrahedralize_surface(V, F, edge_length_abs=float(sizing[2].max()), epsilon=config.epsilon, sizing=sizing,
                                  seed=seed)
