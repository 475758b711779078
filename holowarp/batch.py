"""``python -m holowarp.batch SUITE.toml --out DIR``: every object of a suite through the whole
method, and the paper's tables (issue 18).

Each object of the suite file (format: :mod:`holowarp.suite.spec`) runs synth (for a mesh),
the visual-hull baseline, reconstruct, evaluate and simulate drop with its ground truth as
reference, in ``DIR/NAME/``; ``DIR/summary.json`` and ``DIR/summary.md`` hold the dataset
table (holowarp and the visual hull side by side) and the per-object table. A thin command
over :func:`holowarp.suite.run_suite`.
"""

from __future__ import annotations

import sys
from pathlib import Path

from holowarp import cli

__all__ = ["main", "build_parser"]


def build_parser():
    p = cli.parser("holowarp.batch", "Run every object of a suite file (synth, visual hull, reconstruct, evaluate, "
                                     "simulate) and write the paper's tables.")
    p.add_argument("suite", metavar="SUITE.toml", help="suite file: preset, [overrides], [resources], [[objects]]")
    p.add_argument("--out", required=True, metavar="DIR", help="output folder (one sub-folder per object)")
    p.add_argument("--executor", choices=["local", "ray"], default="ray",
                   help="ray (default): one Ray task per object; local: one object after the other, in this process")
    p.add_argument("--ray-address", default=None, metavar="ADDR",
                   help="submit to the Ray cluster at ADDR (as `ray start --head` prints it); "
                        "default: a local Ray runtime sized to this machine's cores")
    p.add_argument("--workers", type=int, default=None, metavar="N",
                   help="at most N objects at once (ray; default: as many as the suite's resources allow)")
    p.add_argument("--resume", action="store_true",
                   help="continue a run in DIR: done objects are kept, the others continue from their last step")
    cli.add_quiet(p)
    return p


def _run(args) -> int:
    from holowarp.suite import run_suite

    s = run_suite(args.suite, args.out, executor=args.executor, ray_address=args.ray_address, workers=args.workers,
                  resume=args.resume, progress=not args.quiet)
    h, v = s["holowarp"], s["visual_hull"]
    print(f"wrote {Path(args.out) / 'summary.md'}: {s['objects']} objects, {s['done']} done, {s['failed']} failed; "
          f"single component {100 * h['single_component_rate']:.1f}% (visual hull {100 * v['single_component_rate']:.1f}%), "
          f"{s['seconds']:.0f} s")
    return 1 if s["failed"] else 0


def main(argv=None) -> int:
    return cli.run(_run, build_parser().parse_args(argv))


if __name__ == "__main__":
    sys.exit(main())
