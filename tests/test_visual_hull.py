"""Visual-hull baseline: the carving kernel against a NumPy/SciPy reference, the hull of a
sphere end to end through the command, and clear errors when masks and cameras disagree."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from holowarp.baselines.hull import VisualHullError, VisualHullSettings, visual_hull
from holowarp.carve import hull_genus, hull_grid, solid_genus
from holowarp.camera import intrinsics_from_fov, look_at
from holowarp.data import Dataset


def _carve_ref(masks, viewmats, Ks, origin, spacing, shape, outside_is_empty):
    from scipy.ndimage import map_coordinates

    ii, jj, kk = np.meshgrid(*[np.arange(n) for n in shape], indexing="ij")
    p = origin + np.stack([ii, jj, kk], -1).reshape(-1, 3) * spacing
    val = np.ones(len(p))
    h, w = masks.shape[1:]
    for m, V, K in zip(masks, viewmats, Ks):
        pc = p @ V[:3, :3].T + V[:3, 3]
        z = pc[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            x = K[0, 0] * pc[:, 0] / z + K[0, 1] * pc[:, 1] / z + K[0, 2]
            y = K[1, 1] * pc[:, 1] / z + K[1, 2]
        behind = z <= 1e-6
        outside = (x < 0) | (y < 0) | (x > w) | (y > h)
        s = map_coordinates(m.astype(np.float64), [np.nan_to_num(y) - 0.5, np.nan_to_num(x) - 0.5], order=1, mode="nearest")
        v = np.where(outside, 0.0 if outside_is_empty else 1.0, s)
        val = np.where(behind, 0.0, np.minimum(val, v))
    return val.reshape(shape)


def _cameras(rng, n, res):
    K = intrinsics_from_fov(math.radians(39.3), res, res)
    vm = []
    for _ in range(n):
        d = rng.normal(size=3)
        d /= np.linalg.norm(d)
        vm.append(look_at(d * rng.uniform(1.5, 2.5), rng.uniform(-0.1, 0.1, 3), rng.normal(size=3)))
    return np.stack(vm), np.broadcast_to(K, (n, 3, 3)).copy()


@pytest.mark.parametrize("outside_is_empty", [True, False])
def test_hull_grid_is_the_min_over_views_of_bilinear_masks(rng, outside_is_empty):
    n, res = 4, 20
    vm, K = _cameras(rng, n, res)
    K[:, 0, 1] = rng.uniform(-1, 1, n)  # skew exercised too
    masks = rng.random((n, res, res)).astype(np.float32)
    ds = Dataset(images=np.zeros((n, res, res, 3), np.float32), masks=masks, K=K, viewmats=vm, train_idx=np.arange(n), test_idx=[])
    origin, spacing, shape = np.array([-1.2, -1.0, -0.9]), 0.21, (11, 10, 9)
    got = hull_grid(ds, np.arange(n), origin, spacing, shape, outside_is_empty=outside_is_empty)
    ref = _carve_ref(masks, vm, K, origin, spacing, shape, outside_is_empty)
    assert (got > 0).any() and np.ptp(got) > 0.1  # a non-trivial field
    np.testing.assert_allclose(got, ref, atol=1e-5)


def _grid(n):
    ax = (np.arange(n) + 0.5) / n * 2 - 1
    return np.meshgrid(ax, ax, ax, indexing="ij")


def test_solid_genus_counts_handles_of_voxel_shapes(rng):
    n = 40
    x, y, z = _grid(n)
    R, r = rng.uniform(0.45, 0.6), rng.uniform(0.15, 0.25)
    torus = (np.hypot(x, y) - R) ** 2 + z**2 < r**2
    assert solid_genus(torus) == 1
    assert solid_genus(x**2 + y**2 + z**2 < rng.uniform(0.3, 0.8) ** 2) == 0
    # A slab with k square holes through it, k drawn afresh; a void inside a ball is filled.
    k = int(rng.integers(1, 5))
    slab = (np.abs(z) < 0.2) & (np.abs(x) < 0.95) & (np.abs(y) < 0.5)
    for i in range(k):
        cx = -0.95 + (2 * i + 1) * 1.9 / (2 * k)
        slab &= ~((np.abs(x - cx) < 0.6 / k) & (np.abs(y) < 0.3))
    assert solid_genus(slab) == k
    hollow = (x**2 + y**2 + z**2 < 0.8**2) & ~(x**2 + y**2 + z**2 < 0.4**2)
    assert solid_genus(hollow) == 0
    # Only the largest piece counts: a ball beside a smaller torus.
    small = (np.hypot(x + 0.6, y) - 0.25) ** 2 + z**2 < 0.1**2
    assert solid_genus(small | ((x - 0.45) ** 2 + y**2 + z**2 < 0.5**2)) == 0
    assert solid_genus(np.zeros((4, 4, 4), bool)) == 0


def _torus_masks(vm, K, res, R, r):
    """Exact silhouettes of the solid torus (axis z): a pixel is inside when its ray passes
    within r of the circle of radius R (sampled densely along the ray)."""
    masks = np.zeros((len(vm), res, res), np.float32)
    t = np.linspace(0.5, 5.0, 900)
    u, v = np.meshgrid(np.arange(res) + 0.5, np.arange(res) + 0.5)
    for i, (V, Km) in enumerate(zip(vm, K)):
        d = np.stack([(u - Km[0, 2]) / Km[0, 0], (v - Km[1, 2]) / Km[1, 1], np.ones_like(u)], -1) @ V[:3, :3]
        o = -V[:3, :3].T @ V[:3, 3]
        p = o + d[..., None, :] * t[:, None]
        q = (np.hypot(p[..., 0], p[..., 1]) - R) ** 2 + p[..., 2] ** 2
        masks[i] = (q.min(-1) < r**2).astype(np.float32)
    return masks


def test_hull_genus_sees_the_tunnel_the_views_see_through(rng):
    n, res = 14, 40
    K = np.broadcast_to(intrinsics_from_fov(math.radians(39.3), res, res), (n, 3, 3)).copy()
    # Twelve views from around the side (none sees through the hole) and two from above.
    az = rng.uniform(0, 2 * np.pi) + np.arange(12) * 2 * np.pi / 12
    el = rng.uniform(-0.15, 0.15, 12)
    eyes = [2.2 * np.array([np.cos(a) * np.cos(e), np.sin(a) * np.cos(e), np.sin(e)]) for a, e in zip(az, el)]
    vm = np.stack([look_at(p) for p in eyes] + [look_at((0.2, 0.1, 2.2), up=(0.0, 1.0, 0.0)),
                                                look_at((-0.1, 0.3, -2.2), up=(1.0, 0.0, 0.0))])
    R, r = rng.uniform(0.45, 0.55), rng.uniform(0.12, 0.17)
    ds = Dataset(images=np.zeros((n, res, res, 3), np.float32), masks=_torus_masks(vm, K, res, R, r), K=K, viewmats=vm,
                 train_idx=np.arange(n), test_idx=[])
    box = (-(R + r) * np.ones(3), (R + r) * np.ones(3))
    assert hull_genus(ds, *box, cells=48) == 1
    # From the side alone no silhouette shows the hole: the hull is a disc.
    assert hull_genus(ds, *box, views=np.arange(12), cells=48) == 0


def test_sphere_hull_command_writes_one_manifold_tet_mesh(tmp_path):
    import trimesh

    from holowarp import read_tetmesh
    from holowarp.baselines.visual_hull import main
    from holowarp.surface_io import write_surface
    from holowarp.synthesis import synthesize

    s = trimesh.creation.icosphere(subdivisions=3, radius=1.0)
    write_surface(tmp_path / "ball.obj", (s.vertices, s.faces))
    synthesize(tmp_path / "ball.obj", tmp_path / "ds", views=24, res=48, up_axis="z", progress=False)
    rc = main([str(tmp_path / "ds"), "--out", str(tmp_path / "vh"), "--grid", "40", "--edge-length-fac", "0.1", "--max-surface-faces", "1500", "--quiet"])
    assert rc == 0
    mesh = read_tetmesh(tmp_path / "vh" / "tetmesh.vtu")
    assert (tmp_path / "vh" / "surface.obj").is_file()
    rep = json.loads((tmp_path / "vh" / "report.json").read_text())
    assert rep["carving_views"] == 24 - 3  # test views 0, 10, 20 are held out
    assert mesh.num_components() == 1 and mesh.manifold()["manifold"] and mesh.genus() == 0
    assert (mesh.signed_volumes() > 0).all()
    # The hull contains the (normalised, radius 0.5) ball and hugs it with enough views.
    ball = 4 / 3 * math.pi * 0.5**3
    assert ball * 0.98 < mesh.volume() < ball * 1.25
    V, _ = mesh.surface_mesh()
    r = np.linalg.norm(V, axis=1)
    assert r.min() > 0.47 and r.max() < 0.62


def test_hull_of_inconsistent_masks_is_a_clear_error(rng):
    n, res = 6, 16
    vm, K = _cameras(rng, n, res)
    masks = np.zeros((n, res, res), np.float32)
    for i in range(n):  # a small blob in a different corner of every view: no common volume
        y, x = (i % 2) * 12, (i // 2) * 6
        masks[i, y : y + 3, x : x + 3] = 1
    ds = Dataset(images=np.zeros((n, res, res, 3), np.float32), masks=masks, K=K, viewmats=vm, train_idx=np.arange(n), test_idx=[])
    with pytest.raises(VisualHullError, match="masks and cameras disagree|hull is empty"):
        visual_hull(ds, settings=VisualHullSettings(grid=16, coarse_grid=16))


@pytest.mark.slow
def test_torus_hull_keeps_genus_one(tmp_path):
    import trimesh

    from holowarp.surface_io import write_surface
    from holowarp.synthesis import synthesize

    t = trimesh.creation.torus(major_radius=1.0, minor_radius=0.35)
    write_surface(tmp_path / "torus.obj", (t.vertices, t.faces))
    synthesize(tmp_path / "torus.obj", tmp_path / "ds", views=60, res=64, up_axis="z", progress=False)
    mesh = visual_hull(tmp_path / "ds", settings=VisualHullSettings(grid=64, edge_length_fac=0.05, max_surface_faces=4000))
    assert mesh.num_components() == 1 and mesh.manifold()["manifold"] and mesh.genus() == 1
