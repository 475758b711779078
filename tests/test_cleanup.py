"""§7 cleanup and §4 hull: flip, drop, one component, manifold repair, degenerate hulls."""

from __future__ import annotations

import numpy as np
import pytest

from holowarp.primitives import box_tetmesh
from holowarp.manifold import fill_sealed, repair_manifold
from holowarp.stages.cleanup import cleanup
from holowarp.config import CleanupConfig, TetInitConfig
from holowarp.stages.tet_init import HullError, scaled_hull
from holowarp.tetmesh import TetMesh
from oracles import edge_fan


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


def _sealed_by_flood(tets: np.ndarray, keep: np.ndarray) -> np.ndarray:
    """Oracle for :func:`fill_sealed`: breadth-first flood from the mesh's boundary faces
    through removed tets, one face at a time (dict of sorted faces, no sparse graphs)."""
    from collections import deque

    faces: dict = {}
    for e, t in enumerate(tets):
        for k in range(4):
            faces.setdefault(tuple(sorted(np.delete(t, k))), []).append(e)
    reached = np.zeros(len(tets), dtype=bool)
    todo = deque(e for f, es in faces.items() if len(es) == 1 for e in es if not keep[e])
    for e in todo:
        reached[e] = True
    while todo:
        e = todo.popleft()
        for k in range(4):
            for n in faces[tuple(sorted(np.delete(tets[e], k)))]:
                if not keep[n] and not reached[n]:
                    reached[n] = True
                    todo.append(n)
    return ~keep & ~reached


def test_fill_sealed_puts_back_exactly_the_removed_tets_no_flood_from_outside_reaches(rng):
    mesh = box_tetmesh((5, 5, 5))
    centres = mesh.vertices[mesh.tets].mean(axis=1)
    for p in (0.15, 0.3, 0.45):
        keep = rng.random(mesh.num_tets) >= p
        keep[np.linalg.norm(centres - 0.5, axis=1) < 0.15] = False  # a pocket nothing opens
        expected = _sealed_by_flood(mesh.tets, keep)
        assert expected.any()
        out, filled = fill_sealed(keep, mesh.face_adjacency())
        np.testing.assert_array_equal(out, keep | expected)
        assert filled == int(expected.sum())
        assert not (out & ~keep & ~expected).any()
    # Nothing removed, nothing sealed: unchanged.
    all_kept = np.ones(mesh.num_tets, dtype=bool)
    assert fill_sealed(all_kept, mesh.face_adjacency())[1] == 0


def test_cleanup_fills_the_void_a_degenerate_interior_tet_leaves(rng):
    """An interior tet split 1-4 at a point almost on one of its faces: the child on that face
    is degenerate, and dropping it would leave a void of four faces with no mouth (a second
    boundary shell). Cleanup puts it back instead."""
    mesh = box_tetmesh((3, 3, 3))
    mesh = mesh.with_vertices(mesh.vertices + rng.uniform(-0.02, 0.02, mesh.vertices.shape))
    inner = np.ones(mesh.num_vertices, dtype=bool)
    inner[mesh.surface_vertices()] = False
    e = int(np.flatnonzero(inner[mesh.tets].all(axis=1))[0])  # a tet of the central cell
    a, b, c, d = mesh.tets[e]
    V = mesh.vertices
    w = rng.dirichlet(np.ones(3))
    p = w[0] * V[a] + w[1] * V[b] + w[2] * V[c] + 1e-6 * (V[d] - (V[a] + V[b] + V[c]) / 3)
    n = mesh.num_vertices
    children = np.array([[n, b, c, d], [a, n, c, d], [a, b, n, d], [a, b, c, n]])
    T = np.vstack([np.delete(mesh.tets, e, axis=0), children])
    split = TetMesh(np.vstack([V, p]), T)
    vol = split.signed_volumes()
    assert np.all(vol > 0) and vol[-1] < 1e-4 * np.median(vol)
    clean, kept, info = cleanup(split)
    assert info["dropped"] == 0 and info["filled_sealed"] == 1
    assert clean.num_tets == split.num_tets and clean.boundary_shells() == 1
    assert info["manifold"] and info["inverted_after_cleanup"] == 0
    # Without the fill the same mesh has a second shell: the void the test is about.
    assert split.submesh(np.arange(split.num_tets - 1)).boundary_shells() == 2
    # The sliver put back is §7b's to fix, from inside, with the boundary untouched.
    from holowarp.stages.improve import improve

    assert clean.quality_summary()["min_dihedral_worst"] < 0.01
    better, _, rep = improve(clean)
    assert rep["after"]["min_dihedral_worst"] > 10.0 and better.boundary_shells() == 1


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


