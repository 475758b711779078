"""The silhouette polish (holowarp.stages.polish) on an analytic scene: a tet mesh of a sphere
grown by 6% against the masks of the true sphere."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from holowarp.config import PolishConfig, preset
from holowarp.data import Dataset
from holowarp.stages.polish import keep_angles, polish_silhouettes
from holowarp.tetmesh import TetMesh
from holowarp.tetmesh import tetrahedralize_surface

RADIUS = 0.35


@pytest.fixture(scope="module")
def grown_sphere():
    """12 views of a sphere of radius 0.35 at 32x32 (ground-truth renderer), and a tet mesh
    of the same sphere grown by 6% (about a quarter of a pixel at the silhouettes)."""
    from holowarp.render_gt import GTRenderer
    from holowarp.synthesis import protocol_cameras

    s = trimesh.creation.icosphere(subdivisions=4, radius=RADIUS)
    res, n = 32, 12
    viewmats, K = protocol_cameras(n, 1.6, res)
    r = GTRenderer(s.vertices, s.faces, supersample=2)
    rgba = np.stack([r.render(vm, K, res, res)["rgba"] for vm in viewmats]).astype(np.float32)
    ds = Dataset(images=rgba[..., :3], masks=rgba[..., 3], K=np.repeat(K[None], n, axis=0), viewmats=viewmats,
                 train_idx=np.arange(n), test_idx=np.arange(0, n, 4), name="sphere")
    c = trimesh.creation.icosphere(subdivisions=2, radius=RADIUS * 1.06)
    return ds, tetrahedralize_surface(c.vertices, c.faces, edge_length_fac=0.15)


def _boundary_radius_error(V, mesh) -> float:
    b = np.unique(mesh.boundary_faces())
    return float(np.abs(np.linalg.norm(V[b], axis=1) - RADIUS).mean())


def test_polish_pulls_a_grown_boundary_onto_the_silhouettes(grown_sphere):
    ds, mesh = grown_sphere
    V0 = np.asarray(mesh.vertices)
    cfg = PolishConfig(steps=40, views=4, lr=0.03, min_volume_fraction=0.5)
    V, info = polish_silhouettes(mesh, ds, cfg, seed=3)
    before, after = _boundary_radius_error(V0, mesh), _boundary_radius_error(V, mesh)
    assert before > 0.015 and after < 0.4 * before, (before, after)
    assert info["mask_l1_after"] < 0.7 * info["mask_l1_before"]
    # Only boundary vertices move; every tet keeps half its volume (the floor here), so none inverts.
    inner = np.setdiff1d(np.arange(len(V0)), np.unique(mesh.boundary_faces()))
    assert np.array_equal(V[inner], V0[inner])
    vol0, vol = mesh.signed_volumes(), mesh.with_vertices(V).signed_volumes()
    assert np.all(vol >= 0.5 * vol0 * (1 - 1e-5))
    assert info["steps"] == 40 and info["views_per_step"] == 4 and 0 < info["moved_mean"] <= info["moved_max"]
    # The views each step draws are a function of (seed, step).
    V2, _ = polish_silhouettes(mesh, ds, cfg, seed=3)
    assert np.array_equal(V, V2)


def test_the_interior_ring_follows_the_boundary_by_the_set_fraction(grown_sphere):
    ds, mesh = grown_sphere
    V0 = np.asarray(mesh.vertices)
    cfg = PolishConfig(steps=20, views=4, lr=0.03, min_volume_fraction=0.5, interior_follow=0.8)
    V, info = polish_silhouettes(mesh, ds, cfg, seed=3)
    assert info["mask_l1_after"] < 0.7 * info["mask_l1_before"]
    # numpy oracle: an interior vertex with boundary neighbours (over tet edges) moves by 0.8 x
    # their mean displacement; deeper vertices stay
    on = np.zeros(len(V0), dtype=bool)
    on[np.unique(mesh.boundary_faces())] = True
    e = np.asarray(mesh.edges())
    e = np.concatenate([e, e[:, ::-1]])
    e = e[~on[e[:, 0]] & on[e[:, 1]]]
    ring = np.unique(e[:, 0])
    want = np.array([V0[r] + 0.8 * (V[e[e[:, 0] == r, 1]] - V0[e[e[:, 0] == r, 1]]).mean(0) for r in ring])
    close = np.abs(V[ring] - want).max(axis=1) < 1e-6
    assert close.mean() > 0.9 and np.abs(V[ring] - V0[ring]).max() > 1e-3  # the floor may hold a few back
    deep = ~on
    deep[ring] = False
    assert np.array_equal(V[deep], V0[deep])
    assert np.all(mesh.with_vertices(V).signed_volumes() >= 0.5 * mesh.signed_volumes() * (1 - 1e-5))


def test_the_default_floor_keeps_four_fifths_of_every_tet(grown_sphere):
    ds, mesh = grown_sphere
    V, info = polish_silhouettes(mesh, ds, PolishConfig(steps=15, views=4, lr=0.03), seed=1)
    assert info["moved_max"] > 0 and info["mask_l1_after"] < info["mask_l1_before"]
    assert np.all(mesh.with_vertices(V).signed_volumes() >= 0.8 * mesh.signed_volumes() * (1 - 1e-5))


def test_polish_without_steps_leaves_the_mesh_alone(grown_sphere):
    ds, mesh = grown_sphere
    V, info = polish_silhouettes(mesh, ds, PolishConfig(steps=0), seed=0)
    assert np.array_equal(V, np.asarray(mesh.vertices)) and info["moved_max"] == 0.0
    assert info["mask_l1_after"] == pytest.approx(info["mask_l1_before"])


def test_keep_angles_puts_back_exactly_the_moves_that_cost_the_floor(grown_sphere):
    from oracles import min_dihedral_deg

    _, mesh = grown_sphere
    rng_seed = int(np.random.SeedSequence().entropy % 2**32)  # fresh inputs; the seed is in every message
    rng = np.random.default_rng(rng_seed)
    V0 = np.asarray(mesh.vertices)
    b = np.unique(mesh.boundary_faces())
    h = float(np.median(np.linalg.norm(V0[mesh.edges()[:, 0]] - V0[mesh.edges()[:, 1]], axis=1)))
    # Fewer than half the boundary vertices move, so "not every move goes back" below is
    # certain; moving all of them by 0.25 h put more than half back on 8% of the draws.
    V1 = V0.copy()
    moved = rng.choice(b, (len(b) - 1) // 2, replace=False)
    V1[moved] += rng.normal(scale=0.35 * h, size=(len(moved), 3))
    worst0 = min_dihedral_deg(V0, mesh.tets).min()
    floor = min(10.0, worst0)
    assert (min_dihedral_deg(V1, mesh.tets) < floor).sum() > 5, rng_seed  # the moves do cost angles
    V, put_back = keep_angles(mesh, V1, 10.0)
    # Every vertex is where the fit put it or back at its start, and the count says how many went back.
    back = np.all(V == V0, axis=1) & np.any(V1 != V0, axis=1)
    assert np.all(np.all(V == V1, axis=1) | np.all(V == V0, axis=1))
    assert put_back == back.sum() > 0 and back.sum() < 0.5 * len(b), rng_seed
    # No tet below the floor, none inverted.
    assert min_dihedral_deg(V, mesh.tets).min() >= floor - 1e-9, rng_seed
    assert np.all(mesh.with_vertices(V).signed_volumes() > 0)
    # The first round puts back the vertices of the tets below the floor, and only those.
    bad1 = min_dihedral_deg(V1, mesh.tets) < floor
    assert np.isin(np.flatnonzero(back), mesh.tets[bad1]).any()
    # Moves that cost nothing stay: a floor of 0 keeps every non-inverting move.
    small = V0.copy()
    small[b] += rng.normal(scale=1e-4 * h, size=(len(b), 3))
    V2, n2 = keep_angles(mesh, small, 0.0)
    assert n2 == 0 and np.array_equal(V2, small)


def _fan_and_lone_tet(total_deg: float):
    """A fan of 50-degree sectors round the z-axis edge (vertices 0 and 1) adding up to
    ``total_deg``, plus a lone tet far from it; the fan's rim vertices, and those at the
    axis's foot (the ones in the axis's own tets)."""
    from oracles import edge_fan

    fan, _ = edge_fan([(a, a + 50) for a in range(0, int(total_deg), 50)], spiral=0.05)
    lone = np.array([[5.0, 0, 0], [6.0, 0, 0], [5.0, 1.0, 0], [5.0, 0, 1.0]])
    V = np.concatenate([fan.vertices, lone])
    T = np.concatenate([fan.tets, [np.arange(4) + fan.num_vertices]])
    mesh, _ = TetMesh(V, T).oriented()
    return mesh, np.arange(2, fan.num_vertices), np.arange(2, 2 + (fan.num_vertices - 2) // 2)


def test_keep_unfolded_puts_back_the_moves_that_wrap_a_fan_past_a_full_turn(rng):
    from holowarp.stages.polish import keep_unfolded
    from oracles import axis_wedge, turn_rim

    mesh, rim, foot = _fan_and_lone_tet(350.0)
    apex = mesh.num_vertices - 1
    V1 = turn_rim(mesh, (foot, rim[len(foot):]), 1.1)
    V1[apex] += rng.uniform(0.05, 0.1, 3)  # a move far from the fan
    assert np.isclose(axis_wedge(mesh, V1), 385.0) and mesh.with_vertices(V1).overlapping_edges() == 1
    V, put_back = keep_unfolded(mesh, V1)
    # The moved rim vertices of the axis's tets go back (the one at azimuth 0 never moved),
    # the rest of the rim and the lone tet keep their moves.
    back = np.flatnonzero(np.any(V != V1, axis=1))
    assert put_back == len(foot) - 1 and np.array_equal(back, foot[1:])
    assert np.array_equal(V[back], np.asarray(mesh.vertices)[back])
    assert np.array_equal(V[apex], V1[apex]) and np.isclose(axis_wedge(mesh, V), 350.0)
    # Turning the other way (335 degrees) costs nothing and stays.
    V2, n2 = keep_unfolded(mesh, turn_rim(mesh, (foot, rim[len(foot):]), 335.0 / 350.0))
    assert n2 == 0 and np.isclose(axis_wedge(mesh, V2), 335.0)
    # A fan over a full turn already may unwind, not wind further.
    over, rim, foot = _fan_and_lone_tet(400.0)
    V3, n3 = keep_unfolded(over, turn_rim(over, (foot, rim[len(foot):]), 0.95))
    assert n3 == 0 and np.isclose(axis_wedge(over, V3), 380.0)
    V4, n4 = keep_unfolded(over, turn_rim(over, (foot, rim[len(foot):]), 1.02))
    assert n4 == len(foot) - 1 and np.isclose(axis_wedge(over, V4), 400.0)


@pytest.mark.parametrize("bad", [dict(steps=-1), dict(views=0), dict(steps=2.5), dict(lr=float("nan")),
                                 dict(smooth=-1.0), dict(min_volume_fraction=1.0), dict(check_views=0),
                                 dict(pit_depth=-0.1), dict(pit_floor=1.0), dict(after_steps=-1),
                                 dict(after_volume_fraction=1.0), dict(after_angle_floor=-1.0),
                                 dict(after_angle_floor=90.0), dict(after_angle_floor=True),
                                 dict(w_prior=-0.1), dict(w_prior=float("inf")), dict(after_w_surfels=-0.1),
                                 dict(after_w_surfels=float("nan")), dict(refine_bend=(60.0, 25.0)),
                                 dict(refine_bend=(25.0,)), dict(refine_bend=(-1.0, 60.0)),
                                 dict(refine_bend=(25.0, 181.0)), dict(refine_bend=(True, 60.0)),
                                 dict(refine_factor=0.0), dict(refine_factor=1.5), dict(refine_keep_deg=-1.0),
                                 dict(refine_keep_deg=90.0), dict(interior_follow=-0.1),
                                 dict(after_interior_follow=1.5), dict(after_interior_follow=True)])
def test_polish_settings_are_checked(bad):
    with pytest.raises(ValueError, match="PolishConfig"):
        PolishConfig(**bad)


def test_both_presets_polish():
    assert preset("fast").polish.enabled and preset("paper").polish.enabled


def test_the_quality_bench_switches_the_polish_off_as_written():
    from holowarp.bench.quality import apply_overrides

    for word in ("False", "false"):
        assert apply_overrides(preset("fast"), [f"polish.enabled={word}"]).polish.enabled is False
    assert apply_overrides(preset("fast"), ["polish.steps=20"]).polish.steps == 20
    with pytest.raises(ValueError, match="expected a number"):
        apply_overrides(preset("fast"), ["polish.steps=ten"])


def _pit_mesh(z: float):
    """A tetrahedron (a, b, c, p) whose top face is replaced by a fan around v = (0, 0, z): a
    one-tet pit for z < 0, a bump for z > 0; 0.2 across, centred in the sphere scene's views."""
    from holowarp.tetmesh import TetMesh

    ang = 2 * np.pi * np.arange(3) / 3
    V = np.array([[np.cos(t), np.sin(t), 0.0] for t in ang] + [[0.0, 0.0, -2.0], [0.0, 0.0, z]]) * 0.1
    T = np.array([[4, 0, 1, 3], [4, 1, 2, 3], [4, 2, 0, 3]])
    a, b, c, d = (V[T[:, k]] for k in range(4))
    neg = np.einsum("ij,ij->i", b - a, np.cross(c - a, d - a)) < 0
    T[neg] = T[neg][:, [1, 0, 2, 3]]
    return TetMesh(V, T)


