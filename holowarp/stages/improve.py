"""Element improvement after cleanup (method.md §7b): flips, smoothing, sliver removal.

Cleanup (§7) hands over a valid mesh (one component, manifold boundary, no inverted tet)
that is not yet simulation-ready: geometry optimisation leaves flattened caps at the
boundary and distorted tets inside. This stage improves the elements in the manner of
Klingner & Shewchuk, "Aggressive Tetrahedral Mesh Improvement" (IMR 2007), while keeping
what §7b fixes: the same components, genus and manifold boundary, no inverted tet, and a
boundary surface within ``max_surface_move`` mean boundary edges (Hausdorff) of the input.

One *round* runs the four steps below, in order. The first ``inside_rounds`` rounds run
with a zero surface budget (steps 1 and 3 leave the boundary alone), so that everything
that can be fixed from inside is fixed before any surface budget is spent; what is left
for the surface operations is then only what needs them.

1. **boundary flips and cap deletion** (vectorised): a boundary edge whose open fan has
   1..``max_boundary_ring`` tets is removed by retriangulating the fan (its two boundary
   triangles flip to the other diagonal of their quad; a fan of one tet is a *cap*, simply
   deleted), and a tet whose apex is a boundary vertex of valence one (three boundary
   faces) is deleted with that vertex, and a boundary edge shorter than ``collapse_ratio``
   mean boundary edges is collapsed (its ends merge at either end or at its midpoint,
   whichever leaves the best worst tet; the edge's fan vanishes): a needle under a short
   boundary edge keeps its short edge through every flip. These move the surface by the
   local two-sided Hausdorff distance between the old and new triangles, which must fit
   the surface budget left there (see below). A cap is deleted only once the tets it would expose are decent
   (``boundary_threshold``) or caps themselves no worse than it: a bad interior tet can still
   be fixed from inside, but once on the surface only the surface budget could help it. Changes are vertex-disjoint, and every batch is checked
   (components, genus, shells, manifoldness) before it is kept. Boundary changes go first
   in a round, before an interior flip can bury a cap under tets no surface operation reaches;
2. **interior flips** (vectorised, repeated while they help): every interior face is a 2-3
   flip candidate (the two tets on it become three around the edge joining their apexes),
   every interior edge with 3..``max_ring`` tets an *edge removal* candidate (Shewchuk 2002,
   "Two discrete optimization algorithms for the topological improvement of tetrahedral
   meshes": the ring's tets are replaced by the best triangulation of the ring polygon
   with every triangle coned to both edge ends; a ring of 3 is the 3-2 flip, of 4 the 4-4
   flip). All triangulations of every ring are scored at once. A candidate counts only if
   the worst new tet beats the worst old one by ``min_gain`` and, where the worst old tet is
   already decent (``mean_guard``), the new tets' mean quality is no lower than the old
   ones' (polishing must not cost the average); per pass, an independent set
   (no shared tet) of the best is applied. Interior faces and edges are off the boundary,
   so the boundary is untouched;
3. **smoothing** (Warp, :func:`holowarp.kernels.improve.smooth_vertices_kernel`, one launch
   per independent set of a vertex colouring): each vertex climbs the soft minimum of its
   star's qualities and moves only if the star's worst quality rises (and, for a star that is
   already decent, its mean does not drop). Interior vertices
   move freely. Boundary vertices move only tangentially (in the null space of the
   area-weighted normal covariance of their boundary triangles: a smooth vertex slides in
   its tangent plane, a crease vertex along the crease, a corner not at all), and only to
   positions whose surface move fits the budget;
4. **sliver removal** where a round's flips and smoothing leave tets below
   ``split_threshold``: such a tet gets a new vertex at the midpoint of its longest interior
   edge (every tet around the edge splits in two), or at the centroid of its interior face
   when all its edges are on the boundary (the two tets on the face become six). The new
   vertex is interior, is placed by smoothing at once, and the split is kept only if the
   worst child beats the worst tet it replaced.

After the last round, step 5, **overlaps**: where a boundary edge's tets wrap past a full
turn (wedge over 360°: they overlap in space, none inverted), the end tet of its fan that
:func:`holowarp.stages.cleanup.overlap_ends` picks is deleted, through the same topology
check as step 1 (and outside the surface budget: the surface cutting through itself is
worse than a tet's thickness of move). The tangential moves of step 3 can wrap a fan: on the
quality suite at 128² (fast preset, seed 0) §7b left one such edge on the star and two on
the dented box, from smoothing alone. Forbidding those moves instead cost the worst angle
(star 16.1° → 4.8°, plate 10.4° → 7.6°): the flat tet lying across such an edge is often
the worst, and smoothing mends it by opening the fan.

Surface budget. ``err`` (per vertex, metres) bounds how far every boundary triangle at the
vertex has moved from the input surface. A change that replaces the surface patch P by P'
(same rim) costs h = H(P, P'), the two-sided Hausdorff distance measured on sampled points
(times ``hausdorff_margin``; for a vertex move never more than the vertex's displacement,
which bounds it exactly); it is allowed where max(err over the patch's vertices) + h fits
``max_surface_move`` mean boundary edges, and those vertices' err becomes that sum. By the
triangle inequality the whole surface then stays within the bound of the input;
``info["surface_hausdorff"]`` measures it. Sums of bounds over-count moves that partly undo
each other, so before every round that may move the surface ``err`` is measured afresh
against the input surface (``ImproveConfig.remeasure_budget``, :func:`_remeasure_budget`);
on the quality suite at 128² that raised the worst angle left by 0.6-1.3° (bob 11.6° →
12.9°, the dented box 5.4° → 6.3°) with the measured Hausdorff distance still under the bound.

Quality: by default the smaller of the "sine measure" of Klingner & Shewchuk (smallest
dihedral-angle sine over the regular tet's) and Newton's volume-length shape quality eta,
see :mod:`holowarp.kernels.improve`. Both are small for small and for nearly flat (~180°)
dihedral angles alike: the slivers and caps that make an FEM solver substep or soften.

Everything on tets is vectorised NumPy (sorting-based hashing of faces and edges) or Warp
(qualities of whole meshes and of flip candidates, smoothing; ``device`` picks CPU or
CUDA). No Python loop runs over tets, faces, edges or vertices.

Example:
    >>> from holowarp.primitives import box_tetmesh
    >>> out, parent, info = improve(box_tetmesh((2, 2, 2)))
    >>> info["after"]["min_dihedral_worst"] >= info["before"]["min_dihedral_worst"]
    True
"""

from __future__ import annotations

import math
import time
from dataclasses import replace

import numpy as np

from holowarp.config import ETA_HISTOGRAM_EDGES, QUALITY_MEASURES, ImproveConfig
from holowarp.stages.cleanup import overlap_ends
from holowarp.tetmesh import TET_EDGE_FACES, TET_EDGES, TET_FACES, TetMesh

__all__ = [
    "TARGETS",
    "element_targets",
    "missed_targets",
    "ImproveConfig",
    "QUALITY_MEASURES",
    "ETA_HISTOGRAM_EDGES",
    "improve",
    "tet_quality",
    "shape_quality_eta",
    "surface_hausdorff",
    "mean_boundary_edge",
]


_SIN_REGULAR = 2.0 * math.sqrt(2.0) / 3.0

# (i, j, k, l) even permutations of (0, 1, 2, 3), one per local edge (i, j) of TET_EDGES:
# for a positive tet, (t[i], t[j], t[k], t[l]) is positive too, so going round the directed
# edge t[i] -> t[j] the ring steps from t[k] to t[l].
_EDGE_PERM = np.array(
    [[0, 1, 2, 3], [0, 2, 3, 1], [0, 3, 1, 2], [1, 2, 0, 3], [1, 3, 2, 0], [2, 3, 0, 1]], dtype=np.int64
)


# ---------------------------------------------------------------------------- quality
def _quality_of_points(P: np.ndarray, mode: int) -> np.ndarray:
    """Quality (K,) of tets given by corner coordinates P (K, 4, 3), float64: the NumPy
    reference of :func:`holowarp.kernels.improve.tet_quality`."""
    a, b, c, d = P[:, 0], P[:, 1], P[:, 2], P[:, 3]
    vol6 = np.einsum("ij,ij->i", b - a, np.cross(c - a, d - a))
    q = np.full(len(P), np.inf)
    e = P[:, TET_EDGES[:, 1]] - P[:, TET_EDGES[:, 0]]  # [K, 6, 3]
    l2 = np.einsum("kej,kej->ke", e, e)
    if mode != 1:
        f = P[:, TET_FACES]  # [K, 4, 3, 3]
        n = np.linalg.norm(np.cross(f[:, :, 1] - f[:, :, 0], f[:, :, 2] - f[:, :, 0]), axis=2)  # [K, 4]
        den = n[:, TET_EDGE_FACES[:, 0]] * n[:, TET_EDGE_FACES[:, 1]]
        with np.errstate(divide="ignore", invalid="ignore"):
            s = np.where(den > 0, vol6[:, None] * np.sqrt(l2) / den, 0.0)
        q = s.min(axis=1) / _SIN_REGULAR
    if mode != 0:
        sl2 = l2.sum(axis=1)
        with np.errstate(divide="ignore", invalid="ignore"):
            eta = np.where(sl2 > 0, 12.0 * (np.abs(vol6) * 0.5) ** (2.0 / 3.0) / sl2, 0.0)
        q = np.minimum(q, np.sign(vol6) * eta)
    return q


def tet_quality(vertices, tets, measure: str = "sine") -> np.ndarray:
    """Per-tet quality (M,) float64 by ``measure`` (``"sine"``, ``"eta"``, ``"sine_eta"``).

    1 for the regular tetrahedron, 0 for a degenerate tet, negative for an inverted one.
    ``"sine"``: smallest sine of the six dihedral angles over the regular tet's
    (2 sqrt(2) / 3); ``"eta"``: :func:`shape_quality_eta`, signed like the volume.

    Example:
        >>> V = np.array([[1, 1, 1], [1, -1, -1], [-1, 1, -1], [-1, -1, 1]], float)
        >>> round(float(tet_quality(V, [[0, 1, 2, 3]])[0]), 12)
        1.0
    """
    mode = QUALITY_MEASURES[measure]
    V = np.asarray(vertices, dtype=np.float64)
    T = np.asarray(tets, dtype=np.int64).reshape(-1, 4)
    return _quality_of_points(V[T], mode)


