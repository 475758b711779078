"""The tetrahedral mesh core: orientation, boundary, adjacency, components, manifoldness,
topology and element quality.

Conventions (method.md §1):

- ``vertices`` (N, 3) float64, metres; ``tets`` (M, 4) int32.
- A tet ``(a, b, c, d)`` is positively oriented when ``det[b-a, c-a, d-a] / 6 > 0``.
- Boundary faces are the faces used by exactly one tet, wound so that their normal
  ``(v1 - v0) x (v2 - v0)`` points out of that tet.
- Local face ``k`` of a tet is the face opposite its local vertex ``k``; for a positively
  oriented tet the outward windings are ``TET_FACES[k]``.

Everything is vectorised NumPy (sorting-based hashing, ``scipy.sparse.csgraph``): a
million tets takes seconds (``python -m holowarp.bench tetmesh``). Derived structures are
cached on the (immutable) mesh; operations that change the mesh return a new ``TetMesh``.

Example:
    >>> import numpy as np
    >>> from holowarp import TetMesh
    >>> m = TetMesh([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], [[0, 1, 2, 3]])
    >>> m.boundary_faces().shape
    (4, 3)
"""

from __future__ import annotations

import functools
import math

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components

from holowarp.errors import InputError

__all__ = [
    "TET_FACES",
    "TET_EDGES",
    "TET_EDGE_FACES",
    "TetMesh",
    "TetMeshError",
    "tetrahedralize_surface",
    "decimate_surface",
]

#: Outward-wound local faces of a positively oriented tet; row k is the face opposite vertex k.
TET_FACES = np.array([[1, 2, 3], [0, 3, 2], [0, 1, 3], [0, 2, 1]], dtype=np.int64)

#: The six local edges of a tet, and for each the local pair of faces that meet along it
#: (the faces opposite the two vertices NOT on the edge).
TET_EDGES = np.array([[0, 1], [0, 2], [0, 3], [1, 2], [1, 3], [2, 3]], dtype=np.int64)
TET_EDGE_FACES = np.array([[2, 3], [1, 3], [1, 2], [0, 3], [0, 2], [0, 1]], dtype=np.int64)

class TetMeshError(InputError):
    """Invalid tetrahedral mesh data (shapes, indices, non-finite coordinates)."""


def _row_keys(rows: np.ndarray, n: int) -> np.ndarray:
    """Collision-free int64 keys for rows of sorted vertex indices < n (2 or 3 columns).

    Falls back to a lexicographic rank when n is too large for a packed key.
    """
    rows = rows.astype(np.int64, copy=False)
    k = rows.shape[1]
    if n ** k < 2**62:
        key = rows[:, 0].copy()
        for j in range(1, k):
            key *= n
            key += rows[:, j]
        return key
    # Rank rows lexicographically: equal rows get equal ranks.
    order = np.lexsort(rows.T[::-1])
    srt = rows[order]
    new = np.empty(len(rows), dtype=bool)
    new[0] = True
    new[1:] = np.any(srt[1:] != srt[:-1], axis=1)
    rank = np.empty(len(rows), dtype=np.int64)
    rank[order] = np.cumsum(new) - 1
    return rank