@pytest.mark.parametrize("z, flattened", [(-1.0, True), (-0.3, False), (0.3, False)])
def test_a_one_tet_pit_is_put_back_on_its_rim(z, flattened):
    from holowarp.stages.polish import lift_pits

    mesh = _pit_mesh(z)
    V, lifted = lift_pits(mesh, PolishConfig())
    assert lifted == int(flattened)
    if flattened:  # onto the plane of its three neighbours, straight up
        np.testing.assert_allclose(V[4], [0.0, 0.0, 0.0], atol=1e-6)
        assert np.all(mesh.with_vertices(V).signed_volumes() > mesh.signed_volumes())
    else:
        np.testing.assert_array_equal(V, mesh.vertices)
    np.testing.assert_array_equal(V[:4], mesh.vertices[:4])


def test_polish_normal_prior_adds_the_mean_chord_of_a_numpy_reference(grown_sphere):
    from dataclasses import replace

    import torch

    from holowarp.ops import rasterize_mesh
    from holowarp.render_gt import GTRenderer
    from holowarp.stages.polish import _boundary_graph, _view_loss

    ds, mesh = grown_sphere
    r = GTRenderer(*(lambda s: (s.vertices, s.faces))(trimesh.creation.icosphere(subdivisions=4, radius=RADIUS)))
    normals = np.stack([r.render(vm, k, ds.width, ds.height)["normal"] for vm, k in zip(ds.viewmats, ds.K)])
    with_n = replace(ds, normals=normals.astype(np.float32))
    ids, lf, _, _ = _boundary_graph(mesh)
    rng = np.random.default_rng()
    xb = torch.tensor(np.asarray(mesh.vertices)[ids] * rng.uniform(0.97, 1.03, (len(ids), 1)), dtype=torch.float32)
    faces = torch.tensor(lf, dtype=torch.int32)
    v, w = int(rng.integers(len(ds.viewmats))), float(rng.uniform(0.2, 2.0))
    mask, prior = torch.as_tensor(ds.masks[v]), torch.as_tensor(with_n.normals[v])
    got = float(_view_loss(xb, faces, with_n, v, mask, prior, w))
    out = rasterize_mesh(xb, faces, ds.viewmats[v], ds.K[v], ds.width, ds.height)
    a, n = (out[k].detach().numpy().astype(np.float64) for k in ("alpha", "normal"))
    p = with_n.normals[v].astype(np.float64)
    sel = (a > 0.5) & (np.linalg.norm(p, axis=-1) > 0.5)
    cos = (n * p).sum(-1)[sel] / (np.linalg.norm(n, axis=-1)[sel] * np.linalg.norm(p, axis=-1)[sel])
    ref = np.abs(a - ds.masks[v]).mean() + w * np.mean(np.sqrt(2.0 * (1.0 - cos) + 1e-6))
    assert sel.sum() > 100 and 0.0 < np.mean(1.0 - cos) < 0.2
    assert got == pytest.approx(ref, rel=1e-4)
    assert float(_view_loss(xb, faces, with_n, v, mask, None, w)) == pytest.approx(np.abs(a - ds.masks[v]).mean(), rel=1e-5)
    # A prior weight changes the polish only where the dataset has normal maps.
    cfg = PolishConfig(steps=6, views=4, lr=0.03, min_volume_fraction=0.5)
    V0, _ = polish_silhouettes(mesh, ds, cfg, seed=2)
    assert np.array_equal(polish_silhouettes(mesh, ds, replace(cfg, w_prior=1.0), seed=2)[0], V0)
    assert not np.array_equal(polish_silhouettes(mesh, with_n, replace(cfg, w_prior=1.0), seed=2)[0], V0)


