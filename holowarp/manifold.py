"""Boundary-manifold guards for tet meshes whose tets are being removed.

A tet mesh is boundary-manifold when every boundary edge lies in exactly two boundary faces
and every vertex's boundary star is one fan (method.md §9). Removing tets (a prune of §5,
the cleanup of §7) can break that in two ways, and this module holds both remedies:

- :func:`restore_until_manifold`: put removed tets back around the defects until the
  boundary is manifold again (the guard when the removed set is a choice, as in pruning);
- :func:`repair_manifold`: remove the minority fans around the defects (the repair of an
  input that was not manifold to begin with);
- :func:`restore_elsewhere`: take back restored tets that a view shows empty wherever
  putting back other removed tets instead keeps the boundary manifold and the topology;
- :func:`fill_sealed`: put back the removed tets that no longer connect to the outside
  (a sealed void, which no view can see). A guard that puts tets back (the manifold
  restoration, the dent and pit rules) can close the mouth of a removed region and seal
  what lies behind it, and removing an interior tet (cleanup's degenerate tets) opens a
  void with no mouth at all. Such a void is a second boundary shell: its faces count in
  every surface metric, and its genus in the sum over shells, while no image constrains it.
"""

from __future__ import annotations

import numpy as np

from holowarp.config import kept_components
from holowarp.tetmesh import TET_FACES, TetMesh

__all__ = ["restore_until_manifold", "repair_manifold", "vertex_to_tets", "fans", "open_to_outside", "fill_sealed"]


def vertex_to_tets(tets: np.ndarray, n: int):
    """CSR map vertex -> incident tets: (offsets (n+1,), tet ids)."""
    flat = tets.reshape(-1)
    order = np.argsort(flat, kind="stable")
    counts = np.bincount(flat, minlength=n)
    offs = np.zeros(n + 1, dtype=np.int64)
    np.cumsum(counts, out=offs[1:])
    return offs, order // 4


