"""holowarp: HoloTetSphere reconstruction and deformable-body simulation in NVIDIA Warp.

Public entry points (one canonical import path each):

- :class:`holowarp.TetMesh`: the tetrahedral mesh core (orientation, boundary, adjacency,
  components, manifoldness, quality).
- :func:`holowarp.read_tetmesh`, :func:`holowarp.write_tetmesh`,
  :func:`holowarp.write_surface`: mesh I/O (``.vtu``, ``.msh``, ``.npz``; ``.obj``/``.ply``).
- :func:`holowarp.write_usd`: USD export (``UsdGeom.TetMesh`` + surface ``Mesh`` + physics
  material).

Conventions are those of ``method.md`` §1: SI units, Z up, OpenCV cameras, tets ordered so
that ``det[b-a, c-a, d-a] / 6 > 0``.
"""

import importlib

from holowarp.tetmesh import TetMesh

__all__ = [
    "MeshIOError",
    "TetMesh",
    "read_tetmesh",
    "write_surface",
    "write_tetmesh",
    "write_usd",
]

__version__ = "0.1.0"

# I/O and USD are imported on first use so that ``import holowarp`` stays light (no pxr).
_LAZY = {
    "MeshIOError": "holowarp.mesh_io",
    "read_tetmesh": "holowarp.mesh_io",
    "write_surface": "holowarp.mesh_io",
    "write_tetmesh": "holowarp.mesh_io",
    "write_usd": "holowarp.usd",
}


def __getattr__(name):
    mod = _LAZY.get(name)
    if mod is None:
        raise AttributeError(f"module 'holowarp' has no attribute {name!r}")
    return getattr(importlib.import_module(mod), name)
