"""Cleanup of the optimised tet mesh (method.md §7).

In order:

1. **flip**: tets whose signed volume is negative but whose geometry is fine (their
   |volume| is above the degeneracy threshold) are reordered (swap of two vertices), which
   makes them positive without moving anything;
2. **drop**: genuinely degenerate tets (|volume| below ``degenerate_rel`` times the median
   tet volume) are removed;
3. **components**: only the largest face-connected component is kept;
4. **manifold repair**: where the boundary is not a manifold (an edge in more than two
   boundary faces, or a vertex whose boundary star is several fans), the tets around that
   edge/vertex are grouped into fans connected through faces containing it, and all but the
   largest fan are removed; repeated until the boundary is manifold;
5. unused vertices are removed.

Every count is reported, so a user sees exactly what cleanup changed.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from holowarp.tetmesh import TetMesh

__all__ = ["CleanupConfig", "cleanup", "repair_manifold"]


@dataclass(frozen=True)
class CleanupConfig:
    """Settings of §7 cleanup.

    Attributes:
        degenerate_rel: a tet is degenerate when |volume| < degenerate_rel * median |volume|.
        max_repair_rounds: cap on manifold-repair rounds (each round fixes every defect found).
    """

    degenerate_rel: float = 1e-3
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
    m = len(star)
    parent = list(range(m))

    def find(a):
        while parent[a] != a:
            parent[a] = parent[parent[a]]
            a = parent[a]
        return a

    sets = [set(tets[t].tolist()) for t in star]
    piv = set(pivot)
    for i in range(m):
        for j in range(i + 1, m):
            shared = sets[i] & sets[j]
            if len(shared) == 3 and piv <= shared:
                parent[find(i)] = find(j)
    groups: dict[int, list[int]] = {}
    for i in range(m):
        groups.setdefault(find(i), []).append(int(star[i]))
    return [np.array(g) for g in groups.values()]


def repair_manifold(mesh: TetMesh, *, max_rounds: int = 50) -> tuple[TetMesh, dict]:
    """Remove the minority fans around non-manifold boundary edges and vertices until the
    boundary is manifold (see the module docstring).

    Returns:
        (mesh, info) with ``removed_tets``, ``rounds`` and the final ``manifold`` flag.
    """
    removed = 0
    rounds = 0
    for rounds in range(1, max_rounds + 1):
        bad_edges, bad_vertices = mesh.non_manifold_edges(), mesh.non_manifold_vertices()
        if len(bad_edges) == 0 and len(bad_vertices) == 0:
            rounds -= 1
            break
        T = mesh.tets.astype(np.int64)
        offs, v2t = _vertex_to_tets(T, mesh.num_vertices)
        drop = np.zeros(mesh.num_tets, dtype=bool)
        vol = np.abs(mesh.signed_volumes())
        for a, b in bad_edges:
            sa = v2t[offs[a] : offs[a + 1]]
            star = sa[np.any(T[sa] == b, axis=1)]
            fans = _fans(T, star, (int(a), int(b)))
            if len(fans) > 1:
                keep = max(range(len(fans)), key=lambda i: vol[fans[i]].sum())
                for i, f in enumerate(fans):
                    if i != keep:
                        drop[f] = True
        for v in bad_vertices:
            star = v2t[offs[v] : offs[v + 1]]
            fans = _fans(T, star, (int(v),))
            if len(fans) > 1:
                keep = max(range(len(fans)), key=lambda i: vol[fans[i]].sum())
                for i, f in enumerate(fans):
                    if i != keep:
                        drop[f] = True
        if not drop.any():
            # A defect not resolvable by fans (e.g. an edge whose star is one fan but the
            # boundary still pinches): remove the smallest tet touching it.
            cand = np.unique(
                np.concatenate([v2t[offs[v] : offs[v + 1]] for v in np.unique(np.r_[bad_edges.ravel(), bad_vertices])])
            )
            drop[cand[np.argmin(vol[cand])]] = True
        removed += int(drop.sum())
        mesh = mesh.submesh(~drop)
        mesh, _ = mesh.keep_largest_component()
    man = mesh.manifold()
    return mesh, {"removed_tets": removed, "rounds": rounds, "manifold": bool(man["manifold"])}


def cleanup(mesh: TetMesh, config: CleanupConfig = CleanupConfig()) -> tuple[TetMesh, dict]:
    """Run the §7 cleanup; returns the clean mesh and a report of every count.

    Report keys: ``inverted_before_cleanup`` (tets with signed volume <= 0 on entry),
    ``flipped``, ``dropped`` (degenerate), ``components_before``, ``components_removed``,
    ``tets_removed_by_component``, ``tets_removed_for_manifold``, ``manifold``,
    ``tets_before``, ``tets_after``.
    """
    info = {"tets_before": mesh.num_tets}
    vol = mesh.signed_volumes()
    info["inverted_before_cleanup"] = int(np.count_nonzero(vol <= 0))
    if mesh.num_tets == 0:
        raise ValueError("cleanup: the mesh has no tetrahedra")
    thresh = config.degenerate_rel * float(np.median(np.abs(vol)))
    degenerate = np.abs(vol) < thresh
    flip = (vol < 0) & ~degenerate
    t = mesh.tets.copy()
    t[flip, 2], t[flip, 3] = mesh.tets[flip, 3], mesh.tets[flip, 2]
    info["flipped"] = int(flip.sum())
    info["dropped"] = int(degenerate.sum())
    mesh = TetMesh(mesh.vertices, t[~degenerate], validate=False)
    mesh, comp = mesh.keep_largest_component()
    info["components_before"] = comp["components"]
    info["components_removed"] = comp["removed_components"]
    info["tets_removed_by_component"] = comp["removed_tets"]
    mesh, rep = repair_manifold(mesh, max_rounds=config.max_repair_rounds)
    info["tets_removed_for_manifold"] = rep["removed_tets"]
    mesh, _ = mesh.remove_unused_vertices()
    info["manifold"] = rep["manifold"]
    info["components"] = mesh.num_components()
    info["inverted_after_cleanup"] = int(np.count_nonzero(mesh.signed_volumes() <= 0))
    info["tets_after"] = mesh.num_tets
    return mesh, info
