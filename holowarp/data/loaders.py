"""Dataset loaders: one entry point for every folder layout a user brings (method.md §1).

:func:`load_dataset` detects the layout and returns one :class:`holowarp.data.Dataset`:

- NeRF-synthetic / Blender (``transforms_train.json`` [+ ``transforms_test.json``]):
  :mod:`holowarp.data.nerf_synthetic`;
- NeuS / IDR (``cameras_sphere.npz`` + ``image/`` + ``mask/``): :mod:`holowarp.data.neus`;
- COLMAP (``sparse/0/cameras.bin|txt``, ``images.bin|txt`` + ``images/`` + ``masks/``):
  :mod:`holowarp.data.colmap` (``python -m holowarp.poses`` writes this layout from photos).

Every problem raises :class:`DatasetError` naming the file and the reason.
"""

from __future__ import annotations

import os
from pathlib import Path

from holowarp.data.colmap import find_model, load_colmap, write_colmap
from holowarp.data.dataset import Dataset, DatasetError
from holowarp.data.nerf_synthetic import load_nerf_synthetic, write_nerf_synthetic
from holowarp.data.neus import decompose_projection, load_neus

__all__ = [
    "FORMATS",
    "detect_format",
    "load_dataset",
    "load_nerf_synthetic",
    "load_neus",
    "load_colmap",
    "write_nerf_synthetic",
    "write_colmap",
    "decompose_projection",
]

#: The dataset layouts :func:`load_dataset` reads, with what identifies each.
FORMATS = {
    "nerf_synthetic": "transforms_train.json (and transforms_test.json), RGBA images whose alpha is the mask",
    "neus": "cameras_sphere.npz with image/ and mask/ folders (NeuS/IDR, DTU)",
    "colmap": "a COLMAP model in sparse/0 (cameras.bin|txt, images.bin|txt) with images/ and masks/ folders, "
              "masks matched to images by file stem",
}


def detect_format(path: str | os.PathLike) -> str:
    """``"nerf_synthetic"``, ``"neus"`` or ``"colmap"`` for a dataset folder; :class:`DatasetError`
    otherwise."""
    root = Path(path)
    if not root.exists():
        raise DatasetError(f"{root}: no such dataset folder")
    if not root.is_dir():
        raise DatasetError(f"{root}: a dataset must be a folder")
    if (root / "transforms_train.json").is_file() or (root / "transforms_test.json").is_file():
        return "nerf_synthetic"
    if (root / "cameras_sphere.npz").is_file():
        return "neus"
    if find_model(root) is not None:
        return "colmap"
    raise DatasetError(f"{root}: unknown dataset layout (expected " + "; or ".join(FORMATS.values()) + ")")


def load_dataset(path: str | os.PathLike, *, res: int | None = None, **kwargs) -> Dataset:
    """Load a dataset folder, detecting its layout.

    Args:
        path: dataset folder.
        res: if given, the longer image side in pixels: each view is area-resized as it is
            decoded and ``K`` rescaled (:func:`holowarp.data.dataset.scale_intrinsics`).
        kwargs: passed to the layout's loader (e.g. ``test_every``, ``workers``).
    """
    fmt = detect_format(path)
    loader = {"nerf_synthetic": load_nerf_synthetic, "neus": load_neus, "colmap": load_colmap}[fmt]
    return loader(path, res=res, **kwargs)
