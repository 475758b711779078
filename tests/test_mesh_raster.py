"""Triangle rasteriser (method.md §6): analytic coverage, exact normals and depth, gradients
against a dense float64 torch reference, float64 and float32 finite differences."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
import trimesh

from holowarp.camera import intrinsics_from_fov, look_at, project_points
from holowarp.ops import rasterize_mesh
from holowarp.ops.mesh_raster import mesh_face_neighbors
from holowarp.ops.mesh_raster_ref import _edge_neighbors, rasterize_mesh_ref

# One torch thread for the whole module (see conftest.one_torch_thread).
pytestmark = pytest.mark.usefixtures("one_torch_thread")

FOV = math.radians(39.3)


def _camera(res, eye, target=(0.0, 0.0, 0.0), jitter=None):
    K = intrinsics_from_fov(FOV, res, res)
    if jitter is not None:  # move the principal point off the pixel grid
        K[0, 2] += jitter[0]
        K[1, 2] += jitter[1]
    return look_at(eye, target), K


def _bumpy_sphere(rng, subdivisions=1):
    m = trimesh.creation.icosphere(subdivisions=subdivisions, radius=0.5)
    v = m.vertices * (1.0 + 0.15 * rng.uniform(-1.0, 1.0, size=(len(m.vertices), 1)))
    return v, np.array(m.faces, dtype=np.int32)


def _square(center_px, side_px, angle, K, depth=2.0):
    """World square facing an identity camera (viewmat = I), projecting to the given
    pixel square; returns (V, F, pixel corners). Wound to face the camera."""
    c, s = math.cos(angle), math.sin(angle)
    h = side_px / 2
    corners = np.array([[-h, -h], [h, -h], [h, h], [-h, h]]) @ np.array([[c, s], [-s, c]]) + center_px
    f = K[0, 0]
    V = np.c_[(corners[:, 0] - K[0, 2]) * depth / f, (corners[:, 1] - K[1, 2]) * depth / K[1, 1], np.full(4, depth)]
    F = np.array([[0, 1, 2], [0, 2, 3]], dtype=np.int32)
    n = np.cross(V[1] - V[0], V[2] - V[0])
    if n[2] > 0:  # outward normal must point at the camera (-z)
        F = F[:, [0, 2, 1]]
    return V, F, corners


def _dist_to_polygon_boundary(P, corners):
    d = np.full(len(P), np.inf)
    for k in range(len(corners)):
        a, b = corners[k], corners[(k + 1) % len(corners)]
        t = np.clip(((P - a) @ (b - a)) / ((b - a) @ (b - a)), 0, 1)
        d = np.minimum(d, np.linalg.norm(P - (a + t[:, None] * (b - a)), axis=1))
    return d


def _inside_convex(P, corners):
    s = []
    for k in range(len(corners)):
        a, b = corners[k], corners[(k + 1) % len(corners)]
        s.append((b[0] - a[0]) * (P[:, 1] - a[1]) - (b[1] - a[1]) * (P[:, 0] - a[0]))
    s = np.stack(s, 1)
    return (s > 0).all(1) | (s < 0).all(1)


def _pixel_centres(res):
    ys, xs = np.mgrid[0:res, 0:res]
    return np.c_[xs.ravel() + 0.5, ys.ravel() + 0.5]


@pytest.fixture
def scene(rng):
    V, F = _bumpy_sphere(rng)
    eye = rng.normal(size=3)
    eye = 2.6 * eye / np.linalg.norm(eye)
    vm, K = _camera(40, eye, jitter=rng.uniform(-0.5, 0.5, size=2))
    return V, F, vm, K, 40


def test_face_neighbors_match_independent_reference(scene):
    _, F, *_ = scene
    np.testing.assert_array_equal(mesh_face_neighbors(torch.as_tensor(F)).numpy(), np.array(_edge_neighbors(torch.as_tensor(F))))
    open_fan = torch.tensor([[0, 1, 2], [0, 2, 3], [0, 2, 4]], dtype=torch.int32)  # edge 0-2 shared 3 times
    assert (mesh_face_neighbors(open_fan) == -1).all()


def test_outputs_and_gradients_match_dense_float64_reference(scene, rng):
    V, F, vm, K, res = scene
    v32 = torch.tensor(V, dtype=torch.float32, requires_grad=True)
    v64 = torch.tensor(V, dtype=torch.float64, requires_grad=True)
    out = rasterize_mesh(v32, torch.as_tensor(F), vm, K, res, res)
    want = rasterize_mesh_ref(v64, F, vm, K, res, res)
    assert torch.equal(out["face_id"].long(), want["face_id"])
    assert (out["face_id"] >= 0).sum() > 100 and ((out["alpha"] > 0) & (out["alpha"] < 1)).sum() > 20
    torch.testing.assert_close(out["alpha"].double(), want["alpha"], rtol=0, atol=1e-5)
    torch.testing.assert_close(out["normal"].double(), want["normal"], rtol=0, atol=1e-6)
    torch.testing.assert_close(out["depth"].double(), want["depth"], rtol=1e-5, atol=0)
    for key in ("alpha", "normal"):
        w = torch.tensor(rng.normal(size=tuple(out[key].shape)))
        (g32,) = torch.autograd.grad((out[key].double() * w).sum(), v32, retain_graph=True)
        (g64,) = torch.autograd.grad((want[key] * w).sum(), v64, retain_graph=True)
        assert g64.abs().max() > 0
        assert float((g32.double() - g64).norm() / g64.norm()) < 1e-4, key


def test_reference_gradients_match_float64_finite_differences(rng):
    V, F = _bumpy_sphere(rng)
    vm, K = _camera(24, (0.4, -2.5, 0.8), jitter=(0.21, -0.13))
    wa = torch.tensor(rng.normal(size=(24, 24)))
    wn = torch.tensor(rng.normal(size=(24, 24, 3)))

    def loss(v):
        o = rasterize_mesh_ref(v, F, vm, K, 24, 24)
        return (o["alpha"] * wa).sum() + (o["normal"] * wn).sum()

    v = torch.tensor(V, requires_grad=True)
    loss(v).backward()
    # the 10 vertices with the largest gradients and 4 with none (which must stay at 0)
    norms = v.grad.norm(dim=1)
    order = torch.argsort(norms, descending=True)
    zero = torch.nonzero(norms == 0).squeeze(1)
    check = torch.cat([order[:10], zero[torch.randperm(len(zero), generator=torch.Generator().manual_seed(0))[:4]]])
    assert len(zero) >= 4
    fd = torch.zeros_like(v)
    eps = 1e-7
    with torch.no_grad():
        for i in check.tolist():
            for j in range(3):
                vp = v.detach().clone()
                vp[i, j] += eps
                vm_ = v.detach().clone()
                vm_[i, j] -= eps
                fd[i, j] = (loss(vp) - loss(vm_)) / (2 * eps)
    assert fd.abs().max() > 1.0
    assert float((v.grad[check] - fd[check]).abs().max() / fd.abs().max()) < 1e-6


def test_warp_gradients_match_float32_finite_differences(scene, rng):
    """Honest float32 tolerances: alpha is piecewise linear (kinks where a pixel's ramp
    saturates), and ``normal`` jumps wherever a face boundary crosses a pixel centre, so
    coordinates whose step changes the visible face are skipped for the normal check."""
    V, F, vm, K, res = scene
    Ft = torch.as_tensor(F)
    wa = torch.tensor(rng.normal(size=(res, res)))
    wn = torch.tensor(rng.normal(size=(res, res, 3)))
    v = torch.tensor(V, dtype=torch.float32, requires_grad=True)
    out = rasterize_mesh(v, Ft, vm, K, res, res)
    (ga,) = torch.autograd.grad((out["alpha"].double() * wa).sum(), v, retain_graph=True)
    (gn,) = torch.autograd.grad((out["normal"].double() * wn).sum(), v)
    fda, fdn = torch.zeros_like(ga, dtype=torch.float64), torch.zeros_like(gn, dtype=torch.float64)
    keep = torch.ones_like(gn, dtype=torch.bool)
    with torch.no_grad():
        for i in range(V.shape[0]):
            for j in range(3):
                for eps, which in ((1e-4, "alpha"), (1e-3, "normal")):
                    vp = v.detach().clone()
                    vp[i, j] += eps
                    vq = v.detach().clone()
                    vq[i, j] -= eps
                    op = rasterize_mesh(vp, Ft, vm, K, res, res)
                    oq = rasterize_mesh(vq, Ft, vm, K, res, res)
                    if which == "alpha":
                        fda[i, j] = ((op["alpha"].double() - oq["alpha"].double()) * wa).sum() / (2 * eps)
                    else:
                        keep[i, j] = torch.equal(op["face_id"], oq["face_id"])
                        fdn[i, j] = ((op["normal"].double() - oq["normal"].double()) * wn).sum() / (2 * eps)
    assert keep.float().mean() > 0.7
    rel_a = float((ga.double() - fda).abs().max() / fda.abs().max())
    rel_n = float((gn.double() - fdn)[keep].abs().max() / fdn[keep].abs().max())
    assert rel_a < 5e-3 and rel_n < 2e-3, (rel_a, rel_n)


@pytest.mark.parametrize("angle", [0.0, 0.37])
def test_face_on_square_covers_its_area_within_one_pixel_of_its_perimeter(rng, angle):
    res = 64
    K = intrinsics_from_fov(FOV, res, res)
    centre = np.array([31.3, 33.8]) + rng.uniform(-0.5, 0.5, size=2)
    V, F, corners = _square(centre, 30.7, angle, K)
    out = rasterize_mesh(torch.tensor(V, dtype=torch.float32), torch.as_tensor(F), np.eye(4), K, res, res)
    alpha = out["alpha"].numpy().ravel().astype(np.float64)
    P = _pixel_centres(res)
    far = _dist_to_polygon_boundary(P, corners) > 1.0
    inside = _inside_convex(P, corners)
    # away from the perimeter coverage is exactly 1 inside, 0 outside
    np.testing.assert_array_equal(alpha[far], inside[far].astype(np.float64))
    # near it, the box filter integrates to the exact area (corner pixels cost < 1/4 each)
    assert abs(alpha.sum() - 30.7**2) < 1.0
    assert ((alpha > 0) & (alpha < 1)).sum() > 3 * 30


def test_sphere_silhouette_area_matches_pi_r_squared_within_one_percent():
    m = trimesh.creation.icosphere(subdivisions=3, radius=0.5)
    res, D, R = 128, 3.0, 0.5
    vm, K = _camera(res, (0.0, -D, 0.0))
    out = rasterize_mesh(torch.tensor(m.vertices, dtype=torch.float32), torch.as_tensor(m.faces), vm, K, res, res)
    r = K[0, 0] * R / math.sqrt(D * D - R * R)  # exact radius of the projected sphere
    assert out["alpha"].sum().item() == pytest.approx(math.pi * r * r, rel=0.01)
    # watertight: every pixel centre clearly inside the disc is covered, alpha exactly 1
    P = _pixel_centres(res)
    c = K[:2, 2]
    inner = np.linalg.norm(P - c, axis=1) < r - 1.5
    assert (out["alpha"].numpy().ravel()[inner] == 1.0).all()
    assert (out["face_id"].numpy().ravel()[inner] >= 0).all()


def test_alpha_area_matches_the_exact_projected_polygon(rng):
    m = trimesh.creation.icosphere(subdivisions=2, radius=0.5)
    from scipy.spatial import ConvexHull

    for _ in range(3):
        eye = rng.normal(size=3)
        eye = rng.uniform(2.0, 3.5) * eye / np.linalg.norm(eye)
        vm, K = _camera(96, eye, jitter=rng.uniform(-0.5, 0.5, size=2))
        out = rasterize_mesh(torch.tensor(m.vertices, dtype=torch.float32), torch.as_tensor(m.faces), vm, K, 96, 96)
        uv, _ = project_points(m.vertices, vm, K)
        assert abs(out["alpha"].sum().item() - ConvexHull(uv).volume) < 2.0


def test_cube_face_normals_are_exact_and_face_the_camera():
    box = trimesh.creation.box(extents=(0.8, 0.8, 0.8))
    V, F = np.array(box.vertices), np.array(box.faces, dtype=np.int32)
    eye = np.array([1.7, -2.1, 1.3])
    vm, K = _camera(64, eye)
    out = rasterize_mesh(torch.tensor(V, dtype=torch.float32), torch.as_tensor(F), vm, K, 64, 64)
    fid = out["face_id"].numpy().ravel()
    n = out["normal"].numpy().reshape(-1, 3)
    fn = np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]])
    fn /= np.linalg.norm(fn, axis=1, keepdims=True)
    hit = fid >= 0
    np.testing.assert_allclose(n[hit], fn[fid[hit]], atol=1e-6)
    axes = {tuple(np.round(v).astype(int)) for v in n[hit]}
    assert axes == {(1, 0, 0), (0, -1, 0), (0, 0, 1)}  # exactly the three faces seen from eye
    assert (n[~hit] == 0).all()


def test_depth_is_perspective_correct_on_a_slanted_plane():
    res = 48
    K = intrinsics_from_fov(FOV, res, res)
    # plane z = 2 + 0.5 x (camera frame), a big quad covering the view
    xy = np.array([[-2.0, -2.0], [2.0, -2.0], [2.0, 2.0], [-2.0, 2.0]])
    V = np.c_[xy, 2.0 + 0.5 * xy[:, 0]]
    F = np.array([[0, 2, 1], [0, 3, 2]], dtype=np.int32)
    out = rasterize_mesh(torch.tensor(V, dtype=torch.float32), torch.as_tensor(F), np.eye(4), K, res, res)
    P = _pixel_centres(res)
    dx = (P[:, 0] - K[0, 2]) / K[0, 0]  # ray (dx, dy, 1): z = 2 + 0.5 dx z
    z = 2.0 / (1.0 - 0.5 * dx)
    assert (out["face_id"] >= 0).all()
    np.testing.assert_allclose(out["depth"].numpy().ravel(), z, rtol=1e-5)


def test_moving_an_edge_outward_grows_alpha_only_at_that_edge():
    res = 48
    K = intrinsics_from_fov(FOV, res, res)
    V, F, corners = _square(np.array([23.6, 24.2]), 20.0, 0.0, K)
    right = np.flatnonzero(corners[:, 0] > 24)  # two vertices of the right edge
    v = torch.tensor(V, dtype=torch.float32, requires_grad=True)
    out = rasterize_mesh(v, torch.as_tensor(F), np.eye(4), K, res, res)
    out["alpha"].sum().backward()
    px_per_m = K[0, 0] / 2.0  # depth 2
    g = v.grad.numpy() / px_per_m  # d area / d pixel shift
    # shifting the right edge by one pixel adds one edge length of area, all of it there
    assert g[right, 0].sum() == pytest.approx(20.0, rel=1e-3)
    assert (g[right, 0] > 0).all()
    left = np.setdiff1d(np.arange(4), right)
    assert (g[left, 0] < 0).all()  # moving the left edge right (inward) shrinks it
    # finite move: only pixels along the right edge change, and they all grow
    V2 = V.copy()
    V2[right, 0] += 0.3 / px_per_m
    out2 = rasterize_mesh(torch.tensor(V2, dtype=torch.float32), torch.as_tensor(F), np.eye(4), K, res, res)
    d = (out2["alpha"] - out["alpha"].detach()).numpy()
    changed = np.argwhere(np.abs(d) > 1e-6)
    assert len(changed) >= 19 and (d[np.abs(d) > 1e-6] > 0).all()
    x_edge = corners[right, 0].mean()
    assert (np.abs(changed[:, 1] + 0.5 - x_edge) < 1.5).all()
    assert changed[:, 0].min() >= int(corners[:, 1].min()) - 1 and changed[:, 0].max() <= int(corners[:, 1].max()) + 1


def test_moving_one_vertex_outward_grows_alpha_only_along_its_two_edges():
    """Only pixels along the two edges at the vertex change, and they grow. The one
    approximation shows at the edges' fixed ends: distances are measured to the edge's
    line, which rotates slightly inward beyond its fixed endpoint, so a corner pixel there
    may lose a trace of coverage (bounded below at 1% of the largest gain)."""
    res = 48
    K = intrinsics_from_fov(FOV, res, res)
    V, F, corners = _square(np.array([24.3, 23.7]), 22.0, 0.3, K)
    c = corners.mean(0)
    k = 2
    out = rasterize_mesh(torch.tensor(V, dtype=torch.float32), torch.as_tensor(F), np.eye(4), K, res, res)
    V2 = V.copy()
    step_px = 0.4 * (corners[k] - c) / np.linalg.norm(corners[k] - c)  # outward, 0.4 px
    V2[k, :2] += step_px * 2.0 / K[0, 0]
    moved = corners.copy()
    moved[k] += step_px
    out2 = rasterize_mesh(torch.tensor(V2, dtype=torch.float32), torch.as_tensor(F), np.eye(4), K, res, res)
    d = (out2["alpha"] - out["alpha"]).numpy().ravel()
    changed = np.abs(d) > 1e-6
    assert changed.sum() >= 10 and d.sum() > 0
    P_all = _pixel_centres(res)
    shrunk = d < -1e-6
    assert d[shrunk].min(initial=0.0) > -0.01 * d.max()
    fixed_ends = corners[[(k - 1) % 4, (k + 1) % 4]]
    for p in P_all[shrunk]:
        assert np.linalg.norm(fixed_ends - p, axis=1).min() < 1.5
    P = P_all[changed]
    near = np.zeros(len(P), dtype=bool)
    for j in (k - 1, k + 1):  # the two edges at vertex k, before and after the move
        for poly in (corners, moved):
            a, b = poly[j % 4], poly[k]
            t = np.clip(((P - a) @ (b - a)) / ((b - a) @ (b - a)), 0, 1)
            near |= np.linalg.norm(P - (a + t[:, None] * (b - a)), axis=1) < 1.5
    assert near.all()


def test_outputs_do_not_depend_on_tile_size(scene):
    V, F, vm, K, res = scene
    v = torch.tensor(V, dtype=torch.float32)
    base = rasterize_mesh(v, torch.as_tensor(F), vm, K, res, res, tile_size=8)
    for ts in (1, 3, 16, 64):
        o = rasterize_mesh(v, torch.as_tensor(F), vm, K, res, res, tile_size=ts)
        for key in base:
            assert torch.equal(o[key], base[key]), (ts, key)


def test_threaded_row_bands_give_the_single_thread_images_and_gradients(rng):
    """Row bands write disjoint pixels; backward bands sum their own buffers in a fixed order
    whatever the thread count, so both are bit-identical to one thread."""
    from holowarp.device import cpu_threads, set_cpu_threads

    V, F = _bumpy_sphere(rng, subdivisions=3)
    vm, K = _camera(96, (0.4, -2.4, 0.8), jitter=rng.uniform(-0.5, 0.5, size=2))
    w = torch.tensor(rng.normal(size=(96, 96, 3)), dtype=torch.float32)
    before, runs = cpu_threads(), []
    try:
        for threads in (1, 3):
            set_cpu_threads(threads)
            v = torch.tensor(V, dtype=torch.float32, requires_grad=True)
            o = rasterize_mesh(v, torch.as_tensor(F), vm, K, 96, 96)
            ((o["normal"] * w).sum() + o["alpha"].sum()).backward()
            runs.append([o[k].detach() for k in ("alpha", "normal", "depth", "face_id")] + [v.grad])
    finally:
        set_cpu_threads(before)
    assert runs[0][-1].abs().sum() > 0
    for a, b in zip(*runs):
        assert torch.equal(a, b)


def test_back_faces_and_geometry_behind_the_camera_are_not_drawn():
    res = 32
    K = intrinsics_from_fov(FOV, res, res)
    V, F, _ = _square(np.array([16.0, 16.0]), 12.0, 0.0, K)
    vt = torch.tensor(V, dtype=torch.float32)
    assert rasterize_mesh(vt, torch.as_tensor(F), np.eye(4), K, res, res)["alpha"].sum() > 100
    back = rasterize_mesh(vt, torch.as_tensor(F[:, [0, 2, 1]]), np.eye(4), K, res, res)
    assert back["alpha"].sum() == 0 and (back["face_id"] == -1).all() and (back["normal"] == 0).all()
    behind = vt * torch.tensor([1.0, 1.0, -1.0])
    assert rasterize_mesh(behind, torch.as_tensor(F[:, [0, 2, 1]]), np.eye(4), K, res, res)["alpha"].sum() == 0


def test_float64_vertices_get_a_float64_gradient_and_empty_meshes_render_empty(scene):
    V, F, vm, K, res = scene
    v = torch.tensor(V, dtype=torch.float64, requires_grad=True)
    rasterize_mesh(v, torch.as_tensor(F), vm, K, res, res)["alpha"].sum().backward()
    assert v.grad.dtype == torch.float64 and v.grad.abs().max() > 0
    empty = rasterize_mesh(v, torch.zeros((0, 3), dtype=torch.int32), vm, K, res, res)
    assert empty["alpha"].sum() == 0 and (empty["face_id"] == -1).all()


def test_bad_inputs_raise_clear_errors(scene):
    V, F, vm, K, res = scene
    v = torch.tensor(V, dtype=torch.float32)
    Ft = torch.as_tensor(F)
    with pytest.raises(ValueError, match="faces index vertices outside"):
        rasterize_mesh(v, Ft + 1000, vm, K, res, res)
    with pytest.raises(ValueError, match="vertices must be"):
        rasterize_mesh(v[:, :2], Ft, vm, K, res, res)
    with pytest.raises(ValueError, match="viewmat"):
        rasterize_mesh(v, Ft, vm[:3], K, res, res)
    with pytest.raises(ValueError, match="width and height"):
        rasterize_mesh(v, Ft, vm, K, 0, res)
    with pytest.raises(ValueError, match="faces must be"):
        rasterize_mesh(v, Ft.float(), vm, K, res, res)
