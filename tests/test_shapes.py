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
