"""What every dataset loader shares: reading images and masks, checking poses and numbers,
each failure a :class:`holowarp.data.DatasetError` that names the file and the reason."""

from __future__ import annotations

import math
import os
import re
from pathlib import Path

import numpy as np

from holowarp.data.dataset import DatasetError

__all__ = ["IMAGE_EXTS", "read_image", "find_image", "rigid_c2w", "check_mask", "number", "frame_number", "list_images"]

#: Image file extensions the loaders read (case-insensitive).
IMAGE_EXTS = (".png", ".jpg", ".jpeg")


def read_image(path: Path) -> np.ndarray:
    """(H, W[, C]) float32 in [0, 1]; 16-bit images are scaled by 65535."""
    from PIL import Image

    try:
        with Image.open(path) as im:
            im.load()
            if im.mode in ("I;16", "I;16B", "I;16L", "I"):
                return np.asarray(im, dtype=np.float32) / 65535.0
            if im.mode not in ("L", "LA", "RGB", "RGBA"):
                im = im.convert("RGBA" if "A" in im.getbands() else "RGB")
            return np.asarray(im, dtype=np.float32) / 255.0
    except OSError as e:
        raise DatasetError(f"{path}: cannot read image ({e})") from None


def find_image(root: Path, file_path, where: str) -> Path:
    """The image a NeRF-synthetic ``file_path`` names (with or without its extension)."""
    if not isinstance(file_path, str) or not file_path:
        raise DatasetError(f"{where}: file_path must be a non-empty string, got {file_path!r}")
    p = (root / file_path).resolve() if not os.path.isabs(file_path) else Path(file_path)
    if p.suffix.lower() in IMAGE_EXTS and p.is_file():
        return p
    for ext in IMAGE_EXTS:
        q = p.with_name(p.name + ext)
        if q.is_file():
            return q
    raise DatasetError(f"{where}: image {file_path!r} not found (tried {p} with .png/.jpg)")


def number(value, where: str, key: str, *, lo: float | None = None, hi: float | None = None, open_lo: bool = True,
           open_hi: bool = True) -> float:
    """``value`` as a finite float inside the given bounds, or a DatasetError naming ``key``."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise DatasetError(f"{where}: {key} must be a number, got {value!r}")
    v = float(value)
    if not math.isfinite(v):
        raise DatasetError(f"{where}: {key} must be finite, got {value!r}")
    low_bad = lo is not None and (v <= lo if open_lo else v < lo)
    high_bad = hi is not None and (v >= hi if open_hi else v > hi)
    if low_bad or high_bad:
        a = "(" if open_lo else "["
        b = ")" if open_hi else "]"
        raise DatasetError(f"{where}: {key} must lie in {a}{lo}, {hi}{b}, got {value!r}")
    return v


def rigid_c2w(c2w, where: str) -> np.ndarray:
    """A 4x4 camera-to-world rigid transform from a (4, 4) or (3, 4) nested list, made exactly
    orthonormal; DatasetError when it is not numeric, not finite, or not rigid."""
    try:
        c2w = np.asarray(c2w, dtype=np.float64)
    except (TypeError, ValueError):
        raise DatasetError(f"{where}: transform_matrix must be a 4x4 matrix of numbers, got {c2w!r}"[:300]) from None
    if c2w.shape == (3, 4):
        c2w = np.vstack([c2w, [0.0, 0.0, 0.0, 1.0]])
    if c2w.shape != (4, 4):
        raise DatasetError(f"{where}: transform_matrix must be 4x4 (or 3x4), got shape {c2w.shape}")
    if not np.isfinite(c2w).all():
        raise DatasetError(f"{where}: transform_matrix contains NaN or infinity")
    R = c2w[:3, :3]
    det = np.linalg.det(R)
    if abs(det) < 1e-8 or abs(np.linalg.det(c2w)) < 1e-12:
        raise DatasetError(f"{where}: camera pose is not invertible (det = {det:.3g})")
    U, S, Vt = np.linalg.svd(R)
    if np.abs(S - 1.0).max() > 1e-2 or det < 0:
        raise DatasetError(
            f"{where}: camera pose is not a rigid transform (rotation singular values {S.round(4).tolist()}, det {det:.3g})"
        )
    c2w = c2w.copy()
    c2w[:3, :3] = U @ Vt  # remove float noise so viewmats are exactly orthonormal
    return c2w


def check_mask(mask: np.ndarray, where: str):
    if float(mask.max()) <= 0.0:
        raise DatasetError(f"{where}: mask is empty (no foreground pixel)")


_NUMBER = re.compile(r"(\d+)(?!.*\d)")


def frame_number(path: Path) -> int | None:
    """The frame number in a file name: its last run of digits (``000012.png`` and ``12.png``
    are both frame 12), or None when the name has no digit."""
    m = _NUMBER.search(Path(path).stem)
    return int(m.group(1)) if m else None


def list_images(folder: Path) -> list[Path]:
    """The image files of ``folder`` (hidden files skipped), sorted by name."""
    return sorted(p for p in folder.iterdir() if p.suffix.lower() in IMAGE_EXTS and not p.name.startswith("."))
