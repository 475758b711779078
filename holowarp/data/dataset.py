"""The one multi-view dataset type every stage consumes.

Conventions (method.md §1): OpenCV cameras, ``viewmats`` world-to-camera, world Z up,
pixel centres at ``(x + 0.5, y + 0.5)``.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from holowarp.errors import InputError

__all__ = ["Dataset", "DatasetError", "resized_shape", "scale_intrinsics", "area_resize", "resize_view"]


class DatasetError(InputError):
    """A dataset folder or its contents cannot be used; the message names the file."""


@dataclass
class Dataset:
    """Calibrated views of one object.

    Attributes:
        images: (N, H, W, 3) float32 in [0, 1], straight (not premultiplied) RGB.
        masks: (N, H, W) float32 in [0, 1], foreground coverage (alpha).
        K: (N, 3, 3) float64 pinhole intrinsics, in pixels of this resolution.
        viewmats: (N, 4, 4) float64 world-to-camera, OpenCV axes.
        train_idx: (Ntrain,) int64 indices of training views.
        test_idx: (Ntest,) int64 indices of test views.
        normals: optional (N, H, W, 3) float32 world-space unit normals (zero outside mask).
        depths: optional (N, H, W) float32 camera z-depth in world units (0 outside mask).
        root: folder it was read from, if any.
        gt_mesh: path of the ground-truth surface (``gt.obj``) if the folder has one.
        name: short human-readable name.
    """

    images: np.ndarray
    masks: np.ndarray
    K: np.ndarray
    viewmats: np.ndarray
    train_idx: np.ndarray
    test_idx: np.ndarray
    normals: np.ndarray | None = None
    depths: np.ndarray | None = None
    root: Path | None = None
    gt_mesh: Path | None = None
    name: str = "dataset"
    meta: dict = field(default_factory=dict)

    def __post_init__(self):
        n = len(self.images)
        if self.images.ndim != 4 or self.images.shape[-1] != 3:
            raise DatasetError(f"{self.name}: images must be (N,H,W,3), got {self.images.shape}")
        if self.masks.shape != self.images.shape[:3]:
            raise DatasetError(
                f"{self.name}: masks {self.masks.shape} do not match images {self.images.shape[:3]}"
            )
        if self.K.shape != (n, 3, 3) or self.viewmats.shape != (n, 4, 4):
            raise DatasetError(
                f"{self.name}: expected K (N,3,3) and viewmats (N,4,4) with N={n}, "
                f"got {self.K.shape} and {self.viewmats.shape}"
            )
        self.train_idx = np.asarray(self.train_idx, dtype=np.int64)
        self.test_idx = np.asarray(self.test_idx, dtype=np.int64)

    @property
    def num_views(self) -> int:
        return len(self.images)

    @property
    def height(self) -> int:
        return int(self.images.shape[1])

    @property
    def width(self) -> int:
        return int(self.images.shape[2])

    def composite(self, background=(0.0, 0.0, 0.0)) -> np.ndarray:
        """Images composited over a constant ``background`` (3,), shape (N, H, W, 3)."""
        bg = np.asarray(background, dtype=np.float32)
        a = self.masks[..., None]
        return self.images * a + bg * (1.0 - a)

    def scaled(self, scale: float) -> "Dataset":
        """:meth:`resized` to ``scale`` times the longer image side (rounded, at least one
        pixel): the coarse copies of the coarse-to-fine schedules (``Stage0Config`` and
        ``TopologyConfig.coarse_scale``)."""
        return self.resized(max(1, round(max(self.height, self.width) * scale)))

    def resized(self, size: int) -> "Dataset":
        """A copy with the longer image side resized to ``size`` pixels (area filter, see
        :func:`resize_view`); ``K`` is rescaled (:func:`scale_intrinsics`) so the cameras still
        see the same rays. Loaders resize each view as it is decoded instead."""
        h, w = self.height, self.width
        nh, nw = resized_shape(h, w, size)
        if (nh, nw) == (h, w):
            return self
        n = self.num_views
        images = np.empty((n, nh, nw, 3), np.float32)
        masks = np.empty((n, nh, nw), np.float32)
        normals = None if self.normals is None else np.empty((n, nh, nw, 3), np.float32)
        depths = None if self.depths is None else np.empty((n, nh, nw), np.float32)
        for i in range(n):
            v = resize_view((nh, nw), self.images[i], self.masks[i],
                            normal=None if normals is None else self.normals[i],
                            depth=None if depths is None else self.depths[i])
            images[i], masks[i] = v["image"], v["mask"]
            if normals is not None:
                normals[i] = v["normal"]
            if depths is not None:
                depths[i] = v["depth"]
        return replace(self, images=images, masks=masks, K=scale_intrinsics(self.K, (h, w), (nh, nw)),
                       normals=normals, depths=depths)

    def subset(self, idx) -> "Dataset":
        """A dataset holding only views ``idx``; train/test membership is kept."""
        idx = np.asarray(idx, dtype=np.int64)
        remap = {int(o): i for i, o in enumerate(idx)}
        tr = [remap[i] for i in self.train_idx if int(i) in remap]
        te = [remap[i] for i in self.test_idx if int(i) in remap]
        return replace(
            self,
            images=self.images[idx],
            masks=self.masks[idx],
            K=self.K[idx],
            viewmats=self.viewmats[idx],
            normals=None if self.normals is None else self.normals[idx],
            depths=None if self.depths is None else self.depths[idx],
            train_idx=np.array(tr, np.int64),
            test_idx=np.array(te, np.int64),
        )


def resized_shape(height: int, width: int, size: int) -> tuple[int, int]:
    """``(new_height, new_width)`` with the longer side ``size`` pixels and the aspect ratio
    kept (each side rounded, at least 1)."""
    if int(size) < 1:
        raise DatasetError(f"--res must be >= 1 pixel, got {size}")
    s = int(size) / max(height, width)
    if abs(s - 1.0) < 1e-9:
        return int(height), int(width)
    return max(1, round(height * s)), max(1, round(width * s))


def scale_intrinsics(K: np.ndarray, shape: tuple[int, int], new_shape: tuple[int, int]) -> np.ndarray:
    """``K`` (..., 3, 3) for images resized from ``shape`` (H, W) to ``new_shape``.

    Pixel edges map to pixel edges (the image spans [0, W] x [0, H] with pixel centres at
    x + 0.5), so row 0 of K (fx, skew, cx) scales by new_W / W and row 1 (fy, cy) by
    new_H / H: the rays through corresponding image points are unchanged, skew included.
    """
    K = np.array(K, dtype=np.float64, copy=True)
    K[..., 0, :] *= new_shape[1] / shape[1]
    K[..., 1, :] *= new_shape[0] / shape[0]
    return K


def area_resize(a: np.ndarray, new_shape: tuple[int, int]) -> np.ndarray:
    """Area-filtered (box) resize of a (H, W) or (H, W, C) float array to ``new_shape``
    (H', W'), channel by channel in float32 (PIL's BOX filter: each output pixel averages the
    input area it covers, with fractional weights at its edges)."""
    from PIL import Image

    nh, nw = new_shape
    a = np.asarray(a, dtype=np.float32)
    if a.shape[:2] == (nh, nw):
        return a.copy()
    if a.ndim == 2:
        return np.asarray(Image.fromarray(a, mode="F").resize((nw, nh), Image.BOX))
    out = np.empty((nh, nw, a.shape[2]), np.float32)
    for c in range(a.shape[2]):
        out[..., c] = np.asarray(Image.fromarray(np.ascontiguousarray(a[..., c]), mode="F").resize((nw, nh), Image.BOX))
    return out


def resize_view(new_shape: tuple[int, int], image: np.ndarray, mask: np.ndarray, *, normal=None, depth=None) -> dict:
    """One view's arrays area-resized to ``new_shape`` (H', W').

    Args:
        image: (H, W, 3) float RGB in [0, 1].
        mask: (H, W) float coverage in [0, 1].
        normal: optional (H, W, 3) world unit normals; averaged, then renormalised (zero
            where the average vanishes).
        depth: optional (H, W) camera z-depth; averaged over covered pixels only (weighted
            by the mask), so silhouette pixels do not blend with the background's 0.

    Returns:
        dict ``image`` (H', W', 3), ``mask`` (H', W') clipped to [0, 1], and ``normal`` /
        ``depth`` when given, all float32.
    """
    out = {"image": np.clip(area_resize(image, new_shape), 0.0, 1.0),
           "mask": np.clip(area_resize(mask, new_shape), 0.0, 1.0)}
    if normal is not None:
        n = area_resize(normal, new_shape)
        ln = np.linalg.norm(n, axis=-1, keepdims=True)
        out["normal"] = np.where(ln > 1e-6, n / np.maximum(ln, 1e-6), 0.0).astype(np.float32)
    if depth is not None:
        m = area_resize(mask, new_shape)
        dm = area_resize(np.asarray(depth, np.float32) * mask, new_shape)
        out["depth"] = np.where(m > 1e-6, dm / np.maximum(m, 1e-6), 0.0).astype(np.float32)
    return out
