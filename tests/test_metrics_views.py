"""The mesh-against-images checks of real captures (issue 16, :mod:`holowarp.metrics.views`):
``mesh_mask_iou``, ``mesh_surfel_normal_cos`` and ``mesh_see_through_covered``, each against
an independent reference, and on a real rendered frame whose hole the images show."""

from __future__ import annotations

from collections import deque
from types import SimpleNamespace

import numpy as np
import torch

from holowarp.metrics.views import mesh_image_checks, mesh_renders, see_through
from holowarp.primitives import box_tetmesh


def _flood_see_through(mask: np.ndarray) -> np.ndarray:
    """Reference: background pixels NOT reached by a 4-connected breadth-first flood of the
    background from every border pixel."""
    H, W = mask.shape
    bg = mask <= 0.5
    reached = np.zeros_like(bg)
    q = deque((y, x) for y in range(H) for x in range(W) if (y in (0, H - 1) or x in (0, W - 1)) and bg[y, x])
    for y, x in q:
        reached[y, x] = True
    while q:
        y, x = q.popleft()
        for dy, dx in ((1, 0), (-1, 0), (0, 1), (0, -1)):
            v, u = y + dy, x + dx
            if 0 <= v < H and 0 <= u < W and bg[v, u] and not reached[v, u]:
                reached[v, u] = True
                q.append((v, u))
    return bg & ~reached


def test_see_through_matches_a_breadth_first_flood_from_the_border():
    rng = np.random.default_rng()
    for p in (0.3, 0.5, 0.6):
        mask = (rng.random((23, 31)) < p).astype(np.float32) * rng.uniform(0.51, 1.0, (23, 31))
        got, want = see_through(mask), _flood_see_through(mask)
        np.testing.assert_array_equal(got, want)
    ring = np.zeros((9, 9), np.float32)
    ring[2:7, 2:7] = 1.0
    ring[4, 4] = 0.2  # a one-pixel hole, soft-edged mask below 0.5
    assert see_through(ring).sum() == 1 and see_through(ring)[4, 4]


def test_image_checks_match_a_dense_reference_on_random_views():
    rng = np.random.default_rng()
    H, W, n = 17, 13, 3
    mesh_views, surfel_views, masks = [], [], []
    for _ in range(n):
        mesh_views.append({"alpha": rng.random((H, W)).astype(np.float32),
                           "normal": rng.normal(size=(H, W, 3)).astype(np.float32)})
        surfel_views.append({"alpha": rng.random((H, W)).astype(np.float32),
                             "normal": rng.normal(size=(H, W, 3)).astype(np.float32)})
        masks.append(rng.random((H, W)).astype(np.float32))
    got = mesh_image_checks(mesh_views, np.stack(masks), surfel_views)
    # Reference in float64 torch: IoU over all pixels of all views, cosine over pixels both cover.
    a = torch.tensor(np.stack([m["alpha"] for m in mesh_views]), dtype=torch.float64) > 0.5
    b = torch.tensor(np.stack(masks), dtype=torch.float64) > 0.5
    iou = (a & b).sum().item() / (a | b).sum().item()
    both = a & (torch.tensor(np.stack([s["alpha"] for s in surfel_views])) > 0.5)
    n1 = torch.tensor(np.stack([m["normal"] for m in mesh_views]), dtype=torch.float64)[both]
    n2 = torch.tensor(np.stack([s["normal"] for s in surfel_views]), dtype=torch.float64)[both]
    cos = torch.nn.functional.cosine_similarity(n1, n2, dim=-1).mean().item()
    holes = np.stack([_flood_see_through(m) for m in masks])
    covered = (a.numpy() & holes).sum() / holes.sum()
    assert abs(got["mesh_mask_iou"] - iou) < 1e-12
    assert abs(got["mesh_surfel_normal_cos"] - cos) < 1e-5
    assert abs(got["mesh_see_through_covered"] - covered) < 1e-12
    assert len(got["per_view"]["mesh_see_through_covered"]) == n


def _frame(filled: bool):
    """A 6 x 6 x 2-cell slab of side 1 in x, y around the origin, with (or without) its
    central 2 x 2 cells removed: a square frame whose hole goes through along z."""
    cells = np.ones((6, 6, 2), dtype=bool)
    if not filled:
        cells[2:4, 2:4, :] = False
    return box_tetmesh((6, 6, 2), size=(1.0, 1.0, 0.3), origin=(-0.5, -0.5, -0.15), cell_mask=cells)


def _top_view():
    """A one-view 64 x 64 dataset: a camera 3 above the slab, looking down -z (OpenCV: x
    right, y down, z forward)."""
    vm = torch.tensor([[1, 0, 0, 0], [0, -1, 0, 0], [0, 0, -1, 3], [0, 0, 0, 1]], dtype=torch.float32)
    K = torch.tensor([[90.0, 0, 32], [0, 90.0, 32], [0, 0, 1]], dtype=torch.float32)
    return SimpleNamespace(viewmats=vm[None], K=K[None], width=64, height=64)


def test_a_mesh_that_closes_the_hole_the_images_show_covers_its_see_through_pixels():
    ds = _top_view()
    frame = mesh_renders(_frame(False), ds, [0])
    mask = (frame[0]["alpha"] > 0.5).astype(np.float32)  # the images: the frame itself
    assert 80 < see_through(mask).sum() < 150  # the hole: (1/3 * 90 / 2.85)^2 ~ 110 px
    own = mesh_image_checks(frame, mask[None], frame)
    assert own["mesh_mask_iou"] == 1.0 and own["mesh_see_through_covered"] == 0.0
    slab = mesh_renders(_frame(True), ds, [0])
    closed = mesh_image_checks(slab, mask[None], frame)
    assert closed["mesh_see_through_covered"] == 1.0
    assert closed["mesh_mask_iou"] < 0.95 and abs(closed["mesh_surfel_normal_cos"]) > 0.99
    # Without see-through pixels the check has nothing to measure.
    assert mesh_image_checks(slab, np.ones((1, 64, 64)), slab)["mesh_see_through_covered"] is None


def test_the_silhouette_preview_paints_red_only_where_the_mesh_closes_a_see_through_hole(tmp_path):
    from PIL import Image

    from holowarp.previews import preview_silhouettes

    ds = _top_view()
    mask = (mesh_renders(_frame(False), ds, [0])[0]["alpha"] > 0.5).astype(np.float32)
    photo = np.full((64, 64, 3), 0.5, np.float32)

    def red_pixels(mesh_alpha, name):
        path = preview_silhouettes(tmp_path / name, [photo], [mesh_alpha], mask[None], [0])
        img = np.asarray(Image.open(path).convert("RGB"), dtype=np.float32) / 255.0
        return int(((img[..., 0] > 0.6) & (img[..., 1] < 0.35) & (img[..., 2] < 0.35)).sum())

    assert red_pixels(mask, "own.png") == 0
    assert red_pixels(mesh_renders(_frame(True), ds, [0])[0]["alpha"], "closed.png") > 100
