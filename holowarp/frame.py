"""The evaluation frame of method.md §1.

The ground-truth mesh translated and uniformly scaled so its bounding box is centred at the
origin with largest side 1 ("unit-cube normalisation", as Occupancy Networks). Datasets
written by :mod:`holowarp.synthesis` live in this frame; :mod:`holowarp.metrics` reports
every distance in it.
"""

from __future__ import annotations

import numpy as np

from holowarp.errors import InputError

__all__ = ["FrameError", "unit_cube_transform"]


class FrameError(InputError):
    """The points do not define an evaluation frame (empty, non-finite or flat box)."""


def unit_cube_transform(reference_vertices) -> tuple[float, np.ndarray]:
    """``(scale, translation)`` with ``p' = scale * p + translation`` mapping the bounding box
    of ``reference_vertices`` (V, 3) to one centred at the origin with largest side 1.

    Raises:
        FrameError: no points, non-finite coordinates, or a zero-size bounding box.
    """
    v = np.asarray(reference_vertices, dtype=np.float64).reshape(-1, 3)
    if len(v) == 0:
        raise FrameError("the reference mesh has no vertices")
    if not np.isfinite(v).all():
        bad = int(np.flatnonzero(~np.isfinite(v).all(axis=1))[0])
        raise FrameError(f"the reference mesh has a non-finite vertex (index {bad}: {v[bad].tolist()})")
    lo, hi = v.min(0), v.max(0)
    ext = float((hi - lo).max())
    if ext <= 0:
        raise FrameError("the reference mesh has a zero-size bounding box (all vertices coincide)")
    s = 1.0 / ext
    return s, -0.5 * (lo + hi) * s
