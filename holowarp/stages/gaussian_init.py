"""Stage 0, Gaussian initialisation (method.md §3): 2D Gaussian surfels (2DGS) from the images.

:func:`train_gs2d` trains :class:`holowarp.gaussians.GaussianModel` surfels with the numbers of
:class:`holowarp.config.Stage0Config`. Per iteration one random training view is rendered
with the Warp surfel rasteriser and the loss is

    (1 - 0.2) L1 + 0.2 (1 - SSIM)                         on RGB composited on ``background``
    + mask_weight     |alpha - mask|
    + normal_weight   (1 - <n_rendered, n_depth * alpha>)  2DGS normal consistency, from normal_from
    + dist_weight     distortion                           2DGS depth distortion, from dist_from
    + prior_weight    L_prior                              against the dataset's normal maps, if any

with ``L_prior`` the mean over covered pixels (alpha > 0.5) of ``(1 - cos(n_prior, n_rendered))
+ (1 - cos(n_prior, n_depth))``, the term §5's ``L_render`` uses with the same weight. The
depth-normal half moves the surfels themselves, so stage 0's surface follows concavities that
silhouettes and smooth shading do not pin down, and its depth carves them (issue 12).

with the adaptive density control of 3DGS/2DGS: surfels with a large mean screen-space
gradient are cloned (small) or split (large), low-opacity ones pruned, opacities reset
periodically. Surfels start inside the visual hull of the training masks
(:func:`holowarp.carve.sample_points_in_hull`); their centres are the point cloud of §4.
With ``Stage0Config.coarse_fraction`` (off in both presets) the first iterations render and
compare the views at ``coarse_scale`` of the working resolution (area-filtered images, masks
and normal maps), the rest at the full one.

Outputs in ``out_dir``: ``gaussians.ply`` (3DGS layout, see :mod:`holowarp.gaussians`),
``report.json`` (``psnr_test``, ``ssim_test``, ``gaussians``, ``iters``, ``seconds`` and more),
``test_preview.png`` (ground truth beside the render of the first test view) and
``checkpoint.pt`` (written atomically every ``checkpoint_every`` iterations; ``resume=True``
continues from it).
"""

from __future__ import annotations

import math
import time
from dataclasses import asdict
from pathlib import Path

import numpy as np
import torch

from holowarp.camera import camera_center, project_points
from holowarp.carve import sample_points_in_hull
from holowarp.config import Stage0Config, Stage0Schedule
from holowarp.data.dataset import Dataset, DatasetError
from holowarp.device import resolve_device
from holowarp.fileio import atomic_path, atomic_write_json, check_output_dir
from holowarp.gaussians import GaussianModel
from holowarp.losses import (
    depth_to_normal,
    distortion_loss,
    l1_dssim_loss,
    mask_loss,
    normal_consistency_loss,
    prior_error,
)
from holowarp.metrics.image import psnr, ssim
from holowarp.progress import bar as progress_bar
from holowarp.progress import say

__all__ = ["CheckpointError", "train_gs2d", "init_surfels", "evaluate_views"]


class CheckpointError(DatasetError):
    """A stage-0 checkpoint cannot be resumed (unreadable, or made with other settings)."""


# ----------------------------------------------------------------------------- initialisation


def _image_colors(dataset: Dataset, pts: np.ndarray, views) -> np.ndarray:
    """Mean image colour (P, 3) of ``pts`` over ``views`` where they project in frame (0.5
    where no view sees them)."""
    colors = np.zeros((len(pts), 3))
    counts = np.zeros(len(pts))
    h, w = dataset.height, dataset.width
    for i in views:
        uv, z = project_points(pts, dataset.viewmats[i], dataset.K[i])
        col = np.floor(uv[:, 0]).astype(np.int64)
        row = np.floor(uv[:, 1]).astype(np.int64)
        vis = (z > 1e-6) & (col >= 0) & (col < w) & (row >= 0) & (row < h)
        colors[vis] += dataset.images[i][row[vis], col[vis]]
        counts += vis
    return np.where(counts[:, None] > 0, colors / np.maximum(counts, 1)[:, None], 0.5)


