"""Checks of the tet mesh against the images, for data without a ground-truth mesh (issue 16).

On held-out views (the dataset's test views):

- ``mesh_mask_iou``: the tet mesh's own silhouettes (its boundary rasterised with
  :func:`holowarp.ops.rasterize_mesh`, alpha > 0.5) against the masks (> 0.5), as
  intersection over union of all those pixels;
- ``mesh_surfel_normal_cos``: the mean cosine between the mesh's rendered normals and the
  surfels' rendered normals (both world space), over the pixels both cover (alpha > 0.5).

- ``mesh_see_through_covered``: of the masks' see-through pixels (background enclosed by
  the object: a mask's background components that do not touch the image border, i.e. the
  views through a handle, a tunnel or a gap), the fraction the mesh's silhouette covers;
  ``None`` when the views show no such pixel. A mesh of the right genus leaves them open
  (only its one-pixel rim falls on them); one that closed a tunnel the images show covers
  them. On lego (real, 128², fast preset) two thirds of the mesh-only pixels lie in such
  holes (846 of 1275 on the 10 held-out views, 81% of the 1046 see-through pixels), so the
  mask IoU there measures topology more than the rim.

The surfels fit the photos; the mesh has to stand on its own. A mesh that is a lumpy blob
with the right silhouettes shows a low normal agreement even where its IoU is high.
"""

from __future__ import annotations

import numpy as np
import torch

from holowarp.tetmesh import TetMesh

__all__ = ["mesh_renders", "mesh_image_checks", "see_through"]


def mesh_renders(mesh: TetMesh, dataset, views, *, device: str = "cpu") -> list[dict]:
    """Per view of ``views``: the mesh boundary's ``alpha`` (H, W) and world ``normal``
    (H, W, 3) as float32 arrays."""
    from holowarp.ops import rasterize_mesh

    x = torch.tensor(np.asarray(mesh.vertices), dtype=torch.float32, device=device)
    faces = torch.tensor(np.asarray(mesh.boundary_faces()), dtype=torch.int32, device=device)
    out = []
    with torch.no_grad():
        for v in views:
            r = rasterize_mesh(x, faces, dataset.viewmats[v], dataset.K[v], dataset.width, dataset.height)
            out.append({"alpha": r["alpha"].cpu().numpy(), "normal": r["normal"].cpu().numpy()})
    return out


def see_through(mask) -> np.ndarray:
    """(H, W) bool: the see-through pixels of a mask (H, W) in [0, 1]: background (<= 0.5)
    pixels whose 4-connected background component does not touch the image border."""
    from scipy import ndimage

    bg = np.asarray(mask) <= 0.5
    labels, _ = ndimage.label(bg)
    border = np.unique(np.concatenate([labels[0], labels[-1], labels[:, 0], labels[:, -1]]))
    return bg & ~np.isin(labels, border[border > 0])


def mesh_image_checks(mesh_views: list[dict], masks, surfel_views: list[dict]) -> dict:
    """``mesh_mask_iou``, ``mesh_surfel_normal_cos``, ``mesh_see_through_covered`` (module
    docstring) and their per-view values, from :func:`mesh_renders` of the views, their masks
    (N, H, W) and the surfels' renders of the same views (dicts with ``alpha`` (H, W) and
    ``normal`` (H, W, 3))."""
    inter = union = 0
    cos_sum, cos_n = 0.0, 0
    holes = covered = 0
    per_iou, per_cos, per_holes = [], [], []
    for m, mask, s in zip(mesh_views, masks, surfel_views):
        a = m["alpha"] > 0.5
        b = np.asarray(mask) > 0.5
        i, u = int((a & b).sum()), int((a | b).sum())
        inter, union = inter + i, union + u
        per_iou.append(i / u if u else 1.0)
        h = see_through(mask)
        nh, nc = int(h.sum()), int((a & h).sum())
        holes, covered = holes + nh, covered + nc
        per_holes.append(nc / nh if nh else None)
        both = a & (np.asarray(s["alpha"]) > 0.5)
        n1 = m["normal"][both]
        n2 = np.asarray(s["normal"])[both]
        c = (n1 * n2).sum(-1) / np.maximum(np.linalg.norm(n1, axis=-1) * np.linalg.norm(n2, axis=-1), 1e-12)
        cos_sum, cos_n = cos_sum + float(c.sum()), cos_n + len(c)
        per_cos.append(float(c.mean()) if len(c) else None)
    return {
        "mesh_mask_iou": inter / union if union else 1.0,
        "mesh_surfel_normal_cos": cos_sum / cos_n if cos_n else None,
        "mesh_see_through_covered": covered / holes if holes else None,
        "per_view": {"mesh_mask_iou": per_iou, "mesh_surfel_normal_cos": per_cos,
                     "mesh_see_through_covered": per_holes},
    }
