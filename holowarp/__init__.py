"""holowarp: HoloTetSphere reconstruction and deformable-body simulation in NVIDIA Warp.

Public entry points (one canonical import path each):

- :class:`holowarp.TetMesh`: the tetrahedral mesh core (orientation, boundary, adjacency,
  components, manifoldness, quality).
- :func:`holowarp.read_tetmesh`, :func:`holowarp.write_tetmesh`: tet-mesh I/O (``.vtu``,
  ``.msh``, ``.npz``, USD); :func:`holowarp.read_surface`, :func:`holowarp.write_surface`:
  triangle surfaces (every format trimesh reads; ``.obj``/``.ply`` written).
- :func:`holowarp.evaluate_mesh`: method.md §9 metrics.
- the applications: :func:`holowarp.pipeline.reconstruct` (the method) and
  :func:`holowarp.simulation.simulate` (the simulator); ``holowarp.reconstruct`` and
  ``holowarp.simulate`` are their command-line modules.
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
    "evaluate_mesh",
    "read_surface",
    "read_tetmesh",
    "write_surface",
    "write_tetmesh",
    "write_usd",
]

__version__ = "0.1.0"

# Everything but TetMesh is imported on first use, so ``import holowarp`` stays light (no pxr,
# no torch, no Warp).
_LAZY = {
    "MeshIOError": "holowarp.mesh_io",
    "evaluate_mesh": "holowarp.metrics",
    "read_surface": "holowarp.surface_io",
    "read_tetmesh": "holowarp.mesh_io",
    "write_surface": "holowarp.surface_io",
    "write_tetmesh": "holowarp.mesh_io",
    "write_usd": "holowarp.usd",
}


def __getattr__(name):
    mod = _LAZY.get(name)
    if mod is None:
        raise AttributeError(f"module 'holowarp' has no attribute {name!r}")
    return getattr(importlib.import_module(mod), name)