def _with_apex_on_top_face(height):
    """The 2x2x2 box mesh plus one tet glued onto a top boundary face, its apex ``height``
    above the face's centroid: a tet with three boundary faces (its apex is in no other tet)."""
    mesh = box_tetmesh((2, 2, 2))
    bf = mesh.boundary_faces()
    top = bf[np.all(np.isclose(mesh.vertices[bf][:, :, 2], 1.0), axis=1)][0]
    apex = mesh.vertices[top].mean(axis=0) + [0.0, 0.0, height]
    V = np.vstack([mesh.vertices, apex])
    return mesh, TetMesh(V, np.vstack([mesh.tets, [[top[0], top[1], top[2], mesh.num_vertices]]]))


def test_cleanup_drops_flattened_boundary_caps_but_keeps_sound_tets():
    # A cap glued onto a top boundary face: its apex sits just above the face's plane.
    mesh, capped = _with_apex_on_top_face(1e-3)
    assert capped.signed_volumes()[-1] > 0
    clean, kept, info = cleanup(capped)
    assert info["dropped_caps"] == 1 and info["dropped"] == 1
    np.testing.assert_array_equal(np.sort(kept), np.arange(mesh.num_tets))
    assert info["manifold"] and clean.num_tets == mesh.num_tets


def test_cleanup_drops_flaps_below_the_flap_angle_and_keeps_sound_spikes():
    # A flap of 5-10 degrees is no cap (above cap_dihedral_deg) but has three boundary faces.
    mesh, flapped = _with_apex_on_top_face(0.015)
    angle = flapped.quality()["min_dihedral_deg"][-1]
    assert 5.0 < angle < 10.0 and flapped.boundary_mask()[-1].sum() == 3
    clean, kept, info = cleanup(flapped)
    assert info["dropped_flaps"] == 1 and info["dropped_caps"] == 1
    np.testing.assert_array_equal(np.sort(kept), np.arange(mesh.num_tets))
    assert info["manifold"] and clean.num_tets == mesh.num_tets
    # The same flap stays when the flap angle is lowered below it ...
    _, kept, info = cleanup(flapped, CleanupConfig(flap_dihedral_deg=angle - 0.5))
    assert info["dropped_flaps"] == 0 and len(kept) == flapped.num_tets
    # ... and a sound spike (three boundary faces, good angles) is never dropped.
    _, spiked = _with_apex_on_top_face(0.3)
    assert spiked.quality()["min_dihedral_deg"][-1] > 20.0
    _, kept, info = cleanup(spiked)
    assert info["dropped_flaps"] == 0 and len(kept) == spiked.num_tets


