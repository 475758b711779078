"""What every dataset loader shares: reading images and masks, checking poses and numbers,
each failure a :class:`holowarp.data.DatasetError` that names the file and the reason."""

from __future__ import annotations

import math
import os
import re
from pathlib import Path

import numpy as np

from holowarp.data.dataset import DatasetError

__all__ = ["IMAGE_EXTS", "image_size", "read_image", "read_mask", "find_image", "rigid_c2w", "check_mask", "number",
           "frame_number", "list_images", "default_workers", "read_views"]

#: Image file extensions the loaders read (case-insensitive).
IMAGE_EXTS = (".png", ".jpg", ".jpeg")


_SIXTEEN_BIT = ("I;16", "I;16B", "I;16L", "I")


def image_size(path: Path) -> tuple[int, int]:
    """``(H, W)`` of an image file, from its header (nothing is decoded)."""
    from PIL import Image

    try:
        with Image.open(path) as im:
            return int(im.size[1]), int(im.size[0])
    except OSError as e:
        raise DatasetError(f"{path}: cannot read image ({e})") from None


def _bands_to_array(bands, shape, scale: float) -> np.ndarray:
    """Stack PIL bands into (H', W'[, C]) float32 / ``scale``, each band area-resized to
    ``shape`` in PIL's float mode first when ``shape`` is given (BOX is linear, so scaling
    after the resize equals resizing the scaled values)."""
    from PIL import Image

    if shape is not None:
        bands = [b.convert("F").resize((shape[1], shape[0]), Image.BOX) for b in bands]
    arrs = [np.asarray(b, dtype=np.float32) for b in bands]
    a = arrs[0].copy() if len(arrs) == 1 else np.stack(arrs, axis=-1)
    return np.divide(a, scale, out=a)


def _open_checked(path: Path, expect):
    """The opened PIL image; DatasetError naming ``path`` when its size is not ``expect``'s
    (``expect = (other file, (H, W))``; checked from the header, before decoding)."""
    from PIL import Image

    im = Image.open(path)
    if expect is not None and (im.size[1], im.size[0]) != tuple(expect[1]):
        w, h = im.size
        im.close()
        raise DatasetError(f"{path}: size {w}x{h} differs from {expect[0]} ({expect[1][1]}x{expect[1][0]})")
    return im


def _decode(path: Path, shape, expect, pick):
    """Open ``path`` (size checked against ``expect``), normalise its mode and return
    ``pick(im, shape)``; 16-bit images become one band scaled by 65535 instead. A
    ``shape`` equal to the file's size is dropped (no resize)."""
    try:
        with _open_checked(path, expect) as im:
            if shape is not None and (im.size[1], im.size[0]) == tuple(shape):
                shape = None
            im.load()
            if im.mode in _SIXTEEN_BIT:
                return _bands_to_array([im.convert("I").convert("F")], shape, 65535.0)
            if im.mode not in ("L", "LA", "RGB", "RGBA"):
                im = im.convert("RGBA" if "A" in im.getbands() else "RGB")
            return pick(im, shape)
    except OSError as e:
        raise DatasetError(f"{path}: cannot read image ({e})") from None


def read_image(path: Path, *, shape: tuple[int, int] | None = None, expect=None) -> np.ndarray:
    """(H, W[, C]) float32 in [0, 1]; 16-bit images are scaled by 65535.

    Args:
        shape: area-resize to (H', W') while decoding, band by band (never holding a
            full-resolution float copy); ``None`` keeps the file's size.
        expect: ``(other file, (H, W))``: the size the file must have (checked before
            decoding; the error names both files).
    """

    def pick(im, shape):
        if shape is None:
            a = np.asarray(im).astype(np.float32)  # one float copy, divided in place
            return np.divide(a, 255.0, out=a)
        return _bands_to_array(im.split(), shape, 255.0)

    return _decode(path, shape, expect, pick)


def read_mask(path: Path, *, shape: tuple[int, int] | None = None, expect=None) -> np.ndarray:
    """(H, W) float32 coverage in [0, 1] of a mask image: grey as is, grey + alpha its grey
    band, RGB(A) the brightest of R, G, B (masks saved as colour images); 16-bit scaled by
    65535. ``shape`` and ``expect`` as in :func:`read_image`."""
    from PIL import ImageChops

    def pick(im, shape):
        bands = im.split()
        band = bands[0] if len(bands) < 3 else ImageChops.lighter(ImageChops.lighter(bands[0], bands[1]), bands[2])
        return _bands_to_array([band], shape, 255.0)

    return _decode(path, shape, expect, pick)


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


def default_workers() -> int:
    """Decoding threads: one per CPU core, at most 8 (PNG/JPEG decoding and PIL's resize
    release the GIL; beyond 8 the disk, not the CPU, is usually the limit)."""
    return max(1, min(8, os.cpu_count() or 1))


def read_views(n: int, read_one, *, full_shape: tuple[int, int], size: int | None = None,
               workers: int | None = None) -> dict:
    """Decode ``n`` views in a thread pool, each resized as it is decoded, into one stack per
    array (full-resolution views are never all held at once).

    Args:
        n: number of views (>= 1).
        read_one: ``read_one(i, shape) -> arrays``: view ``i`` at ``shape`` (H', W'), a dict
            with ``"image"`` (H', W', 3) and ``"mask"`` (H', W') float32, optionally
            ``"normal"`` (H', W', 3) and ``"depth"`` (H', W') (the same keys for every view).
            It checks that its files have ``full_shape`` (:func:`read_image`'s ``expect``).
        full_shape: (H, W) of the files (view 0's, from :func:`image_size`).
        size: longer side of the output in pixels (``None``: keep the full resolution).
        workers: decoding threads (default :func:`default_workers`).

    Returns:
        dict of stacked float32 arrays ``image`` (n, H', W', 3), ``mask`` (n, H', W'), and
        ``normal`` / ``depth`` when the views have them, plus ``full_shape`` (H, W) and
        ``shape`` (H', W'); rescale intrinsics with
        :func:`holowarp.data.dataset.scale_intrinsics`. The first failing view, in index
        order, raises its error.
    """
    from concurrent.futures import ThreadPoolExecutor

    from holowarp.data.dataset import resized_shape

    full = tuple(int(x) for x in full_shape)
    shape = full if size is None else resized_shape(full[0], full[1], size)
    out: dict = {}

    def put(i: int) -> None:
        arrays = read_one(i, shape)
        for k, a in arrays.items():
            if k not in out:  # first view to finish allocates (keys and shapes are common)
                out.setdefault(k, np.empty((n,) + np.shape(a), np.float32))
            out[k][i] = a

    pool = ThreadPoolExecutor(max_workers=max(1, min(n, workers or default_workers())))
    try:
        futures = [pool.submit(put, i) for i in range(n)]
        for f in futures:
            f.result()
    finally:
        pool.shutdown(wait=True, cancel_futures=True)
    out["full_shape"], out["shape"] = full, shape
    return out
