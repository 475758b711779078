"""NeRF-synthetic / Blender folders (``transforms_train.json``, ``transforms_test.json``).

- The image's alpha channel is the mask.
- ``camera_angle_x`` (in (0, pi)) gives the focal length; ``fl_x``, ``fl_y``, ``cx``, ``cy`` are
  honoured when present (scaled from the JSON's ``w``/``h`` to the image's size).
- ``transform_matrix`` is camera-to-world in OpenGL axes and becomes the OpenCV
  world-to-camera ``viewmat`` (``inv(c2w @ diag(1, -1, -1, 1))``).
- Train views come from ``transforms_train.json``, test views from the other splits. A
  folder without test views (``transforms_train.json`` alone, as the real lego capture)
  holds out every ``test_every``-th training view for the test metrics; the dataset's
  ``meta["held_out"]`` lists them.
- Views written by :func:`holowarp.synthesis.synthesize` carry ``view_index`` and are put
  back in their original order; otherwise train views come first, then test views. World
  normals and depths are read from ``*_geom.npz`` (exact) or the ``*_normal.png`` /
  ``*_depth.png`` images when the frames name them.
"""

from __future__ import annotations

import json
import math
import os
from pathlib import Path

import numpy as np

from holowarp.camera import opengl_c2w_to_viewmat, viewmat_to_opengl_c2w
from holowarp.data.common import check_mask, find_image, image_size, number, read_image, read_views, rigid_c2w
from holowarp.data.dataset import Dataset, DatasetError, resize_view, scale_intrinsics

__all__ = ["load_nerf_synthetic", "write_nerf_synthetic"]


def _read_transforms(root: Path, splits) -> tuple[list, dict]:
    """Every frame of the transforms files, as ``(split, k, frame, doc, json_path)``."""
    entries, docs = [], {}
    for split in splits:
        jp = root / f"transforms_{split}.json"
        if not jp.is_file():
            continue
        try:
            doc = json.loads(jp.read_text(encoding="utf-8"))
        except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
            raise DatasetError(f"{jp}: cannot parse JSON ({e})") from None
        if not isinstance(doc, dict) or not isinstance(doc.get("frames"), list):
            raise DatasetError(f"{jp}: expected an object with a 'frames' list")
        if "camera_angle_x" not in doc and "fl_x" not in doc:
            raise DatasetError(f"{jp}: no 'camera_angle_x' (or 'fl_x') to give the focal length")
        docs[split] = doc
        for k, fr in enumerate(doc["frames"]):
            if not isinstance(fr, dict) or "file_path" not in fr or "transform_matrix" not in fr:
                raise DatasetError(f"{jp}: frame {k} lacks 'file_path' or 'transform_matrix'")
            entries.append((split, k, fr, doc, jp))
    if not entries:
        raise DatasetError(f"{root}: no frames in transforms_{{{','.join(splits)}}}.json")
    if all("view_index" in e[2] for e in entries):
        try:
            vi = [int(e[2]["view_index"]) for e in entries]
        except (TypeError, ValueError):
            raise DatasetError(f"{root}: view_index values must be integers") from None
        if len(set(vi)) != len(vi):
            raise DatasetError(f"{root}: duplicate view_index values in the transforms files")
        entries = [e for _, e in sorted(zip(vi, entries), key=lambda t: t[0])]
    return entries, docs