def test_cleanup_puts_back_caps_whose_removal_would_pinch_the_boundary():
    # Two thick fans around one edge, joined on one side by a 2-degree sliver sector and
    # open on the other: manifold as given. Dropping the sliver tets (caps: min dihedral
    # < 5 degrees, on the boundary) would leave two fans meeting at the edge only.
    sectors = [(0, 40), (40, 80), (80, 120), (120, 160), (160, 162), (162, 200), (200, 240), (240, 280), (280, 320)]
    mesh, owner = edge_fan(sectors)
    assert mesh.manifold()["manifold"] and mesh.num_components() == 1
    q = mesh.quality()["min_dihedral_deg"]
    assert np.all(q[owner == 4] < 5.0) and np.all(q[owner != 4] > 5.0)
    without = TetMesh(mesh.vertices, mesh.tets[owner != 4], validate=False)
    assert not without.manifold()["manifold"]  # what plain cap removal would leave

    clean, kept, info = cleanup(mesh)
    assert info["caps_restored_for_manifold"] > 0
    assert info["tets_removed_for_manifold"] == 0 and info["components_removed"] == 0
    assert info["manifold"] and clean.manifold()["manifold"] and clean.num_components() == 1
    # Every sound tet survives; only caps that the boundary does not need are gone.
    assert set(np.flatnonzero(owner != 4)) <= set(kept.tolist())
    assert info["dropped_caps"] + info["caps_restored_for_manifold"] == int((owner == 4).sum())
    assert clean.num_tets == mesh.num_tets - info["dropped_caps"]


def test_a_flap_put_back_with_a_pinching_cap_is_dropped_on_its_own():
    # The pinching sliver sector of the test above, plus a flap glued onto the top face of
    # one of its tets: the flap goes with the slivers, comes back with them (it touches the
    # pinched edge's vertex), and must then go alone.
    sectors = [(0, 40), (40, 80), (80, 120), (120, 160), (160, 162), (162, 200), (200, 240), (240, 280), (280, 320)]
    fan, owner = edge_fan(sectors)
    V, T = fan.vertices, fan.tets
    top = next(f for f in fan.boundary_faces() if np.allclose(V[f][:, 2], 1.0)
               and any(set(f) <= set(T[i]) for i in np.flatnonzero(owner == 4)))
    apex = V[top].mean(axis=0) + [0.0, 0.0, 0.05]  # 8.5 degrees, thick enough not to be degenerate
    mesh, _ = TetMesh(np.vstack([V, apex]), np.vstack([T, [[*top, len(V)]]]), validate=False).oriented()
    assert mesh.boundary_mask()[-1].sum() == 3 and mesh.manifold()["manifold"]

    clean, kept, info = cleanup(mesh)
    assert mesh.num_tets - 1 not in kept  # the flap is gone ...
    assert set(np.flatnonzero(owner != 4)) <= set(kept.tolist())  # ... every sound tet stays
    assert info["dropped_flaps"] == 1 and info["manifold"] and clean.manifold()["manifold"]
    assert clean.num_components() == 1 and clean.num_tets == mesh.num_tets - info["dropped_caps"]
    assert info["dropped_caps"] + info["caps_restored_for_manifold"] == int((owner == 4).sum()) + 1


def _prism(apex_deg: float, segments: int = 6, rng=None):
    """A triangular prism along z whose cross-section has an apex of ``apex_deg`` at the
    origin (a knife ridge along z) and 80°-ish corners elsewhere; each of ``segments``
    slabs is three tets (the staircase split of a prism). Vertices jittered by ``rng``."""
    h = np.tan(np.radians(apex_deg / 2))
    tri = np.array([[0.0, 0.0], [1.0, -h], [1.0, h]])
    z = np.linspace(0.0, 1.5, segments + 1)
    V = np.array([[x, y, zz] for zz in z for (x, y) in tri])
    if rng is not None:
        V += rng.uniform(-0.01, 0.01, V.shape)
    T = []
    for s in range(segments):
        a, b, c = 3 * s, 3 * s + 1, 3 * s + 2
        d, e, f = a + 3, b + 3, c + 3
        T += [[a, b, c, d], [b, c, d, e], [c, d, e, f]]
    mesh, _ = TetMesh(V, np.array(T)).oriented()
    return mesh


