"""Conforming local refinement of a tet mesh by longest-edge bisection (Rivara's LEPP).

The prunes (method.md §5) only remove tets, so without refinement the initial edge length
fixes how finely the surface can follow the images: a see-through hole narrower than a tet,
or a stud smaller than one, is out of reach (issues 12 and 16). :func:`bisect_longest_edges`
halves the tets a caller marks until their longest edge is at most a target length, and
keeps the mesh conforming (no hanging vertex) by splitting whole edge rings:

- every tet's *longest edge* is taken in one strict global order (length, then vertex ids),
  so it is unique;
- an edge is *terminal* when it is the longest edge of every tet around it. Splitting a
  terminal edge at its midpoint cuts each tet of its ring in two along it, and each child
  keeps the longer half of the parent's edges away from the split: this is the bisection
  that bounds the element shapes (Rivara 1984; Rivara & Levin 1992 for 3D);
- a marked tet whose longest edge is not terminal waits, and the tets around that edge
  whose own longest edge is longer are split first (the longest-edge propagation path,
  LEPP). Lengths strictly grow along such a path, so it ends at a terminal edge.

Two terminal edges never share a tet (a tet has one longest edge), so every round splits
all the terminal edges it reached at once; no Python loop runs over tets or edges. A split
replaces one vertex of a positively oriented tet by a point on one of its edges, so the
children stay positively oriented and the boundary, as a point set, is unchanged: a
boundary edge's midpoint lies on both of its boundary triangles.

The pipeline refines once, after the prune that ``TopologyConfig.refine_at_prune`` names
(:func:`holowarp.stages.topology.refine_near_surface`); the config's docstring gives what
each placement measured.
"""

from __future__ import annotations

import numpy as np

from holowarp.tetmesh import TET_EDGES

__all__ = ["bisect_longest_edges", "boundary_band", "edge_table"]


def boundary_band(tets: np.ndarray, num_vertices: int, boundary_vertices: np.ndarray, rings: int) -> np.ndarray:
    """(M,) bool: the tets within ``rings`` vertex rings of the boundary (``rings`` = 1: the
    tets with a vertex in ``boundary_vertices``; each further ring adds the tets sharing a
    vertex with the band)."""
    on = np.zeros(num_vertices, dtype=bool)
    on[np.asarray(boundary_vertices, dtype=np.int64)] = True
    band = on[tets].any(axis=1)
    for _ in range(int(rings) - 1):
        on[tets[band].ravel()] = True
        band = on[tets].any(axis=1)
    return band


def edge_table(V: np.ndarray, T: np.ndarray):
    """Unique edges of ``T``: ends (E, 2), per-tet edge ids (M, 6), lengths (E,), and each
    tet's longest edge (M,) in the strict order (length, then the ends' ids)."""
    N = len(V)
    e = np.sort(T[:, TET_EDGES], axis=2).reshape(-1, 2)
    keys, inv = np.unique(e[:, 0] * N + e[:, 1], return_inverse=True)
    ends = np.stack([keys // N, keys % N], axis=1)
    inv = inv.reshape(-1, 6)
    length = np.linalg.norm(V[ends[:, 0]] - V[ends[:, 1]], axis=1)
    # Rank: unique keys are sorted, so lexsort on (key, length) gives a strict order.
    rank = np.empty(len(keys), dtype=np.int64)
    rank[np.lexsort((keys, length))] = np.arange(len(keys))
    longest = inv[np.arange(len(T)), np.argmax(rank[inv], axis=1)]
    return ends, inv, length, longest


def bisect_longest_edges(vertices, tets, marked, target: float, *, max_rounds: int = 200, max_hops: int = 64):
    """Bisect the ``marked`` tets until their longest edge is at most ``target`` (module docstring).

    Args:
        vertices: (N, 3) float positions.
        tets: (M, 4) int, positively oriented.
        marked: (M,) bool, the tets to refine; their children stay marked, the tets split
            only to keep the mesh conforming do not.
        target: the longest-edge length (same units as ``vertices``) below which a marked
            tet is left alone.
        max_rounds: bound on the rounds (each splits every terminal edge it reaches).
        max_hops: bound on the propagation path followed per round.

    Returns:
        ``(vertices (N', 3), tets (M', 4), parent (M',), ends (N' - N, 2))``: the refined
        mesh (the first N vertices unchanged, new vertices appended), each output tet's
        input tet, and the two input-or-new vertices whose midpoint each new vertex is (in
        creation order, so a value on vertices interpolates linearly by
        ``x[N + k] = (x[ends[k, 0]] + x[ends[k, 1]]) / 2`` applied in order).

    Raises:
        ValueError: ``target`` is not positive, or the shapes disagree.
    """
    V = np.asarray(vertices, dtype=np.float64)
    T = np.asarray(tets, dtype=np.int64)
    want = np.asarray(marked, dtype=bool)
    if not target > 0:
        raise ValueError(f"bisect_longest_edges: target must be > 0, got {target!r}")
    if V.ndim != 2 or V.shape[1] != 3 or T.ndim != 2 or T.shape[1] != 4 or want.shape != (len(T),):
        raise ValueError(f"bisect_longest_edges: vertices (N, 3), tets (M, 4) and marked (M,) expected, got "
                         f"{V.shape}, {T.shape}, {want.shape}")
    parent = np.arange(len(T))
    new_ends = []
    for _ in range(int(max_rounds)):
        if len(T) == 0:
            break
        ends, inv, length, longest = edge_table(V, T)
        active = want & (length[longest] > target)
        if not active.any():
            break
        n_edges = len(ends)
        ring = np.bincount(inv.ravel(), minlength=n_edges)
        as_longest = np.bincount(longest, minlength=n_edges)
        terminal = as_longest == ring
        split = np.zeros(n_edges, dtype=bool)
        frontier = active.copy()
        seen_edges = np.zeros(n_edges, dtype=bool)
        for _hop in range(int(max_hops)):
            reached = np.zeros(n_edges, dtype=bool)
            reached[longest[frontier]] = True
            reached &= ~seen_edges
            if not reached.any():
                break
            seen_edges |= reached
            split |= reached & terminal
            waiting = reached & ~terminal
            if not waiting.any():
                break
            # The tets around a waiting edge whose longest edge is another (longer) one.
            frontier = waiting[inv].any(axis=1) & ~waiting[longest]
        ids = np.flatnonzero(split)
        if len(ids) == 0:  # cannot happen (a LEPP ends at a terminal edge); bounded anyway
            break
        N = len(V)
        m = np.full(n_edges, -1, dtype=np.int64)
        m[ids] = N + np.arange(len(ids))
        V = np.concatenate([V, 0.5 * (V[ends[ids, 0]] + V[ends[ids, 1]])])
        new_ends.append(ends[ids])
        cut = split[longest]
        t_cut, e_cut = T[cut], longest[cut]
        a, b = ends[e_cut, 0], ends[e_cut, 1]
        k1, k2 = t_cut.copy(), t_cut.copy()
        k1[k1 == a[:, None]] = m[e_cut]
        k2[k2 == b[:, None]] = m[e_cut]
        T = np.concatenate([T[~cut], k1, k2])
        parent = np.concatenate([parent[~cut], parent[cut], parent[cut]])
        want = np.concatenate([want[~cut], want[cut], want[cut]])
    ends_all = np.concatenate(new_ends) if new_ends else np.zeros((0, 2), dtype=np.int64)
    return V, T, parent, ends_all
