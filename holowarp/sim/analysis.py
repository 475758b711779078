"""Measurements on simulated tet meshes: centre of mass, volume, inverted tets, and whether
face-connected pieces held together.
"""

from __future__ import annotations

import numpy as np

from holowarp.tetmesh import TetMesh

__all__ = ["center_of_mass", "pieces_apart", "SEPARATION_FRACTION"]

#: Two pieces count as moved apart when their initial contact opened (or slid) by more than
#: this fraction of the object's rest bounding-box diagonal.
SEPARATION_FRACTION = 0.05


def center_of_mass(positions, masses) -> np.ndarray:
    """Mass-weighted mean (3,) of ``positions`` (N, 3) with ``masses`` (N,)."""
    m = np.asarray(masses, dtype=np.float64)
    return (np.asarray(positions, dtype=np.float64) * m[:, None]).sum(0) / m.sum()


def pieces_apart(mesh: TetMesh, end_positions, *, separation: float | None = None,
                 contact_tol: float | None = None) -> tuple[int, dict]:
    """How many groups the mesh's face-connected pieces form at the end of a simulation.

    Definition (``components_end`` of the simulation report):

    1. The pieces are the face-connected components of ``mesh`` (its rest shape is
       ``mesh.vertices``).
    2. Two pieces are in contact at rest through their *interface pairs*: boundary vertices
       of one and of the other closer than ``contact_tol`` (default: half the median
       boundary edge length), e.g. the coincident vertices of two blocks that touch.
    3. At the end they still hold together if the median end distance of their interface
       pairs is at most ``separation`` (default: :data:`SEPARATION_FRACTION` of the rest
       bounding-box diagonal); otherwise their shared contact opened or slid: they moved
       apart. Pieces without interface pairs never hold together.
    4. The result is the number of groups of pieces that hold together (union of the
       pairwise relation). A single connected mesh gives 1.

    Args:
        mesh: the rest mesh.
        end_positions: (N, 3) positions at the end.

    Returns:
        (groups, info) with ``info = {"pieces": k, "joined_pairs": [...], "opened_pairs": [...]}``.
    """
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components
    from scipy.spatial import cKDTree

    labels, k = mesh.components()
    info = {"pieces": int(k), "joined_pairs": [], "opened_pairs": []}
    if k <= 1:
        return int(k), info
    X = mesh.vertices
    Y = np.asarray(end_positions, dtype=np.float64)
    bf = mesh.boundary_faces()
    if contact_tol is None:
        e = np.concatenate([bf[:, [0, 1]], bf[:, [1, 2]], bf[:, [2, 0]]])
        contact_tol = 0.5 * float(np.median(np.linalg.norm(X[e[:, 0]] - X[e[:, 1]], axis=1)))
    if separation is None:
        separation = SEPARATION_FRACTION * float(np.linalg.norm(np.ptp(X, axis=0)))
    # Piece of each boundary vertex (a vertex belongs to one face-connected piece unless
    # pieces share it; then take the piece of its first boundary face).
    vpiece = np.full(len(X), -1, dtype=np.int64)
    owner = labels[mesh.boundary_face_tets()]
    vpiece[bf.reshape(-1)] = np.repeat(owner, 3)
    sv = np.flatnonzero(vpiece >= 0)
    tree = cKDTree(X[sv])
    pairs = tree.query_pairs(contact_tol, output_type="ndarray")  # [P, 2] into sv
    joined = []
    if len(pairs):
        i, j = sv[pairs[:, 0]], sv[pairs[:, 1]]
        pa, pb = vpiece[i], vpiece[j]
        cross = pa != pb
        i, j, pa, pb = i[cross], j[cross], pa[cross], pb[cross]
        lo, hi = np.minimum(pa, pb), np.maximum(pa, pb)
        d_end = np.linalg.norm(Y[i] - Y[j], axis=1)
        for a, b in set(zip(lo.tolist(), hi.tolist())):
            sel = (lo == a) & (hi == b)
            med = float(np.median(d_end[sel]))
            rec = {"pieces": [a, b], "interface_pairs": int(sel.sum()), "median_end_distance": med}
            if med <= separation:
                info["joined_pairs"].append(rec)
                joined.append((a, b))
            else:
                info["opened_pairs"].append(rec)
    a, b = np.array(joined, dtype=np.int64).reshape(-1, 2).T
    groups = int(connected_components(coo_matrix((np.ones(len(a)), (a, b)), shape=(k, k)), directed=False)[0])
    info["separation"] = separation
    info["contact_tol"] = contact_tol
    return groups, info
