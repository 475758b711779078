"""Surface metrics between two triangle meshes (method.md §9), in the evaluation frame.

Both surfaces are sampled with :func:`sample_surface` (area-weighted, 100,000 points by
default), each sample carrying the normal of the face it was drawn from. Nearest
neighbours come from ``scipy.spatial.cKDTree`` (all cores). Distances are unsquared
Euclidean distances ``d``.

- Chamfer-L1 = 0.5 (mean d(pred->gt) + mean d(gt->pred));
- Chamfer-L2 = 0.5 (mean d^2(pred->gt) + mean d^2(gt->pred));
- Hausdorff = max of the two one-sided maxima;
- precision = fraction of pred samples within ``tau`` of the gt samples, recall the
  converse, F-score their harmonic mean (tau = 0.01; ``f_score_005``, ``precision_005`` and
  ``recall_005`` at tau = 0.005, where staircases and pits of a coarse surface show. The two
  sides tell a missing part from a wrong one: a cavity carved part of the way down misses the
  recall of a lid and, having more area, loses more precision);
- normal consistency = 0.5 (mean |n_pred . n_nearest gt| + mean |n_gt . n_nearest pred|);
- the Chamfer floor: Chamfer-L1 of the ground truth against itself (two independent sample
  sets of the same size), the value a perfect prediction would get (:func:`chamfer_floor`);
- concave Chamfer: the mean distance to the prediction of the GT samples that lie deeper
  than ``concave_margin`` (0.01) inside the GT's convex hull, the regions no silhouette sees
  (:func:`concave_mask`);
- edge metrics (Neural Marching Cubes): a sample is an edge sample when some other sample
  of the same surface within 0.004 has |n . n'| < 0.2; edge precision/recall/F1 are the
  precision/recall/F-score at tau = 0.005 computed on edge samples only. Precision is NaN
  when the prediction has no edge samples and recall when the ground truth has none; F1 is
  then 0 if the other side scored 0 (all edges missed, or all predicted edges false) and NaN
  when neither surface has an edge (a smooth object: the metric does not apply).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = [
    "SurfaceMetricSettings",
    "sample_surface",
    "nearest",
    "chamfer_metrics",
    "chamfer_floor",
    "concave_mask",
    "edge_sample_mask",
    "edge_metrics",
]


@dataclass(frozen=True)
class SurfaceMetricSettings:
    """The fixed numbers of method.md §9 (evaluation-frame units)."""

    num_samples: int = 100_000
    tau: float = 0.01
    tau_fine: float = 0.005
    concave_margin: float = 0.01
    edge_radius: float = 0.004
    edge_cos: float = 0.2
    edge_tau: float = 0.005


def sample_surface(vertices, faces, num: int, *, rng=None, seed: int | None = None):
    """Area-weighted uniform samples on a triangle surface.

    Args:
        vertices: (V, 3) positions.
        faces: (F, 3) vertex indices.
        num: number of samples.
        rng: a ``numpy.random.Generator`` (else one is made from ``seed``).

    Returns:
        ``points`` (num, 3) float64, ``normals`` (num, 3) float64 unit normals of the
        sampled faces (winding orientation), ``face_index`` (num,) int64.

    Raises:
        ValueError: empty surface or zero total area.
    """
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64)
    if len(f) == 0 or len(v) == 0:
        raise ValueError("sample_surface: the surface has no triangles")
    rng = rng if rng is not None else np.random.default_rng(seed)
    a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    cr = np.cross(b - a, c - a)
    dbl_area = np.linalg.norm(cr, axis=1)
    total = dbl_area.sum()
    if not np.isfinite(total) or total <= 0:
        raise ValueError("sample_surface: the surface has zero area")
    fi = rng.choice(len(f), size=num, p=dbl_area / total)
    r1 = np.sqrt(rng.random(num))
    r2 = rng.random(num)
    w0 = 1.0 - r1
    w1 = r1 * (1.0 - r2)
    w2 = r1 * r2
    pts = a[fi] * w0[:, None] + b[fi] * w1[:, None] + c[fi] * w2[:, None]
    n = cr[fi] / dbl_area[fi, None]
    return pts, n, fi.astype(np.int64)


def nearest(src, dst, *, tree=None):
    """Distance (P,) and index (P,) of the nearest ``dst`` point for every ``src`` point."""
    from scipy.spatial import cKDTree

    tree = tree if tree is not None else cKDTree(dst)
    d, i = tree.query(src, k=1, workers=-1)
    return d, i


def _prf(d_p2g, d_g2p, tau):
    prec = float(np.mean(d_p2g < tau)) if len(d_p2g) else float("nan")
    rec = float(np.mean(d_g2p < tau)) if len(d_g2p) else float("nan")
    if np.isnan(prec) or np.isnan(rec):
        # One side has no samples: still a total miss if the other side scored 0.
        f = 0.0 if (prec == 0.0 or rec == 0.0) else float("nan")
    else:
        f = 0.0 if prec + rec == 0 else 2.0 * prec * rec / (prec + rec)
    return prec, rec, f


def chamfer_metrics(pred_pts, pred_n, gt_pts, gt_n, *, tau: float = 0.01, tau_fine: float = 0.005, trees=None,
                    distances: dict | None = None) -> dict:
    """Chamfer-L1/L2, Hausdorff, precision/recall/F-score at ``tau`` and ``tau_fine`` (keys
    ``precision``, ``recall``, ``f_score``; ``precision_005``, ``recall_005``, ``f_score_005``),
    normal consistency.

    Args:
        pred_pts, gt_pts: (P, 3), (G, 3) samples.
        pred_n, gt_n: their unit normals.
        trees: optional pre-built ``(pred_tree, gt_tree)``.
        distances: if given, receives the one-sided distances ``"pred_to_gt"`` (P,) and
            ``"gt_to_pred"`` (G,).
    """
    from scipy.spatial import cKDTree

    tp, tg = trees if trees is not None else (cKDTree(pred_pts), cKDTree(gt_pts))
    d_p2g, i_p2g = nearest(pred_pts, None, tree=tg)
    d_g2p, i_g2p = nearest(gt_pts, None, tree=tp)
    prec, rec, f = _prf(d_p2g, d_g2p, tau)
    prec_fine, rec_fine, f_fine = _prf(d_p2g, d_g2p, tau_fine)
    if distances is not None:
        distances.update(pred_to_gt=d_p2g, gt_to_pred=d_g2p)
    nc_p = np.abs(np.einsum("ij,ij->i", pred_n, gt_n[i_p2g])).mean()
    nc_g = np.abs(np.einsum("ij,ij->i", gt_n, pred_n[i_g2p])).mean()
    return {
        "chamfer_l1": float(0.5 * (d_p2g.mean() + d_g2p.mean())),
        "chamfer_l2": float(0.5 * ((d_p2g**2).mean() + (d_g2p**2).mean())),
        "hausdorff": float(max(d_p2g.max(), d_g2p.max())),
        "precision": prec,
        "recall": rec,
        "f_score": f,
        "normal_consistency": float(0.5 * (nc_p + nc_g)),
        "f_score_005": f_fine,
        "precision_005": prec_fine,
        "recall_005": rec_fine,
    }


def chamfer_floor(vertices, faces, num: int, *, rng) -> float:
    """Chamfer-L1 between two independent ``num``-sample sets of the same surface: the score
    of a perfect prediction at this sample count (sampling noise, not error)."""
    a, _, _ = sample_surface(vertices, faces, num, rng=rng)
    b, _, _ = sample_surface(vertices, faces, num, rng=rng)
    d_ab, _ = nearest(a, b)
    d_ba, _ = nearest(b, a)
    return float(0.5 * (d_ab.mean() + d_ba.mean()))


def concave_mask(points, hull_points, *, margin: float = 0.01, device: str = "cpu") -> np.ndarray:
    """(P,) bool: ``points`` inside the convex hull of ``hull_points`` and farther than
    ``margin`` from its boundary (exact distances to the hull's triangles on a BVH,
    :func:`holowarp.ops.closest.closest_distance`; inside by winding number)."""
    from scipy.spatial import ConvexHull

    from holowarp.ops.closest import closest_distance
    from holowarp.ops.winding import winding_inside

    hp = np.asarray(hull_points, dtype=np.float64)
    hull = ConvexHull(hp)
    tri = hull.simplices.copy()
    n = np.cross(hp[tri[:, 1]] - hp[tri[:, 0]], hp[tri[:, 2]] - hp[tri[:, 0]])
    inward = np.einsum("ij,ij->i", n, hull.equations[:, :3]) < 0  # qhull's facet normals point out
    tri[inward] = tri[inward][:, [0, 2, 1]]
    pts = np.asarray(points, dtype=np.float64)
    return winding_inside(hp, tri, pts, device=device) & (closest_distance(hp, tri, pts, device=device) > margin)


def edge_sample_mask(points, normals, *, radius: float = 0.004, cos_threshold: float = 0.2, tree=None) -> np.ndarray:
    """(P,) bool: samples with a neighbour within ``radius`` whose normal satisfies
    ``|n . n'| < cos_threshold`` (a crease or sharp feature passes between them)."""
    from scipy.spatial import cKDTree

    tree = tree if tree is not None else cKDTree(points)
    pairs = tree.query_pairs(radius, output_type="ndarray")
    mask = np.zeros(len(points), dtype=bool)
    if len(pairs):
        dots = np.abs(np.einsum("ij,ij->i", normals[pairs[:, 0]], normals[pairs[:, 1]]))
        sharp = pairs[dots < cos_threshold]
        mask[sharp[:, 0]] = True
        mask[sharp[:, 1]] = True
    return mask


