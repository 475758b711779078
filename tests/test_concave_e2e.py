"""The quality benchmark's CI-sized form (issue 12): one concave object at 32x32, a few
hundred iterations, and the visual hull of the same masks. No silhouette sees the dent in
the box's top face, so the hull fills it; the reconstruction must carve it deeper."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

RES = 32


@pytest.fixture(scope="module")
def dented_box(tmp_path_factory):
    """40 Fibonacci views (36 train) of the suite's dented box, synthesised at 32x32."""
    from holowarp.shapes import write_shape
    from holowarp.synthesis import synthesize

    root = tmp_path_factory.mktemp("dented_box")
    write_shape("dented_box", root / "shape.obj", resolution=64, max_faces=4000)
    synthesize(root / "shape.obj", root / "data", views=40, res=RES, up_axis="z", progress=False)
    return root / "data"


def test_tiny_reconstruction_carves_the_dent_deeper_than_the_visual_hull(dented_box, tmp_path):
    from holowarp.baselines.hull import VisualHullSettings, hull_surface
    from holowarp.config import preset
    from holowarp.data.loaders import load_dataset
    from holowarp.metrics.evaluate import evaluate_mesh
    from holowarp.pipeline import reconstruct

    cfg = preset("fast").scaled(0.15)  # a few hundred iterations
    cfg = replace(cfg, resolution=RES, checkpoint_every=10**6, tet_init=replace(cfg.tet_init, edge_length_fac=0.07))
    report = reconstruct(dented_box, tmp_path / "run", config=cfg, progress=False)
    assert report["components"] == 1 and report["manifold"] is True and report["genus"] == 0

    hV, hF, _ = hull_surface(load_dataset(dented_box), settings=VisualHullSettings(grid=48))
    gt = dented_box / "gt.obj"
    pred = evaluate_mesh(tmp_path / "run" / "tetmesh.vtu", gt, num_samples=20_000, volume_points=100_000)
    hull = evaluate_mesh((hV, hF), gt, num_samples=20_000, volume_points=100_000)
    assert np.isfinite(hull["concave_chamfer"]) and hull["concave_chamfer"] > 0.05  # the hull fills the dent
    # Measured 0.055-0.067 against the hull's 0.147 (0.37-0.45x); 0.7x leaves room for fTetWild's draws.
    assert pred["concave_chamfer"] < 0.7 * hull["concave_chamfer"]
