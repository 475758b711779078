"""Dataset loaders: NeRF-synthetic and NeuS/IDR folders into one :class:`Dataset` (method.md §1).

- **NeRF-synthetic / Blender** (``transforms_train.json``, ``transforms_test.json``): the
  image's alpha channel is the mask; ``camera_angle_x`` gives the focal length (``fl_x``,
  ``fl_y``, ``cx``, ``cy`` are honoured when present); ``transform_matrix`` is camera-to-world
  in OpenGL axes and becomes the OpenCV world-to-camera ``viewmat``
  (``inv(c2w @ diag(1, -1, -1, 1))``). Train and test views come from the two files. Views
  written by :func:`holowarp.data.synth.synthesize` carry ``view_index`` and are put back in
  their original order; otherwise train views come first, then test views. World normals
  and depths are read from ``*_geom.npz`` (exact) or the ``*_normal.png``/``*_depth.png``
  images when the frames name them.
- **NeuS / IDR** (``cameras_sphere.npz`` + ``image/`` + ``mask/``): ``P = world_mat @
  scale_mat`` is decomposed into ``K [R | t]``. NeuS puts pixel centres at integer
  coordinates; holowarp puts them at ``x + 0.5`` (method.md §1), so the principal point is
  shifted by +0.5 px. Every ``test_every``-th view is a test view.

Every problem raises :class:`DatasetError` naming the file and the reason: a missing image,
images of different sizes, a missing or empty mask, a non-invertible pose.
"""

from __future__ import annotations

import json
import math
import os
from pathlib import Path

import numpy as np

from holowarp.camera import opengl_c2w_to_viewmat, viewmat_to_opengl_c2w
from holowarp.data.dataset import Dataset, DatasetError

__all__ = [
    "detect_format",
    "load_dataset",
    "load_nerf_synthetic",
    "load_neus",
    "write_nerf_synthetic",
    "decompose_projection",
]

_IMG_EXTS = (".png", ".jpg", ".jpeg", ".PNG", ".JPG", ".JPEG")


def detect_format(path: str | os.PathLike) -> str:
    """``"nerf_synthetic"`` or ``"neus"`` for a dataset folder; :class:`DatasetError` otherwise."""
    root = Path(path)
    if not root.exists():
        raise DatasetError(f"{root}: no such dataset folder")
    if not root.is_dir():
        raise DatasetError(f"{root}: a dataset must be a folder")
    if (root / "transforms_train.json").is_file() or (root / "transforms_test.json").is_file():
        return "nerf_synthetic"
    if (root / "cameras_sphere.npz").is_file():
        return "neus"
    raise DatasetError(
        f"{root}: unknown dataset layout (expected transforms_train.json/transforms_test.json "
        "for NeRF-synthetic or cameras_sphere.npz with image/ and mask/ for NeuS/IDR)"
    )


def load_dataset(path: str | os.PathLike, *, res: int | None = None, **kwargs) -> Dataset:
    """Load a dataset folder, detecting its format.

    Args:
        path: dataset folder.
        res: if given, resize so the longer image side is ``res`` pixels (``Dataset.resized``).
        kwargs: passed to :func:`load_nerf_synthetic` or :func:`load_neus`.
    """
    fmt = detect_format(path)
    if fmt == "nerf_synthetic":
        return load_nerf_synthetic(path, res=res, **kwargs)
    return load_neus(path, res=res, **kwargs)


# ----------------------------------------------------------------------------- helpers


def _read_image(path: Path) -> np.ndarray:
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
        raise DatasetError(f"{path}: cannot read image ({e})") from e


def _find_image(root: Path, file_path: str) -> Path:
    p = (root / file_path).resolve() if not os.path.isabs(file_path) else Path(file_path)
    if p.suffix in _IMG_EXTS and p.is_file():
        return p
    for ext in (".png", ".jpg", ".jpeg"):
        q = p.with_name(p.name + ext)
        if q.is_file():
            return q
    raise DatasetError(f"{root}: image {file_path!r} not found (tried {p} with .png/.jpg)")


def _rigid_from_c2w(c2w: np.ndarray, where: str) -> np.ndarray:
    c2w = np.asarray(c2w, dtype=np.float64)
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


def _check_mask(mask: np.ndarray, where: str):
    if float(mask.max()) <= 0.0:
        raise DatasetError(f"{where}: mask is empty (no foreground pixel)")


# ----------------------------------------------------------------------- NeRF-synthetic


