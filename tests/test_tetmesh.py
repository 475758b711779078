"""TetMesh core against analytic oracles and brute-force references."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest

from holowarp.primitives import box_tetmesh
from holowarp.tetmesh import TetMesh, TetMeshError

REGULAR = np.array([[1, 1, 1], [1, -1, -1], [-1, 1, -1], [-1, -1, 1]], dtype=np.float64)
CUBE_V = np.array([[x, y, z] for z in (0, 1) for y in (0, 1) for x in (0, 1)], dtype=np.float64)
CUBE_5 = [[0, 1, 2, 4], [1, 3, 2, 7], [1, 4, 5, 7], [2, 4, 7, 6], [1, 2, 4, 7]]
CUBE_6 = [[0, 1, 3, 7], [0, 3, 2, 7], [0, 2, 6, 7], [0, 6, 4, 7], [0, 4, 5, 7], [0, 5, 1, 7]]


def _random_rotation(rng):
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q *= np.sign(np.diag(r))
    if np.linalg.det(q) < 0:
        q[:, 0] *= -1
    return q


def _jittered_box(rng, cells=(3, 3, 2)):
    m = box_tetmesh(cells, (1.0, 1.2, 0.8))
    # Jitter keeps every tet positive: displacement well below the smallest cell height.
    h = min(1.0 / cells[0], 1.2 / cells[1], 0.8 / cells[2])
    return m.with_vertices(m.vertices + rng.uniform(-0.08, 0.08, m.vertices.shape) * h)


def test_regular_tet_has_textbook_quality():
    mesh, flipped = TetMesh(REGULAR, [[0, 1, 2, 3]]).oriented()
    q = mesh.quality()
    assert flipped == 1  # this vertex order is negatively oriented
    assert q["min_dihedral_deg"][0] == pytest.approx(70.528779, abs=1e-5)
    assert q["aspect_ratio"][0] == pytest.approx(1.0, abs=1e-12)
    assert q["radius_ratio"][0] == pytest.approx(1.0, abs=1e-12)
    assert mesh.signed_volumes()[0] == pytest.approx(8.0 / 3.0)


@pytest.mark.parametrize("tets,expected", [(CUBE_5, [1 / 6] * 4 + [1 / 3]), (CUBE_6, [1 / 6] * 6)])
def test_unit_cube_splits_have_known_volumes_and_closed_outward_boundary(tets, expected):
    mesh = TetMesh(CUBE_V, tets)
    np.testing.assert_allclose(mesh.signed_volumes(), expected, atol=1e-14)
    bf = mesh.boundary_faces()
    assert bf.shape == (12, 3)
    P = mesh.vertices[bf]
    normal = np.cross(P[:, 1] - P[:, 0], P[:, 2] - P[:, 0])
    # Every boundary triangle lies on a cube face and its normal points away from the centre.
    outward = np.einsum("ij,ij->i", P.mean(axis=1) - 0.5, normal)
    assert np.all(outward > 0)
    assert 0.5 * np.linalg.norm(normal, axis=1).sum() == pytest.approx(6.0)
    assert mesh.genus() == 0 and mesh.euler_characteristic() == 2
    assert mesh.manifold()["manifold"]
    assert mesh.num_components() == 1
    assert np.array_equal(mesh.surface_vertices(), np.arange(8))
    assert len(mesh.edges()) == (18 if len(tets) == 5 else 19)


def test_structured_solid_torus_has_genus_one():
    mask = np.ones((4, 4, 2), dtype=bool)
    mask[1:3, 1:3, :] = False
    for split in (5, 6):
        mesh = box_tetmesh((4, 4, 2), (1, 1, 0.5), split=split, cell_mask=mask)
        assert mesh.genus() == 1
        assert mesh.euler_characteristic() == 0
        assert mesh.manifold()["manifold"]
        assert mesh.num_components() == 1
        assert mesh.volume() == pytest.approx(1.0 * 1.0 * 0.5 * 12 / 16)


def test_hollow_box_has_two_shells_and_genus_zero():
    mask = np.ones((3, 3, 3), dtype=bool)
    mask[1, 1, 1] = False  # an internal cavity: the boundary is two spheres
    mesh = box_tetmesh((3, 3, 3), split=6, cell_mask=mask)
    assert mesh.boundary_shells() == 2
    assert mesh.euler_characteristic() == 4
    assert mesh.genus() == 0


def test_two_disjoint_cubes_are_two_components_and_largest_is_kept(rng):
    a = box_tetmesh((2, 2, 2))
    b = box_tetmesh((1, 1, 1), origin=(3.0, 0.0, 0.0))
    both = TetMesh(np.vstack([a.vertices, b.vertices]), np.vstack([a.tets, b.tets + a.num_vertices]))
    labels, n = both.components()
    assert n == 2
    assert set(np.bincount(labels)) == {a.num_tets, b.num_tets}
    kept, info = both.keep_largest_component()
    assert info == {"components": 2, "removed_tets": b.num_tets, "removed_components": 1}
    assert kept.num_tets == a.num_tets and kept.num_vertices == a.num_vertices
    np.testing.assert_allclose(kept.volume(), a.volume())


def _two_cubes_touching(shift):
    a = box_tetmesh((1, 1, 1))
    b = box_tetmesh((1, 1, 1), origin=shift)
    V = np.vstack([a.vertices, b.vertices])
    T = np.vstack([a.tets, b.tets + a.num_vertices])
    # Merge coincident vertices so the cubes really share them.
    uniq, inv = np.unique(np.round(V, 9), axis=0, return_inverse=True)
    return TetMesh(uniq, inv.reshape(-1)[T])


def test_cubes_sharing_only_a_vertex_are_vertex_non_manifold():
    mesh = _two_cubes_touching((1.0, 1.0, 1.0))
    man = mesh.manifold()
    assert man["edge_manifold"] and not man["vertex_manifold"] and not man["manifold"]
    assert man["bad_vertices"] == 1
    assert mesh.num_components() == 2


def test_cubes_sharing_only_an_edge_are_edge_non_manifold():
    mesh = _two_cubes_touching((1.0, 1.0, 0.0))
    man = mesh.manifold()
    assert not man["edge_manifold"] and not man["manifold"]
    assert man["bad_edges"] == 1
    assert mesh.num_components() == 2


def test_cubes_sharing_a_face_are_one_manifold_component():
    mesh = _two_cubes_touching((1.0, 0.0, 0.0))
    assert mesh.manifold()["manifold"]
    assert mesh.num_components() == 1
    assert len(mesh.boundary_faces()) == 20


def test_inverted_tets_are_flipped_and_counted(rng):
    mesh = _jittered_box(rng)
    flip = rng.random(mesh.num_tets) < 0.3
    t = mesh.tets.copy()
    t[flip, 0], t[flip, 1] = mesh.tets[flip, 1], mesh.tets[flip, 0]
    bad = TetMesh(mesh.vertices, t)
    assert np.count_nonzero(bad.signed_volumes() < 0) == flip.sum()
    fixed, n = bad.oriented()
    assert n == int(flip.sum()) > 0
    assert np.all(fixed.signed_volumes() > 0)
    np.testing.assert_allclose(fixed.signed_volumes(), mesh.signed_volumes(), rtol=1e-12)
    assert fixed.oriented()[1] == 0
    # The boundary of the inverted mesh is still wound out of the actual volume.
    bf = bad.boundary_faces()
    P = bad.vertices[bf]
    nrm = np.cross(P[:, 1] - P[:, 0], P[:, 2] - P[:, 0])
    vol = np.einsum("ij,ij->i", P[:, 0], nrm).sum() / 6.0  # divergence theorem
    assert vol == pytest.approx(mesh.volume(), rel=1e-9)


def test_face_adjacency_matches_brute_force(rng):
    mesh = _jittered_box(rng, cells=(2, 3, 2))
    owners = {}
    for e, tet in enumerate(mesh.tets):
        for k in range(4):
            owners.setdefault(frozenset(np.delete(tet, k).tolist()), []).append((e, k))
    expected = np.full((mesh.num_tets, 4), -1)
    for lst in owners.values():
        if len(lst) == 2:
            (e1, k1), (e2, k2) = lst
            expected[e1, k1] = e2
            expected[e2, k2] = e1
    np.testing.assert_array_equal(mesh.face_adjacency(), expected)
    L = mesh.adjacency_laplacian().toarray()
    np.testing.assert_array_equal(L, L.T)
    np.testing.assert_allclose(L.sum(axis=1), 0.0)
    np.testing.assert_array_equal(np.diag(L), (expected >= 0).sum(axis=1))
    boundary = {frozenset(f.tolist()) for f in mesh.boundary_faces()}
    assert boundary == {f for f, lst in owners.items() if len(lst) == 1}


def test_edges_match_brute_force(rng):
    mesh = _jittered_box(rng, cells=(2, 2, 3))
    ref = sorted({tuple(sorted(p)) for t in mesh.tets.tolist() for p in itertools.combinations(t, 2)})
    np.testing.assert_array_equal(mesh.edges(), np.array(ref))


def _dihedral_reference(P):
    """Six dihedral angles of one tet by explicit plane normals (degrees)."""
    out = []
    for i, j in itertools.combinations(range(4), 2):
        k, l = [m for m in range(4) if m not in (i, j)]
        e = P[j] - P[i]
        e /= np.linalg.norm(e)
        u = P[k] - P[i]
        w = P[l] - P[i]
        u -= e * (u @ e)
        w -= e * (w @ e)
        out.append(math.degrees(math.acos(np.clip(u @ w / np.linalg.norm(u) / np.linalg.norm(w), -1, 1))))
    return out


def _circumradius_reference(P):
    A = 2 * (P[1:] - P[0])
    b = (P[1:] ** 2).sum(1) - (P[0] ** 2).sum()
    c = np.linalg.solve(A, b)
    return np.linalg.norm(c - P[0])


def test_quality_matches_independent_geometry(rng):
    P = rng.normal(size=(20, 4, 3))
    mesh, _ = TetMesh(P.reshape(-1, 3), np.arange(80).reshape(20, 4)).oriented()
    q = mesh.quality()
    for e in range(20):
        X = mesh.vertices[mesh.tets[e]]
        assert q["min_dihedral_deg"][e] == pytest.approx(min(_dihedral_reference(X)), abs=1e-8)
        vol = abs(np.linalg.det(X[1:] - X[0])) / 6
        areas = sum(
            0.5 * np.linalg.norm(np.cross(X[b] - X[a], X[c] - X[a]))
            for a, b, c in itertools.combinations(range(4), 3)
        )
        r_in = 3 * vol / areas
        longest = max(np.linalg.norm(X[a] - X[b]) for a, b in itertools.combinations(range(4), 2))
        assert q["aspect_ratio"][e] == pytest.approx(longest / (2 * math.sqrt(6) * r_in), rel=1e-9)
        assert q["radius_ratio"][e] == pytest.approx(3 * r_in / _circumradius_reference(X), rel=1e-7)
    s = mesh.quality_summary()
    assert s["inverted_ratio"] == 0.0
    assert s["min_dihedral_worst"] == pytest.approx(q["min_dihedral_deg"].min())


def test_quality_is_invariant_under_similarity_transforms(rng):
    mesh = _jittered_box(rng)
    R = _random_rotation(rng)
    moved = mesh.with_vertices(2.5 * mesh.vertices @ R.T + rng.normal(size=3))
    a, b = mesh.quality(), moved.quality()
    for k in a:
        np.testing.assert_allclose(a[k], b[k], rtol=1e-9)
    np.testing.assert_allclose(moved.signed_volumes(), 2.5**3 * mesh.signed_volumes(), rtol=1e-9)


def test_degenerate_tet_reports_zero_dihedral_and_counts_as_inverted():
    V = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0]], dtype=np.float64)  # flat
    mesh = TetMesh(V, [[0, 1, 2, 3]])
    q = mesh.quality()
    assert q["min_dihedral_deg"][0] == 0.0 and np.isinf(q["aspect_ratio"][0])
    assert mesh.quality_summary()["inverted_ratio"] == 1.0
    assert mesh.oriented()[1] == 0  # zero volume is degenerate, not inverted


def test_remove_unused_vertices_and_submesh_keep_geometry(rng):
    mesh = _jittered_box(rng)
    keep = rng.random(mesh.num_tets) < 0.5
    sub = mesh.submesh(keep)
    np.testing.assert_allclose(sub.signed_volumes(), mesh.signed_volumes()[keep])
    assert sub.num_vertices == len(np.unique(mesh.tets[keep]))
    extra = TetMesh(np.vstack([mesh.vertices, rng.normal(size=(5, 3))]), mesh.tets)
    compact, old_to_new = extra.remove_unused_vertices()
    assert compact.num_vertices == mesh.num_vertices
    assert np.all(old_to_new[-5:] == -1)
    np.testing.assert_allclose(compact.vertices, mesh.vertices)


@pytest.mark.parametrize(
    "vertices,tets,match",
    [
        (np.zeros((4, 2)), [[0, 1, 2, 3]], "shape"),
        (np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, np.nan]]), [[0, 1, 2, 3]], "non-finite"),
        (np.eye(4, 3), [[0, 1, 2, 4]], "indices must lie"),
        (np.eye(4, 3), [[0, 1, 2, -1]], "indices must lie"),
        (np.eye(4, 3), [[0, 1, 2, 2]], "repeat a vertex"),
        (np.eye(4, 3), [[0, 1, 2]], "shape"),
    ],
)
def test_invalid_meshes_raise_clear_errors(vertices, tets, match):
    with pytest.raises(TetMeshError, match=match):
        TetMesh(vertices, tets)


def test_decimated_surface_stays_on_the_sphere_and_closed(rng):
    import trimesh

    from holowarp.tetmesh import TetMeshError, decimate_surface, tetrahedralize_surface

    s = trimesh.creation.icosphere(subdivisions=5, radius=1.0)  # 20480 triangles
    R = trimesh.transformations.random_rotation_matrix(rng.random(3))[:3, :3]
    V0 = s.vertices @ R.T
    V, F = decimate_surface(V0, s.faces, 2000)
    assert 1500 <= len(F) <= 2100 and F.dtype == np.int32
    # The oracle: every vertex of the decimated sphere is still on the unit sphere (quadric
    # decimation keeps vertices near the original surface), and the surface stays closed.
    r = np.linalg.norm(V, axis=1)
    assert np.abs(r - 1.0).max() < 0.02
    assert trimesh.Trimesh(V, F, process=True).is_watertight
    # At or below the limit nothing changes.
    V2, F2 = decimate_surface(V0, s.faces, len(s.faces))
    assert np.array_equal(V2, V0) and np.array_equal(F2, s.faces)
    with pytest.raises(TetMeshError, match="max_faces"):
        decimate_surface(V0, s.faces, 3)
    mesh = tetrahedralize_surface(V0, s.faces, edge_length_fac=0.15, max_faces=2000)
    assert mesh.num_components() == 1 and mesh.manifold()["manifold"]
    assert np.all(mesh.signed_volumes() > 0)
    assert abs(mesh.volume() - 4.0 / 3.0 * np.pi) < 0.05 * 4.0 / 3.0 * np.pi
