"""Metrics of method.md §9, in the evaluation frame of §1 (:mod:`holowarp.frame`).

- :mod:`holowarp.metrics.surface`: area-weighted surface sampling, Chamfer-L1/L2,
  Hausdorff, precision/recall/F-score, normal consistency, NMC edge metrics;
- :mod:`holowarp.metrics.volume`: winding-number inside tests and volume IoU;
- :mod:`holowarp.metrics.image`: PSNR (RGB and silhouettes), SSIM, LPIPS availability;
- :mod:`holowarp.metrics.evaluate`: :func:`evaluate_mesh`, every metric of a prediction
  against a ground truth, with the JSON contract :data:`METRIC_KEYS`.
"""

from holowarp.metrics.evaluate import METRIC_KEYS, EvaluationError, evaluate_mesh, load_surface

__all__ = ["METRIC_KEYS", "EvaluationError", "evaluate_mesh", "load_surface"]