def shape_quality_eta(vertices, tets) -> np.ndarray:
    """Newton's shape quality ``eta = 12 (3|V|)^(2/3) / sum(l^2)`` per tet (M,), >= 0
    (1 for the regular tet; Newton's ``validate_tet_mesh`` warns below 0.01)."""
    return np.abs(tet_quality(vertices, tets, "eta"))


def _summary(V: np.ndarray, T: np.ndarray, q: np.ndarray) -> dict:
    mq = TetMesh(V, T, validate=False).quality()
    ar = mq["aspect_ratio"]
    fin = np.isfinite(ar)
    return {
        "tets": int(len(T)),
        "vertices": int(len(np.unique(T))),
        "min_dihedral_worst": float(mq["min_dihedral_deg"].min()),
        "min_dihedral_mean": float(mq["min_dihedral_deg"].mean()),
        "aspect_ratio_mean": float(ar[fin].mean()) if fin.any() else float("inf"),
        "aspect_ratio_worst": float(ar.max()),
        "quality_min": float(q.min()),
        "quality_mean": float(q.mean()),
        "eta_min": float(shape_quality_eta(V, T).min()),
        "inverted": int(np.count_nonzero(TetMesh(V, T, validate=False).signed_volumes() <= 0)),
        "tets_below_min_dihedral_target": int(np.count_nonzero(
            mq["min_dihedral_deg"] < TARGETS["min_dihedral_worst"][1])),
    }


#: method.md §7b's targets for the improved elements, by :func:`_summary` key: (">=" or
#: "<=", bound). eta: Newton's ``validate_tet_mesh`` threshold.
TARGETS = {
    "min_dihedral_worst": (">=", 10.0),
    "min_dihedral_mean": (">=", 40.0),
    "aspect_ratio_mean": ("<=", 1.8),
    "eta_min": (">=", 0.01),
}


def element_targets(summary: dict) -> dict:
    """Each of :data:`TARGETS` checked on a quality summary (``info["after"]``):
    ``{key: {"value", "target", "met"}}``, ``target`` as text (e.g. ``">= 10"``); the
    dihedral entry also has ``tets_below`` when the summary counts them.

    The stage does not promise them: its operations keep the topology and the surface
    budget, and a surface that is thin or sharp at the scale of its tets can leave a tet
    below the dihedral target (on a perturbed run of the quality suite's star, 7.4°)."""
    out = {}
    for key, (op, bound) in TARGETS.items():
        v = float(summary[key])
        out[key] = {"value": v, "target": f"{op} {bound:g}", "met": bool(v >= bound if op == ">=" else v <= bound)}
    if "tets_below_min_dihedral_target" in summary:
        out["min_dihedral_worst"]["tets_below"] = int(summary["tets_below_min_dihedral_target"])
    return out


def missed_targets(info: dict) -> list[str]:
    """One line per method.md §7b target that the improved mesh misses, for the commands'
    warnings (``info`` as :func:`improve` returns it; nothing for a report without
    ``targets``)."""
    names = {"min_dihedral_worst": "worst minimum dihedral angle (deg)",
             "min_dihedral_mean": "mean minimum dihedral angle (deg)",
             "aspect_ratio_mean": "mean aspect ratio",
             "eta_min": "smallest shape quality eta"}
    lines = []
    for key, t in (info.get("targets") or {}).items():
        if not t["met"]:
            below = f" ({t['tets_below']} tets below)" if "tets_below" in t else ""
            lines.append(f"{names.get(key, key)} is {t['value']:.3g}{below}, outside method.md §7b's target "
                         f"{t['target']}: the flips, smoothing and splits found no better elements within the "
                         f"topology and the surface bound there")
    return lines


def _eta_histogram(V, T, edges) -> dict:
    eta = shape_quality_eta(V, T)
    e = np.asarray(edges, dtype=np.float64)
    counts, _ = np.histogram(np.clip(eta, e[0], e[-1]), bins=e)
    return {"bin_edges": [float(x) for x in e], "counts": counts.astype(int).tolist(),
            "below_0.01": int(np.count_nonzero(eta < 0.01))}


# ---------------------------------------------------------------------------- surface distance
def mean_boundary_edge(mesh: TetMesh) -> float:
    """Mean length (m) of the boundary surface's edges (0 for a mesh without boundary)."""
    bf = mesh.boundary_faces().astype(np.int64)
    if len(bf) == 0:
        return 0.0
    e = np.unique(np.sort(np.concatenate([bf[:, [0, 1]], bf[:, [1, 2]], bf[:, [2, 0]]]), axis=1), axis=0)
    V = mesh.vertices
    return float(np.linalg.norm(V[e[:, 0]] - V[e[:, 1]], axis=1).mean())


def _closest_on_triangles(p, a, b, c):
    """Distances (K,) from points p (K, 3) to triangles (a, b, c) (K, 3 each), exact
    (Ericson, Real-Time Collision Detection §5.1.5, vectorised over the regions)."""
    ab, ac = b - a, c - a
    d1 = np.einsum("ij,ij->i", ab, p - a)
    d2 = np.einsum("ij,ij->i", ac, p - a)
    d3 = np.einsum("ij,ij->i", ab, p - b)
    d4 = np.einsum("ij,ij->i", ac, p - b)
    d5 = np.einsum("ij,ij->i", ab, p - c)
    d6 = np.einsum("ij,ij->i", ac, p - c)
    va, vb, vc = d3 * d6 - d5 * d4, d5 * d2 - d1 * d6, d1 * d4 - d3 * d2
    with np.errstate(divide="ignore", invalid="ignore"):
        den = va + vb + vc
        q = a + ab * np.where(den != 0, vb / den, 0.0)[:, None] + ac * np.where(den != 0, vc / den, 0.0)[:, None]
        # Edge regions, then vertex regions; later assignments win where several apply.
        m = (vc <= 0) & (d1 >= 0) & (d3 <= 0)
        q = np.where(m[:, None], a + ab * np.where(d1 != d3, d1 / (d1 - d3), 0.0)[:, None], q)
        m = (vb <= 0) & (d2 >= 0) & (d6 <= 0)
        q = np.where(m[:, None], a + ac * np.where(d2 != d6, d2 / (d2 - d6), 0.0)[:, None], q)
        e43, e56 = d4 - d3, d5 - d6
        m = (va <= 0) & (e43 >= 0) & (e56 >= 0)
        q = np.where(m[:, None], b + (c - b) * np.where(e43 + e56 != 0, e43 / (e43 + e56), 0.0)[:, None], q)
    q = np.where(((d1 <= 0) & (d2 <= 0))[:, None], a, q)
    q = np.where(((d3 >= 0) & (d4 <= d3))[:, None], b, q)
    q = np.where(((d6 >= 0) & (d5 <= d6))[:, None], c, q)
    return np.linalg.norm(p - q, axis=1)


def _point_surface_distance(points: np.ndarray, V: np.ndarray, F: np.ndarray, device: str = "cpu") -> np.ndarray:
    """Distance (P,) from each point to the triangle surface (V, F): Warp's mesh BVH
    (float32, :meth:`holowarp.ops.improve.ImproveKernels.closest_faces`) finds the closest
    triangle, and the distance to it is then taken exactly in float64."""
    from holowarp.ops.improve import ImproveKernels

    face, d = ImproveKernels(device).closest_faces(points, V, F)
    hit = face >= 0
    g = F[face[hit]]
    d[hit] = _closest_on_triangles(points[hit], V[g[:, 0]], V[g[:, 1]], V[g[:, 2]])
    return d


def _surface_samples(V: np.ndarray, F: np.ndarray, per_face: int, rng) -> np.ndarray:
    e = np.unique(np.sort(np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]]), axis=1), axis=0)
    pts = [V[np.unique(F)], 0.5 * (V[e[:, 0]] + V[e[:, 1]]), V[F].mean(axis=1)]
    if per_face > 0:
        r1 = np.sqrt(rng.random((len(F), per_face)))
        r2 = rng.random((len(F), per_face))
        w = np.stack([1 - r1, r1 * (1 - r2), r1 * r2], axis=2)  # [F, k, 3]
        pts.append(np.einsum("fkj,fjd->fkd", w, V[F]).reshape(-1, 3))
    return np.concatenate(pts)


def surface_hausdorff(va, fa, vb, fb, *, samples_per_face: int = 8, seed: int = 0, device: str = "cpu") -> float:
    """Hausdorff distance between two triangle surfaces, in their units.

    Both one-sided distances are taken over every vertex, edge midpoint and face centroid
    plus ``samples_per_face`` random points per triangle of the source surface, each
    measured exactly to the other surface (point to triangle, not point to sample), so the
    estimate approaches the true distance from below as the sampling densifies.
    """
    rng = np.random.default_rng(seed)
    va, vb = np.asarray(va, np.float64), np.asarray(vb, np.float64)
    fa, fb = np.asarray(fa, np.int64), np.asarray(fb, np.int64)
    pa = _surface_samples(va, fa, samples_per_face, rng)
    pb = _surface_samples(vb, fb, samples_per_face, rng)
    return float(max(_point_surface_distance(pa, vb, fb, device).max(), _point_surface_distance(pb, va, fa, device).max()))


def _barycentric_grid(level: int) -> np.ndarray:
    """(K, 3) barycentric points of a triangle on a regular grid of ``level`` steps."""
    i, j = np.meshgrid(np.arange(level + 1), np.arange(level + 1), indexing="ij")
    m = i + j <= level
    return np.stack([level - i[m] - j[m], i[m], j[m]], axis=1).astype(np.float64) / level


_PATCH_GRID = _barycentric_grid(6)  # 28 points per triangle


def _patch_hausdorff(Po: np.ndarray, Pn: np.ndarray, vo: np.ndarray, vn: np.ndarray, grid: np.ndarray = _PATCH_GRID) -> np.ndarray:
    """Two-sided Hausdorff distance (C,) between small triangle patches sharing their rim,
    given by corner coordinates ``Po`` (C, A, 3, 3) and ``Pn`` (C, B, 3, 3) with validity
    masks ``vo`` (C, A), ``vn`` (C, B); each side sampled at the barycentric points ``grid``
    (K, 3) of every triangle (28 by default) and measured exactly to the other side's
    triangles. The NumPy reference of :func:`holowarp.kernels.improve.umbrella_move`."""

    def one_way(src, vs, dst, vd):
        C, A = src.shape[:2]
        B = dst.shape[1]
        P = np.einsum("kj,cajd->cakd", grid, src)  # [C, A, K, 3]
        K = P.shape[2]
        p = np.broadcast_to(P[:, :, :, None, :], (C, A, K, B, 3)).reshape(-1, 3)
        tri = np.broadcast_to(dst[:, None, None], (C, A, K, B, 3, 3)).reshape(-1, 3, 3)
        d = _closest_on_triangles(p, tri[:, 0], tri[:, 1], tri[:, 2]).reshape(C, A, K, B)
        d = np.where(vd[:, None, None, :], d, np.inf).min(axis=3)  # [C, A, K]
        return np.where(vs[:, :, None], d, 0.0).reshape(C, -1).max(axis=1)

    if len(Po) == 0:
        return np.zeros(0)
    return np.maximum(one_way(Po, vo, Pn, vn), one_way(Pn, vn, Po, vo))


