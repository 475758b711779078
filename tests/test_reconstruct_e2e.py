"""End to end: the real pipeline, tiny, on a synthesised genus-1 object; resume; CLI errors."""

from __future__ import annotations

import json
import shutil
from dataclasses import replace

import numpy as np
import pytest
import trimesh

from holowarp.config import preset
from holowarp.pipeline import ReconstructionError, reconstruct
from holowarp.reconstruct import main as cli_main

RES = 40


@pytest.fixture(scope="module")
def torus_dataset(tmp_path_factory):
    """40 Fibonacci views (36 train) of a solid torus at 40x40, written by the synthesiser."""
    from holowarp.data.synth import synthesize

    root = tmp_path_factory.mktemp("torus")
    t = trimesh.creation.torus(major_radius=0.3, minor_radius=0.12, major_sections=48, minor_sections=24)
    t.export(root / "torus.obj")
    synthesize(root / "torus.obj", root / "data", views=40, res=RES, up_axis="z", progress=False)
    return root / "data"


def tiny_config(**changes):
    """The fast preset shrunk to a few hundred iterations, 40x40, coarse tets."""
    cfg = preset("fast").scaled(0.15)
    cfg = replace(cfg, resolution=RES, checkpoint_every=40, tet_init=replace(cfg.tet_init, edge_length_fac=0.07))
    return replace(cfg, **changes)


def test_tiny_reconstruction_is_one_manifold_genus_one_inversion_free_mesh(torus_dataset, tmp_path):
    from holowarp import read_tetmesh
    from holowarp.gaussians import load_gaussians_ply

    out = tmp_path / "run"
    report = reconstruct(torus_dataset, out, config=tiny_config(), progress=False)
    assert report["components"] == 1
    assert report["manifold"] is True
    assert report["genus"] == 1
    assert report["inverted_ratio"] == 0.0
    mesh = read_tetmesh(out / "tetmesh.vtu")
    assert mesh.num_tets == report["tets_final"] and np.all(mesh.signed_volumes() > 0)
    assert read_tetmesh(out / "tetmesh.msh").num_tets == mesh.num_tets
    assert len(load_gaussians_ply(out / "gaussians.ply")["means"]) == mesh.num_tets  # one surfel per tet
    saved = json.loads((out / "report.json").read_text())
    for key in ("preset", "device", "seconds_total", "stages", "tets_initial", "tets_final", "components",
                "manifold", "genus", "inverted_before_cleanup", "flipped", "dropped", "psnr_test",
                "ssim_test", "peak_rss_mb", "metrics"):
        assert key in saved, key
    assert saved["metrics"]["volume_iou"] > 0.5
    assert saved["psnr_test"] > 15.0
    for stage in ("stage0", "tet_init", "topology", "gaussian", "geometry", "cleanup"):
        assert saved["stages"][stage]["seconds"] > 0
    assert (out / "scene.usda").is_file() and (out / "surface.obj").is_file()
    assert {p.name for p in (out / "previews").iterdir()} >= {"cutaway_components.png", "losses.png"}


