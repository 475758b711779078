"""Outputs of a reconstruction (method.md §7): files other tools open, and previews.

- ``tetmesh.vtu``, ``tetmesh.msh``: the tet mesh;
- ``surface.obj``: its outward boundary;
- ``gaussians.ply``: one surfel per tet in the 3DGS viewer layout;
- ``scene.usda``: UsdGeom.TetMesh + surface Mesh + physics material (Z up, metres).

:func:`render_test_views` renders the surfels at the test views for the report and the
previews (:mod:`holowarp.previews`). Every file is written atomically.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from holowarp.tetgs import TetGaussians
from holowarp.tetmesh import TetMesh

__all__ = ["write_outputs", "render_test_views", "render_surfel_views"]


def write_outputs(out_dir: Path, model: TetGaussians, mesh: TetMesh, *, material=None, name: str = "Object",
                  usd: bool = True) -> dict:
    """Write the mesh, surface, surfels and (``usd``) the one-body USD stage; returns their
    paths. A scene-level run writes its own ``scene.usda``, one body per object
    (:mod:`holowarp.stages.objects`)."""
    from holowarp.gaussians import write_gaussians_ply
    from holowarp.mesh_io import write_tetmesh
    from holowarp.surface_io import write_surface
    from holowarp.usd import PhysicsMaterial, write_usd

    out_dir = Path(out_dir)
    paths = {
        "tetmesh_vtu": write_tetmesh(out_dir / "tetmesh.vtu", mesh),
        "tetmesh_msh": write_tetmesh(out_dir / "tetmesh.msh", mesh),
        "surface_obj": write_surface(out_dir / "surface.obj", mesh),
    }
    if usd:
        paths["scene_usda"] = write_usd(out_dir / "scene.usda", mesh, material=material or PhysicsMaterial(), name=name)
    with torch.no_grad():
        write_gaussians_ply(
            out_dir / "gaussians.ply",
            means=model.means(),
            quats=model.quats,
            scales=model.scales(),
            opacities=model.opacities(),
            colors=model.colors(),
        )
    paths["gaussians_ply"] = out_dir / "gaussians.ply"
    return {k: str(v) for k, v in paths.items()}


def render_surfel_views(model: TetGaussians, dataset, views, *, background) -> list[dict]:
    """Per view of ``views``: the surfels' ``rgb`` (H, W, 3, clamped to [0, 1]), ``alpha``
    (H, W) and world ``normal`` (H, W, 3), float32 arrays."""
    out = []
    with torch.no_grad():
        for v in views:
            r = model.render(dataset.viewmats[v], dataset.K[v], dataset.width, dataset.height, background=background)
            out.append({"rgb": r["rgb"].clamp(0, 1).cpu().numpy(), "alpha": r["alpha"].cpu().numpy(),
                        "normal": r["normal"].cpu().numpy()})
    return out


def render_test_views(model: TetGaussians, dataset, views, *, background) -> list[np.ndarray]:
    """RGB renders (H, W, 3) float32 of ``views``."""
    return [r["rgb"] for r in render_surfel_views(model, dataset, views, background=background)]