def _local_hausdorff(V: np.ndarray, old_f: np.ndarray, new_f: np.ndarray) -> np.ndarray:
    """:func:`_patch_hausdorff` of patches given as vertex ids (C, A, 3) / (C, B, 3) into
    ``V``; rows starting with -1 are ignored."""
    return _patch_hausdorff(V[np.maximum(old_f, 0)], V[np.maximum(new_f, 0)], old_f[:, :, 0] >= 0, new_f[:, :, 0] >= 0)


# ---------------------------------------------------------------------------- combinatorics
def _polygon_triangulations(n: int) -> np.ndarray:
    """All triangulations of a convex polygon 0..n-1: (C_{n-2}, n-2, 3) int64 (Catalan
    many), each triangle's corners in polygon order."""

    def rec(poly):
        if len(poly) < 3:
            return [[]]
        out = []
        for i in range(1, len(poly) - 1):
            for left in rec(poly[: i + 1]):
                for right in rec(poly[i:]):
                    out.append(left + right + [(poly[0], poly[i], poly[-1])])
        return out

    return np.array(rec(list(range(n))), dtype=np.int64).reshape(-1, max(n - 2, 0), 3)


class _PolygonTables:
    """For an n-gon: its distinct triangles ``combos`` (C, 3), every triangulation as rows
    of combo ids ``tri`` (Tn, n-2), and per triangulation its inner diagonals ``diag``
    (Tn, n-3, 2) in polygon positions."""

    def __init__(self, n: int):
        tri = _polygon_triangulations(n)
        self.combos = np.unique(tri.reshape(-1, 3), axis=0)
        cid = {tuple(c): i for i, c in enumerate(self.combos.tolist())}
        self.tri = np.array([[cid[tuple(t)] for t in tr] for tr in tri.tolist()], dtype=np.int64).reshape(len(tri), n - 2)
        diag = []
        for tr in tri.tolist():
            e = {tuple(sorted(p)) for t in tr for p in ((t[0], t[1]), (t[1], t[2]), (t[0], t[2]))}
            diag.append(sorted(d for d in e if (d[1] - d[0]) % n not in (1, n - 1)))
        self.diag = np.array(diag, dtype=np.int64).reshape(len(tri), max(n - 3, 0), 2)


_POLYGONS = {n: _PolygonTables(n) for n in range(3, 10)}


def _lex_order(major: np.ndarray, minor: np.ndarray, n_major: int, n_minor: int) -> np.ndarray:
    """``np.argsort(major * n_minor + minor, kind="stable")`` for non-negative ``major`` <
    ``n_major`` and ``minor`` < ``n_minor``, as two stable passes of NumPy's radix sort on
    16-bit keys where both fit (about four times faster at 200k entries, and the same
    permutation: a stable sort by ``minor`` then by ``major`` orders by the pair, ties in
    input order); the edge tables of the flip passes sort that much dozens of times."""
    if max(n_major, n_minor) > 1 << 16:
        return np.argsort(major.astype(np.int64) * n_minor + minor, kind="stable")
    o = np.argsort(minor.astype(np.uint16), kind="stable")
    return o[np.argsort(major.astype(np.uint16)[o], kind="stable")]


def _edge_keys(u, v, n):
    lo, hi = np.minimum(u, v), np.maximum(u, v)
    return lo.astype(np.int64) * n + hi


class _EdgeTable:
    """Every edge of the mesh with its ring of tets in cyclic order.

    Attributes (E edges, R = longest ring kept):
        u, v: (E,) endpoints, u < v; keys: (E,) sorted ``u * N + v``.
        n: (E,) tets around the edge (R + 1 marks a broken ring: non-manifold input).
        boundary: (E,) the fan is open (a boundary edge).
        tets: (E, R) ring tets in order, -1 padded (only for n <= R).
        verts: (E, R + 1) ring vertices in order: p_0..p_n for open fans, p_0..p_{n-1} for
            closed rings (so that (u, v, p_i, p_{i+1}) is a positive tet), -1 padded.
    """

    def __init__(self, T: np.ndarray, N: int, R: int):
        M = len(T)
        P = T[:, _EDGE_PERM]  # [M, 6, 4]
        u, v, a, b = (P[:, :, i].reshape(-1) for i in range(4))
        tet = np.repeat(np.arange(M, dtype=np.int64), 6)
        swap = u > v
        u, v = np.where(swap, v, u), np.where(swap, u, v)
        a, b = np.where(swap, b, a), np.where(swap, a, b)
        order = _lex_order(u, v, N, N)
        key = (u * N + v)[order]
        a, b, tet = a[order], b[order], tet[order]
        start = np.r_[True, key[1:] != key[:-1]]
        gid = np.cumsum(start) - 1
        first = np.flatnonzero(start)
        E = len(first)
        n = np.diff(np.r_[first, len(key)])
        # An entry whose 'from' vertex is no entry's 'to' vertex opens its (open) fan.
        ka = gid * N + a
        kb = gid * N + b
        kb = kb[_lex_order(gid, b, E, N)]
        pos = np.minimum(np.searchsorted(kb, ka), len(kb) - 1)
        opener = kb[pos] != ka
        boundary = np.zeros(E, dtype=bool)
        boundary[gid[opener]] = True
        st = first.copy()
        st[gid[opener]] = np.flatnonzero(opener)
        ka_order = _lex_order(gid, a, E, N)
        ka_sorted = ka[ka_order]
        keep = np.flatnonzero(n <= R)
        rt = np.full((E, R), -1, dtype=np.int64)
        rv = np.full((E, R + 1), -1, dtype=np.int64)
        cur = st[keep]
        rt[keep, 0] = tet[cur]
        rv[keep, 0] = a[cur]
        rv[keep, 1] = b[cur]
        # Walk every ring at once: the successor is the entry whose 'from' is our 'to',
        # looked up once for every entry (queries in group order: a fast search).
        want = gid * N + b
        p = np.minimum(np.searchsorted(ka_sorted, want), len(ka_sorted) - 1)
        found, succ = ka_sorted[p] == want, ka_order[p]
        for step in range(1, R):
            live = np.flatnonzero(n[keep] > step)
            if len(live) == 0:
                break
            g, c = keep[live], cur[live]
            ok = found[c]
            n[g[~ok]] = R + 1  # broken ring: kept out of every operation
            nxt = succ[c[ok]]
            rt[g[ok], step] = tet[nxt]
            rv[g[ok], step + 1] = b[nxt]
            cur[live[ok]] = nxt
        closed = np.flatnonzero(~boundary & (n <= R))
        rv[closed, n[closed]] = -1  # a closed ring came back to p_0
        self.u, self.v, self.n, self.boundary = u[order[first]], v[order[first]], n, boundary
        self.tets, self.verts, self.keys, self.N = rt, rv, key[first], N

    def contains(self, a, b) -> np.ndarray:
        """(K,) bool: the edge (a, b) exists."""
        k = _edge_keys(np.asarray(a, np.int64), np.asarray(b, np.int64), self.N)
        p = np.minimum(np.searchsorted(self.keys, k), len(self.keys) - 1)
        return self.keys[p] == k


def _select_independent(items: np.ndarray, priority: np.ndarray, n_items: int) -> np.ndarray:
    """Greedy independent set: (C,) bool over candidates, no two sharing an item.

    ``items`` (C, W) lists each candidate's items (-1 padded). A candidate is taken when it
    has the best priority among all candidates touching each of its items, so the result
    is independent and holds the best candidate.
    """
    C = len(items)
    if C == 0:
        return np.zeros(0, dtype=bool)
    rank = np.empty(C, dtype=np.int64)
    rank[np.argsort(-priority, kind="stable")] = np.arange(C)
    valid = items >= 0
    claim = np.full(n_items, C, dtype=np.int64)
    r = np.broadcast_to(rank[:, None], items.shape)
    np.minimum.at(claim, items[valid], r[valid])
    return np.where(valid, claim[np.maximum(items, 0)] == r, True).all(axis=1)


def _locate(V: np.ndarray, T: np.ndarray, old: np.ndarray, points: np.ndarray, old_parent: np.ndarray) -> np.ndarray:
    """Parent of each point: the parent of the old tet (of the same candidate) in which the
    point lies most deeply (largest smallest barycentric coordinate).

    Args:
        old: (C, A) ids into ``T`` (-1 padded); points: (C, B, 3); old_parent: per id of T.
    Returns:
        (C, B) int64.
    """
    oc = V[T[np.maximum(old, 0)]]  # [C, A, 4, 3]
    D = np.stack([oc[:, :, 1] - oc[:, :, 0], oc[:, :, 2] - oc[:, :, 0], oc[:, :, 3] - oc[:, :, 0]], axis=-1)
    lam = np.einsum("caij,cbaj->cbai", np.linalg.pinv(D), points[:, :, None, :] - oc[:, None, :, 0])
    depth = np.minimum(1.0 - lam.sum(axis=-1), lam.min(axis=-1))  # [C, B, A]
    depth = np.where((old >= 0)[:, None, :], depth, -np.inf)
    return old_parent[np.take_along_axis(old, np.argmax(depth, axis=2), axis=1)]