def load_nerf_synthetic(
    path: str | os.PathLike,
    *,
    res: int | None = None,
    splits=("train", "test"),
    load_normals: bool = True,
    load_depths: bool = True,
) -> Dataset:
    """Read a NeRF-synthetic folder (see module docstring).

    Args:
        path: folder with ``transforms_<split>.json``.
        res: optional output resolution (longer side).
        splits: which transforms files to read; ``"train"`` views go to ``train_idx`` and
            every other split (``"test"``, ``"val"``) to ``test_idx``.
        load_normals: read world normals when the frames provide them.
        load_depths: read depths when the frames provide them.
    """
    root = Path(path)
    detect_format(root)
    entries = []  # (split, frame, doc)
    docs = {}
    for split in splits:
        jp = root / f"transforms_{split}.json"
        if not jp.is_file():
            continue
        try:
            doc = json.loads(jp.read_text())
        except (OSError, json.JSONDecodeError) as e:
            raise DatasetError(f"{jp}: cannot parse JSON ({e})") from e
        if not isinstance(doc, dict) or not isinstance(doc.get("frames"), list):
            raise DatasetError(f"{jp}: expected an object with a 'frames' list")
        if "camera_angle_x" not in doc and "fl_x" not in doc:
            raise DatasetError(f"{jp}: no 'camera_angle_x' (or 'fl_x') to give the focal length")
        docs[split] = doc
        for k, fr in enumerate(doc["frames"]):
            if "file_path" not in fr or "transform_matrix" not in fr:
                raise DatasetError(f"{jp}: frame {k} lacks 'file_path' or 'transform_matrix'")
            entries.append((split, k, fr, doc, jp))
    if not entries:
        raise DatasetError(f"{root}: no frames in transforms_{{{','.join(splits)}}}.json")
    if all("view_index" in e[2] for e in entries):
        vi = [int(e[2]["view_index"]) for e in entries]
        if len(set(vi)) != len(vi):
            raise DatasetError(f"{root}: duplicate view_index values in the transforms files")
        entries = [e for _, e in sorted(zip(vi, entries), key=lambda t: t[0])]

    n = len(entries)
    images = masks = None
    normals = depths = None
    K = np.zeros((n, 3, 3))
    viewmats = np.zeros((n, 4, 4))
    train, test = [], []
    first_shape, first_path = None, None
    want_n = load_normals and all(("geometry_path" in e[2]) or ("normal_path" in e[2]) for e in entries)
    want_d = load_depths and all(("geometry_path" in e[2]) or ("depth_path" in e[2]) for e in entries)
    for i, (split, k, fr, doc, jp) in enumerate(entries):
        where = f"{jp} frame {k}"
        ip = _find_image(root, fr["file_path"])
        im = _read_image(ip)
        if im.ndim != 3 or im.shape[2] != 4:
            raise DatasetError(f"{ip}: image has no alpha channel; NeRF-synthetic images are RGBA with alpha as the mask")
        if first_shape is None:
            first_shape, first_path = im.shape, ip
            h, w = im.shape[:2]
            images = np.empty((n, h, w, 3), np.float32)
            masks = np.empty((n, h, w), np.float32)
            normals = np.zeros((n, h, w, 3), np.float32) if want_n else None
            depths = np.zeros((n, h, w), np.float32) if want_d else None
        elif im.shape != first_shape:
            raise DatasetError(f"{ip}: size {im.shape[1]}x{im.shape[0]} differs from {first_path} ({first_shape[1]}x{first_shape[0]})")
        images[i] = im[..., :3]
        masks[i] = im[..., 3]
        _check_mask(masks[i], str(ip))
        h, w = im.shape[:2]
        # Intrinsics: the JSON may describe another resolution; scale to the image's.
        jw = float(doc.get("w", w))
        jh = float(doc.get("h", h))
        if "camera_angle_x" in doc:
            fx = 0.5 * w / math.tan(0.5 * float(doc["camera_angle_x"]))
            fy = 0.5 * h / math.tan(0.5 * float(doc["camera_angle_y"])) if "camera_angle_y" in doc else fx
        else:
            fx = float(doc["fl_x"]) * w / jw
            fy = float(doc.get("fl_y", doc["fl_x"])) * h / jh
        cx = float(doc["cx"]) * w / jw if "cx" in doc else 0.5 * w
        cy = float(doc["cy"]) * h / jh if "cy" in doc else 0.5 * h
        if not (fx > 0 and fy > 0 and math.isfinite(fx) and math.isfinite(fy)):
            raise DatasetError(f"{jp}: invalid focal length (camera_angle_x must lie in (0, pi))")
        K[i] = [[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]]
        viewmats[i] = opengl_c2w_to_viewmat(_rigid_from_c2w(fr["transform_matrix"], where))
        (train if split == "train" else test).append(i)
        if want_n or want_d:
            geom = None
            if "geometry_path" in fr:
                gp = (root / fr["geometry_path"]).resolve()
                if not gp.is_file():
                    raise DatasetError(f"{where}: geometry file {gp} not found")
                try:
                    with np.load(gp) as z:
                        geom = {kk: z[kk] for kk in z.files}
                except (OSError, ValueError) as e:
                    raise DatasetError(f"{gp}: cannot read ({e})") from e
            if want_n:
                if geom is not None and "normal" in geom:
                    nm = geom["normal"]
                else:
                    npth = (root / fr["normal_path"]).resolve()
                    if not npth.is_file():
                        raise DatasetError(f"{where}: normal map {npth} not found")
                    enc = _read_image(npth)
                    nm = enc[..., :3] * 2.0 - 1.0
                    ln = np.linalg.norm(nm, axis=-1, keepdims=True)
                    nm = np.where((ln > 0.5) & (masks[i][..., None] > 0), nm / np.maximum(ln, 1e-6), 0.0)
                if nm.shape != (h, w, 3):
                    raise DatasetError(f"{where}: normal map shape {nm.shape} does not match image {h}x{w}")
                normals[i] = nm
            if want_d:
                if geom is not None and "depth" in geom:
                    dm = geom["depth"]
                else:
                    dp = (root / fr["depth_path"]).resolve()
                    if not dp.is_file():
                        raise DatasetError(f"{where}: depth map {dp} not found")
                    scale = doc.get("holowarp", {}).get("depth_png_scale")
                    if scale is None:
                        raise DatasetError(f"{jp}: depth PNGs need holowarp.depth_png_scale")
                    dm = _read_image(dp)
                    dm = (dm[..., 0] if dm.ndim == 3 else dm) * 65535.0 * float(scale)
                if dm.shape != (h, w):
                    raise DatasetError(f"{where}: depth map shape {dm.shape} does not match image {h}x{w}")
                depths[i] = dm
    meta = {"format": "nerf_synthetic"}
    hw = next((d.get("holowarp") for d in docs.values() if isinstance(d.get("holowarp"), dict)), None)
    if hw is not None:
        meta["holowarp"] = {k: v for k, v in hw.items() if k not in ("split", "view_order")}
    gt = root / "gt.obj"
    ds = Dataset(
        images=images,
        masks=masks,
        K=K,
        viewmats=viewmats,
        train_idx=np.array(train, np.int64),
        test_idx=np.array(test, np.int64),
        normals=normals,
        depths=depths,
        root=root,
        gt_mesh=gt if gt.is_file() else None,
        name=root.name,
        meta=meta,
    )
    return ds.resized(res) if res else ds


