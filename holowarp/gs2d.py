"""Stage 0 (method.md §3): train 2D Gaussian surfels (2DGS) on a multi-view dataset.

API: :func:`train_gs2d` with a :class:`GS2DConfig`; command line::

    python -m holowarp.gs2d DATASET --out DIR [--iters N] [--res R] [--device cpu|cuda] [--resume]

Per iteration one random training view is rendered with the Warp surfel rasteriser and the
loss is (method.md §3, 2DGS)

    (1 - 0.2) L1 + 0.2 (1 - SSIM)                         on RGB composited on ``background``
    + mask_weight     |alpha - mask|
    + normal_weight   (1 - <n_rendered, n_depth * alpha>)  2DGS normal consistency, from normal_from
    + dist_weight     distortion                           2DGS depth distortion, from dist_from

with the adaptive density control of 3DGS/2DGS: surfels with a large mean screen-space
gradient are cloned (small) or split in two (large), low-opacity ones pruned, opacities reset
periodically. Surfels start inside the visual hull of the training masks.

Outputs in ``DIR``: ``gaussians.ply`` (3DGS layout, see :mod:`holowarp.gaussians`; the centres
are the point cloud stage 1 starts from), ``report.json`` (``psnr_test``, ``ssim_test``,
``gaussians``, ``iters``, ``seconds`` and more), ``test_preview.png`` (ground truth over render of
the first test view) and ``checkpoint.pt`` (written atomically every ``checkpoint_every``
iterations; ``resume=True`` / ``--resume`` continues from it).
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import sys
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch

from holowarp.camera import axes_focus
from holowarp.data.dataset import Dataset, DatasetError
from holowarp.device import DeviceError, resolve_device
from holowarp.fileio import atomic_path, atomic_write_json
from holowarp.gaussians import GaussianModel
from holowarp.losses import (
    LAMBDA_DSSIM,
    depth_to_normal,
    distortion_loss,
    l1_dssim_loss,
    mask_loss,
    normal_consistency_loss,
    psnr,
    ssim,
)

__all__ = ["GS2DConfig", "train_gs2d", "init_points_from_masks", "evaluate_views", "main"]

#: Iteration count of the paper's stage 0 (method.md §3, §8).
PAPER_ITERS = 10_000
#: Fields of GS2DConfig that count iterations; :meth:`GS2DConfig.for_iterations` scales them.
_ITER_FIELDS = ("normal_from", "dist_from", "densify_from", "densify_until", "opacity_reset_interval",
                "checkpoint_every")  # fmt: skip


@dataclass
class GS2DConfig:
    """Every number of stage 0. Defaults are the CPU preset (3000 iterations, sized so spot at
    128^2 trains in a few minutes); :meth:`paper` is the paper's 10k-iteration, 512^2 preset and
    :meth:`for_iterations` rescales every iteration count to another length.

    Attributes:
        iters: training iterations (one view each).
        resolution: resize images so the longer side has this many pixels (None: as loaded).
        background: colour the images are composited on, and rendered over (RGB in [0, 1]).
        seed: seeds view order, initialisation and splits.
        init_points: surfels sampled inside the masks' visual hull at the start.
        init_candidates: uniform samples tested against the masks to find them.
        init_opacity: initial opacity (3DGS: 0.1).
        lr_means, lr_means_final: position learning rate, times the scene extent, decayed
            exponentially from the first to the second over training (3DGS).
        lr_scales, lr_quats, lr_opacity, lr_colors: Adam learning rates (3DGS/2DGS values).
        dssim_weight: lambda_DSSIM of the photometric loss (method.md §3: 0.2).
        mask_weight: weight of |alpha - mask|.
        normal_weight, normal_from: 2DGS normal consistency weight and first iteration.
        dist_weight, dist_from: 2DGS depth-distortion weight (on camera depth, metres^2) and
            first iteration.
        densify_from, densify_until, densify_interval: when clone/split/prune run.
        opacity_reset_interval: opacities are reset to ``reset_opacity`` this often while
            densifying.
        reset_opacity: opacity after a reset.
        grad_threshold: mean screen-space gradient (in NDC units, i.e. pixel gradient times
            half the image size, as 3DGS) above which a surfel is cloned or split.
        percent_dense: surfels larger than this fraction of the scene extent are split, smaller
            ones cloned.
        prune_opacity: surfels below this opacity are removed at each densification.
        prune_big_fraction: after the first reset, surfels larger than this fraction of the
            scene extent are removed.
        max_gaussians: no clone/split beyond this many surfels.
        checkpoint_every: iterations between checkpoints.
    """

    iters: int = 3000
    resolution: int | None = None
    background: tuple[float, float, float] = (0.0, 0.0, 0.0)
    seed: int = 0
    init_points: int = 4000
    init_candidates: int = 200_000
    init_opacity: float = 0.1
    lr_means: float = 1.6e-4
    lr_means_final: float = 1.6e-6
    lr_scales: float = 5e-3
    lr_quats: float = 1e-3
    lr_opacity: float = 0.05
    lr_colors: float = 2.5e-3
    dssim_weight: float = LAMBDA_DSSIM
    mask_weight: float = 0.1
    normal_weight: float = 0.05
    normal_from: int = 1000
    dist_weight: float = 0.0
    dist_from: int = 1000
    densify_from: int = 100
    densify_until: int = 1800
    densify_interval: int = 100
    opacity_reset_interval: int = 900
    reset_opacity: float = 0.01
    grad_threshold: float = 2e-4
    percent_dense: float = 0.01
    prune_opacity: float = 0.05
    prune_big_fraction: float = 0.1
    max_gaussians: int = 300_000
    checkpoint_every: int = 500

    @classmethod
    def for_iterations(cls, iters: int, **overrides) -> "GS2DConfig":
        """The default schedule stretched to ``iters`` iterations (same order of events).

        ``densify_interval`` is not stretched: it is the number of views the gradient
        statistics average over, and the time a reset opacity has to recover before the next
        prune. The reset interval stays a multiple of it.
        """
        base = cls()
        f = iters / base.iters
        scaled = {k: max(1, int(round(getattr(base, k) * f))) for k in _ITER_FIELDS}
        di = base.densify_interval
        scaled["opacity_reset_interval"] = max(di, di * int(round(scaled["opacity_reset_interval"] / di)))
        scaled.update(overrides)
        return dataclasses.replace(base, iters=int(iters), **scaled)

    @classmethod
    def paper(cls, **overrides) -> "GS2DConfig":
        """The paper's stage 0: 10k iterations at 512^2 (method.md §3, §8)."""
        return cls.for_iterations(PAPER_ITERS, resolution=512, **overrides)

    def validate(self):
        if self.iters < 0:
            raise ValueError(f"GS2DConfig.iters must be >= 0, got {self.iters}")
        if self.resolution is not None and self.resolution < 16:
            raise ValueError(f"GS2DConfig.resolution must be >= 16 pixels, got {self.resolution}")
        if len(self.background) != 3:
            raise ValueError(f"GS2DConfig.background must be RGB, got {self.background}")