# ---------------------------------------------------------------------------- the work mesh
class _Work:
    """The mesh under improvement: positions, tets, parents, surface budget, counters.

    Qualities come from :class:`holowarp.ops.improve.ImproveKernels` on ``device`` (whole
    meshes and flip candidates alike)."""

    def __init__(self, mesh: TetMesh, cfg: ImproveConfig, device: str):
        from holowarp.ops.improve import ImproveKernels

        self.kernels = ImproveKernels(device)
        self.device = self.kernels.device
        self.V = np.array(mesh.vertices, dtype=np.float64)  # [N, 3], replaced, never edited in place
        self.T = np.array(mesh.tets, dtype=np.int64)  # [M, 4]
        self.parent = np.arange(mesh.num_tets, dtype=np.int64)  # [M] input tet of each tet
        # [N] bound, m, on how far every boundary triangle at the vertex has moved from the
        # input surface (module docstring).
        self.err = np.zeros(len(self.V))
        # [M] tets changed since the last interior flip pass (only those can gain a flip).
        self.dirty = np.ones(mesh.num_tets, dtype=bool)
        self.mode = QUALITY_MEASURES[cfg.quality]
        self.cfg = cfg
        self.mean_edge = mean_boundary_edge(mesh)  # m, the input's: the unit of the surface budget
        self.counts = {"2-3": 0, "3-2": 0, "4-4": 0, "edge_removal_5+": 0, "boundary_edge_removal": 0,
                       "cap_removal": 0, "cap_vertex_removal": 0, "boundary_edge_collapse": 0, "overlap_removal": 0}
        self.splits = {"edge": 0, "face": 0}
        self._mesh = None
        self._q = None

    def mesh(self) -> TetMesh:
        if self._mesh is None:
            self._mesh = TetMesh(self.V.copy(), self.T, validate=False)
        return self._mesh

    def changed(self):
        """Forget derived data after ``T`` or ``V`` changed (``V`` is always replaced)."""
        self._mesh = None
        self._q = None

    def quality_of(self, T: np.ndarray) -> np.ndarray:
        """Quality (K,) of the tets T (K, 4) at the current positions."""
        return self.kernels.quality(self.V, T, self.mode)

    def quality(self) -> np.ndarray:
        if self._q is None:
            self._q = self.quality_of(self.T)
        return self._q

    def replace(self, drop: np.ndarray, new_tets: np.ndarray, new_parent: np.ndarray):
        keep = np.ones(len(self.T), dtype=bool)
        keep[drop] = False
        new_tets = new_tets.reshape(-1, 4)
        self.T = np.concatenate([self.T[keep], new_tets])
        self.parent = np.concatenate([self.parent[keep], new_parent.reshape(-1)])
        self.dirty = np.concatenate([self.dirty[keep], np.ones(len(new_tets), dtype=bool)])
        self.changed()


def _retriangulate_rings(w: _Work, u, v, rv, m: int, edges: _EdgeTable):
    """Best retriangulation of G rings of polygon size m around the edges (u, v).

    The ring's tets are replaced by a triangulation of the polygon ``rv`` (G, m) (in ring
    order), every triangle coned to u and to v; for an open fan the chord p_0 p_{m-1}
    closes the polygon. Returns (quality of the worst new tet (G,), their mean quality (G,),
    the new tets (G, 2(m-2), 4), ok (G,): the triangulation's inner diagonals are not edges
    yet).
    """
    tab = _POLYGONS[m]
    G = len(u)
    c = tab.combos
    pa, pb, pc = rv[:, c[:, 0]], rv[:, c[:, 1]], rv[:, c[:, 2]]  # [G, Cc]
    uu = np.broadcast_to(u[:, None], pa.shape)
    vv = np.broadcast_to(v[:, None], pa.shape)
    up = np.stack([uu, pa, pb, pc], axis=-1).reshape(-1, 4)
    dn = np.stack([vv, pa, pc, pb], axis=-1).reshape(-1, 4)
    qu, qd = w.quality_of(up).reshape(pa.shape), w.quality_of(dn).reshape(pa.shape)
    qc = np.minimum(qu, qd)  # [G, Cc]
    qt = qc[:, tab.tri].min(axis=2)  # [G, Tn]
    best = np.argmax(qt, axis=1)
    qbest = qt[np.arange(G), best]
    qmean = (qu + qd)[np.arange(G)[:, None], tab.tri[best]].sum(axis=1) / (2 * (m - 2))
    trs = c[tab.tri[best]]  # [G, m-2, 3] polygon positions
    A, B, C = (np.take_along_axis(rv, trs[:, :, i], axis=1) for i in range(3))
    uu, vv = np.broadcast_to(u[:, None], A.shape), np.broadcast_to(v[:, None], A.shape)
    new = np.concatenate([np.stack([uu, A, B, C], -1), np.stack([vv, A, C, B], -1)], axis=1)
    ok = np.ones(G, dtype=bool)
    dg = tab.diag[best]  # [G, m-3, 2]
    for j in range(dg.shape[1]):
        a_ = np.take_along_axis(rv, dg[:, j, :1], axis=1)[:, 0]
        b_ = np.take_along_axis(rv, dg[:, j, 1:], axis=1)[:, 0]
        ok &= ~edges.contains(a_, b_)
    return qbest, qmean, new, ok


def _pad(arrs, fill=-1):
    W = max(a.shape[1] for a in arrs)
    return np.concatenate([np.pad(a, [(0, 0), (0, W - a.shape[1])] + [(0, 0)] * (a.ndim - 2), constant_values=fill) for a in arrs])


def _interior_flip_pass(w: _Work) -> int:
    """One batch of 2-3 flips and interior edge removals (3-2, 4-4, 5-6, ...) among the
    faces and edges that touch a changed tet. Returns the number applied."""
    cfg = w.cfg
    T = w.T
    N = len(w.V)
    q = w.quality()
    dirty = w.dirty
    edges = _EdgeTable(T, N, cfg.max_ring)
    c_old, c_new, c_gain, c_kind = [], [], [], []

    # ---- 2-3 flips: interior faces (each once) with a bad tet on either side.
    adj = w.mesh().face_adjacency().astype(np.int64)
    e_ids, k_ids = np.nonzero(adj > np.arange(len(T))[:, None])
    f_ids = adj[e_ids, k_ids]
    qo = np.minimum(q[e_ids], q[f_ids])
    sel = (qo < cfg.flip_threshold) & (dirty[e_ids] | dirty[f_ids])
    e_ids, k_ids, f_ids, qo = e_ids[sel], k_ids[sel], f_ids[sel], qo[sel]
    if len(e_ids):
        d = T[e_ids, k_ids]
        face = T[e_ids[:, None], TET_FACES[k_ids]]  # [C, 3] outward from e
        o = T[f_ids].sum(axis=1) - face.sum(axis=1)  # the other apex
        new = np.stack([np.stack([d, o, face[:, i], face[:, (i + 1) % 3]], axis=1) for i in range(3)], axis=1)
        qn = w.quality_of(new.reshape(-1, 4)).reshape(-1, 3)
        gain = qn.min(axis=1) - qo
        # A flip must raise the worst tet and must not lower the tets' mean quality.
        keeps_mean = (qo < cfg.mean_guard) | (qn.mean(axis=1) >= 0.5 * (q[e_ids] + q[f_ids]))
        ok = (gain > cfg.min_gain) & keeps_mean & ~edges.contains(d, o)
        if ok.any():
            c_old.append(np.stack([e_ids, f_ids], axis=1)[ok])
            c_new.append(new[ok])
            c_gain.append(gain[ok])
            c_kind.append(np.full(int(ok.sum()), 2))

    # ---- edge removal: interior edges with a ring of 3..max_ring tets.
    for n in range(3, cfg.max_ring + 1):
        g = np.flatnonzero(~edges.boundary & (edges.n == n))
        if len(g) == 0:
            continue
        rt = edges.tets[g, :n]
        qold = q[rt].min(axis=1)
        s = (qold < cfg.flip_threshold) & dirty[rt].any(axis=1)
        g, rt, qold = g[s], rt[s], qold[s]
        if len(g) == 0:
            continue
        qbest, qmean, new, ok = _retriangulate_rings(w, edges.u[g], edges.v[g], edges.verts[g, :n], n, edges)
        gain = qbest - qold
        ok &= (gain > cfg.min_gain) & ((qold < cfg.mean_guard) | (qmean >= q[rt].mean(axis=1)))
        if ok.any():
            c_old.append(rt[ok])
            c_new.append(new[ok])
            c_gain.append(gain[ok])
            c_kind.append(np.full(int(ok.sum()), n))
    w.dirty[:] = False
    if not c_old:
        return 0
    old, new = _pad(c_old), _pad(c_new)
    gain, kind = np.concatenate(c_gain), np.concatenate(c_kind)
    take = _select_independent(old, gain, len(T))
    old, new, kind = old[take], new[take], kind[take]
    parents = _locate(w.V, T, old, w.V[np.maximum(new, 0)].mean(axis=2), w.parent)
    valid = new[:, :, 0] >= 0
    w.replace(old[old >= 0], new[valid], parents[valid])
    for k, name in ((2, "2-3"), (3, "3-2"), (4, "4-4")):
        w.counts[name] += int((kind == k).sum())
    w.counts["edge_removal_5+"] += int((kind >= 5).sum())
    return int(len(kind))


def _boundary_edge_keys(mesh: TetMesh, N: int) -> np.ndarray:
    bf = mesh.boundary_faces().astype(np.int64)
    e = np.concatenate([bf[:, [0, 1]], bf[:, [1, 2]], bf[:, [2, 0]]])
    return np.unique(_edge_keys(e[:, 0], e[:, 1], N))


class _Candidates:
    """Boundary changes collected for one pass: replaced tets, new tets, touched vertices,
    priority, surface move (m) and kind (0: cap vertex, 1: cap, k >= 2: fan of k)."""

    def __init__(self):
        self.old, self.new, self.verts, self.prio, self.h, self.kind = [], [], [], [], [], []

    def add(self, ok, old, new, verts, prio, h, kind: int):
        if ok.any():
            n = int(ok.sum())
            new = new[ok] if new.shape[1] else np.full((n, 1, 4), -1, dtype=np.int64)
            for lst, x in ((self.old, old[ok]), (self.new, new), (self.verts, verts[ok]), (self.prio, prio[ok]),
                           (self.h, h[ok]), (self.kind, np.full(n, kind))):
                lst.append(x)

    def arrays(self):
        return (_pad(self.old), _pad(self.new), _pad(self.verts), np.concatenate(self.prio), np.concatenate(self.h),
                np.concatenate(self.kind))


def _exposable(q, capped, under, q_self, threshold):
    """May the tets ``under`` (C, A) (-1: none) be exposed to the surface by deleting caps of
    quality ``q_self`` (C,)? Deleting a cap hands the tets under it to the surface, where only
    the surface budget could still improve them: so only decent ones, or caps themselves
    (two boundary faces) no worse than the deleted one, which become deletable in turn."""
    u = np.maximum(under, 0)
    return ((under < 0) | (q[u] >= threshold) | (capped[u] & (q[u] >= q_self[:, None]))).all(axis=1)


