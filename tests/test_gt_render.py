"""Ground-truth ray caster against analytic oracles: sphere depth/normals/shading, texture
lookup (scipy ``map_coordinates``), UV orientation, vertex colours, antialiased coverage."""

from __future__ import annotations

import math

import numpy as np
import pytest

from oracles import pixel_rays

from holowarp.camera import intrinsics_from_fov, look_at
from holowarp.render_gt import GTRenderer, Lighting, corner_normals

RES = 64


def _icosphere(radius, subdivisions=5):
    import trimesh

    s = trimesh.creation.icosphere(subdivisions=subdivisions, radius=radius)
    return np.asarray(s.vertices), np.asarray(s.faces)


def _random_camera(rng, centre, dist=2.5):
    d = rng.normal(size=3)
    d /= np.linalg.norm(d)
    up = rng.normal(size=3)
    return look_at(centre + dist * d, centre + rng.uniform(-0.05, 0.05, 3), up)


def _analytic_sphere(viewmat, K, centre, radius):
    o, d, zpt = pixel_rays(viewmat, K, RES, RES)
    oc = o - centre
    b = d @ oc
    c = oc @ oc - radius * radius
    disc = b * b - c
    hit = disc > 0
    t = -b - np.sqrt(np.clip(disc, 0, None))
    p = o + t[..., None] * d
    n = (p - centre) / radius
    # Distance of each ray from the centre, for excluding near-tangent pixels.
    miss_dist = np.sqrt(np.clip(oc @ oc - b * b, 0, None))
    cos_inc = np.abs(np.einsum("hwk,hwk->hw", n, d))
    return hit, t * zpt, n, miss_dist, cos_inc


@pytest.mark.parametrize("smooth", [True, False])
def test_sphere_depth_normals_and_mask_match_analytic_sphere(rng, smooth):
    R = 0.5
    centre = rng.uniform(-0.2, 0.2, 3)
    v, f = _icosphere(R)
    r = GTRenderer(v + centre, f, smooth_normals=smooth)
    K = intrinsics_from_fov(math.radians(39.3), RES, RES)
    for _ in range(2):
        V = _random_camera(rng, centre)
        out = r.render(V, K, RES, RES)
        hit, depth, n, miss_dist, cos_inc = _analytic_sphere(V, K, centre, R)
        sure_in = miss_dist < R * (1 - 2e-3)
        sure_out = miss_dist > R
        assert (out["mask"][sure_in] == 1).all()
        assert (out["mask"][sure_out] == 0).all()
        assert (out["face"][sure_out] == -1).all() and (out["face"][sure_in] >= 0).all()
        good = sure_in & (cos_inc > 0.3)
        assert good.sum() > 500
        # Polyhedral sphere sits inside the true one by at most the sagitta (~1e-4 R).
        assert np.abs(out["depth"][good] - depth[good]).max() < 1.5e-3
        dots = np.einsum("hwk,hwk->hw", out["normal"], n)[good]
        assert dots.min() > (0.9995 if smooth else 0.998)
        assert np.allclose(np.linalg.norm(out["normal"][good], axis=-1), 1, atol=1e-5)
        assert (out["depth"][sure_out] == 0).all() and (out["normal"][sure_out] == 0).all()


def test_lambert_shading_follows_fixed_world_lights(rng):
    R = 0.5
    v, f = _icosphere(R)
    light = rng.normal(size=3)
    light /= np.linalg.norm(light)
    albedo = (0.5, 0.6, 0.7)
    lt = Lighting(ambient=(0.2, 0.2, 0.2), directions=(tuple(light),), colors=((0.6, 0.6, 0.6),))
    r = GTRenderer(v, f, albedo=albedo, lighting=lt)
    K = intrinsics_from_fov(math.radians(39.3), RES, RES)
    V = _random_camera(rng, np.zeros(3))
    out = r.render(V, K, RES, RES)
    hit, _, n, miss_dist, cos_inc = _analytic_sphere(V, K, np.zeros(3), R)
    good = (miss_dist < R * 0.998) & (cos_inc > 0.3)
    expect = np.asarray(albedo) * (0.2 + 0.6 * np.clip(n @ light, 0, None))[..., None]
    assert np.abs(out["rgba"][..., :3][good] - expect[good]).max() < 3e-3


