"""The stages of the HoloTetSphere method, one module per method.md section, in order (each
imports only earlier ones; ``tests/test_layers.py`` checks it).

- ``gaussian_init``: §3, stage 0 — 2DGS surfels trained from the images.
- ``tet_init``: §4, tetrahedral initialisation — convex hull of the surfel centres, scaled by
  1.1, tetrahedralised with fTetWild.
- ``topology``: §4–5, one surfel per tet; topology optimisation — the per-vertex field phi,
  L_topo, pruning.
- ``geometry``: §6, geometry optimisation — mesh-only blocks driven by L_geo.
- ``cleanup``: §7, flip / drop / one component / manifold repair.
- ``polish``: the silhouette polish — one-tet pits lifted, then the cleaned boundary fitted
  to the masks, several views per step, and fitted again briefly after ``improve`` (issue
  12; not in the paper).
- ``improve``: §7b, element improvement — flips, smoothing, sliver removal.
- ``export``: §7, every output file.
- ``objects``: §11, scene level — the final mesh split into objects, one tet mesh and one
  deformable body each.

The order of events between them is :meth:`holowarp.config.Schedule.events`; the pipeline
that runs them is :mod:`holowarp.pipeline`.
"""