def _fan_candidates(w: _Work, cand: _Candidates, edges: _EdgeTable, k: int, bound: float, ctx: dict):
    """Removals of boundary edges whose open fan has k tets (k = 1: a cap)."""
    cfg, q, V, N = w.cfg, ctx["q"], w.V, len(w.V)
    g = np.flatnonzero(edges.boundary & (edges.n == k))
    rt = edges.tets[g, :k]
    qold = q[rt].min(axis=1) if len(g) else np.zeros(0)
    s = qold < cfg.boundary_threshold
    g, rt, qold = g[s], rt[s], qold[s]
    if len(g) == 0:
        return
    rv = edges.verts[g, : k + 1]
    u, v, p0, pk = edges.u[g], edges.v[g], rv[:, 0], rv[:, k]
    touched = np.concatenate([u[:, None], v[:, None], rv], axis=1)
    ok = w.err[touched].max(axis=1) <= bound
    if k == 1:
        # The chord becomes a boundary edge: it must not be one already (a pinch).
        ok &= ~np.isin(_edge_keys(p0, pk, N), ctx["bnd_keys"])
        ok &= _exposable(q, ctx["capped"], ctx["adj"][rt[:, 0]], qold, cfg.boundary_threshold)
        new = np.zeros((len(g), 0, 4), dtype=np.int64)
        prio = 1.0 - qold  # the worse the cap, the sooner
    else:
        ok &= ~edges.contains(p0, pk)
        qnew, qmean, new, diag_ok = _retriangulate_rings(w, u, v, rv, k + 1, edges)
        prio = qnew - qold
        ok &= diag_ok & (prio > cfg.min_gain) & ((qold < cfg.mean_guard) | (qmean >= q[rt].mean(axis=1)))
    # The quad's two boundary triangles flip to its other diagonal: measured only where the
    # change is otherwise allowed (the sampled distance is most of this pass's cost).
    h = np.zeros(len(g))
    i = np.flatnonzero(ok)
    h[i] = cfg.hausdorff_margin * _local_hausdorff(
        V, np.stack([np.stack([u[i], v[i], p0[i]], 1), np.stack([u[i], v[i], pk[i]], 1)], 1),
        np.stack([np.stack([u[i], p0[i], pk[i]], 1), np.stack([v[i], p0[i], pk[i]], 1)], 1),
    )
    ok[i] &= h[i] + w.err[touched[i]].max(axis=1) <= bound
    cand.add(ok, rt, new, touched, prio, h, k)


def _cap_vertex_candidates(w: _Work, cand: _Candidates, bound: float, ctx: dict):
    """Deletions of tets whose apex has valence one (three boundary faces), with the apex."""
    cfg, q, T, bmask = w.cfg, ctx["q"], w.T, ctx["bmask"]
    three = np.flatnonzero((bmask.sum(axis=1) == 3) & (q < cfg.boundary_threshold))
    if len(three) == 0:
        return
    loc = np.argmin(bmask[three], axis=1)  # the apex is opposite the interior face
    apex = T[three, loc]
    base = T[three[:, None], TET_FACES[loc]]
    cone = np.stack([np.stack([apex, base[:, i], base[:, (i + 1) % 3]], 1) for i in range(3)], 1)
    h = cfg.hausdorff_margin * _local_hausdorff(w.V, cone, base[:, None, :])
    valence = np.bincount(T.reshape(-1), minlength=len(w.V))
    ok = (valence[apex] == 1) & (h + w.err[T[three]].max(axis=1) <= bound)
    ok &= _exposable(q, ctx["capped"], ctx["adj"][three, loc][:, None], q[three], cfg.boundary_threshold)
    ok &= ctx["adj"][three, loc] >= 0
    cand.add(ok, three[:, None], np.zeros((len(three), 0, 4), dtype=np.int64), T[three], 1.0 - q[three], h, 0)


def _collapse_candidates(w: _Work, cand: _Candidates, edges: _EdgeTable, bound: float, ctx: dict):
    """Collapses of short boundary edges (module docstring, step 1): a boundary edge (u, v)
    shorter than ``collapse_ratio`` mean boundary edges whose open fan holds a tet below
    ``boundary_threshold`` becomes one new vertex at u, at v or at their midpoint (three
    candidates): the tets around u and v are replaced by the same tets with both moved
    there, and the edge's fan vanishes. Appends the positions of the candidates that pass
    to ``w.V`` (the ones not applied stay unused) and adds them to ``cand``.

    A flip keeps every vertex, so a boundary triangle with one edge far shorter than the
    others (the polish's slide along a crease leaves some) stays a needle whatever the tets
    under it: bob's README job (fast, 128²) ended §7b at 8.9° on one such tet, under a
    0.006 edge where the mean boundary edge is 0.03."""
    cfg, q, V, T, N = w.cfg, ctx["q"], w.V, w.T, len(w.V)
    if cfg.collapse_ratio <= 0:
        return
    g = np.flatnonzero(edges.boundary & (edges.n <= edges.tets.shape[1]))
    g = g[np.linalg.norm(V[edges.u[g]] - V[edges.v[g]], axis=1) < cfg.collapse_ratio * w.mean_edge]
    fan = edges.tets[g]
    g = g[np.where(fan >= 0, q[np.maximum(fan, 0)], np.inf).min(axis=1) < cfg.boundary_threshold]
    if len(g) == 0:
        return
    u, v = np.tile(edges.u[g], 3), np.tile(edges.v[g], 3)
    k = len(g)
    pos = np.concatenate([V[u[:k]], V[v[:k]], 0.5 * (V[u[:k]] + V[v[:k]])])
    C = len(u)
    m = N + np.arange(C)  # the merged vertex of each candidate, in the extended positions
    Vx = np.concatenate([V, pos])
    offs, ids, _ = _vertex_stars(T, N)  # only here: most passes have no short edge
    su, sv = _padded_rows(offs, ids, u), _padded_rows(offs, ids, v)
    sv = np.where((T[np.maximum(sv, 0)] == u[:, None, None]).any(axis=2), -1, sv)  # the fan: in su already
    star = np.concatenate([su, sv], axis=1)
    live = star >= 0
    old_t = np.where(live[:, :, None], T[np.maximum(star, 0)], -1)  # [C, S, 4]
    hit = (old_t == u[:, None, None]) | (old_t == v[:, None, None])
    keep = live & (hit.sum(axis=2) == 1)
    new = np.where(keep[:, :, None], np.where(hit, m[:, None, None], old_t), -1)
    qn = np.full(keep.shape, np.inf)
    qn[keep] = w.kernels.quality(Vx, new[keep], w.mode)
    q_old = np.where(live, q[np.maximum(star, 0)], np.nan)
    qold, qnew = np.nanmin(q_old, axis=1), qn.min(axis=1)
    mean_old = np.nanmean(q_old, axis=1)
    mean_new = np.where(keep, qn, 0.0).sum(axis=1) / np.maximum(keep.sum(axis=1), 1)
    prio = qnew - qold
    ok = keep.any(axis=1) & (prio > cfg.min_gain) & ((qold < cfg.mean_guard) | (mean_new >= mean_old))
    # Tets (u, x, y, z) and (v, x, y, z) would both become (m, x, y, z): the link condition's
    # failure, which no manifold check sees when the pair is all there is of them.
    c, j = np.nonzero(keep)
    rest = np.sort(np.where(new[c, j] == m[c, None], -1, new[c, j]), axis=1)[:, 1:]  # the three others
    _, first, count = np.unique(np.column_stack([c, rest]), axis=0, return_index=True, return_counts=True)
    ok[c[first[count > 1]]] = False
    touched = old_t.reshape(C, -1)
    budget = np.where(touched >= 0, w.err[np.maximum(touched, 0)], 0.0).max(axis=1)
    ok &= budget <= bound
    # The surface patch: the boundary triangles at u and v before, the same at the merged
    # vertex after (the two on the edge vanish).
    bm = ctx["bmask"][np.maximum(star, 0)] & live[:, :, None]  # [C, S, 4]
    old_f = np.where(bm[..., None], old_t[:, :, TET_FACES], -1).reshape(C, -1, 3)
    hit_f = (old_f == u[:, None, None]) | (old_f == v[:, None, None])
    new_f = np.where(hit_f, m[:, None, None], old_f)
    new_f = np.where((hit_f.sum(axis=2) > 1)[..., None], -1, new_f)
    old_f, new_f = _leading_rows(old_f), _leading_rows(new_f)  # few of the 4 S rows are boundary faces
    h = np.zeros(C)
    i = np.flatnonzero(ok)
    h[i] = cfg.hausdorff_margin * _patch_hausdorff(Vx[np.maximum(old_f[i], 0)], Vx[np.maximum(new_f[i], 0)],
                                                   old_f[i, :, 0] >= 0, new_f[i, :, 0] >= 0)
    ok[i] &= h[i] + budget[i] <= bound
    if not ok.any():
        return
    # Keep the positions of the candidates that passed, renumbered after the current ones.
    ids_new = np.full(C, -1)
    ids_new[ok] = N + np.arange(int(ok.sum()))
    new = np.where(new >= N, ids_new[np.maximum(new - N, 0)], new)
    w.V = np.concatenate([V, pos[ok]])
    w.err = np.concatenate([w.err, np.zeros(int(ok.sum()))])
    w._mesh = None  # unused vertices added; the tets, and so their qualities, are as they were
    touched = np.concatenate([touched, ids_new[:, None]], axis=1)
    cand.add(ok, star, new, touched, prio, h, -1)


def _leading_rows(f: np.ndarray) -> np.ndarray:
    """``f`` (C, A, 3) with each candidate's valid rows (first entry >= 0) moved to the front
    and the columns no candidate uses dropped."""
    valid = f[:, :, 0] >= 0
    order = np.argsort(~valid, axis=1, kind="stable")
    width = max(int(valid.sum(axis=1).max()), 1) if len(f) else 1
    return np.take_along_axis(f, order[:, :width, None], axis=1)


def _padded_rows(offs: np.ndarray, ids: np.ndarray, rows: np.ndarray) -> np.ndarray:
    """CSR rows as a (len(rows), longest) array, -1 padded."""
    owner, entry = _gather_csr(offs, ids, rows)
    size = offs[rows + 1] - offs[rows]
    out = np.full((len(rows), max(int(size.max()), 1) if len(rows) else 1), -1, dtype=np.int64)
    out[owner, np.arange(len(owner)) - np.repeat(np.cumsum(size) - size, size)] = entry
    return out


