"""Pipeline stages in isolation: schedule, field init, pruning, the orientation guarantee and
one geometry block, on a small analytic sphere scene."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
import trimesh

from holowarp.config import FAST_FACTOR, GeometryConfig, TopologyConfig, preset
from holowarp.data import Dataset
from holowarp.primitives import box_tetmesh
from holowarp.stages.geometry import (
    GeometryState,
    mesh_lambda,
    revert_inverting_moves,
    run_geometry_block,
    signed_volumes_t,
)
from holowarp.stages.tet_init import scaled_hull
from holowarp.stages.topology import init_phi, prune, sample_masks
from holowarp.tetgs import TetGaussians
from holowarp.tetmesh import tetrahedralize_surface

RADIUS = 0.35


@pytest.fixture(scope="module")
def sphere_scene():
    """16 views (12 train, 4 test) of a sphere of radius 0.35 at 40x40, rendered with the
    ground-truth renderer, and a coarse tet mesh of its 1.1-scaled convex hull."""
    from holowarp.data.synth import protocol_cameras
    from holowarp.render_gt import GTRenderer

    s = trimesh.creation.icosphere(subdivisions=4, radius=RADIUS)
    res, n = 40, 16
    viewmats, K = protocol_cameras(n, 1.6, res)
    r = GTRenderer(s.vertices, s.faces, supersample=2)
    out = [r.render(vm, K, res, res) for vm in viewmats]
    rgba = np.stack([o["rgba"] for o in out]).astype(np.float32)
    test = np.arange(0, n, 4)
    ds = Dataset(
        images=rgba[..., :3],
        masks=rgba[..., 3],
        K=np.repeat(K[None], n, axis=0),
        viewmats=viewmats,
        train_idx=np.setdiff1d(np.arange(n), test),
        test_idx=test,
        normals=np.stack([o["normal"] for o in out]).astype(np.float32),
        name="sphere",
    )
    V, F = scaled_hull(s.vertices * 1.25)
    mesh = tetrahedralize_surface(V, F, edge_length_fac=0.12)
    return ds, mesh


def test_fast_preset_scales_every_count_by_one_factor_and_keeps_the_order():
    paper, fast = preset("paper"), preset("fast")
    fast.schedule.validate()
    ps, fs = paper.schedule, fast.schedule
    assert fs.main_iters == round(ps.main_iters * FAST_FACTOR)
    assert fs.prune_at == tuple(round(p * FAST_FACTOR) for p in ps.prune_at)
    assert fs.mesh_blocks_at == tuple(round(p * FAST_FACTOR) for p in ps.mesh_blocks_at)
    assert fs.prune_at[0] == fs.topology_until and fs.mesh_blocks_at[0] in fs.prune_at
    assert fast.resolution < paper.resolution
    # Only numbers differ: same fields, same loss weights.
    assert fast.topology == paper.topology
    assert fast.geometry.lr_start == pytest.approx(paper.geometry.lr_start / FAST_FACTOR)
    with pytest.raises(ValueError, match="preset"):
        preset("slow")


def test_mesh_lambda_decays_quadratically_to_zero():
    T = 1000
    assert mesh_lambda(0, T) == 1.0
    assert mesh_lambda(500, T) == pytest.approx(0.25)
    assert mesh_lambda(T, T) == 0.0


def test_revert_keeps_every_tet_above_its_floor_and_leaves_others_alone(rng):
    mesh = box_tetmesh((4, 4, 4))
    tets = torch.tensor(np.array(mesh.tets), dtype=torch.int64)
    x_old = torch.tensor(np.array(mesh.vertices), dtype=torch.float64)
    vol0 = signed_volumes_t(x_old, tets)
    floor = 0.05 * vol0
    x_new = x_old + torch.as_tensor(rng.normal(scale=0.12, size=mesh.vertices.shape))
    moved_before = x_new.clone()
    assert bool((signed_volumes_t(x_new, tets) <= floor).any())  # the step breaks some tets
    n = revert_inverting_moves(x_new, x_old, tets, floor=floor)
    assert n > 0
    assert bool((signed_volumes_t(x_new, tets) > floor).all())
    kept = (x_new == moved_before).all(dim=1)
    reverted = (x_new == x_old).all(dim=1)
    assert bool((kept | reverted).all())  # every vertex either kept its move or went back
    assert int(kept.sum()) > 0


def test_sample_masks_reads_inside_and_outside_of_the_silhouettes(sphere_scene):
    ds, _ = sphere_scene
    pts = np.array([[0.0, 0.0, 0.0], [0.2, -0.1, 0.1], [0.6, 0.0, 0.0], [0.0, 0.0, 5.0]])
    m = sample_masks(pts, ds, ds.train_idx).min(axis=1)
    assert m[0] > 0.99 and m[1] > 0.99
    assert m[2] < 0.01 and m[3] == 0.0


def test_visual_hull_field_is_negative_inside_and_grows_like_a_distance(sphere_scene):
    ds, mesh = sphere_scene
    phi = init_phi(mesh, ds, ds.train_idx, TopologyConfig())
    r = np.linalg.norm(mesh.vertices, axis=1)
    h = np.linalg.norm(mesh.vertices[mesh.edges()[:, 0]] - mesh.vertices[mesh.edges()[:, 1]], axis=1).max()
    assert np.all(phi[r < RADIUS - h] < 0)
    assert np.all(phi[r > RADIUS + h] > 0)
    # A graph distance overestimates the Euclidean one by at most a path's detours.
    far = r > RADIUS + 2 * h
    assert np.all(phi[far] >= (r[far] - RADIUS) - h)
    assert np.all(phi[far] <= 2.0 * (r[far] - RADIUS) + h)
    assert np.array_equal(init_phi(mesh, ds, ds.train_idx, TopologyConfig(phi_init="inside")), np.full(mesh.num_vertices, -0.3))


def test_prune_removes_low_alpha_tets_and_keeps_the_largest_piece():
    a = box_tetmesh((3, 3, 3))
    model = TetGaussians(a, continuous_opacity=False)
    alpha = np.full(model.num_tets, 0.9)
    centres = a.vertices[a.tets].mean(axis=1)
    # Carve a slab through the middle, leaving two pieces of different sizes.
    slab = (centres[:, 0] > 1 / 3) & (centres[:, 0] < 2 / 3)
    small = centres[:, 0] < 1 / 3
    alpha[slab] = 0.01
    with torch.no_grad():
        model.opacity_logit.data = torch.logit(torch.as_tensor(alpha, dtype=torch.float32))
    info = prune(model, TopologyConfig())
    assert info["pruned"] == int(slab.sum())
    assert info["removed_components"] == 1 and info["tets_removed_by_component"] == int(small.sum())
    assert model.num_tets == a.num_tets - slab.sum() - small.sum()
    assert model.mesh().num_components() == 1
    with torch.no_grad():
        model.opacity_logit.data[:] = -10.0
    emptied = prune(model, TopologyConfig())
    assert emptied["emptied"] and model.num_tets == info["tets_after"]


def test_geometry_block_fits_silhouettes_without_inverting_tets(sphere_scene):
    ds, mesh = sphere_scene
    # Start as the pipeline does after a prune: the hull's tets carved by the visual-hull
    # field, a staircase around the sphere that the block must fit to the silhouettes.
    phi = init_phi(mesh, ds, ds.train_idx, TopologyConfig())
    carved, _ = mesh.submesh(phi[mesh.tets].mean(axis=1) < 0).keep_largest_component()
    model = TetGaussians(carved, continuous_opacity=False)
    before = _mask_error(model, ds)
    ball = 4 / 3 * math.pi * RADIUS**3
    cfg = GeometryConfig(lr_start=4e-3, lr_end=2e-3)
    state = GeometryState()
    summary = run_geometry_block(
        model, ds, ds.train_idx, cfg, block_iters=60, total_mesh_iters=60, state=state, seed=3
    )
    after = _mask_error(model, ds)
    assert after < 0.5 * before
    assert summary["inverted"] == 0 and state.mesh_iter == 60
    assert bool((signed_volumes_t(model.vertices.detach(), model.tets) > 0).all())
    # 12 views of 40x40 pin the sphere to within about a pixel (~3% of its radius).
    assert model.mesh().volume() == pytest.approx(ball, rel=0.2)


def _mask_error(model, ds) -> float:
    from holowarp.ops import rasterize_mesh

    faces = torch.tensor(np.array(model.mesh().boundary_faces()), dtype=torch.int32)
    err = 0.0
    with torch.no_grad():
        for v in ds.train_idx:
            out = rasterize_mesh(model.vertices.detach(), faces, ds.viewmats[v], ds.K[v], ds.width, ds.height)
            err += float((out["alpha"] - torch.as_tensor(ds.masks[v])).abs().mean())
    return err / len(ds.train_idx)


def test_prune_never_opens_sealed_cavities_nor_leaves_a_non_manifold_boundary(rng):
    mesh = box_tetmesh((6, 6, 6))
    model = TetGaussians(mesh, continuous_opacity=False)
    centres = mesh.vertices[mesh.tets].mean(axis=1)
    # Random low-alpha tets everywhere (pinches galore) plus one sealed central pocket.
    low = rng.random(mesh.num_tets) < 0.2
    pocket = np.linalg.norm(centres - 0.5, axis=1) < 0.12
    low |= pocket
    with torch.no_grad():
        model.opacity_logit.data = torch.logit(torch.as_tensor(np.where(low, 0.02, 0.9), dtype=torch.float32))
    info = prune(model, TopologyConfig())
    out = model.mesh()
    assert out.manifold()["manifold"] and out.num_components() == 1
    assert info["pruned"] > 0 and info["kept_cavity"] >= int(pocket.sum())
    assert out.boundary_shells() == 1  # no internal void surface
    assert info["low_alpha"] == int(low.sum())
    assert info["pruned"] + info["kept_cavity"] + info["kept_dents"] + info["restored_for_manifold"] == info["low_alpha"]
