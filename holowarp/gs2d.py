"""``python -m holowarp.gs2d DATASET --out DIR``: stage 0 alone (method.md §3).

Thin command over :func:`holowarp.stages.gaussian_init.train_gs2d`: trains 2D Gaussian
surfels with the stage-0 schedule and resolution of a preset (``fast`` by default) and writes
``DIR/gaussians.ply`` (3DGS viewer layout), ``DIR/report.json``, ``DIR/test_preview.png`` and a
resumable ``DIR/checkpoint.pt``.
"""

from __future__ import annotations

import sys
from pathlib import Path

from holowarp import cli

__all__ = ["main", "build_parser"]


def build_parser():
    p = cli.parser("holowarp.gs2d", "Stage 0 (method.md §3): train 2D Gaussian surfels on a dataset folder "
                   "(NeRF-synthetic, NeuS/IDR or COLMAP). Writes DIR/gaussians.ply and DIR/report.json.")
    p.add_argument("dataset", metavar="DATASET", help="dataset folder (transforms_*.json, cameras_sphere.npz or COLMAP sparse/0 + images/ + masks/)")
    p.add_argument("--out", required=True, metavar="DIR", help="output folder")
    cli.add_preset(p, what="stage-0 iterations and image resolution")
    p.add_argument("--iters", type=int, default=None, metavar="N", help="training iterations (default: the preset's; >= 0)")
    p.add_argument("--res", type=int, default=None, metavar="PX", help="longer image side in pixels (default: the preset's; >= 16)")
    p.add_argument("--seed", type=int, default=None, help="random seed (default: the preset's)")
    p.add_argument("--resume", action="store_true", help="continue from DIR/checkpoint.pt")
    cli.add_device(p)
    cli.add_quiet(p)
    return p


def _run(args) -> int:
    import torch

    from holowarp.config import preset
    from holowarp.data import load_dataset
    from holowarp.device import resolve_device
    from holowarp.stages.gaussian_init import train_gs2d

    if args.iters is not None and args.iters < 0:
        cli.fail(f"--iters must be >= 0, got {args.iters}")
    if args.res is not None and args.res < 16:
        cli.fail(f"--res must be at least 16 pixels, got {args.res}")
    cfg = preset(args.preset)
    device = resolve_device(args.device)
    torch.set_num_threads(1)
    dataset = load_dataset(args.dataset, res=cfg.resolution if args.res is None else args.res)
    iters = cfg.schedule.stage0_iters if args.iters is None else args.iters
    seed = cfg.seed if args.seed is None else args.seed
    res = train_gs2d(dataset, cfg.stage0, args.out, iters=iters, seed=seed, device=device, resume=args.resume,
                     progress=not args.quiet)
    summary = {k: res[k] for k in ("psnr_test", "ssim_test", "gaussians", "iters", "seconds")}
    print(" ".join(f"{k}={v:.4g}" if isinstance(v, float) else f"{k}={v}" for k, v in summary.items()))
    print(f"wrote {Path(args.out) / 'gaussians.ply'} and {Path(args.out) / 'report.json'}")
    return 0


def main(argv=None) -> int:
    return cli.run(_run, build_parser().parse_args(argv))


if __name__ == "__main__":
    sys.exit(main())
