"""Oracle tests of the Warp surfel rasteriser (kernels/surfels.py, holowarp.ops.surfels).

The oracle is the dense float64 torch reference (holowarp.ops.surfels_ref): every surfel at
every pixel, the same rules, torch autograd. Values must agree to 1e-5 and gradients to 1e-3,
both measured as max |warp - ref| / max |ref| per output tensor: the kernels run in float32
and many entries are near zero (uncovered pixels, surfels that barely contribute), where an
entry-wise relative error would only measure float32 noise. Analytic checks cover the
compositing rules themselves (opacity cap, transmittance stop, background weight, plane depth
and normal).
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from holowarp.camera import intrinsics_from_fov, look_at
from holowarp.kernels.surfels import ALPHA_MAX, T_MIN
from holowarp.ops import rasterize_surfels
from holowarp.ops.surfels_ref import rasterize_surfels_ref

OUTPUTS = ("rgb", "alpha", "normal", "depth", "median_depth", "distortion")
VALUE_TOL = 1e-5
GRAD_TOL = 1e-3


def random_scene(rng, n, width, height):
    """Surfels scattered in a unit box seen by a perspective camera: mixed sizes (tiny ones
    exercise the screen-space low-pass branch), random orientations (some nearly edge-on)."""
    means = rng.uniform(-0.5, 0.5, (n, 3))
    scales = np.exp(rng.uniform(np.log(0.004), np.log(0.15), (n, 2)))
    opac = rng.uniform(0.02, 0.999, n)
    colors = rng.uniform(0.0, 1.0, (n, 3))
    eye = rng.normal(size=3)
    eye = 2.4 * eye / np.linalg.norm(eye)
    viewmat = look_at(eye)
    quats = rng.normal(size=(n, 4))
    K = intrinsics_from_fov(math.radians(40.0), width, height)
    K[0, 2] += rng.uniform(-2, 2)  # off-centre principal point
    background = rng.uniform(0.0, 1.0, 3)
    return [torch.tensor(a) for a in (means, quats, scales, opac, colors, viewmat, K, background)]


#: Pixels where a float64 decision of the reference (alpha skip, transmittance stop, median
#: choice, branch) lies within this relative distance of its threshold are not compared: there
#: a float32 implementation may rightly decide the other way, a jump no tolerance covers.
DECISION_MARGIN = 1e-4


def render_both(scene, width, height, cotangents=None):
    """Render with the reference (float64 leaves) and the kernels (float32 leaves).

    Both get the same input values (rounded to float32 once): edge-on surfels are sensitive
    enough to their orientation that the rounding of the *inputs* alone would move alpha by
    more than 1e-5. Returns ``(warp, ref, ambiguous)``, each result ``(outputs, grads)``;
    ``ambiguous`` [H, W] marks pixels within DECISION_MARGIN of a discontinuity, whose
    cotangents are zeroed so they do not enter the gradient comparison either.
    """
    scene = [t.float().double() for t in scene]
    means, quats, scales, opac, colors, viewmat, K, bg = scene
    runs = []
    for fn, dtype in ((rasterize_surfels_ref, torch.float64), (rasterize_surfels, torch.float32)):
        leaves = [t.clone().to(dtype).requires_grad_(True) for t in (means, quats, scales, opac, colors, bg)]
        runs.append((leaves, fn(*leaves[:5], viewmat, K, width, height, leaves[5])))
    ambiguous = runs[0][1]["decision_margin"] < DECISION_MARGIN
    keep = (~ambiguous).double()
    results = []
    for leaves, out in (runs[1], runs[0]):
        grads = None
        if cotangents is not None:
            loss = 0.0
            for k in OUTPUTS:
                cot = cotangents[k] * (keep[..., None] if cotangents[k].ndim == 3 else keep)
                loss = loss + (out[k].double() * cot).sum()
            loss.backward()
            grads = [t.grad for t in leaves] + [out["means2d"].grad]
        results.append((out, grads))
    return results[0], results[1], ambiguous


def max_rel_err(a, b, skip=None):
    """max |a - b| / max |b|, ignoring pixels where ``skip`` [H, W] is set."""
    a, b = a.detach().double(), b.detach().double()
    diff = (a - b).abs()
    if skip is not None:
        diff = diff * ~skip.reshape(skip.shape + (1,) * (diff.ndim - 2))
    return float(diff.max() / b.abs().max().clamp_min(1e-12))


@pytest.mark.parametrize("n,width,height", [(200, 32, 32), (400, 64, 48)])
def test_forward_matches_dense_float64_reference(rng, n, width, height):
    scene = random_scene(rng, n, width, height)
    (ow, _), (orf, _), ambiguous = render_both(scene, width, height)
    assert float(orf["alpha"].detach().max()) > 0.5  # the scene is actually visible
    assert float(ambiguous.double().mean()) < 0.01
    for k in OUTPUTS:
        assert ow[k].dtype == torch.float32
        assert ow[k].shape == orf[k].shape, k
        err = max_rel_err(ow[k], orf[k], ambiguous)
        assert err < VALUE_TOL, f"{k}: max rel err {err:.2e}"
    assert max_rel_err(ow["means2d"], orf["means2d"]) < VALUE_TOL


@pytest.mark.parametrize("n,width,height", [(200, 32, 32), (400, 64, 48)])
def test_gradients_match_dense_float64_reference(rng, n, width, height):
    scene = random_scene(rng, n, width, height)
    cot = {k: torch.tensor(rng.normal(size=(height, width, 3) if k in ("rgb", "normal") else (height, width)))
           for k in OUTPUTS}  # fmt: skip
    (_, gw), (_, gr), ambiguous = render_both(scene, width, height, cot)
    assert float(ambiguous.double().mean()) < 0.01
    names = ("means", "quats", "scales", "opacities", "colors", "background", "means2d")
    for name, a, b in zip(names, gw, gr):
        assert a is not None and b is not None, name
        assert float(b.abs().max()) > 0, name
        err = max_rel_err(a, b)
        assert err < GRAD_TOL, f"d/d{name}: max rel err {err:.2e}"


def facing_camera_scene(n=1, depth=2.0, width=32, height=32):
    """Surfels at (0, 0, depth) in camera space of an identity camera, normal along -z."""
    viewmat = torch.eye(4, dtype=torch.float64)
    K = torch.tensor(intrinsics_from_fov(math.radians(50.0), width, height))
    means = torch.tensor([[0.0, 0.0, depth]] * n, dtype=torch.float64)
    quats = torch.tensor([[1.0, 0.0, 0.0, 0.0]] * n, dtype=torch.float64)
    scales = torch.full((n, 2), 0.1, dtype=torch.float64)
    return means, quats, scales, viewmat, K


@pytest.mark.parametrize("opacity", [0.6, 0.999])
def test_single_surfel_peak_equals_opacity_capped_at_099(opacity):
    means, quats, scales, viewmat, K = facing_camera_scene()
    # Centre the surfel exactly on pixel (16, 16)'s centre (16.5, 16.5): the principal point
    # is at 16.0, so shift it by half a pixel.
    K[0, 2] += 0.5
    K[1, 2] += 0.5
    out = rasterize_surfels(means, quats, scales, torch.tensor([opacity]), torch.ones(1, 3), viewmat, K, 32, 32)
    peak = float(out["alpha"].max())
    assert peak == pytest.approx(min(opacity, ALPHA_MAX), abs=1e-6)
    assert float(out["alpha"][16, 16]) == pytest.approx(peak, abs=1e-7)


def test_transmittance_stop_skips_the_surfel_that_would_cross_threshold():
    # Six opaque-ish surfels on the optical axis, front to back, alpha 0.95 each at the centre
    # pixel: T after three is 0.05^3 = 1.25e-4 >= T_MIN, after four 6.25e-6 < T_MIN, so the
    # fourth is skipped and compositing stops there.
    n = 6
    means, quats, scales, viewmat, K = facing_camera_scene(n)
    K[0, 2] += 0.5
    K[1, 2] += 0.5
    means[:, 2] = torch.arange(n, dtype=torch.float64) * 0.1 + 2.0
    colors = torch.eye(3, dtype=torch.float64).repeat(2, 1)  # r, g, b, r, g, b
    colors[3:] *= 0.5
    out = rasterize_surfels(means, quats, scales, torch.full((n,), 0.95), colors, viewmat, K, 32, 32,
                            torch.tensor([0.3, 0.3, 0.3]))  # fmt: skip
    a = 0.95
    weights = [a, a * (1 - a), a * (1 - a) ** 2]
    T_final = (1 - a) ** 3
    assert T_final >= T_MIN > T_final * (1 - a)
    expected = torch.tensor(weights) + 0.3 * T_final
    rgb = out["rgb"][16, 16].double()
    assert torch.allclose(rgb, expected.double(), rtol=1e-5, atol=1e-7), (rgb, expected)
    assert float(out["alpha"][16, 16]) == pytest.approx(1 - T_final, abs=1e-6)
    z = 2.0 * weights[0] + 2.1 * weights[1] + 2.2 * weights[2]
    assert float(out["depth"][16, 16]) == pytest.approx(z, rel=1e-5)
    # The median contributor is the first surfel (T drops from 1 to 0.05 across it).
    assert float(out["median_depth"][16, 16]) == pytest.approx(2.0, rel=1e-6)


def test_background_weight_equals_final_transmittance(rng):
    width = height = 32
    means, quats, scales, opac, colors, viewmat, K, _ = random_scene(rng, 150, width, height)
    bg = torch.tensor(rng.uniform(0.2, 1.0, 3), dtype=torch.float32, requires_grad=True)
    out_black = rasterize_surfels(means, quats, scales, opac, colors, viewmat, K, width, height)
    out_bg = rasterize_surfels(means, quats, scales, opac, colors, viewmat, K, width, height, bg)
    T_final = 1.0 - out_bg["alpha"]
    T_final = T_final.detach()
    assert float(T_final.min()) < 0.1 and float(T_final.max()) == pytest.approx(1.0)
    diff = out_bg["rgb"] - out_black["rgb"]
    assert torch.allclose(diff, T_final[..., None] * bg.detach(), atol=2e-6)
    cot = torch.tensor(rng.normal(size=(height, width, 3)), dtype=torch.float32)
    (out_bg["rgb"] * cot).sum().backward()
    expected = (cot * T_final.detach()[..., None]).sum((0, 1))
    assert torch.allclose(bg.grad, expected, rtol=1e-4, atol=1e-4)


def plane_of_surfels(normal_cam, point_cam, spacing=0.05, extent=0.6, flip_half=True):
    """A dense grid of surfels lying in one plane (camera space = world space here)."""
    n = np.asarray(normal_cam, float)
    n /= np.linalg.norm(n)
    t1 = np.cross(n, [0.0, 1.0, 0.0])
    t1 /= np.linalg.norm(t1)
    t2 = np.cross(n, t1)
    g = np.arange(-extent, extent + 1e-9, spacing)
    a, b = np.meshgrid(g, g)
    pts = np.asarray(point_cam) + a.reshape(-1, 1) * t1 + b.reshape(-1, 1) * t2
    # Rotation with columns (t1, t2, n) as a wxyz quaternion; half of the surfels get the
    # opposite normal (columns t1, -t2, -n: same plane), which the rasteriser must flip back
    # to face the camera.
    from scipy.spatial.transform import Rotation

    def wxyz(R):
        x, y, z, w = Rotation.from_matrix(R).as_quat()
        return np.array([w, x, y, z])

    quats = np.tile(wxyz(np.stack([t1, t2, n], axis=1)), (len(pts), 1))
    if flip_half:
        quats[::2] = wxyz(np.stack([t1, -t2, -n], axis=1))
    return pts, quats


@pytest.mark.parametrize("tilt_deg", [0.0, 35.0])
def test_plane_of_surfels_gives_analytic_depth_and_normal(tilt_deg):
    width = height = 48
    t = math.radians(tilt_deg)
    normal = np.array([0.0, math.sin(t), -math.cos(t)])  # facing the camera (towards -z)
    point = np.array([0.0, 0.0, 2.0])
    pts, quats = plane_of_surfels(normal, point)
    n = len(pts)
    viewmat = torch.eye(4, dtype=torch.float64)
    K = torch.tensor(intrinsics_from_fov(math.radians(30.0), width, height))
    out = rasterize_surfels(
        torch.tensor(pts), torch.tensor(quats), torch.full((n, 2), 0.04, dtype=torch.float64),
        torch.full((n,), 0.9), torch.rand(n, 3), viewmat, K, width, height,
    )  # fmt: skip
    alpha = out["alpha"].double()
    inner = alpha > 0.99
    assert int(inner.sum()) > 0.5 * width * height  # the plane fills the middle of the view
    # Analytic depth of the plane along each pixel's ray: z = (n . p0) / (n . d), d = K^-1 (x, y, 1).
    ys, xs = torch.meshgrid(torch.arange(height) + 0.5, torch.arange(width) + 0.5, indexing="ij")
    d = torch.stack([(xs - K[0, 2]) / K[0, 0], (ys - K[1, 2]) / K[1, 1], torch.ones_like(xs)], -1).double()
    nz = torch.tensor(normal)
    z_plane = (nz @ torch.tensor(point)) / (d @ nz)
    depth = out["depth"].double() / alpha.clamp_min(1e-9)
    assert torch.allclose(depth[inner], z_plane[inner], rtol=2e-5)
    assert torch.allclose(out["median_depth"].double()[inner], z_plane[inner], rtol=2e-5)
    nrm = out["normal"].double() / alpha.clamp_min(1e-9)[..., None]
    assert torch.allclose(nrm[inner], nz.expand_as(nrm[inner]), atol=2e-5)
    # One surface, one depth: no distortion (up to float32 rounding of z^2 terms).
    assert float(out["distortion"][inner].abs().max()) < 1e-5 * 2.0**2


def test_culled_surfels_render_only_background_and_get_zero_gradients():
    means, quats, scales, viewmat, K = facing_camera_scene(3)
    means[0, 2] = -1.0  # behind the camera
    means[1, 2] = 0.005  # in front of the near plane
    opac = torch.tensor([0.9, 0.9, 0.5 / 255.0], requires_grad=True)  # third never reaches 1/255
    bg = torch.tensor([0.1, 0.2, 0.3])
    colors = torch.rand(3, 3, requires_grad=True)
    out = rasterize_surfels(means, quats, scales, opac, colors, viewmat, K, 32, 32, bg)
    assert torch.allclose(out["rgb"], bg.expand(32, 32, 3))
    assert float(out["alpha"].detach().abs().max()) == 0.0
    assert not bool(out["visible"].any())
    (out["rgb"].sum() + out["alpha"].sum()).backward()
    assert float(opac.grad.abs().max()) == 0.0 and float(colors.grad.abs().max()) == 0.0


def test_float64_inputs_get_float64_gradients_and_zero_surfels_work():
    means, quats, scales, viewmat, K = facing_camera_scene(2)
    means = means.clone().requires_grad_(True)
    out = rasterize_surfels(means, quats, scales, torch.full((2,), 0.5, dtype=torch.float64),
                            torch.rand(2, 3, dtype=torch.float64), viewmat, K, 20, 12)  # fmt: skip
    assert out["rgb"].shape == (12, 20, 3) and out["means2d"].shape == (2, 2)
    out["alpha"].sum().backward()
    assert means.grad.dtype == torch.float64 and float(means.grad.abs().max()) > 0
    empty = rasterize_surfels(torch.zeros(0, 3), torch.zeros(0, 4), torch.zeros(0, 2), torch.zeros(0),
                              torch.zeros(0, 3), viewmat, K, 20, 12, torch.tensor([1.0, 0.5, 0.0]))  # fmt: skip
    assert torch.allclose(empty["rgb"], torch.tensor([1.0, 0.5, 0.0]).expand(12, 20, 3))


@pytest.mark.parametrize(
    "change,match",
    [
        (dict(means=torch.zeros(4, 2)), "means must have shape"),
        (dict(quats=torch.zeros(4, 3)), "quats must have shape"),
        (dict(scales=torch.zeros(3, 2)), "scales must have shape"),
        (dict(opacities=torch.zeros(4, 1)), "opacities must have shape"),
        (dict(colors=torch.zeros(4, 4)), "colors must have shape"),
        (dict(viewmat=torch.eye(3)), "viewmat must have shape"),
        (dict(K=torch.eye(3) * 2), "K must be a pinhole matrix"),
        (dict(width=0), "width and height must be positive"),
        (dict(background=torch.zeros(4)), "background must be a tensor of shape"),
    ],
)
def test_bad_inputs_raise_errors_naming_the_argument(change, match):
    args = dict(
        means=torch.zeros(4, 3), quats=torch.ones(4, 4), scales=torch.ones(4, 2), opacities=torch.ones(4) * 0.5,
        colors=torch.zeros(4, 3), viewmat=torch.eye(4), K=torch.eye(3), width=8, height=8, background=None,
    )  # fmt: skip
    args.update(change)
    with pytest.raises(ValueError, match=match):
        rasterize_surfels(**args)


def test_more_surfels_than_a_list_entry_can_rank_are_refused(monkeypatch):
    # A list entry packs the depth rank into 23 bits; the limit is lowered here so that the
    # check can be seen without allocating 2^23 surfels.
    import holowarp.ops.surfels as S

    monkeypatch.setattr(S.K_, "MAX_SURFELS", 3)
    with pytest.raises(ValueError, match="at most 3 surfels per call"):
        rasterize_surfels(torch.zeros(4, 3), torch.ones(4, 4), torch.ones(4, 2), torch.ones(4) * 0.5,
                          torch.zeros(4, 3), torch.eye(4), torch.eye(3), 8, 8)  # fmt: skip


def test_reference_in_checkpointed_pixel_chunks_matches_the_single_pass(rng):
    # The benchmark runs the reference in chunks to bound memory; chunking must not change it.
    width, height = 24, 20
    scene = random_scene(rng, 100, width, height)
    results = []
    for chunk in (None, 50):
        leaves = [t.clone().requires_grad_(True) for t in scene[:5]]
        out = rasterize_surfels_ref(*leaves, scene[5], scene[6], width, height, scene[7], pixel_chunk=chunk)
        (out["rgb"].sum() + out["depth"].sum() + out["distortion"].sum() + out["median_depth"].sum()).backward()
        results.append(([out[k].detach() for k in OUTPUTS], [t.grad for t in leaves] + [out["means2d"].grad]))
    (v0, g0), (v1, g1) = results
    for a, b in zip(v0 + g0, v1 + g1):
        assert torch.allclose(a, b, rtol=1e-12, atol=1e-12)


def test_threaded_launches_give_the_single_thread_images_and_gradients(rng):
    """The forward slices write disjoint pixels; the backward pieces sum per-piece gradient
    buffers in a fixed order whatever the thread count: both are bit-identical."""
    from holowarp.device import cpu_threads, set_cpu_threads

    n, res = 600, 64
    means = torch.tensor(rng.normal(scale=0.3, size=(n, 3)), dtype=torch.float32, requires_grad=True)
    q = torch.tensor(rng.normal(size=(n, 4)), dtype=torch.float32, requires_grad=True)
    s = torch.tensor(rng.uniform(0.02, 0.1, (n, 2)), dtype=torch.float32, requires_grad=True)
    o = torch.tensor(rng.uniform(0.2, 0.95, n), dtype=torch.float32, requires_grad=True)
    c = torch.tensor(rng.uniform(0, 1, (n, 3)), dtype=torch.float32, requires_grad=True)
    V = torch.tensor(look_at((0.3, -2.2, 0.9)), dtype=torch.float32)
    K = torch.tensor(intrinsics_from_fov(0.8, res, res), dtype=torch.float32)
    w = torch.tensor(rng.normal(size=(res, res, 3)), dtype=torch.float32)
    before = cpu_threads()
    runs = []
    try:
        for threads in (1, 3):
            set_cpu_threads(threads)
            out = rasterize_surfels(means, q, s, o, c, V, K, res, res)
            loss = (out["rgb"] * w).sum() + out["alpha"].sum() + out["depth"].sum()
            grads = torch.autograd.grad(loss, [means, q, s, o, c])
            runs.append(([out[k].detach() for k in ("rgb", "alpha", "depth", "normal")], grads))
    finally:
        set_cpu_threads(before)
    for a, b in zip(runs[0][0] + list(runs[0][1]), runs[1][0] + list(runs[1][1])):
        assert torch.equal(a, b)


def test_binning_lists_every_contributing_pixel_and_drops_what_thin_splats_miss(rng):
    """The binning (kernels/surfels.py, step 3) shrinks each (block, surfel) entry to the
    pixels the splat's cut-off ellipse may reach and leaves out blocks it misses. Oracle: a
    dense float64 rho = min(u^2 + v^2, 2 |d|^2) of every surfel at every pixel, from the
    reference's projection. Every pixel a surfel clearly reaches (rho below its cut-off
    2 ln(255 o)) must find the surfel in its list with a box that holds it; on needle-like,
    oblique splats the lists must hold far fewer (pixel, surfel) pairs than their boxes."""
    from holowarp.kernels.surfels import BLOCK_SIZE, NEAR_PLANE, TILE_SIZE
    from holowarp.ops.surfels import ProjectSurfels, _Binning
    from holowarp.ops.surfels_ref import project_surfels_ref

    n, W, H = 300, 48, 40
    means, quats, scales, opac, colors, viewmat, K, _ = random_scene(rng, n, W, H)
    scales[:, 1] = scales[:, 0] * 0.05  # needles
    f32 = [t.float() for t in (means, quats, scales, opac, colors, viewmat, K)]
    with torch.no_grad():
        proj = ProjectSurfels.apply(*f32[:3], f32[5], f32[6])
        bins = _Binning(*proj, f32[3], f32[4], W, H, NEAR_PLANE)
    # Dense float64 oracle on the float32-rounded inputs.
    Hm, centers, _, _ = project_surfels_ref(*[t.double() for t in f32[:3]], f32[5].double(), f32[6].double())
    ys, xs = np.mgrid[0:H, 0:W]
    px = torch.tensor(xs.ravel() + 0.5)[:, None]
    py = torch.tensor(ys.ravel() + 0.5)[:, None]
    hx = px[..., None] * Hm[None, :, 2] - Hm[None, :, 0]
    hy = py[..., None] * Hm[None, :, 2] - Hm[None, :, 1]
    c = torch.linalg.cross(hx, hy, dim=-1)
    rho3d = (c[..., 0] ** 2 + c[..., 1] ** 2) / c[..., 2] ** 2
    rho2d = 2.0 * ((px - centers[None, :, 0]) ** 2 + (py - centers[None, :, 1]) ** 2)
    rho = torch.minimum(rho3d, rho2d).numpy()  # [pixels, surfels]
    cut = 2.0 * np.log(255.0 * opac.float().double().numpy())
    drawn = bins.counts.numpy() > 0
    clear = (rho < cut[None, :] * (1 - 1e-3)) & drawn[None, :]
    # What the lists give each pixel.
    listed = np.zeros_like(clear)
    start, end, entries, order = (t.numpy() for t in (bins.list_start, bins.list_end, bins.list_ranks, bins.order))
    blocks_x = TILE_SIZE // BLOCK_SIZE
    for p, (x, y) in enumerate(zip(xs.ravel(), ys.ravel())):
        bx, by = x // BLOCK_SIZE, y // BLOCK_SIZE
        key = ((by // blocks_x) * bins.tiles_x + bx // blocks_x) * blocks_x**2 + (by % blocks_x) * blocks_x + bx % blocks_x
        e = entries[start[key]:end[key]]
        lx, ly = x % BLOCK_SIZE, y % BLOCK_SIZE
        inside = (lx >= (e & 3)) & (lx <= (e >> 2) & 3) & (ly >= (e >> 4) & 3) & (ly <= (e >> 6) & 3)
        listed[p, order[e[inside] >> 8]] = True
    assert clear.sum() > 500  # the scene covers pixels
    missed = clear & ~listed
    assert not missed.any(), f"{int(missed.sum())} (pixel, surfel) pairs within the cut-off are not listed"
    boxes = bins.boxes.numpy()
    in_boxes = int((np.clip(boxes[:, 2] - boxes[:, 0] + 1, 0, None) * np.clip(boxes[:, 3] - boxes[:, 1] + 1, 0, None)).sum())
    assert listed.sum() < 0.8 * in_boxes, (int(listed.sum()), in_boxes)
    assert int(end[-1] - start[-1]) > 0  # blocks left out altogether (the last list)
