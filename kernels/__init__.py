"""Every Warp kernel of holowarp, importable as ``holowarp.kernels``.

This package is Warp + NumPy only: no torch import may appear anywhere below it. The torch
autograd wrappers that launch these kernels live one level up, in ``holowarp.ops``.

The folder sits at the repository root as ``kernels/`` and is installed as
``holowarp.kernels`` through a package-dir mapping (see ``setup.py``), so no generic
top-level ``kernels`` module ever lands in site-packages.
"""