def test_a_normals_source_stands_in_for_the_datasets_maps(grown_sphere):
    """``polish_silhouettes(normals=...)`` compares with the given maps exactly as with the
    dataset's own, and :class:`SurfelNormals` gives the surfels' rendered normals, unit where
    they are opaque and 0 elsewhere, rendered once per view."""
    from dataclasses import replace

    import torch

    from holowarp.render_gt import GTRenderer
    from holowarp.stages.polish import SurfelNormals
    from holowarp.tetgs import TetGaussians

    ds, mesh = grown_sphere
    r = GTRenderer(*(lambda s: (s.vertices, s.faces))(trimesh.creation.icosphere(subdivisions=4, radius=RADIUS)))
    maps = np.stack([r.render(vm, k, ds.width, ds.height)["normal"] for vm, k in zip(ds.viewmats, ds.K)]).astype(np.float32)
    cfg = PolishConfig(steps=6, views=4, lr=0.03, min_volume_fraction=0.5, w_prior=1.0)
    own, _ = polish_silhouettes(mesh, replace(ds, normals=maps), cfg, seed=2)
    given, _ = polish_silhouettes(mesh, ds, cfg, seed=2, normals=lambda v: torch.as_tensor(maps[v]))
    assert np.array_equal(own, given)
    assert not np.array_equal(given, polish_silhouettes(mesh, ds, cfg, seed=2)[0])

    model = TetGaussians(mesh)
    src = SurfelNormals(model, ds, "cpu")
    v = int(np.random.default_rng().integers(len(ds.viewmats)))
    n = src(v)
    assert src(v) is n and n.shape == (ds.height, ds.width, 3) and n.dtype == torch.float32
    with torch.no_grad():
        out = model.render(ds.viewmats[v], ds.K[v], ds.width, ds.height)
    ref = out["normal"].double().numpy()
    opaque = out["alpha"].numpy() > 0.5
    ref = np.where(opaque[..., None], ref / np.maximum(np.linalg.norm(ref, axis=-1, keepdims=True), 1e-8), 0.0)
    assert opaque.sum() > 50 and (~opaque).sum() > 50
    np.testing.assert_allclose(n.numpy(), ref, atol=1e-5)


