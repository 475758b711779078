"""``python -m holowarp.reconstruct [DATASET] --out DIR``: the product's main job.

Reconstructs one connected, manifold, inversion-free tet mesh with surfels bound to it from
multi-view images (method.md §3–§8); with ``--scene-level`` one such mesh per object of a
capture of several (method.md §11, :mod:`holowarp.stages.objects`). Without DATASET it synthesises the built-in default
object (bob, genus 1) and reconstructs it. See :func:`holowarp.pipeline.reconstruct`.
"""

from __future__ import annotations

import math
import sys
from dataclasses import replace

from holowarp import cli

__all__ = ["main", "build_parser", "config_from_args"]


def build_parser():
    p = cli.parser("holowarp.reconstruct",
                   "Reconstruct ONE connected, simulation-ready tet mesh (HoloTetSphere) from multi-view images.")
    p.add_argument("dataset", nargs="?", metavar="DATASET",
                   help="NeRF-synthetic (transforms_*.json), NeuS/IDR (cameras_sphere.npz) or COLMAP (sparse/0) folder; "
                        "omitted: the built-in bob, synthesised into DIR/data")  # fmt: skip
    p.add_argument("--out", required=True, metavar="DIR", help="output folder")
    cli.add_preset(p)
    p.add_argument("--resume", action="store_true", help="continue from DIR/checkpoints/state.pt")
    p.add_argument("--no-continuous-opacity", action="store_true",
                   help="ablation: one free opacity per tet instead of the vertex field")
    p.add_argument("--uniform-biharmonic", action="store_true", help="ablation: bi-harmonic weight 1 everywhere")
    p.add_argument("--single-stage-hc", action="store_true", help="ablation: HC-Laplacian with lam_cond = 1 throughout")
    p.add_argument("--res", type=int, default=None, metavar="PX", help="override the preset's image resolution (>= 16)")
    p.add_argument("--scale-iters", type=float, default=None, metavar="F",
                   help="multiply every iteration count of the preset by F (> 0)")
    p.add_argument("--edge-length", type=float, default=None, metavar="FAC",
                   help="fTetWild edge length / bbox diagonal, in (0, 1) (the resolution knob)")
    p.add_argument("--refine", choices=("off", "band", "silhouette"), default=None,
                   help="after the last prune, bisect the tets next to the surface so the last mesh block works finer: "
                        "all of them (band) or those that reach outside the masks' visual hull (silhouette); "
                        "default: the preset's (fast: band at 0.85, paper: off)")
    p.add_argument("--refine-factor", type=float, default=None, metavar="F",
                   help="with --refine: bisect until the longest edge is F x the marked tets' median, in (0, 1]")
    p.add_argument("--seed", type=int, default=None, help="random seed (default: the preset's)")
    p.add_argument("--test-every", type=int, default=None, metavar="N",
                   help="without a test split in the dataset, hold out every N-th view for the test metrics (default 10)")
    p.add_argument("--no-improve", action="store_true",
                   help="skip the element improvement after cleanup (method.md §7b; the paper's pipeline ends at cleanup)")
    p.add_argument("--no-polish", action="store_true",
                   help="skip the silhouette polish of the final mesh (holowarp.stages.polish)")
    p.add_argument("--scene-level", action="store_true",
                   help="several objects in one capture (method.md §11): keep every component above --min-component, "
                        "split the result into objects and write DIR/objects/NAME/tetmesh.vtu, a multi-body "
                        "DIR/scene.usda and DIR/scene.toml for holowarp.simulate")
    p.add_argument("--min-component", type=float, default=None, metavar="F",
                   help="with --scene-level: keep components with at least this fraction of the kept tets, in (0, 1] "
                        "(default 0.02)")
    p.add_argument("--objects", type=int, default=None, metavar="N",
                   help="with --scene-level: the capture holds N objects (default: the dataset's objects/ folders, "
                        "else one per component); touching objects are split by clustering")
    p.add_argument("--object-size", type=float, default=None, metavar="S",
                   help="with --scene-level: largest side of the largest object in the capture's frame units; the "
                        "length-valued settings are scaled to it (default: measured from the masks' visual hull)")
    cli.add_device(p)
    cli.add_quiet(p)
    return p