def fans(tets: np.ndarray, star: np.ndarray, pivot: tuple[int, ...]) -> list[np.ndarray]:
    """Group the tets of ``star`` (all containing the pivot vertices) into fans: two tets
    are in one fan when they share a face that contains every pivot vertex."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    m = len(star)
    faces = np.sort(tets[star][:, TET_FACES], axis=2).reshape(-1, 3)  # (4m, 3)
    owner = np.repeat(np.arange(m), 4)
    on_pivot = np.all([np.any(faces == p, axis=1) for p in pivot], axis=0)
    faces, owner = faces[on_pivot], owner[on_pivot]
    _, key = np.unique(faces, axis=0, return_inverse=True)
    key = key.reshape(-1)
    # Tets listing the same face key share that face: chain them in key order.
    order = np.argsort(key, kind="stable")
    same = key[order[1:]] == key[order[:-1]]
    a, b = owner[order[:-1]][same], owner[order[1:]][same]
    _, lab = connected_components(coo_matrix((np.ones(len(a)), (a, b)), shape=(m, m)), directed=False)
    return [star[lab == g] for g in np.unique(lab)]


def restore_until_manifold(
    vertices: np.ndarray, tets: np.ndarray, keep: np.ndarray, candidates: np.ndarray, *, max_rounds: int = 1000
) -> tuple[np.ndarray, int]:
    """Put removed tets back around non-manifold boundary edges and vertices until the
    boundary of the kept tets is a manifold.

    Each round finds the non-manifold edges and vertices of ``tets[keep]`` and restores
    every candidate tet that touches one of their vertices. Restoring every candidate
    gives back ``keep | candidates``, so the loop ends with a manifold boundary whenever
    that mesh has one.

    Args:
        vertices: (N, 3) float positions.
        tets: (M, 4) int vertex ids.
        keep: (M,) bool, the tets kept so far (not modified).
        candidates: (M,) bool, the removed tets that may be put back.
        max_rounds: safety cap on rounds.

    Returns:
        (keep, restored): the new (M,) bool mask and how many tets were put back.
    """
    keep = keep.copy()
    candidates = candidates & ~keep
    restored = 0
    for _ in range(max_rounds):
        sub = TetMesh(vertices, tets[keep], validate=False)
        bad = np.union1d(sub.non_manifold_edges().ravel(), sub.non_manifold_vertices())
        if len(bad) == 0:
            break
        back = candidates & np.isin(tets, bad).any(axis=1)
        if not back.any():
            break
        keep |= back
        candidates &= ~back
        restored += int(back.sum())
    return keep, restored


def restore_elsewhere(vertices: np.ndarray, tets: np.ndarray, keep: np.ndarray, seen: np.ndarray,
                      spare: np.ndarray) -> tuple[np.ndarray, int]:
    """Take back restored tets some view shows to be empty (``seen``) wherever restoring
    other removed tets (``spare``) mends the boundary instead.

    :func:`restore_until_manifold` puts back every removed tet at a non-manifold spot, those
    the images show empty among them. Where a prune leaves a corner of a hole pinched, they
    fill it: a web one or two tets thick across space every view sees through (the quality
    suite's plate kept one in a hole's corner, its Hausdorff point). Each face-connected
    group of ``keep & seen`` is taken out, and :func:`restore_until_manifold` restores
    from ``spare`` only (the prune passes the removed tets inside every silhouette); the
    group stays out when the kept set then has the same components, genus and boundary
    shells as before and a manifold boundary, and goes back otherwise.

    Args:
        vertices: (N, 3); tets: (M, 4); keep: (M,) bool kept tets, boundary-manifold (not
            modified); seen: (M,) bool tets that should rather go; spare: (M,) bool removed
            tets that may come back instead.
    Returns:
        (keep, taken): the new (M,) bool mask and how many ``seen`` tets went.
    """
    signature = lambda k: TetMesh(vertices, tets[k], validate=False).topology_signature()  # noqa: E731
    keep = keep.copy()
    ref = signature(keep)
    taken, gone_in_pass = 0, 1
    # A group that stays in one pass may go in the next, once a neighbour's swap changed
    # what it touches: passes until one takes nothing.
    while gone_in_pass:
        cand = keep & seen
        lab = np.full(len(tets), -1)
        lab[cand] = TetMesh(vertices, tets[cand], validate=False).components()[0]
        gone_in_pass = 0
        for grp in np.unique(lab[cand]):
            group = (lab == grp) & keep
            trial, _ = restore_until_manifold(vertices, tets, keep & ~group, spare & ~keep)
            gone = int((group & ~trial).sum())
            if gone and signature(trial) == ref:
                keep, gone_in_pass = trial, gone_in_pass + gone
        taken += gone_in_pass
    return keep, taken


def open_to_outside(removed: np.ndarray, adj: np.ndarray) -> np.ndarray:
    """The removed tets (M,) bool that connect, through faces shared with other removed
    tets, to a boundary face of the whole mesh: space a view can look into. The rest of
    ``removed`` are sealed voids.

    Args:
        removed: (M,) bool, the tets removed (or about to be) from a mesh of M tets.
        adj: (M, 4) face neighbours of that whole mesh (:meth:`TetMesh.face_adjacency`,
            -1 on its boundary).
    """
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    M = len(removed)
    if not removed.any():
        return removed.copy()
    rows = np.repeat(np.arange(M), 4)
    cols = adj.reshape(-1).astype(np.int64)
    both = (cols >= 0) & removed[rows] & removed[np.maximum(cols, 0)]
    g = coo_matrix((np.ones(int(both.sum())), (rows[both], cols[both])), shape=(M, M))
    _, lab = connected_components(g, directed=False)
    open_comp = np.zeros(lab.max() + 1, dtype=bool)
    open_comp[lab[removed & np.any(adj < 0, axis=1)]] = True
    return removed & open_comp[lab]


def fill_sealed(keep: np.ndarray, adj: np.ndarray) -> tuple[np.ndarray, int]:
    """Put back every removed tet (``~keep``) that :func:`open_to_outside` finds sealed.

    Filling a void removes its whole boundary shell and touches no other boundary face, so
    the kept set's components, manifoldness and outer surface are unchanged.

    Args:
        keep: (M,) bool kept tets (not modified); adj: (M, 4) face neighbours of all M tets.
    Returns:
        (keep, filled): the new (M,) bool mask and how many tets were put back.
    """
    removed = ~keep
    sealed = removed & ~open_to_outside(removed, adj)
    return keep | sealed, int(sealed.sum())


def repair_manifold(mesh: TetMesh, *, max_rounds: int = 50,
                    min_component: float | None = None) -> tuple[np.ndarray, dict]:
    """Remove the minority fans around non-manifold boundary edges and vertices until the
    boundary is manifold (see the module docstring).

    A removal that splits the mesh keeps its largest component (``min_component`` None, one
    object) or every component with at least that fraction of the tets (scene level,
    :func:`holowarp.config.kept_components`). Vertices are never renumbered here, so the
    result is a mask over ``mesh.tets``.

    Returns:
        (keep, info): keep (M,) bool over the input tets; info with ``removed_tets``,
        ``rounds`` and the final ``manifold`` flag.
    """
    keep = np.ones(mesh.num_tets, dtype=bool)
    vol = np.abs(mesh.signed_volumes())
    rounds = 0
    current = mesh
    for rounds in range(1, max_rounds + 1):
        bad_edges, bad_vertices = current.non_manifold_edges(), current.non_manifold_vertices()
        if len(bad_edges) == 0 and len(bad_vertices) == 0:
            rounds -= 1
            break
        ids = np.flatnonzero(keep)
        T = current.tets.astype(np.int64)
        offs, v2t = vertex_to_tets(T, current.num_vertices)
        drop = np.zeros(len(ids), dtype=bool)
        v = vol[ids]
        stars = [(sa := v2t[offs[a] : offs[a + 1]])[np.any(T[sa] == b, axis=1)] for a, b in bad_edges]
        pivots = [(int(a), int(b)) for a, b in bad_edges]
        stars += [v2t[offs[x] : offs[x + 1]] for x in bad_vertices]
        pivots += [(int(x),) for x in bad_vertices]
        for star, pivot in zip(stars, pivots):
            groups = fans(T, star, pivot)
            if len(groups) > 1:
                best = max(range(len(groups)), key=lambda i: v[groups[i]].sum())
                for i, f in enumerate(groups):
                    if i != best:
                        drop[f] = True
            elif len(pivot) == 1:
                # One fan of tets but several boundary fans: empty space touches the vertex
                # from separate sides (a cavity or tunnel pinching the surface). Removing
                # the vertex's star merges those gaps into one.
                drop[star] = True
        keep[ids[drop]] = False
        sub = TetMesh(mesh.vertices, mesh.tets[keep], validate=False)
        labels, n = sub.components()
        if n > 1:
            largest = kept_components(labels, n, min_component)
            keep[np.flatnonzero(keep)[~largest]] = False
            sub = TetMesh(mesh.vertices, mesh.tets[keep], validate=False)
        current = sub
    man = current.manifold()
    return keep, {"removed_tets": int((~keep).sum()), "rounds": rounds, "manifold": bool(man["manifold"])}
