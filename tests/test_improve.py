"""Element improvement (method.md §7b): kernels against dense NumPy references, the stage's
invariants on random and adversarial meshes, and the ``python -m holowarp.improve`` command."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from holowarp.bench.improve import plant_slivers
from holowarp.mesh_io import read_tetmesh, write_tetmesh
from holowarp.primitives import box_tetmesh
from holowarp.stages import improve as I
from holowarp.tetmesh import TET_EDGES, TetMesh

REGULAR = np.array([[1, 1, 1], [1, -1, -1], [-1, 1, -1], [-1, -1, 1]], dtype=np.float64)


# ---------------------------------------------------------------------------- references
def _ref_sine_quality(P: np.ndarray) -> np.ndarray:
    """Smallest of the six dihedral-angle sines, each signed like the volume, over the
    regular tet's; from the angles themselves (between the faces' in-plane directions
    orthogonal to the edge), independent of the 6V l / (|n_k| |n_l|) identity the kernels use."""
    out = np.empty(len(P))
    for i, p in enumerate(P):
        vol = np.dot(p[1] - p[0], np.cross(p[2] - p[0], p[3] - p[0]))
        sines = []
        for a, b in TET_EDGES:
            c, d = [k for k in range(4) if k not in (a, b)]
            e = p[b] - p[a]
            e /= np.linalg.norm(e)
            u = p[c] - p[a] - np.dot(p[c] - p[a], e) * e  # in-face directions orthogonal to the edge
            w = p[d] - p[a] - np.dot(p[d] - p[a], e) * e
            nu, nw = np.linalg.norm(u), np.linalg.norm(w)
            ang = math.acos(np.clip(np.dot(u, w) / (nu * nw), -1, 1)) if nu > 0 and nw > 0 else 0.0
            sines.append(math.sin(ang))
        out[i] = min(np.sign(vol) * np.array(sines)) / (2 * math.sqrt(2) / 3)
    return out


def _ref_point_triangle(p, a, b, c) -> np.ndarray:
    """Distance from points to triangles: to the plane where the projection falls inside,
    else to the nearest of the three edge segments (no Voronoi-region logic)."""
    n = np.cross(b - a, c - a)
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    s = np.einsum("ij,ij->i", p - a, n)
    proj = p - s[:, None] * n
    inside = np.ones(len(p), dtype=bool)
    for x, y in ((a, b), (b, c), (c, a)):
        inside &= np.einsum("ij,ij->i", np.cross(y - x, proj - x), n) >= 0
    seg = []
    for x, y in ((a, b), (b, c), (c, a)):
        t = np.clip(np.einsum("ij,ij->i", p - x, y - x) / np.einsum("ij,ij->i", y - x, y - x), 0, 1)
        seg.append(np.linalg.norm(p - (x + t[:, None] * (y - x)), axis=1))
    return np.where(inside, np.abs(s), np.min(seg, axis=0))


def _ref_hausdorff(ma: TetMesh, mb: TetMesh, rng, per_face: int = 40) -> float:
    """Brute-force two-sided Hausdorff: dense samples of each boundary, every sample to every
    triangle of the other with :func:`_ref_point_triangle`."""
    def samples(V, F):
        r1, r2 = np.sqrt(rng.random((len(F), per_face))), rng.random((len(F), per_face))
        w = np.stack([1 - r1, r1 * (1 - r2), r1 * r2], axis=2)
        e = np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]])
        return np.concatenate([V[np.unique(F)], 0.5 * (V[e[:, 0]] + V[e[:, 1]]),
                               np.einsum("fkj,fjd->fkd", w, V[F]).reshape(-1, 3)])

    def one_way(P, V, F):
        d = np.full(len(P), np.inf)
        A, B, C = V[F[:, 0]], V[F[:, 1]], V[F[:, 2]]
        for f in range(len(F)):
            d = np.minimum(d, _ref_point_triangle(P, *(np.broadcast_to(X[f], P.shape) for X in (A, B, C))))
        return d.max()

    va, fa = ma.surface_mesh()
    vb, fb = mb.surface_mesh()
    fa, fb = fa.astype(np.int64), fb.astype(np.int64)
    return max(one_way(samples(va, fa), vb, fb), one_way(samples(vb, fb), va, fa))


def _random_tets(rng, n: int) -> np.ndarray:
    """(n, 4, 3) tets: random, nearly flat (slivers, caps), needles and inverted ones."""
    P = rng.normal(size=(n, 4, 3))
    k = n // 4
    P[:k, 3] = P[:k, :3].mean(axis=1) + rng.normal(size=(k, 3)) * 1e-3  # flat: apex near the base
    P[k : 2 * k, 1] = P[k : 2 * k, 0] + rng.normal(size=(k, 3)) * 1e-2  # needles: a short edge
    return P


# ---------------------------------------------------------------------------- kernel oracles
def test_quality_kernel_matches_numpy_and_dihedral_references(rng):
    P = _random_tets(rng, 400)
    V = P.reshape(-1, 3)
    T = np.arange(len(V)).reshape(-1, 4)
    ref = _ref_sine_quality(P)
    # arccos of nearly parallel directions keeps only ~8 digits: the angle route is the loose one.
    np.testing.assert_allclose(I.tet_quality(V, T, "sine"), ref, rtol=1e-7, atol=1e-10)
    w = I._Work(TetMesh(V, T), I.ImproveConfig(), "cpu")
    eta = 12 * (3 * np.abs(np.linalg.det(P[:, 1:] - P[:, :1])) / 6) ** (2 / 3) / sum(
        np.sum((P[:, j] - P[:, i]) ** 2, axis=1) for i, j in TET_EDGES)
    eta *= np.sign(np.linalg.det(P[:, 1:] - P[:, :1]))
    np.testing.assert_allclose(I.tet_quality(V, T, "eta"), eta, rtol=1e-9, atol=1e-14)  # det vs cross: flat tets cancel
    for measure in ("sine", "eta", "sine_eta"):
        w.mode = I.QUALITY_MEASURES[measure]  # the Warp kernel against the NumPy float64 reference
        np.testing.assert_allclose(w.quality_of(T), I.tet_quality(V, T, measure), rtol=1e-10, atol=1e-14)
    np.testing.assert_allclose(I.tet_quality(V, T, "sine_eta"), np.minimum(I.tet_quality(V, T, "sine"), eta), rtol=1e-9)
    assert I.tet_quality(REGULAR[[0, 2, 1, 3]], [[0, 1, 2, 3]])[0] == pytest.approx(1.0, abs=1e-12)
    assert I.shape_quality_eta(REGULAR, [[0, 1, 2, 3]])[0] == pytest.approx(1.0, abs=1e-12)


def test_point_triangle_distances_match_the_plane_and_segment_reference(rng):
    a, b, c = (rng.normal(size=(2000, 3)) for _ in range(3))
    p = rng.normal(size=(2000, 3)) * 2
    ref = _ref_point_triangle(p, a, b, c)
    np.testing.assert_allclose(I._closest_on_triangles(p, a, b, c), ref, rtol=1e-9, atol=1e-12)
    # Warp's BVH query (float32) on one random closed surface.
    V, F = box_tetmesh((2, 2, 2)).surface_mesh()
    V = V + rng.normal(size=V.shape) * 0.05
    F = F.astype(np.int64)
    q = rng.uniform(-0.5, 1.5, size=(500, 3))
    dense = np.min([_ref_point_triangle(q, *(np.broadcast_to(V[F[f, i]], q.shape) for i in range(3))) for f in range(len(F))], axis=0)
    np.testing.assert_allclose(I._point_surface_distance(q, V, F), dense, atol=2e-6)


def _ref_smooth_step(V, T, bf, verts, proj, budget, cfg, mode):
    """One step of optimisation-based smoothing for independent ``verts``, written out
    densely in NumPy float64 (the kernel's documented algorithm); returns positions and the
    surface move charged per vertex."""
    V = V.copy()
    charged = np.zeros(len(verts))
    grid = I._barycentric_grid(cfg.surface_samples)
    for i, v in enumerate(verts):
        star, loc = np.nonzero(T == v)
        x0 = V[v].copy()

        def qs(y, star=star, loc=loc):
            P = V[T[star]].copy()
            P[np.arange(len(star)), loc] = y
            return I._quality_of_points(P, mode)

        h = np.linalg.norm(V[T[star]] - x0, axis=2).sum() / (3 * len(star))
        q0, mean0 = qs(x0).min(), qs(x0).mean()

        def soft(y):
            q = qs(y)
            m = q.min()
            return m - np.log(np.exp(-cfg.smooth_beta * (q - m)).sum()) / cfg.smooth_beta

        fd = cfg.smooth_fd * h
        g = np.array([(soft(x0 + fd * e) - soft(x0 - fd * e)) / (2 * fd) for e in np.eye(3)])
        d = proj[v] @ g
        if np.linalg.norm(d) == 0:
            continue
        d /= np.linalg.norm(d)
        faces = bf[np.any(bf == v, axis=1)]
        best, best_y, best_h = q0, x0, 0.0
        alpha = cfg.smooth_step * h
        for _ in range(cfg.smooth_line_steps):
            y = x0 + alpha * d
            alpha *= 0.5
            q = qs(y).min()
            if q > best and (q0 < cfg.mean_guard or qs(y).mean() >= mean0):
                hm = 0.0
                if len(faces):
                    Po = V[faces][None]
                    Pn = Po.copy()
                    Pn[0][faces == v] = y
                    ok = np.ones((1, len(faces)), dtype=bool)
                    hm = min(cfg.hausdorff_margin * I._patch_hausdorff(Po, Pn, ok, ok, grid)[0], np.linalg.norm(y - x0))
                if hm <= budget[v]:
                    best, best_y, best_h = q, y, hm
        if best > q0 + 0.1 * cfg.min_gain:
            V[v] = best_y
            charged[i] = best_h
    return V, charged


def test_smoothing_kernel_matches_dense_numpy_reference(rng):
    mesh = plant_slivers(box_tetmesh((4, 4, 4)), 0.3, rng)
    # Roughen the boundary too, so boundary vertices have curved umbrellas to measure.
    V = mesh.vertices.copy()
    bnd = np.unique(mesh.boundary_faces())
    V[bnd] += rng.normal(size=(len(bnd), 3)) * 0.01
    mesh = TetMesh(V, mesh.tets)
    assert np.all(mesh.signed_volumes() > 0)
    cfg = I.ImproveConfig()
    w = I._Work(mesh, cfg, "cpu")
    classes = I._colour_classes(mesh.edges().astype(np.int64), np.ones(mesh.num_vertices, dtype=bool), rng)
    verts = max(classes, key=lambda c: min(np.isin(c, bnd).sum(), (~np.isin(c, bnd)).sum()))
    assert np.isin(verts, bnd).any() and (~np.isin(verts, bnd)).any()
    proj = I._tangent_projectors(mesh, cfg.feature_ratio)
    bound = 0.004  # tight enough that some boundary steps are refused
    bf = mesh.boundary_faces().astype(np.int64)
    ref_V, ref_h = _ref_smooth_step(mesh.vertices, mesh.tets.astype(np.int64), bf, verts, proj,
                                    np.full(mesh.num_vertices, bound), cfg, w.mode)
    moved = I._smooth(w, proj, bound, None, 1, only=verts)
    assert moved[verts].any() and (~moved[verts]).any()
    np.testing.assert_allclose(w.V, ref_V, atol=1e-12)
    # The charged surface moves are the kernel's, and stay within the budget.
    np.testing.assert_allclose(w.err[verts], ref_h, atol=1e-12)
    assert w.err.max() <= bound + 1e-15
    # Boundary vertices moved tangentially only (up to the projector's null space).
    dv = w.V - mesh.vertices
    assert np.allclose(np.einsum("nij,nj->ni", proj, dv), dv, atol=1e-12)


def test_edge_table_rings_are_cyclic_and_positive(rng):
    mesh = plant_slivers(box_tetmesh((3, 2, 2)), 0.2, rng)
    T = mesh.tets.astype(np.int64)
    et = I._EdgeTable(T, mesh.num_vertices, 12)
    uniq = mesh.edges()
    np.testing.assert_array_equal(np.stack([et.u, et.v], 1), uniq)
    counts = np.bincount(np.searchsorted(et.keys, I._edge_keys(T[:, TET_EDGES[:, 0]], T[:, TET_EDGES[:, 1]], mesh.num_vertices)).ravel())
    np.testing.assert_array_equal(et.n, counts)
    bkeys = I._boundary_edge_keys(mesh, mesh.num_vertices)
    np.testing.assert_array_equal(et.boundary, np.isin(et.keys, bkeys))
    V = mesh.vertices
    for e in range(len(et.u)):
        n = et.n[e]
        ring = et.verts[e, : n + 1] if et.boundary[e] else np.r_[et.verts[e, :n], et.verts[e, 0]]
        for i in range(n):  # (u, v, p_i, p_i+1) is the ring tet, positively oriented
            t = [et.u[e], et.v[e], ring[i], ring[i + 1]]
            assert sorted(t) == sorted(T[et.tets[e, i]].tolist())
            assert np.linalg.det(V[t[1:]] - V[t[0]]) > 0


@pytest.mark.parametrize("n_major, n_minor", [(50, 7), (9000, 65536), (70000, 300)])
def test_lex_order_is_the_stable_argsort_of_the_pair_key(rng, n_major, n_minor):
    # Many ties (few distinct pairs) and the 16-bit radix path as well as the fallback.
    major = rng.integers(0, n_major, 40000)
    minor = rng.integers(0, n_minor, 40000)
    want = np.argsort(major.astype(np.int64) * n_minor + minor, kind="stable")
    np.testing.assert_array_equal(I._lex_order(major, minor, n_major, n_minor), want)


def test_improvement_is_bitwise_the_same_on_one_and_two_cpu_threads():
    """The quality, closest-face and smoothing launches run in pieces on the CPU threads;
    every thread writes only its own outputs (smoothing: its own vertex of an independent
    set), so the improved mesh is the one-thread mesh, bit for bit."""
    from holowarp.device import cpu_threads, set_cpu_threads

    mesh = plant_slivers(_rough_box(np.random.default_rng(7), cells=(6, 6, 6)), 0.3, np.random.default_rng(8))
    before, runs = cpu_threads(), []
    try:
        for threads in (1, 2):
            set_cpu_threads(threads)
            runs.append(I.improve(mesh))
    finally:
        set_cpu_threads(before)
    (m1, p1, i1), (m2, p2, i2) = runs
    assert i1["after"]["min_dihedral_worst"] > i1["before"]["min_dihedral_worst"]  # it did work
    np.testing.assert_array_equal(m1.vertices, m2.vertices)
    np.testing.assert_array_equal(m1.tets, m2.tets)
    np.testing.assert_array_equal(p1, p2)


def test_every_polygon_triangulation_is_enumerated():
    for n, catalan in ((3, 1), (4, 2), (5, 5), (6, 14), (7, 42), (8, 132)):
        tab = I._POLYGONS[n]
        assert tab.tri.shape == (catalan, n - 2)
        tris = {tuple(sorted(map(tuple, tab.combos[r].tolist()))) for r in tab.tri}
        assert len(tris) == catalan  # all distinct
        # Each triangulation covers the polygon's area exactly (regular polygon).
        ang = 2 * np.pi * np.arange(n) / n
        P = np.stack([np.cos(ang), np.sin(ang)], 1)
        area = 0.5 * n * np.sin(2 * np.pi / n)
        for r in tab.tri:
            t = P[tab.combos[r]]
            e1, e2 = t[:, 1] - t[:, 0], t[:, 2] - t[:, 0]
            a = 0.5 * (e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0])
            assert np.all(a > 0) and a.sum() == pytest.approx(area)


# ---------------------------------------------------------------------------- adversarial meshes
def _rough_box(rng, cells=(4, 4, 4), amp=0.2):
    """A box whose vertices (boundary ones too) are jittered: a random, rough-surfaced mesh."""
    m = box_tetmesh(cells)
    h = 1.0 / max(cells)
    V0 = m.vertices
    V = V0 + rng.uniform(-amp, amp, V0.shape) * h
    while True:
        bad = TetMesh(V.copy(), m.tets, validate=False).signed_volumes() <= 1e-3 * h**3
        if not bad.any():
            return TetMesh(V, m.tets)
        back = np.unique(m.tets[bad])
        V[back] = V0[back]


def _capped_box(rng):
    """A jittered box with two flat caps glued onto one top cell: a vertex a hair above the
    middle of the cell's diagonal, coned to both of its triangles. Each cap has two boundary
    faces; deleting one turns the other into a cap with three."""
    m = plant_slivers(box_tetmesh((3, 3, 2)), 0.02, rng)
    V, T = m.vertices, m.tets.astype(np.int64)
    bf = m.boundary_faces().astype(np.int64)
    top = bf[np.all(np.isclose(V[bf][:, :, 2], 1.0), axis=1)]
    # Two top triangles sharing an edge (the diagonal of a cell).
    e0 = {tuple(sorted(p)) for p in ((top[0, 0], top[0, 1]), (top[0, 1], top[0, 2]), (top[0, 2], top[0, 0]))}
    j = next(i for i in range(1, len(top)) if len(e0 & {tuple(sorted(p)) for p in
             ((top[i, 0], top[i, 1]), (top[i, 1], top[i, 2]), (top[i, 2], top[i, 0]))}) == 1)
    a, c = sorted(e0 & {tuple(sorted(p)) for p in ((top[j, 0], top[j, 1]), (top[j, 1], top[j, 2]), (top[j, 2], top[j, 0]))})[0]
    b = int(np.setdiff1d(top[0], [a, c])[0])
    d = int(np.setdiff1d(top[j], [a, c])[0])
    e = len(V)
    L = np.linalg.norm(V[a] - V[c])
    apex = 0.5 * (V[a] + V[c]) + [0, 0, 0.01 * L]
    caps = np.array([[a, b, c, e], [a, c, d, e]])
    mesh, _ = TetMesh(np.vstack([V, apex]), np.vstack([T, caps])).oriented()
    return mesh


def _split_edge_near_end(mesh: TetMesh, boundary: bool, t: float = 0.02) -> TetMesh:
    """Split one edge (a boundary edge or an interior one) at ``t`` of its length: the tets
    around it become needles (a very short edge) and slivers."""
    T = mesh.tets.astype(np.int64)
    bk = I._boundary_edge_keys(mesh, mesh.num_vertices)
    E = mesh.edges().astype(np.int64)
    on_b = np.isin(I._edge_keys(E[:, 0], E[:, 1], mesh.num_vertices), bk)
    ln = np.linalg.norm(mesh.vertices[E[:, 0]] - mesh.vertices[E[:, 1]], axis=1)
    cand = np.flatnonzero(on_b == boundary)
    u, v = E[cand[np.argmax(ln[cand])]]
    m = mesh.num_vertices
    x = mesh.vertices[u] + t * (mesh.vertices[v] - mesh.vertices[u])
    ring = np.flatnonzero(np.isin(T, [u, v]).sum(axis=1) == 2)
    A, B = T[ring].copy(), T[ring].copy()
    A[A == v] = m
    B[B == u] = m
    keep = np.setdiff1d(np.arange(len(T)), ring)
    return TetMesh(np.vstack([mesh.vertices, x]), np.vstack([T[keep], A, B]))


def _genus_one(rng):
    mask = np.ones((5, 5, 3), dtype=bool)
    mask[2, 2, :] = False
    return plant_slivers(box_tetmesh((5, 5, 3), cell_mask=mask), 0.1, rng)


CASES = {
    "planted_slivers": lambda rng: plant_slivers(box_tetmesh((5, 5, 5)), 0.05, rng),
    "rough_random": lambda rng: _rough_box(rng),
    "boundary_cap": _capped_box,
    "boundary_needle": lambda rng: _split_edge_near_end(plant_slivers(box_tetmesh((3, 3, 3)), 0.0, rng), True),
    "interior_needle": lambda rng: _split_edge_near_end(plant_slivers(box_tetmesh((3, 3, 3)), 0.0, rng), False),
    "genus_one": _genus_one,
    "thin_slab": lambda rng: _rough_box(rng, cells=(6, 6, 1), amp=0.15),
}


@pytest.fixture(scope="module")
def improved():
    """Every adversarial case, improved once with the default settings."""
    out = {}
    for i, (name, make) in enumerate(CASES.items()):
        rng = np.random.default_rng(1000 + i)
        mesh = make(rng)
        out[name] = (mesh, *I.improve(mesh))
    return out


@pytest.mark.parametrize("name", list(CASES))
def test_improvement_keeps_topology_orientation_and_surface(improved, name):
    mesh, out, parent, info = improved[name]
    assert np.all(mesh.signed_volumes() > 0)
    m0, m1 = mesh.manifold(), out.manifold()
    assert m0["manifold"] and m1["manifold"]
    assert out.num_components() == mesh.num_components() == 1
    assert out.genus() == mesh.genus()
    assert out.boundary_shells() == mesh.boundary_shells()
    assert np.all(out.signed_volumes() > 0), "an inverted or flat tet was produced"
    assert info["after"]["inverted"] == 0
    # The surface stays within 0.1 mean boundary edge (brute-force Hausdorff).
    L = I.mean_boundary_edge(mesh)
    hd = _ref_hausdorff(mesh, out, np.random.default_rng(7))
    assert hd <= 0.1 * L
    # The report's sampled value is a lower estimate too (float32 BVH: round-off of ~1e-7).
    assert info["surface_hausdorff"] <= hd + 1e-6 * L
    assert info["surface_hausdorff_mean_edges"] <= 0.1
    # Quality never gets worse, and the volume changes only where caps were cut.
    assert info["after"]["quality_min"] >= info["before"]["quality_min"]
    assert info["after"]["min_dihedral_worst"] >= info["before"]["min_dihedral_worst"]
    v0, f0 = mesh.surface_mesh()
    area = 0.5 * np.linalg.norm(np.cross(v0[f0[:, 1]] - v0[f0[:, 0]], v0[f0[:, 2]] - v0[f0[:, 0]]), axis=1).sum()
    assert abs(out.volume() - mesh.volume()) <= 0.1 * L * area
    # Parents are input tets, and most output tets overlap theirs.
    assert parent.shape == (out.num_tets,) and parent.min() >= 0 and parent.max() < mesh.num_tets
    cen = out.vertices[out.tets].mean(axis=1)
    P = mesh.vertices[mesh.tets[parent]]
    lam = np.linalg.solve(np.transpose(P[:, 1:] - P[:, :1], (0, 2, 1)), (cen - P[:, 0])[..., None])[..., 0]
    inside = np.minimum(1 - lam.sum(axis=1), lam.min(axis=1)) > -0.5
    assert inside.mean() > 0.9


@pytest.mark.parametrize("name,worst", [("planted_slivers", 10.0), ("genus_one", 10.0), ("boundary_cap", 10.0),
                                        ("boundary_needle", 10.0), ("interior_needle", 10.0), ("rough_random", 5.0)])
def test_improvement_removes_slivers_caps_and_needles(improved, name, worst):
    mesh, out, _, info = improved[name]
    assert info["before"]["min_dihedral_worst"] < 3.0 or name == "rough_random"
    assert info["after"]["min_dihedral_worst"] >= worst
    assert info["after"]["eta_min"] >= 0.01
    assert info["after"]["aspect_ratio_mean"] <= info["before"]["aspect_ratio_mean"]


def test_caps_are_deleted_when_surface_work_comes_first_and_report_counts_every_operation(rng):
    # By default the first round works from inside only (it re-triangulates the caps away);
    # without that round the caps are deleted: one, then its neighbour with its apex.
    mesh = _capped_box(rng)
    out, _, info = I.improve(mesh, I.ImproveConfig(inside_rounds=0, thin_fraction=None))
    assert info["flips"]["cap_removal"] == 1 and info["flips"]["cap_vertex_removal"] == 1
    assert out.num_vertices == mesh.num_vertices - 1  # the caps' apex is gone
    assert out.manifold()["manifold"] and out.genus() == mesh.genus() and np.all(out.signed_volumes() > 0)
    assert info["surface_hausdorff_mean_edges"] <= 0.1
    for key in ("2-3", "3-2", "4-4", "edge_removal_5+", "boundary_edge_removal", "cap_removal", "cap_vertex_removal",
                "boundary_edge_collapse"):
        assert isinstance(info["flips"][key], int)
    h = info["eta_histogram_after"]
    assert h["bin_edges"] == list(I.ETA_HISTOGRAM_EDGES)
    assert sum(h["counts"]) == out.num_tets and h["below_0.01"] == 0
    json.dumps(info)  # report.json-ready


def test_a_short_boundary_edge_is_collapsed_within_the_surface_budget(rng):
    # A boundary edge split near one end: the tets at the short piece are needles that no
    # flip mends (a flip keeps every vertex) and, without smoothing, nothing else does.
    mesh = _split_edge_near_end(box_tetmesh((3, 3, 3)), True, t=float(rng.uniform(0.02, 0.1)))
    fixed = dict(smooth_passes=0, inside_rounds=0, thin_fraction=None, split_threshold=0.0)
    kept, _, k_info = I.improve(mesh, I.ImproveConfig(collapse_ratio=0.0, **fixed))
    out, parent, info = I.improve(mesh, I.ImproveConfig(**fixed))
    assert k_info["flips"]["boundary_edge_collapse"] == 0 and k_info["after"]["min_dihedral_worst"] < 6.0
    assert info["flips"]["boundary_edge_collapse"] >= 1
    assert out.num_vertices == mesh.num_vertices - info["flips"]["boundary_edge_collapse"]
    E = out.edges()
    L = I.mean_boundary_edge(mesh)
    assert np.linalg.norm(out.vertices[E[:, 0]] - out.vertices[E[:, 1]], axis=1).min() > 0.5 * L
    assert info["after"]["min_dihedral_worst"] > 40.0  # the box's own tets again
    assert out.topology_signature() == mesh.topology_signature() and np.all(out.signed_volumes() > 0)
    assert _ref_hausdorff(mesh, out, rng) <= 0.1 * L
    assert parent.shape == (out.num_tets,) and parent.max() < mesh.num_tets


def test_a_collapse_that_would_make_two_tets_one_is_never_a_candidate(rng):
    # u and v (a short edge, in a thin tet) both see the triangle xyz: merging them would
    # turn (u, x, y, z) and (v, x, y, z) into one tet twice, which no manifold check sees.
    s = rng.uniform(0.05, 0.1)
    V = np.array([[0, 0, s], [0, 0, -s], [-1, 1, 0], [-1, -1, 0], [1.5, 0, 1], [1.5, 1, -0.5], [1.5, -1, -0.5]], float)
    u, v, a, b, x, y, z = range(7)
    def candidates(tets):
        mesh, _ = TetMesh(V, np.array(tets)).oriented()
        w = I._Work(mesh, I.ImproveConfig(), "cpu")
        N = len(w.V)
        ctx = {"q": w.quality(), "bmask": mesh.boundary_mask()}
        cand = I._Candidates()
        I._collapse_candidates(w, cand, I._EdgeTable(w.T, N, 6), np.inf, ctx)
        return len(cand.old)

    assert candidates([[u, v, a, b], [u, x, y, z]]) > 0
    assert candidates([[u, v, a, b], [u, x, y, z], [v, x, y, z]]) == 0


def test_red_refinement_splits_every_tet_in_eight_inside_it_and_keeps_the_surface(rng):
    mesh = _genus_one(rng)
    w = I._Work(mesh, I.ImproveConfig(), "cpu")
    w.err = rng.random(len(w.V)) * 1e-3
    err0, parent0 = w.err.copy(), w.parent.copy()
    I._red_refine(w)
    out = TetMesh(w.V, w.T)
    M = mesh.num_tets
    assert out.num_tets == 8 * M and np.all(out.signed_volumes() > 0)
    assert out.volume() == pytest.approx(mesh.volume(), rel=1e-12)
    assert out.manifold()["manifold"] and out.genus() == mesh.genus() and out.num_components() == 1
    # Child j * M + i lies in tet i, and inherits its parent.
    assert np.array_equal(w.parent, np.tile(parent0, 8))
    P = mesh.vertices[mesh.tets[np.tile(np.arange(M), 8)]]
    lam = np.linalg.solve(np.transpose(P[:, 1:] - P[:, :1], (0, 2, 1)),
                          (out.vertices[out.tets].mean(axis=1) - P[:, 0])[..., None])[..., 0]
    assert np.minimum(1 - lam.sum(axis=1), lam.min(axis=1)).min() > 0
    # The surface: each old boundary triangle is four new ones with the same area, and each
    # new vertex is an edge midpoint with the larger surface bound of the edge's ends.
    v0, f0 = mesh.surface_mesh()
    v1, f1 = out.surface_mesh()
    area = lambda v, f: 0.5 * np.linalg.norm(np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]]), axis=1).sum()  # noqa: E731
    assert len(f1) == 4 * len(f0) and area(v1, f1) == pytest.approx(area(v0, f0), rel=1e-12)
    assert _ref_hausdorff(mesh, out, rng) <= 1e-12
    E = mesh.edges().astype(np.int64)
    mids = 0.5 * (mesh.vertices[E[:, 0]] + mesh.vertices[E[:, 1]])
    new = w.V[mesh.num_vertices:]
    order = np.lexsort(new.T[::-1]), np.lexsort(mids.T[::-1])
    assert np.allclose(new[order[0]], mids[order[1]])
    assert np.allclose(np.sort(w.err[mesh.num_vertices:]), np.sort(np.maximum(err0[E[:, 0]], err0[E[:, 1]])))


def test_a_thin_mesh_is_refined_and_improved_again(improved):
    mesh, out, parent, info = improved["thin_slab"]
    ref = info["refinement"]
    assert ref is not None and ref["thin_fraction"] > 0.4 and ref["kept"] and ref["tets_after_refinement"] == 8 * ref["tets_before"]
    assert info["splits"]["refined"] == ref["tets_before"] and out.num_tets >= 7 * ref["tets_before"]
    assert info["after"]["min_dihedral_mean"] > info["before"]["min_dihedral_mean"]
    assert improved["planted_slivers"][3]["refinement"] is None  # a solid box is not thin
    _, out2, _, info2 = improved["thin_slab"][0], *I.improve(mesh, I.ImproveConfig(thin_fraction=None))
    assert info2["refinement"] is None and out2.num_tets < 2 * mesh.num_tets


@pytest.mark.parametrize("name,kept", [("planted_slivers", True), ("boundary_needle", False)])
def test_a_refinement_is_kept_only_when_it_pays(improved, name, kept):
    """Forced (any share of all-boundary tets counts), the refined mesh stays only if its
    worst and mean quality are no lower than before it; else the stage undoes it."""
    mesh, _, _, base = improved[name]
    out, parent, info = I.improve(mesh, I.ImproveConfig(thin_fraction=0.0))
    ref = info["refinement"]
    assert ref is not None and ref["kept"] is kept
    if kept:
        assert out.num_tets >= 7 * ref["tets_before"] and info["splits"]["refined"] == ref["tets_before"]
        assert info["after"]["quality_min"] >= base["after"]["quality_min"] - 1e-12
    else:
        assert out.num_tets == base["after"]["tets"] and info["splits"] == base["splits"]
        assert info["after"]["quality_min"] == base["after"]["quality_min"]
    assert parent.shape == (out.num_tets,) and out.manifold()["manifold"] and np.all(out.signed_volumes() > 0)


def test_zero_surface_budget_keeps_the_boundary_exactly(rng):
    mesh = _rough_box(rng, cells=(3, 3, 3))
    # Refined (forced: any share of all-boundary tets counts), the surface is the same point
    # set, split into more triangles.
    refined, _, rinfo = I.improve(mesh, I.ImproveConfig(max_surface_move=0.0, thin_fraction=0.0))
    assert rinfo["refinement"] is not None and _ref_hausdorff(mesh, refined, rng) <= 1e-12
    out, _, info = I.improve(mesh, I.ImproveConfig(max_surface_move=0.0, thin_fraction=None))
    v0, f0 = mesh.surface_mesh()
    v1, f1 = out.surface_mesh()
    def key(V, F):
        return sorted(tuple(sorted(map(tuple, np.round(V[f], 12).tolist()))) for f in F)

    assert key(v0, f0) == key(v1, f1)
    assert info["surface_hausdorff"] <= 1e-12 * I.mean_boundary_edge(mesh)
    assert info["after"]["quality_min"] >= info["before"]["quality_min"]


def test_element_targets_compare_each_value_with_method_md_s_bound():
    at = {"min_dihedral_worst": 10.0, "min_dihedral_mean": 40.0, "aspect_ratio_mean": 1.8, "eta_min": 0.01}
    t = I.element_targets(at)
    assert set(t) == set(I.TARGETS) and all(v["met"] for v in t.values())  # the bounds themselves pass
    assert t["min_dihedral_worst"]["target"] == ">= 10" and t["aspect_ratio_mean"]["target"] == "<= 1.8"
    off = {"min_dihedral_worst": 9.99, "min_dihedral_mean": 39.9, "aspect_ratio_mean": 1.81, "eta_min": 0.0099}
    t = I.element_targets(off)
    assert not any(v["met"] for v in t.values())
    assert t["eta_min"]["value"] == 0.0099


def test_a_slab_too_thin_to_improve_reports_the_missed_targets_and_the_cli_warns(tmp_path, capsys):
    """With the surface held (bound 0), a slab 0.03 thick under 0.25 x 0.25 cells keeps flat
    tets whatever the stage does: the report says which targets it missed and how many tets
    lie below the dihedral bound, and the command line warns on stderr."""
    mesh = box_tetmesh((4, 4, 1), (1.0, 1.0, 0.03))
    src, dst, rep = tmp_path / "slab.npz", tmp_path / "out.npz", tmp_path / "r.json"
    write_tetmesh(src, mesh)
    rc, out, err = _run(capsys, src, dst, "--max-surface-move", "0", "--json", rep, "--quiet")
    assert rc == 0 and out.startswith(f"wrote {dst}")
    r = json.loads(rep.read_text())
    t = r["targets"]
    assert not t["min_dihedral_worst"]["met"] and not t["aspect_ratio_mean"]["met"] and t["eta_min"]["met"]
    assert t["min_dihedral_worst"]["value"] == pytest.approx(r["after"]["min_dihedral_worst"])
    res = read_tetmesh(dst)
    assert t["min_dihedral_worst"]["tets_below"] == int((res.quality()["min_dihedral_deg"] < 10.0).sum()) > 0
    lines = [ln for ln in err.splitlines() if ln.startswith("warning:")]
    assert len(lines) == 3  # worst and mean dihedral, mean aspect ratio
    assert "worst minimum dihedral angle (deg)" in lines[0] and "method.md §7b's target >= 10" in lines[0]
    assert f"({t['min_dihedral_worst']['tets_below']} tets below)" in lines[0]


def test_missed_targets_name_each_miss_in_one_line():
    t = I.element_targets({"min_dihedral_worst": 7.4, "min_dihedral_mean": 47.0, "aspect_ratio_mean": 1.6,
                           "eta_min": 0.004})
    t["min_dihedral_worst"]["tets_below"] = 3
    lines = I.missed_targets({"targets": t})
    assert len(lines) == 2
    assert lines[0].startswith("worst minimum dihedral angle (deg) is 7.4 (3 tets below), outside method.md §7b's "
                               "target >= 10")
    assert lines[1].startswith("smallest shape quality eta is 0.004, outside method.md §7b's target >= 0.01")
    assert I.missed_targets({}) == []  # a report from before the targets existed


def test_improve_refuses_inverted_tets_and_empty_meshes():
    with pytest.raises(ValueError, match="inverted"):
        I.improve(TetMesh(REGULAR, [[0, 1, 2, 3]]))
    with pytest.raises(ValueError, match="no tetrahedra"):
        I.improve(TetMesh(REGULAR, np.zeros((0, 4), int)))
    with pytest.raises(ValueError, match="max_surface_move"):
        I.ImproveConfig(max_surface_move=-1.0)
    for bad in (-0.1, 1.0, float("nan")):
        with pytest.raises(ValueError, match="collapse_ratio"):
            I.ImproveConfig(collapse_ratio=bad)
    assert I.ImproveConfig(collapse_ratio=0.0).collapse_ratio == 0.0  # an explicit 0 turns it off


# ---------------------------------------------------------------------------- command line
def _run(capsys, *argv):
    from holowarp.improve import main

    rc = main([str(a) for a in argv])
    cap = capsys.readouterr()
    return rc, cap.out, cap.err


def test_cli_improves_a_tetgen_wound_mesh_and_writes_the_report(tmp_path, capsys, rng):
    mesh = plant_slivers(box_tetmesh((3, 3, 3)), 0.2, rng)
    neg = TetMesh(mesh.vertices, mesh.tets[:, [0, 2, 1, 3]])  # every tet negative (TetGen winding)
    src, dst, rep = tmp_path / "in.msh", tmp_path / "out.vtu", tmp_path / "r.json"
    write_tetmesh(src, neg)
    rc, out, err = _run(capsys, src, dst, "--json", rep, "--quiet")
    assert rc == 0, err
    assert out.count("\n") == 1 and out.startswith(f"wrote {dst}") and "re-oriented all" in out
    res = read_tetmesh(dst)
    assert np.all(res.signed_volumes() > 0) and res.manifold()["manifold"]
    r = json.loads(rep.read_text())
    assert r["input"]["reoriented"] == mesh.num_tets
    assert r["after"]["min_dihedral_worst"] > r["before"]["min_dihedral_worst"]
    assert r["surface_move_bound_mean_edges"] == 0.1


def test_cli_takes_an_explicit_zero_bound(tmp_path, capsys, rng):
    mesh = _rough_box(rng, cells=(3, 3, 2))
    src, dst, rep = tmp_path / "in.npz", tmp_path / "out.npz", tmp_path / "r.json"
    write_tetmesh(src, mesh)
    rc, out, err = _run(capsys, src, dst, "--max-surface-move", "0", "--json", rep, "--quiet")
    assert rc == 0, err
    r = json.loads(rep.read_text())
    assert r["surface_move_bound_mean_edges"] == 0.0 and r["surface_hausdorff_mean_edges"] <= 1e-12


@pytest.mark.parametrize("args,names", [
    (["{src}", "{tmp}/out.vtu", "--max-surface-move", "-0.5"], "--max-surface-move"),
    (["{src}", "{tmp}/out.vtu", "--max-surface-move", "nan"], "--max-surface-move"),
    (["{src}", "{tmp}/out.stl"], "out.stl"),
    (["{src}", "{tmp}"], "OUT"),
    (["{tmp}/missing.vtu", "{tmp}/out.vtu"], "missing.vtu"),
    (["{mixed}", "{tmp}/out.vtu"], "mixed.npz"),
    (["{src}", "{tmp}/out.vtu", "--json", "{tmp}/r.txt"], "--json"),
    (["{src}", "{tmp}/out.vtu", "--device", "tpu"], "--device"),
])
def test_cli_errors_are_one_line_naming_the_culprit_before_any_work(tmp_path, capsys, rng, args, names):
    mesh = box_tetmesh((2, 2, 2))
    src, mixed = tmp_path / "in.npz", tmp_path / "mixed.npz"
    write_tetmesh(src, mesh)
    t = mesh.tets.copy()
    t[0] = t[0, [0, 2, 1, 3]]
    write_tetmesh(mixed, TetMesh(mesh.vertices, t))
    argv = [a.format(src=src, tmp=tmp_path, mixed=mixed) for a in args]
    rc, _, err = _run(capsys, *argv)
    assert rc == 2
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: ") and names in lines[0], err
    assert not (tmp_path / "out.vtu").exists()


def test_cli_help_states_formats_and_the_bound(capsys):
    from holowarp.improve import build_parser

    text = build_parser().format_help()
    for word in (".vtu", ".msh", ".npz", ".usda", "FRAC", ">= 0", "0.1", "--device", "--quiet", "--json"):
        assert word in text


def test_remeasured_budget_is_the_distance_to_the_input_surface():
    from holowarp.config import ImproveConfig
    from holowarp.stages.improve import _PATCH_GRID, _Work, _remeasure_budget

    mesh = box_tetmesh((2, 2, 2))
    V = mesh.vertices
    top = int(np.flatnonzero(np.all(np.isclose(V, [0.5, 0.5, 1.0]), axis=1))[0])  # centre of the top face
    va, fa = mesh.surface_mesh()
    va, fa = np.asarray(va, np.float64), np.asarray(fa, np.int64)
    ref = (va, fa, np.einsum("kj,fjd->fkd", _PATCH_GRID, va[fa]).reshape(-1, 3))
    w = _Work(mesh, ImproveConfig(), "cpu")
    w.err[:] = 1.0  # an accumulated bound far above the truth
    _remeasure_budget(w, ref)
    np.testing.assert_allclose(w.err, 0.0, atol=1e-12)  # nothing has moved
    moved = w.V.copy()
    moved[top, 2] += 0.01  # lift the vertex off the plane: its umbrella leaves the input by 0.01
    w.V = moved
    w.changed()
    _remeasure_budget(w, ref)
    umbrella = np.unique(mesh.boundary_faces()[(mesh.boundary_faces() == top).any(axis=1)])
    np.testing.assert_allclose(w.err[umbrella], ImproveConfig().hausdorff_margin * 0.01, rtol=1e-9)
    others = np.setdiff1d(np.unique(mesh.boundary_faces()), umbrella)
    assert np.all(w.err[others] < 1e-12) and np.all(w.err[~np.isin(np.arange(len(V)), mesh.boundary_faces())] == 0.0)


def test_improve_deletes_an_end_tet_where_a_boundary_fan_wraps_past_a_full_turn():
    from oracles import edge_fan

    # Eight 50-degree sectors round one edge: 400 degrees, so the first and last sectors
    # overlap in space though every tet is positive.
    mesh, _ = edge_fan([(a, a + 50) for a in range(0, 400, 50)], spiral=0.05)
    assert mesh.overlapping_edges() == 1 and np.all(mesh.signed_volumes() > 0)
    out, parent, info = I.improve(mesh)
    assert out.overlapping_edges() == 0 and info["flips"]["overlap_removal"] >= 1
    assert info["topology"] == {"components": 1, "genus": 0, "boundary_shells": 1, "manifold": True}
    assert np.all(out.signed_volumes() > 0) and len(parent) == out.num_tets