def test_blunting_opens_knife_ridges_within_its_move_bound(rng):
    from holowarp.stages.cleanup import blunt_ridges

    mesh = _prism(20.0, rng=rng)
    edges, wedge = mesh.boundary_wedges()
    apex = np.arange(0, mesh.num_vertices, 3)
    ridge = np.isin(edges, apex).all(axis=1)
    # The oracle: the wedge along the ridge is the cross-section's apex angle.
    assert np.allclose(wedge[ridge], 20.0, atol=2.5)
    assert wedge[~ridge].min() > 30.0
    cfg = CleanupConfig()
    out, info = blunt_ridges(mesh, cfg)
    assert info["sharp_edges_before"] == ridge.sum() and info["sharp_edges_after"] < info["sharp_edges_before"]
    L = np.linalg.norm(mesh.vertices[edges[:, 0]] - mesh.vertices[edges[:, 1]], axis=1).mean()
    move = np.linalg.norm(out.vertices - mesh.vertices, axis=1)
    assert move.max() <= cfg.blunt_max_move * L * (1 + 1e-9)
    assert np.isclose(info["max_move_mean_edges"], move.max() / L)
    # Only the ridge's vertices move, and they move into the body (towards the base, +x).
    assert np.all(move[np.setdiff1d(np.arange(mesh.num_vertices), apex)] == 0)
    assert np.all(out.vertices[apex, 0] > mesh.vertices[apex, 0])
    assert np.all(out.signed_volumes() > 0)
    assert out.boundary_wedges()[1][ridge].min() > wedge[ridge].max()
    # A box has 90° ridges: nothing moves, and 0 turns the step off.
    box = box_tetmesh((2, 2, 2))
    same, info = blunt_ridges(box, cfg)
    assert info["sharp_edges_before"] == 0 and np.array_equal(same.vertices, box.vertices)
    off, info = blunt_ridges(mesh, CleanupConfig(blunt_wedge_deg=0.0))
    assert info["vertices_moved"] == 0 and np.array_equal(off.vertices, mesh.vertices)
    with pytest.raises(ValueError, match="blunt_step"):
        CleanupConfig(blunt_step=0.0)


def test_blunting_moves_no_vertex_of_a_tet_it_would_leave_below_min_volume():
    from holowarp.stages.cleanup import blunt_ridges

    mesh = _prism(20.0)
    # Demand more volume of every tet than any has: no move is allowed, none happens.
    big = 10 * np.abs(mesh.signed_volumes()).max()
    out, info = blunt_ridges(mesh, CleanupConfig(), min_volume=-big)
    assert info["vertices_moved"] > 0
    still, info = blunt_ridges(mesh, CleanupConfig(), min_volume=big)
    assert info["vertices_moved"] == 0 and info["rounds"] == 0 and np.array_equal(still.vertices, mesh.vertices)


def test_a_cap_whose_removal_would_leave_a_knife_ridge_is_put_back():
    # An open fan of a 28-degree sector and a 3-degree one beside it: the thin sector's tets
    # are caps, but without them the fan's edge would be a knife ridge (wedge 28 < 30
    # degrees), which every tet there would have to cut at less than 28 degrees. (The flap
    # rule is off: one of the thin tets is also a flap, which goes whatever it leaves.)
    mesh, owner = edge_fan([(0, 28), (28, 31)])
    q = mesh.quality()["min_dihedral_deg"]
    assert np.all(q[owner == 1] < CleanupConfig().cap_dihedral_deg) and np.all(q[owner == 0] > 5.0)
    edges, wedge = mesh.boundary_wedges()
    axis = np.flatnonzero((np.sort(edges, axis=1) == [0, 1]).all(axis=1))
    assert np.isclose(wedge[axis], 31.0).all() and wedge.min() >= 30.0

    clean, kept, info = cleanup(mesh, CleanupConfig(flap_dihedral_deg=0.0))
    # The cap at the edge is put back; the two others go, as they leave no ridge behind.
    assert info["caps_restored_for_folds"] == 1 and info["dropped_caps"] == 2
    assert 3 in kept and info["blunt"]["sharp_edges_before"] == 0 and clean.boundary_wedges()[1].min() >= 30.0
    # Without the knife-ridge rule (blunting off) the caps go and the ridge sharpens.
    clean, kept, info = cleanup(mesh, CleanupConfig(flap_dihedral_deg=0.0, blunt_wedge_deg=0.0))
    assert info["dropped_caps"] == int((owner == 1).sum()) and info["caps_restored_for_folds"] == 0
    assert clean.boundary_wedges()[1].min() < 28.5


