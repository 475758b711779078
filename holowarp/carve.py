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
field initialisation uses with the stage-0 surfels' depth maps. Where the dataset has normal
maps, :func:`depth_from_normals` first corrects those depth maps by integrating the normals
from the silhouette inwards (a cavity's floor that the surfels leave too high).

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
    "lid_pixels",
    "nearest_depths",
    "depth_from_normals",
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


def _normal_edges(ok, n, ray, log0, *, jump: float, crease: float, grazing: float):
    """The 4-neighbour edges :func:`depth_from_normals` integrates over: ``(a, b, g)``, the
    two pixels' indices among ``ok``'s pixels (row-major) and the log-depth step from ``a``
    to ``b`` the normals give, for the edges its cuts keep. ``n`` (H, W, 3) camera-frame unit
    normals, ``ray`` (H, W, 3) pixel rays with z = 1, ``log0`` (H, W) the render's log depth."""
    H, W = ok.shape
    idx = np.full((H, W), -1, dtype=np.int64)
    idx[ok] = np.arange(int(ok.sum()))
    ray_len = np.linalg.norm(ray, axis=-1)
    a_list, b_list, g_list = [], [], []
    for dy, dx in ((0, 1), (1, 0)):
        both = ok[: H - dy, : W - dx] & ok[dy:, dx:]
        ys, xs = np.nonzero(both)
        ys2, xs2 = ys + dy, xs + dx
        nm = n[ys, xs] + n[ys2, xs2]
        nm /= np.maximum(np.linalg.norm(nm, axis=-1, keepdims=True), 1e-12)
        dp, dq = (nm * ray[ys, xs]).sum(-1), (nm * ray[ys2, xs2]).sum(-1)
        good = (dp < -grazing * ray_len[ys, xs]) & (dq < -grazing * ray_len[ys2, xs2])
        g = np.log(np.abs(dp) / np.maximum(np.abs(dq), 1e-12))
        good &= np.abs(log0[ys2, xs2] - log0[ys, xs] - g) <= jump
        g1, g2 = (np.log(np.abs((nk * ray[ys, xs]).sum(-1)) / np.maximum(np.abs((nk * ray[ys2, xs2]).sum(-1)), 1e-12))
                  for nk in (n[ys, xs], n[ys2, xs2]))
        good &= np.abs(g1 - g2) <= crease
        a_list.append(idx[ys[good], xs[good]])
        b_list.append(idx[ys2[good], xs2[good]])
        g_list.append(g[good])
    return np.concatenate(a_list), np.concatenate(b_list), np.concatenate(g_list)


def _integrate(a, b, g, anchored, target):
    """Least-squares log depths of :func:`depth_from_normals`: ``(solve, x)``, which of the
    M pixels are solved for (those whose region, connected by the edges ``(a, b)`` with
    steps ``g``, holds an ``anchored`` pixel) and their log depths (sum(solve),), minimising
    ``sum_edges (x_b - x_a - g)^2 + sum_anchored (x - target)^2``."""
    from scipy import sparse
    from scipy.sparse.csgraph import connected_components
    from scipy.sparse.linalg import spsolve

    m = len(anchored)
    n_comp, comp = connected_components(sparse.coo_matrix((np.ones(len(a)), (a, b)), shape=(m, m)), directed=False)
    has_anchor = np.zeros(n_comp, dtype=bool)
    has_anchor[comp[anchored]] = True
    solve = has_anchor[comp]
    if not solve.any():
        return solve, np.zeros(0)
    # Unknowns: the anchored regions' pixels only (an edge's two ends share a region).
    sub = np.full(m, -1, dtype=np.int64)
    sub[solve] = np.arange(int(solve.sum()))
    keep = solve[a]
    a, b, g = sub[a[keep]], sub[b[keep]], g[keep]
    e, k = len(g), int(solve.sum())
    D = sparse.csr_matrix((np.concatenate([-np.ones(e), np.ones(e)]), (np.tile(np.arange(e), 2), np.concatenate([a, b]))),
                          shape=(e, k))
    w = anchored[solve].astype(np.float64)
    return solve, spsolve((D.T @ D + sparse.diags(w)).tocsc(), D.T @ g + w * target[solve])


def depth_from_normals(depth, alpha, normal, viewmat, K, *, jump: float = 0.02, crease: float = 0.01,
                       grazing: float = 0.4, rim: int = 2) -> np.ndarray:
    """A rendered depth map (H, W) corrected by integrating a normal map, anchored at the
    silhouette: the depth the normals imply away from the outline, where the render is only
    as good as its optimisation got (a cavity's floor the surfels left as a lid).

    Between 4-neighbours ``p, q`` a plane with normal ``n`` (their mean, camera frame) gives
    ``log z_q - log z_p = log(<n, r_p> / <n, r_q>)`` exactly, ``r`` the pixels' rays
    ``K^-1 (u + 0.5, v + 0.5, 1)`` and ``z`` camera depth. The corrected map minimises, over
    the pixels where the render is opaque (``alpha > 0.5``) and the map holds a normal,
    ``sum_edges (log z_q - log z_p - g_pq)^2 + sum_rim (log z_p - log depth_p)^2`` (one
    sparse solve, scipy). Anchors (``rim``): the pixels within ``rim`` pixels of the opaque
    region's outline, where the silhouettes pin the render. Left out, so that the
    integration never bridges what the normals cannot see:

    - edges whose normal faces either pixel's ray by less than ``grazing`` (the cosine): a
      steep wall's log-depth slope is too large to integrate;
    - edges across a step of the render (``|log depth_q - log depth_p - g_pq| > jump``): an
      occluding edge, where the near and far surfaces do not meet (its depth jump is what
      the normals cannot give);
    - edges across a crease: ``p``'s plane and ``q``'s plane, each extended to the other
      pixel, give log-depth steps more than ``crease`` apart (the mean normal's step is
      then a guess, and an occluding crease looks like one);
    - every pixel of a region those cuts leave without an anchor: it keeps ``depth``.

    Measured on the stage-0 depth maps of the quality suite (128², the fast preset's 800
    iterations): see :attr:`holowarp.config.TopologyConfig.depth_carve_normals`.

    Args:
        depth: (H, W) camera depth of the render (metres; the stage-0 median depth).
        alpha: (H, W) its opacity.
        normal: (H, W, 3) world-space normal map, zero where it holds none.
        viewmat: (4, 4) world-to-camera (OpenCV); K: (3, 3) intrinsics.
        jump, crease, grazing, rim: see above (log-depth units, log-depth units, cosine,
            pixels).

    Returns:
        (H, W) float32 corrected depth (``depth`` where nothing is corrected).
    """
    from scipy.ndimage import binary_erosion

    depth = np.asarray(depth, dtype=np.float64)
    H, W = depth.shape
    opaque = np.asarray(alpha) > 0.5
    nw = np.asarray(normal, dtype=np.float64)
    ok = opaque & (np.linalg.norm(nw, axis=-1) > 0.5) & (depth > 0)
    out = depth.astype(np.float32)
    if not ok.any():
        return out
    vm = np.asarray(viewmat, dtype=np.float64)
    n = nw @ vm[:3, :3].T
    n /= np.maximum(np.linalg.norm(n, axis=-1, keepdims=True), 1e-12)
    u, v = np.meshgrid(np.arange(W) + 0.5, np.arange(H) + 0.5)
    ray = np.stack([u, v, np.ones_like(u)], -1) @ np.linalg.inv(np.asarray(K, dtype=np.float64)).T
    log0 = np.log(np.where(ok, depth, 1.0))
    a, b, g = _normal_edges(ok, n, ray, log0, jump=jump, crease=crease, grazing=grazing)
    anchored = (opaque & ~binary_erosion(opaque, iterations=max(int(rim), 1)))[ok]
    solve, x = _integrate(a, b, g, anchored, log0[ok])
    if not solve.any():
        return out
    flat = out[ok]
    flat[solve] = np.exp(x).astype(np.float32)
    out[ok] = flat
    return out


def in_front_of_surface(dataset, points, views, depths, alphas, *, tol, min_views: int = 1,
                        window: int = 1) -> np.ndarray:
    """(P,) bool: ``points`` (P, 3) that at least ``min_views`` of ``views`` see in front of
    the surface, i.e. empty space the silhouettes cannot show (a concavity seen from outside).

    ``depths`` and ``alphas`` (len(views), H, W) are rendered depth and opacity maps of the
    surface (e.g. the stage-0 surfels' median depth). A point is in front of the surface in a
    view when it projects into the image where the surface is opaque (``alpha > 0.5`` over the
    whole ``(2 window + 1)²`` neighbourhood) and its camera depth is smaller than the NEAREST
    surface depth of that neighbourhood by more than ``tol``: taking the nearest depth keeps
    thin walls whole where the depth map jumps (a bowl's rim in front of its floor).
    ``tol`` is a number (scene units) or a per-pixel map (len(views), H, W).
    """
    P = np.asarray(points, dtype=np.float64)
    count = np.zeros(len(P), dtype=np.int64)
    H, W = dataset.height, dataset.width
    for j, v in enumerate(views):
        opaque, near = _opaque_nearest(depths[j], alphas[j], window)
        uv, z = project_points(P, dataset.viewmats[v], dataset.K[v])
        col = np.floor(uv[:, 0]).astype(np.int64)
        row = np.floor(uv[:, 1]).astype(np.int64)
        ok = (z > 1e-6) & (col >= 0) & (col < W) & (row >= 0) & (row < H)
        hit = np.zeros(len(P), dtype=bool)
        r, c = row[ok], col[ok]
        t = tol if np.ndim(tol) == 0 else np.asarray(tol[j])[r, c]
        hit[ok] = opaque[r, c] & (z[ok] < near[r, c] - t)
        count += hit
    return count >= min_views


def nearest_depths(depth, alpha, corrected, *, window: int = 1):
    """A surface's depth map and its normal-corrected version (:func:`depth_from_normals`),
    each pixel's the nearest of its ``(2 window + 1)²`` neighbourhood, as
    :func:`in_front_of_surface` takes them: ``(opaque, near_surface, near_corrected)``, (H, W):
    bool, the pixels whose whole neighbourhood is opaque (``alpha > 0.5``), and float64,
    the nearest depths over the opaque pixels of the neighbourhood (inf where there are none,
    and, for the corrected one, where it is unknown: NaN or inf)."""
    from scipy.ndimage import minimum_filter

    opaque, near0 = _opaque_nearest(depth, alpha, window)
    dc = np.asarray(corrected, dtype=np.float64)
    nearc = minimum_filter(np.where(opaque & np.isfinite(dc), dc, np.inf), size=2 * window + 1)
    return opaque, near0, nearc


def _opaque_nearest(depth, alpha, window: int):
    """``(opaque, near)`` (H, W): the pixels whose whole ``(2 window + 1)²`` neighbourhood has
    ``alpha > 0.5``, and the nearest ``depth`` over those pixels of each neighbourhood (inf
    where there are none)."""
    from scipy.ndimage import minimum_filter

    size = 2 * window + 1
    opaque = minimum_filter((np.asarray(alpha) > 0.5).astype(np.uint8), size=size) > 0
    near = minimum_filter(np.where(opaque, np.asarray(depth, dtype=np.float64), np.inf), size=size)
    return opaque, near


def lid_pixels(depth, alpha, corrected, *, gap: float, window: int = 1):
    """Where a surface's depth map closes a cavity that the normal-corrected depth opens.

    ``depth``, ``alpha``, ``corrected`` (H, W): a rendered surface's depth and opacity and
    the same depth corrected by the normal maps (:func:`depth_from_normals`, NaN or inf
    where it is unknown), each taken as the nearest of its neighbourhood
    (:func:`nearest_depths`, so a rim next to a deeper floor is not a lid). Returns
    ``(lid, near_corrected)``: (H, W) bool, the pixels whose corrected depth lies more than
    ``gap`` behind the surface (a lid over a cavity), and (H, W) float64, that nearest
    corrected depth (inf where unknown or not opaque)."""
    opaque, near0, nearc = nearest_depths(depth, alpha, corrected, window=window)
    return opaque & np.isfinite(nearc) & (nearc > near0 + gap), nearc
