"""Local refinement by longest-edge bisection (holowarp.refine) and the surfels following it.

Oracles: volumes and boundary areas summed in float64 (a conforming refinement keeps both),
each parent's volume against the sum over its children, an affine field reproduced exactly
at every new vertex, and the mesh's own topology counts before and after."""

import numpy as np
import pytest
import torch

from holowarp.config import TopologyConfig
from holowarp.primitives import box_tetmesh
from holowarp.refine import bisect_longest_edges, boundary_band, edge_table
from holowarp.tetgs import TetGaussians
from holowarp.tetmesh import TET_EDGES, TetMesh
from oracles import surface_area


def _ring_mesh(rng) -> TetMesh:
    """A genus-1 block (4 x 4 x 2 cells, the middle 2 x 2 column removed), its interior and
    boundary vertices jittered by up to 0.12 cells so no two edges tie in length."""
    mask = np.ones((4, 4, 2), dtype=bool)
    mask[1:3, 1:3, :] = False
    m = box_tetmesh((4, 4, 2), size=(1.0, 1.0, 0.5), cell_mask=mask)
    V = m.vertices + rng.uniform(-0.03, 0.03, m.vertices.shape)
    return TetMesh(V, m.tets)


def _min_dihedral(V, T) -> float:
    return float(TetMesh(V, T, validate=False).dihedral_angles().min())


@pytest.mark.parametrize("rings", [1, 2])
def test_bisection_is_conforming_and_keeps_volume_boundary_and_topology(rings):
    rng = np.random.default_rng(rings + 17)
    m = _ring_mesh(rng)
    band = boundary_band(m.tets, m.num_vertices, m.surface_vertices(), rings)
    _, _, length, longest = edge_table(m.vertices, m.tets)
    target = 0.6 * float(np.median(length[longest[band]]))
    V, T, parent, ends = bisect_longest_edges(m.vertices, m.tets, band, target)
    out = TetMesh(V, T)  # validates indices
    assert out.num_tets > 2 * m.num_tets
    # Conforming: every face on two tets or on the boundary, a manifold boundary, the same
    # topology, and the boundary as a point set (same area); all children positive.
    assert out.non_manifold_faces() == 0 and out.manifold()["manifold"]
    assert (out.genus(), out.num_components(), out.boundary_shells()) == (m.genus(), 1, m.boundary_shells()) == (1, 1, 1)
    assert out.signed_volumes().min() > 0
    assert out.volume() == pytest.approx(m.volume(), rel=1e-12)
    assert surface_area(out) == pytest.approx(surface_area(m), rel=1e-12)
    assert len(out.boundary_faces()) > len(m.boundary_faces())
    # Each parent's volume is the sum of its children's.
    per_parent = np.bincount(parent, weights=out.signed_volumes(), minlength=m.num_tets)
    np.testing.assert_allclose(per_parent, m.signed_volumes(), rtol=1e-12)
    # New vertices are midpoints (in creation order) of earlier ones.
    N = m.num_vertices
    assert V.shape == (N + len(ends), 3) and np.all(ends < N + np.arange(len(ends))[:, None])
    np.testing.assert_allclose(V[N:], 0.5 * (V[ends[:, 0]] + V[ends[:, 1]]), atol=0)
    np.testing.assert_array_equal(V[:N], m.vertices)
    # Every descendant of a band tet meets the target; the split shapes stay bounded.
    P = V[T]
    longest_len = np.linalg.norm(P[:, TET_EDGES[:, 0]] - P[:, TET_EDGES[:, 1]], axis=2).max(axis=1)
    assert longest_len[band[parent]].max() <= target * (1 + 1e-12)
    assert _min_dihedral(V, T) > 0.4 * _min_dihedral(m.vertices, m.tets)


def test_bisection_leaves_far_tets_alone_and_refines_nothing_below_target():
    rng = np.random.default_rng(3)
    m = box_tetmesh((7, 7, 7))
    m = TetMesh(m.vertices + rng.uniform(-0.02, 0.02, m.vertices.shape) * (m.vertices % 1.0 != 0), m.tets)
    band = boundary_band(m.tets, m.num_vertices, m.surface_vertices(), 1)
    assert 0 < band.sum() < m.num_tets
    _, _, length, longest = edge_table(m.vertices, m.tets)
    V, T, parent, _ = bisect_longest_edges(m.vertices, m.tets, band, 0.6 * float(np.median(length[longest[band]])))
    # A tet of the core whose vertices no split touched is copied unchanged.
    untouched = np.bincount(parent, minlength=m.num_tets) == 1
    assert untouched[~band].any()
    kept = T[np.isin(parent, np.flatnonzero(untouched))]
    np.testing.assert_array_equal(np.sort(kept, axis=0), np.sort(m.tets[untouched], axis=0))
    # A target above every edge changes nothing.
    V2, T2, p2, e2 = bisect_longest_edges(m.vertices, m.tets, band, 10.0)
    assert len(e2) == 0 and np.array_equal(T2, m.tets) and np.array_equal(p2, np.arange(m.num_tets))


