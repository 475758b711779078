"""``python -m holowarp.baselines.visual_hull DATASET --out DIR [--grid 128]``: the visual-hull
baseline (carve, marching cubes, fTetWild), a thin command over
:func:`holowarp.baselines.hull.run_visual_hull`."""

from __future__ import annotations

import sys
from pathlib import Path

from holowarp import cli
from holowarp.baselines.hull import VisualHullSettings, run_visual_hull

__all__ = ["main", "build_parser"]


def build_parser():
    p = cli.parser("holowarp.baselines.visual_hull",
                   "Visual-hull baseline: carve the training masks, marching cubes, fTetWild -> DIR/tetmesh.vtu")
    p.add_argument("dataset", metavar="DATASET", help="dataset folder (NeRF-synthetic, NeuS/IDR or COLMAP)")
    p.add_argument("--out", required=True, metavar="DIR", help="output folder")
    p.add_argument("--grid", type=int, default=128, help="carving nodes along the hull's longest side (default 128, >= 8)")
    p.add_argument("--res", type=int, default=None, metavar="PX", help="load the dataset at this resolution (longer side)")
    p.add_argument("--edge-length-fac", type=float, default=VisualHullSettings.edge_length_fac,
                   help="fTetWild ideal edge length / bbox diagonal, in (0, 1)")
    p.add_argument("--max-surface-faces", type=int, default=VisualHullSettings.max_surface_faces,
                   help="decimate the marching-cubes surface to this many triangles before fTetWild (>= 100)")
    cli.add_device(p)
    cli.add_quiet(p)
    return p


def _run(args) -> int:
    from holowarp.data.loaders import load_dataset

    if args.grid < 8:
        cli.fail(f"--grid {args.grid}: at least 8 carving nodes are needed")
    if not 0 < args.edge_length_fac < 1:
        cli.fail(f"--edge-length-fac {args.edge_length_fac}: must lie in (0, 1)")
    if args.max_surface_faces < 100:
        cli.fail(f"--max-surface-faces {args.max_surface_faces}: must be >= 100")

    ds = load_dataset(args.dataset, res=args.res)
    st = VisualHullSettings(grid=args.grid, edge_length_fac=args.edge_length_fac, max_surface_faces=args.max_surface_faces)
    rep = run_visual_hull(ds, args.out, settings=st, device=args.device, progress=not args.quiet)
    s = rep["summary"]
    print(
        f"visual hull: {s['tets']} tets, {s['vertices']} vertices, components {s['components']}, "
        f"manifold {s['manifold']}, genus {s['genus']}; {rep['seconds']['total']:.1f}s -> {Path(args.out) / 'tetmesh.vtu'}"
    )
    return 0


def main(argv=None) -> int:
    return cli.run(_run, build_parser().parse_args(argv))


if __name__ == "__main__":
    sys.exit(main())
