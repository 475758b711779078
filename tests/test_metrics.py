"""Metrics of method.md §9 against analytic oracles: concentric and shifted spheres, nested
cubes, a cube's 12 edges, PSNR of identical images, the winding-number inside test; plus the
exact-keys contract of ``evaluate_mesh`` and ``python -m holowarp.evaluate``."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from holowarp.frame import FrameError, unit_cube_transform
from holowarp.metrics import METRIC_KEYS, evaluate_mesh
from holowarp.metrics.evaluate import TET_KEYS
from holowarp.metrics.image import mask_psnr, psnr
from holowarp.metrics.surface import chamfer_metrics, edge_metrics, edge_sample_mask, sample_surface
from holowarp.metrics.volume import inside_mask

N = 50_000


def _sphere(radius, centre=(0.0, 0.0, 0.0), subdivisions=5):
    import trimesh

    s = trimesh.creation.icosphere(subdivisions=subdivisions, radius=radius)
    return np.asarray(s.vertices) + np.asarray(centre), np.asarray(s.faces)


def _cube(side, centre=(0.0, 0.0, 0.0)):
    import trimesh

    b = trimesh.creation.box(extents=(side, side, side))
    return np.asarray(b.vertices) + np.asarray(centre), np.asarray(b.faces)


def test_sampling_is_area_weighted_and_on_the_surface(rng):
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1.0], [3, 0, 1.0], [0, 2, 1.0]])
    f = np.array([[0, 1, 2], [3, 4, 5]])  # areas 0.5 and 3: ratio 1 : 6
    p, n, fi = sample_surface(v, f, 70_000, rng=rng)
    assert abs(np.mean(fi == 0) - 1 / 7) < 0.005
    np.testing.assert_allclose(p[fi == 0, 2], 0)
    np.testing.assert_allclose(p[fi == 1, 2], 1)
    assert (p[fi == 0, :2].sum(1) <= 1 + 1e-12).all() and (p[fi == 1, 0] / 3 + p[fi == 1, 1] / 2 <= 1 + 1e-12).all()
    np.testing.assert_allclose(n, np.tile([0, 0, 1.0], (len(n), 1)))


def test_concentric_spheres_give_chamfer_equal_to_the_radius_gap(rng):
    gv, gf = _sphere(0.5)
    pv, pf = _sphere(0.45)
    m = evaluate_mesh((pv, pf), (gv, gf), num_samples=N, seed=int(rng.integers(1 << 30)))
    s, _ = unit_cube_transform(gv)
    gap = 0.05 * s
    assert m["chamfer_l1"] == pytest.approx(gap, rel=0.01)
    assert m["chamfer_l2"] == pytest.approx(gap**2, rel=0.02)
    # The max of nearest-SAMPLE distances sits a little above the surface gap (sparsest spot).
    assert gap * 0.99 < m["hausdorff"] < gap * 1.1
    assert m["precision"] == 0 and m["recall"] == 0 and m["f_score"] == 0
    assert m["normal_consistency"] > 0.999
    assert m["volume_iou"] == pytest.approx(0.9**3, abs=0.01)
    assert all(m[k] is None for k in TET_KEYS)  # a surface has no tets


def test_shifted_sphere_gives_the_known_chamfer_and_lens_iou(rng):
    r, delta = 0.5, 0.1
    gv, gf = _sphere(r)
    direction = rng.normal(size=3)
    direction /= np.linalg.norm(direction)
    m = evaluate_mesh((gv + delta * direction, gf), (gv, gf), num_samples=N, seed=int(rng.integers(1 << 30)))
    s, _ = unit_cube_transform(gv)
    # Distance from the shifted copy to the sphere: |sqrt(r^2 + 2 r delta u + delta^2) - r|,
    # u = cos(angle to the shift) uniform in [-1, 1] by area (and the same the other way).
    u = np.linspace(-1, 1, 200_001)
    d = np.abs(np.sqrt(r * r + 2 * r * delta * u + delta * delta) - r)
    assert m["chamfer_l1"] == pytest.approx(d.mean() * s, rel=0.02)
    assert m["chamfer_l2"] == pytest.approx((d**2).mean() * s * s, rel=0.02)
    assert delta * s * 0.99 < m["hausdorff"] < delta * s * 1.1
    lens = math.pi * (4 * r + delta) * (2 * r - delta) ** 2 / 12
    ball = 4 / 3 * math.pi * r**3
    assert m["volume_iou"] == pytest.approx(lens / (2 * ball - lens), abs=0.01)


def test_nested_cubes_give_known_iou_chamfer_and_tet_quality():
    from holowarp.primitives import box_tetmesh

    a = 0.6  # inner cube side; GT cube side 1 is already the evaluation frame
    inner = box_tetmesh((4, 4, 4), size=(a, a, a), origin=(-a / 2, -a / 2, -a / 2))
    m = evaluate_mesh(inner, _cube(1.0), num_samples=N, seed=3)
    assert list(m) == list(METRIC_KEYS)
    assert m["volume_iou"] == pytest.approx(a**3, abs=0.006)
    # pred -> gt: every inner point is exactly 0.2 from the parallel outer face.
    # gt -> pred: sqrt(0.2^2 + excess_y^2 + excess_z^2) averaged over an outer face.
    g = (np.arange(2000) + 0.5) / 2000 - 0.5
    ex = np.clip(np.abs(g) - a / 2, 0, None)
    d_g = np.sqrt(0.2**2 + ex[:, None] ** 2 + ex[None, :] ** 2)
    assert m["chamfer_l1"] == pytest.approx(0.5 * (0.2 + d_g.mean()), rel=0.005)
    assert m["chamfer_l2"] == pytest.approx(0.5 * (0.04 + (d_g**2).mean()), rel=0.005)
    assert m["hausdorff"] == pytest.approx(math.sqrt(3) * 0.2, abs=0.01)
    assert m["components"] == 1 and m["manifold"] is True and m["genus"] == 0
    assert m["tets"] == 6 * 4**3 and m["inverted_ratio"] == 0
    # Kuhn tets of a cube: smallest dihedral 45 degrees, aspect ratio 1 + 1/sqrt(2).
    assert m["min_dihedral_mean"] == pytest.approx(45.0) and m["min_dihedral_worst"] == pytest.approx(45.0)
    assert m["aspect_ratio_mean"] == pytest.approx(1 + 1 / math.sqrt(2))


def test_inverted_tets_are_counted_on_the_mesh_as_given():
    from holowarp import TetMesh
    from holowarp.primitives import box_tetmesh

    box = box_tetmesh((2, 2, 2))
    t = box.tets.copy()
    t[:5] = t[:5][:, [0, 1, 3, 2]]
    m = evaluate_mesh(TetMesh(box.vertices, t), _cube(1.0, (0.5, 0.5, 0.5)), num_samples=5000, volume_points=20_000)
    assert m["inverted_ratio"] == pytest.approx(5 / len(t))
    assert m["volume_iou"] == pytest.approx(1.0, abs=0.01)  # geometry is unchanged


def test_edge_samples_find_the_twelve_cube_edges_and_none_on_a_sphere(rng):
    v, f = _cube(1.0)
    p, n, _ = sample_surface(v, f, 100_000, rng=rng)
    e = p[edge_sample_mask(p, n)]
    # Distance to the nearest cube edge: the two smallest |coord| - 0.5 gaps.
    gaps = np.sort(np.abs(np.abs(e) - 0.5), axis=1)
    assert np.sqrt(gaps[:, 0] ** 2 + gaps[:, 1] ** 2).max() <= 0.004 + 1e-9
    # Which edge: the axis along which the sample is NOT at a face, and the signs of the others.
    along = np.argmax(np.abs(np.abs(e) - 0.5), axis=1)
    keys = set()
    for q, ax in zip(e, along):
        others = [k for k in range(3) if k != ax]
        keys.add((ax,) + tuple(np.sign(q[others]).astype(int)))
    assert len(keys) == 12
    sv, sf = _sphere(0.5, subdivisions=4)
    ps, ns, _ = sample_surface(sv, sf, 100_000, rng=rng)
    assert not edge_sample_mask(ps, ns).any()


def test_edge_precision_recall_count_edge_samples_within_tau():
    # Two sharp "edges" along x: pairs of samples 0.002 apart with perpendicular normals.
    xs = np.arange(0, 1, 0.001)

    def edge(y):
        pts = np.concatenate([np.stack([xs, np.full_like(xs, y), np.zeros_like(xs)], 1),
                              np.stack([xs, np.full_like(xs, y + 0.002), np.zeros_like(xs)], 1)])
        nrm = np.concatenate([np.tile([0, 0, 1.0], (len(xs), 1)), np.tile([0, 1.0, 0], (len(xs), 1))])
        return pts, nrm

    g1, gn1 = edge(0.0)
    g2, gn2 = edge(0.5)
    gt = np.concatenate([g1, g2]), np.concatenate([gn1, gn2])
    p1, pn1 = edge(0.003)  # within tau = 0.005 of gt edge 1
    p2, pn2 = edge(0.8)  # 0.3 away from everything
    pred = np.concatenate([p1, p2]), np.concatenate([pn1, pn2])
    em = edge_metrics(pred[0], pred[1], gt[0], gt[1])
    assert em["edge_precision"] == pytest.approx(0.5)
    assert em["edge_recall"] == pytest.approx(0.5)
    assert em["edge_f1"] == pytest.approx(0.5)
    flat = np.tile([0, 0, 1.0], (len(p1), 1))  # same points, one normal: no edge samples
    none = edge_metrics(p1, flat, gt[0], gt[1])
    assert math.isnan(none["edge_precision"]) and none["edge_recall"] == 0 and none["edge_f1"] == 0


def test_precision_and_recall_at_both_thresholds_count_the_samples_within_them(rng):
    # GT: a 20 x 20 grid of spacing 0.05 on z = 0, in random order. Prediction: 200 of its
    # points exactly (d = 0), the next 100 lifted by 0.007 (within 0.01, not within 0.005), and
    # 50 points far above. The other 100 GT points are >= 0.05 from every prediction sample.
    g = np.stack(np.meshgrid(np.arange(20), np.arange(20), indexing="ij"), -1).reshape(-1, 2) * 0.05
    gt = np.concatenate([g, np.zeros((400, 1))], 1)[rng.permutation(400)]
    far = np.concatenate([rng.uniform(0, 1, (50, 2)), np.full((50, 1), 0.5)], 1)
    pred = np.concatenate([gt[:200], gt[200:300] + [0, 0, 0.007], far])
    up = lambda k: np.tile([0.0, 0.0, 1.0], (k, 1))  # noqa: E731
    m = chamfer_metrics(pred, up(len(pred)), gt, up(400), tau=0.01, tau_fine=0.005)
    assert m["precision"] == pytest.approx(300 / 350) and m["recall"] == pytest.approx(300 / 400)
    assert m["precision_005"] == pytest.approx(200 / 350) and m["recall_005"] == pytest.approx(200 / 400)
    p, r = 200 / 350, 200 / 400
    assert m["f_score_005"] == pytest.approx(2 * p * r / (p + r))


def test_chamfer_metrics_of_identical_samples_are_perfect(rng):
    p, n, _ = sample_surface(*_sphere(0.5, subdivisions=3), 5000, rng=rng)
    m = chamfer_metrics(p, n, p, n)
    assert m["chamfer_l1"] == 0 and m["hausdorff"] == 0 and m["f_score"] == 1 and m["normal_consistency"] == pytest.approx(1)


def test_identical_images_give_infinite_psnr_and_offsets_the_known_value(rng):
    img = rng.random((2, 8, 9, 3))
    assert psnr(img, img.copy()) == math.inf
    assert psnr(np.full((4, 4), 0.3), np.full((4, 4), 0.4)) == pytest.approx(20.0)
    m = rng.random((3, 5, 5))
    assert mask_psnr(m, m) == math.inf
    m2 = m.copy()
    m2[0, 0, 0] += 0.5 if m2[0, 0, 0] < 0.5 else -0.5  # one pixel of 75 off by 0.5
    assert mask_psnr(m2, m) == pytest.approx(10 * math.log10(75 / 0.25))


def test_winding_inside_test_matches_the_analytic_ball_even_with_holes(rng):
    v, f = _sphere(0.5, subdivisions=4)
    pts = rng.uniform(-0.7, 0.7, (20_000, 3))
    r = np.linalg.norm(pts, axis=1)
    clear = np.abs(r - 0.5) > 5e-3
    ins = inside_mask(v, f, pts)
    np.testing.assert_array_equal(ins[clear], (r < 0.5)[clear])
    holey = f[rng.permutation(len(f))[:-20]]  # drop 20 faces: no longer watertight
    ins2 = inside_mask(v, holey, pts)
    assert np.mean(ins2[clear] == (r < 0.5)[clear]) > 0.995


def test_winding_inside_gives_the_same_answer_on_one_thread_and_in_pieces(rng):
    from holowarp.device import set_cpu_threads
    from holowarp.ops.winding import winding_inside

    v, f = _sphere(rng.uniform(0.3, 0.6), subdivisions=3)
    pts = rng.uniform(-0.7, 0.7, (5_000 + int(rng.integers(0, 300)), 3))  # not a whole number of pieces
    try:
        set_cpu_threads(1)
        one = winding_inside(v, f, pts)
        set_cpu_threads(2)
        pieces = winding_inside(v, f, pts)
    finally:
        set_cpu_threads(None)
    np.testing.assert_array_equal(one, pieces)
    assert 0 < one.sum() < len(one)


def test_unit_cube_normalisation_centres_and_scales_by_the_reference():
    ref = np.array([[1.0, 2.0, 3.0], [3.0, 3.0, 4.0]])
    s, t = unit_cube_transform(ref)
    np.testing.assert_allclose(ref * s + t, [[-0.5, -0.25, -0.25], [0.5, 0.25, 0.25]])
    np.testing.assert_allclose(np.array([[2.0, 2.5, 3.5]]) * s + t, [[0, 0, 0]])
    with pytest.raises(FrameError, match="zero-size"):
        unit_cube_transform(np.ones((4, 3)))
    with pytest.raises(FrameError, match="non-finite vertex"):
        unit_cube_transform([[0.0, 0.0, 0.0], [np.nan, 1.0, 1.0]])


def test_evaluate_command_writes_exactly_the_contract_keys(tmp_path, capsys):
    from holowarp import write_tetmesh
    from holowarp.evaluate import main
    from holowarp.surface_io import write_surface
    from holowarp.primitives import box_tetmesh

    write_tetmesh(tmp_path / "pred.vtu", box_tetmesh((3, 3, 3), size=(0.8, 0.8, 0.8), origin=(-0.4, -0.4, -0.4)))
    write_surface(tmp_path / "gt.obj", _cube(1.0))
    out = tmp_path / "m.json"
    rc = main([str(tmp_path / "pred.vtu"), "--gt", str(tmp_path / "gt.obj"), "--json", str(out), "--samples", "5000"])
    assert rc == 0
    doc = json.loads(out.read_text())
    assert list(doc) == list(METRIC_KEYS)
    assert doc["components"] == 1 and doc["tets"] == 6 * 27
    text = capsys.readouterr().out
    assert "Chamfer-L1" in text and "LPIPS" in text
    assert main([str(tmp_path / "missing.vtu"), "--gt", str(tmp_path / "gt.obj")]) == 2
    assert "missing.vtu" in capsys.readouterr().err


def test_evaluate_with_dataset_adds_silhouette_psnr(tmp_path):
    from holowarp.data import load_dataset
    from holowarp.surface_io import write_surface
    from holowarp.synthesis import synthesize
    from holowarp.primitives import box_tetmesh

    write_surface(tmp_path / "cube.obj", _cube(2.0))
    synthesize(tmp_path / "cube.obj", tmp_path / "ds", views=20, res=32, up_axis="z", progress=False)
    ds = load_dataset(tmp_path / "ds")
    exact = box_tetmesh((2, 2, 2), size=(1, 1, 1), origin=(-0.5, -0.5, -0.5))
    smaller = box_tetmesh((2, 2, 2), size=(0.8, 0.8, 0.8), origin=(-0.4, -0.4, -0.4))
    m1 = evaluate_mesh(exact, ds.gt_mesh, dataset=ds, num_samples=5000, volume_points=20_000)
    m2 = evaluate_mesh(smaller, ds.gt_mesh, dataset=ds, num_samples=5000, volume_points=20_000)
    assert list(m1) == list(METRIC_KEYS) + ["psnr_mask"]
    assert m1["psnr_mask"] > 40 and m2["psnr_mask"] < 20
    # 5000 samples on a unit cube: the chamfer floor is the sample spacing (~0.017).
    assert m1["chamfer_l1"] < 0.025 < m2["chamfer_l1"] and m1["volume_iou"] > 0.99


def test_concave_mask_is_the_distance_inside_a_convex_hull(rng):
    from holowarp.metrics.surface import concave_mask

    # Inside the unit cube the distance to the hull boundary is the distance to the nearest face.
    cube = np.array([[x, y, z] for x in (0, 1) for y in (0, 1) for z in (0, 1)], float)
    pts = rng.uniform(-0.2, 1.2, (5000, 3))
    d = np.min(np.concatenate([pts, 1 - pts], axis=1), axis=1)  # negative outside
    np.testing.assert_array_equal(concave_mask(pts, cube, margin=0.1), d > 0.1)


def test_chamfer_floor_is_sampling_noise_and_shrinks_with_more_samples(rng):
    from holowarp.metrics.surface import chamfer_floor

    V, F = _sphere(0.5)
    coarse = chamfer_floor(V, F, 2_000, rng=rng)
    fine = chamfer_floor(V, F, 50_000, rng=rng)
    # Nearest-sample distances scale like the sample spacing ~ sqrt(area / n).
    assert 0 < fine < coarse
    assert fine / coarse == pytest.approx(np.sqrt(2_000 / 50_000), rel=0.25)


def test_fine_f_score_and_concave_chamfer_see_a_filled_bowl(rng):
    """A hemispherical bowl against its convex hull (what silhouettes give): the concave
    Chamfer is about the depth of the missing cavity, the fine F-score drops."""
    import trimesh

    from holowarp.metrics.surface import concave_mask
    from holowarp.shapes import shape_surface

    V, F = shape_surface("bowl", resolution=64, max_faces=None)
    h = trimesh.convex.convex_hull(V)
    gt, gn, _ = sample_surface(V, F, 100_000, rng=rng)
    concave = concave_mask(gt, V)
    scores = {}
    for name, (pv, pf) in {"self": (V, F), "hull": (np.asarray(h.vertices), np.asarray(h.faces))}.items():
        pp, pn, _ = sample_surface(pv, pf, 100_000, rng=rng)
        d: dict = {}
        m = chamfer_metrics(pp, pn, gt, gn, distances=d)
        scores[name] = (m["f_score_005"], float(d["gt_to_pred"][concave].mean()))
    assert concave.mean() > 0.3  # the inside of the bowl
    assert scores["self"][1] < 0.005 < 0.05 < scores["hull"][1]  # the hull misses the cavity's depth
    assert scores["self"][0] > 0.9 and scores["hull"][0] < scores["self"][0] - 0.2


def test_error_maps_colour_both_surfaces_on_the_fixed_scale(tmp_path):
    import trimesh

    from holowarp.previews import ERROR_SCALE, write_error_maps

    big, small = _sphere(0.5), _sphere(0.49)
    out = write_error_maps(tmp_path, small, big)
    for name in ("pred_error.ply", "gt_missing.ply", "error_views.png"):
        assert (tmp_path / name).is_file()
    assert out["distances"]["pred_to_gt"]["mean"] == pytest.approx(0.01, abs=1e-3)
    ply = trimesh.load(tmp_path / "pred_error.ply", process=False)
    colors = np.asarray(ply.visual.vertex_colors)[:, :3]
    assert len(np.unique(colors, axis=0)) <= 4  # one distance everywhere: one colour (up to float32)
    assert out["scale"] == [0.0, ERROR_SCALE]


def test_closest_distance_kernel_matches_trimesh_on_random_points(rng):
    import trimesh
    from oracles import point_triangle_distance

    from holowarp.ops.closest import closest_distance

    s = trimesh.creation.icosphere(subdivisions=2, radius=0.4)
    V = np.asarray(s.vertices) + rng.normal(scale=0.02, size=s.vertices.shape)  # not a sphere any more
    F = np.asarray(s.faces)
    pts = rng.uniform(-0.8, 0.8, (2000, 3))
    ref = point_triangle_distance(pts, V[F[:, 0]], V[F[:, 1]], V[F[:, 2]]).min(axis=1)
    np.testing.assert_allclose(closest_distance(V, F, pts), ref, atol=2e-6)
