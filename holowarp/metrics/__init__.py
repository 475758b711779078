"""Evaluation of a reconstructed tet mesh against a ground-truth surface (method.md §9).

:func:`evaluate_mesh` returns exactly the keys of :data:`METRIC_KEYS` (plus ``psnr_mask``
when a dataset is given):

- surface (evaluation frame, 100k area-weighted samples per surface): ``chamfer_l1``,
  ``chamfer_l2``, ``hausdorff``, ``precision``, ``recall``, ``f_score`` (tau = 0.01),
  ``normal_consistency``, ``edge_precision``, ``edge_recall``, ``edge_f1``;
- volume: ``volume_iou`` (winding-number inside test on 100k uniform points);
- topology of the prediction: ``components`` (face-connected tet components), ``manifold``
  (boundary edge- and vertex-manifold), ``genus`` (of the boundary), ``tets``;
- tet quality: ``inverted_ratio`` (signed volume <= 0, on the mesh AS GIVEN),
  ``min_dihedral_mean``, ``min_dihedral_worst`` (degrees), ``aspect_ratio_mean``.

Frames. The GT surface is mapped to the evaluation frame of method.md §1 by its own
bounding box (centred at the origin, largest side 1) and the prediction by the SAME map, so
relative placement is kept. A prediction reconstructed from a dataset written by
``python -m holowarp.synth`` lives in that dataset's world, whose ``gt.obj`` is already
normalised: the map is then the identity and the prediction is evaluated unchanged.

The prediction's surface is the outward boundary of the tet mesh after orienting every tet
positively (so winding numbers and normals are consistent); orientation does not change the
geometry. A plain triangle surface is accepted as a prediction too; its tet keys are then
``None``.

LPIPS: not part of this dictionary. It scores RGB renders, which the mesh evaluator does
not make (its renders are silhouettes, for ``psnr_mask``); :func:`image.lpips_status`
reports whether LPIPS could run at all, and ``python -m holowarp.evaluate`` prints that
note in its table. Keeping it out of the JSON keeps the top level exactly the contract.
"""

from __future__ import annotations

import os
import time
from pathlib import Path

import numpy as np

from holowarp.metrics.image import lpips_status, mask_psnr, psnr, ssim
from holowarp.metrics.surface import (
    SurfaceMetricSettings,
    chamfer_metrics,
    edge_metrics,
    edge_sample_mask,
    sample_surface,
)
from holowarp.metrics.volume import inside_mask, volume_iou

__all__ = [
    "METRIC_KEYS",
    "EvaluationError",
    "evaluate_mesh",
    "load_surface",
    "unit_cube_transform",
    "normalize_to_unit_cube",
    "render_masks",
    "sample_surface",
    "chamfer_metrics",
    "edge_metrics",
    "edge_sample_mask",
    "volume_iou",
    "inside_mask",
    "psnr",
    "mask_psnr",
    "ssim",
    "lpips_status",
    "SurfaceMetricSettings",
]

#: The top-level keys of the evaluation JSON, in order (the issue's contract).
METRIC_KEYS = (
    "chamfer_l1",
    "chamfer_l2",
    "hausdorff",
    "precision",
    "recall",
    "f_score",
    "normal_consistency",
    "volume_iou",
    "edge_precision",
    "edge_recall",
    "edge_f1",
    "components",
    "manifold",
    "genus",
    "tets",
    "inverted_ratio",
    "min_dihedral_mean",
    "min_dihedral_worst",
    "aspect_ratio_mean",
)


class EvaluationError(ValueError):
    """Inputs to the evaluation cannot be used; the message names the file and reason."""


def unit_cube_transform(reference_vertices) -> tuple[float, np.ndarray]:
    """``(scale, translation)`` with ``p' = scale * p + translation`` mapping the bounding box of
    ``reference_vertices`` (V, 3) to one centred at the origin with largest side 1."""
    v = np.asarray(reference_vertices, dtype=np.float64)
    lo, hi = v.min(0), v.max(0)
    ext = float((hi - lo).max())
    if not np.isfinite(ext) or ext <= 0:
        raise EvaluationError("the reference mesh has a zero-size bounding box")
    s = 1.0 / ext
    return s, -0.5 * (lo + hi) * s


