"""Preview images of a run, for people: labelled test views, a cut-away of the tets, loss curves.

- :func:`preview_test_views`: ground truth beside the reconstruction for a few test views,
  each panel labelled (what it is, the view, its PSNR);
- :func:`preview_cutaway`: the tets on one side of a mid plane, coloured by face-connected
  component, edges drawn;
- :func:`preview_losses`: the loss curves of every stage (log scale) from ``history.jsonl``;
- :func:`write_error_maps`: a prediction and its ground truth coloured by their distances
  on a fixed scale (``pred_error.ply``, ``gt_missing.ply``, ``error_views.png``).

Every file is written atomically; small renders are upscaled (nearest) so pixels stay visible.
The 3D views are drawn by holowarp's own rasteriser (:func:`_render_shaded`), not by VTK:
VTK's off-screen renders were the peak of a run's memory (about 300 MB at its end).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from holowarp.fileio import atomic_path
from holowarp.tetmesh import TetMesh

__all__ = [
    "ERROR_SCALE",
    "ERROR_CMAP",
    "preview_test_views",
    "preview_cutaway",
    "preview_losses",
    "labelled",
    "error_colors",
    "write_error_maps",
    "preview_silhouettes",
    "preview_turntable",
]

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


def _outline(a: np.ndarray) -> np.ndarray:
    """(H, W) bool: the pixels of region ``a`` (bool) that touch a pixel outside it."""
    p = np.pad(a, 1, constant_values=False)
    inner = p[:-2, 1:-1] & p[2:, 1:-1] & p[1:-1, :-2] & p[1:-1, 2:]
    return a & ~inner


def preview_silhouettes(path: Path, photos, mesh_alphas, masks, views) -> str:
    """Up to three photos side by side, each with the tet mesh's silhouette overlaid: the
    mesh region tinted green, where it closes a hole the mask sees through tinted red
    (:func:`holowarp.metrics.views.see_through`: a tunnel or handle the mesh filled), its
    outline in green and the mask's outline in magenta, so the two outlines show where they
    disagree. Labelled with the view, its silhouette IoU and the share of the see-through
    pixels the mesh closes."""
    from PIL import Image

    from holowarp.metrics.views import see_through

    tiles = []
    for photo, alpha, mask, v in list(zip(photos, mesh_alphas, masks, views))[:3]:
        a, m = np.asarray(alpha) > 0.5, np.asarray(mask) > 0.5
        holes = see_through(mask)
        closed = a & holes
        img = np.asarray(photo, dtype=np.float32)[..., :3].copy()
        img[a] = 0.6 * img[a] + 0.4 * np.array([0.2, 0.8, 0.3])
        img[closed] = 0.3 * img[closed] + 0.7 * np.array([1.0, 0.1, 0.1])
        img[_outline(m)] = (1.0, 0.1, 0.9)
        img[_outline(a)] = (0.1, 1.0, 0.2)
        union = (a | m).sum()
        text = f"view {int(v)}: mesh (green) vs mask (magenta), IoU {(a & m).sum() / max(union, 1):.3f}"
        if holes.any():
            text += f"\nmesh over the mask's see-through pixels (red): {closed.sum() / holes.sum():.0%}"
        tiles.append(labelled(img, text))
    canvas = Image.new("RGB", (sum(t.width for t in tiles) + 8 * (len(tiles) - 1), max(t.height for t in tiles)),
                       (255, 255, 255))
    x = 0
    for t in tiles:
        canvas.paste(t, (x, 0))
        x += t.width + 8
    return _save(Path(path), canvas)


def _render_shaded(vertices, faces, face_rgb, eyes, centre, *, res: int, up=(0.0, 0.0, 1.0), edges: bool = False,
                   device: str = "cpu") -> list[np.ndarray]:
    """Flat-coloured, Lambert-shaded views of a triangle mesh with holowarp's own rasteriser
    (:func:`holowarp.ops.rasterize_mesh`; no VTK, whose off-screen renders cost a run about
    300 MB at its end).

    Args:
        vertices: (V, 3) positions; faces: (F, 3) vertex ids (either winding: the shade
            uses |cos| to the camera).
        face_rgb: (F, 3) colours in [0, 1].
        eyes: camera positions (K, 3), each looking at ``centre`` (3,) with ``up``.
        res: square image size in pixels.
        edges: darken the pixels where the visible face changes (the triangles' edges).

    Returns:
        K images (res, res, 3) in [0, 1] on a white background.
    """
    import torch

    from holowarp.camera import FOV_DEG, intrinsics_from_fov, look_at
    from holowarp.ops import rasterize_mesh

    K = intrinsics_from_fov(np.radians(FOV_DEG), res, res)
    x = torch.tensor(np.asarray(vertices, dtype=np.float64), dtype=torch.float32, device=device)
    f = torch.tensor(np.asarray(faces, dtype=np.int64), dtype=torch.int32, device=device)
    rgb_f = np.asarray(face_rgb, dtype=np.float64).reshape(-1, 3)
    out = []
    for eye in np.asarray(eyes, dtype=np.float64).reshape(-1, 3):
        vm = look_at(eye, centre, up)
        with torch.no_grad():
            r = rasterize_mesh(x, f, vm, K, res, res)
        fid = r["face_id"].cpu().numpy()
        n = r["normal"].cpu().numpy()
        a = r["alpha"].cpu().numpy()
        to_cam = -vm[2, :3]  # world direction from the surface back to the camera
        shade = np.abs(n @ to_cam) / np.maximum(np.linalg.norm(n, axis=-1), 1e-12)
        rgb = (0.25 + 0.75 * shade)[..., None] * rgb_f[np.maximum(fid, 0)]
        if edges:
            line = np.zeros(fid.shape, dtype=bool)
            line[:, 1:] |= fid[:, 1:] != fid[:, :-1]
            line[1:, :] |= fid[1:, :] != fid[:-1, :]
            rgb = np.where(line[..., None], 0.15 * rgb, rgb)
        out.append(a[..., None] * rgb + (1 - a[..., None]) * 1.0)
    return out


def _framing(vertices) -> tuple[np.ndarray, float]:
    """Centre (3,) and the camera distance at which a bounding sphere fills the view."""
    from holowarp.camera import FOV_DEG

    V = np.asarray(vertices, dtype=np.float64)
    lo, hi = V.min(axis=0), V.max(axis=0)
    return 0.5 * (lo + hi), 1.1 * 0.5 * float(np.linalg.norm(hi - lo)) / np.sin(np.radians(FOV_DEG) / 2)


def preview_turntable(path: Path, mesh: TetMesh, *, frames: int = 8, res: int = 256, device: str = "cpu") -> str:
    """The tet mesh's boundary, shaded (a light at the camera, Lambert), from ``frames``
    cameras on a circle around it (elevation 20 degrees, up +Z), in one row of tiles."""
    centre, dist = _framing(mesh.vertices)
    az, el = 2 * np.pi * np.arange(frames) / frames, np.radians(20.0)
    eyes = centre + dist * np.stack([np.cos(az) * np.cos(el), np.sin(az) * np.cos(el), np.full(frames, np.sin(el))], 1)
    faces = np.asarray(mesh.boundary_faces())
    tiles = _render_shaded(mesh.vertices, faces, np.tile([0.85, 0.8, 0.7], (len(faces), 1)), eyes, centre, res=res,
                           device=device)
    im = _to_image(np.concatenate(tiles, axis=1), min_height=res)
    labelled_im = labelled(np.asarray(im, dtype=np.float32) / 255.0,
                           f"{mesh.num_tets} tets, {len(mesh.boundary_faces())} boundary faces; turntable", min_height=res)
    return _save(Path(path), labelled_im)


def preview_cutaway(path: Path, mesh: TetMesh, *, axis: int = 1, res: int = 800, device: str = "cpu") -> str:
    """The tets on one side of a mid plane, coloured by face-connected component (one colour
    per component, tab10), their edges drawn, seen from the cut's side."""
    from matplotlib import colormaps

    labels, n = mesh.components()
    c = mesh.vertices[mesh.tets].mean(axis=1)
    mid = 0.5 * (mesh.vertices[:, axis].min() + mesh.vertices[:, axis].max())
    sel = c[:, axis] <= mid
    if not sel.any():
        sel[:] = True
    half = TetMesh(mesh.vertices, mesh.tets[sel], validate=False)
    faces = half.boundary_faces()
    rgb = colormaps["tab10"](labels[sel][half.boundary_face_tets()] % 10)[:, :3]
    centre, dist = _framing(mesh.vertices)
    # Look at the cut face: the kept half lies on the low side of the plane, so the camera
    # sits on the high side, a little above and to the side.
    side = np.roll(np.eye(3)[axis], 1)
    up = np.array([0.0, 0.0, 1.0]) if axis != 2 else np.array([0.0, 1.0, 0.0])
    view = np.eye(3)[axis] + 0.35 * side + 0.35 * up
    eye = centre + 0.8 * dist * view / np.linalg.norm(view)
    (img,) = _render_shaded(mesh.vertices, faces, rgb, [eye], centre, res=res, up=up, edges=True, device=device)
    im = labelled(img, f"{mesh.num_tets} tets, {n} component(s); cut at mid-plane", min_height=res)
    return _save(Path(path), im)


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


#: Fixed colour scale of the error maps, evaluation-frame units (object bbox largest side 1):
#: 0 is dark, ERROR_SCALE and beyond the brightest colour of the map.
ERROR_SCALE = 0.02
ERROR_CMAP = "inferno"


def error_colors(distances) -> np.ndarray:
    """(N, 3) uint8 colours of distances on the fixed scale [0, :data:`ERROR_SCALE`]."""
    from matplotlib import colormaps

    t = np.clip(np.asarray(distances, dtype=np.float64) / ERROR_SCALE, 0.0, 1.0)
    return (colormaps[ERROR_CMAP](t)[:, :3] * 255 + 0.5).astype(np.uint8)


def write_error_maps(out_dir, pred, gt, *, device: str = "cpu", title: str = "") -> dict:
    """The error maps of a prediction against a ground truth, in the evaluation frame:

    - ``pred_error.ply``: the predicted surface, each vertex coloured by its distance to GT;
    - ``gt_missing.ply``: GT, each vertex coloured by its distance to the prediction (what is
      missing);
    - ``error_views.png``: both, from four views, with the colour bar.

    ``pred`` and ``gt`` are ``(vertices (V, 3), faces (F, 3))`` pairs already in the
    evaluation frame. Distances are exact point-to-surface distances
    (:func:`holowarp.ops.closest.closest_distance`); the colour scale is fixed
    (:data:`ERROR_SCALE`), so maps of different runs compare by eye.

    Returns the paths and per-side distance statistics (mean, 95th percentile, max).
    """
    from holowarp.ops.closest import closest_distance
    from holowarp.surface_io import write_surface

    out = Path(out_dir)
    (pV, pF), (gV, gF) = pred, gt
    d_pred = closest_distance(gV, gF, pV, device=device)
    d_gt = closest_distance(pV, pF, gV, device=device)
    paths = {
        "pred_error": str(write_surface(out / "pred_error.ply", (pV, pF), colors=error_colors(d_pred),
                                        header=f"prediction coloured by distance to GT, {ERROR_CMAP} 0..{ERROR_SCALE}")),
        "gt_missing": str(write_surface(out / "gt_missing.ply", (gV, gF), colors=error_colors(d_gt),
                                        header=f"GT coloured by distance to the prediction, {ERROR_CMAP} 0..{ERROR_SCALE}")),
    }
    paths["error_views"] = _error_views(out / "error_views.png", (pV, pF, d_pred), (gV, gF, d_gt), title,
                                        device=device)
    stats = {name: {"mean": float(d.mean()), "p95": float(np.percentile(d, 95)), "max": float(d.max())}
             for name, d in (("pred_to_gt", d_pred), ("gt_to_pred", d_gt))}
    return {"paths": paths, "distances": stats, "scale": [0.0, ERROR_SCALE], "colormap": ERROR_CMAP}


def _colour_bar(height: int, width: int = 90) -> np.ndarray:
    """(height, width, 3) legend of :func:`error_colors`: the colour scale from 0 (bottom) to
    :data:`ERROR_SCALE`, below the label band that :func:`labelled` draws over the top."""
    from PIL import Image, ImageDraw

    top, bottom = height // 8, height - 8
    bar = np.ones((height, width, 3))
    bar[top:bottom, 8:30] = error_colors(np.linspace(ERROR_SCALE, 0.0, bottom - top)).astype(np.float64)[:, None] / 255.0
    im = Image.fromarray((bar * 255).astype(np.uint8))
    draw = ImageDraw.Draw(im)
    for k in range(3):
        draw.text((34, top + k * (bottom - top - 10) // 2), f"{ERROR_SCALE * (1 - k / 2):.3f}", fill=(0, 0, 0))
    return np.asarray(im, dtype=np.float64) / 255.0


def _error_views(path: Path, pred, gt, title: str, *, res: int = 400, device: str = "cpu") -> str:
    """Two rows (prediction error, GT missing) by four views, each face coloured by the mean
    distance of its corners on the fixed scale, and the colour bar."""
    views = np.array([(1, -1, 0.6), (-1, -1, 0.6), (-1, 1, -0.4), (1, 1, 0.9)], dtype=np.float64)
    views /= np.linalg.norm(views, axis=1, keepdims=True)
    rows = []
    for (V, F, d), label in ((pred, "prediction: distance to GT"), (gt, "GT: distance to prediction")):
        V, F = np.asarray(V, np.float64), np.asarray(F, np.int64)
        centre, dist = _framing(V)
        rgb = error_colors(np.asarray(d, np.float64)[F].mean(axis=1)).astype(np.float64) / 255.0
        tiles = _render_shaded(V, F, rgb, centre + dist * views, centre, res=res, device=device)
        row = np.concatenate(tiles + [_colour_bar(res)], axis=1)
        text = label + (f" ({title})" if title else "") + f"; {ERROR_CMAP}, 0 to {ERROR_SCALE}"
        # Kept as 8-bit: float64 copies of the 1690x800 sheet were the run's peak memory.
        rows.append(np.asarray(labelled(row, text, min_height=res), dtype=np.uint8))
    from PIL import Image

    return _save(path, Image.fromarray(np.concatenate(rows, axis=0)))
