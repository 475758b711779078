"""Stage 0 (holowarp.stages.gaussian_init, python -m holowarp.gs2d) and the Gaussian model (holowarp.gaussians).

The training tests use a tiny in-memory dataset whose images are rendered by the surfel
rasteriser itself from a known set of surfels on a sphere, so the trainer must be able to
fit them; they run a few dozen iterations at 32x32.
"""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch

from holowarp.camera import fibonacci_sphere, intrinsics_from_fov, look_at
from holowarp.data.dataset import Dataset
from holowarp.gaussians import (
    FLAT_LOG_SCALE,
    GaussianModel,
    PlyError,
    load_gaussians_ply,
    quat_to_rotmat,
    quats_facing,
    write_gaussians_ply,
)
from holowarp.config import Stage0Config, preset
from holowarp.gs2d import main
from holowarp.stages.gaussian_init import init_surfels, train_gs2d
from holowarp.ops import rasterize_surfels

LRS = {"means": 1e-3, "log_scales": 5e-3, "quats": 1e-3, "opacity_logits": 0.05, "sh_dc": 2.5e-3}


def random_model(rng, n, device="cpu"):
    q = rng.normal(size=(n, 4))
    return GaussianModel(
        rng.normal(size=(n, 3)), np.log(rng.uniform(0.01, 0.1, (n, 2))), q / np.linalg.norm(q, axis=1, keepdims=True),
        rng.normal(size=n), rng.normal(size=(n, 3)), device=device,
    )  # fmt: skip


def test_ply_round_trip_in_the_3dgs_viewer_layout(rng, tmp_path):
    g = random_model(rng, 50)
    path = g.save_ply(tmp_path / "g.ply")
    header = path.read_bytes().split(b"end_header\n")[0].decode()
    names = [ln.split()[-1] for ln in header.splitlines() if ln.startswith("property")]
    assert names == ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2", "opacity",
                     "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]  # fmt: skip
    assert "binary_little_endian" in header and "element vertex 50" in header
    back = load_gaussians_ply(path)
    assert np.allclose(back["means"], g.means.detach().numpy(), atol=1e-6)
    assert np.allclose(back["scales"], g.scales().detach().numpy(), rtol=1e-5)
    assert np.allclose(back["opacities"], g.opacities().detach().numpy(), atol=1e-6)
    assert np.allclose(back["sh_dc"], g.params["sh_dc"].detach().numpy(), atol=1e-6)
    q = g.quats.detach().numpy()
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    assert np.allclose(back["quats"], q, atol=1e-6)
    raw = np.frombuffer(path.read_bytes().split(b"end_header\n")[1], dtype="<f4").reshape(50, 17)
    assert np.allclose(raw[:, 12], FLAT_LOG_SCALE)  # flat third axis for 3D viewers
    assert np.allclose(raw[:, 3:6], back["normals"], atol=1e-6)  # nx ny nz = surfel normals
    g2 = GaussianModel.from_ply(path)
    assert torch.allclose(g2.colors(), g.colors().detach(), atol=1e-5)


def test_load_gaussians_ply_names_the_file_on_bad_input(tmp_path):
    with pytest.raises(PlyError, match="missing.ply"):
        load_gaussians_ply(tmp_path / "missing.ply")
    bad = tmp_path / "bad.ply"
    bad.write_bytes(b"ply\nformat ascii 1.0\nelement vertex 0\nend_header\n")
    with pytest.raises(PlyError, match="bad.ply.*ascii"):
        load_gaussians_ply(bad)
    with pytest.raises(ValueError, match="quats"):
        write_gaussians_ply(tmp_path / "x.ply", means=np.zeros((2, 3)), quats=np.zeros((3, 4)),
                            scales=np.ones((2, 2)), opacities=np.ones(2) * 0.5, colors=np.zeros((2, 3)))  # fmt: skip


def test_density_control_keeps_adam_moments_aligned_with_their_surfels(rng):
    g = random_model(rng, 20)
    g.setup_optimizer(LRS)
    g.params["means"].grad = torch.tensor(rng.normal(size=(20, 3)), dtype=torch.float32)
    for n in ("log_scales", "quats", "opacity_logits", "sh_dc"):
        g.params[n].grad = torch.zeros_like(g.params[n])
    g.step()
    m_before = g.optimizer.state[g.params["means"]]["exp_avg"].clone()
    means_before = g.means.detach().clone()
    clone = torch.zeros(20, dtype=torch.bool)
    clone[[1, 4]] = True
    g.clone(clone)
    assert g.num == 22
    st = g.optimizer.state[g.params["means"]]
    assert torch.equal(st["exp_avg"][:20], m_before) and float(st["exp_avg"][20:].abs().max()) == 0
    assert torch.equal(g.means.detach()[20:], means_before[[1, 4]])
    remove = torch.zeros(22, dtype=torch.bool)
    remove[[0, 21]] = True
    g.prune(remove)
    assert g.num == 20
    assert torch.equal(g.optimizer.state[g.params["means"]]["exp_avg"][0], m_before[1])
    assert g.optimizer.param_groups[0]["params"][0] is g.params["means"]


