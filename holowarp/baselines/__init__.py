"""Baselines every reconstruction is compared against.

- :mod:`holowarp.baselines.hull`: the visual hull, silhouette carving -> marching cubes ->
  fTetWild (:func:`~holowarp.baselines.hull.visual_hull`, :func:`~holowarp.baselines.hull.run_visual_hull`);
  its command is ``python -m holowarp.baselines.visual_hull DATASET --out DIR``.
"""
