"""Baselines every reconstruction is compared against.

- :func:`holowarp.baselines.visual_hull.visual_hull`: silhouette carving -> marching cubes ->
  fTetWild (``python -m holowarp.baselines.visual_hull DATASET --out DIR``).
"""

from __future__ import annotations

__all__ = ["visual_hull", "run_visual_hull"]


def __getattr__(name):
    if name in __all__:
        from holowarp.baselines import visual_hull as _vh

        return getattr(_vh, name)
    raise AttributeError(f"module 'holowarp.baselines' has no attribute {name!r}")