def test_split_replaces_a_surfel_by_two_smaller_ones_in_its_plane(rng):
    g = random_model(rng, 5)
    g.setup_optimizer(LRS)
    sel = torch.tensor([False, False, True, False, False])
    parent_mean = g.means.detach()[2].clone()
    parent_scale = g.scales().detach()[2].clone()
    normal = g.normals()[2].clone()
    g.split(sel, generator=torch.Generator().manual_seed(0))
    assert g.num == 6
    kids = g.means.detach()[4:]
    assert torch.allclose((kids - parent_mean) @ normal, torch.zeros(2), atol=1e-5)  # in the plane
    assert torch.allclose(g.scales().detach()[4:], (parent_scale / 1.6).expand(2, 2), rtol=1e-5)


def test_reset_opacity_caps_opacities_and_clears_their_moments(rng):
    g = random_model(rng, 10)
    g.setup_optimizer(LRS)
    for n in g.params:
        g.params[n].grad = torch.ones_like(g.params[n])
    g.step()
    before = g.opacities().detach().clone()
    g.reset_opacity(0.01)
    assert torch.allclose(g.opacities().detach(), torch.clamp_max(before, 0.01), atol=1e-7)
    assert float(g.optimizer.state[g.params["opacity_logits"]]["exp_avg"].abs().max()) == 0.0


def tiny_dataset(n_views=8, size=32, n_surfels=120, seed=0, normals=False):
    """Views of a ground-truth set of surfels on a sphere, rendered by the rasteriser (with
    ``normals``, their rendered unit normals as the dataset's normal maps)."""
    rng = np.random.default_rng(seed)
    d = fibonacci_sphere(n_surfels)
    means = 0.4 * d
    quats = quats_facing(d)
    colors = 0.5 + 0.4 * d  # smooth colour field
    K = intrinsics_from_fov(math.radians(40.0), size, size)
    eyes = 2.2 * fibonacci_sphere(n_views)
    images, masks, Vs, nmaps = [], [], [], []
    for e in eyes:
        V = look_at(e)
        out = rasterize_surfels(
            torch.tensor(means), torch.tensor(quats), torch.full((n_surfels, 2), 0.09), torch.full((n_surfels,), 0.97),
            torch.tensor(colors), torch.tensor(V), torch.tensor(K), size, size,
        )  # fmt: skip
        a = out["alpha"].numpy()
        images.append(np.where(a[..., None] > 1e-6, out["rgb"].numpy() / np.maximum(a, 1e-6)[..., None], 0.0))
        masks.append(a)
        Vs.append(V)
        n = out["normal"].numpy()
        nmaps.append(np.where(a[..., None] > 0.5, n / np.maximum(np.linalg.norm(n, axis=-1, keepdims=True), 1e-9), 0.0))
    return Dataset(
        images=np.clip(np.stack(images), 0, 1).astype(np.float32), masks=np.stack(masks).astype(np.float32),
        K=np.repeat(K[None], n_views, 0), viewmats=np.stack(Vs), train_idx=np.arange(1, n_views),
        test_idx=np.array([0]), name="tiny", normals=np.stack(nmaps).astype(np.float32) if normals else None,
    )  # fmt: skip


