"""``python -m holowarp.synth MESH --out DIR``: ground-truth views in NeRF-synthetic layout.

Thin command over :func:`holowarp.synthesis.synthesize` (method.md §2): 120 Fibonacci-sphere
views by default, every 10th a test view, fov 39.3 degrees, RGBA + world normals + depth,
plus the welded, Z-up, normalised ``gt.obj``. A ``.toml`` MESH is a scene file of several
objects rendered together (:func:`holowarp.scene_synth.synthesize_scene`, method.md §11).
"""

from __future__ import annotations

import json
import sys

from holowarp import cli

__all__ = ["main", "build_parser"]


def build_parser():
    from holowarp.surface_io import SURFACE_READ_FORMATS

    p = cli.parser("holowarp.synth", "Render ground-truth views of a mesh (method.md §2) in NeRF-synthetic layout.")
    p.add_argument("mesh", metavar="MESH", help=f"input surface ({', '.join(SURFACE_READ_FORMATS)}; textures from OBJ/GLB), "
                                                "or a SCENE.toml placing several objects in one capture")
    p.add_argument("--out", required=True, metavar="DIR", help="dataset folder to write")
    p.add_argument("--views", type=int, default=120, help="number of Fibonacci-sphere views (default 120; at least one must be a training view)")
    p.add_argument("--res", type=int, default=512, metavar="PX", help="image width = height in pixels (default 512, >= 8)")
    p.add_argument("--up-axis", default="y", choices=["y", "z"],
                   help="the model's up axis (default y, OBJ convention; in a scene, of objects without up_axis)")
    p.add_argument("--test-every", type=int, default=10, metavar="N", help="view i is a test view when i %% N == 0 (default 10, >= 1)")
    p.add_argument("--supersample", type=int, default=2, metavar="S", help="antialiasing rays per pixel along each axis (default 2, >= 1)")
    p.add_argument("--resume", action="store_true", help="keep views already written by an interrupted run")
    p.add_argument("--overwrite", action="store_true", help="write into a folder that already holds a dataset")
    cli.add_device(p)
    cli.add_quiet(p)
    return p


def _run(args) -> int:
    from holowarp.synthesis import synthesize

    if str(args.mesh).lower().endswith(".toml"):
        from holowarp.scene_synth import synthesize_scene as synthesize
    summary = synthesize(args.mesh, args.out, views=args.views, res=args.res, device=args.device, up_axis=args.up_axis,
                         test_every=args.test_every, supersample=args.supersample, resume=args.resume,
                         overwrite=args.overwrite, progress=not args.quiet)
    print(json.dumps(summary, indent=2))
    return 0


def main(argv=None) -> int:
    return cli.run(_run, build_parser().parse_args(argv))


if __name__ == "__main__":
    sys.exit(main())
