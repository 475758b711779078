"""``python -m holowarp.simulate MESH --scene drop|compress|PATH.toml --out DIR``.

Simulates a tet mesh with holowarp's Vertex Block Descent stable Neo-Hookean solver
(method.md §10) and writes ``DIR/sim.usda`` (animated at 60 fps, Z up, metres) and
``DIR/report.json``. With ``--reference GT_MESH`` the reference is simulated in the same
scene and the report gains ``sim_chamfer``; with ``--render`` PNG frames go to
``DIR/frames/``. The command is a thin wrapper of :func:`holowarp.simulation.simulate`.

Exit status: 0 on success, 2 for input that cannot be used (one line ``error: ...`` naming
the file or argument), 1 when the simulation itself failed (non-finite state; nothing is
written, so an earlier ``sim.usda``/``report.json`` stays).
"""

from __future__ import annotations

import json
import sys

from holowarp import cli

__all__ = ["main", "build_parser"]

_SUMMARY_KEYS = ("frames", "steps", "seconds", "steps_per_second", "max_inverted", "min_volume_ratio",
                 "max_volume_ratio", "max_penetration", "nan", "components_end", "sim_chamfer")


def build_parser():
    from holowarp.simulation import MESH_FORMATS_HELP

    p = cli.parser(
        "holowarp.simulate",
        "Simulate a tet mesh in a scene (drop, compress or a TOML file); write sim.usda and report.json.",
        epilog=f"MESH and GT_MESH: {MESH_FORMATS_HELP}.\nScenes with [[bodies]] may name further meshes "
               "themselves; bodies without one use MESH.",
    )
    p.add_argument("mesh", metavar="MESH", help="the mesh to simulate (formats below)")
    p.add_argument("--scene", required=True, help="built-in scene name (drop, compress) or a path to a .toml scene")
    p.add_argument("--out", required=True, help="output folder for sim.usda and report.json")
    p.add_argument("--reference", default=None, metavar="GT_MESH",
                   help="ground-truth mesh simulated in the same scene; adds sim_chamfer to the report")
    p.add_argument("--render", action="store_true", help="also write PNG frames to OUT/frames/ (pyvista, off screen)")
    p.add_argument("--allow-long", action="store_true",
                   help="run even when the estimated work (steps x substeps x iterations x tets) is above the cap")
    p.add_argument("--chamfer-samples", type=int, default=None,
                   help="surface samples per mesh for sim_chamfer (default 100000, method.md §9)")
    cli.add_device(p)
    cli.add_quiet(p)
    return p


def _run(args) -> int:
    from pathlib import Path

    from holowarp.simulation import simulate

    if args.chamfer_samples is not None and args.chamfer_samples < 100:
        cli.fail(f"--chamfer-samples must be >= 100, got {args.chamfer_samples}")
    out = Path(args.out)
    report = simulate(
        args.mesh, args.scene, device=args.device, reference=args.reference, out_dir=out,
        render_dir=(out / "frames") if args.render else None, progress=not args.quiet,
        chamfer_samples=args.chamfer_samples, allow_long=args.allow_long,
    )
    summary = {k: report[k] for k in _SUMMARY_KEYS if k in report}
    print(json.dumps(summary, indent=2))
    if not args.quiet:
        print(f"wrote {out / 'sim.usda'} and {out / 'report.json'}", file=sys.stderr)
    return 0


def main(argv=None) -> int:
    return cli.run(_run, build_parser().parse_args(argv))


if __name__ == "__main__":
    sys.exit(main())
