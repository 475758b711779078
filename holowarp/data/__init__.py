"""Multi-view datasets: one :class:`Dataset` type and loaders for the layouts of the field.

- :class:`holowarp.data.Dataset`: images, masks, intrinsics, world-to-camera matrices,
  optional normal maps, and the train/test split (method.md §1–§2).
- :func:`holowarp.data.load_dataset`: NeRF-synthetic (``transforms_*.json``), NeuS/IDR
  (``cameras_sphere.npz``) and COLMAP (``sparse/0`` + ``images/`` + ``masks/``) folders.
"""

from holowarp.data.dataset import Dataset, DatasetError

__all__ = ["Dataset", "DatasetError", "load_dataset"]


def __getattr__(name):
    if name == "load_dataset":
        from holowarp.data.loaders import load_dataset

        return load_dataset
    raise AttributeError(f"module 'holowarp.data' has no attribute {name!r}")
