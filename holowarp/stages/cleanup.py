"""Cleanup of the optimised tet mesh (method.md §7).

In order:

1. **flip**: tets whose signed volume is negative but whose geometry is fine (their
   |volume| is above the degeneracy threshold) are reordered (swap of two vertices), which
   makes them positive without moving anything;
2. **drop**: genuinely degenerate tets (|volume| below ``degenerate_rel`` times the median
   tet volume) are removed, and so are boundary "caps": tets with a boundary face whose
   minimum dihedral angle is below ``cap_dihedral_deg`` (four nearly coplanar surface
   vertices, flattened while the surface was fitted). Caps hold almost no volume, so the
   surface barely moves, while their near-singular deformation gradients would stiffen or
   destabilise an FEM solve; removal repeats while newly exposed caps appear;
3. **cap restoration**: dropping a cap can pinch the boundary (two fans of tets meeting at
   an edge or a vertex that the cap used to join). The dropped caps around every
   non-manifold edge or vertex are put back, repeatedly, until the boundary is manifold
   again. Putting back every cap gives back the input, so this ends with a manifold
   boundary whenever the input had one, and it costs a few slivers instead of the deep
   pits that removing whole fans digs (measured on bob: Chamfer-L1 of a pitted run
   0.0041 → 0.0037, at the level of the mesh before cleanup);
4. **components**: only the largest face-connected component is kept;
5. **manifold repair** (only for inputs that were not manifold to begin with): where the
   boundary is not a manifold (an edge in more than two boundary faces, or a vertex whose
   boundary star is several fans), the tets around that edge/vertex are grouped into fans
   connected through faces containing it, and all but the largest fan are removed; a vertex
   whose tets form one fan while empty space reaches it from separate sides loses its
   whole star; repeated until the boundary is manifold;
6. unused vertices are removed.

Every count is reported, so a user sees exactly what cleanup changed.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from holowarp.tetmesh import TET_FACES, TetMesh

__all__ = ["CleanupConfig", "cleanup", "repair_manifold", "restore_until_manifold"]


@dataclass(frozen=True)
class CleanupConfig:
    """Settings of §7 cleanup.

    Attributes:
        degenerate_rel: a tet is degenerate when |volume| < degenerate_rel * median |volume|.
        cap_dihedral_deg: boundary tets with a smaller minimum dihedral angle are dropped.
        max_cap_rounds: passes of cap removal.
        max_repair_rounds: cap on manifold-repair rounds (each round fixes every defect found).
    """

    degenerate_rel: float = 1e-3
    cap_dihedral_deg: float = 5.0
    max_cap_rounds: int = 5
    max_repair_rounds: int = 50


def _vertex_to_tets(tets: np.ndarray, n: int):
    """CSR map vertex -> incident tets: (offsets (n+1,), tet ids)."""
    flat = tets.reshape(-1)
    order = np.argsort(flat, kind="stable")
    counts = np.bincount(flat, minlength=n)
    offs = np.zeros(n + 1, dtype=np.int64)
    np.cumsum(counts, out=offs[1:])
    return offs, order // 4


def _fans(tets: np.ndarray, star: np.ndarray, pivot: tuple[int, ...]) -> list[np.ndarray]:
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


def repair_manifold(mesh: TetMesh, *, max_rounds: int = 50) -> tuple[np.ndarray, dict]:
    """Remove the minority fans around non-manifold boundary edges and vertices until the
    boundary is manifold (see the module docstring).

    Vertices are never renumbered here, so the result is a mask over ``mesh.tets``.

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
        offs, v2t = _vertex_to_tets(T, current.num_vertices)
        drop = np.zeros(len(ids), dtype=bool)
        v = vol[ids]
        stars = [(sa := v2t[offs[a] : offs[a + 1]])[np.any(T[sa] == b, axis=1)] for a, b in bad_edges]
        pivots = [(int(a), int(b)) for a, b in bad_edges]
        stars += [v2t[offs[x] : offs[x + 1]] for x in bad_vertices]
        pivots += [(int(x),) for x in bad_vertices]
        for star, pivot in zip(stars, pivots):
            fans = _fans(T, star, pivot)
            if len(fans) > 1:
                best = max(range(len(fans)), key=lambda i: v[fans[i]].sum())
                for i, f in enumerate(fans):
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
            largest = labels == np.argmax(np.bincount(labels))
            keep[np.flatnonzero(keep)[~largest]] = False
            sub = TetMesh(mesh.vertices, mesh.tets[keep], validate=False)
        current = sub
    man = current.manifold()
    return keep, {"removed_tets": int((~keep).sum()), "rounds": rounds, "manifold": bool(man["manifold"])}


