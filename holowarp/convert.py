"""``python -m holowarp.convert IN OUT``: convert between tet-mesh formats.

The output format follows OUT's extension: ``.vtu``, ``.msh``, ``.npz``, ``.usd``/``.usda``/
``.usdc`` (tet mesh + surface + physics material), or ``.obj``/``.ply`` (the outward
boundary surface only). IN is any tet-mesh format (``.vtu``, ``.msh``, ``.npz``, USD).
"""

from __future__ import annotations

import argparse
import sys

from holowarp.mesh_io import SURFACE_FORMATS, TET_FORMATS, MeshIOError, read_tetmesh, write_surface, write_tetmesh

__all__ = ["convert", "main"]


def convert(src, dst, *, orient: bool = False, material=None) -> dict:
    """Read ``src`` and write ``dst`` (format by extension). Returns a summary dict.

    Args:
        orient: reorder inverted tets before writing (their count is reported).
        material: :class:`holowarp.usd.PhysicsMaterial` for USD outputs.
    """
    from pathlib import Path

    mesh = read_tetmesh(src)
    flipped = 0
    if orient:
        mesh, flipped = mesh.oriented()
    ext = Path(dst).suffix.lower()
    if ext in SURFACE_FORMATS:
        write_surface(dst, mesh)
    elif ext in (".usd", ".usda", ".usdc"):
        write_tetmesh(dst, mesh, material=material, name=Path(src).stem)
    elif ext in TET_FORMATS:
        write_tetmesh(dst, mesh)
    else:
        raise MeshIOError(
            f"{dst}: unknown output extension {ext!r}; use one of {', '.join(TET_FORMATS + SURFACE_FORMATS)}"
        )
    info = mesh.summary()
    info["flipped"] = flipped
    return info


def main(argv=None) -> int:
    p = argparse.ArgumentParser(
        prog="python -m holowarp.convert",
        description="Convert a tet mesh between .vtu, .msh, .npz and USD, or export its boundary as .obj/.ply.",
    )
    p.add_argument("src", metavar="IN", help="input tet mesh (.vtu, .msh, .npz, .usd, .usda)")
    p.add_argument("dst", metavar="OUT", help="output file; its extension picks the format")
    p.add_argument("--orient", action="store_true", help="reorder inverted tets before writing")
    p.add_argument("--youngs-modulus", type=float, default=None, help="USD physics material E [Pa]")
    p.add_argument("--poissons-ratio", type=float, default=None, help="USD physics material nu")
    p.add_argument("--density", type=float, default=None, help="USD physics material density [kg/m^3]")
    args = p.parse_args(argv)
    material = None
    if any(x is not None for x in (args.youngs_modulus, args.poissons_ratio, args.density)):
        from holowarp.usd import PhysicsMaterial

        d = PhysicsMaterial()
        try:
            material = PhysicsMaterial(
                youngs_modulus=args.youngs_modulus or d.youngs_modulus,
                poissons_ratio=d.poissons_ratio if args.poissons_ratio is None else args.poissons_ratio,
                density=args.density or d.density,
            )
        except ValueError as e:
            p.error(str(e))
    try:
        info = convert(args.src, args.dst, orient=args.orient, material=material)
    except (MeshIOError, OSError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 1
    print(
        f"wrote {args.dst}: {info['vertices']} vertices, {info['tets']} tets, "
        f"{info['boundary_faces']} boundary faces, {info['components']} component(s), "
        f"manifold={info['manifold']}, genus={info['genus']}, inverted={info['inverted']}"
        + (f", flipped={info['flipped']}" if args.orient else "")
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
