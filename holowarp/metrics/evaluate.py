"""Evaluation of a reconstructed tet mesh against a ground-truth surface (method.md §9).

:func:`evaluate_mesh` returns exactly the keys of :data:`METRIC_KEYS` (plus ``psnr_mask``
when a dataset is given):

- surface (evaluation frame, 100k area-weighted samples per surface): ``chamfer_l1``,
  ``chamfer_l2``, ``hausdorff``, ``precision``, ``recall``, ``f_score`` (tau = 0.01),
  ``normal_consistency``, ``edge_precision``, ``edge_recall``, ``edge_f1``, ``f_score_005``
  with its ``precision_005`` and ``recall_005`` (tau = 0.005), ``chamfer_l1_floor`` (GT
  against itself at the same sample count: what a perfect prediction scores) and
  ``concave_chamfer`` (the mean distance to the prediction of the GT samples deeper than
  0.01 inside the GT's convex hull, where silhouettes are blind; NaN for a convex GT);
- volume: ``volume_iou`` (winding-number inside test on 100k uniform points);
- topology of the prediction: ``components`` (face-connected tet components), ``manifold``
  (boundary edge- and vertex-manifold), ``genus`` (of the boundary, summed over its shells),
  ``tets``, ``boundary_shells`` (connected pieces of the boundary: 1 unless a sealed void
  adds an inner one, which no view sees and ``genus`` does not show), ``overlapping_edges``
  (boundary edges whose tets' dihedral angles add up to more than 360°: the tets overlap in
  space there and the surface cuts through itself, though none is inverted; 0 for an
  embedded mesh);
- tet quality: ``inverted_ratio`` (signed volume <= 0, on the mesh AS GIVEN),
  ``min_dihedral_mean``, ``min_dihedral_worst`` (degrees), ``aspect_ratio_mean``.

Frames. The GT surface is mapped to the evaluation frame of method.md §1 by its own
bounding box (:func:`holowarp.frame.unit_cube_transform`) and the prediction by the SAME
map, so relative placement is kept. A prediction reconstructed from a dataset written by
``python -m holowarp.synth`` lives in that dataset's world, whose ``gt.obj`` is already
normalised: the map is then the identity and the prediction is evaluated unchanged.

The prediction's surface is the outward boundary of the tet mesh after orienting every tet
positively (so winding numbers and normals are consistent); orientation does not change the
geometry. A plain triangle surface is accepted as a prediction too; its tet keys are then
``None``.

LPIPS: not part of this dictionary. It scores RGB renders, which the mesh evaluator does
not make (its renders are silhouettes, for ``psnr_mask``); :func:`holowarp.metrics.image.lpips_status`
reports whether LPIPS could run at all, and ``python -m holowarp.evaluate`` prints that
note in its table. Keeping it out of the JSON keeps the top level exactly the contract.
"""

from __future__ import annotations

import os
import time
from pathlib import Path

import numpy as np

from holowarp.errors import InputError
from holowarp.frame import FrameError, unit_cube_transform
from holowarp.metrics.image import lpips_status, mask_psnr
from holowarp.metrics.surface import (
    SurfaceMetricSettings,
    chamfer_floor,
    chamfer_metrics,
    concave_mask,
    edge_metrics,
    sample_surface,
)
from holowarp.metrics.volume import volume_iou

__all__ = ["METRIC_KEYS", "TET_KEYS", "EvaluationError", "evaluate_mesh", "evaluation_surfaces", "load_surface"]

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
    "f_score_005",
    "chamfer_l1_floor",
    "concave_chamfer",
    "boundary_shells",
    "overlapping_edges",
    "precision_005",
    "recall_005",
)
#: The keys that describe the prediction's tets (``None`` for a surface prediction).
#: ``boundary_shells``: connected pieces of the boundary surface. One object without a
#: sealed void has one; ``genus`` sums over shells, so a void would hide in it.
#: ``overlapping_edges``: boundary edges whose tets wrap past a full turn (overlap in space).
TET_KEYS = ("components", "manifold", "genus", "tets", "inverted_ratio", "min_dihedral_mean", "min_dihedral_worst",
            "aspect_ratio_mean", "boundary_shells", "overlapping_edges")


class EvaluationError(InputError):
    """Inputs to the evaluation cannot be used; the message names the file and reason."""


def load_surface(path: str | os.PathLike):
    """(V (N, 3) float64, F (F, 3) int32, tetmesh or None) from a surface or tet-mesh file.

    Surfaces are welded (UV seams); tet meshes give their oriented boundary.
    """
    from holowarp.mesh_io import TET_FORMATS, read_tetmesh
    from holowarp.surface_io import read_surface

    path = Path(path)
    if path.suffix.lower() in TET_FORMATS:
        tm = read_tetmesh(path)
        if tm.num_tets == 0:
            raise EvaluationError(f"{path}: the tet mesh has no tetrahedra")
        V, F = tm.oriented()[0].surface_mesh()
        return V, F, tm
    V, F = read_surface(path)
    return V, F, None


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


