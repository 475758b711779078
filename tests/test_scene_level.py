"""Scene level (method.md §11, ``reconstruct --scene-level``, :mod:`holowarp.stages.objects`):
the component rule of the prunes and the cleanup, the clustering split of touching objects,
the names, the simulation scene, a tiny end-to-end run of two separated boxes, and (slow)
spot, bob and a box against their single-object reconstructions."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from holowarp.config import CleanupConfig, TopologyConfig, kept_components, preset
from holowarp.primitives import box_tetmesh
from holowarp.stages.objects import assign_objects, cluster_split, name_objects, scene_toml

RES = 32

TWO_BOXES = """
[[objects]]
name = "red"
box = [0.3, 0.3, 0.3]
position = [0.0, 0.0, 0.0]
color = [0.85, 0.2, 0.15]
[[objects]]
name = "blue"
box = [0.25, 0.25, 0.4]
position = [0.6, 0.0, 0.05]
color = [0.15, 0.3, 0.85]
"""


# ---------------------------------------------------------------------------- the component rule
def test_component_rule_keeps_the_largest_or_every_one_above_the_threshold():
    labels = np.repeat([0, 1, 2, 3], [50, 30, 15, 5])  # 100 tets in four components
    assert np.array_equal(kept_components(labels, 4, None), labels == 0)
    assert np.array_equal(kept_components(labels, 4, 0.1), labels <= 2)  # 5 tets < 10% of 100
    assert np.array_equal(kept_components(labels, 4, 0.9), labels == 0)  # the largest always stays
    with pytest.raises(ValueError, match="min_component"):
        TopologyConfig(min_component=0.0)
    with pytest.raises(ValueError, match="min_component"):
        CleanupConfig(min_component=1.5)


def test_cleanup_keeps_both_separated_objects_only_at_scene_level():
    from holowarp.stages.cleanup import cleanup
    from holowarp.tetmesh import TetMesh

    a = box_tetmesh((3, 3, 3), size=(1, 1, 1))
    b = box_tetmesh((2, 2, 2), size=(0.6, 0.6, 0.6), origin=(3.0, 0.0, 0.0))
    both = TetMesh(np.concatenate([a.vertices, b.vertices]), np.concatenate([a.tets, b.tets + a.num_vertices]))
    one, _, info = cleanup(both, CleanupConfig())
    assert one.num_tets == a.num_tets and info["components_removed"] == 1
    two, _, info = cleanup(both, CleanupConfig(min_component=0.05))
    assert two.num_tets == both.num_tets and two.num_components() == 2 and info["components_removed"] == 0


# ---------------------------------------------------------------------------- object size
@pytest.mark.parametrize("k", [0.4, 2.5])
def test_at_object_size_runs_the_same_field_optimisation_on_a_scaled_object(rng, k):
    """A mesh k times smaller with phi' = k phi under ``at_object_size(k)`` gives the same
    opacities, and Adam steps on the field objective (a target opacity per tet, L_eik and
    L_smooth with the config's weights and learning rates) keep phi' = k phi and
    kappa' = kappa / k."""
    from holowarp.ops.tet_energy import phi_edge_losses
    from holowarp.stages.topology import GaussianOptimizers
    from holowarp.tetgs import TetGaussians
    from holowarp.tetmesh import TetMesh
    import torch

    base = box_tetmesh((3, 3, 3), size=(1.0, 0.8, 0.6))
    mesh = TetMesh(base.vertices + rng.uniform(-0.03, 0.03, base.vertices.shape), base.tets)
    phi = rng.uniform(-0.2, 0.1, mesh.num_vertices)
    target = torch.tensor(rng.uniform(0.05, 0.95, mesh.num_tets), dtype=torch.float32)
    cfg = preset("fast")
    scaled = cfg.at_object_size(k)
    assert scaled.scene.object_size == k and cfg.scene.object_size is None
    runs = []
    for c, m, p in ((cfg, mesh, phi), (scaled, TetMesh(mesh.vertices * k, mesh.tets), phi * k)):
        model = TetGaussians(m, phi=p, config=c.topology)
        opts = GaussianOptimizers(model, c.topology, learn_scales=False)
        edges = torch.tensor(np.array(m.edges()), dtype=torch.int32)
        alphas = [model.field_opacities().detach().clone()]
        for _ in range(3):
            eik, smooth = phi_edge_losses(model.phi, edges, model.vertices.detach())
            loss = ((model.field_opacities() - target) ** 2).mean() + c.topology.lam_eik * eik + \
                c.topology.lam_smooth * smooth
            opts.zero_grad()
            loss.backward()
            opts.step()
        runs.append((alphas[0], model.phi.detach().numpy(), float(model.kappa.detach())))
    (a0, phi0, kappa0), (a1, phi1, kappa1) = runs
    assert torch.allclose(a0, a1, atol=1e-5)
    assert not np.allclose(phi0, phi)  # the steps moved the field
    assert np.allclose(phi1, k * phi0, rtol=1e-4, atol=1e-6 * k)
    assert kappa1 == pytest.approx(kappa0 / k, rel=1e-4)
    with pytest.raises(ValueError, match="object size"):
        cfg.at_object_size(0.0)
    with pytest.raises(ValueError, match="object_size"):
        replace(cfg.scene, object_size=-1.0)


def test_object_size_is_the_largest_objects_side_from_the_masks(two_boxes):
    """Two separated boxes: the measured size is the larger box's largest side (its ground
    truth in the dataset's frame), within a grid cell below and the visual hull's excess above."""
    import trimesh

    from holowarp.data import load_dataset
    from holowarp.stages.objects import hull_pieces, measure_object_size

    sides = {n: float(np.ptp(trimesh.load(two_boxes / "objects" / n / "gt.obj", force="mesh").vertices, axis=0).max())
             for n in ("red", "blue")}
    ds = load_dataset(two_boxes, res=RES)
    size = measure_object_size(ds)
    assert max(sides.values()) - 0.02 <= size <= max(sides.values()) + 0.06, (size, sides)
    assert size < 0.6  # not the whole scene (largest side 1)
    # hull_pieces: one box per object, each holding its ground truth's (less a grid cell)
    # and not much more.
    pieces = hull_pieces(ds)
    assert len(pieces) == 2
    gts = [trimesh.load(two_boxes / "objects" / n / "gt.obj", force="mesh").vertices for n in sides]
    for lo, hi in pieces:
        v = min(gts, key=lambda g: np.linalg.norm(g.mean(0) - 0.5 * (lo + hi)))
        assert np.all(lo <= v.min(0) + 0.02) and np.all(hi >= v.max(0) - 0.02), (n, lo, hi, v.min(0), v.max(0))
        assert np.all(lo >= v.min(0) - 0.08) and np.all(hi <= v.max(0) + 0.08), (n, lo, hi, v.min(0), v.max(0))


def _cube_pieces():
    """Two separated cubes, sides 1 and 0.5: their boxes and their corners."""
    import trimesh

    big, small = trimesh.creation.box((1.0, 1.0, 1.0)), trimesh.creation.box((0.5, 0.5, 0.5))
    small.apply_translation((2.0, 0.3, 0.0))
    return [(m.bounds[0], m.bounds[1]) for m in (big, small)], np.concatenate([big.vertices, small.vertices])


def test_object_sizing_gives_each_object_its_own_edge_length():
    """Oracle: a node in or near an object's box has ``SIZING_GAIN * fac * hull_scale *``
    its box diagonal, a node far from both the larger of those and ``fac`` x the diagonal of
    the box asked for; the grid covers that box, with positive tets."""
    from holowarp.stages.tet_init import SIZING_GAIN, SIZING_MARGIN, object_sizing

    pieces, pts = _cube_pieces()
    lo, hi = pts.min(0) - 0.3, pts.max(0) + 0.3
    X, T, val = object_sizing(pieces, lo, hi, edge_length_fac=0.04, hull_scale=1.1, cells=20)
    assert np.all(X.min(0) <= lo) and np.all(X.max(0) >= hi)
    e = X[T]
    assert np.all(np.einsum("ij,ij->i", np.cross(e[:, 1] - e[:, 0], e[:, 2] - e[:, 0]), e[:, 3] - e[:, 0]) > 0)
    edge = [SIZING_GAIN * 0.04 * 1.1 * np.sqrt(3) * side for side in (1.0, 0.5)]
    step = (hi - lo).max() / 20
    for i, (plo, phi) in enumerate(pieces):
        d = np.linalg.norm(np.maximum(plo - X, 0) + np.maximum(X - phi, 0), axis=1)
        assert np.allclose(val[d == 0], edge[i]) and (d == 0).sum() >= 8
        assert np.allclose(val[(d > 0) & (d <= SIZING_MARGIN * step * 0.99)], edge[i])
    far = np.all([np.linalg.norm(np.maximum(a - X, 0) + np.maximum(X - b, 0), axis=1) > SIZING_MARGIN * step * 1.01
                  for a, b in pieces], axis=0)
    assert far.sum() > 0 and np.allclose(val[far], 0.04 * np.linalg.norm(hi - lo))  # longer than the objects'
    X, T, val = object_sizing(pieces, pieces[0][0], pieces[0][1], edge_length_fac=0.2, hull_scale=2.0, cells=20)
    assert np.isclose(val.max(), SIZING_GAIN * 0.2 * 2.0 * np.sqrt(3))  # here the big cube's is longer
    with pytest.raises(ValueError, match="no objects"):
        object_sizing([], lo, hi, edge_length_fac=0.04)


def test_initial_tetmesh_meshes_each_object_as_finely_as_alone():
    """fTetWild with the sizing field: inside each cube of a two-cube scene the mean tet
    edge is within 15% of the cube's own when tetrahedralised alone (one convex hull each),
    where one edge length for the whole scene would give the small cube about twice its own."""
    from holowarp.config import TetInitConfig
    from holowarp.stages.tet_init import initial_tetmesh

    pieces, pts = _cube_pieces()
    cfg = TetInitConfig(edge_length_fac=0.05, min_points=8)

    def mean_edge(mesh, lo, hi):
        c = mesh.vertices[mesh.tets].mean(axis=1)
        t = mesh.tets[np.all((c > lo) & (c < hi), axis=1)]
        e = np.concatenate([t[:, [i, j]] for i in range(4) for j in range(i + 1, 4)])
        return np.linalg.norm(mesh.vertices[e[:, 0]] - mesh.vertices[e[:, 1]], axis=1).mean()

    scene = initial_tetmesh(pts, config=cfg, pieces=pieces)
    for i, (lo, hi) in enumerate(pieces):
        alone = initial_tetmesh(pts[8 * i:8 * i + 8], config=cfg)
        ratio = mean_edge(scene, lo, hi) / mean_edge(alone, lo, hi)
        assert 0.85 <= ratio <= 1.15, (i, ratio)
    # One edge length for the scene: fac x the hull's diagonal, twice the small cube's here.
    hull = 1.1 * np.linalg.norm(np.ptp(pts, axis=0))
    assert mean_edge(scene, *pieces[1]) < 0.6 * 0.05 * hull


# ---------------------------------------------------------------------------- clustering
def _touching_blobs(rng):
    """A 4 x 1 x 1 bar of tets: the first unit (x < 1) is one red object, the other three
    units one blue object, touching across the plane x = 1. Returns (mesh, centroids,
    noisy colours, oracle labels: True for the red object)."""
    mesh = box_tetmesh((16, 4, 4), size=(4.0, 1.0, 1.0))
    c = mesh.vertices[mesh.tets].mean(axis=1)
    red = c[:, 0] < 1.0
    colors = np.where(red[:, None], [0.8, 0.2, 0.15], [0.15, 0.3, 0.8]) + rng.normal(0, 0.05, (len(c), 3))
    return mesh, c, colors.clip(0, 1), red


def test_touching_objects_of_different_colours_are_split_by_clustering(rng):
    mesh, c, colors, red = _touching_blobs(rng)
    assert mesh.num_components() == 1
    objects, info = assign_objects(mesh, c, colors, 2)
    assert len(objects) == 2 and info["split_components"] == [{"component": 0, "tets": mesh.num_tets, "objects": 2}]
    blue_ids, red_ids = objects  # largest first
    assert np.array_equal(np.sort(red_ids), np.flatnonzero(red))
    assert np.array_equal(np.sort(blue_ids), np.flatnonzero(~red))
    assert info["unassigned_tets"] == 0
    for ids in objects:
        m = mesh.submesh(ids)
        assert m.num_components() == 1 and m.manifold()["manifold"] and m.genus() == 0
    # The positions alone would cut the bar in its middle (x = 2), not where the colours change.
    alone = cluster_split(c, colors, 2, color_weight=0.0)
    assert abs(np.mean(c[alone == alone[np.argmin(c[:, 0])], 0] < 1.0) - 1.0) > 0.3


def test_clusters_are_made_face_connected():
    from holowarp.stages.objects import _connected_clusters

    mesh = box_tetmesh((8, 1, 1), size=(8.0, 1.0, 1.0))
    cell = np.floor(mesh.vertices[mesh.tets].mean(axis=1)[:, 0]).astype(int)
    labels = (cell >= 4).astype(np.int64)
    labels[cell == 1] = 1  # a stray piece of cluster 1 inside cluster 0, which it cuts in two
    labels[(cell == 6) & (mesh.vertices[mesh.tets].mean(axis=1)[:, 1] > 0.5)] = 0  # and stray tets of 0 in 1
    fixed = _connected_clusters(mesh.face_adjacency(), labels)
    assert np.array_equal(fixed, (cell >= 4).astype(np.int64))


def test_more_components_than_objects_keeps_the_largest_and_reports_the_rest():
    from holowarp.tetmesh import TetMesh

    a = box_tetmesh((3, 3, 3))
    b = box_tetmesh((1, 1, 1), origin=(3.0, 0.0, 0.0))
    m = TetMesh(np.concatenate([a.vertices, b.vertices]), np.concatenate([a.tets, b.tets + a.num_vertices]))
    c = m.vertices[m.tets].mean(axis=1)
    objects, info = assign_objects(m, c, np.full_like(c, 0.5), 1)
    assert len(objects) == 1 and len(objects[0]) == a.num_tets and info["unassigned_tets"] == b.num_tets


def test_objects_are_named_after_the_nearest_ground_truth():
    gt = {"spot": [0.0, 0.0, 0.0], "bob": [1.0, 0.0, 0.0]}
    assert name_objects([[0.95, 0.1, 0.0], [0.05, 0.0, 0.0]], gt) == ["bob", "spot"]
    assert name_objects([[0.9, 0, 0], [5, 5, 5], [0, 0, 0]], gt) == ["bob", "object_0", "spot"]
    assert name_objects([[0, 0, 0], [1, 1, 1]], {}) == ["object_0", "object_1"]
    assert name_objects([[0, 0, 0], [1, 1, 1]], {"object_0": [1, 1, 1]}) == ["object_1", "object_0"]


def test_the_simulation_scene_keeps_the_objects_relative_positions(tmp_path):
    from holowarp.sim.scene import load_scene, placement_transform

    a = box_tetmesh((2, 2, 2), size=(0.4, 0.4, 0.4), origin=(-0.5, -0.2, -0.1))
    b = box_tetmesh((1, 1, 2), size=(0.2, 0.2, 0.3), origin=(0.3, 0.1, 0.05))
    text = scene_toml([a, b], ["a.vtu", "b.vtu"], ["big", "small-1"])
    (tmp_path / "scene.toml").write_text(text)
    scene = load_scene(tmp_path / "scene.toml")
    assert [s.name for s in scene.bodies] == ["big", "small_1"]
    assert [Path(s.mesh).name for s in scene.bodies] == ["a.vtu", "b.vtu"]
    placed = []
    for m, sp in zip((a, b), scene.bodies):
        R, s, pos = placement_transform(m.vertices, sp.placement)
        assert np.allclose(R, np.eye(3)) and s == pytest.approx(0.1 / 0.4)
        placed.append(m.vertices * s + pos)
    # One scale and one translation for both: the layout is the reconstruction's, scaled.
    k = 0.1 / 0.4
    assert np.allclose(placed[0] - k * a.vertices, placed[1][0] - k * b.vertices[0])
    assert min(p[:, 2].min() for p in placed) == pytest.approx(0.05)


# ---------------------------------------------------------------------------- end to end, tiny
@pytest.fixture(scope="module")
def two_boxes(tmp_path_factory):
    from holowarp.scene_synth import synthesize_scene

    root = tmp_path_factory.mktemp("two_boxes")
    (root / "scene.toml").write_text(TWO_BOXES)
    synthesize_scene(root / "scene.toml", root / "data", views=24, res=RES, progress=False)
    (root / "data" / "gt.obj").unlink()  # the whole scene's metrics are the single-object path's, tested elsewhere
    return root / "data"


def tiny_scene_config():
    """The fast preset shrunk to a couple of hundred iterations at 32 x 32, coarse tets."""
    cfg = preset("fast").scaled(0.1)
    cfg = replace(cfg, resolution=RES, checkpoint_every=40, tet_init=replace(cfg.tet_init, edge_length_fac=0.08))
    cfg = cfg.scene_level()
    return replace(cfg, scene=replace(cfg.scene, evaluate_objects=False))


@pytest.fixture(scope="module")
def tiny_scene_run(two_boxes, tmp_path_factory, one_torch_thread):
    from holowarp.pipeline import reconstruct

    out = tmp_path_factory.mktemp("scene_run") / "run"
    return out, reconstruct(two_boxes, out, config=tiny_scene_config(), progress=False)


def test_two_separated_boxes_give_two_named_clean_objects(tiny_scene_run):
    from holowarp import read_tetmesh

    out, report = tiny_scene_run
    scene = report["scene"]
    assert sorted(o["name"] for o in scene["objects"]) == ["blue", "red"]
    assert scene["split_components"] == [] and scene["unassigned_tets"] == 0 and scene["missing"] == []
    for o in scene["objects"]:
        assert (o["components"], o["manifold"], o["inverted"], o["genus"]) == (1, True, 0, 0), o
        m = read_tetmesh(out / "objects" / o["name"] / "tetmesh.vtu")
        assert m.num_tets == o["tets"] and np.all(m.signed_volumes() > 0)
    # The blue box is the one at +x (position 0.6 against 0.0 in the scene file).
    x = {o["name"]: o["centre"][0] for o in scene["objects"]}
    assert x["blue"] > x["red"]
    # The whole scene stays the single-object outputs: both objects in tetmesh.vtu.
    assert report["components"] == 2 and read_tetmesh(out / "tetmesh.vtu").num_tets == sum(
        o["tets"] for o in scene["objects"])
    assert json.loads((out / "report.json").read_text())["scene"]["objects"] == scene["objects"]
    # The run scaled its length-valued settings to the measured object size; the checkpoint
    # keeps the caller's config, so --resume compares like with like.
    from holowarp.runstate import Checkpoint

    size = report["config"]["scene"]["object_size"]
    assert 0.3 < size < 0.6
    clamp = tiny_scene_config().topology.kappa_clamp[1]
    assert report["config"]["topology"]["kappa_clamp"][1] == pytest.approx(clamp / size)
    assert Checkpoint.load(out).config["scene"]["object_size"] is None


def test_the_scene_usd_has_one_deformable_body_per_object(tiny_scene_run):
    from pxr import Usd, UsdGeom

    out, report = tiny_scene_run
    stage = Usd.Stage.Open(str(out / "scene.usda"))
    tets = {p.GetParent().GetName(): len(UsdGeom.TetMesh(p).GetTetVertexIndicesAttr().Get())
            for p in stage.Traverse() if p.IsA(UsdGeom.TetMesh)}
    assert tets == {o["name"]: o["tets"] for o in report["scene"]["objects"]}
    for name in tets:
        # Authored apiSchemas: GetAppliedSchemas() hides the codeless Omni Physics ones.
        schemas = stage.GetPrimAtPath(f"/World/{name}").GetMetadata("apiSchemas").GetAddedOrExplicitItems()
        assert "OmniPhysicsDeformableBodyAPI" in list(schemas)


def test_the_reconstructed_scene_falls_and_lands_stably(tiny_scene_run, tmp_path):
    from holowarp.sim.scene import load_scene
    from holowarp.simulation import simulate

    out, report = tiny_scene_run
    scene = load_scene(out / "scene.toml")
    scene = replace(scene, sim=replace(scene.sim, duration=0.5))
    rep = simulate(out / "tetmesh.vtu", scene, progress=False)
    assert rep["nan"] is False and rep["max_inverted"] == 0
    assert [b["name"] for b in rep["bodies"]] == [o["name"] for o in report["scene"]["objects"]]
    from holowarp.mesh_io import read_tetmesh

    for b, sp in zip(rep["bodies"], scene.bodies):
        # Each body starts with its lowest point sp.placement.height above the ground; after
        # 0.5 s it rests there: its centre fell by about that height and is still above 0.
        m = read_tetmesh(sp.mesh)
        k = sp.placement.size / float(np.ptp(m.vertices, axis=0).max())
        vol = m.signed_volumes()
        cz = float((m.vertices[m.tets].mean(axis=1)[:, 2] * vol).sum() / vol.sum())
        start = sp.placement.height + k * (cz - float(m.vertices[:, 2].min()))
        assert 0.0 < b["com_end"][2] < start - 0.5 * sp.placement.height, (b, start)


def test_scene_flags_need_scene_level_and_valid_values(tmp_path, capsys):
    from holowarp.reconstruct import build_parser, config_from_args, main

    assert main([str(tmp_path), "--out", str(tmp_path / "o"), "--objects", "2", "--quiet"]) == 2
    assert "--objects: only with --scene-level" in capsys.readouterr().err
    assert main([str(tmp_path), "--out", str(tmp_path / "o"), "--scene-level", "--min-component", "0",
                 "--quiet"]) == 2
    assert "--min-component 0.0: must lie in (0, 1]" in capsys.readouterr().err
    assert main([str(tmp_path), "--out", str(tmp_path / "o"), "--object-size", "0.5", "--quiet"]) == 2
    assert "--object-size: only with --scene-level" in capsys.readouterr().err
    assert main([str(tmp_path), "--out", str(tmp_path / "o"), "--scene-level", "--object-size", "0", "--quiet"]) == 2
    assert "--object-size 0.0: must be a finite number > 0" in capsys.readouterr().err
    cfg = config_from_args(build_parser().parse_args(["d", "--out", "o", "--scene-level", "--object-size", "0.4"]))
    assert cfg.scene.object_size == 0.4 and cfg.topology.kappa_clamp == preset("fast").topology.kappa_clamp
    cfg = config_from_args(build_parser().parse_args(["d", "--out", "o", "--scene-level", "--min-component", "0.1",
                                                      "--objects", "3"]))
    assert (cfg.scene.enabled, cfg.scene.objects, cfg.topology.min_component, cfg.cleanup.min_component) == (
        True, 3, 0.1, 0.1)
    assert preset("fast").topology.min_component is None and preset("fast").cleanup.min_component is None


# ---------------------------------------------------------------------------- slow: spot, bob and a box
THREE = """
[[objects]]
mesh = "{spot}"
name = "spot"
position = [0.0, 0.0, 0.0]
[[objects]]
mesh = "{bob}"
name = "bob"
position = [1.5, 0.0, 0.0]
[[objects]]
box = [1.0, 1.0, 1.0]
name = "box"
position = [0.75, 1.4, 0.0]
color = [0.3, 0.55, 0.8]
"""

#: Genus of each object of THREE.
GENUS = {"spot": 0, "bob": 1, "box": 0}
#: Image side (px) of the single-object runs: the fast preset's.
SINGLE_RES = 128
#: The scene is rendered this many times larger, so each object covers about as many pixels
#: as alone (the scene is ~2.5 objects wide). That holds because the three are the same size
#: (largest side 1, synth's): the resolution is shared, so a smaller object gets fewer pixels
#: than alone, where it fills the frame. Tets need no such factor: a scene run meshes each
#: object at the edge length it has alone (holowarp.stages.tet_init.object_sizing).
SCENE_ZOOM = 2.5


def _one_object(scene_text: str, name: str) -> str:
    """The ``[[objects]]`` entry of ``scene_text`` named ``name``, as a scene of its own."""
    entries = scene_text.split("[[objects]]")[1:]
    return "[[objects]]" + next(e for e in entries if f'name = "{name}"' in e)


@pytest.mark.slow
def test_three_separated_objects_match_their_single_object_reconstructions(tmp_path):
    """Each object of a three-object scene is within 1.3x of its own single-object
    Chamfer-L1 (each measured in that object's evaluation frame) with the right genus."""
    from conftest import shared_mesh

    from holowarp.pipeline import reconstruct
    from holowarp.scene_synth import synthesize_scene

    (tmp_path / "three.toml").write_text(THREE.format(spot=shared_mesh("spot"), bob=shared_mesh("bob")))
    res = int(round(SINGLE_RES * SCENE_ZOOM))
    synthesize_scene(tmp_path / "three.toml", tmp_path / "scene", res=res, progress=False)
    cfg = preset("fast")
    report = reconstruct(tmp_path / "scene", tmp_path / "scene_run", config=replace(cfg, resolution=res).scene_level(),
                         progress=False)
    objects = {o["name"]: o for o in report["scene"]["objects"]}
    assert sorted(objects) == sorted(GENUS)
    for name, genus in GENUS.items():
        o = objects[name]
        assert (o["components"], o["manifold"], o["inverted"], o["genus"]) == (1, True, 0, genus), o
        # The object alone: a one-object scene file renders it exactly as synth would, in its colours.
        alone = tmp_path / f"{name}.toml"
        alone.write_text(_one_object(THREE.format(spot=shared_mesh("spot"), bob=shared_mesh("bob")), name))
        synthesize_scene(alone, tmp_path / f"{name}_data", res=SINGLE_RES, progress=False)
        single = reconstruct(tmp_path / f"{name}_data", tmp_path / f"{name}_run", config=cfg, progress=False)
        assert o["metrics"]["chamfer_l1"] <= 1.3 * single["metrics"]["chamfer_l1"], (name, o["metrics"], single["metrics"])