class TetMesh:
    """An immutable tetrahedral mesh.

    Args:
        vertices: (N, 3) coordinates in metres; stored as float64.
        tets: (M, 4) vertex indices; stored as int32.
        validate: check shapes, finiteness, index range and repeated indices (cheap, on by
            default). Orientation is NOT changed here: use :meth:`oriented`.

    Raises:
        TetMeshError: with the reason, when ``validate`` finds a problem.
    """

    __slots__ = ("vertices", "tets", "__dict__")

    def __init__(self, vertices, tets, *, validate: bool = True):
        v = np.asarray(vertices, dtype=np.float64)
        t = np.asarray(tets)
        if validate:
            if v.ndim != 2 or v.shape[1] != 3:
                raise TetMeshError(f"vertices must have shape (N, 3), got {v.shape}")
            if t.ndim != 2 or t.shape[1] != 4:
                if t.size == 0:
                    t = t.reshape(0, 4)
                else:
                    raise TetMeshError(f"tets must have shape (M, 4), got {t.shape}")
            if t.size and not np.issubdtype(t.dtype, np.integer):
                if not np.all(np.mod(t, 1) == 0):
                    raise TetMeshError("tets must hold integer vertex indices")
            if not np.all(np.isfinite(v)):
                rows = np.flatnonzero(~np.isfinite(v).all(axis=1))
                raise TetMeshError(f"{len(rows)} vertices have non-finite coordinates (first: vertex {int(rows[0])} = "
                                   f"{v[rows[0]].tolist()})")
            if t.size:
                lo, hi = int(t.min()), int(t.max())
                if lo < 0 or hi >= len(v):
                    raise TetMeshError(
                        f"tet indices must lie in [0, {len(v) - 1}], found range [{lo}, {hi}]"
                    )
                s = np.sort(t, axis=1)
                rep = np.any(s[:, 1:] == s[:, :-1], axis=1)
                if rep.any():
                    raise TetMeshError(
                        f"{int(rep.sum())} tets repeat a vertex index (first: tet "
                        f"{int(np.argmax(rep))} = {t[np.argmax(rep)].tolist()})"
                    )
        self.vertices = np.ascontiguousarray(v)  # [N, 3]
        self.tets = np.ascontiguousarray(t, dtype=np.int32).reshape(-1, 4)  # [M, 4]
        self.vertices.setflags(write=False)
        self.tets.setflags(write=False)

    # ------------------------------------------------------------------ basics
    @property
    def num_vertices(self) -> int:
        return int(self.vertices.shape[0])

    @property
    def num_tets(self) -> int:
        return int(self.tets.shape[0])

    def __repr__(self) -> str:
        return f"TetMesh(vertices={self.num_vertices}, tets={self.num_tets})"

    def with_vertices(self, vertices) -> "TetMesh":
        """Same connectivity, new positions (N, 3). Skips the index checks."""
        v = np.asarray(vertices, dtype=np.float64)
        if v.shape != self.vertices.shape:
            raise TetMeshError(f"with_vertices: expected {self.vertices.shape}, got {v.shape}")
        return TetMesh(v, self.tets, validate=False)

    def _corners(self):
        T = self.tets
        V = self.vertices
        return V[T[:, 0]], V[T[:, 1]], V[T[:, 2]], V[T[:, 3]]

    @functools.cached_property
    def _signed_volumes(self) -> np.ndarray:
        a, b, c, d = self._corners()
        vol = np.einsum("ij,ij->i", b - a, np.cross(c - a, d - a)) / 6.0
        vol.setflags(write=False)
        return vol

    def signed_volumes(self) -> np.ndarray:
        """Signed volumes (M,) in m³: ``det[b-a, c-a, d-a] / 6``."""
        return self._signed_volumes

    def volume(self) -> float:
        """Total signed volume in m³."""
        return float(self._signed_volumes.sum())

    def oriented(self) -> tuple["TetMesh", int]:
        """Reorder inverted tets (swap local vertices 2 and 3) so every volume is >= 0.

        Tets with exactly zero volume are degenerate, not inverted, and are left alone.

        Returns:
            (mesh, n_flipped): the reoriented mesh and how many tets were flipped.
        """
        neg = self._signed_volumes < 0
        n = int(neg.sum())
        if n == 0:
            return self, 0
        t = self.tets.copy()
        t[neg, 2], t[neg, 3] = self.tets[neg, 3], self.tets[neg, 2]
        return TetMesh(self.vertices, t, validate=False), n

    # ------------------------------------------------------------------ faces
    @functools.cached_property
    def _face_table(self):
        """All 4M local faces: sorted keys, owner tets, local ids, and pairing info."""
        M = self.num_tets
        faces = self.tets[:, TET_FACES].reshape(-1, 3).astype(np.int64)  # [4M, 3]
        keys = _row_keys(np.sort(faces, axis=1), max(self.num_vertices, 1))
        order = np.argsort(keys, kind="stable")
        sk = keys[order]
        start = np.ones(len(sk), dtype=bool)
        if len(sk):
            start[1:] = sk[1:] != sk[:-1]
        group = np.cumsum(start) - 1  # group id in sorted order
        counts = np.bincount(group) if len(sk) else np.zeros(0, np.int64)
        count_of = np.empty(4 * M, dtype=np.int64)
        count_of[order] = counts[group]
        return faces, order, group, counts, count_of

    def boundary_mask(self) -> np.ndarray:
        """(M, 4) bool: local face k of tet e is a boundary face (used by exactly one tet)."""
        return (self._face_table[4] == 1).reshape(-1, 4)

    @functools.cached_property
    def _boundary(self):
        faces, _, _, _, count_of = self._face_table
        sel = np.flatnonzero(count_of == 1)
        bf = faces[sel].astype(np.int32)
        owner = sel // 4
        # Winding follows the tet's own orientation: for an inverted tet, flip the face so
        # it still points out of the tet's actual volume.
        inv = self._signed_volumes[owner] < 0
        if inv.any():
            bf[inv] = bf[inv][:, [0, 2, 1]]
        bf.setflags(write=False)
        owner.setflags(write=False)
        return bf, owner

    def boundary_faces(self) -> np.ndarray:
        """Boundary triangles (F, 3) int32, wound outward (normal points out of the owner)."""
        return self._boundary[0]

    def boundary_face_tets(self) -> np.ndarray:
        """Owning tet (F,) int64 of each boundary face, aligned with :meth:`boundary_faces`."""
        return self._boundary[1]

    def surface_vertices(self) -> np.ndarray:
        """Sorted unique ids (S,) int64 of the vertices on boundary faces."""
        return np.unique(self.boundary_faces()).astype(np.int64)

    def surface_mesh(self) -> tuple[np.ndarray, np.ndarray]:
        """The boundary as a compact triangle mesh: vertices (S, 3) float64, faces (F, 3) int32."""
        bf = self.boundary_faces()
        used, inv = np.unique(bf, return_inverse=True)
        return self.vertices[used], inv.reshape(-1, 3).astype(np.int32)

    def non_manifold_faces(self) -> int:
        """Number of distinct faces shared by more than two tets (0 for a valid mesh)."""
        counts = self._face_table[3]
        return int(np.count_nonzero(counts > 2))

    # ------------------------------------------------------------------ edges
    @functools.cached_property
    def _edges(self) -> np.ndarray:
        e = np.sort(self.tets[:, TET_EDGES].reshape(-1, 2), axis=1).astype(np.int64)
        keys = _row_keys(e, max(self.num_vertices, 1))
        _, idx = np.unique(keys, return_index=True)
        out = e[idx].astype(np.int32)
        out.setflags(write=False)
        return out

    def edges(self) -> np.ndarray:
        """Unique undirected edges (E, 2) int32 with ``i < j``, sorted."""
        return self._edges

    # ------------------------------------------------------------------ adjacency
    @functools.cached_property
    def _face_adjacency(self) -> np.ndarray:
        M = self.num_tets
        _, order, group, counts, _ = self._face_table
        adj = np.full(4 * M, -1, dtype=np.int64)
        # Interior faces appear exactly twice, consecutively in sorted order.
        pair_start = np.flatnonzero((counts[group] == 2) & np.r_[True, group[1:] != group[:-1]])
        a = order[pair_start]
        b = order[pair_start + 1]
        adj[a] = b // 4
        adj[b] = a // 4
        out = adj.reshape(M, 4).astype(np.int32)
        out.setflags(write=False)
        return out

    def face_adjacency(self) -> np.ndarray:
        """(M, 4) int32: ``[e, k]`` is the tet sharing the face opposite local vertex k of
        tet e, or -1 when that face is on the boundary (or shared by more than two tets)."""
        return self._face_adjacency

    def adjacency_matrix(self) -> sp.csr_matrix:
        """Symmetric (M, M) 0/1 CSR matrix of face-adjacent tet pairs."""
        M = self.num_tets
        adj = self._face_adjacency
        rows = np.repeat(np.arange(M), 4)
        cols = adj.reshape(-1)
        keep = cols >= 0
        return sp.csr_matrix(
            (np.ones(int(keep.sum())), (rows[keep], cols[keep])), shape=(M, M)
        )

    def adjacency_laplacian(self) -> sp.csr_matrix:
        """Tet face-adjacency graph Laplacian (M, M) float64 (method.md §6):
        ``L[e, e]`` = number of face neighbours of e, ``L[e, e'] = -1`` for face neighbours.
        Rows sum to zero, so a constant per-tet field (a rigid motion's F) maps to zero."""
        A = self.adjacency_matrix()
        deg = np.asarray(A.sum(axis=1)).ravel()
        return (sp.diags(deg) - A).tocsr()

    # ------------------------------------------------------------------ components
    @functools.cached_property
    def _components(self):
        if self.num_tets == 0:
            return np.zeros(0, np.int64), 0
        n, labels = connected_components(self.adjacency_matrix(), directed=False)
        return labels.astype(np.int64), int(n)

    def components(self) -> tuple[np.ndarray, int]:
        """Face-connected components: labels (M,) int64 and their count."""
        return self._components

    def num_components(self) -> int:
        return self._components[1]

    def submesh(self, select) -> "TetMesh":
        """The mesh made of the selected tets (bool mask (M,) or indices), vertices compacted."""
        t = self.tets[np.asarray(select)]
        used, inv = np.unique(t, return_inverse=True)
        return TetMesh(self.vertices[used], inv.reshape(-1, 4), validate=False)

    def keep_largest_component(self) -> tuple["TetMesh", dict]:
        """Keep the face-connected component with the most tets.

        Returns:
            (mesh, info) with ``info = {"components": n_before, "removed_tets": k,
            "removed_components": n_before - 1}``. Unused vertices are removed.
        """
        labels, n = self._components
        if n <= 1:
            m, _ = self.remove_unused_vertices()
            return m, {"components": n, "removed_tets": 0, "removed_components": 0}
        sizes = np.bincount(labels, minlength=n)
        keep = labels == int(np.argmax(sizes))
        return self.submesh(keep), {
            "components": n,
            "removed_tets": int((~keep).sum()),
            "removed_components": n - 1,
        }

    def remove_unused_vertices(self) -> tuple["TetMesh", np.ndarray]:
        """Drop vertices no tet uses.

        Returns:
            (mesh, old_to_new): ``old_to_new`` (N,) int64 maps old ids to new ones, -1 for
            removed vertices.
        """
        used = np.zeros(self.num_vertices, dtype=bool)
        used[self.tets.reshape(-1)] = True
        old_to_new = np.full(self.num_vertices, -1, dtype=np.int64)
        old_to_new[used] = np.arange(int(used.sum()))
        if used.all():
            return self, old_to_new
        return TetMesh(self.vertices[used], old_to_new[self.tets], validate=False), old_to_new

    # ------------------------------------------------------------------ topology
    @functools.cached_property
    def _boundary_edges(self):
        """Boundary half-edges grouped into undirected edges: (edges (Eb,2), counts (Eb,))."""
        bf = self.boundary_faces().astype(np.int64)
        if len(bf) == 0:
            return np.zeros((0, 2), np.int64), np.zeros(0, np.int64)
        he = np.stack([bf[:, [0, 1]], bf[:, [1, 2]], bf[:, [2, 0]]], axis=1).reshape(-1, 2)
        keys = _row_keys(np.sort(he, axis=1), max(self.num_vertices, 1))
        uk, idx, counts = np.unique(keys, return_index=True, return_counts=True)
        return np.sort(he[idx], axis=1), counts

    def non_manifold_edges(self) -> np.ndarray:
        """Boundary edges (K, 2) int64 that lie in a number of boundary faces other than two."""
        edges, counts = self._boundary_edges
        return edges[counts != 2]

    def non_manifold_vertices(self) -> np.ndarray:
        """Boundary vertices (K,) int64 whose boundary faces form more than one fan, i.e.
        whose link in the boundary surface has several connected components."""
        bf = self.boundary_faces().astype(np.int64)
        if len(bf) == 0:
            return np.zeros(0, np.int64)
        n = max(self.num_vertices, 1)
        # Link of vertex v in face (v, u, w) is the edge u-w. Nodes of the link graph are
        # (v, u) pairs; the number of link components per v must be 1.
        centre = bf.reshape(-1)  # [3F]
        u = bf[:, [1, 2, 0]].reshape(-1)
        w = bf[:, [2, 0, 1]].reshape(-1)
        nodes, inv = np.unique(np.concatenate([centre * n + u, centre * n + w]), return_inverse=True)
        k = len(centre)
        g = sp.coo_matrix((np.ones(k), (inv[:k], inv[k:])), shape=(len(nodes), len(nodes)))
        _, lab = connected_components(g, directed=False)
        pairs = np.unique(np.stack([nodes // n, lab], axis=1), axis=0)
        per_vertex = np.bincount(pairs[:, 0], minlength=self.num_vertices)
        return np.flatnonzero(per_vertex > 1)

    def manifold(self) -> dict:
        """Boundary manifoldness (method.md §9).

        - edge-manifold: every boundary edge lies in exactly two boundary faces;
        - vertex-manifold: around every boundary vertex the boundary faces form ONE fan
          (its link is a single cycle), so no two surface sheets touch at a vertex.

        Returns:
            dict with ``manifold``, ``edge_manifold``, ``vertex_manifold`` (bools),
            ``bad_edges`` and ``bad_vertices`` (counts), ``non_manifold_faces`` (faces in
            more than two tets).
        """
        bad_edges = len(self.non_manifold_edges())
        bad_vertices = len(self.non_manifold_vertices())
        nmf = self.non_manifold_faces()
        return {
            "manifold": bad_edges == 0 and bad_vertices == 0 and nmf == 0,
            "edge_manifold": bad_edges == 0,
            "vertex_manifold": bad_vertices == 0,
            "bad_edges": bad_edges,
            "bad_vertices": bad_vertices,
            "non_manifold_faces": nmf,
        }

    def topology_signature(self) -> tuple[int, int, int, bool]:
        """``(components, genus, boundary shells, manifold boundary)``: what the guards that
        edit a mesh (the prune's swap, the element improvement) must leave as it was."""
        return self.num_components(), self.genus(), self.boundary_shells(), bool(self.manifold()["manifold"])

    def boundary_shells(self) -> int:
        """Number of connected pieces of the boundary surface (via shared vertices)."""
        bf = self.boundary_faces().astype(np.int64)
        if len(bf) == 0:
            return 0
        used, inv = np.unique(bf, return_inverse=True)
        inv = inv.reshape(-1, 3)
        r = np.concatenate([inv[:, 0], inv[:, 1]])
        c = np.concatenate([inv[:, 1], inv[:, 2]])
        g = sp.coo_matrix((np.ones(len(r)), (r, c)), shape=(len(used), len(used)))
        return int(connected_components(g, directed=False)[0])

    def euler_characteristic(self) -> int:
        """Euler characteristic V - E + F of the boundary surface."""
        bf = self.boundary_faces()
        edges, _ = self._boundary_edges
        return int(len(np.unique(bf)) - len(edges) + len(bf))

    def genus(self) -> int:
        """Total genus of the boundary surface: ``sum_shells (2 - chi_s) / 2``
        = ``(2 * shells - chi) / 2``. A ball gives 0, a solid torus 1. Meaningful for a
        closed, edge-manifold boundary."""
        shells = self.boundary_shells()
        return int(round((2 * shells - self.euler_characteristic()) / 2))

    # ------------------------------------------------------------------ quality
    @functools.cached_property
    def _face_area_vectors(self) -> tuple[np.ndarray, np.ndarray]:
        """Area vectors of the local faces (M, 4, 3), outward for positive tets, magnitude
        twice the face's area, and their norms (M, 4)."""
        a, b, c, d = self._corners()
        f = np.stack([a, b, c, d], axis=1)[:, TET_FACES]  # [M, 4, 3, 3]
        n = np.cross(f[:, :, 1] - f[:, :, 0], f[:, :, 2] - f[:, :, 0])
        return n, np.linalg.norm(n, axis=2)

    def dihedral_angles(self) -> np.ndarray:
        """Interior dihedral angles (M, 6) float64 in degrees, column k at local edge
        ``TET_EDGES[k]``; nan for a degenerate tet (a face of zero area)."""
        n, nn = self._face_area_vectors
        with np.errstate(divide="ignore", invalid="ignore"):
            cosang = -np.einsum("mek,mek->me", n[:, TET_EDGE_FACES[:, 0]], n[:, TET_EDGE_FACES[:, 1]]) / (
                nn[:, TET_EDGE_FACES[:, 0]] * nn[:, TET_EDGE_FACES[:, 1]]
            )
        return np.degrees(np.arccos(np.clip(cosang, -1.0, 1.0)))

    def boundary_wedges(self) -> tuple[np.ndarray, np.ndarray]:
        """The boundary edges (E, 2) int64 and the solid's wedge angle at each (E,) float64,
        in degrees: the sum of the dihedral angles of the tets around the edge (180 on a flat
        surface, under 90 on a convex ridge sharper than a box's, near 0 on a knife edge).
        Over 360 the tets around the edge wrap past a full turn: they overlap in space and
        the surface cuts through itself there, although none of them is inverted."""
        edges, wedge_of = ridge_index(self)
        return edges, wedge_of(self)

    def overlapping_edges(self) -> int:
        """How many boundary edges have a wedge (:meth:`boundary_wedges`) over 360°."""
        return int(np.count_nonzero(self.boundary_wedges()[1] > 360.0))

    def quality(self) -> dict:
        """Per-tet quality measures (method.md §9).

        Returns:
            dict of (M,) float64 arrays:
            - ``min_dihedral_deg``: smallest of the six dihedral angles (regular: 70.53°);
            - ``aspect_ratio``: longest edge / (2·sqrt(6)·inradius) (regular: 1, grows to inf);
            - ``radius_ratio``: 3·inradius / circumradius (regular: 1, degenerate: 0).
            Degenerate (zero-volume) tets get dihedral 0, aspect inf and radius ratio 0.
        """
        a, b, c, d = self._corners()
        P = np.stack([a, b, c, d], axis=1)  # [M, 4, 3]
        _, nn = self._face_area_vectors  # [M, 4]: twice the face areas
        vol = np.abs(self._signed_volumes)
        dihedral = self.dihedral_angles()  # [M, 6]
        with np.errstate(divide="ignore", invalid="ignore"):
            min_dih = np.nan_to_num(dihedral.min(axis=1), nan=0.0)
            area_sum = 0.5 * nn.sum(axis=1)
            inradius = 3.0 * vol / area_sum
            e = P[:, TET_EDGES[:, 1]] - P[:, TET_EDGES[:, 0]]
            el = np.linalg.norm(e, axis=2)  # [M, 6]
            aspect = el.max(axis=1) / (2.0 * math.sqrt(6.0) * inradius)
            # Circumradius from opposite-edge products (edges 0-5, 1-4, 2-3 are opposite).
            p = el[:, 0] * el[:, 5]
            q = el[:, 1] * el[:, 4]
            r = el[:, 2] * el[:, 3]
            s = (p + q + r) * (p + q - r) * (p - q + r) * (-p + q + r)
            circum = np.sqrt(np.clip(s, 0.0, None)) / (24.0 * vol)
            radius_ratio = 3.0 * inradius / circum
        degenerate = ~(vol > 0)
        aspect = np.where(degenerate, np.inf, aspect)
        radius_ratio = np.where(degenerate, 0.0, np.nan_to_num(radius_ratio, nan=0.0))
        min_dih = np.where(degenerate, 0.0, min_dih)
        return {"min_dihedral_deg": min_dih, "aspect_ratio": aspect, "radius_ratio": radius_ratio}

    def quality_summary(self) -> dict:
        """Mesh-level quality figures (method.md §9): means and worsts of :meth:`quality`
        over all tets, and ``inverted_ratio`` = fraction with signed volume <= 0."""
        q = self.quality()
        M = self.num_tets
        if M == 0:
            nan = float("nan")
            return {
                "tets": 0, "inverted": 0, "inverted_ratio": nan, "min_dihedral_mean": nan,
                "min_dihedral_worst": nan, "aspect_ratio_mean": nan, "aspect_ratio_worst": nan,
                "radius_ratio_mean": nan, "radius_ratio_worst": nan,
            }
        inverted = int(np.count_nonzero(self._signed_volumes <= 0))
        ar = q["aspect_ratio"]
        finite = np.isfinite(ar)
        return {
            "tets": M,
            "inverted": inverted,
            "inverted_ratio": inverted / M,
            "min_dihedral_mean": float(q["min_dihedral_deg"].mean()),
            "min_dihedral_worst": float(q["min_dihedral_deg"].min()),
            # Degenerate tets have infinite aspect; the mean is over the finite ones and
            # the worst reports inf, so a single sliver cannot hide.
            "aspect_ratio_mean": float(ar[finite].mean()) if finite.any() else float("inf"),
            "aspect_ratio_worst": float(ar.max()),
            "radius_ratio_mean": float(q["radius_ratio"].mean()),
            "radius_ratio_worst": float(q["radius_ratio"].min()),
        }

    def summary(self) -> dict:
        """One dict with counts, topology and quality: what ``convert``/reports print."""
        man = self.manifold()
        out = {
            "vertices": self.num_vertices,
            "tets": self.num_tets,
            "boundary_faces": int(len(self.boundary_faces())),
            "components": self.num_components(),
            "manifold": man["manifold"],
            "genus": self.genus(),
            "overlapping_edges": self.overlapping_edges(),
            "volume": self.volume(),
        }
        out.update({k: v for k, v in self.quality_summary().items() if k != "tets"})
        return out


def ridge_index(mesh: TetMesh, *, fans: bool = False):
    """(boundary edges (E, 2), ``wedge_of(m)``): the wedge angles (E,) of those edges
    (:meth:`TetMesh.boundary_wedges`) in any mesh ``m`` with ``mesh``'s tets, the edge-to-tet
    bookkeeping done once. With ``fans``, a third item ``fan_of(select)``: the ids of the
    tets around the selected edges (``select`` (E,) bool)."""
    edges, _ = mesh._boundary_edges
    n = max(mesh.num_vertices, 1)
    tet_keys = _row_keys(np.sort(mesh.tets[:, TET_EDGES].reshape(-1, 2), axis=1).astype(np.int64), n)
    uk, inv = np.unique(tet_keys, return_inverse=True)
    at = np.searchsorted(uk, _row_keys(edges, n))

    def wedge_of(m: TetMesh) -> np.ndarray:
        return np.bincount(inv, weights=np.nan_to_num(m.dihedral_angles().ravel()), minlength=len(uk))[at]

    def fan_of(select: np.ndarray) -> np.ndarray:
        return np.unique(np.flatnonzero(np.isin(inv, at[select])) // 6)

    return (edges, wedge_of, fan_of) if fans else (edges, wedge_of)


def decimate_surface(vertices, faces, max_faces: int) -> tuple[np.ndarray, np.ndarray]:
    """A triangle surface (V, 3), (F, 3) decimated to about ``max_faces`` triangles by
    quadric error (VTK's vtkQuadricDecimation through pyvista, duplicate points merged), as
    (V', 3) float64 and (F', 3) int32. A surface with at most ``max_faces`` triangles comes back unchanged."""
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64)
    if max_faces < 4:
        raise TetMeshError(f"decimate_surface: max_faces must be at least 4, got {max_faces}")
    if len(f) <= max_faces:
        return v, f.astype(np.int32)
    import pyvista as pv

    poly = pv.PolyData(v, np.hstack([np.full((len(f), 1), 3), f]).ravel())
    out = poly.decimate(1.0 - max_faces / len(f)).clean()
    return np.asarray(out.points, dtype=np.float64), np.asarray(out.faces).reshape(-1, 4)[:, 1:].astype(np.int32)


def _in_scratch_folder(fn, *args, **kwargs):
    """``fn(*args, **kwargs)`` run in a temporary working folder: fTetWild drops a debug file
    (__tracked_surface.stl) into the working folder, and users' folders stay clean."""
    import contextlib
    import os
    import tempfile

    with tempfile.TemporaryDirectory(prefix="holowarp-tetwild-") as scratch:
        cwd = os.getcwd()
        os.chdir(scratch)
        try:
            return fn(*args, **kwargs)
        finally:
            with contextlib.suppress(OSError):
                os.chdir(cwd)


def tetrahedralize_surface(
    vertices,
    faces,
    *,
    edge_length_fac: float = 0.05,
    edge_length_abs: float | None = None,
    epsilon: float = 1e-3,
    optimize: bool = True,
    num_threads: int = 0,
    max_faces: int | None = None,
    sizing: tuple | None = None,
    seed: int = 0,
) -> TetMesh:
    """Tetrahedralise a closed triangle surface with fTetWild (pytetwild).

    Args:
        vertices: (V, 3) surface positions.
        faces: (F, 3) triangle indices.
        edge_length_fac: ideal edge length as a fraction of the bbox diagonal (the
            resolution knob of method.md §4).
        edge_length_abs: absolute ideal edge length; overrides ``edge_length_fac``.
        epsilon: envelope size relative to the bbox (method.md §4: 1e-3).
        optimize: let fTetWild improve element quality.
        max_faces: a surface with more triangles is first decimated to about this many
            (quadric error, VTK through pyvista). fTetWild's time grows with the input's
            triangles, not with the output's tets: a 60k-triangle mug takes it minutes at
            ``edge_length_fac`` 0.05, the same mug decimated to 10k well under two (and
            the same Chamfer-L1 to the original surface, at the 100k-sample floor).
        sizing: optional spatially varying ideal edge length, ``(bg_vertices (B, 3),
            bg_tets (T, 4), bg_values (B,))``: a background tet mesh and the edge length at
            its vertices (absolute units), interpolated inside its tets (fTetWild's sizing
            field). fTetWild refines towards it but never coarsens past the global ideal
            edge length, so give ``edge_length_abs`` >= its largest value.
        seed: fTetWild's random choices are drawn from this seed where
            :mod:`holowarp.repeatable` can seed them (then one surface and one seed give one
            mesh on one machine), else they differ from call to call.

    Returns:
        A positively oriented :class:`TetMesh` (fTetWild output is re-oriented and unused
        vertices are dropped).

    Raises:
        TetMeshError: the input is empty or fTetWild produced no tets.
    """
    from holowarp import repeatable

    rd = repeatable.random_device()  # before pytetwild's extension loads, so that it binds to it
    import pytetwild

    v = np.ascontiguousarray(vertices, dtype=np.float64)
    f = np.ascontiguousarray(faces, dtype=np.int32)
    if len(v) < 4 or len(f) < 4:
        raise TetMeshError(f"tetrahedralize_surface: need a closed surface, got {len(v)} vertices, {len(f)} faces")
    if max_faces is not None and len(f) > max_faces:
        v, f = decimate_surface(v, f, max_faces)
    bg = {}
    if sizing is not None:
        bv, bt, bs = sizing
        # Fresh writable copies: the binding refuses read-only arrays (TetMesh's are).
        bg = dict(bg_vertices=np.array(bv, dtype=np.float64, order="C"),
                  bg_tets=np.array(bt, dtype=np.int32, order="C"), bg_values=np.array(bs, dtype=np.float64, order="C"))
    if rd is not None:
        rd.seed(seed)
    tv, tt = _in_scratch_folder(pytetwild.tetrahedralize, v, f, edge_length_fac=edge_length_fac,
                                edge_length_abs=edge_length_abs, optimize=optimize, epsilon=epsilon,
                                num_threads=num_threads, quiet=True, **bg)
    if rd is not None and rd.draws() == 0:
        repeatable.unbound()
    if tt is None or len(tt) == 0:
        raise TetMeshError("tetrahedralize_surface: fTetWild produced no tetrahedra")
    mesh, _ = TetMesh(tv, tt).oriented()
    mesh, _ = mesh.remove_unused_vertices()
    return mesh
