"""Preview images of a run, for people: labelled test views, a cut-away of the tets, loss curves.

- :func:`preview_test_views`: ground truth beside the reconstruction for a few test views,
  each panel labelled (what it is, the view, its PSNR);
- :func:`preview_cutaway`: the tets on one side of a mid plane, coloured by face-connected
  component (pyvista, off screen);
- :func:`preview_losses`: the loss curves of every stage (log scale) from ``history.jsonl``.

Every file is written atomically; small renders are upscaled (nearest) so pixels stay visible.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from holowarp.fileio import atomic_path
from holowarp.tetmesh import TetMesh

__all__ = ["preview_test_views", "preview_cutaway", "preview_losses", "labelled"]

#: Previews are upscaled to at least this many pixels of height.
MIN_HEIGHT = 384


def _to_image(img: np.ndarray, min_height: int = MIN_HEIGHT):
    from PIL import Image

    im = Image.fromarray((np.clip(img, 0, 1) * 255 + 0.5).astype(np.uint8))
    k = max(1, -(-min_height // im.height))
    if k > 1:
        im = im.resize((im.width * k, im.height * k), Image.NEAREST)
    return im


def labelled(img: np.ndarray, text: str, *, min_height: int = MIN_HEIGHT):
    """A PIL image of ``img`` (H, W, 3) in [0, 1], upscaled, with ``text`` on a dark band at
    the top."""
    from PIL import ImageDraw, ImageFont

    im = _to_image(img, min_height)
    draw = ImageDraw.Draw(im)
    size = max(12, im.height // 24)
    try:
        font = ImageFont.load_default(size=size)
    except TypeError:  # Pillow < 10.1 has one fixed-size default font
        font = ImageFont.load_default()
    box = draw.textbbox((0, 0), text, font=font)
    draw.rectangle([0, 0, im.width, box[3] - box[1] + 2 * (size // 3)], fill=(0, 0, 0))
    draw.text((size // 2, size // 3 - box[1]), text, fill=(255, 255, 255), font=font)
    return im


def _save(path: Path, im) -> str:
    with atomic_path(path) as tmp:
        im.save(tmp, format="PNG")
    return str(path)


def preview_test_views(out_dir: Path, renders, gts, views, *, psnrs=None, max_views: int = 4) -> list[str]:
    """``test_VVV.png`` for up to ``max_views`` views: the ground truth and the reconstruction
    side by side, labelled with the view index and (given ``psnrs``) the view's PSNR."""
    from PIL import Image

    paths = []
    for j, (r, g, v) in enumerate(list(zip(renders, gts, views))[:max_views]):
        extra = f", PSNR {psnrs[j]:.2f} dB" if psnrs is not None else ""
        left = labelled(g, f"ground truth, view {int(v)}")
        right = labelled(r, f"reconstruction, view {int(v)}{extra}")
        canvas = Image.new("RGB", (left.width + right.width + 8, left.height), (255, 255, 255))
        canvas.paste(left, (0, 0))
        canvas.paste(right, (left.width + 8, 0))
        paths.append(_save(Path(out_dir) / f"test_{int(v):03d}.png", canvas))
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