def init_surfels(dataset: Dataset, config: Stage0Config, *, seed: int = 0, device: str = "cpu"):
    """Initial surfel centres (P, 3) inside the masks' visual hull and their colours (P, 3),
    each the mean over ``init_color_views`` random training views that see it."""
    idx = _train_views(dataset)
    pts, _ = sample_points_in_hull(dataset, config.init_points, views=idx, candidates=config.init_candidates,
                                   seed=seed, tolerance=config.hull, device=device)
    rng = np.random.default_rng([seed, 1])
    return pts, _image_colors(dataset, pts, rng.permutation(idx)[: config.init_color_views])


def _train_views(dataset: Dataset) -> np.ndarray:
    return np.asarray(dataset.train_idx if len(dataset.train_idx) else np.arange(dataset.num_views))


def _scene_extent(dataset: Dataset, factor: float) -> float:
    """3DGS's scene scale: ``factor`` x the largest distance of a camera from the cameras' mean."""
    o = np.stack([camera_center(V) for V in dataset.viewmats])
    return factor * float(np.max(np.linalg.norm(o - o.mean(0), axis=1)))


# ----------------------------------------------------------------------------- evaluation


@torch.no_grad()
def evaluate_views(model: GaussianModel, dataset: Dataset, idx, *, background, device) -> dict:
    """Mean PSNR/SSIM of renders against images composited on ``background``."""
    bg = torch.tensor(background, dtype=torch.float32, device=device)
    gts = dataset.composite(background)
    ps, ss, renders = [], [], []
    for i in idx:
        out = model.render(dataset.viewmats[i], dataset.K[i], dataset.width, dataset.height, background=bg)
        rgb = out["rgb"].clamp(0.0, 1.0)
        gt = torch.from_numpy(np.ascontiguousarray(gts[i])).to(device)
        ps.append(psnr(rgb, gt))
        ss.append(float(ssim(rgb, gt)))
        renders.append(rgb.cpu().numpy())
    return {"psnr": float(np.mean(ps)), "ssim": float(np.mean(ss)), "renders": renders, "psnr_views": ps}


def _write_preview(path: Path, gt: np.ndarray, render: np.ndarray):
    from PIL import Image

    img = np.concatenate([gt, render], axis=1)
    with atomic_path(path) as tmp:
        Image.fromarray((np.clip(img, 0, 1) * 255 + 0.5).astype(np.uint8)).save(tmp, format="PNG")


# ----------------------------------------------------------------------------- training


def _lrs(cfg: Stage0Config, extent: float) -> dict:
    return {
        "means": cfg.lr_means * extent,
        "log_scales": cfg.lr_scales,
        "quats": cfg.lr_quats,
        "opacity_logits": cfg.lr_opacity,
        "sh_dc": cfg.lr_colors,
    }


def _means_lr(cfg: Stage0Config, iters: int, extent: float, it: int) -> float:
    t = min(max(it / max(iters, 1), 0.0), 1.0)
    return extent * math.exp((1 - t) * math.log(cfg.lr_means) + t * math.log(cfg.lr_means_final))


