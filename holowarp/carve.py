"""The visual hull of a dataset's masks: one carve for every user.

A point is inside the visual hull when it projects inside every training mask. The carve
field is the minimum over views of the mask sampled bilinearly at the point's projection
(:mod:`holowarp.ops.carve`), so its 0.5 level set is the hull boundary with sub-pixel
placement from soft mask edges. Users:

- preflight (:mod:`holowarp.preflight`): do the masks agree on a 3D object at all?
- the vertex-field initialisation of §5 (:func:`holowarp.stages.topology.init_phi`);
- stage 0's initial surfels (:func:`sample_points_in_hull`);
- the visual-hull baseline (:mod:`holowarp.baselines.hull`), on a grid;
- the prune's genus guard, whose bound is the hull's genus (:func:`hull_genus`): a tunnel
  some view sees through is a tunnel of the hull.

Silhouettes cannot see concavities; a rendered surface can: :func:`in_front_of_surface`
marks the points some view sees in front of the surface (depth carving), which the vertex
field initialisation uses with the stage-0 surfels' depth maps.

Regions: :func:`look_region` is the cube every camera looks into (centred where the optical
axes meet, half-size the nearest camera distance); :func:`view_sphere` the sphere every
camera sees whole.
"""

from __future__ import annotations

import numpy as np

from holowarp.camera import axes_focus, camera_center, project_points
from holowarp.ops.carve import carve_grid, carve_points

__all__ = [
    "hull_field",
    "inside_hull",
    "hull_grid",
    "look_region",
    "view_sphere",
    "sample_points_in_hull",
    "in_front_of_surface",
    "hull_genus",
    "solid_genus",
]


def _views(dataset, views):
    return np.asarray(dataset.train_idx if views is None else views, dtype=np.int64)


def _tolerance(dataset, v, tolerance) -> dict:
    """Carve arguments (outliers, margin_px) of a :class:`holowarp.config.HullTolerance`
    (``None``: the plain visual hull)."""
    if tolerance is None:
        return {}
    k, m = tolerance.counts(len(v), dataset.width, dataset.height)
    return {"outliers": k, "margin_px": m}


def hull_field(dataset, points, views=None, *, outside_is_empty: bool = True, tolerance=None, device: str = "cpu"):
    """Carve field (P,) and the number of views seeing each point (P,) at world ``points``
    (P, 3), over ``views`` (default: the training views). ``tolerance``: a
    :class:`holowarp.config.HullTolerance` (all but k views, dilated masks); ``None`` trusts
    every mask as it is."""
    v = _views(dataset, views)
    return carve_points(dataset.viewmats[v], dataset.K[v], dataset.masks[v], points,
                        outside_is_empty=outside_is_empty, device=device, **_tolerance(dataset, v, tolerance))


def inside_hull(dataset, points, views=None, *, threshold: float = 0.5, tolerance=None,
                device: str = "cpu") -> np.ndarray:
    """(P,) bool: ``points`` (P, 3) inside the visual hull of ``views`` (every view sees the
    whole object, so a point outside an image is outside the hull), with ``tolerance`` as in
    :func:`hull_field`."""
    field, _ = hull_field(dataset, points, views, tolerance=tolerance, device=device)
    return field > threshold


def hull_grid(dataset, views, origin, spacing: float, shape, *, outside_is_empty: bool = True,
              device: str = "cpu") -> np.ndarray:
    """The carve field (NX, NY, NZ) float32 at grid nodes ``origin + (i, j, k) * spacing``."""
    v = _views(dataset, views)
    return carve_grid(dataset.viewmats[v], dataset.K[v], dataset.masks[v], origin, spacing, shape,
                      outside_is_empty=outside_is_empty, device=device)


def solid_genus(occupied: np.ndarray) -> int:
    """Genus of the boundary of the largest 26-connected piece of a voxel set (NX, NY, NZ)
    bool, its cavities filled: ``1 - chi`` with ``chi`` the Euler characteristic of the union
    of the closed voxels (vertices - edges + faces - cubes of the cubical complex). A ball
    gives 0, a solid torus 1, a plate with three holes 3."""
    from scipy import ndimage

    lab, n = ndimage.label(occupied, structure=np.ones((3, 3, 3), dtype=bool))
    if n == 0:
        return 0
    solid = lab == (np.argmax(np.bincount(lab.ravel())[1:]) + 1)
    # The complement's 6-connected pieces that do not reach the border are cavities.
    air, _ = ndimage.label(~np.pad(solid, 1))
    solid = np.pad(solid, 1) | (air != air[0, 0, 0])
    p = np.pad(solid, 1)

    def cells(axes: tuple) -> int:
        # The cells spanning the ``axes`` directions of the complex one grid step less long
        # there: present when any voxel around them is.
        shape = tuple(d - 1 if i in axes else d for i, d in enumerate(p.shape))
        out = np.zeros(shape, dtype=bool)
        for offs in np.ndindex(*(2 if i in axes else 1 for i in range(3))):
            out |= p[tuple(slice(o, o + shape[i]) for i, o in enumerate(offs))]
        return int(out.sum())

    faces = sum(cells((a,)) for a in range(3))
    edges = sum(cells(tuple(b for b in range(3) if b != a)) for a in range(3))
    chi = cells((0, 1, 2)) - edges + faces - int(p.sum())
    return 1 - chi