def tiny_config(iters, **kw):
    """Stage 0 with its schedule written for exactly ``iters`` iterations."""
    base = dict(reference_iters=max(iters, 1), init_points=300, init_candidates=20_000, densify_from=10,
                densify_until=max(iters, 1), densify_interval=10, opacity_reset_interval=10_000,
                normal_from=max(iters // 2, 1), checkpoint_every=10)
    base.update(kw)  # fmt: skip
    return Stage0Config(**base)


def test_initial_surfels_lie_inside_every_training_mask_that_sees_them():
    from oracles import bilinear_masks

    ds = tiny_dataset()
    pts, cols = init_surfels(ds, tiny_config(1, init_points=200))
    assert len(pts) == 200 and cols.shape == (200, 3) and np.isfinite(cols).all()
    vals, seen = bilinear_masks(pts, ds, ds.train_idx)
    assert seen.any(axis=1).all()
    assert (np.where(seen, vals, 1.0) >= 0.5 - 1e-5).all()  # every view that sees a surfel has it inside


def test_training_lowers_the_loss_and_writes_ply_and_report(tmp_path):
    ds = tiny_dataset()
    res = train_gs2d(ds, tiny_config(60), tmp_path, iters=60, progress=False)
    report = json.loads((tmp_path / "report.json").read_text())
    for key in ("psnr_test", "ssim_test", "gaussians", "iters", "seconds"):
        assert key in report
    assert report["iters"] == 60 and report["gaussians"] == res["model"].num
    g = load_gaussians_ply(tmp_path / "gaussians.ply")
    assert len(g["means"]) == report["gaussians"]
    # Before training (the visual-hull initialisation) versus after.
    init = train_gs2d(ds, tiny_config(0), tmp_path / "init", iters=0, progress=False)
    assert report["psnr_test"] > init["psnr_test"] + 3.0, (report["psnr_test"], init["psnr_test"])
    assert (tmp_path / "test_preview.png").is_file()


def test_resumed_training_reproduces_the_uninterrupted_run(tmp_path, monkeypatch):
    ds = tiny_dataset()
    cfg = tiny_config(30)
    full = train_gs2d(ds, cfg, tmp_path / "full", iters=30, progress=False)
    _interrupt_and_resume(ds, cfg, tmp_path / "part", 30, after=20, monkeypatch=monkeypatch, full=full)


def _interrupt_and_resume(ds, cfg, out, iters: int, *, after: int, monkeypatch, full, checkpoint_at=None):
    """Interrupt ``train_gs2d`` at its loss call ``after + 1``, check that it left a
    checkpoint (at ``checkpoint_at`` when given) and no report, resume it, and compare the
    result with the uninterrupted run ``full``."""
    import holowarp.stages.gaussian_init as gi

    calls = {"n": 0}
    real_loss = gi.l1_dssim_loss

    def interrupted(*a, **kw):
        calls["n"] += 1
        if calls["n"] > after:
            raise KeyboardInterrupt
        return real_loss(*a, **kw)

    monkeypatch.setattr(gi, "l1_dssim_loss", interrupted)
    with pytest.raises(KeyboardInterrupt):
        train_gs2d(ds, cfg, out, iters=iters, progress=False)
    assert (out / "checkpoint.pt").is_file() and not (out / "report.json").exists()
    if checkpoint_at is not None:
        assert torch.load(out / "checkpoint.pt", weights_only=False)["iteration"] == checkpoint_at
    monkeypatch.setattr(gi, "l1_dssim_loss", real_loss)
    resumed = train_gs2d(ds, cfg, out, iters=iters, resume=True, progress=False)
    assert resumed["gaussians"] == full["gaussians"]
    for name in ("means", "log_scales", "opacity_logits", "sh_dc"):
        assert torch.allclose(resumed["model"].params[name], full["model"].params[name], atol=1e-5), name


def _normal_error(model, ds, views) -> float:
    """Mean 1 - cos between the rendered normals and the dataset's normal maps where both cover."""
    errs = []
    with torch.no_grad():
        for v in views:
            o = model.render(ds.viewmats[v], ds.K[v], ds.width, ds.height)
            n, g = o["normal"].numpy(), ds.normals[v]
            has = (o["alpha"].numpy() > 0.5) & (np.linalg.norm(g, axis=-1) > 0.5)
            c = (n[has] * g[has]).sum(-1) / np.maximum(np.linalg.norm(n[has], axis=-1), 1e-12)
            errs.append(1.0 - c)
    return float(np.concatenate(errs).mean())


def test_the_normal_map_prior_pulls_the_surfels_normals_onto_the_maps(tmp_path):
    # The same run with and without stage 0's L_prior: with it, the trained surfels' rendered
    # normals agree better with the normal maps, on the training views and, less so from 7
    # views, on the held-out one (40 iterations: the rotations get a faster learning rate).
    ds = tiny_dataset(normals=True)
    runs = {w: train_gs2d(ds, tiny_config(40, prior_weight=w, lr_quats=0.03), tmp_path / str(w), iters=40,
                          progress=False)["model"] for w in (0.0, 1.0)}
    for views, gain in ((ds.train_idx, 0.6), (ds.test_idx, 0.9)):
        off, on = (_normal_error(runs[w], ds, views) for w in (0.0, 1.0))
        assert on < gain * off, (views, off, on)


def test_the_normal_map_prior_is_off_without_normal_maps(tmp_path):
    ds = tiny_dataset()
    a, b = (train_gs2d(ds, tiny_config(12, prior_weight=w), tmp_path / str(w), iters=12, progress=False)["model"]
            for w in (0.0, 0.25))
    for name in ("means", "quats", "opacity_logits"):
        assert torch.equal(a.params[name], b.params[name]), name
    with pytest.raises(ValueError, match="prior_weight"):
        tiny_config(1, prior_weight=-1.0).validate()


def test_a_garbage_checkpoint_is_refused_with_a_clear_error(tmp_path):
    from holowarp.stages.gaussian_init import CheckpointError

    (tmp_path / "checkpoint.pt").write_bytes(b"not a torch file")
    with pytest.raises(CheckpointError, match="unreadable stage-0 checkpoint"):
        train_gs2d(tiny_dataset(), tiny_config(5), tmp_path, iters=5, resume=True, progress=False)


def test_cli_trains_a_dataset_folder_and_reports_bad_requests_clearly(tmp_path, capsys):
    from holowarp.data.loaders import write_nerf_synthetic

    data = write_nerf_synthetic(tiny_dataset(n_views=10), tmp_path / "data")
    out = tmp_path / "o"
    assert main([str(data), "--out", str(out), "--iters", "12", "--res", "32", "--quiet"]) == 0
    assert "psnr_test=" in capsys.readouterr().out
    report = json.loads((out / "report.json").read_text())
    assert report["iters"] == 12 and report["gaussians"] > 0
    assert len(load_gaussians_ply(out / "gaussians.ply")["means"]) == report["gaussians"]
    assert main([str(tmp_path / "nope"), "--out", str(tmp_path / "o2")]) == 2
    err = capsys.readouterr().err
    assert "nope" in err and err.count("\n") == 1
    assert main([str(data), "--out", str(tmp_path / "o3"), "--iters", "-3"]) == 2
    assert "--iters" in capsys.readouterr().err


def test_stage0_schedules_keep_the_order_of_events():
    cfg = Stage0Config()
    for n in (100, 800, 3000, 10_000):
        s = cfg.schedule(n)
        assert s.iters == n
        assert 1 <= s.densify_from < s.densify_until <= n
        assert s.normal_from < n and s.dist_from < n
        assert s.opacity_reset_interval % s.densify_interval == 0
    # The paper's preset runs 10k stage-0 iterations at 512^2 (method.md §3, §8), fast 800 at 128^2.
    assert preset("paper").schedule.stage0_iters == 10_000 and preset("paper").resolution == 512
    fast = preset("fast")
    assert fast.schedule.stage0_iters == 800 and fast.resolution == 128
    assert fast.stage0.schedule(800).densify_until == round(1800 * 800 / 3000)
    # The coarse start is an option (Stage0Config.coarse_fraction has the measurements).
    assert fast.stage0.coarse_fraction == 0.0 and preset("paper").stage0.coarse_fraction == 0.0
    for bad in (dict(coarse_fraction=-0.1), dict(coarse_fraction=1.5), dict(coarse_scale=0.0), dict(coarse_scale=2.0)):
        with pytest.raises(ValueError, match=next(iter(bad))):
            Stage0Config(**bad).validate()


def test_a_coarse_start_renders_its_iterations_smaller_and_resumes_into_the_same_phase(tmp_path, monkeypatch):
    """Stage0Config.coarse_fraction: the first half of the iterations render at half the
    size, with the intrinsics scaled alike, the rest at the full size; a run interrupted in
    the coarse half resumes there and ends where the uninterrupted run does."""
    from holowarp.gaussians import GaussianModel

    ds = tiny_dataset(size=32, normals=True)
    cfg = tiny_config(20, coarse_fraction=0.5, coarse_scale=0.5, checkpoint_every=5)
    seen = []
    real_render = GaussianModel.render

    def spy(self, viewmat, K, width, height, **kw):
        seen.append((width, height, float(K[0, 0]), float(K[0, 2])))
        return real_render(self, viewmat, K, width, height, **kw)

    monkeypatch.setattr(GaussianModel, "render", spy)
    full = train_gs2d(ds, cfg, tmp_path / "full", iters=20, progress=False)
    steps = seen[:20]
    assert [s[:2] for s in steps] == [(16, 16)] * 10 + [(32, 32)] * 10
    assert steps[0][2] == pytest.approx(ds.K[0, 0, 0] / 2) and steps[0][3] == pytest.approx(ds.K[0, 0, 2] / 2)
    assert steps[-1][2] == pytest.approx(ds.K[0, 0, 0])
    assert all(s[:2] == (32, 32) for s in seen[20:])  # the test views are scored at the full size
    _interrupt_and_resume(ds, cfg, tmp_path / "part", 20, after=7, checkpoint_at=5, monkeypatch=monkeypatch,
                          full=full)


def test_quats_facing_turns_z_onto_each_normal(rng):
    d = rng.normal(size=(64, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    q = quats_facing(d)
    np.testing.assert_allclose(np.linalg.norm(q, axis=1), 1.0, atol=1e-12)
    R = quat_to_rotmat(torch.tensor(q)).numpy()
    np.testing.assert_allclose(R[:, :, 2], d, atol=1e-12)
