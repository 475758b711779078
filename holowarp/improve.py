"""``python -m holowarp.improve IN OUT [--max-surface-move FRAC]``: make any tet mesh
simulation-ready.

Runs the element-improvement stage (:func:`holowarp.stages.improve.improve`, method.md §7b)
on a tet mesh from any source (holowarp, TetGen, fTetWild, Gmsh): flips, smoothing and
sliver removal, keeping components, genus and a manifold boundary, no inverted tet, and the
boundary surface within FRAC mean boundary edges (Hausdorff) of the input. OUT's extension
picks the format; it is written atomically. A one-line summary goes to stdout; ``--json``
also writes the full report (the ``report.json -> improve`` section).

Orientation (holowarp's convention ``det[b-a, c-a, d-a] > 0``): a mesh whose tets are all
negative (raw TetGen/fTetWild winding) is re-oriented and the summary says so; a mesh with
some negative tets is refused unless ``--orient`` flips them; zero-volume tets are refused.

Exit status: 0 on success, 2 for input that cannot be used (one line ``error: ...`` naming
the file or argument, before any work is done), 1 when the stage itself failed.
"""

from __future__ import annotations

import math
import sys
from pathlib import Path

from holowarp import cli

__all__ = ["main", "build_parser", "improve_file"]


def _frac(text: str | None) -> float | None:
    """The --max-surface-move value, checked here (not by argparse) so that a bad one is one
    ``error:`` line like every other input error."""
    if text is None:
        return None
    try:
        v = float(text)
    except ValueError:
        v = float("nan")
    if not math.isfinite(v) or v < 0:
        cli.fail(f"--max-surface-move {text}: expected a finite number >= 0 (mean boundary edges)")
    return v


def build_parser():
    from holowarp.mesh_io import TET_FORMATS

    fmts = ", ".join(TET_FORMATS)
    p = cli.parser(
        "holowarp.improve",
        "Improve the elements of a tet mesh (flips, smoothing, sliver removal) without changing its "
        "topology or moving its surface by more than FRAC mean boundary edges.",
        epilog=f"IN and OUT formats: {fmts} (OUT's extension picks the format).\n"
               "FRAC: a number >= 0; 0 keeps the surface exactly (boundary vertices stay put and no "
               "boundary flip is made), 0.1 is method.md's bound.",
    )
    p.add_argument("src", metavar="IN", help=f"input tet mesh ({fmts})")
    p.add_argument("dst", metavar="OUT", help=f"output tet mesh ({fmts})")
    p.add_argument("--max-surface-move", default=None, metavar="FRAC",
                   help="bound on the Hausdorff distance between the surfaces before and after, in mean "
                        "boundary edge lengths (default 0.1)")
    p.add_argument("--orient", action="store_true",
                   help="flip the negative tets of a mixed-orientation mesh (without it such a mesh is refused)")
    p.add_argument("--json", default=None, metavar="REPORT", help="also write the full report as JSON here")
    cli.add_device(p)
    cli.add_quiet(p)
    return p


def improve_file(src, dst, *, max_surface_move: float | None = None, orient: bool = False, device: str = "cpu",
                 json_path=None, progress: bool = True) -> dict:
    """Read ``src``, run the improvement stage, write ``dst`` (and ``json_path``).

    Returns the stage's info dict plus ``input`` (``path``, ``reoriented``, ``flipped``) and
    ``output``. Raises :class:`holowarp.errors.InputError` (checked before any work) for a bad
    argument, file or device.
    """
    from holowarp.device import resolve_device
    from holowarp.errors import InputError
    from holowarp.fileio import atomic_write_json, check_output_file
    from holowarp.mesh_io import TET_FORMATS, load_tetmesh, write_tetmesh
    from holowarp.progress import bar
    from holowarp.stages.improve import ImproveConfig, improve

    cfg = ImproveConfig() if max_surface_move is None else ImproveConfig(max_surface_move=float(max_surface_move))
    ext = Path(dst).suffix.lower()
    if ext not in TET_FORMATS:
        raise InputError(f"OUT {dst}: unknown tet-mesh extension {ext!r}; use one of {', '.join(TET_FORMATS)}")
    check_output_file(dst, what="OUT")
    if json_path is not None:
        if Path(json_path).suffix.lower() != ".json":
            raise InputError(f"--json {json_path}: expected a .json file name")
        check_output_file(json_path, what="--json")
    device = resolve_device(device)
    mesh, oinfo = load_tetmesh(src, fix_orientation=orient)
    with bar(cfg.max_rounds, desc="improve", unit="round", progress=progress) as b:
        out, _, info = improve(mesh, cfg, device=device, progress=b)
    write_tetmesh(dst, out)
    info["input"] = {"path": str(src), "reoriented": oinfo["reoriented"], "flipped": oinfo["flipped"]}
    info["output"] = str(dst)
    if json_path is not None:
        atomic_write_json(json_path, info)
    return info


def _run(args) -> int:
    info = improve_file(args.src, args.dst, max_surface_move=_frac(args.max_surface_move), orient=args.orient,
                        device=args.device, json_path=args.json, progress=not args.quiet)
    b, a = info["before"], info["after"]
    flips = sum(info["flips"].values())
    splits = sum(v for k, v in info["splits"].items() if k != "refined")
    o = info["input"]
    note = ""
    if o["reoriented"]:
        note = f"; re-oriented all {o['reoriented']} tets (the file used the opposite winding)"
    elif o["flipped"]:
        note = f"; flipped {o['flipped']} negative tets (--orient)"
    if info.get("refinement"):
        r = info["refinement"]
        note += (f"; thin mesh ({r['thin_fraction']:.0%} of the tets on the boundary alone): every tet split in "
                 f"eight and improved again")
    print(
        f"wrote {args.dst}: {a['tets']} tets ({b['tets']} before), worst min dihedral "
        f"{b['min_dihedral_worst']:.2f} -> {a['min_dihedral_worst']:.2f} deg, mean {b['min_dihedral_mean']:.1f} -> "
        f"{a['min_dihedral_mean']:.1f} deg, mean aspect {b['aspect_ratio_mean']:.2f} -> {a['aspect_ratio_mean']:.2f}, "
        f"min eta {b['eta_min']:.3g} -> {a['eta_min']:.3g}, surface moved {info['surface_hausdorff_mean_edges']:.3f} "
        f"mean edges (bound {info['surface_move_bound_mean_edges']:g}), {flips} flips, {splits} splits, "
        f"{info['vertices_smoothed']} vertices smoothed, {info['seconds']:.1f} s{note}"
    )
    from holowarp.stages.improve import missed_targets

    for line in missed_targets(info):
        print(f"warning: {line}", file=sys.stderr)
    return 0


def main(argv=None) -> int:
    return cli.run(_run, build_parser().parse_args(argv))


if __name__ == "__main__":
    sys.exit(main())