def normalize_to_unit_cube(vertices, reference_bbox) -> np.ndarray:
    """Map ``vertices`` (V, 3) by the unit-cube normalisation of ``reference_bbox``.

    Args:
        vertices: points to map.
        reference_bbox: (2, 3) ``[min corner, max corner]`` of the reference (GT) mesh.
    """
    lo, hi = np.asarray(reference_bbox, dtype=np.float64)
    s, t = unit_cube_transform(np.stack([lo, hi]))
    return np.asarray(vertices, dtype=np.float64) * s + t


def load_surface(path: str | os.PathLike):
    """(V (N, 3) float64, F (F, 3) int32, tetmesh or None) from a surface or tet-mesh file.

    OBJ positions are welded (UV seams); tet meshes give their oriented boundary.
    """
    from holowarp.mesh_io import TET_FORMATS, MeshIOError, read_surface, read_tetmesh

    path = Path(path)
    if not path.is_file():
        raise EvaluationError(f"{path}: no such file")
    ext = path.suffix.lower()
    try:
        if ext in TET_FORMATS:
            tm = read_tetmesh(path)
            if tm.num_tets == 0:
                raise EvaluationError(f"{path}: the tet mesh has no tetrahedra")
            V, F = tm.oriented()[0].surface_mesh()
            return V, F, tm
        if ext == ".obj":
            from holowarp.data.obj import ObjError, load_obj

            try:
                m = load_obj(path, load_texture=False).welded()
            except ObjError as e:
                raise EvaluationError(str(e)) from e
            return m.positions, m.faces, None
        V, F = read_surface(path)
        return V, F, None
    except MeshIOError as e:
        raise EvaluationError(str(e)) from e


def _as_surface(x, what: str):
    from holowarp.tetmesh import TetMesh

    if isinstance(x, (str, os.PathLike)):
        return load_surface(x)
    if isinstance(x, TetMesh):
        if x.num_tets == 0:
            raise EvaluationError(f"{what}: the tet mesh has no tetrahedra")
        V, F = x.oriented()[0].surface_mesh()
        return V, F, x
    if isinstance(x, (tuple, list)) and len(x) == 2:
        V = np.asarray(x[0], dtype=np.float64)
        F = np.asarray(x[1], dtype=np.int64)
        if V.ndim != 2 or V.shape[1] != 3 or F.ndim != 2 or F.shape[1] != 3:
            raise EvaluationError(f"{what}: expected (vertices (V,3), faces (F,3)), got {V.shape}, {F.shape}")
        return V, F, None
    raise EvaluationError(f"{what}: expected a path, a TetMesh or a (vertices, faces) pair, got {type(x).__name__}")


def render_masks(vertices, faces, dataset, views, *, supersample: int | None = None, device: str = "cpu") -> np.ndarray:
    """Silhouettes (len(views), H, W) of a surface seen by ``dataset``'s cameras ``views``.

    ``supersample`` defaults to the one the dataset was synthesised with (so soft edges
    compare like with like), else 2.
    """
    from holowarp.render_gt import GTRenderer

    if supersample is None:
        supersample = int((dataset.meta or {}).get("holowarp", {}).get("supersample", 2))
    r = GTRenderer(vertices, faces, supersample=supersample, smooth_normals=False, device=device)
    views = np.asarray(views, dtype=np.int64)
    out = np.empty((len(views), dataset.height, dataset.width), np.float32)
    for j, _r in r.render_views(dataset.viewmats[views], dataset.K[views], dataset.width, dataset.height):
        out[j] = _r["mask"]
    return out