def _intrinsics(doc: dict, w: int, h: int, jp: Path) -> np.ndarray:
    """K (3, 3) of a transforms file for images of ``w`` x ``h`` pixels."""
    where = str(jp)
    jw = number(doc.get("w", w), where, "w", lo=0)
    jh = number(doc.get("h", h), where, "h", lo=0)
    if "camera_angle_x" in doc:
        ax = number(doc["camera_angle_x"], where, "camera_angle_x", lo=0, hi=math.pi)
        fx = 0.5 * w / math.tan(0.5 * ax)
        fy = fx
        if "camera_angle_y" in doc:
            fy = 0.5 * h / math.tan(0.5 * number(doc["camera_angle_y"], where, "camera_angle_y", lo=0, hi=math.pi))
    else:
        fx = number(doc["fl_x"], where, "fl_x", lo=0) * w / jw
        fy = number(doc.get("fl_y", doc["fl_x"]), where, "fl_y", lo=0) * h / jh
    cx = number(doc["cx"], where, "cx") * w / jw if "cx" in doc else 0.5 * w
    cy = number(doc["cy"], where, "cy") * h / jh if "cy" in doc else 0.5 * h
    return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])


def _geometry_file(root: Path, fr: dict, where: str) -> dict | None:
    if "geometry_path" not in fr:
        return None
    gp = (root / str(fr["geometry_path"])).resolve()
    if not gp.is_file():
        raise DatasetError(f"{where}: geometry file {gp} not found")
    try:
        with np.load(gp) as z:
            return {kk: z[kk] for kk in z.files}
    except (OSError, ValueError) as e:
        raise DatasetError(f"{gp}: cannot read ({e})") from None


def _normal_map(root: Path, fr: dict, geom, mask: np.ndarray, where: str) -> np.ndarray:
    if geom is not None and "normal" in geom:
        nm = geom["normal"]
    else:
        npth = (root / str(fr["normal_path"])).resolve()
        if not npth.is_file():
            raise DatasetError(f"{where}: normal map {npth} not found")
        nm = read_image(npth)[..., :3] * 2.0 - 1.0
        ln = np.linalg.norm(nm, axis=-1, keepdims=True)
        nm = np.where((ln > 0.5) & (mask[..., None] > 0), nm / np.maximum(ln, 1e-6), 0.0)
    if nm.shape != mask.shape + (3,):
        raise DatasetError(f"{where}: normal map shape {nm.shape} does not match image {mask.shape[0]}x{mask.shape[1]}")
    return nm


def _depth_map(root: Path, fr: dict, geom, doc: dict, shape, where: str, jp: Path) -> np.ndarray:
    if geom is not None and "depth" in geom:
        dm = geom["depth"]
    else:
        dp = (root / str(fr["depth_path"])).resolve()
        if not dp.is_file():
            raise DatasetError(f"{where}: depth map {dp} not found")
        scale = (doc.get("holowarp") or {}).get("depth_png_scale")
        if scale is None:
            raise DatasetError(f"{jp}: depth PNGs need holowarp.depth_png_scale")
        dm = read_image(dp)
        dm = (dm[..., 0] if dm.ndim == 3 else dm) * 65535.0 * number(scale, str(jp), "holowarp.depth_png_scale", lo=0)
    if dm.shape != shape:
        raise DatasetError(f"{where}: depth map shape {dm.shape} does not match image {shape[0]}x{shape[1]}")
    return dm


def _frame_reader(root: Path, entries, want_n: bool, want_d: bool):
    """``(read_one(i, shape) -> arrays, full = (first image, (H, W)))`` for
    :func:`holowarp.data.common.read_views`; every image file is looked up first, so a
    missing one fails before any decoding."""
    paths = [find_image(root, fr["file_path"], f"{jp} frame {k}") for _, k, fr, _, jp in entries]
    full = (paths[0], image_size(paths[0]))

    def read_one(i: int, shape):
        _, k, fr, doc, jp = entries[i]
        where, ip = f"{jp} frame {k}", paths[i]
        # Normals and depths are resized with the full-resolution mask (resize_view), so
        # only views without them are resized while decoding.
        geometry = want_n or want_d
        im = read_image(ip, shape=None if geometry else shape, expect=full)
        if im.ndim != 3 or im.shape[2] != 4:
            raise DatasetError(f"{ip}: image has no alpha channel; NeRF-synthetic images are RGBA with alpha as the mask")
        out = {"image": np.ascontiguousarray(im[..., :3]), "mask": np.ascontiguousarray(im[..., 3])}
        check_mask(out["mask"], str(ip))
        if not geometry:
            return out
        geom = _geometry_file(root, fr, where)
        if want_n:
            out["normal"] = _normal_map(root, fr, geom, out["mask"], where)
        if want_d:
            out["depth"] = _depth_map(root, fr, geom, doc, im.shape[:2], where, jp)
        if tuple(shape) != im.shape[:2]:
            out = resize_view(shape, out["image"], out["mask"], normal=out.get("normal"), depth=out.get("depth"))
        return out

    return read_one, full