def cleanup(mesh: TetMesh, config: CleanupConfig = CleanupConfig()) -> tuple[TetMesh, np.ndarray, dict]:
    """Run the §7 cleanup.

    Returns:
        (mesh, kept, info): the clean mesh (unused vertices removed), ``kept`` (K,) int64
        the indices of its tets in the input (tet i of the output is input tet kept[i],
        possibly with two vertices swapped), and a report of every count:
        ``inverted_before_cleanup`` (signed volume <= 0 on entry), ``flipped``, ``dropped``
        (degenerate), ``dropped_caps`` (boundary slivers, net of those put back),
        ``caps_restored_for_manifold``, ``components_before``, ``components_removed``,
        ``tets_removed_by_component``, ``tets_removed_for_manifold``, ``manifold``,
        ``components``, ``inverted_after_cleanup``, ``tets_before``, ``tets_after``.
    """
    if mesh.num_tets == 0:
        raise ValueError("cleanup: the mesh has no tetrahedra")
    info = {"tets_before": mesh.num_tets}
    vol = mesh.signed_volumes()
    info["inverted_before_cleanup"] = int(np.count_nonzero(vol <= 0))
    thresh = config.degenerate_rel * float(np.median(np.abs(vol)))
    degenerate = np.abs(vol) < thresh
    flip = (vol < 0) & ~degenerate
    t = mesh.tets.copy()
    t[flip, 2], t[flip, 3] = mesh.tets[flip, 3], mesh.tets[flip, 2]
    info["flipped"] = int(flip.sum())
    keep = ~degenerate
    for _ in range(config.max_cap_rounds):
        ids = np.flatnonzero(keep)
        work = TetMesh(mesh.vertices, t[ids], validate=False)
        on_boundary = np.zeros(work.num_tets, dtype=bool)
        on_boundary[work.boundary_face_tets()] = True
        cap = on_boundary & (work.quality()["min_dihedral_deg"] < config.cap_dihedral_deg)
        if not cap.any() or cap.all():
            break
        keep[ids[cap]] = False
    capped = ~keep & ~degenerate
    keep, restored = restore_until_manifold(mesh.vertices, t, keep, capped)
    caps = int(capped.sum()) - restored
    info["dropped"] = int(degenerate.sum()) + caps
    info["dropped_caps"] = caps
    info["caps_restored_for_manifold"] = restored
    kept = np.flatnonzero(keep)
    work = TetMesh(mesh.vertices, t[kept], validate=False)
    labels, n = work.components()
    info["components_before"] = n
    info["components_removed"] = max(n - 1, 0)
    if n > 1:
        largest = labels == np.argmax(np.bincount(labels))
        info["tets_removed_by_component"] = int((~largest).sum())
        kept = kept[largest]
        work = TetMesh(mesh.vertices, t[kept], validate=False)
    else:
        info["tets_removed_by_component"] = 0
    keep, rep = repair_manifold(work, max_rounds=config.max_repair_rounds)
    kept = kept[keep]
    info["tets_removed_for_manifold"] = rep["removed_tets"]
    out, _ = TetMesh(mesh.vertices, t[kept], validate=False).remove_unused_vertices()
    info["manifold"] = rep["manifold"]
    info["components"] = out.num_components()
    info["inverted_after_cleanup"] = int(np.count_nonzero(out.signed_volumes() <= 0))
    info["tets_after"] = out.num_tets
    return out, kept.astype(np.int64), info
