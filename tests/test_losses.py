"""Losses of holowarp.losses against independent implementations and analytic cases."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from holowarp.camera import intrinsics_from_fov, look_at
from holowarp.losses import (
    depth_to_normal,
    depth_to_points,
    distortion_loss,
    l1_dssim_loss,
    mask_loss,
    nearest_box,
    normal_consistency_loss,
    prior_error,
    ranked_loss,
    ranked_normal_loss,
)
from holowarp.metrics.image import psnr, ssim


@pytest.mark.parametrize("shape", [(40, 36, 3), (330, 24, 2)])  # banded-matmul and convolution paths
def test_ssim_matches_pytorch_msssim_values_and_gradients(rng, shape):
    pytorch_msssim = pytest.importorskip("pytorch_msssim")
    a = torch.tensor(rng.uniform(0, 1, shape), requires_grad=True)
    b = (a.detach() + torch.tensor(rng.normal(0, 0.1, shape))).clamp(0, 1)
    ours = ssim(a, b)
    ours.backward()
    g_ours = a.grad.clone()
    a.grad = None
    ref = pytorch_msssim.ssim(a.permute(2, 0, 1)[None], b.permute(2, 0, 1)[None], data_range=1.0,
                              win_size=11, win_sigma=1.5)  # fmt: skip
    ref.backward()
    # pytorch-msssim builds its window in float32, hence 1e-7 rather than float64 round-off.
    assert float(ours.detach()) == pytest.approx(float(ref.detach()), abs=1e-7)
    assert torch.allclose(g_ours, a.grad, atol=1e-7)
    assert float(ssim(b, b)) == pytest.approx(1.0, abs=1e-12)


def test_psnr_and_l1_dssim_on_known_images():
    a = torch.zeros(16, 16, 3)
    b = torch.full((16, 16, 3), 0.1)
    assert float(psnr(a, b)) == pytest.approx(20.0, abs=1e-4)  # mse 0.01
    # Constant images: SSIM = (c1 / (0.01 + c1)) * 1 from the luminance term alone.
    c1 = 0.01**2
    s = c1 / (0.1**2 + c1)
    assert float(ssim(a, b)) == pytest.approx(s, rel=1e-5)
    assert float(l1_dssim_loss(a, b)) == pytest.approx(0.8 * 0.1 + 0.2 * (1 - s), rel=1e-5)
    assert float(mask_loss(torch.ones(4, 4), torch.zeros(4, 4))) == 1.0


@pytest.mark.parametrize("tilt", [0.0, 0.6])
def test_depth_to_normal_recovers_a_plane_normal_facing_the_camera(rng, tilt):
    w, h = 40, 30
    eye = np.array([0.3, -2.5, 0.8])
    V = look_at(eye)
    K = intrinsics_from_fov(math.radians(45), w, h)
    # World plane through the origin with normal n (either orientation).
    n = np.array([math.sin(tilt), -math.cos(tilt), 0.2])
    n /= np.linalg.norm(n)
    if rng.uniform() < 0.5:
        n = -n
    # Camera-z depth of the plane at every pixel: ray x = eye + t d_world, n . x = 0.
    ys, xs = np.meshgrid(np.arange(h) + 0.5, np.arange(w) + 0.5, indexing="ij")
    d_cam = np.stack([(xs - K[0, 2]) / K[0, 0], (ys - K[1, 2]) / K[1, 1], np.ones_like(xs)], -1)
    d_world = d_cam @ V[:3, :3]  # R^T d, with d_cam.z = 1 so t is the camera depth
    depth = -(eye @ n) / (d_world @ n)
    normals = depth_to_normal(torch.tensor(depth), torch.tensor(K), torch.tensor(V))
    facing = n if (eye @ n) > 0 else -n  # towards the camera
    inner = normals[1:-1, 1:-1].reshape(-1, 3).numpy()
    assert np.allclose(inner, facing, atol=1e-8)
    assert float(normals[0].abs().max()) == 0.0  # border


def test_normal_consistency_and_distortion_losses():
    n = torch.nn.functional.normalize(torch.randn(8, 8, 3, dtype=torch.float64), dim=-1)
    assert float(normal_consistency_loss(n, n)) == pytest.approx(0.0, abs=1e-12)
    assert float(normal_consistency_loss(n, -n)) == pytest.approx(2.0, abs=1e-12)
    w = torch.zeros(8, 8, dtype=torch.float64)
    w[:4] = 1.0
    assert float(normal_consistency_loss(n, -n, weight=w)) == pytest.approx(1.0, abs=1e-12)
    d = torch.rand(8, 8)
    assert float(distortion_loss(d)) == pytest.approx(float(d.mean()))


def test_ranked_loss_averages_only_the_largest_errors(rng):
    e = torch.tensor(rng.uniform(0, 1, 100), requires_grad=True)
    loss = ranked_loss(e, top_fraction=0.1)
    top = torch.sort(e.detach(), descending=True).values[:10]
    assert float(loss.detach()) == pytest.approx(float(top.mean()))
    loss.backward()
    assert int((e.grad != 0).sum()) == 10  # the gradient goes to the worst pixels only
    assert float(ranked_loss(e.detach(), top_fraction=1.0)) == pytest.approx(float(e.detach().mean()))
    mask = torch.zeros(100, dtype=torch.bool)
    assert float(ranked_loss(e.detach(), mask=mask)) == 0.0
    with pytest.raises(ValueError, match="top_fraction"):
        ranked_loss(e, top_fraction=0.0)


@pytest.mark.parametrize("frac", [0.37, 1.0])
def test_grouped_ranked_loss_ranks_each_group_apart(rng, frac):
    """Value and gradient against a NumPy loop over the groups: each group's largest
    ceil(frac * valid) errors, averaged together. One group is the ungrouped loss."""
    shape, count = (30, 40), 4
    e = torch.tensor(rng.uniform(0.1, 2.0, shape), requires_grad=True)
    labels = torch.tensor(rng.integers(0, count - 1, shape), dtype=torch.int32)  # group 3 stays empty
    labels[0, :5] = 2
    mask = torch.tensor(rng.uniform(size=shape) > 0.3)
    loss = ranked_loss(e, mask=mask, top_fraction=frac, groups=(labels, count))
    loss.backward()
    E, L, M = e.detach().numpy(), labels.numpy(), mask.numpy()
    want = np.zeros(shape, dtype=bool)
    for g in range(count):
        idx = np.flatnonzero(((L == g) & M).ravel())
        k = math.ceil(frac * idx.size)
        want.ravel()[idx[np.argsort(-E.ravel()[idx], kind="stable")[:k]]] = True
    assert float(loss.detach()) == pytest.approx(float(E[want].mean()), rel=1e-12)
    assert np.allclose(e.grad.numpy(), want / want.sum())
    ones = torch.zeros(shape, dtype=torch.int32)
    plain = ranked_loss(e.detach(), mask=mask, top_fraction=frac)
    assert float(ranked_loss(e.detach(), mask=mask, top_fraction=frac, groups=(ones, 1))) == pytest.approx(float(plain))
    # A group of small errors keeps its share: ungrouped, the large group takes the ranking.
    small = torch.where(labels == 0, e.detach() * 0.01, e.detach())
    g0 = (labels == 0) & mask
    assert float(ranked_loss(small, mask=g0, top_fraction=frac)) > 0
    if frac < 1:
        picked = torch.zeros_like(small, requires_grad=True)
        ranked_loss(small + picked, mask=mask, top_fraction=frac).backward()
        assert float(picked.grad[g0].abs().sum()) == 0.0
        picked.grad = None
        ranked_loss(small + picked, mask=mask, top_fraction=frac, groups=(labels, count)).backward()
        assert int((picked.grad[g0] != 0).sum()) == math.ceil(frac * int(g0.sum()))


def test_pixels_are_labelled_by_the_box_nearest_their_surface_point(rng):
    """depth_to_points inverts the projection (skew included); nearest_box against a loop."""
    w, h = 20, 16
    V = look_at(np.array([0.4, -2.0, 0.9]))
    K = intrinsics_from_fov(math.radians(50), w, h)
    K[0, 1] = 0.7
    depth = rng.uniform(1.5, 2.5, (h, w))
    pts = depth_to_points(torch.tensor(depth), torch.tensor(K), torch.tensor(V)).numpy()
    cam = pts @ V[:3, :3].T + V[:3, 3]
    uv = cam @ K.T
    ys, xs = np.meshgrid(np.arange(h) + 0.5, np.arange(w) + 0.5, indexing="ij")
    assert np.allclose(cam[..., 2], depth) and np.allclose(uv[..., 0] / uv[..., 2], xs)
    assert np.allclose(uv[..., 1] / uv[..., 2], ys)
    lo = rng.uniform(-1, 0.5, (3, 3))
    lo[:, 0] = [-1.0, 0.0, 1.0]  # disjoint boxes: a point inside one is inside only that one
    boxes = np.stack([lo, lo + rng.uniform(0.1, 0.6, (3, 3))], 1)
    got = nearest_box(torch.tensor(pts), torch.tensor(boxes)).numpy()
    p = pts[..., None, :]
    gap = np.maximum(boxes[:, 0] - p, 0) + np.maximum(p - boxes[:, 1], 0)
    assert np.array_equal(got, np.linalg.norm(gap, axis=-1).argmin(-1))
    assert nearest_box(torch.tensor(boxes[1].mean(0)), torch.tensor(boxes)).item() == 1


def test_ranked_normal_loss_is_scale_invariant_and_skips_empty_pixels():
    a = torch.nn.functional.normalize(torch.randn(6, 6, 3, dtype=torch.float64), dim=-1)
    b = torch.nn.functional.normalize(torch.randn(6, 6, 3, dtype=torch.float64), dim=-1)
    ref = ranked_normal_loss(a, b, top_fraction=1.0)
    cos = (a * b).sum(-1)
    assert float(ref) == pytest.approx(float((1 - cos).mean()))
    # Alpha-weighted (non-unit) rendered normals give the same cosine.
    assert float(ranked_normal_loss(0.3 * a, b, top_fraction=1.0)) == pytest.approx(float(ref))
    a0 = a.clone()
    a0[0] = 0.0  # uncovered row: skipped
    expected = (1 - cos[1:]).mean()
    assert float(ranked_normal_loss(a0, b, top_fraction=1.0)) == pytest.approx(float(expected))


def test_prior_error_sums_one_minus_cos_per_map_and_marks_where_the_prior_holds_a_normal(rng):
    prior = rng.normal(size=(12, 9, 3))
    prior[rng.random((12, 9)) < 0.3] = 0.0  # no normal there
    a, b = rng.normal(size=(12, 9, 3)), rng.normal(size=(12, 9, 3))

    def cos(u, v):  # float64 reference
        return (u * v).sum(-1) / np.maximum(np.linalg.norm(u, axis=-1) * np.linalg.norm(v, axis=-1), 1e-12)

    at = torch.tensor(a, dtype=torch.float32, requires_grad=True)
    err, has = prior_error(torch.tensor(prior, dtype=torch.float32), at, torch.tensor(b, dtype=torch.float32))
    np.testing.assert_allclose(err.detach().numpy(), (1 - cos(prior, a)) + (1 - cos(prior, b)), atol=1e-5)
    np.testing.assert_array_equal(has.numpy(), np.linalg.norm(prior, axis=-1) > 0.5)
    # The gradient against a central difference in float64, on one pixel with a prior.
    i, j = np.argwhere(np.linalg.norm(prior, axis=-1) > 0.5)[0]
    (g,) = torch.autograd.grad(err[i, j], at)
    h, num = 1e-6, np.zeros(3)
    for k in range(3):
        up, dn = a.copy(), a.copy()
        up[i, j, k] += h
        dn[i, j, k] -= h
        num[k] = -(cos(prior, up)[i, j] - cos(prior, dn)[i, j]) / (2 * h)
    np.testing.assert_allclose(g[i, j].numpy(), num, rtol=1e-3, atol=1e-5)
    assert torch.count_nonzero(g).item() == 3  # only that pixel's normal moves


def test_covered_prior_chord_is_the_distance_between_unit_normals_and_pulls_small_tilts(rng):
    from holowarp.losses import covered_prior_loss

    prior = rng.normal(size=(10, 8, 3))
    prior[rng.random((10, 8)) < 0.25] = 0.0  # no normal there
    n = rng.normal(size=(10, 8, 3))
    alpha = rng.uniform(0.0, 1.0, (10, 8))
    unit = lambda u: u / np.maximum(np.linalg.norm(u, axis=-1, keepdims=True), 1e-300)  # noqa: E731
    sel = (alpha > 0.5) & (np.linalg.norm(prior, axis=-1) > 0.5)
    chord = np.sqrt(np.linalg.norm(unit(n) - unit(prior), axis=-1) ** 2 + 1e-6)  # float64 reference
    nt = torch.tensor(n, dtype=torch.float32, requires_grad=True)
    got = covered_prior_loss(torch.tensor(prior, dtype=torch.float32), nt, torch.tensor(alpha, dtype=torch.float32),
                             chord=True)
    assert float(got.detach()) == pytest.approx(chord[sel].mean(), rel=1e-4)
    # Near agreement the chord is the angle: a tilt of 0.01 rad costs 0.01, where 1 - cos
    # costs 5e-5; its gradient stays at about one per radian.
    z = np.zeros((1, 1, 3)); z[..., 2] = 1.0
    t = torch.tensor([[[np.sin(0.01), 0.0, np.cos(0.01)]]], dtype=torch.float64, requires_grad=True)
    one = torch.ones((1, 1), dtype=torch.float64)
    loss = covered_prior_loss(torch.tensor(z), t, one, chord=True)
    assert float(loss.detach()) == pytest.approx(0.01, rel=1e-2)
    assert float(covered_prior_loss(torch.tensor(z), t.detach(), one)) == pytest.approx(1 - np.cos(0.01), rel=1e-6)
    (g,) = torch.autograd.grad(loss, t)
    assert float(g[0, 0, 0]) == pytest.approx(1.0, rel=0.05)