def config_from_args(args):
    """The :class:`holowarp.config.ReconConfig` the arguments ask for."""
    from holowarp.config import preset

    cfg = preset(args.preset).with_ablations(
        continuous_opacity=not args.no_continuous_opacity,
        uniform_biharmonic=args.uniform_biharmonic,
        single_stage_hc=args.single_stage_hc,
    )
    if args.res is not None:
        if args.res < 16:
            cli.fail(f"--res {args.res}: at least 16 pixels")
        cfg = replace(cfg, resolution=args.res)
    if args.scale_iters is not None:
        if not args.scale_iters > 0:
            cli.fail(f"--scale-iters {args.scale_iters}: must be > 0")
        cfg = cfg.scaled(args.scale_iters)
    if args.edge_length is not None:
        if not 0 < args.edge_length < 1:
            cli.fail(f"--edge-length {args.edge_length}: must lie in (0, 1)")
        cfg = replace(cfg, tet_init=replace(cfg.tet_init, edge_length_fac=args.edge_length))
    if args.refine_factor is not None and not 0 < args.refine_factor <= 1:
        cli.fail(f"--refine-factor {args.refine_factor}: must lie in (0, 1]")
    if args.refine is not None or args.refine_factor is not None:
        topo = cfg.topology
        if args.refine == "off":
            if args.refine_factor is not None:
                cli.fail("--refine-factor: not with --refine off")
            topo = replace(topo, refine_rings=0)
        else:
            if args.refine is not None:
                topo = replace(topo, refine_where=args.refine, refine_rings=max(topo.refine_rings, 1),
                               refine_at_prune=len(cfg.schedule.prune_at) - 1)
            elif topo.refine_rings == 0:
                cli.fail("--refine-factor: the preset does not refine; add --refine band or --refine silhouette")
            if args.refine_factor is not None:
                topo = replace(topo, refine_factor=args.refine_factor)
        cfg = replace(cfg, topology=topo)
    if args.seed is not None:
        cfg = replace(cfg, seed=args.seed)
    if args.test_every is not None:
        if args.test_every < 1:
            cli.fail(f"--test-every {args.test_every}: must be >= 1")
        cfg = replace(cfg, test_every=args.test_every)
    if args.no_improve:
        cfg = replace(cfg, improve=replace(cfg.improve, enabled=False))
    if args.no_polish:
        cfg = replace(cfg, polish=replace(cfg.polish, enabled=False))
    if not args.scene_level:
        for flag, v in (("--min-component", args.min_component), ("--objects", args.objects),
                        ("--object-size", args.object_size)):
            if v is not None:
                cli.fail(f"{flag}: only with --scene-level")
    else:
        if args.min_component is not None and not 0 < args.min_component <= 1:
            cli.fail(f"--min-component {args.min_component}: must lie in (0, 1]")
        if args.objects is not None and args.objects < 1:
            cli.fail(f"--objects {args.objects}: must be >= 1")
        if args.object_size is not None and not (math.isfinite(args.object_size) and args.object_size > 0):
            cli.fail(f"--object-size {args.object_size}: must be a finite number > 0")
        cfg = cfg.scene_level(min_component=args.min_component, objects=args.objects)
        if args.object_size is not None:
            cfg = replace(cfg, scene=replace(cfg.scene, object_size=args.object_size))
    return cfg


def _run(args) -> int:
    from holowarp.pipeline import reconstruct

    cfg = config_from_args(args)
    report = reconstruct(args.dataset, args.out, config=cfg, device=args.device, resume=args.resume,
                         progress=not args.quiet)
    m = report.get("metrics") or {}
    print(
        f"wrote {args.out}: {report['tets_final']} tets, {report['components']} component(s), "
        f"manifold={report['manifold']}, genus={report['genus']}, inverted={report['inverted_ratio']:.4f}, "
        + (f"overlapping edges={report['overlapping_edges']}, " if report.get("overlapping_edges") else "")
        + f"PSNR {report['psnr_test']:.2f} dB, {report['seconds_total']:.0f} s"
        + (f", chamfer_l1 {m['chamfer_l1']:.4f}, volume_iou {m['volume_iou']:.3f}" if m else "")
    )
    for o in (report.get("scene") or {}).get("objects", []):
        om = o.get("metrics") or {}
        print(f"  object {o['name']}: {o['tets']} tets, {o['components']} component(s), manifold={o['manifold']}, "
              f"genus={o['genus']}, inverted={o['inverted']}"
              + (f", chamfer_l1 {om['chamfer_l1']:.4f}" if om else ""))
    if report.get("improve"):
        from holowarp.stages.improve import missed_targets

        for line in missed_targets(report["improve"]):
            print(f"warning: element improvement: {line}", file=sys.stderr)
    if report.get("scene"):
        print(f"simulate the scene: python -m holowarp.simulate {args.out}/tetmesh.vtu --scene "
              f"{report['outputs']['scene_toml']} --out SIM")
    return 0


def main(argv=None) -> int:
    return cli.run(_run, build_parser().parse_args(argv))


if __name__ == "__main__":
    sys.exit(main())