class _Trainer:
    """Stage 0's mutable state: the model, the RNGs, the densification statistics and the
    view order, with their checkpoint (everything a resumed run needs to continue exactly)."""

    def __init__(self, dataset: Dataset, cfg: Stage0Config, sch: Stage0Schedule, out: Path, *, seed: int, device):
        self.ds, self.cfg, self.sch, self.dev = dataset, cfg, sch, device
        self.W, self.H = dataset.width, dataset.height
        self.extent = _scene_extent(dataset, cfg.scene_extent_factor)
        self.lrs = _lrs(cfg, self.extent)
        self.bg = torch.tensor(cfg.background, dtype=torch.float32, device=device)
        self.Vs = torch.from_numpy(dataset.viewmats).double()
        # The views as the loss sees them: at the working resolution, and for the first
        # ``coarse_until`` iterations at ``coarse_scale`` of it (Stage0Config.coarse_fraction).
        self.coarse_until = int(round(cfg.coarse_fraction * sch.iters))
        self.sets = {False: self._view_set(dataset)}
        if self.coarse_until > 0:
            self.sets[True] = self._view_set(dataset.scaled(cfg.coarse_scale))
        self._use(False)
        self.ckpt_path = out / "checkpoint.pt"
        self.rng = np.random.default_rng(seed)
        self.gen = torch.Generator().manual_seed(seed)
        self.seed = seed
        self.order: list[int] = []  # views left in the current pass over the training set
        self.start, self.elapsed, self.last_loss = 0, 0.0, float("nan")
        self.model: GaussianModel | None = None
        self.grad_acc = self.denom = None

    def _view_set(self, ds: Dataset) -> tuple:
        """(W, H, RGB targets (N, H, W, 3), masks (N, H, W), normal maps (N, H, W, 3) or None,
        intrinsics (N, 3, 3) float64) of ``ds`` as torch tensors on the trainer's device."""
        as_t = lambda a: torch.from_numpy(np.ascontiguousarray(a, dtype=np.float32)).to(self.dev)  # noqa: E731
        normals = as_t(ds.normals) if ds.normals is not None and self.cfg.prior_weight > 0 else None
        return (ds.width, ds.height, as_t(ds.composite(self.cfg.background)), as_t(ds.masks), normals,
                torch.from_numpy(ds.K).double())

    def _use(self, coarse: bool):
        """Render and compare the views at the coarse resolution or at the working one."""
        self.rW, self.rH, self.targets, self.masks, self.normals, self.Ks = self.sets[coarse]

    def fresh(self):
        pts, cols = init_surfels(self.ds, self.cfg, seed=self.seed, device=self.dev)
        self.model = GaussianModel.from_points(pts, cols, opacity=self.cfg.init_opacity, seed=self.seed, device=self.dev)
        self.model.setup_optimizer(self.lrs)
        self._zero_stats()

    def _zero_stats(self):
        self.grad_acc = torch.zeros(self.model.num, device=self.dev)
        self.denom = torch.zeros(self.model.num, device=self.dev)

    def resume(self) -> bool:
        """Load ``checkpoint.pt`` if there is one; False when there is none."""
        if not self.ckpt_path.is_file():
            return False
        try:
            ck = torch.load(self.ckpt_path, map_location="cpu", weights_only=False)
            size = (ck["width"], ck["height"])
            params = [ck["model"][n] for n in ("means", "log_scales", "quats", "opacity_logits", "sh_dc")]
        except Exception as e:  # a foreign or damaged file: torch/pickle raise many types
            raise CheckpointError(f"{self.ckpt_path}: unreadable stage-0 checkpoint ({type(e).__name__}: {e}); "
                                  "delete it or choose another --out") from None
        if size != (self.W, self.H):
            raise CheckpointError(
                f"{self.ckpt_path}: checkpoint was trained at {size[0]}x{size[1]}, the dataset is now "
                f"{self.W}x{self.H}; use the same --res or start without --resume")
        self.model = GaussianModel(*params, device=self.dev)
        self.model.load_state_dict(ck["model"], self.lrs)
        self.start, self.elapsed = int(ck["iteration"]), float(ck["seconds"])
        self.last_loss = float(ck.get("loss", float("nan")))
        self.rng.bit_generator.state = ck["numpy_rng"]
        self.gen.set_state(ck["torch_rng"])
        self.grad_acc, self.denom = ck["grad_acc"].to(self.dev), ck["denom"].to(self.dev)
        self.order = [int(v) for v in ck["view_order"]]
        return True

    def save(self, it: int, seconds: float):
        state = {
            "iteration": it, "seconds": seconds, "loss": self.last_loss, "model": self.model.state_dict(),
            "numpy_rng": self.rng.bit_generator.state, "torch_rng": self.gen.get_state(),
            "view_order": list(self.order), "grad_acc": self.grad_acc.cpu(), "denom": self.denom.cpu(),
            "width": self.W, "height": self.H, "config": asdict(self.cfg), "schedule": asdict(self.sch),
        }
        with atomic_path(self.ckpt_path) as tmp:
            torch.save(state, tmp)

    def loss(self, it: int, i: int, o: dict) -> torch.Tensor:
        cfg, sch = self.cfg, self.sch
        loss = l1_dssim_loss(o["rgb"], self.targets[i], lambda_dssim=cfg.dssim_weight)
        if cfg.mask_weight > 0:
            loss = loss + cfg.mask_weight * mask_loss(o["alpha"], self.masks[i])
        consistency = cfg.normal_weight > 0 and it >= sch.normal_from
        if consistency or self.normals is not None:
            # One depth-normal map for both terms that read it.
            alpha = o["alpha"]
            n_depth = depth_to_normal(o["depth"] / alpha.clamp_min(1e-6), self.Ks[i].to(self.dev),
                                      self.Vs[i].to(self.dev))
        if consistency:
            loss = loss + cfg.normal_weight * normal_consistency_loss(o["normal"], n_depth * alpha.detach()[..., None])
        if cfg.dist_weight > 0 and it >= sch.dist_from:
            loss = loss + cfg.dist_weight * distortion_loss(o["distortion"])
        if self.normals is not None:
            loss = loss + cfg.prior_weight * self._prior(i, o, n_depth)
        return loss

    def _prior(self, i: int, o: dict, n_depth: torch.Tensor) -> torch.Tensor:
        """``L_prior`` of view ``i`` (module docstring) for the render ``o`` and its depth
        normals ``n_depth`` (H, W, 3)."""
        prior, alpha = self.normals[i], o["alpha"]
        err, has = prior_error(prior, o["normal"], n_depth.to(alpha.dtype))
        has = ((alpha.detach() > 0.5) & has).to(alpha.dtype)
        return (err * has).sum() / has.sum().clamp_min(1.0)

    def step(self, it: int, train_idx) -> None:
        """One iteration: render a view, back-propagate, gather densification statistics,
        step, and run density control when it is due."""
        if not self.order:
            self.order = list(self.rng.permutation(train_idx))
        i = int(self.order.pop())
        self._use(it < self.coarse_until)
        model, sch, W, H = self.model, self.sch, self.rW, self.rH
        model.set_lr("means", _means_lr(self.cfg, sch.iters, self.extent, it))
        o = model.render(self.Vs[i], self.Ks[i], W, H, background=self.bg)
        loss = self.loss(it, i, o)
        loss.backward()
        with torch.no_grad():
            g2 = o["means2d"].grad
            if it < sch.densify_until and g2 is not None:
                gn = torch.stack([g2[:, 0] * (W / 2), g2[:, 1] * (H / 2)], -1).norm(dim=-1)
                self.grad_acc += gn * o["visible"]
                self.denom += o["visible"]
        model.step()
        self.last_loss = float(loss.detach())
        done = it + 1
        if sch.densify_from <= done < sch.densify_until and done % sch.densify_interval == 0:
            _densify(model, self.grad_acc, self.denom, self.cfg, self.extent, self.gen,
                     prune_big=done > sch.opacity_reset_interval)
            self._zero_stats()
        if done < sch.densify_until and done % sch.opacity_reset_interval == 0:
            model.reset_opacity(self.cfg.reset_opacity)