def write_nerf_synthetic(dataset: Dataset, out_dir: str | os.PathLike) -> Path:
    """Write a :class:`Dataset` as a NeRF-synthetic folder (RGBA PNGs + transforms JSONs).

    Views keep their index as ``view_index`` and in the file names, so
    :func:`load_nerf_synthetic` reads back the same ordering and split. Only square-pixel,
    centred-principal-point cameras are representable by ``camera_angle_x``; the exact
    ``fl_x``/``fl_y``/``cx``/``cy`` of view 0 are written too, and all views must share them.
    """
    from PIL import Image

    from holowarp.fileio import atomic_path, atomic_write_json

    out = Path(out_dir)
    K0 = dataset.K[0]
    if not np.allclose(dataset.K, K0[None], rtol=1e-6, atol=1e-6):
        raise DatasetError("write_nerf_synthetic: all views must share one K in this layout")
    test = set(int(i) for i in dataset.test_idx)
    for split in ("train", "test"):
        frames = []
        idx = [i for i in range(dataset.num_views) if (i in test) == (split == "test")]
        for i in idx:
            rgba = np.concatenate([dataset.images[i], dataset.masks[i][..., None]], axis=-1)
            p = out / split / f"r_{i}.png"
            with atomic_path(p) as tmp:
                Image.fromarray(np.clip(np.rint(rgba * 255), 0, 255).astype(np.uint8)).save(tmp, format="PNG")
            frames.append(
                {
                    "file_path": f"./{split}/r_{i}",
                    "transform_matrix": viewmat_to_opengl_c2w(dataset.viewmats[i]).tolist(),
                    "view_index": i,
                }
            )
        doc = {
            "camera_angle_x": 2.0 * math.atan(0.5 * dataset.width / K0[0, 0]),
            "w": dataset.width,
            "h": dataset.height,
            "fl_x": float(K0[0, 0]),
            "fl_y": float(K0[1, 1]),
            "cx": float(K0[0, 2]),
            "cy": float(K0[1, 2]),
            "frames": frames,
        }
        atomic_write_json(out / f"transforms_{split}.json", doc)
    if dataset.gt_mesh is not None and Path(dataset.gt_mesh).is_file():
        import shutil

        with atomic_path(out / "gt.obj") as tmp:
            shutil.copyfile(dataset.gt_mesh, tmp)
    return out