def edge_metrics(
    pred_pts,
    pred_n,
    gt_pts,
    gt_n,
    *,
    radius: float = 0.004,
    cos_threshold: float = 0.2,
    tau: float = 0.005,
    trees=None,
) -> dict:
    """Edge precision/recall/F1 (Neural Marching Cubes, method.md §9).

    Returns:
        dict ``edge_precision``, ``edge_recall``, ``edge_f1`` and the sample counts
        ``pred_edge_samples``, ``gt_edge_samples``.
    """
    from scipy.spatial import cKDTree

    tp, tg = trees if trees is not None else (None, None)
    mp = edge_sample_mask(pred_pts, pred_n, radius=radius, cos_threshold=cos_threshold, tree=tp)
    mg = edge_sample_mask(gt_pts, gt_n, radius=radius, cos_threshold=cos_threshold, tree=tg)
    ep, eg = pred_pts[mp], gt_pts[mg]
    if len(ep) and len(eg):
        d_p2g, _ = cKDTree(eg).query(ep, workers=-1)
        d_g2p, _ = cKDTree(ep).query(eg, workers=-1)
    elif len(ep):  # gt has no edges: every predicted edge sample is a false edge
        d_p2g, d_g2p = np.full(len(ep), np.inf), np.zeros(0)
    elif len(eg):  # pred has no edges: every gt edge is missed
        d_p2g, d_g2p = np.zeros(0), np.full(len(eg), np.inf)
    else:
        d_p2g = d_g2p = np.zeros(0)
    prec, rec, f = _prf(d_p2g, d_g2p, tau)
    return {
        "edge_precision": prec,
        "edge_recall": rec,
        "edge_f1": f,
        "pred_edge_samples": int(mp.sum()),
        "gt_edge_samples": int(mg.sum()),
    }
