"""NeuS / IDR folders: ``cameras_sphere.npz`` + ``image/`` + ``mask/`` (DTU and BlendedMVS
in the NeuS layout).

- Camera ``i`` (``world_mat_i``, ``scale_mat_i``) belongs to the ``i``-th image in name order.
  ``P = world_mat @ scale_mat`` is decomposed into ``K [R | t]`` (:func:`decompose_projection`;
  the skew ``K[0, 1]`` of such decompositions is kept). NeuS puts pixel centres at integer
  coordinates; holowarp puts them at ``x + 0.5`` (method.md §1), so the principal point is
  shifted by +0.5 px.
- Masks are paired with images by the FRAME NUMBER in their names (the last run of digits:
  DTU's ``mask/000.png`` goes with ``image/000000.png``), never by sorted position, which
  would pair ``mask/10.png`` with ``image/002.png``. A missing, extra or duplicated number is
  an error that names the files. RGB masks are reduced to their brightest channel.
- Every ``test_every``-th view is a test view.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from holowarp.data.common import check_mask, frame_number, image_size, list_images, read_image, read_mask, read_views
from holowarp.data.dataset import Dataset, DatasetError, scale_intrinsics

__all__ = ["load_neus", "decompose_projection", "pair_masks"]


def decompose_projection(P: np.ndarray):
    """Split a 3x4 projection ``P ~ K [R | t]`` into ``K`` (3, 3), ``R`` (3, 3), centre ``c`` (3,).

    ``K`` is normalised (``K[2, 2] = 1``) with a positive diagonal and ``R`` is a proper
    rotation. Raises ``np.linalg.LinAlgError`` when the left 3x3 block is singular.
    """
    from scipy.linalg import rq

    P = np.asarray(P, dtype=np.float64)[:3, :4]
    M = P[:, :3]
    det = np.linalg.det(M)
    if not np.isfinite(det) or abs(det) < 1e-12 * max(1.0, np.abs(M).max()) ** 3:
        raise np.linalg.LinAlgError("projection matrix has a singular 3x3 block")
    if det < 0:  # P is defined up to scale; pick the sign with det(K R) > 0
        P = -P
        M = P[:, :3]
    Kr, R = rq(M)
    D = np.diag(np.sign(np.diag(Kr)))
    Kr, R = Kr @ D, D @ R  # D = D^-1
    c = -np.linalg.solve(M, P[:, 3])
    return Kr / Kr[2, 2], R, c


def _numbered(files: list[Path], folder: Path) -> dict[int, Path]:
    out: dict[int, Path] = {}
    for f in files:
        n = frame_number(f)
        if n is None:
            raise DatasetError(f"{f}: no frame number in the file name (NeuS/IDR files are named like 000012.png)")
        if n in out:
            raise DatasetError(f"{folder}: {out[n].name} and {f.name} have the same frame number {n}")
        out[n] = f
    return out


def pair_masks(img_files: list[Path], mask_files: list[Path], img_dir: Path, mask_dir: Path) -> list[Path]:
    """The mask of each image, matched by frame number (see the module docstring)."""
    imgs = _numbered(img_files, img_dir)
    masks = _numbered(mask_files, mask_dir)
    missing = sorted(set(imgs) - set(masks))
    extra = sorted(set(masks) - set(imgs))
    if missing or extra:
        parts = []
        if missing:
            parts.append("no mask for " + ", ".join(imgs[n].name for n in missing[:5]) + (" ..." if len(missing) > 5 else ""))
        if extra:
            parts.append("masks without an image: " + ", ".join(masks[n].name for n in extra[:5])
                         + (" ..." if len(extra) > 5 else ""))
        raise DatasetError(f"{mask_dir}: masks do not match the images of {img_dir} by frame number ({'; '.join(parts)})")
    return [masks[frame_number(f)] for f in img_files]


def _camera(cams, i: int, cam_path: Path) -> tuple[np.ndarray, np.ndarray]:
    """(K (3, 3), viewmat (4, 4)) of camera ``i``."""
    try:
        wm = np.asarray(cams[f"world_mat_{i}"], dtype=np.float64)
        sm = np.asarray(cams[f"scale_mat_{i}"], dtype=np.float64) if f"scale_mat_{i}" in cams.files else np.eye(4)
    except (TypeError, ValueError):
        raise DatasetError(f"{cam_path}: world_mat_{i}/scale_mat_{i} are not numeric matrices") from None
    if wm.shape not in ((4, 4), (3, 4)) or sm.shape != (4, 4):
        raise DatasetError(f"{cam_path}: world_mat_{i} must be 4x4 (or 3x4) and scale_mat_{i} 4x4, "
                           f"got {wm.shape} and {sm.shape}")
    if not (np.isfinite(wm).all() and np.isfinite(sm).all()):
        raise DatasetError(f"{cam_path}: world_mat_{i}/scale_mat_{i} contain NaN or infinity")
    if abs(np.linalg.det(sm)) < 1e-12:
        raise DatasetError(f"{cam_path}: scale_mat_{i} is not invertible")
    try:
        Ki, R, c = decompose_projection((wm[:3, :4] @ sm)[:3, :4])
    except np.linalg.LinAlgError as e:
        raise DatasetError(f"{cam_path}: world_mat_{i} @ scale_mat_{i} is not an invertible projection ({e})") from None
    Ki = Ki.copy()
    Ki[0, 2] += 0.5  # NeuS: pixel centres at integers; holowarp: at x + 0.5
    Ki[1, 2] += 0.5
    V = np.eye(4)
    V[:3, :3] = R
    V[:3, 3] = -R @ c
    return Ki, V


def _files(root: Path):
    cam_path = root / "cameras_sphere.npz"
    if not cam_path.is_file():
        raise DatasetError(f"{root}: cameras_sphere.npz not found")
    img_dir, mask_dir = root / "image", root / "mask"
    if not img_dir.is_dir():
        raise DatasetError(f"{img_dir}: image folder not found")
    if not mask_dir.is_dir():
        raise DatasetError(f"{mask_dir}: mask folder not found (NeuS/IDR datasets need foreground masks)")
    img_files = list_images(img_dir)
    if not img_files:
        raise DatasetError(f"{img_dir}: no images")
    mask_files = pair_masks(img_files, list_images(mask_dir), img_dir, mask_dir)
    try:
        cams = np.load(cam_path)
    except (OSError, ValueError, EOFError) as e:
        raise DatasetError(f"{cam_path}: cannot read ({e})") from None
    for i, f in enumerate(img_files):
        if f"world_mat_{i}" not in cams.files:
            raise DatasetError(f"{cam_path}: world_mat_{i} missing for image {f.name} ({len(img_files)} images)")
    return cam_path, cams, img_files, mask_files


def _read_view(img: Path, msk: Path, shape, full) -> dict:
    """Image (H', W', 3) and mask (H', W') of one view, area-resized to ``shape`` as decoded;
    both files must have the size ``full = (first image, (H, W))``."""
    im = read_image(img, shape=shape, expect=full)
    if im.ndim == 2:
        im = np.repeat(im[..., None], 3, axis=-1)
    mk = read_mask(msk, shape=shape, expect=(f"its image {img.name}", full[1]))
    check_mask(mk, str(msk))
    return {"image": np.ascontiguousarray(im[..., :3]), "mask": mk}


def load_neus(path: str | os.PathLike, *, res: int | None = None, test_every: int = 10,
              workers: int | None = None) -> Dataset:
    """Read a NeuS/IDR folder (see the module docstring).

    Args:
        path: dataset folder.
        res: optional output resolution (longer side); each view is area-resized as it is
            decoded.
        test_every: view ``i`` is a test view when ``i % test_every == 0``.
        workers: decoding threads (default :func:`holowarp.data.common.default_workers`).
    """
    root = Path(path)
    if int(test_every) < 1:
        raise DatasetError(f"--test-every must be >= 1, got {test_every}")
    cam_path, cams, img_files, mask_files = _files(root)
    n = len(img_files)
    cameras = [_camera(cams, i, cam_path) for i in range(n)]  # bad cameras fail before any decoding
    full = (img_files[0], image_size(img_files[0]))
    views = read_views(n, lambda i, shape: _read_view(img_files[i], mask_files[i], shape, full), full_shape=full[1],
                       size=res, workers=workers)
    K = scale_intrinsics(np.stack([c[0] for c in cameras]), views["full_shape"], views["shape"])
    idx = np.arange(n)
    return Dataset(images=views["image"], masks=views["mask"], K=K, viewmats=np.stack([c[1] for c in cameras]),
                   train_idx=idx[idx % test_every != 0], test_idx=idx[idx % test_every == 0], root=root,
                   gt_mesh=(root / "gt.obj") if (root / "gt.obj").is_file() else None, name=root.name,
                   meta={"format": "neus", "mask_files": [str(m.name) for m in mask_files],
                         "held_out": {"test_every": int(test_every), "views": idx[idx % test_every == 0].tolist()}})