# ------------------------------------------------------------------------------ NeuS/IDR


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


def _sorted_images(folder: Path):
    return sorted(p for p in folder.iterdir() if p.suffix in _IMG_EXTS and not p.name.startswith("."))


def load_neus(path: str | os.PathLike, *, res: int | None = None, test_every: int = 10) -> Dataset:
    """Read a NeuS/IDR folder: ``cameras_sphere.npz``, ``image/``, ``mask/`` (module docstring).

    Args:
        path: dataset folder.
        res: optional output resolution (longer side).
        test_every: view ``i`` is a test view when ``i % test_every == 0``.
    """
    root = Path(path)
    cam_path = root / "cameras_sphere.npz"
    if not cam_path.is_file():
        raise DatasetError(f"{root}: cameras_sphere.npz not found")
    img_dir, mask_dir = root / "image", root / "mask"
    if not img_dir.is_dir():
        raise DatasetError(f"{img_dir}: image folder not found")
    if not mask_dir.is_dir():
        raise DatasetError(f"{mask_dir}: mask folder not found (NeuS/IDR datasets need foreground masks)")
    img_files = _sorted_images(img_dir)
    mask_files = _sorted_images(mask_dir)
    if not img_files:
        raise DatasetError(f"{img_dir}: no images")
    if len(mask_files) != len(img_files):
        raise DatasetError(f"{mask_dir}: {len(mask_files)} masks for {len(img_files)} images in {img_dir}")
    try:
        cams = np.load(cam_path)
    except (OSError, ValueError) as e:
        raise DatasetError(f"{cam_path}: cannot read ({e})") from e
    n = len(img_files)
    for i in range(n):
        if f"world_mat_{i}" not in cams.files:
            raise DatasetError(f"{cam_path}: world_mat_{i} missing for image {img_files[i].name} ({n} images)")
    images = masks = None
    K = np.zeros((n, 3, 3))
    viewmats = np.zeros((n, 4, 4))
    first = None
    for i in range(n):
        im = _read_image(img_files[i])
        if im.ndim == 2:
            im = np.repeat(im[..., None], 3, axis=-1)
        mk = _read_image(mask_files[i])
        if mk.ndim == 3:
            mk = mk[..., :3].max(axis=-1) if mk.shape[2] >= 3 else mk[..., 0]
        if first is None:
            first = (im.shape[:2], img_files[i])
            images = np.empty((n,) + im.shape[:2] + (3,), np.float32)
            masks = np.empty((n,) + im.shape[:2], np.float32)
        elif im.shape[:2] != first[0]:
            raise DatasetError(f"{img_files[i]}: size {im.shape[1]}x{im.shape[0]} differs from {first[1]} ({first[0][1]}x{first[0][0]})")
        if mk.shape != im.shape[:2]:
            raise DatasetError(f"{mask_files[i]}: mask size {mk.shape[1]}x{mk.shape[0]} differs from its image {im.shape[1]}x{im.shape[0]}")
        _check_mask(mk, str(mask_files[i]))
        images[i] = im[..., :3]
        masks[i] = mk
        wm = cams[f"world_mat_{i}"].astype(np.float64)
        sm = cams[f"scale_mat_{i}"].astype(np.float64) if f"scale_mat_{i}" in cams.files else np.eye(4)
        if not (np.isfinite(wm).all() and np.isfinite(sm).all()):
            raise DatasetError(f"{cam_path}: world_mat_{i}/scale_mat_{i} contain NaN or infinity")
        if abs(np.linalg.det(sm)) < 1e-12:
            raise DatasetError(f"{cam_path}: scale_mat_{i} is not invertible")
        try:
            Ki, R, c = decompose_projection((wm @ sm)[:3, :4])
        except np.linalg.LinAlgError as e:
            raise DatasetError(f"{cam_path}: world_mat_{i} @ scale_mat_{i} is not an invertible projection ({e})") from e
        Ki = Ki.copy()
        Ki[0, 2] += 0.5  # NeuS: pixel centres at integers; holowarp: at x + 0.5
        Ki[1, 2] += 0.5
        K[i] = Ki
        viewmats[i] = np.eye(4)
        viewmats[i, :3, :3] = R
        viewmats[i, :3, 3] = -R @ c
    idx = np.arange(n)
    ds = Dataset(
        images=images,
        masks=masks,
        K=K,
        viewmats=viewmats,
        train_idx=idx[idx % test_every != 0],
        test_idx=idx[idx % test_every == 0],
        root=root,
        gt_mesh=(root / "gt.obj") if (root / "gt.obj").is_file() else None,
        name=root.name,
        meta={"format": "neus"},
    )
    return ds.resized(res) if res else ds