def test_the_quality_bench_checks_the_element_angles_too():
    from holowarp.bench.quality import _ratios, _targets

    rng = np.random.default_rng()
    side = lambda worst, mean: {"components": 1, "genus": 1, "boundary_shells": 1, "manifold": True,  # noqa: E731
                                "inverted_ratio": 0.0, "volume_iou": 0.9, "f_score_005": 0.9,
                                "normal_consistency": 0.95, "hausdorff": 0.02, "chamfer_l1": 0.003,
                                "chamfer_l1_floor": 0.002, "concave_chamfer": 0.004,
                                "min_dihedral_worst": worst, "min_dihedral_mean": mean}
    for worst, mean in ((rng.uniform(10.0, 20.0), rng.uniform(40.0, 55.0)), (rng.uniform(0.5, 9.99), 47.0),
                        (12.0, rng.uniform(30.0, 39.9))):
        row = {"object": "bob", "concave": False, "genus_expected": 1, "holowarp": side(worst, mean),
               "hull": side(10.0, 45.0)}
        t = _targets(row, _ratios(row))
        assert t["worst_dihedral_ge_10"] == (worst >= 10.0) and t["mean_dihedral_ge_40"] == (mean >= 40.0)
        assert t["exact_genus"] and t["normal_consistency_ge_hull"]