def _boundary_pass(w: _Work, signature: tuple, bound: float) -> int:
    """One batch of boundary edge removals and cap deletions (module docstring, step 1).
    Returns the number applied."""
    N = len(w.V)
    mesh = w.mesh()
    bmask = mesh.boundary_mask()
    ctx = {"q": w.quality(), "bnd_keys": _boundary_edge_keys(mesh, N), "adj": mesh.face_adjacency().astype(np.int64),
           "bmask": bmask, "capped": bmask.sum(axis=1) >= 2}
    edges = _EdgeTable(w.T, N, w.cfg.max_boundary_ring + 1)
    cand = _Candidates()
    for k in range(1, w.cfg.max_boundary_ring + 1):
        _fan_candidates(w, cand, edges, k, bound, ctx)
    _cap_vertex_candidates(w, cand, bound, ctx)
    _collapse_candidates(w, cand, edges, bound, ctx)
    if not cand.old:
        return 0
    old, new, vts, prio, h, kind = cand.arrays()
    # Vertex-disjoint: two boundary changes sharing a vertex are never judged apart.
    take = _select_independent(vts, prio, len(w.V))  # collapses add vertices
    old, new, vts, h, kind = old[take], new[take], vts[take], h[take], kind[take]
    applied = _apply_checked(w, signature, old, new, vts, np.arange(len(kind)), depth=6)
    if len(applied) == 0:
        return 0
    vv = vts[applied]
    e_new = np.where(vv >= 0, w.err[np.maximum(vv, 0)], 0.0).max(axis=1) + h[applied]
    # Every new boundary triangle of a change lies within e_new of the input surface.
    np.maximum.at(w.err, vv[vv >= 0], np.broadcast_to(e_new[:, None], vv.shape)[vv >= 0])
    kk = kind[applied]
    w.counts["cap_vertex_removal"] += int((kk == 0).sum())
    w.counts["cap_removal"] += int((kk == 1).sum())
    w.counts["boundary_edge_removal"] += int((kk >= 2).sum())
    w.counts["boundary_edge_collapse"] += int((kk < 0).sum())
    return int(len(applied))


def _apply_checked(w: _Work, signature: tuple, old, new, vts, idx, depth: int) -> np.ndarray:
    """Apply the boundary changes ``idx`` if the topology signature survives; otherwise drop
    the ones at non-manifold vertices and retry, or try both halves. Returns those applied."""
    if len(idx) == 0:
        return idx
    T, V = w.T, w.V
    o, nw = old[idx], new[idx]
    valid = nw[:, :, 0] >= 0
    keep = np.ones(len(T), dtype=bool)
    keep[o[o >= 0]] = False
    T2 = np.concatenate([T[keep], nw[valid]])
    trial, _ = TetMesh(V, T2, validate=False).remove_unused_vertices()
    if trial.topology_signature() == signature:
        parents = _locate(V, T, o, V[np.maximum(nw, 0)].mean(axis=2), w.parent)
        w.replace(o[o >= 0], nw[valid], parents[valid])
        return idx
    if depth <= 0 or len(idx) == 1:
        return idx[:0]
    used = np.unique(T2)  # trial's vertices are compacted: map the offenders back
    bad = used[np.union1d(trial.non_manifold_edges().ravel(), trial.non_manifold_vertices())]
    if len(bad):
        hit = np.isin(vts[idx], bad).any(axis=1)
        if hit.any() and not hit.all():
            return _apply_checked(w, signature, old, new, vts, idx[~hit], depth - 1)
    half = len(idx) // 2
    a = _apply_checked(w, signature, old, new, vts, idx[:half], depth - 1)
    b = _apply_checked(w, signature, old, new, vts, idx[half:], depth - 1)
    return np.concatenate([a, b])


# ---------------------------------------------------------------------------- smoothing
def _vertex_stars(T: np.ndarray, N: int):
    """CSR vertex -> incident tets: offsets (N+1,), tet ids (4M,), local index (4M,)."""
    flat = T.reshape(-1)
    order = np.argsort(flat, kind="stable")
    offs = np.zeros(N + 1, dtype=np.int64)
    np.cumsum(np.bincount(flat, minlength=N), out=offs[1:])
    return offs, order // 4, order % 4


def _gather_csr(offs: np.ndarray, ids: np.ndarray, rows: np.ndarray):
    """Entries of CSR rows: (owner row index (K,), entry (K,)) for the given rows."""
    cnt = offs[rows + 1] - offs[rows]
    owner = np.repeat(np.arange(len(rows)), cnt)
    pos = np.repeat(offs[rows], cnt) + np.arange(int(cnt.sum())) - np.repeat(np.cumsum(cnt) - cnt, cnt)
    return owner, ids[pos]


def _colour_classes(edges: np.ndarray, active: np.ndarray, rng) -> list[np.ndarray]:
    """Partition the active vertices into independent sets of the edge graph
    (Jones & Plassmann 1993: a vertex joins the current set when its random priority beats
    every still-uncoloured active neighbour's)."""
    N = len(active)
    pri = rng.random(N)
    left = active.copy()
    a, b = edges[:, 0], edges[:, 1]
    live = left[a] & left[b]
    a, b = a[live], b[live]
    out = []
    while left.any():
        best = np.full(N, -1.0)
        np.maximum.at(best, a, pri[b])
        np.maximum.at(best, b, pri[a])
        pick = left & (pri > best)
        out.append(np.flatnonzero(pick))
        left &= ~pick
        keep = left[a] & left[b]
        a, b = a[keep], b[keep]
    return out


def _tangent_projectors(mesh: TetMesh, ratio: float) -> np.ndarray:
    """(N, 3, 3) projector onto each vertex's allowed directions: identity inside, the
    complement of the boundary normal space on the boundary (module docstring)."""
    N = mesh.num_vertices
    P = np.broadcast_to(np.eye(3), (N, 3, 3)).copy()
    bf = mesh.boundary_faces().astype(np.int64)
    if len(bf) == 0:
        return P
    V = mesh.vertices
    n = np.cross(V[bf[:, 1]] - V[bf[:, 0]], V[bf[:, 2]] - V[bf[:, 0]])
    area = np.linalg.norm(n, axis=1)
    nu = n / np.maximum(area, 1e-300)[:, None]
    outer = area[:, None, None] * nu[:, :, None] * nu[:, None, :]  # [F, 3, 3]
    cov = np.zeros((N, 3, 3))
    for j in range(3):
        np.add.at(cov, bf[:, j], outer)
    sv = np.unique(bf)
    lam, vec = np.linalg.eigh(cov[sv])  # ascending
    normal = (lam > ratio * lam[:, 2:3]).astype(np.float64)  # [S, 3]
    P[sv] = np.eye(3) - np.einsum("sij,skj,sj->sik", vec, vec, normal)
    return P


def _smooth(w: _Work, proj: np.ndarray, bound: float, rng, passes: int, only=None) -> np.ndarray:
    """Smooth ``passes`` times (module docstring, step 3); returns (N,) bool, the vertices
    that moved.

    A boundary vertex moves only to positions where its boundary triangles move (two-sided
    Hausdorff, measured in the kernel) by no more than ``bound - w.err`` there; the move is
    then charged to ``w.err`` of the triangles' vertices. ``only``: smooth just these
    vertices, which must form one independent set (no two in a tet); by default every
    vertex with a tet below ``smooth_threshold`` (``boundary_threshold`` for boundary
    vertices) in its star, in the independent sets of a colouring."""
    cfg, T, N = w.cfg, w.T, len(w.V)
    mesh = w.mesh()
    bf = mesh.boundary_faces().astype(np.int64)
    on_b = np.zeros(N, dtype=bool)
    on_b[bf.reshape(-1)] = True
    if only is None:
        q = w.quality()
        bad_i = np.zeros(N, dtype=bool)
        bad_i[T[q < cfg.smooth_threshold].reshape(-1)] = True
        bad_b = np.zeros(N, dtype=bool)
        bad_b[T[q < cfg.boundary_threshold].reshape(-1)] = True
        movable = np.where(on_b, bad_b, bad_i) & (np.abs(proj).sum(axis=(1, 2)) > 1e-12)
    else:
        movable = np.zeros(N, dtype=bool)
        movable[only] = True
    if not movable.any():
        return movable
    f_offs = np.zeros(N + 1, dtype=np.int64)  # boundary triangles per vertex (CSR)
    np.cumsum(np.bincount(bf.reshape(-1), minlength=N), out=f_offs[1:])
    f_ids = np.argsort(bf.reshape(-1), kind="stable") // 3
    params = (cfg.smooth_beta, cfg.smooth_step, cfg.smooth_line_steps, cfg.smooth_fd, 0.1 * cfg.min_gain,
              cfg.surface_samples, cfg.hausdorff_margin, cfg.mean_guard)
    sp = w.kernels.smoothing_pass(w.V, T, _vertex_stars(T, N), (f_offs, f_ids, bf), proj, w.mode, params)
    edges = mesh.edges().astype(np.int64) if only is None else None
    moved = np.zeros(N, dtype=bool)
    for _ in range(passes):
        classes = [np.flatnonzero(movable)] if only is not None else _colour_classes(edges, movable, rng)
        for cls in classes:
            qb, qa, h = sp.step(cls, np.maximum(bound - w.err, 0.0))
            went = qa > qb
            moved[cls[went]] = True
            charged = went & (h > 0)
            if charged.any():
                _charge_umbrellas(w, cls[charged], h[charged], bf, f_offs, f_ids)
    w.V = sp.positions()
    w.changed()
    # Every tet of a moved vertex may now gain a flip.
    w.dirty |= moved[T].any(axis=1)
    return moved


def _charge_umbrellas(w: _Work, verts, h, bf, f_offs, f_ids):
    """Record that the boundary triangles around each of ``verts`` moved by ``h`` (m): they
    now lie within (old bound at the vertex + h) of the input surface, and every vertex of
    those triangles has to respect that bound from now on."""
    w.err[verts] += h
    owner, fid = _gather_csr(f_offs, f_ids, verts)
    np.maximum.at(w.err, bf[fid].reshape(-1), np.repeat(w.err[verts][owner], 3))