def evaluate_mesh(
    pred,
    gt,
    *,
    dataset=None,
    num_samples: int = 100_000,
    seed: int = 0,
    volume_points: int = 100_000,
    device: str = "cpu",
    details: bool = False,
):
    """Every metric of method.md §9 for ``pred`` against ``gt`` (see the module docstring).

    Args:
        pred: a :class:`holowarp.TetMesh`, a tet-mesh file (``.vtu``, ``.msh``, ``.npz``,
            ``.usd[a|c]``), or a surface (file or ``(V, F)`` pair; tet keys are then None).
        gt: ground-truth surface: file (``.obj``/``.ply``/... or a tet-mesh file) or pair.
        dataset: optional :class:`holowarp.data.Dataset`; adds ``psnr_mask`` over its test
            views (or all views if it has none). The prediction is rendered in the
            dataset's world, i.e. BEFORE the evaluation-frame map.
        num_samples: surface samples per mesh.
        seed: seeds the surface and volume sampling.
        volume_points: uniform points for volume IoU (>= 100k per method.md §9).
        device: Warp device of the inside tests and renders.
        details: also return a second dict with non-contract information (sample counts,
            edge sample counts, the frame map, timings, the LPIPS note).

    Returns:
        dict with exactly :data:`METRIC_KEYS` (+ ``psnr_mask``), values float/int/bool/None;
        or ``(metrics, details)``.
    """
    t0 = time.perf_counter()
    if num_samples < 1:
        raise EvaluationError(f"num_samples must be >= 1, got {num_samples}")
    pV, pF, ptm = _as_surface(pred, "prediction")
    gV, gF, _ = _as_surface(gt, "ground truth")
    if len(pF) == 0:
        raise EvaluationError("prediction: the surface has no triangles")
    s, t = unit_cube_transform(gV)
    gVn = gV * s + t
    pVn = pV * s + t
    rng = np.random.default_rng(seed)
    try:
        pp, pn, _ = sample_surface(pVn, pF, num_samples, rng=rng)
        gp, gn, _ = sample_surface(gVn, gF, num_samples, rng=rng)
    except ValueError as e:
        raise EvaluationError(str(e)) from e
    from scipy.spatial import cKDTree

    st = SurfaceMetricSettings()
    trees = (cKDTree(pp), cKDTree(gp))
    t1 = time.perf_counter()
    out = chamfer_metrics(pp, pn, gp, gn, tau=st.tau, trees=trees)
    t2 = time.perf_counter()
    em = edge_metrics(pp, pn, gp, gn, radius=st.edge_radius, cos_threshold=st.edge_cos, tau=st.edge_tau, trees=trees)
    t3 = time.perf_counter()
    out["volume_iou"] = volume_iou(pVn, pF, gVn, gF, num_points=volume_points, rng=rng, device=device)
    t4 = time.perf_counter()
    out.update({k: em[k] for k in ("edge_precision", "edge_recall", "edge_f1")})
    if ptm is not None:
        q = ptm.quality_summary()
        oriented = ptm.oriented()[0]
        out.update(
            components=int(ptm.num_components()),
            manifold=bool(oriented.manifold()["manifold"]),
            genus=int(oriented.genus()),
            tets=int(ptm.num_tets),
            inverted_ratio=float(q["inverted_ratio"]),
            min_dihedral_mean=float(q["min_dihedral_mean"]),
            min_dihedral_worst=float(q["min_dihedral_worst"]),
            aspect_ratio_mean=float(q["aspect_ratio_mean"]),
        )
    else:
        out.update({k: None for k in METRIC_KEYS[11:]})
    metrics = {k: out[k] for k in METRIC_KEYS}
    t5 = time.perf_counter()
    if dataset is not None:
        views = dataset.test_idx if len(dataset.test_idx) else np.arange(dataset.num_views)
        pm = render_masks(pV, pF, dataset, views, device=device)
        metrics["psnr_mask"] = mask_psnr(pm, dataset.masks[views])
    t6 = time.perf_counter()
    if not details:
        return metrics
    ok, why = lpips_status()
    info = {
        "num_samples": num_samples,
        "volume_points": volume_points,
        "seed": seed,
        "pred_edge_samples": em["pred_edge_samples"],
        "gt_edge_samples": em["gt_edge_samples"],
        "frame": {"scale": s, "translation": t.tolist(), "doc": "p_eval = scale * p + translation (GT bbox)"},
        "pred_surface": {"vertices": int(len(pV)), "faces": int(len(pF))},
        "gt_surface": {"vertices": int(len(gV)), "faces": int(len(gF))},
        "lpips": {"available": ok, "reason": why, "computed": False,
                  "note": "LPIPS scores RGB renders; the mesh evaluator renders silhouettes only"},
        "seconds": {
            "sampling": t1 - t0,
            "chamfer": t2 - t1,
            "edges": t3 - t2,
            "volume_iou": t4 - t3,
            "tet_quality": t5 - t4,
            "psnr_mask": t6 - t5,
            "total": t6 - t0,
        },
    }
    if dataset is not None:
        info["psnr_mask_views"] = [int(i) for i in views]
    return metrics, info