def _read_frames(root: Path, entries, load_normals: bool, load_depths: bool, res, workers):
    """(views of :func:`read_views`, K (N, 3, 3), viewmats (N, 4, 4), train, test)."""
    want_n = load_normals and all(("geometry_path" in e[2]) or ("normal_path" in e[2]) for e in entries)
    want_d = load_depths and all(("geometry_path" in e[2]) or ("depth_path" in e[2]) for e in entries)
    viewmats = np.stack([opengl_c2w_to_viewmat(rigid_c2w(fr["transform_matrix"], f"{jp} frame {k}"))
                         for _, k, fr, _, jp in entries])
    read_one, full = _frame_reader(root, entries, want_n, want_d)
    views = read_views(len(entries), read_one, full_shape=full[1], size=res, workers=workers)
    h, w = views["full_shape"]
    K = scale_intrinsics(np.stack([_intrinsics(doc, w, h, jp) for _, _, _, doc, jp in entries]), (h, w), views["shape"])
    train = [i for i, e in enumerate(entries) if e[0] == "train"]
    test = [i for i, e in enumerate(entries) if e[0] != "train"]
    return views, K, viewmats, train, test


def load_nerf_synthetic(
    path: str | os.PathLike,
    *,
    res: int | None = None,
    splits=("train", "test"),
    load_normals: bool = True,
    load_depths: bool = True,
    test_every: int = 10,
    workers: int | None = None,
) -> Dataset:
    """Read a NeRF-synthetic folder (see the module docstring).

    Args:
        path: folder with ``transforms_<split>.json``.
        res: optional output resolution (longer side); each view is area-resized as it is
            decoded.
        splits: which transforms files to read; ``"train"`` views go to ``train_idx`` and
            every other split (``"test"``, ``"val"``) to ``test_idx``.
        load_normals: read world normals when the frames provide them.
        load_depths: read depths when the frames provide them.
        test_every: without test views, training view ``i`` is held out when
            ``i % test_every == 0``.
        workers: decoding threads (default :func:`holowarp.data.common.default_workers`).
    """
    root = Path(path)
    if int(test_every) < 1:
        raise DatasetError(f"--test-every must be >= 1, got {test_every}")
    entries, docs = _read_transforms(root, splits)
    views, K, viewmats, train, test = _read_frames(root, entries, load_normals, load_depths, res, workers)
    meta = {"format": "nerf_synthetic"}
    hw = next((d.get("holowarp") for d in docs.values() if isinstance(d.get("holowarp"), dict)), None)
    if hw is not None:
        meta["holowarp"] = {k: v for k, v in hw.items() if k not in ("split", "view_order")}
    if not test:
        test = [v for j, v in enumerate(train) if j % int(test_every) == 0]
        train = [v for j, v in enumerate(train) if j % int(test_every) != 0]
        meta["held_out"] = {"test_every": int(test_every), "views": test}
    gt = root / "gt.obj"
    return Dataset(images=views["image"], masks=views["mask"], K=K, viewmats=viewmats,
                   train_idx=np.array(train, np.int64), test_idx=np.array(test, np.int64), normals=views.get("normal"),
                   depths=views.get("depth"), root=root, gt_mesh=gt if gt.is_file() else None, name=root.name,
                   meta=meta)


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