def _remeasure_budget(w: _Work, ref) -> None:
    """Replace the accumulated per-vertex surface bounds ``w.err`` by measured ones.

    Adding every move's local bound to ``err`` (the triangle inequality) over-counts moves
    that partly undo each other: on the dented box, 607 of the 748 boundary vertices whose
    ``err`` had reached 90% of the bound were truly within half of it, and the last
    slivers sat exactly there. So before each round that may move the surface, ``err[v]``
    becomes ``hausdorff_margin`` times the larger of
      - the farthest sampled point of v's boundary triangles from the input surface, and
      - the farthest input-surface sample whose closest current point lies on one of them,
    which bounds both sides of the Hausdorff distance over v's umbrella as the charges do.

    Args:
        ref: the input surface as (vertices (P, 3), faces (Q, 3), samples (S, 3) on it).
    """
    va, fa, samples = ref
    bf = w.mesh().boundary_faces().astype(np.int64)
    N = len(w.V)
    err = np.zeros(N)
    if len(bf):
        pts = np.einsum("kj,fjd->fkd", _PATCH_GRID, w.V[bf]).reshape(-1, 3)
        out = _point_surface_distance(pts, va, fa, w.device).reshape(len(bf), -1).max(axis=1)
        face, _ = w.kernels.closest_faces(samples, w.V, bf)
        hit = face >= 0
        g = bf[face[hit]]
        back = np.zeros(len(bf))
        np.maximum.at(back, face[hit], _closest_on_triangles(samples[hit], w.V[g[:, 0]], w.V[g[:, 1]], w.V[g[:, 2]]))
        np.maximum.at(err, bf.reshape(-1), np.repeat(w.cfg.hausdorff_margin * np.maximum(out, back), 3))
    w.err = err


# ---------------------------------------------------------------------------- sliver removal
def _split_simplices(w: _Work, bad: np.ndarray, q: np.ndarray):
    """For each bad tet, the simplex to split and the tets holding it: its longest interior
    edge, else (all edges on the boundary) its largest interior face. Returns simplices
    (S, 3) (edges padded with -1), rings (S, R) (-1 padded) and priorities (S,)."""
    T, V, N = w.T, w.V, len(w.V)
    mesh = w.mesh()
    eu, ev = T[bad][:, TET_EDGES[:, 0]], T[bad][:, TET_EDGES[:, 1]]
    inner = ~np.isin(_edge_keys(eu, ev, N), _boundary_edge_keys(mesh, N))  # [B, 6]
    has_inner = inner.any(axis=1)
    simplices, rings, prio = [], [], []
    eb = np.flatnonzero(has_inner)
    if len(eb):
        ln = np.linalg.norm(V[eu[eb]] - V[ev[eb]], axis=2)
        j = np.argmax(np.where(inner[eb], ln, -1.0), axis=1)
        su, sv = eu[eb, j], ev[eb, j]
        _, first = np.unique(_edge_keys(su, sv, N), return_index=True)
        su, sv = su[first], sv[first]
        offs, st, _ = _vertex_stars(T, N)
        owner, flat = _gather_csr(offs, st, su)  # the tets of u's star that hold v
        hit = np.any(T[flat] == sv[owner][:, None], axis=1)
        owner, flat = owner[hit], flat[hit]
        n_ring = np.bincount(owner, minlength=len(su))
        ring = np.full((len(su), max(int(n_ring.max()), 2)), -1, dtype=np.int64)
        ring[owner, np.arange(len(owner)) - np.repeat(np.cumsum(n_ring) - n_ring, n_ring)] = flat
        worst = np.full(len(su), np.inf)
        np.minimum.at(worst, owner, q[flat])
        simplices.append(np.stack([su, sv, np.full_like(su, -1)], axis=1))
        rings.append(ring)
        prio.append(-worst)
    fb = bad[~has_inner]
    if len(fb):
        adj = mesh.face_adjacency().astype(np.int64)[fb]
        P = V[T[fb][:, TET_FACES]]  # [F, 4, 3, 3]
        area = np.linalg.norm(np.cross(P[:, :, 1] - P[:, :, 0], P[:, :, 2] - P[:, :, 0]), axis=2)
        k = np.argmax(np.where(adj >= 0, area, -1.0), axis=1)
        other = adj[np.arange(len(fb)), k]
        okf = other >= 0
        if okf.any():
            fb, k, other = fb[okf], k[okf], other[okf]
            simplices.append(T[fb[:, None], TET_FACES[k]])
            rings.append(np.stack([fb, other], axis=1))
            prio.append(-np.minimum(q[fb], q[other]))
    if not simplices:
        return None
    return np.concatenate(simplices), _pad(rings), np.concatenate(prio)


def _split_pass(w: _Work, limit: int) -> int:
    """Sliver removal by vertex insertion (module docstring, step 4) for at most ``limit``
    tets below ``split_threshold``, worst first. Returns the splits kept."""
    cfg, T, V = w.cfg, w.T, w.V
    N, M = len(V), len(T)
    q = w.quality()
    bad = np.flatnonzero(q < cfg.split_threshold)
    if len(bad) == 0 or limit <= 0:
        return 0
    found = _split_simplices(w, bad[np.argsort(q[bad])][:limit], q)
    if found is None:
        return 0
    simplex, ring, prio = found
    take = _select_independent(ring, prio, M)
    ring, simplex = ring[take], simplex[take]
    S = len(simplex)
    m_ids = N + np.arange(S)
    on = simplex >= 0
    mid = np.einsum("sk,skd->sd", on.astype(np.float64), V[np.maximum(simplex, 0)]) / on.sum(axis=1)[:, None]
    # Each tet holding the simplex is copied once per simplex vertex, that vertex -> m.
    rt = ring[ring >= 0]
    owner = np.repeat(np.arange(S), (ring >= 0).sum(axis=1))
    kids, kid_owner, kid_parent = [], [], []
    for c in range(3):
        vc = simplex[owner, c]
        ok = vc >= 0
        t = T[rt[ok]].copy()
        t[t == vc[ok][:, None]] = m_ids[owner[ok]]
        kids.append(t), kid_owner.append(owner[ok]), kid_parent.append(w.parent[rt[ok]])
    kids, kid_owner, kid_parent = np.concatenate(kids), np.concatenate(kid_owner), np.concatenate(kid_parent)
    ring_worst = np.full(S, np.inf)
    np.minimum.at(ring_worst, owner, q[rt])
    saved = (w.V, w.T, w.parent, w.err, w.dirty)
    w.V = np.concatenate([V, mid])
    w.err = np.concatenate([w.err, np.zeros(S)])  # new vertices are interior
    w.replace(rt, kids, kid_parent)
    Nn = len(w.V)
    _smooth(w, np.broadcast_to(np.eye(3), (Nn, 3, 3)).copy(), 0.0, None, cfg.split_smooth_passes, only=m_ids)
    kid_worst = np.full(S, np.inf)
    np.minimum.at(kid_worst, kid_owner, w.quality_of(kids))
    good = kid_worst > ring_worst + cfg.min_gain
    if not good.all():
        # Undo the splits that did not pay: their tets come back, their vertex stays unused.
        Vn = w.V
        w.V, w.T, w.parent, w.err, w.dirty = saved
        if good.any():
            w.V = np.concatenate([V, Vn[N:]])
            w.err = np.concatenate([w.err, np.zeros(S)])
            g = good[kid_owner]
            w.replace(rt[good[owner]], kids[g], kid_parent[g])
        w.changed()
    w.splits["edge"] += int((good & ~on[:, 2]).sum())
    w.splits["face"] += int((good & on[:, 2]).sum())
    return int(good.sum())


# ---------------------------------------------------------------------------- the stage
def improve(mesh: TetMesh, config: ImproveConfig = ImproveConfig(), *, device: str = "cpu", progress=None):
    """Improve the elements of a valid tet mesh (method.md §7b; module docstring).

    Args:
        mesh: positively oriented tet mesh (zero-volume tets are allowed, inverted ones
            not), usually cleanup's output: one component, manifold boundary.
        config: :class:`ImproveConfig`.
        device: Warp device of the quality and smoothing kernels (``"cpu"``, ``"cuda[:N]"``).
        progress: optional tqdm-like bar, updated once per round.

    Returns:
        ``(mesh, parent, info)``:

        - the improved mesh (positively oriented, unused vertices removed);
        - ``parent`` (K,) int64: for each output tet an input tet it derives from (the tet
          it was split from, or, for a flip, the replaced tet that held its centroid);
        - ``info``, the ``report.json -> improve`` section: ``flips`` (counts by type:
          ``2-3``, ``3-2``, ``4-4``, ``edge_removal_5+``, ``boundary_edge_removal``,
          ``cap_removal``, ``cap_vertex_removal``, ``boundary_edge_collapse``,
          ``overlap_removal``: step 5), ``splits``
          (``edge``, ``face``),
          ``vertices_smoothed``, ``before``/``after`` (tets, vertices, worst and mean
          minimum dihedral in degrees, mean and worst aspect ratio, min and mean quality,
          minimum eta, inverted, tets under the 10° target),
          ``eta_histogram_before``/``_after`` (counts per bin of ``bin_edges``,
          :data:`ETA_HISTOGRAM_EDGES` by default, and ``below_0.01``),
          ``mean_boundary_edge`` (m), ``surface_hausdorff`` (m) and
          ``surface_hausdorff_mean_edges`` (in input mean boundary edges),
          ``surface_move_bound_mean_edges``, ``topology``, ``rounds``, ``seconds``, and
          ``targets``: :func:`element_targets` of ``after`` (method.md §7b's four).

    Raises:
        ValueError: an empty mesh or inverted tets.
        holowarp.device.DeviceError: an unavailable device.
    """
    from holowarp.device import resolve_device

    t0 = time.perf_counter()
    cfg = config
    device = resolve_device(device)
    if mesh.num_tets == 0:
        raise ValueError("improve: the mesh has no tetrahedra")
    vol = mesh.signed_volumes()
    if np.any(vol < 0):
        raise ValueError(
            f"improve: {int(np.count_nonzero(vol < 0))} of {mesh.num_tets} tets are inverted; "
            "orient the mesh first (TetMesh.oriented) or run cleanup"
        )
    mesh, _ = mesh.remove_unused_vertices()
    w = _Work(mesh, cfg, device)
    signature = mesh.topology_signature()
    L = w.mean_edge
    bound = cfg.max_surface_move * L
    rng = np.random.default_rng(0)
    q0 = w.quality()
    before = _summary(w.V, w.T, q0)
    ref = _surface_reference(mesh) if cfg.remeasure_budget and bound > 0 else None
    rounds, moved = _rounds(w, signature, bound, ref, rng, np.zeros(len(w.V), dtype=bool), progress)
    refinement, more, moved = _refine_if_thin(w, signature, bound, ref, rng, moved, progress)
    rounds += more
    w.counts["overlap_removal"] = _peel_overlaps(w, signature)
    out, _ = TetMesh(w.V, w.T, validate=False).remove_unused_vertices()
    info = _report(w, mesh, out, before, L, signature, int(moved.sum()))
    info.update(rounds=rounds, refinement=refinement, seconds=time.perf_counter() - t0)
    return out, w.parent.copy(), info


