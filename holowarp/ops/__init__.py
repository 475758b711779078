"""Torch-facing differentiable operators built on the Warp kernels in ``holowarp.kernels``.

Each operator is a ``torch.autograd.Function`` that launches Warp kernels; a plain-PyTorch
reference of the same computation lives beside it (``*_ref`` modules) and the tests compare
the two, as gsplat does.

Public API (contracts):

- ``rasterize_surfels(means, quats, scales, opacities, colors, viewmat, K, width, height,
  background=None) -> dict`` (2D Gaussian surfels, method.md §3)
- ``rasterize_mesh(vertices, faces, viewmat, K, width, height) -> dict`` (tet boundary
  triangles, method.md §6)

Imports are lazy so that ``import holowarp.ops`` does not compile kernels it won't use.
"""

from __future__ import annotations

import importlib

__all__ = ["rasterize_surfels", "rasterize_mesh"]

_LAZY = {
    "rasterize_surfels": "holowarp.ops.surfels",
    "rasterize_mesh": "holowarp.ops.mesh_raster",
}


def __getattr__(name):
    mod = _LAZY.get(name)
    if mod is None:
        raise AttributeError(f"module 'holowarp.ops' has no attribute {name!r}")
    return getattr(importlib.import_module(mod), name)