# ----------------------------------------------------------------------------- initialisation


def _camera_centres(viewmats: np.ndarray) -> np.ndarray:
    R = viewmats[:, :3, :3]
    t = viewmats[:, :3, 3]
    return -np.einsum("nji,nj->ni", R, t)


def _view_volume(dataset: Dataset, idx) -> tuple[np.ndarray, float]:
    """Centre (3,) and radius of a sphere every camera in ``idx`` sees whole: the point
    nearest to all optical axes, and the largest radius inside the narrowest field of view."""
    V = dataset.viewmats[idx]
    o = _camera_centres(V)
    c = axes_focus(V)
    K = dataset.K[idx]
    half = np.minimum.reduce([
        np.arctan(K[:, 0, 2] / K[:, 0, 0]), np.arctan((dataset.width - K[:, 0, 2]) / K[:, 0, 0]),
        np.arctan(K[:, 1, 2] / K[:, 1, 1]), np.arctan((dataset.height - K[:, 1, 2]) / K[:, 1, 1]),
    ])  # fmt: skip
    r = float(np.min(np.linalg.norm(o - c, axis=1) * np.sin(half)))
    return c, r


def init_points_from_masks(dataset: Dataset, n_points: int, *, candidates: int = 200_000, seed: int = 0):
    """Points inside the visual hull of the training masks, with colours from the images.

    Uniform samples in the cube around the volume all training cameras see are kept if
    every training view that sees them has mask >= 0.5 there. Each kept point takes the
    mean colour of up to 16 views that see it.

    Returns:
        points (P, 3) float64, colours (P, 3) float64, and the sampling radius.
    """
    rng = np.random.default_rng(seed)
    idx = np.asarray(dataset.train_idx if len(dataset.train_idx) else np.arange(dataset.num_views))
    c, r = _view_volume(dataset, idx)
    pts = c + rng.uniform(-r, r, (candidates, 3))
    alive = np.arange(candidates)  # candidates not carved away yet (shrinks view by view)
    seen = np.zeros(candidates, dtype=np.int64)
    h, w = dataset.height, dataset.width
    for i in idx:
        V, K = dataset.viewmats[i], dataset.K[i]
        pc = pts[alive] @ V[:3, :3].T + V[:3, 3]
        z = pc[:, 2]
        uv = (pc[:, :2] / np.maximum(z, 1e-9)[:, None]) @ K[:2, :2].T + K[:2, 2]
        col = np.floor(uv[:, 0]).astype(np.int64)
        row = np.floor(uv[:, 1]).astype(np.int64)
        vis = (z > 1e-6) & (col >= 0) & (col < w) & (row >= 0) & (row < h)
        m = np.zeros(len(alive))
        m[vis] = dataset.masks[i][row[vis], col[vis]]
        seen[alive] += vis
        alive = alive[~vis | (m >= 0.5)]
    inside = np.zeros(candidates, dtype=bool)
    inside[alive] = True
    keep = inside & (seen > 0)
    if keep.sum() < max(16, n_points // 50):
        # Masks carved (almost) everything: fall back to the whole view volume.
        keep = np.linalg.norm(pts - c, axis=1) <= r
    pts = pts[keep]
    if len(pts) > n_points:
        pts = pts[rng.choice(len(pts), n_points, replace=False)]
    colors = np.zeros((len(pts), 3))
    counts = np.zeros(len(pts))
    for i in rng.permutation(idx)[:16]:
        V, K = dataset.viewmats[i], dataset.K[i]
        pc = pts @ V[:3, :3].T + V[:3, 3]
        uv = (pc[:, :2] / np.maximum(pc[:, 2], 1e-9)[:, None]) @ K[:2, :2].T + K[:2, 2]
        col = np.floor(uv[:, 0]).astype(np.int64)
        row = np.floor(uv[:, 1]).astype(np.int64)
        vis = (pc[:, 2] > 1e-6) & (col >= 0) & (col < w) & (row >= 0) & (row < h)
        colors[vis] += dataset.images[i][row[vis], col[vis]]
        counts += vis
    colors = np.where(counts[:, None] > 0, colors / np.maximum(counts, 1)[:, None], 0.5)
    return pts, colors, r


def _scene_extent(dataset: Dataset) -> float:
    """3DGS's scene scale: 1.1 x the largest distance of a camera from the cameras' mean."""
    o = _camera_centres(dataset.viewmats)
    return 1.1 * float(np.max(np.linalg.norm(o - o.mean(0), axis=1)))


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
        ps.append(float(psnr(rgb, gt)))
        ss.append(float(ssim(rgb, gt)))
        renders.append(rgb.cpu().numpy())
    return {"psnr": float(np.mean(ps)), "ssim": float(np.mean(ss)), "renders": renders, "psnr_views": ps}


def _write_preview(path: Path, gt: np.ndarray, render: np.ndarray):
    from PIL import Image

    img = np.concatenate([gt, render], axis=1)
    with atomic_path(path) as tmp:
        Image.fromarray((np.clip(img, 0, 1) * 255 + 0.5).astype(np.uint8)).save(tmp, format="PNG")


# ----------------------------------------------------------------------------- training


def _lrs(cfg: GS2DConfig, extent: float) -> dict:
    return {
        "means": cfg.lr_means * extent,
        "log_scales": cfg.lr_scales,
        "quats": cfg.lr_quats,
        "opacity_logits": cfg.lr_opacity,
        "sh_dc": cfg.lr_colors,
    }


def _means_lr(cfg: GS2DConfig, extent: float, it: int) -> float:
    t = min(max(it / max(cfg.iters, 1), 0.0), 1.0)
    return extent * math.exp((1 - t) * math.log(cfg.lr_means) + t * math.log(cfg.lr_means_final))


def train_gs2d(
    dataset: Dataset,
    config: GS2DConfig | None = None,
    out_dir=".",
    *,
    device: str = "cpu",
    resume: bool = False,
    progress: bool = True,
) -> dict:
    """Train stage 0 and write its outputs to ``out_dir`` (see module docstring).

    Args:
        dataset: the views; ``config.resolution`` resizes them first.
        config: all settings (:class:`GS2DConfig()` if None).
        out_dir: output folder (created).
        device: ``"cpu"`` or ``"cuda[:N]"``.
        resume: continue from ``out_dir/checkpoint.pt`` if it exists (else start fresh).
        progress: show a tqdm bar with the loss and the number of surfels.

    Returns:
        the report dict written to ``report.json`` plus ``model`` (the trained
        :class:`GaussianModel`) and ``out_dir``.
    """
    from tqdm import tqdm

    cfg = config or GS2DConfig()
    cfg.validate()
    dev = resolve_device(device)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    if cfg.resolution is not None:
        dataset = dataset.resized(cfg.resolution)
    train_idx = np.asarray(dataset.train_idx if len(dataset.train_idx) else np.arange(dataset.num_views))
    if len(train_idx) == 0:
        raise DatasetError(f"{dataset.name}: no views to train on")
    W, H = dataset.width, dataset.height
    extent = _scene_extent(dataset)
    lrs = _lrs(cfg, extent)
    bg = torch.tensor(cfg.background, dtype=torch.float32, device=dev)
    targets = torch.from_numpy(np.ascontiguousarray(dataset.composite(cfg.background), dtype=np.float32)).to(dev)
    masks = torch.from_numpy(np.ascontiguousarray(dataset.masks, dtype=np.float32)).to(dev)
    Ks = torch.from_numpy(dataset.K).double()
    Vs = torch.from_numpy(dataset.viewmats).double()

    ckpt_path = out / "checkpoint.pt"
    rng = np.random.default_rng(cfg.seed)
    gen = torch.Generator().manual_seed(cfg.seed)
    grad_acc = denom = None
    order: list[int] = []  # views left in the current pass over the training set
    start, elapsed, last_loss = 0, 0.0, float("nan")
    model = None
    if resume and ckpt_path.is_file():
        ck = torch.load(ckpt_path, map_location="cpu", weights_only=False)
        if (ck["width"], ck["height"]) != (W, H):
            raise ValueError(
                f"{ckpt_path}: checkpoint was trained at {ck['width']}x{ck['height']}, the dataset is now {W}x{H}; "
                "use the same --res or start without --resume"
            )
        model = GaussianModel(*(ck["model"][n] for n in ("means", "log_scales", "quats", "opacity_logits", "sh_dc")),
                              device=dev)  # fmt: skip
        model.load_state_dict(ck["model"], lrs)
        start, elapsed, last_loss = int(ck["iteration"]), float(ck["seconds"]), float(ck.get("loss", float("nan")))
        rng.bit_generator.state = ck["numpy_rng"]
        gen.set_state(ck["torch_rng"])
        grad_acc, denom = ck["grad_acc"].to(dev), ck["denom"].to(dev)
        order = [int(v) for v in ck["view_order"]]
        if progress:
            tqdm.write(f"gs2d: resuming {ckpt_path} at iteration {start}")
    if model is None:
        pts, cols, _ = init_points_from_masks(dataset, cfg.init_points, candidates=cfg.init_candidates, seed=cfg.seed)
        model = GaussianModel.from_points(pts, cols, opacity=cfg.init_opacity, seed=cfg.seed, device=dev)
        model.setup_optimizer(lrs)
    if grad_acc is None:
        grad_acc = torch.zeros(model.num, device=dev)
        denom = torch.zeros(model.num, device=dev)

    def save_checkpoint(it: int, seconds: float):
        state = {
            "iteration": it,
            "seconds": seconds,
            "loss": last_loss,
            "model": model.state_dict(),
            "numpy_rng": rng.bit_generator.state,
            "torch_rng": gen.get_state(),
            "view_order": list(order),
            "grad_acc": grad_acc.cpu(),
            "denom": denom.cpu(),
            "width": W,
            "height": H,
            "config": asdict(cfg),
        }
        with atomic_path(ckpt_path) as tmp:
            torch.save(state, tmp)

    t0 = time.perf_counter()
    bar = tqdm(total=cfg.iters, initial=min(start, cfg.iters), disable=not progress, desc="gs2d", unit="it",
               dynamic_ncols=True)  # fmt: skip
    for it in range(start, cfg.iters):
        if not order:
            order = list(rng.permutation(train_idx))
        i = int(order.pop())
        model.set_lr("means", _means_lr(cfg, extent, it))
        o = model.render(Vs[i], Ks[i], W, H, background=bg)
        loss = l1_dssim_loss(o["rgb"], targets[i], lambda_dssim=cfg.dssim_weight)
        if cfg.mask_weight > 0:
            loss = loss + cfg.mask_weight * mask_loss(o["alpha"], masks[i])
        if cfg.normal_weight > 0 and it >= cfg.normal_from:
            alpha = o["alpha"]
            depth = o["depth"] / alpha.clamp_min(1e-6)
            surf = depth_to_normal(depth, Ks[i].to(dev), Vs[i].to(dev)) * alpha.detach()[..., None]
            loss = loss + cfg.normal_weight * normal_consistency_loss(o["normal"], surf)
        if cfg.dist_weight > 0 and it >= cfg.dist_from:
            loss = loss + cfg.dist_weight * distortion_loss(o["distortion"])
        loss.backward()
        with torch.no_grad():
            if it < cfg.densify_until:
                vis = o["visible"]
                g2 = o["means2d"].grad
                if g2 is not None:
                    gn = torch.stack([g2[:, 0] * (W / 2), g2[:, 1] * (H / 2)], -1).norm(dim=-1)
                    grad_acc += gn * vis
                    denom += vis
        model.step()
        last_loss = float(loss.detach())
        step = it + 1
        if cfg.densify_from <= step < cfg.densify_until and step % cfg.densify_interval == 0:
            _densify(model, grad_acc, denom, cfg, extent, gen, prune_big=step > cfg.opacity_reset_interval)
            grad_acc = torch.zeros(model.num, device=dev)
            denom = torch.zeros(model.num, device=dev)
        if step < cfg.densify_until and step % cfg.opacity_reset_interval == 0:
            model.reset_opacity(cfg.reset_opacity)
        if step % 10 == 0 or step == cfg.iters:
            bar.set_postfix(loss=f"{last_loss:.4f}", gaussians=model.num, refresh=False)
        bar.update(1)
        if step % cfg.checkpoint_every == 0 and step < cfg.iters:
            save_checkpoint(step, elapsed + time.perf_counter() - t0)
    bar.close()
    seconds_train = elapsed + time.perf_counter() - t0
    if cfg.iters > start:
        save_checkpoint(cfg.iters, seconds_train)

    t_eval = time.perf_counter()
    model.save_ply(out / "gaussians.ply")
    test_idx = np.asarray(dataset.test_idx)
    eval_on = "test" if len(test_idx) else "train"
    ev = evaluate_views(model, dataset, test_idx if len(test_idx) else train_idx, background=cfg.background,
                        device=dev)  # fmt: skip
    first = int(test_idx[0] if len(test_idx) else train_idx[0])
    _write_preview(out / "test_preview.png", dataset.composite(cfg.background)[first], ev["renders"][0])
    seconds = seconds_train + (time.perf_counter() - t_eval)
    report = {
        "psnr_test": ev["psnr"],
        "ssim_test": ev["ssim"],
        "gaussians": model.num,
        "iters": cfg.iters,
        "seconds": seconds,
        "seconds_train": seconds_train,
        "eval_views": eval_on,
        "num_eval_views": len(ev["psnr_views"]),
        "resolution": [W, H],
        "device": dev,
        "dataset": str(dataset.root) if dataset.root else dataset.name,
        "final_loss": last_loss,
        "config": asdict(cfg),
    }
    atomic_write_json(out / "report.json", report)
    return {**report, "model": model, "out_dir": str(out)}


def _densify(model: GaussianModel, grad_acc, denom, cfg: GS2DConfig, extent: float, gen, *, prune_big: bool):
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
    model.split(split, generator=gen)
    with torch.no_grad():
        remove = model.opacities() < cfg.prune_opacity
        if prune_big:
            remove |= model.scales().max(dim=1).values > cfg.prune_big_fraction * extent
        if bool(remove.all()):
            return  # never prune everything away
    model.prune(remove)


# ----------------------------------------------------------------------------- command line


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="python -m holowarp.gs2d",
        description="Stage 0 (method.md §3): train 2D Gaussian surfels on a dataset folder "
        "(NeRF-synthetic or NeuS/IDR). Writes DIR/gaussians.ply and DIR/report.json.",
    )
    p.add_argument("dataset", help="dataset folder")
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--iters", type=int, default=None, help="training iterations (default: preset's)")
    p.add_argument("--res", type=int, default=None, help="resize the longer image side to R pixels")
    p.add_argument("--device", default="cpu", help="cpu, cuda or cuda:N (default cpu)")
    p.add_argument("--preset", choices=("cpu", "paper"), default="cpu",
                   help="cpu: 3000 iterations (default); paper: 10k iterations at 512^2")  # fmt: skip
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--resume", action="store_true", help="continue from DIR/checkpoint.pt")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.add_argument("--threads", type=int, default=1,
                   help="torch CPU threads (default 1: the per-view tensors are small and Warp's CPU "
                        "kernels are serial, so more threads mostly add synchronisation)")  # fmt: skip
    return p


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    from holowarp.data import load_dataset

    try:
        if args.threads < 1:
            raise ValueError(f"--threads must be >= 1, got {args.threads}")
        torch.set_num_threads(args.threads)
        device = resolve_device(args.device)
        iters = args.iters if args.iters is not None else (PAPER_ITERS if args.preset == "paper" else GS2DConfig().iters)
        if iters < 0:
            raise ValueError(f"--iters must be >= 0, got {iters}")
        over = {"seed": args.seed}
        if args.preset == "paper":
            over["resolution"] = 512
        cfg = GS2DConfig.for_iterations(iters, **over)
        if args.res is not None:
            if args.res < 16:
                raise ValueError(f"--res must be at least 16 pixels, got {args.res}")
            cfg.resolution = None  # the loader resizes
        dataset = load_dataset(args.dataset, res=args.res)
        res = train_gs2d(dataset, cfg, args.out, device=device, resume=args.resume, progress=not args.no_progress)
    except (DatasetError, DeviceError, ValueError, OSError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    summary = {k: res[k] for k in ("psnr_test", "ssim_test", "gaussians", "iters", "seconds")}
    print(" ".join(f"{k}={v:.4g}" if isinstance(v, float) else f"{k}={v}" for k, v in summary.items()))
    print(f"wrote {Path(args.out) / 'gaussians.ply'} and {Path(args.out) / 'report.json'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