def _bilinear_wrap_ref(tex, uv):
    from scipy.ndimage import map_coordinates

    h, w, _ = tex.shape
    # Texel centres at integer coordinates for map_coordinates; row 0 = top (v = 1).
    x = np.mod(uv[:, 0], 1.0) * w - 0.5
    y = (1.0 - np.mod(uv[:, 1], 1.0)) * h - 0.5
    return np.stack(
        [map_coordinates(tex[..., c], [y, x], order=1, mode="grid-wrap") for c in range(3)], axis=-1
    )


def test_texture_lookup_is_bilinear_with_wrapping(rng):
    import warp as wp

    from holowarp.device import init_warp
    from holowarp.kernels.raycast import texture_lookup_kernel

    init_warp()
    tex = rng.random((5, 7, 3)).astype(np.float32)
    uv = rng.uniform(-1.5, 2.5, (500, 2)).astype(np.float32)
    out = wp.zeros(len(uv), dtype=wp.vec3)
    wp.launch(
        texture_lookup_kernel,
        dim=len(uv),
        inputs=[wp.array(tex, dtype=wp.vec3), wp.array(uv, dtype=wp.vec2)],
        outputs=[out],
    )
    np.testing.assert_allclose(out.numpy(), _bilinear_wrap_ref(tex.astype(np.float64), uv.astype(np.float64)), atol=2e-5)


def _quad_camera():
    # Camera above the z = 0 plane looking down, image up = world +y, image right = +x.
    V = look_at((0.0, 0.0, 3.0), (0.0, 0.0, 0.0), (0.0, 1.0, 0.0))
    K = intrinsics_from_fov(math.radians(39.3), RES, RES)
    return V, K


def _plane_hits(V, K):
    o, d, _ = pixel_rays(V, K, RES, RES)
    t = -o[2] / d[..., 2]
    return o + t[..., None] * d


QUAD = np.array([[-1.0, -1.0, 0.0], [1.0, -1.0, 0.0], [1.0, 1.0, 0.0], [-1.0, 1.0, 0.0]])
QUAD_FACES = np.array([[0, 1, 2], [0, 2, 3]])
FLAT_WHITE = Lighting(ambient=(1.0, 1.0, 1.0), directions=((0.0, 0.0, 1.0),), colors=((0.0, 0.0, 0.0),))


def test_textured_quad_shows_texture_upright_at_interpolated_uvs(rng):
    tex = rng.random((6, 9, 3)).astype(np.float32)
    uvs = np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]])
    r = GTRenderer(QUAD, QUAD_FACES, uvs=uvs, face_uvs=QUAD_FACES, texture=tex, lighting=FLAT_WHITE)
    V, K = _quad_camera()
    out = r.render(V, K, RES, RES)
    p = _plane_hits(V, K)
    inside = (np.abs(p[..., 0]) < 0.99) & (np.abs(p[..., 1]) < 0.99)
    assert inside.sum() > 1000 and (out["mask"][inside] == 1).all()
    uv = ((p[..., :2] + 1.0) / 2.0)[inside]
    expect = _bilinear_wrap_ref(tex.astype(np.float64), uv)
    np.testing.assert_allclose(out["rgba"][..., :3][inside], expect, atol=2e-4)
    np.testing.assert_allclose(out["normal"][inside], np.tile([0.0, 0.0, 1.0], (inside.sum(), 1)), atol=1e-6)


def test_vertex_colours_interpolate_barycentrically(rng):
    A = rng.uniform(-0.2, 0.2, (3, 3))
    b = rng.uniform(0.4, 0.6, 3)
    colors = QUAD @ A.T + b  # affine in position: exact under linear interpolation
    r = GTRenderer(QUAD, QUAD_FACES, vertex_colors=colors, lighting=FLAT_WHITE)
    V, K = _quad_camera()
    out = r.render(V, K, RES, RES)
    p = _plane_hits(V, K)
    inside = (np.abs(p[..., 0]) < 0.99) & (np.abs(p[..., 1]) < 0.99)
    np.testing.assert_allclose(out["rgba"][..., :3][inside], (p @ A.T + b)[inside], atol=1e-4)


