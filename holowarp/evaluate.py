"""``python -m holowarp.evaluate PRED --gt GT [--dataset DIR] --json OUT``: method.md §9 metrics.

Thin command over :func:`holowarp.metrics.evaluate_mesh`. PRED is any tet-mesh file
(``.vtu``, ``.msh``, ``.npz``, ``.usd[a|c]``); GT a surface (``gt.obj`` of a synthesised
dataset) or tet mesh. Both are put in the evaluation frame by the GT's bounding box. With
``--dataset`` the prediction's boundary is also rendered at the test views and ``psnr_mask``
(silhouette agreement) is added. The JSON's top level holds exactly the metric keys; the
table printed on stdout also gives the LPIPS note (unavailable and why) and timings.
"""

from __future__ import annotations

import math
import sys

from holowarp import cli

__all__ = ["main", "build_parser", "format_table"]

_ROWS = [
    ("chamfer_l1", "Chamfer-L1", "lower is better"),
    ("chamfer_l1_floor", "Chamfer-L1 floor", "GT against itself: a perfect score"),
    ("concave_chamfer", "concave Chamfer", "GT regions silhouettes cannot see; nan if convex"),
    ("chamfer_l2", "Chamfer-L2", "lower is better"),
    ("hausdorff", "Hausdorff", "lower is better"),
    ("precision", "precision @0.01", ""),
    ("recall", "recall @0.01", ""),
    ("f_score", "F-score @0.01", ""),
    ("f_score_005", "F-score @0.005", ""),
    ("precision_005", "precision @0.005", "prediction near GT"),
    ("recall_005", "recall @0.005", "GT near prediction"),
    ("normal_consistency", "normal consistency", ""),
    ("volume_iou", "volume IoU", ""),
    ("edge_precision", "edge precision @0.005", "NMC edge samples"),
    ("edge_recall", "edge recall @0.005", ""),
    ("edge_f1", "edge F1", ""),
    ("components", "components", "face-connected"),
    ("manifold", "manifold", "boundary"),
    ("genus", "genus", "boundary"),
    ("boundary_shells", "boundary shells", "1 = no sealed void"),
    ("overlapping_edges", "overlapping edges", "0 = no self-overlap"),
    ("tets", "tets", ""),
    ("inverted_ratio", "inverted ratio", "signed volume <= 0"),
    ("min_dihedral_mean", "min dihedral mean", "degrees"),
    ("min_dihedral_worst", "min dihedral worst", "degrees"),
    ("aspect_ratio_mean", "aspect ratio mean", "1 = regular"),
    ("psnr_mask", "PSNR mask", "dB, test-view silhouettes"),
]


def _fmt(v) -> str:
    if v is None:
        return "n/a"
    if isinstance(v, bool):
        return "yes" if v else "no"
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        if math.isnan(v):
            return "nan (undefined)"
        if math.isinf(v):
            return "inf"
        return f"{v:.6g}" if abs(v) >= 1e-3 or v == 0 else f"{v:.4e}"
    return str(v)


def format_table(metrics: dict, info: dict | None = None, *, title: str = "") -> str:
    """A readable, aligned table of ``metrics`` (+ LPIPS note and timing from ``info``)."""
    lines = [title] if title else []
    w = max(len(label) for _, label, _ in _ROWS)
    for key, label, note in _ROWS:
        if key not in metrics:
            continue
        val = _fmt(metrics[key])
        lines.append(f"  {label:<{w}}  {val:>16}" + (f"   ({note})" if note else ""))
    if info is not None:
        lp = info.get("lpips", {})
        lines.append(f"  {'LPIPS':<{w}}  {'unavailable' if not lp.get('available') else 'not computed':>16}   ({lp.get('reason', '')}; {lp.get('note', '')})")
        sec = info.get("seconds", {})
        if sec:
            lines.append(f"  {'time':<{w}}  {sec.get('total', 0.0):>15.2f}s")
    return "\n".join(lines)


def build_parser():
    p = cli.parser("holowarp.evaluate", "Evaluate a reconstructed tet mesh against the ground truth (method.md §9).")
    p.add_argument("pred", metavar="PRED", help="predicted tet mesh (.vtu, .msh, .npz, .usd[a|c]) or surface")
    p.add_argument("--gt", metavar="GT", help="ground-truth surface (.obj, .off, .stl, .ply, .glb) or tet mesh; "
                   "default: DIR/gt.obj of --dataset")
    p.add_argument("--dataset", metavar="DIR", help="dataset folder: adds psnr_mask over its test views")
    p.add_argument("--res", type=int, default=None, metavar="PX", help="load the dataset at this resolution (longer side)")
    p.add_argument("--json", metavar="OUT", help="write the metrics JSON here (atomically)")
    p.add_argument("--details", metavar="OUT", help="also write non-contract details (timings, LPIPS note, counts)")
    p.add_argument("--error-map", metavar="DIR",
                   help="write pred_error.ply, gt_missing.ply and error_views.png (distances on a fixed colour scale)")
    p.add_argument("--samples", type=int, default=100_000, metavar="N", help="surface samples per mesh (default 100000, >= 1)")
    p.add_argument("--volume-points", type=int, default=100_000, metavar="N",
                   help="uniform points for volume IoU (default 100000, >= 1)")
    p.add_argument("--seed", type=int, default=0, help="sampling seed (default 0)")
    cli.add_device(p)
    cli.add_quiet(p)
    return p


def _run(args) -> int:
    from pathlib import Path

    from holowarp.fileio import atomic_write_json
    from holowarp.metrics import EvaluationError, evaluate_mesh

    from holowarp.fileio import check_output_file

    if args.samples < 1:
        cli.fail(f"--samples must be >= 1, got {args.samples}")
    for flag, path in (("--json", args.json), ("--details", args.details)):
        if path is not None:
            check_output_file(path, what=flag)
    if args.error_map is not None:
        from holowarp.fileio import check_output_dir

        check_output_dir(args.error_map, what="--error-map")
    if args.volume_points < 1:
        cli.fail(f"--volume-points must be >= 1, got {args.volume_points}")
    dataset = None
    if args.dataset:
        from holowarp.data.loaders import load_dataset

        dataset = load_dataset(args.dataset, res=args.res)
    gt = args.gt
    if gt is None:
        if dataset is None or dataset.gt_mesh is None:
            raise EvaluationError("--gt is required (no --dataset with a gt.obj was given)")
        gt = dataset.gt_mesh
    if not Path(args.pred).is_file():
        raise EvaluationError(f"{args.pred}: no such prediction file")
    metrics, info = evaluate_mesh(args.pred, gt, dataset=dataset, num_samples=args.samples,
                                  volume_points=args.volume_points, seed=args.seed, device=args.device, details=True)
    print(format_table(metrics, info, title=f"{args.pred} vs {gt}"))
    if args.json:
        atomic_write_json(args.json, metrics)
        print(f"wrote {args.json}")
    if args.details:
        atomic_write_json(args.details, info)
    if args.error_map:
        from holowarp.metrics.evaluate import evaluation_surfaces
        from holowarp.previews import ERROR_CMAP, ERROR_SCALE, write_error_maps

        maps = write_error_maps(args.error_map, *evaluation_surfaces(args.pred, gt), device=args.device)
        print(f"wrote error maps to {args.error_map} (colour scale {ERROR_CMAP}: 0 dark .. {ERROR_SCALE} bright, "
              "evaluation units; the object's largest side is 1)")
    return 0


def main(argv=None) -> int:
    return cli.run(_run, build_parser().parse_args(argv))


if __name__ == "__main__":
    sys.exit(main())