def evaluation_surfaces(pred, gt):
    """``((pred_vertices, pred_faces), (gt_vertices, gt_faces))`` in the evaluation frame
    (the GT's bounding box centred at the origin, largest side 1), from anything
    :func:`evaluate_mesh` accepts."""
    pV, pF, _ = _as_surface(pred, "prediction")
    gV, gF, _ = _as_surface(gt, "ground truth")
    s, t = unit_cube_transform(gV)
    return (pV * s + t, np.asarray(pF)), (gV * s + t, np.asarray(gF))


def _tet_keys(ptm) -> dict:
    """The topology and tet-quality keys of the prediction (``None`` for a surface)."""
    if ptm is None:
        return {k: None for k in TET_KEYS}
    q = ptm.quality_summary()
    oriented = ptm.oriented()[0]
    return {
        "components": int(ptm.num_components()),
        "manifold": bool(oriented.manifold()["manifold"]),
        "genus": int(oriented.genus()),
        "tets": int(ptm.num_tets),
        "inverted_ratio": float(q["inverted_ratio"]),
        "min_dihedral_mean": float(q["min_dihedral_mean"]),
        "min_dihedral_worst": float(q["min_dihedral_worst"]),
        "aspect_ratio_mean": float(q["aspect_ratio_mean"]),
        "boundary_shells": int(ptm.boundary_shells()),
        "overlapping_edges": int(oriented.overlapping_edges()),
    }


def _surface_keys(pVn, pF, gVn, gF, *, num_samples: int, rng, volume_points: int, device: str, timings: dict):
    """Surface and volume metrics of two surfaces already in the evaluation frame."""
    from scipy.spatial import cKDTree

    t0 = time.perf_counter()
    try:
        pp, pn, _ = sample_surface(pVn, pF, num_samples, rng=rng)
        gp, gn, _ = sample_surface(gVn, gF, num_samples, rng=rng)
    except ValueError as e:
        raise EvaluationError(str(e)) from None
    st = SurfaceMetricSettings()
    trees = (cKDTree(pp), cKDTree(gp))
    t1 = time.perf_counter()
    dist: dict = {}
    out = chamfer_metrics(pp, pn, gp, gn, tau=st.tau, tau_fine=st.tau_fine, trees=trees, distances=dist)
    concave = concave_mask(gp, gVn, margin=st.concave_margin)
    out["concave_chamfer"] = float(dist["gt_to_pred"][concave].mean()) if concave.any() else float("nan")
    t2 = time.perf_counter()
    em = edge_metrics(pp, pn, gp, gn, radius=st.edge_radius, cos_threshold=st.edge_cos, tau=st.edge_tau, trees=trees)
    t3 = time.perf_counter()
    out["volume_iou"] = volume_iou(pVn, pF, gVn, gF, num_points=volume_points, rng=rng, device=device)
    # Drawn after everything else from the same generator, so the other metrics keep their samples.
    out["chamfer_l1_floor"] = chamfer_floor(gVn, gF, num_samples, rng=rng)
    timings.update(sampling=t1 - t0, chamfer=t2 - t1, edges=t3 - t2, volume_iou=time.perf_counter() - t3)
    out.update({k: em[k] for k in ("edge_precision", "edge_recall", "edge_f1")})
    return out, em


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
        gt: ground-truth surface: file (any format of :mod:`holowarp.surface_io`, or a
            tet-mesh file) or pair.
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
    if volume_points < 1:
        raise EvaluationError(f"volume_points must be >= 1, got {volume_points}")
    pV, pF, ptm = _as_surface(pred, "prediction")
    gV, gF, _ = _as_surface(gt, "ground truth")
    if len(pF) == 0:
        raise EvaluationError("prediction: the surface has no triangles")
    try:
        s, t = unit_cube_transform(gV)
    except FrameError as e:
        name = str(gt) if isinstance(gt, (str, os.PathLike)) else "ground truth"
        raise EvaluationError(f"{name}: {e}") from None
    if not np.isfinite(pV).all():
        raise EvaluationError("prediction: the surface has non-finite vertex coordinates")
    timings: dict = {}
    rng = np.random.default_rng(seed)
    out, em = _surface_keys(pV * s + t, pF, gV * s + t, gF, num_samples=num_samples, rng=rng,
                            volume_points=volume_points, device=device, timings=timings)
    t4 = time.perf_counter()
    out.update(_tet_keys(ptm))
    metrics = {k: out[k] for k in METRIC_KEYS}
    timings["tet_quality"] = time.perf_counter() - t4
    views = None
    if dataset is not None:
        from holowarp.render_gt import render_silhouettes

        t5 = time.perf_counter()
        views = dataset.test_idx if len(dataset.test_idx) else np.arange(dataset.num_views)
        pm = render_silhouettes(pV, pF, dataset, views, device=device)
        metrics["psnr_mask"] = mask_psnr(pm, dataset.masks[views])
        timings["psnr_mask"] = time.perf_counter() - t5
    timings["total"] = time.perf_counter() - t0
    if not details:
        return metrics
    return metrics, _details(em, s, t, pV, pF, gV, gF, views, num_samples, volume_points, seed, timings)


def _details(em, s, t, pV, pF, gV, gF, views, num_samples, volume_points, seed, timings) -> dict:
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
        "seconds": timings,
    }
    if views is not None:
        info["psnr_mask_views"] = [int(i) for i in views]
    return info
