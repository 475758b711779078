"""The procedural concavity suite: closed, manifold surfaces of the stated genus, with concave
regions inside their convex hulls."""

from __future__ import annotations

import numpy as np
import pytest

from holowarp.metrics.surface import concave_mask, sample_surface
from holowarp.shapes import SHAPES, shape_surface, surface_genus


@pytest.mark.parametrize("name", list(SHAPES))
def test_every_shape_is_a_closed_manifold_surface_of_its_genus_with_hidden_concavities(name, rng):
    V, F = shape_surface(name, resolution=64, max_faces=None)
    e = np.sort(np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]]), axis=1)
    _, counts = np.unique(e, axis=0, return_counts=True)
    assert (counts == 2).all()  # closed and edge-manifold
    assert surface_genus(V, F) == SHAPES[name][2]
    vol = np.einsum("ij,ij->i", V[F[:, 0]], np.cross(V[F[:, 1]], V[F[:, 2]])).sum() / 6.0
    assert vol > 0  # outward winding
    pts, _, _ = sample_surface(V, F, 20_000, rng=rng)
    ext = float(np.ptp(V, axis=0).max())
    assert concave_mask(pts / ext, V / ext).mean() > 0.02  # a part of the surface deep inside its hull


def test_the_renderers_normals_on_a_decimated_box_follow_its_signed_distance(rng):
    """The normal maps the synthesiser renders interpolate :func:`corner_normals` across each
    triangle. A decimated box keeps each flat face as a few large triangles beside thin bevels;
    their interpolated normals must stay those of the face (the signed distance's gradient),
    not tilt it towards the bevels (corner-angle weights at 60° were 12-14° off here)."""
    from holowarp.render_gt import corner_normals

    sdf = SHAPES["dented_box"][0]
    for resolution, faces in ((64, 3000), (96, 6000)):
        V, F = shape_surface("dented_box", resolution=resolution, max_faces=faces)
        p = V[F]
        area = 0.5 * np.linalg.norm(np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), axis=1)
        fi = rng.choice(len(F), 20_000, p=area / area.sum())
        s, r = np.sqrt(rng.random(len(fi))), rng.random(len(fi))
        bary = np.stack([1 - s, s * (1 - r), s * r], axis=1)
        pts = np.einsum("nk,nki->ni", bary, p[fi])
        grad = np.stack([sdf(pts + 1e-5 * e) - sdf(pts - 1e-5 * e) for e in np.eye(3)], axis=1)
        n = np.einsum("nk,nki->ni", bary, corner_normals(V, F).astype(np.float64)[fi])
        cos = (n * grad).sum(1) / (np.linalg.norm(n, axis=1) * np.linalg.norm(grad, axis=1))
        err = np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))
        assert err.mean() < 3.0 and np.quantile(err, 0.9) < 3.0, (resolution, err.mean(), np.quantile(err, 0.9))