def _refine_if_thin(w: _Work, signature: tuple, bound: float, ref, rng, moved: np.ndarray, progress):
    """When more than ``thin_fraction`` of the tets are thin after the rounds, red-refine
    every tet and run the rounds again, kept only if that lowers neither the worst quality
    nor the mean. Returns (the report's ``refinement`` or None, rounds run, moved (N,) bool)."""
    cfg = w.cfg
    share = _thin_share(w)
    if cfg.thin_fraction is None or share <= cfg.thin_fraction:
        return None, 0, moved
    tets_before, q_before = len(w.T), w.quality()
    saved = (w.V, w.T, w.parent, w.err, dict(w.counts), dict(w.splits), moved)
    _red_refine(w)
    w.cfg = replace(cfg, boundary_threshold=max(cfg.boundary_threshold, cfg.thin_boundary_threshold))
    more, moved = _rounds(w, signature, bound, ref, rng, np.r_[moved, np.zeros(len(w.V) - len(moved), bool)], progress)
    w.cfg = cfg
    q = w.quality()
    # Kept only if it lowers neither the worst tet nor the mean: refinement is for meshes
    # that the rounds could not improve from inside, not a second lottery on the worst.
    kept = bool(q.min() >= q_before.min() and q.mean() >= q_before.mean())
    if not kept:
        w.V, w.T, w.parent, w.err, w.counts, w.splits, moved = saved
        w.dirty = np.zeros(len(w.T), dtype=bool)
        w.changed()
    return ({"thin_fraction": share, "tets_before": tets_before, "tets_after_refinement": 8 * tets_before,
             "rounds": more, "kept": kept}, more, moved)


def _peel_overlaps(w: _Work, signature: tuple) -> int:
    """Step 5 of the module docstring: delete the tets
    :func:`holowarp.stages.cleanup.overlap_ends` picks where a boundary edge's tets wrap
    past a full turn, batch by batch through the topology check, trying an edge's other
    end where the first one fails it. Ends: a round deletes a tet or rules one out, and
    deleting tets raises no wedge. Returns the number of tets deleted."""
    failed: set = set()
    deleted = 0
    while True:
        ends = overlap_ends(w.mesh(), skip=lambda tt: np.array([tuple(np.sort(t)) in failed for t in w.T[tt]], bool))
        if len(ends) == 0:
            break
        keys = [tuple(np.sort(t)) for t in w.T[ends]]  # before the deletions renumber the tets
        applied = _apply_checked(w, signature, ends[:, None], np.full((len(ends), 1, 4), -1, dtype=np.int64),
                                 w.T[ends].astype(np.int64), np.arange(len(ends)), depth=6)
        done = set(applied.tolist())
        failed.update(k for i, k in enumerate(keys) if i not in done)
        deleted += len(applied)
    return deleted


def _surface_reference(mesh: TetMesh):
    """The input surface for :func:`_remeasure_budget`: (vertices, faces, samples)."""
    va, fa = mesh.surface_mesh()
    va, fa = np.asarray(va, np.float64), np.asarray(fa, np.int64)
    return va, fa, np.einsum("kj,fjd->fkd", _PATCH_GRID, va[fa]).reshape(-1, 3)


def _rounds(w: _Work, signature: tuple, bound: float, ref, rng, moved: np.ndarray, progress) -> tuple[int, np.ndarray]:
    """Rounds (module docstring) until one raises neither the worst nor the mean quality and
    splits nothing, or ``max_rounds``; returns (rounds run, vertices smoothed (N,) bool)."""
    cfg = w.cfg
    q0 = w.quality()
    best_worst, best_mean = float(q0.min()), float(q0.mean())
    rounds = 0
    for rounds in range(1, cfg.max_rounds + 1):
        if rounds > cfg.inside_rounds and ref is not None:
            _remeasure_budget(w, ref)
        moved = _round(w, signature, bound if rounds > cfg.inside_rounds else 0.0, rng, moved)
        q = w.quality()
        worst, mean = float(q.min()), float(q.mean())
        progressed = worst > best_worst + cfg.min_gain or mean > best_mean + cfg.mean_tol
        best_worst, best_mean = max(best_worst, worst), max(best_mean, mean)
        if progress is not None:
            progress.update(1)
            progress.set_postfix(worst=f"{worst:.3f}", mean=f"{mean:.3f}", tets=len(w.T), refresh=False)
        if worst < cfg.split_threshold and _split_pass(w, max(1, int(cfg.max_splits_fraction * len(w.T)))) > 0:
            continue
        if not progressed and rounds > cfg.inside_rounds:
            break
    return rounds, moved


# ---------------------------------------------------------------------------- thin meshes
def _thin_share(w: _Work) -> float:
    """Share of the tets whose four vertices all lie on the boundary (0 for no tets)."""
    bf = w.mesh().boundary_faces().reshape(-1)
    on_b = np.zeros(len(w.V), dtype=bool)
    on_b[bf] = True
    return float(on_b[w.T].all(axis=1).mean()) if len(w.T) else 0.0


def _red_refine(w: _Work) -> None:
    """Split every tet into eight (Bey's red refinement): a vertex at every edge midpoint,
    four corner tets like the parent, and the inner octahedron cut into four along its
    shortest diagonal. Midpoints of boundary edges lie on the boundary triangles, so the
    surface is unchanged as a point set; each child keeps its parent's parent, and a new
    vertex the surface bound of its edge's ends (its triangles lie inside theirs)."""
    V, T, N = w.V, w.T, len(w.V)
    e = np.sort(T[:, TET_EDGES], axis=2).reshape(-1, 2)
    keys, inv = np.unique(e[:, 0] * N + e[:, 1], return_inverse=True)
    eu, ev = keys // N, keys % N
    mid = (N + inv.reshape(-1, 6)).T  # midpoints of the local edges ab ac ad bc bd cd
    V2 = np.concatenate([V, 0.5 * (V[eu] + V[ev])])
    a, b, c, d = T.T
    ab, ac, ad, bc, bd, cd = mid
    kids = [(a, ab, ac, ad), (ab, b, bc, bd), (ac, bc, c, cd), (ad, bd, cd, d)]
    # The octahedron around each diagonal, its other four corners in cyclic order.
    octs = (((ab, cd), (ac, bc, bd, ad)), ((ac, bd), (ab, bc, cd, ad)), ((ad, bc), (ab, ac, cd, bd)))
    length = np.stack([np.linalg.norm(V2[p] - V2[q], axis=1) for (p, q), _ in octs], axis=1)
    best = np.argmin(length, axis=1)
    pick = lambda xs: np.choose(best, xs)  # noqa: E731
    p, q = pick([o[0][0] for o in octs]), pick([o[0][1] for o in octs])
    ring = [pick([o[1][i] for o in octs]) for i in range(4)]
    kids += [(p, q, ring[i], ring[(i + 1) % 4]) for i in range(4)]
    T2 = np.concatenate([np.stack(k, axis=1) for k in kids])
    P = V2[T2]
    neg = np.einsum("ij,ij->i", P[:, 1] - P[:, 0], np.cross(P[:, 2] - P[:, 0], P[:, 3] - P[:, 0])) < 0
    T2[neg] = T2[neg][:, [1, 0, 2, 3]]
    w.V, w.T = V2, T2
    w.parent = np.tile(w.parent, 8)
    w.err = np.concatenate([w.err, np.maximum(w.err[eu], w.err[ev])])
    w.dirty = np.ones(len(T2), dtype=bool)
    w.splits["refined"] = w.splits.get("refined", 0) + len(T)
    w.changed()


def _round(w: _Work, signature: tuple, bound: float, rng, moved: np.ndarray) -> np.ndarray:
    """One round of the module docstring's steps 1-3; returns ``moved`` (N,) bool updated
    with the vertices smoothed in it."""
    cfg = w.cfg
    # Boundary changes first: an interior flip under a flattened cap would otherwise bury it
    # under tets that no surface operation can reach.
    if cfg.max_boundary_ring > 0 and bound > 0:
        for _ in range(cfg.max_flip_passes):
            if _boundary_pass(w, signature, bound) == 0:
                break
    for _ in range(cfg.max_flip_passes):
        if _interior_flip_pass(w) == 0:
            break
    now = _smooth(w, _tangent_projectors(w.mesh(), cfg.feature_ratio), cfg.smooth_budget_share * bound, rng,
                  cfg.smooth_passes)
    for _ in range(cfg.max_flip_passes):
        if _interior_flip_pass(w) == 0:
            break
    out = np.zeros(len(w.V), dtype=bool)
    out[: len(moved)] = moved
    out[: len(now)] |= now
    return out


def _report(w: _Work, mesh: TetMesh, out: TetMesh, before: dict, L: float, signature: tuple, smoothed: int) -> dict:
    """The ``report.json -> improve`` section (see :func:`improve`)."""
    cfg = w.cfg
    va, fa = mesh.surface_mesh()
    vb, fb = out.surface_mesh()
    hd = surface_hausdorff(va, fa, vb, fb, samples_per_face=cfg.hausdorff_samples_per_face, device=w.device)
    after = _summary(w.V, w.T, w.quality())
    return {
        "flips": dict(w.counts),
        "splits": dict(w.splits),
        "vertices_smoothed": smoothed,
        "before": before,
        "after": after,
        "targets": element_targets(after),
        "eta_histogram_before": _eta_histogram(mesh.vertices, mesh.tets, cfg.eta_histogram_edges),
        "eta_histogram_after": _eta_histogram(out.vertices, out.tets, cfg.eta_histogram_edges),
        "mean_boundary_edge": L,
        "surface_hausdorff": hd,
        "surface_hausdorff_mean_edges": hd / L if L > 0 else 0.0,
        "surface_move_bound_mean_edges": cfg.max_surface_move,
        "topology": {"components": signature[0], "genus": signature[1], "boundary_shells": signature[2],
                     "manifold": signature[3]},
        "quality_measure": cfg.quality,
        "device": w.device,
    }
