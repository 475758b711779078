"""§7 cleanup and §4 hull: flip, drop, one component, manifold repair, degenerate hulls."""

from __future__ import annotations

import numpy as np
import pytest

from holowarp.primitives import box_tetmesh
from holowarp.stages.cleanup import cleanup, repair_manifold
from holowarp.config import TetInitConfig
from holowarp.stages.tet_init import HullError, scaled_hull
from holowarp.tetmesh import TetMesh


def _edge_pinched_block():
    # 2x2x2 cells; removing two bottom cells leaves the other two bottom cells touching
    # along one vertical edge, while the full top layer keeps everything connected.
    mask = np.ones((2, 2, 2), dtype=bool)
    mask[1, 0, 0] = mask[0, 1, 0] = False
    return box_tetmesh((2, 2, 2), split=6, cell_mask=mask)


def _vertex_pinched_block():
    # A 2x2x2 block and a single cube touching it at one corner only (merged vertex).
    a = box_tetmesh((2, 2, 2), (2, 2, 2))
    b = box_tetmesh((1, 1, 1), origin=(2, 2, 2))
    V = np.vstack([a.vertices, b.vertices])
    T = np.vstack([a.tets, b.tets + a.num_vertices])
    uniq, inv = np.unique(np.round(V, 9), axis=0, return_inverse=True)
    return TetMesh(uniq, inv.reshape(-1)[T])


@pytest.mark.parametrize("make,defect", [(_edge_pinched_block, "edge"), (_vertex_pinched_block, "vertex")])
def test_pinched_boundary_is_repaired_into_one_manifold_component(make, defect):
    mesh = make()
    man = mesh.manifold()
    assert not man["manifold"]
    assert (man["bad_edges"] if defect == "edge" else man["bad_vertices"]) > 0
    keep, info = repair_manifold(mesh)
    fixed = mesh.submesh(keep)
    assert info["manifold"] and fixed.manifold()["manifold"]
    assert fixed.num_components() == 1
    assert 0 < info["removed_tets"] < mesh.num_tets // 2


def test_cleanup_flips_fine_inverted_tets_and_drops_degenerate_ones(rng):
    mesh = box_tetmesh((3, 3, 3))
    mesh = mesh.with_vertices(mesh.vertices + rng.uniform(-0.02, 0.02, mesh.vertices.shape))
    t = mesh.tets.copy()
    inv = rng.choice(mesh.num_tets, 7, replace=False)
    t[inv, 0], t[inv, 1] = mesh.tets[inv, 1], mesh.tets[inv, 0]
    # A sliver: a tet on four nearly coplanar new vertices, glued to nothing.
    V = np.vstack([mesh.vertices, [[5, 5, 5], [6, 5, 5], [5, 6, 5], [6, 6, 5 + 1e-9]]])
    n = mesh.num_vertices
    bad = TetMesh(V, np.vstack([t, [[n, n + 1, n + 2, n + 3]]]))
    clean, kept, info = cleanup(bad)
    np.testing.assert_array_equal(np.sort(kept), np.arange(mesh.num_tets))
    assert info["inverted_before_cleanup"] == 7  # the sliver is tiny but positive
    assert info["flipped"] == 7
    assert info["dropped"] == 1
    assert info["components"] == 1 and info["manifold"]
    assert info["inverted_after_cleanup"] == 0
    assert clean.num_tets == mesh.num_tets
    np.testing.assert_allclose(clean.volume(), mesh.volume(), rtol=1e-12)


def test_cleanup_keeps_largest_component_and_counts_the_rest():
    a = box_tetmesh((2, 2, 2))
    b = box_tetmesh((1, 1, 1), origin=(5, 0, 0))
    both = TetMesh(np.vstack([a.vertices, b.vertices]), np.vstack([a.tets, b.tets + a.num_vertices]))
    clean, kept, info = cleanup(both)
    np.testing.assert_array_equal(kept, np.arange(a.num_tets))
    assert info["components_before"] == 2 and info["components_removed"] == 1
    assert info["tets_removed_by_component"] == b.num_tets
    assert clean.num_tets == a.num_tets


def test_scaled_hull_is_outward_and_scaled_about_its_centroid(rng):
    P = rng.normal(size=(200, 3)) * [1.0, 0.5, 0.3]
    V, F = scaled_hull(P)
    import trimesh

    tm = trimesh.Trimesh(V, F, process=False)
    assert tm.is_watertight and tm.volume > 0
    from scipy.spatial import ConvexHull

    assert tm.volume == pytest.approx(ConvexHull(P).volume * TetInitConfig.hull_scale**3, rel=1e-9)


@pytest.mark.parametrize(
    "points,match",
    [
        (np.zeros((3, 3)), "at least 4 points"),
        (np.c_[np.random.default_rng(0).normal(size=(50, 2)), np.zeros(50)], "no 3D hull|degenerate"),
    ],
)
def test_degenerate_hulls_raise_clear_errors(points, match):
    with pytest.raises(HullError, match=match):
        scaled_hull(points)


def test_cleanup_drops_flattened_boundary_caps_but_keeps_sound_tets():
    mesh = box_tetmesh((2, 2, 2))
    bf = mesh.boundary_faces()
    top = bf[np.all(np.isclose(mesh.vertices[bf][:, :, 2], 1.0), axis=1)][0]
    # A cap glued onto a top boundary face: its apex sits just above the face's plane.
    apex = mesh.vertices[top].mean(axis=0) + [0.0, 0.0, 1e-3]
    V = np.vstack([mesh.vertices, apex])
    cap = np.array([[top[0], top[1], top[2], mesh.num_vertices]])  # apex on the outward side: positive
    capped = TetMesh(V, np.vstack([mesh.tets, cap]))
    assert capped.signed_volumes()[-1] > 0
    clean, kept, info = cleanup(capped)
    assert info["dropped_caps"] == 1 and info["dropped"] == 1
    np.testing.assert_array_equal(np.sort(kept), np.arange(mesh.num_tets))
    assert info["manifold"] and clean.num_tets == mesh.num_tets