def test_a_fold_cap_sharper_than_what_its_removal_leaves_is_dropped_again():
    """A cap put back for a fold must leave the boundary less sharp than without it: in a
    fan that almost closes (a 3-degree sector of caps beside a 345-degree fan), putting back
    the cap at the axis turns a 15-degree slit into a 12-degree one, with a 3-degree tet
    standing in it; so it goes again, and every tet left is sound. The 28 + 3 degree fan of
    the test above keeps its cap: without it the ridge would be sharper."""
    from holowarp.stages.cleanup import _sharpest_at

    mesh, owner = edge_fan([(0, 90), (90, 180), (180, 270), (270, 345), (345, 348)])
    q = mesh.quality()["min_dihedral_deg"]
    assert np.all(q[owner == 4] < CleanupConfig().cap_dihedral_deg) and np.all(q[owner < 4] > 20.0)
    t = mesh.tets.astype(np.int64)
    cap = int(np.flatnonzero((owner == 4) & (t == 0).any(axis=1) & (t == 1).any(axis=1))[0])  # the sector's tet at the axis
    with_cap = TetMesh(mesh.vertices, t[(owner < 4) | (np.arange(len(t)) == cap)])
    assert np.isclose(_sharpest_at(with_cap, t[[cap]], mesh.num_vertices)[0], 12.0, atol=1e-6)
    assert np.isclose(_sharpest_at(TetMesh(mesh.vertices, t[owner < 4]), t[[cap]], mesh.num_vertices)[0], 15.0,
                      atol=1e-6)
    clean, kept, info = cleanup(mesh, CleanupConfig(flap_dihedral_deg=0.0))
    assert info["caps_restored_for_folds"] == 0 and info["dropped_caps"] == int((owner == 4).sum())
    assert info["manifold"] and clean.quality()["min_dihedral_deg"].min() > 20.0


def test_tets_wrapping_past_a_full_turn_are_peeled_at_an_end_of_their_fan():
    # Eight 50-degree sectors round one edge: 400 degrees, so the first and the last
    # sector overlap in space (the rim spirals outwards, so no two vertices coincide). The
    # oracle is the construction: the wedge at the axis is the sum of the sectors.
    sectors = [(50 * k, 50 * (k + 1)) for k in range(8)]
    mesh, owner = edge_fan(sectors, spiral=0.05)
    assert mesh.manifold()["manifold"] and np.all(mesh.signed_volumes() > 0)
    edges, wedge = mesh.boundary_wedges()
    axis = (np.sort(edges, axis=1) == [0, 1]).all(axis=1)
    assert np.isclose(wedge[axis], 400.0).all() and mesh.overlapping_edges() == 1
    clean, kept, info = cleanup(mesh, CleanupConfig())
    # One end tet at the axis goes (50 degrees): the fan no longer overlaps, nothing else changes.
    assert info["dropped_overlaps"] == 1 and clean.num_tets == mesh.num_tets - 1
    assert clean.overlapping_edges() == 0 and clean.manifold()["manifold"]
    edges, wedge = clean.boundary_wedges()
    assert np.isclose(wedge[(np.sort(edges, axis=1) == [0, 1]).all(axis=1)], 350.0).all()
    # A fan short of a full turn is left alone.
    mesh, _ = edge_fan(sectors[:7], spiral=0.05)
    clean, kept, info = cleanup(mesh, CleanupConfig())
    assert info["dropped_overlaps"] == 0 and mesh.overlapping_edges() == 0 and clean.num_tets == mesh.num_tets
