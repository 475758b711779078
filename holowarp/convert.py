"""``python -m holowarp.convert IN OUT``: convert between tet-mesh formats.

The output format follows OUT's extension: ``.vtu``, ``.msh``, ``.npz``, ``.usd``/``.usda``/
``.usdc`` (tet mesh + surface + physics material), or ``.obj``/``.ply`` (the outward
boundary surface only). IN is any tet-mesh format (``.vtu``, ``.msh``, ``.npz``, USD).

Orientation (holowarp's convention: ``det[b-a, c-a, d-a] > 0``): a mesh whose tets are all
negative (raw TetGen/fTetWild winding) is re-oriented and the summary says so; a mesh with
some negative tets is refused unless ``--orient`` flips them; zero-volume tets and meshes
without tets are errors.
"""

from __future__ import annotations

import sys
from pathlib import Path

from holowarp import cli
from holowarp.fileio import check_output_file
from holowarp.mesh_io import TET_FORMATS, MeshIOError, load_tetmesh, write_tetmesh
from holowarp.surface_io import SURFACE_WRITE_FORMATS, write_surface

__all__ = ["convert", "main", "build_parser"]


def convert(src, dst, *, orient: bool = False, material=None) -> dict:
    """Read ``src`` and write ``dst`` (format by extension). Returns a summary dict with
    ``reoriented`` (tets flipped because all were negative) and ``flipped`` (by ``orient``).

    Args:
        orient: flip the negative tets of a mixed-orientation mesh (else it is an error).
        material: :class:`holowarp.usd.PhysicsMaterial` for USD outputs.
    """
    check_output_file(dst, what="OUT")
    ext = Path(dst).suffix.lower()
    if ext not in TET_FORMATS + SURFACE_WRITE_FORMATS:
        raise MeshIOError(
            f"{dst}: unknown output extension {ext!r}; use one of {', '.join(TET_FORMATS + SURFACE_WRITE_FORMATS)}"
        )
    mesh, oinfo = load_tetmesh(src, fix_orientation=orient)
    flipped = oinfo["flipped"]
    if ext in SURFACE_WRITE_FORMATS:
        write_surface(dst, mesh)
    elif ext in (".usd", ".usda", ".usdc"):
        write_tetmesh(dst, mesh, material=material, name=Path(src).stem)
    else:
        write_tetmesh(dst, mesh)
    info = mesh.summary()
    info.update(flipped=flipped, reoriented=oinfo["reoriented"])
    return info


def build_parser():
    p = cli.parser("holowarp.convert",
                   "Convert a tet mesh between .vtu, .msh, .npz and USD, or export its boundary as .obj/.ply.")
    p.add_argument("src", metavar="IN", help="input tet mesh (" + ", ".join(TET_FORMATS) + ")")
    p.add_argument("dst", metavar="OUT", help="output file; its extension picks the format ("
                   + ", ".join(TET_FORMATS + SURFACE_WRITE_FORMATS) + ")")
    p.add_argument("--orient", action="store_true",
                   help="flip the negative tets of a mixed-orientation mesh (without it such a mesh is refused)")
    p.add_argument("--youngs-modulus", type=float, default=None, metavar="PA", help="USD physics material E [Pa] (> 0)")
    p.add_argument("--poissons-ratio", type=float, default=None, metavar="NU",
                   help="USD physics material nu, in [0, 0.5)")
    p.add_argument("--density", type=float, default=None, metavar="RHO",
                   help="USD physics material density [kg/m^3] (> 0)")
    cli.add_device(p, note="convert runs no kernels; accepted so every command takes the same options", threads=False)
    cli.add_quiet(p)
    return p


def _material(args):
    if all(x is None for x in (args.youngs_modulus, args.poissons_ratio, args.density)):
        return None
    from holowarp.usd import PhysicsMaterial

    d = PhysicsMaterial()
    try:
        return PhysicsMaterial(
            youngs_modulus=d.youngs_modulus if args.youngs_modulus is None else args.youngs_modulus,
            poissons_ratio=d.poissons_ratio if args.poissons_ratio is None else args.poissons_ratio,
            density=d.density if args.density is None else args.density,
        )
    except ValueError as e:
        cli.fail(f"material: {e}")


def _run(args) -> int:
    from holowarp.device import resolve_device

    resolve_device(args.device)
    info = convert(args.src, args.dst, orient=args.orient, material=_material(args))
    print(
        f"wrote {args.dst}: {info['vertices']} vertices, {info['tets']} tets, "
        f"{info['boundary_faces']} boundary faces, {info['components']} component(s), "
        f"manifold={info['manifold']}, genus={info['genus']}, inverted={info['inverted']}"
        + (f", flipped={info['flipped']}" if args.orient else "")
        + (f", overlapping edges={info['overlapping_edges']} (the tets around them overlap in space)"
           if info["overlapping_edges"] else "")
        + (f"; re-oriented all {info['reoriented']} tets (the file used the opposite winding)" if info["reoriented"] else "")
    )
    return 0


def main(argv=None) -> int:
    return cli.run(_run, build_parser().parse_args(argv))


if __name__ == "__main__":
    sys.exit(main())
