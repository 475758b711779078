"""The one multi-view dataset type every stage consumes.

Conventions (method.md §1): OpenCV cameras, ``viewmats`` world-to-camera, world Z up,
pixel centres at ``(x + 0.5, y + 0.5)``.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from holowarp.errors import InputError

__all__ = ["Dataset", "DatasetError"]


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

    def resized(self, size: int) -> "Dataset":
        """A copy with the longer image side resized to ``size`` pixels (area filter).

        ``K`` is rescaled so the cameras still see the same rays.
        """
        from PIL import Image

        h, w = self.height, self.width
        s = size / max(h, w)
        if abs(s - 1.0) < 1e-9:
            return self
        nh, nw = max(1, round(h * s)), max(1, round(w * s))

        def rs(stack, channels):
            out = np.empty((len(stack), nh, nw) + ((channels,) if channels else ()), np.float32)
            for i, im in enumerate(stack):
                if channels:
                    for c in range(channels):
                        out[i, ..., c] = np.asarray(
                            Image.fromarray(im[..., c].astype(np.float32), mode="F").resize(
                                (nw, nh), Image.BOX
                            )
                        )
                else:
                    out[i] = np.asarray(
                        Image.fromarray(im.astype(np.float32), mode="F").resize((nw, nh), Image.BOX)
                    )
            return out

        K = self.K.copy()
        K[:, 0, :] *= nw / w
        K[:, 1, :] *= nh / h
        normals = None
        if self.normals is not None:
            normals = rs(self.normals, 3)
            nrm = np.linalg.norm(normals, axis=-1, keepdims=True)
            normals = np.where(nrm > 1e-6, normals / np.maximum(nrm, 1e-6), 0.0).astype(np.float32)
        depths = None
        if self.depths is not None:
            # Area-average depth over covered pixels only, so edges don't blend with 0.
            m = rs(self.masks, 0)
            dm = rs(self.depths * self.masks, 0)
            depths = np.where(m > 1e-6, dm / np.maximum(m, 1e-6), 0.0).astype(np.float32)
        return replace(
            self,
            images=np.clip(rs(self.images, 3), 0, 1),
            masks=np.clip(rs(self.masks, 0), 0, 1),
            K=K,
            normals=normals,
            depths=depths,
        )

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