def train_gs2d(
    dataset: Dataset,
    config: Stage0Config,
    out_dir=".",
    *,
    iters: int,
    seed: int = 0,
    device: str = "cpu",
    resume: bool = False,
    progress: bool = True,
) -> dict:
    """Train stage 0 for ``iters`` iterations and write its outputs to ``out_dir`` (see the
    module docstring).

    Args:
        dataset: the views, at the working resolution.
        config: :class:`holowarp.config.Stage0Config`.
        out_dir: output folder (created).
        iters: training iterations (one view each); 0 writes the initial surfels.
        seed: seeds the view order, the initialisation and the splits.
        device: ``"cpu"`` or ``"cuda[:N]"``.
        resume: continue from ``out_dir/checkpoint.pt`` if it exists (else start fresh).
        progress: show a progress bar (see :mod:`holowarp.progress`).

    Returns:
        the report dict written to ``report.json`` plus ``model`` (the trained
        :class:`GaussianModel`) and ``out_dir``.

    Raises:
        DatasetError: no views to train on; CheckpointError: a checkpoint that cannot be resumed.
    """
    config.validate()
    if iters < 0:
        raise ValueError(f"stage 0: iters must be >= 0, got {iters}")
    dev = resolve_device(device)
    out = check_output_dir(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    train_idx = _train_views(dataset)
    if len(train_idx) == 0:
        raise DatasetError(f"{dataset.name}: no views to train on")
    tr = _Trainer(dataset, config, config.schedule(iters), out, seed=seed, device=dev)
    if resume and tr.resume():
        say(f"gs2d: resuming {tr.ckpt_path} at iteration {tr.start}", progress)
    if tr.model is None:
        tr.fresh()
    t0 = time.perf_counter()
    bar = progress_bar(iters, initial=min(tr.start, iters), desc="gs2d", progress=progress)
    for it in range(tr.start, iters):
        tr.step(it, train_idx)
        step = it + 1
        if step % 10 == 0 or step == iters:
            bar.set_postfix(loss=f"{tr.last_loss:.4f}", gaussians=tr.model.num, refresh=False)
        bar.update(1)
        if step % tr.sch.checkpoint_every == 0 and step < iters:
            tr.save(step, tr.elapsed + time.perf_counter() - t0)
    bar.close()
    seconds_train = tr.elapsed + time.perf_counter() - t0
    if iters > tr.start:
        tr.save(iters, seconds_train)
    return _finish(tr, out, train_idx, iters, seconds_train, dev)


def _finish(tr: _Trainer, out: Path, train_idx, iters: int, seconds_train: float, dev) -> dict:
    """Write the PLY, evaluate on the test views (train views if there are none), preview,
    report."""
    t_eval = time.perf_counter()
    ds, cfg = tr.ds, tr.cfg
    tr.model.save_ply(out / "gaussians.ply")
    test_idx = np.asarray(ds.test_idx)
    eval_idx = test_idx if len(test_idx) else train_idx
    ev = evaluate_views(tr.model, ds, eval_idx, background=cfg.background, device=dev)
    _write_preview(out / "test_preview.png", ds.composite(cfg.background)[int(eval_idx[0])], ev["renders"][0])
    report = {
        "psnr_test": ev["psnr"],
        "ssim_test": ev["ssim"],
        "gaussians": tr.model.num,
        "iters": iters,
        "seconds": seconds_train + (time.perf_counter() - t_eval),
        "seconds_train": seconds_train,
        "eval_views": "test" if len(test_idx) else "train",
        "num_eval_views": len(ev["psnr_views"]),
        "resolution": [ds.width, ds.height],
        "device": dev,
        "dataset": str(ds.root) if ds.root else ds.name,
        "final_loss": tr.last_loss,
        "config": asdict(cfg),
        "schedule": asdict(tr.sch),
    }
    atomic_write_json(out / "report.json", report)
    return {**report, "model": tr.model, "out_dir": str(out)}


def _densify(model: GaussianModel, grad_acc, denom, cfg: Stage0Config, extent: float, gen, *, prune_big: bool):
    """One round of 3DGS/2DGS adaptive density control."""
    with torch.no_grad():
        avg = torch.where(denom > 0, grad_acc / denom.clamp_min(1), torch.zeros_like(grad_acc))
        big = model.scales().max(dim=1).values > cfg.percent_dense * extent
        grow = (avg >= cfg.grad_threshold) & (model.num < cfg.max_gaussians)
        clone = grow & ~big
        split = grow & big
    n0 = model.num
    model.clone(clone)
    # The clones were appended; they are not split.
    split = torch.cat([split, torch.zeros(model.num - n0, dtype=torch.bool, device=split.device)])
    model.split(split, n_split=cfg.split_count, generator=gen)
    with torch.no_grad():
        remove = model.opacities() < cfg.prune_opacity
        if prune_big:
            remove |= model.scales().max(dim=1).values > cfg.prune_big_fraction * extent
        if bool(remove.all()):
            return  # never prune everything away
    model.prune(remove)
