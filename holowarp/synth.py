"""``python -m holowarp.synth MESH --out DIR``: ground-truth views in NeRF-synthetic layout.

Thin command over :func:`holowarp.data.synth.synthesize` (method.md §2): 120 Fibonacci-sphere
views by default, every 10th a test view, fov 39.3 degrees, RGBA + world normals + depth,
plus the welded, Z-up, normalised ``gt.obj``.
"""

from __future__ import annotations

import argparse
import json
import sys

__all__ = ["main"]


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="python -m holowarp.synth",
        description="Render ground-truth views of a mesh (method.md §2) in NeRF-synthetic layout.",
    )
    p.add_argument("mesh", metavar="MESH", help="input .obj (textured or not)")
    p.add_argument("--out", required=True, metavar="DIR", help="dataset folder to write")
    p.add_argument("--views", type=int, default=120, help="number of Fibonacci-sphere views (default 120)")
    p.add_argument("--res", type=int, default=512, help="image width = height in pixels (default 512)")
    p.add_argument("--device", default="cpu", help="cpu | cuda | cuda:N (default cpu)")
    p.add_argument("--up-axis", default="y", choices=["y", "z"], help="the model's up axis (default y, OBJ convention)")
    p.add_argument("--test-every", type=int, default=10, help="view i is a test view when i %% N == 0 (default 10)")
    p.add_argument("--supersample", type=int, default=2, help="antialiasing rays per pixel along each axis (default 2)")
    p.add_argument("--resume", action="store_true", help="keep views already written by an interrupted run")
    p.add_argument("--overwrite", action="store_true", help="write into a folder that already holds a dataset")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    return p


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    from holowarp.data.synth import SynthError, synthesize
    from holowarp.device import DeviceError

    try:
        summary = synthesize(
            args.mesh,
            args.out,
            views=args.views,
            res=args.res,
            device=args.device,
            up_axis=args.up_axis,
            test_every=args.test_every,
            supersample=args.supersample,
            resume=args.resume,
            overwrite=args.overwrite,
            progress=not args.quiet,
        )
    except (SynthError, DeviceError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    print(json.dumps(summary, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
