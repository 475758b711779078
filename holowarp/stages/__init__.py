"""The stages of the HoloTetSphere method, one module per method.md section.

- ``gaussian_init``: §3, stage 0 — 2DGS surfels trained from the images (``holowarp.gs2d``).
- ``tet_init``: §4, tetrahedral initialisation — convex hull of the surfel centres, scaled by
  1.1, tetrahedralised with fTetWild, one surfel per tet.
- ``topology``: §5, topology optimisation — the per-vertex field phi, L_topo, pruning.
- ``geometry``: §6, geometry optimisation — mesh-only blocks driven by L_geo.
- ``cleanup``: §7, flip / drop / one component / manifold repair.
- ``export``: §7, every output file and the previews.
"""