def test_bisection_rejects_bad_arguments():
    m = box_tetmesh((1, 1, 1))
    with pytest.raises(ValueError, match="target must be > 0"):
        bisect_longest_edges(m.vertices, m.tets, np.ones(m.num_tets, bool), 0.0)
    with pytest.raises(ValueError, match="marked"):
        bisect_longest_edges(m.vertices, m.tets, np.ones(m.num_tets + 1, bool), 0.1)


def test_surfels_follow_a_refinement_and_the_field_is_unchanged():
    rng = np.random.default_rng(11)
    m = _ring_mesh(rng)
    a, b = rng.normal(size=3), float(rng.normal())
    phi = m.vertices @ a + b  # affine: a piecewise-linear field reproduces it exactly
    colors = rng.uniform(0.1, 0.9, (m.num_tets, 3))
    model = TetGaussians(m, colors=colors, phi=phi, config=TopologyConfig(), seed=4)
    model.opacity_logit.data = torch.as_tensor(rng.normal(size=m.num_tets), dtype=torch.float32)
    old = {k: getattr(model, k).detach().clone() for k in ("color_logit", "quats", "opacity_logit", "log_scales")}
    band = boundary_band(m.tets, m.num_vertices, m.surface_vertices(), 1)
    V, T, parent, ends = bisect_longest_edges(m.vertices, m.tets, band, 0.15)
    with pytest.raises(ValueError, match="parent"):
        model.apply_refine(V, T, parent[:-1], ends)
    with pytest.raises(ValueError, match="midpoints"):
        model.apply_refine(V[:-1], T, parent, ends)
    saved = model.state_dict()
    model.apply_refine(V, T, parent, ends)
    assert model.num_tets == len(T) and model.num_vertices == len(V)
    np.testing.assert_allclose(model.phi.detach().numpy(), V @ a + b, rtol=0, atol=2e-5)
    for k in ("color_logit", "quats", "opacity_logit"):
        np.testing.assert_array_equal(getattr(model, k).detach().numpy(), old[k].numpy()[parent])
    # Scales shrink with the tets' mean radius (centroid-to-vertex distance).
    def radius(X, TT):
        P = X[TT]
        return np.linalg.norm(P - P.mean(1, keepdims=True), axis=2).mean(1)
    ratio = radius(V, T) / radius(m.vertices, m.tets)[parent]
    np.testing.assert_allclose(np.exp(model.log_scales.detach().numpy()),
                               np.exp(old["log_scales"].numpy()[parent]) * ratio[:, None], rtol=1e-5)
    # Loading the saved state undoes the refinement in place (the finish's way back when §7b
    # cannot mend the refined mesh), into fresh parameters.
    model.load_state_dict(saved)
    assert model.num_tets == m.num_tets and model.num_vertices == m.num_vertices
    for k in TetGaussians._TENSORS:
        assert torch.equal(getattr(model, k).detach(), saved[k]), k
    assert isinstance(model.vertices, torch.nn.Parameter) and not isinstance(model.tets, torch.nn.Parameter)
    model.vertices.data += 1.0  # a copy, not the saved tensor
    assert not torch.equal(model.vertices.detach(), saved["vertices"])


def test_refine_near_surface_follows_the_config():
    from holowarp.stages.topology import refine_near_surface

    rng = np.random.default_rng(5)
    m = _ring_mesh(rng)
    model = TetGaussians(m, phi=rng.normal(size=m.num_vertices), config=TopologyConfig())
    assert refine_near_surface(model, TopologyConfig()) is None and model.num_tets == m.num_tets
    info = refine_near_surface(model, TopologyConfig(refine_rings=1, refine_factor=0.7))
    assert info["tets_before"] == m.num_tets and info["tets_after"] == model.num_tets > m.num_tets
    assert info["band"] == int(boundary_band(m.tets, m.num_vertices, m.surface_vertices(), 1).sum())
    out = model.mesh()
    assert out.genus() == 1 and out.manifold()["manifold"] and out.signed_volumes().min() > 0
    with pytest.raises(ValueError, match="refine_factor"):
        TopologyConfig(refine_rings=1, refine_factor=0.0)
    with pytest.raises(ValueError, match="refine_rings"):
        TopologyConfig(refine_rings=-1)