def _skewed_camera(rng, width, height):
    """A random upper-triangular K with skew and unequal focal lengths, and a camera looking
    down at the z = 0 plane from a random tilted pose."""
    f = rng.uniform(0.9, 1.3) * width
    K = np.array([[f, rng.uniform(0.04, 0.12) * f * rng.choice([-1, 1]), width * rng.uniform(0.4, 0.6)],
                  [0.0, f * rng.uniform(0.85, 1.15), height * rng.uniform(0.4, 0.6)], [0.0, 0.0, 1.0]])
    eye = np.r_[rng.uniform(-0.4, 0.4, 2), rng.uniform(2.5, 3.5)]
    return look_at(eye, np.r_[rng.uniform(-0.1, 0.1, 2), 0.0], (rng.uniform(-0.3, 0.3), 1.0, 0.0)), K


def _plane_hits_through_K(V, K, width, height):
    """World points (H, W, 3) where the rays ``K^-1 [x + 0.5, y + 0.5, 1]`` meet z = 0, and
    their camera z-depth (H, W): dense float64 NumPy, independent of the renderer."""
    u, v = np.meshgrid(np.arange(width) + 0.5, np.arange(height) + 0.5)
    d_cam = np.stack([u, v, np.ones_like(u)], -1) @ np.linalg.inv(K).T  # z component 1
    R, t = V[:3, :3], V[:3, 3]
    o = -R.T @ t
    d = d_cam @ R  # R^T d_cam
    s = -o[2] / d[..., 2]
    return o + s[..., None] * d, s  # depth = s * d_cam.z = s


def test_rays_follow_the_inverse_of_a_skewed_non_square_K(rng):
    width, height = 40, 28
    V, K = _skewed_camera(rng, width, height)
    A = rng.uniform(-0.2, 0.2, (3, 3))
    b = rng.uniform(0.4, 0.6, 3)
    quad = QUAD * 4.0  # covers the whole image
    r = GTRenderer(quad, QUAD_FACES, vertex_colors=quad @ A.T + b, lighting=FLAT_WHITE)
    out = r.render(V, K, width, height)
    p, depth = _plane_hits_through_K(V, K, width, height)
    assert out["rgba"].shape == (height, width, 4) and (out["mask"] == 1).all()
    np.testing.assert_allclose(out["rgba"][..., :3], p @ A.T + b, atol=1e-4)
    np.testing.assert_allclose(out["depth"], depth, rtol=1e-5)
    # The check has teeth: dropping the skew moves the hits by far more than the tolerance.
    K0 = K.copy()
    K0[0, 1] = 0.0
    p0, _ = _plane_hits_through_K(V, K0, width, height)
    assert np.abs((p0 - p) @ A.T).max() > 1e-2


def test_supersampled_alpha_is_the_covered_fraction_of_the_pixel():
    V, K = _quad_camera()
    f = K[0, 0]
    edge_u = 20.3  # pixel 20 has 4x4 samples at x + 1/8, 3/8, 5/8, 7/8: one column is covered
    e = (edge_u - K[0, 2]) * 3.0 / f
    quad = np.array([[-10.0, -10.0, 0.0], [e, -10.0, 0.0], [e, 10.0, 0.0], [-10.0, 10.0, 0.0]])
    r = GTRenderer(quad, QUAD_FACES, supersample=4)
    a = r.render(V, K, RES, RES)["mask"]
    np.testing.assert_allclose(a[:, :20], 1.0)
    np.testing.assert_allclose(a[:, 20], 0.25, atol=1e-6)
    np.testing.assert_allclose(a[:, 21:], 0.0)


def test_corner_normals_keep_cube_creases_sharp_and_smooth_spheres(rng):
    import trimesh

    box = trimesh.creation.box(extents=(1, 1, 1))
    cn = corner_normals(box.vertices, box.faces, crease_angle_deg=60)
    fn = np.asarray(box.face_normals)
    np.testing.assert_allclose(cn, np.repeat(fn[:, None], 3, axis=1), atol=1e-6)
    v, f = _icosphere(1.0, 3)
    cn = corner_normals(v, f)
    # unit sphere: normal = position; area weights leave 0.6° on this 1280-face sphere
    # (corner-angle weights 0.3°), in exchange for decimated flat faces (test_shapes.py)
    np.testing.assert_allclose(cn, v[f], atol=1.2e-2)


def test_bad_renderer_inputs_raise_clear_errors():
    with pytest.raises(ValueError, match="face indices"):
        GTRenderer(QUAD, np.array([[0, 1, 7]]))
    with pytest.raises(ValueError, match="NaN"):
        GTRenderer(QUAD * np.nan, QUAD_FACES)
