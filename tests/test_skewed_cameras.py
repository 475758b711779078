"""Cameras from NeuS/IDR decompositions have a skew ``K[0, 1]`` and non-square images: the
triangle rasteriser and the depth-derived normals are checked here against dense float64
NumPy projections with a random skewed K (the ray caster's check is in test_gt_render.py,
the carve's in test_visual_hull.py through ``oracles.bilinear_masks``)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from holowarp.camera import look_at
from holowarp.losses import depth_to_normal
from holowarp.ops import rasterize_mesh

pytestmark = pytest.mark.usefixtures("one_torch_thread")

WIDTH, HEIGHT = 56, 36


def _skewed_K(rng):
    f = rng.uniform(0.9, 1.3) * WIDTH
    return np.array([[f, rng.uniform(0.04, 0.12) * f * rng.choice([-1, 1]), WIDTH * rng.uniform(0.4, 0.6)],
                     [0.0, f * rng.uniform(0.85, 1.15), HEIGHT * rng.uniform(0.4, 0.6)], [0.0, 0.0, 1.0]])


def _random_view(rng):
    eye = rng.normal(size=3)
    eye *= 3.0 / np.linalg.norm(eye)
    return look_at(eye, rng.uniform(-0.05, 0.05, 3), rng.normal(size=3))


def _project(X, V, K):
    """Pixel coordinates (P, 2) and camera z (P,) of world points: ``K @ (R X + t)``."""
    pc = X @ V[:3, :3].T + V[:3, 3]
    q = pc @ K.T
    return q[:, :2] / q[:, 2:], pc[:, 2]


def _oracle_raster(X, F, V, K):
    """Nearest front face and its camera z at every pixel centre (x + 0.5, y + 0.5), and the
    distance (pixels) from each centre to the nearest projected edge; dense float64 NumPy."""
    uv, z = _project(X, V, K)
    u, v = np.meshgrid(np.arange(WIDTH) + 0.5, np.arange(HEIGHT) + 0.5)
    P = np.stack([u.ravel(), v.ravel()], 1)
    best_iz = np.zeros(len(P))
    face = np.full(len(P), -1)
    edge_d = np.full(len(P), np.inf)
    for f, (a, b, c) in enumerate(F):
        A, B, C = uv[a], uv[b], uv[c]
        area = (B[0] - A[0]) * (C[1] - A[1]) - (B[1] - A[1]) * (C[0] - A[0])
        for p, q in ((A, B), (B, C), (C, A)):
            e = q - p
            t = np.clip(((P - p) @ e) / (e @ e), 0, 1)
            edge_d = np.minimum(edge_d, np.linalg.norm(P - (p + t[:, None] * e), axis=1))
        if area >= 0:  # back face: an outward (counter-clockwise) front face has a negative
            continue  # signed area in pixel coordinates, whose y axis points down
        w0 = ((B[0] - P[:, 0]) * (C[1] - P[:, 1]) - (B[1] - P[:, 1]) * (C[0] - P[:, 0])) / area
        w1 = ((C[0] - P[:, 0]) * (A[1] - P[:, 1]) - (C[1] - P[:, 1]) * (A[0] - P[:, 0])) / area
        w2 = 1.0 - w0 - w1
        inside = (w0 >= 0) & (w1 >= 0) & (w2 >= 0)
        iz = w0 / z[a] + w1 / z[b] + w2 / z[c]  # 1/z is affine in screen space
        better = inside & (iz > best_iz)
        best_iz[better] = iz[better]
        face[better] = f
    depth = np.where(face >= 0, 1.0 / np.maximum(best_iz, 1e-30), 0.0)
    return face.reshape(HEIGHT, WIDTH), depth.reshape(HEIGHT, WIDTH), edge_d.reshape(HEIGHT, WIDTH)


def test_triangle_rasteriser_projects_through_a_skewed_non_square_K(rng):
    import trimesh

    m = trimesh.creation.icosphere(subdivisions=1, radius=0.6)
    X = np.asarray(m.vertices) * (1.0 + 0.2 * rng.uniform(-1, 1, (len(m.vertices), 1)))
    F = np.asarray(m.faces, dtype=np.int32)
    for _ in range(2):
        V, K = _random_view(rng), _skewed_K(rng)
        out = rasterize_mesh(torch.tensor(X, dtype=torch.float32), torch.tensor(F), V, K, WIDTH, HEIGHT)
        face, depth, edge_d = _oracle_raster(X, F, V, K)
        clear = edge_d > 1e-3  # pixel centres on an edge may go to either face
        assert clear.sum() > 0.9 * WIDTH * HEIGHT and (face >= 0).sum() > 300
        np.testing.assert_array_equal(out["face_id"].numpy()[clear], face[clear])
        np.testing.assert_allclose(out["depth"].numpy()[clear], depth[clear], rtol=1e-4)
        # Sensitivity: without the skew the oracle disagrees with the rasteriser.
        K0 = K.copy()
        K0[0, 1] = 0.0
        assert (_oracle_raster(X, F, V, K0)[0][clear] != face[clear]).sum() > 20


def test_depth_normals_of_a_plane_seen_through_a_skewed_non_square_K(rng):
    V, K = _random_view(rng), _skewed_K(rng)
    R, t = V[:3, :3], V[:3, 3]
    centre = -R.T @ t
    # A plane through a point near the origin, tilted by up to ~35 degrees from facing the
    # camera, so every pixel's ray meets it in front of the camera.
    c_hat = centre / np.linalg.norm(centre)
    perp = np.cross(c_hat, rng.normal(size=3))
    a = np.radians(rng.uniform(10.0, 35.0))
    n = c_hat * np.cos(a) + perp / np.linalg.norm(perp) * np.sin(a)
    d0 = n @ rng.uniform(-0.1, 0.1, 3)  # plane n . x = d0
    u, v = np.meshgrid(np.arange(WIDTH) + 0.5, np.arange(HEIGHT) + 0.5)
    d_cam = np.stack([u, v, np.ones_like(u)], -1) @ np.linalg.inv(K).T  # rays with z = 1
    s = (d0 - n @ centre) / ((d_cam @ R) @ n)  # the camera depth of the plane at each pixel
    assert (s > 0).all()
    normals = depth_to_normal(torch.tensor(s), torch.tensor(K), torch.tensor(V)).numpy()
    inner = normals[1:-1, 1:-1].reshape(-1, 3)
    np.testing.assert_allclose(inner, np.tile(n, (len(inner), 1)), atol=1e-6)
    # Sensitivity: a K without the skew unprojects to a sheared plane, whose normal misses
    # by far more than the tolerance above.
    K0 = K.copy()
    K0[0, 1] = 0.0
    sheared = depth_to_normal(torch.tensor(s), torch.tensor(K0), torch.tensor(V)).numpy()[1:-1, 1:-1].reshape(-1, 3)
    assert np.abs(sheared - n).max() > 1e-4