def test_a_killed_run_resumes_to_the_same_result(torus_dataset, tmp_path, monkeypatch):
    import holowarp.stages.geometry as geometry
    import holowarp.stages.topology as topology

    cfg = tiny_config()
    cfg = replace(cfg, schedule=replace(cfg.schedule, stage0_iters=40), checkpoint_every=25)
    base = tmp_path / "base"

    # Stop right after the tet initialisation so both runs share its (non-deterministic)
    # fTetWild output.
    def stop(*a, **k):
        raise KeyboardInterrupt

    monkeypatch.setattr(topology, "gaussian_step", stop)
    with pytest.raises(KeyboardInterrupt):
        reconstruct(torus_dataset, base, config=cfg, progress=False)
    monkeypatch.undo()
    a, b = tmp_path / "a", tmp_path / "b"
    shutil.copytree(base, a)
    shutil.copytree(base, b)
    ra = reconstruct(torus_dataset, a, config=cfg, resume=True, progress=False)

    # b is killed twice: in the topology phase, and in the middle of a geometry block.
    real_step, calls = topology.gaussian_step, {"n": 0}

    def flaky_step(*args, **kwargs):
        calls["n"] += 1
        if calls["n"] == 37:
            raise KeyboardInterrupt
        return real_step(*args, **kwargs)

    monkeypatch.setattr(topology, "gaussian_step", flaky_step)
    with pytest.raises(KeyboardInterrupt):
        reconstruct(torus_dataset, b, config=cfg, resume=True, progress=False)
    monkeypatch.undo()
    real_block = geometry.run_geometry_block

    def flaky_block(*args, **kwargs):
        kwargs["checkpoint_every"] = 7
        ckpt = kwargs["checkpoint"]
        seen = {"n": 0}

        def ckpt_then_die(step, opt_state):
            ckpt(step, opt_state)
            seen["n"] += 1
            if seen["n"] == 2:
                raise KeyboardInterrupt

        kwargs["checkpoint"] = ckpt_then_die
        return real_block(*args, **kwargs)

    monkeypatch.setattr(geometry, "run_geometry_block", flaky_block)
    with pytest.raises(KeyboardInterrupt):
        reconstruct(torus_dataset, b, config=cfg, resume=True, progress=False)
    monkeypatch.undo()
    rb = reconstruct(torus_dataset, b, config=cfg, resume=True, progress=False)

    from holowarp import read_tetmesh

    ma, mb = read_tetmesh(a / "tetmesh.vtu"), read_tetmesh(b / "tetmesh.vtu")
    np.testing.assert_array_equal(ma.tets, mb.tets)
    np.testing.assert_allclose(ma.vertices, mb.vertices, atol=1e-6)
    assert ra["psnr_test"] == pytest.approx(rb["psnr_test"], abs=1e-3)
    assert ra["prunes"] == rb["prunes"]


def test_bad_requests_fail_before_any_work(torus_dataset, tmp_path, capsys):
    from holowarp.data import load_dataset
    from holowarp.data.loaders import write_nerf_synthetic
    from holowarp.pipeline import preflight

    # Unreadable dataset.
    assert cli_main([str(tmp_path / "nope"), "--out", str(tmp_path / "o1"), "--quiet"]) == 1
    assert "no such folder" in capsys.readouterr().err
    empty = tmp_path / "empty"
    empty.mkdir()
    assert cli_main([str(empty), "--out", str(tmp_path / "o2"), "--quiet"]) == 1
    assert "cannot read the dataset" in capsys.readouterr().err
    # CUDA without a GPU (this machine has none; on a GPU machine the check is moot).
    import warp as wp

    if not wp.is_cuda_available():
        assert cli_main([str(torus_dataset), "--out", str(tmp_path / "o3"), "--device", "cuda", "--quiet"]) == 1
        assert "no CUDA GPU" in capsys.readouterr().err
    ds = load_dataset(torus_dataset)
    with pytest.raises(ReconstructionError, match="at least 8 training views"):
        preflight(ds.subset(np.concatenate([ds.train_idx[:5], ds.test_idx[:2]])))
    full = replace(ds, masks=np.ones_like(ds.masks))
    with pytest.raises(ReconstructionError, match="cover the whole frame"):
        preflight(full)
    blank = ds.masks.copy()
    blank[ds.train_idx[3]] = 0.0
    with pytest.raises(ReconstructionError, match=rf"views \[{ds.train_idx[3]}\] are empty"):
        preflight(replace(ds, masks=blank))
    # Masks that agree on nothing: each view sees the object somewhere else.
    rng = np.random.default_rng(0)
    shuffled = replace(ds, viewmats=ds.viewmats[rng.permutation(ds.num_views)])
    with pytest.raises(ReconstructionError, match="visual hull degenerates"):
        preflight(shuffled)
    # An output folder that already holds a run needs --resume.
    out = tmp_path / "o4"
    (out / "checkpoints").mkdir(parents=True)
    write_nerf_synthetic  # noqa: B018  (imported to show the writer exists for users)
    import torch

    torch.save({"config": {}, "state": {}}, out / "checkpoints" / "state.pt")
    with pytest.raises(ReconstructionError, match="pass --resume"):
        reconstruct(torus_dataset, out, config=tiny_config(), progress=False)