def _bends_by_brute_force(mesh: TetMesh, lo: float, hi: float) -> np.ndarray:
    """Reference for bend_tets: every pair of boundary faces sharing an edge (and no third
    face on it), their outward normals' angle, one pair at a time."""
    faces, owner = mesh.boundary_faces(), mesh.boundary_face_tets()
    V = np.asarray(mesh.vertices, dtype=np.float64)
    normal = [np.cross(V[f[1]] - V[f[0]], V[f[2]] - V[f[0]]) for f in faces]
    by_edge = {}
    for k, f in enumerate(faces):
        for a, b in ((f[0], f[1]), (f[1], f[2]), (f[2], f[0])):
            by_edge.setdefault((min(a, b), max(a, b)), []).append(k)
    marked = np.zeros(mesh.num_tets, bool)
    for pair in by_edge.values():
        if len(pair) != 2:
            continue
        n1, n2 = normal[pair[0]], normal[pair[1]]
        deg = np.degrees(np.arccos(np.clip(n1 @ n2 / np.linalg.norm(n1) / np.linalg.norm(n2), -1.0, 1.0)))
        if lo < deg < hi:
            marked[owner[pair]] = True
    return marked


def test_bend_tets_finds_the_edge_a_fan_bends_at():
    """A fan of 230 degrees round the z-axis edge: its two end faces there meet at 180 - 230
    = -50 degrees, i.e. their normals 50 degrees apart; every other boundary edge of the fan
    is flat (0), a cap's (90), between sides (115) or a side's against an end (140)."""
    from holowarp.stages.polish import bend_tets
    from oracles import edge_fan

    mesh, owner = edge_fan([(0, 100), (100, 230)])
    marked = bend_tets(mesh, 45.0, 55.0)
    at_axis = np.flatnonzero(np.all(np.isin(mesh.tets, [0, 1]).sum(1, keepdims=True) == 2, axis=1))
    # The axis's own tets are one per sector ([0, p, q, 1]); both hold an end face.
    assert np.array_equal(np.flatnonzero(marked), at_axis) and len(at_axis) == 2
    assert set(owner[marked]) == {0, 1}
    assert not bend_tets(mesh, 55.0, 85.0).any() and not bend_tets(mesh, 0.0, 45.0)[at_axis].any()
    for lo, hi in ((0.0, 180.0), (45.0, 55.0), (85.0, 95.0), (100.0, 180.0), (1.0, 60.0)):
        assert np.array_equal(bend_tets(mesh, lo, hi), _bends_by_brute_force(mesh, lo, hi)), (lo, hi)


