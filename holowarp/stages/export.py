"""Outputs of a reconstruction (method.md §7): files other tools open, and previews.

- ``tetmesh.vtu``, ``tetmesh.msh``: the tet mesh;
- ``surface.obj``: its outward boundary;
- ``gaussians.ply``: one surfel per tet in the 3DGS viewer layout;
- ``scene.usda``: UsdGeom.TetMesh + surface Mesh + physics material (Z up, metres);
- ``previews/``: test views rendered beside the ground truth, a cut-away of the tets
  coloured by face-connected component (pyvista, off-screen), and the loss curves.

Every file is written atomically.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from holowarp.fileio import atomic_path
from holowarp.tetgs import TetGaussians
from holowarp.tetmesh import TetMesh

__all__ = ["write_outputs", "render_test_views", "preview_cutaway", "preview_losses", "preview_test_views"]


def write_outputs(out_dir: Path, model: TetGaussians, mesh: TetMesh, *, material=None, name: str = "Object") -> dict:
    """Write the mesh, surface, surfels and USD stage; returns their paths."""
    from holowarp.gaussians import write_gaussians_ply
    from holowarp.mesh_io import write_surface, write_tetmesh
    from holowarp.usd import PhysicsMaterial, write_usd

    out_dir = Path(out_dir)
    paths = {
        "tetmesh_vtu": write_tetmesh(out_dir / "tetmesh.vtu", mesh),
        "tetmesh_msh": write_tetmesh(out_dir / "tetmesh.msh", mesh),
        "surface_obj": write_surface(out_dir / "surface.obj", mesh),
        "scene_usda": write_usd(out_dir / "scene.usda", mesh, material=material or PhysicsMaterial(), name=name),
    }
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


def render_test_views(model: TetGaussians, dataset, views, *, background) -> list[np.ndarray]:
    """RGB renders (H, W, 3) float32 of ``views``."""
    out = []
    with torch.no_grad():
        for v in views:
            r = model.render(dataset.viewmats[v], dataset.K[v], dataset.width, dataset.height, background=background)
            out.append(r["rgb"].clamp(0, 1).cpu().numpy())
    return out


def _save_png(path: Path, img: np.ndarray, *, min_height: int = 384):
    """Save an RGB float image; small renders are upscaled (nearest) so pixels stay visible."""
    from PIL import Image

    im = Image.fromarray((np.clip(img, 0, 1) * 255 + 0.5).astype(np.uint8))
    k = max(1, -(-min_height // im.height))
    if k > 1:
        im = im.resize((im.width * k, im.height * k), Image.NEAREST)
    with atomic_path(path) as tmp:
        im.save(tmp, format="PNG")


def preview_test_views(out_dir: Path, renders, gts, views, *, max_views: int = 4) -> list[str]:
    """Side-by-side PNGs (ground truth | reconstruction) of up to ``max_views`` test views."""
    paths = []
    for r, g, v in list(zip(renders, gts, views))[:max_views]:
        sep = np.ones((g.shape[0], 4, 3), dtype=np.float32)
        p = Path(out_dir) / f"test_{int(v):03d}.png"
        _save_png(p, np.concatenate([g, sep, r], axis=1))
        paths.append(str(p))
    return paths


def preview_cutaway(path: Path, mesh: TetMesh, *, axis: int = 1) -> str:
    """Off-screen pyvista render of the tets on one side of a mid plane, coloured by
    face-connected component (one colour per component), edges shown."""
    import pyvista as pv

    from holowarp.viz import offscreen_plotter

    labels, n = mesh.components()
    c = mesh.vertices[mesh.tets].mean(axis=1)
    mid = 0.5 * (mesh.vertices[:, axis].min() + mesh.vertices[:, axis].max())
    sel = c[:, axis] <= mid
    if not sel.any():
        sel[:] = True
    cells = np.hstack([np.full((int(sel.sum()), 1), 4), mesh.tets[sel]]).astype(np.int64).ravel()
    grid = pv.UnstructuredGrid(cells, np.full(int(sel.sum()), pv.CellType.TETRA, dtype=np.uint8), mesh.vertices)
    grid.cell_data["component"] = labels[sel]
    plotter = offscreen_plotter((800, 800))
    plotter.add_mesh(
        grid,
        scalars="component",
        show_edges=True,
        edge_color="black",
        line_width=0.5,
        cmap="tab10",
        clim=(0, max(n - 1, 1)),
        show_scalar_bar=False,
    )
    plotter.add_text(f"{mesh.num_tets} tets, {n} component(s); cut at mid-plane", font_size=10)
    centre = mesh.vertices.mean(axis=0)
    extent = float(np.ptp(mesh.vertices, axis=0).max())
    # Look at the cut face: the kept half lies on the low side of the plane, so the camera
    # sits on the high side, a little above and to the side.
    side = np.roll(np.eye(3)[axis], 1)
    up = np.array([0.0, 0.0, 1.0]) if axis != 2 else np.array([0.0, 1.0, 0.0])
    eye = centre + extent * 2.0 * (np.eye(3)[axis] + 0.35 * side + 0.35 * up)
    plotter.camera_position = [tuple(eye), tuple(centre), tuple(up)]
    plotter.reset_camera()
    plotter.camera.zoom(1.3)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(path) as tmp:
        plotter.screenshot(str(tmp))
    plotter.close()
    return str(path)


def preview_losses(path: Path, history: dict) -> str:
    """Loss curves (log scale) of every stage: ``history`` maps a stage name to a list of
    per-step dicts of floats."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    stages = [(k, v) for k, v in history.items() if v]
    fig, axes = plt.subplots(1, max(len(stages), 1), figsize=(5 * max(len(stages), 1), 3.6), squeeze=False)
    for ax, (name, rows) in zip(axes[0], stages):
        keys = sorted({k for r in rows for k, v in r.items() if isinstance(v, float) and k not in ("lam", "lam_cond")})
        x = [r.get("iter", r.get("mesh_iter", i)) for i, r in enumerate(rows)]
        for k in keys:
            y = np.array([r.get(k, np.nan) for r in rows], dtype=float)
            if np.all(~np.isfinite(y)) or np.nanmax(np.abs(y)) == 0:
                continue
            ax.plot(x, np.abs(y), label=k, linewidth=0.8)
        ax.set_yscale("log")
        ax.set_title(name)
        ax.set_xlabel("iteration")
        ax.legend(fontsize=7)
    fig.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=110, format="png")
    plt.close(fig)
    return str(path)