def hull_genus(dataset, lo, hi, views=None, *, cells: int = 160, device: str = "cpu") -> int:
    """Genus of the visual hull of ``views`` (default: the training views) inside the box
    ``lo``..``hi`` (3,), carved on a grid of ``cells`` along the box's longest side
    (:func:`solid_genus` of the carve field above 0.5). A tunnel some view sees through is a
    tunnel of the hull, so no reconstruction whose tunnels the views show has a larger genus;
    see-through gaps finer than the grid are missed (they are finer than a tet as well)."""
    lo, hi = np.asarray(lo, dtype=np.float64), np.asarray(hi, dtype=np.float64)
    spacing = float((hi - lo).max()) / int(cells)
    if not spacing > 0:
        return 0
    shape = tuple(int(np.ceil(e / spacing)) + 7 for e in hi - lo)
    field = hull_grid(dataset, views, lo - 3 * spacing, spacing, shape, device=device)
    return solid_genus(field > 0.5)


def look_region(viewmats) -> tuple[np.ndarray, float]:
    """``(centre (3,), half_size)``: the point nearest to every optical axis, and the distance
    of the nearest camera from it; anything all cameras see in front of them lies in the cube
    of that half-size around the centre."""
    centre = axes_focus(viewmats)
    dists = np.linalg.norm(np.array([camera_center(V) for V in viewmats]) - centre, axis=1)
    return centre, float(dists.min())


def view_sphere(dataset, views) -> tuple[np.ndarray, float]:
    """Centre (3,) and radius of a sphere every camera in ``views`` sees whole: the point
    nearest to all optical axes, and the largest radius inside the narrowest field of view."""
    V = dataset.viewmats[views]
    o = np.stack([camera_center(m) for m in V])
    c = axes_focus(V)
    K = dataset.K[views]
    half = np.minimum.reduce([
        np.arctan(K[:, 0, 2] / K[:, 0, 0]), np.arctan((dataset.width - K[:, 0, 2]) / K[:, 0, 0]),
        np.arctan(K[:, 1, 2] / K[:, 1, 1]), np.arctan((dataset.height - K[:, 1, 2]) / K[:, 1, 1]),
    ])  # fmt: skip
    r = float(np.min(np.linalg.norm(o - c, axis=1) * np.sin(half)))
    return c, r


def sample_points_in_hull(dataset, n_points: int, *, views=None, candidates: int = 200_000, seed: int = 0,
                          tolerance=None, device: str = "cpu") -> tuple[np.ndarray, float]:
    """Up to ``n_points`` uniform random points inside the visual hull of ``views``.

    Candidates are uniform in the cube around :func:`view_sphere`; a candidate is kept when
    at least one view sees it and every view that sees it has mask >= 0.5 there (views it
    falls outside of do not count: the sphere, not the whole cube, is seen by all). If the
    masks carve (almost) everything away, the whole view sphere is used instead.
    ``tolerance`` as in :func:`hull_field`.

    Returns:
        points (P, 3) float64 and the sampling radius.
    """
    rng = np.random.default_rng(seed)
    idx = _views(dataset, views)
    c, r = view_sphere(dataset, idx)
    pts = c + rng.uniform(-r, r, (candidates, 3))
    field, seen = hull_field(dataset, pts, idx, outside_is_empty=False, tolerance=tolerance, device=device)
    keep = (field >= 0.5) & (seen > 0)
    if keep.sum() < max(16, n_points // 50):
        keep = np.linalg.norm(pts - c, axis=1) <= r
    pts = pts[keep]
    if len(pts) > n_points:
        pts = pts[rng.choice(len(pts), n_points, replace=False)]
    return pts, r


def in_front_of_surface(dataset, points, views, depths, alphas, *, tol: float, min_views: int = 1,
                        window: int = 1) -> np.ndarray:
    """(P,) bool: ``points`` (P, 3) that at least ``min_views`` of ``views`` see in front of
    the surface, i.e. empty space the silhouettes cannot show (a concavity seen from outside).

    ``depths`` and ``alphas`` (len(views), H, W) are rendered depth and opacity maps of the
    surface (e.g. the stage-0 surfels' median depth). A point is in front of the surface in a
    view when it projects into the image where the surface is opaque (``alpha > 0.5`` over the
    whole ``(2 window + 1)²`` neighbourhood) and its camera depth is smaller than the NEAREST
    surface depth of that neighbourhood by more than ``tol``: taking the nearest depth keeps
    thin walls whole where the depth map jumps (a bowl's rim in front of its floor).
    """
    from scipy.ndimage import minimum_filter

    P = np.asarray(points, dtype=np.float64)
    count = np.zeros(len(P), dtype=np.int64)
    H, W = dataset.height, dataset.width
    size = 2 * window + 1
    for j, v in enumerate(views):
        d = np.where(alphas[j] > 0.5, depths[j], 0.0)
        opaque = minimum_filter((alphas[j] > 0.5).astype(np.uint8), size=size) > 0
        near = minimum_filter(np.where(opaque, d, np.inf), size=size)
        uv, z = project_points(P, dataset.viewmats[v], dataset.K[v])
        col = np.floor(uv[:, 0]).astype(np.int64)
        row = np.floor(uv[:, 1]).astype(np.int64)
        ok = (z > 1e-6) & (col >= 0) & (col < W) & (row >= 0) & (row < H)
        hit = np.zeros(len(P), dtype=bool)
        r, c = row[ok], col[ok]
        hit[ok] = opaque[r, c] & (z[ok] < near[r, c] - tol)
        count += hit
    return count >= min_views