def test_bend_tets_matches_a_brute_force_reference_on_a_jittered_sphere(grown_sphere, rng):
    from holowarp.stages.polish import bend_tets

    _, mesh = grown_sphere
    b = np.unique(mesh.boundary_faces())
    V = np.array(mesh.vertices)
    V[b] *= rng.uniform(0.9, 1.1, size=(len(b), 1))
    jittered = mesh.with_vertices(V)
    for lo, hi in ((5.0, 30.0), (25.0, 60.0), (0.0, 180.0)):
        ours = bend_tets(jittered, lo, hi)
        assert ours.any() and np.array_equal(ours, _bends_by_brute_force(jittered, lo, hi)), (lo, hi)


def test_refine_bends_splits_the_bent_tets_and_keeps_the_solid(grown_sphere, rng):
    from holowarp.refine import edge_table
    from holowarp.stages.polish import bend_tets, refine_bends
    from oracles import min_dihedral_deg, surface_area

    _, mesh = grown_sphere
    b = np.unique(mesh.boundary_faces())
    V = np.array(mesh.vertices)
    V[b[rng.choice(len(b), 6, replace=False)]] *= 1.15  # six spikes: the only sharp bends
    spiky = mesh.with_vertices(V)
    cfg = PolishConfig(refine_bend=(25.0, 60.0), refine_factor=0.75)
    marked = bend_tets(spiky, 25.0, 60.0)
    assert 0 < marked.sum() < 0.2 * spiky.num_tets
    V2, T2, parent, ends, info = refine_bends(spiky, cfg)
    refined = TetMesh(V2, T2)
    assert info["marked"] == marked.sum() and info["tets_before"] == spiky.num_tets
    assert info["tets_after"] == len(T2) > spiky.num_tets and len(ends) == len(V2) - len(V)
    assert np.array_equal(V2[: len(V)], V) and np.allclose(V2[len(V):], 0.5 * (V2[ends[:, 0]] + V2[ends[:, 1]]))
    # Conforming and positive; the solid and its boundary are the same point set.
    assert refined.manifold()["manifold"] and refined.num_components() == 1 and min_dihedral_deg(V2, T2).min() > 0
    assert np.isclose(refined.volume(), spiky.volume(), rtol=1e-9)
    assert np.isclose(surface_area(refined), surface_area(spiky), rtol=1e-9)
    # Every child of a marked tet is down to the target.
    _, _, length, longest = edge_table(V2, T2)
    assert np.all(length[longest[marked[parent]]] <= info["target"] * (1 + 1e-9))
    _, _, length0, longest0 = edge_table(V, spiky.tets)
    assert np.isclose(info["target"], 0.75 * np.median(length0[longest0[marked]]))
    # Off, or nothing bent that much: nothing to do.
    assert refine_bends(spiky, PolishConfig(refine_bend=None)) is None
    assert refine_bends(mesh, PolishConfig(refine_bend=(89.0, 90.0))) is None


@pytest.mark.parametrize("with_deg, without_deg, kept", [(12.0, None, True), (3.8, 17.0, False), (9.8, 7.1, True)])
def test_the_finish_keeps_the_bisection_only_where_improve_still_reaches_its_target(monkeypatch, with_deg,
                                                                                    without_deg, kept):
    """report._polish_and_improve with the polish and §7b replaced by stand-ins whose worst
    angle is given: the refined mesh stays when §7b reaches 10° on it, else the polish and
    §7b run again without the bisection and the better of the two meshes is kept. The
    surfels are refitted once, after the choice, on the kept mesh."""
    import holowarp.report as report

    class Model:
        def __init__(self):
            self.state, self.loads = "cleaned", []

        def state_dict(self):
            return self.state

        def load_state_dict(self, d):
            self.loads.append(d)
            self.state = d

    calls = []

    def polish(model, clean, dataset, config, device, state):
        bisect = config.polish.refine_bend is not None
        calls.append(("polish", bisect, clean))
        model.state = "refined" if bisect else "plain"
        info = {"tets_before": 10, "tets_after": 20} if bisect else None
        return f"{model.state} mesh", {"refined": info}

    def improve(model, clean, dataset, config, device, state):
        calls.append(("improve", clean))
        worst = with_deg if clean == "refined mesh" else without_deg
        return f"improved {clean}", {"after": {"min_dihedral_worst": worst}}

    monkeypatch.setattr(report, "_polish", polish)
    refits = []

    def refit(model, dataset, config, device, state, info):
        refits.append((model.state, info["after"]["min_dihedral_worst"]))
        return info

    monkeypatch.setattr(report, "_improve", improve)
    monkeypatch.setattr(report, "_refit", refit)
    model, config = Model(), preset("fast")
    mesh, pinfo, iinfo = report._polish_and_improve(model, "cleaned mesh", None, config, "cpu", None)
    ref = pinfo["refined"]
    assert ref["kept"] is kept and ref["min_dihedral_worst"] == with_deg
    assert ref.get("without") == without_deg and (len(calls) == 2) == (without_deg is None)
    if without_deg is not None:  # the second pass starts from the model as cleanup left it
        assert calls[2] == ("polish", False, "cleaned mesh") and model.loads[0] == "cleaned"
    assert mesh == ("improved refined mesh" if kept else "improved plain mesh")
    assert model.state == ("refined" if kept else "plain")
    assert iinfo["after"]["min_dihedral_worst"] == (with_deg if kept else without_deg)
    assert refits == [(model.state, iinfo["after"]["min_dihedral_worst"])]
