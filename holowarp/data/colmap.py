"""COLMAP folders: ``sparse/0/`` (``cameras``, ``images``, ``points3D``, as ``.bin`` or
``.txt``; ``sparse/`` itself is accepted too), ``images/`` and ``masks/``.

- The model is read with pycolmap (:func:`read_model`), never parsed by hand; a model
  without ``points3D`` (cameras only) is read too. Only registered images (those with a
  pose) become views, in name order; every ``test_every``-th is a test view.
- Conventions: COLMAP's cameras are OpenCV's (x right, y down, z forward,
  ``cam_from_world`` is holowarp's world-to-camera ``viewmat``) and its image coordinates
  put pixel centres at ``x + 0.5``, as holowarp's (method.md §1): its SIFT keypoint of a
  blob centred on pixel (i, j) is at (i + 0.5, j + 0.5) (checked in tests/test_colmap.py),
  so K is COLMAP's calibration matrix unchanged.
- Camera models: SIMPLE_PINHOLE and PINHOLE are read as they are; SIMPLE_RADIAL, RADIAL,
  OPENCV and FULL_OPENCV are undistorted while loading to the PINHOLE camera with the same
  focal lengths, principal point and image size (each undistorted pixel centre is mapped
  through pycolmap's distortion model, ``Camera.img_from_cam``, and the photo and its mask
  are sampled bilinearly there; pixels that map outside the photo become background).
  Other models (fisheye, FOV, ...) are refused with a message saying how to undistort them.
- Masks are matched to images by file stem: ``masks/a/b.png`` (or COLMAP's own
  ``masks/a/b.jpg.png``) is the mask of ``images/a/b.jpg``. Every registered image needs one.
- The world is normalised (:func:`holowarp.data.normalize.normalize_to_unit_sphere`): the
  masks' visual hull to the unit sphere, as NeuS's ``scale_mat``, and the mean camera up to
  +Z. ``meta["normalization"]`` records the transform (``scale_mat`` maps the loaded world
  back to COLMAP's).
"""

from __future__ import annotations

import os
import shutil
import tempfile
import threading
from pathlib import Path

import numpy as np

from holowarp.data.common import IMAGE_EXTS, check_mask, image_size, read_image, read_mask, read_views
from holowarp.data.dataset import Dataset, DatasetError, area_resize, scale_intrinsics
from holowarp.errors import one_line

__all__ = ["find_model", "read_model", "load_colmap", "write_colmap", "camera_matrix", "match_masks",
           "PINHOLE_MODELS", "UNDISTORTED_MODELS"]

#: Camera models read as they are, and models undistorted while loading.
PINHOLE_MODELS = ("SIMPLE_PINHOLE", "PINHOLE")
UNDISTORTED_MODELS = ("SIMPLE_RADIAL", "RADIAL", "OPENCV", "FULL_OPENCV")
_MODEL_DIRS = ("sparse/0", "sparse")
_POSE_FILES = ("cameras", "images", "rigs", "frames")  # all a model needs but points3D


def _model_ext(folder: Path) -> str | None:
    for ext in (".bin", ".txt"):
        if (folder / f"cameras{ext}").is_file() and (folder / f"images{ext}").is_file():
            return ext
    return None


def find_model(root: str | os.PathLike) -> Path | None:
    """The model folder of a COLMAP dataset (``sparse/0`` or ``sparse``), or None."""
    for sub in _MODEL_DIRS:
        if _model_ext(Path(root) / sub) is not None:
            return Path(root) / sub
    return None


def read_model(model_dir: str | os.PathLike):
    """The ``pycolmap.Reconstruction`` in ``model_dir``; a model without ``points3D`` is read
    through a temporary copy that has an empty one. DatasetError naming the folder otherwise."""
    import pycolmap

    model_dir = Path(model_dir)
    ext = _model_ext(model_dir)
    if ext is None:
        raise DatasetError(f"{model_dir}: no COLMAP model (cameras.bin/.txt and images.bin/.txt)")
    try:
        if (model_dir / f"points3D{ext}").is_file():
            return pycolmap.Reconstruction(model_dir)
        with tempfile.TemporaryDirectory(prefix="holowarp-colmap-") as tmp:
            empty = pycolmap.Reconstruction()  # its files, of the model's format, hold nothing
            if ext == ".bin":
                empty.write(tmp)
            else:
                empty.write_text(tmp)
            for name in _POSE_FILES:
                src, dst = model_dir / f"{name}{ext}", Path(tmp) / f"{name}{ext}"
                if src.is_file():
                    shutil.copyfile(src, dst)
                else:  # a model from before COLMAP's rigs and frames
                    dst.unlink(missing_ok=True)
            return pycolmap.Reconstruction(tmp)
    except (ValueError, RuntimeError, OSError) as e:
        raise DatasetError(f"{model_dir}: pycolmap cannot read the model ({one_line(e)})") from None


def camera_matrix(camera, where: str) -> np.ndarray:
    """The pinhole ``K`` (3, 3) of a pycolmap camera (focal lengths and principal point; the
    distortion, if any, is removed by :func:`_undistorter`); DatasetError for other models."""
    name = camera.model.name
    if name not in PINHOLE_MODELS + UNDISTORTED_MODELS:
        raise DatasetError(
            f"{where}: camera {camera.camera_id} is {name}; holowarp reads {', '.join(PINHOLE_MODELS)} as they are and "
            f"undistorts {', '.join(UNDISTORTED_MODELS)} (run `colmap image_undistorter` on this model first)")
    return np.array([[camera.focal_length_x, 0.0, camera.principal_point_x],
                     [0.0, camera.focal_length_y, camera.principal_point_y], [0.0, 0.0, 1.0]])


def _stem_key(rel: str) -> str:
    """A file's path without its image extension(s): ``a/b.jpg`` and ``a/b.jpg.png`` -> ``a/b``."""
    for _ in range(2):
        base, ext = os.path.splitext(rel)
        if ext.lower() not in IMAGE_EXTS:
            break
        rel = base
    return rel


def match_masks(names: list[str], mask_dir: Path) -> list[Path]:
    """The mask file of each image name (a path relative to ``images/``), matched by stem."""
    if not mask_dir.is_dir():
        raise DatasetError(f"{mask_dir}: mask folder not found (COLMAP datasets need a masks/ folder, one mask per image)")
    index: dict[str, Path] = {}
    for p in sorted(mask_dir.rglob("*")):
        if p.is_file() and p.suffix.lower() in IMAGE_EXTS and not p.name.startswith("."):
            key = _stem_key(p.relative_to(mask_dir).as_posix())
            if key in index:
                raise DatasetError(f"{mask_dir}: {index[key].name} and {p.name} are both masks of image stem {key!r}")
            index[key] = p
    missing = [n for n in names if _stem_key(n) not in index]
    if missing:
        raise DatasetError(f"{mask_dir}: no mask for " + ", ".join(missing[:5]) + (" ..." if len(missing) > 5 else "")
                           + f" ({len(missing)} of {len(names)} images; masks are matched to images by file stem)")
    return [index[_stem_key(n)] for n in names]


class _Undistorter:
    """Per camera, the source pixel (rows, cols) of every undistorted pixel centre, computed
    once (shared by the decoding threads)."""

    def __init__(self):
        self._maps: dict = {}
        self._lock = threading.Lock()

    def coords(self, camera, K: np.ndarray) -> np.ndarray:
        with self._lock:
            if camera.camera_id not in self._maps:
                h, w = camera.height, camera.width
                u, v = np.meshgrid(np.arange(w) + 0.5, np.arange(h) + 0.5)
                ray = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], -1).reshape(-1, 3)
                uv = camera.img_from_cam(ray)  # distorted image point, pixel centres at x + 0.5
                self._maps[camera.camera_id] = np.stack([uv[:, 1] - 0.5, uv[:, 0] - 0.5]).reshape(2, h, w)
            return self._maps[camera.camera_id]

    def apply(self, a: np.ndarray, coords: np.ndarray) -> np.ndarray:
        from scipy.ndimage import map_coordinates

        if a.ndim == 2:
            return map_coordinates(a, coords, order=1, mode="constant", cval=0.0).astype(np.float32)
        return np.stack([self.apply(a[..., c], coords) for c in range(a.shape[2])], axis=-1)


def _views(rec, root: Path) -> list[dict]:
    """The registered images, in name order: name, image and mask paths, camera, K, viewmat."""
    img_dir = root / "images"
    if not img_dir.is_dir():
        raise DatasetError(f"{img_dir}: image folder not found")
    regs = sorted((im for im in rec.images.values() if im.has_pose), key=lambda im: im.name)
    if not regs:
        raise DatasetError(f"{root}: the COLMAP model has no registered image")
    masks = match_masks([im.name for im in regs], root / "masks")
    out = []
    for im, mask in zip(regs, masks):
        path = img_dir / im.name
        if not path.is_file():
            raise DatasetError(f"{path}: image {im.name!r} of the COLMAP model not found")
        cam = rec.cameras[im.camera_id]
        size = image_size(path)
        if size != (cam.height, cam.width):
            raise DatasetError(f"{path}: size {size[1]}x{size[0]} differs from its COLMAP camera {cam.camera_id} "
                               f"({cam.width}x{cam.height})")
        V = np.eye(4)
        V[:3, :4] = im.cam_from_world().matrix()
        out.append({"name": im.name, "path": path, "mask": mask, "camera": cam,
                    "K": camera_matrix(cam, str(root / "sparse")), "viewmat": V})
    return out


def _reader(views: list[dict]):
    """``read_one(i, shape)`` for :func:`read_views`: decode, undistort at full resolution
    when the camera has distortion, area-resize to ``shape``."""
    full = (views[0]["path"], image_size(views[0]["path"]))
    und = _Undistorter()

    def read_one(i: int, shape):
        v = views[i]
        distorted = v["camera"].model.name not in PINHOLE_MODELS
        at = None if distorted else shape
        im = read_image(v["path"], shape=at, expect=full)
        if im.ndim == 2:
            im = np.repeat(im[..., None], 3, axis=-1)
        mk = read_mask(v["mask"], shape=at, expect=(f"its image {v['path'].name}", full[1]))
        check_mask(mk, str(v["mask"]))
        im = np.ascontiguousarray(im[..., :3])
        if distorted:
            coords = und.coords(v["camera"], v["K"])
            im, mk = und.apply(im, coords), und.apply(mk, coords)
            if tuple(shape) != im.shape[:2]:
                im, mk = area_resize(im, shape), area_resize(mk, shape)
        return {"image": np.clip(im, 0.0, 1.0), "mask": np.clip(mk, 0.0, 1.0)}

    return read_one, full


def load_colmap(path: str | os.PathLike, *, res: int | None = None, test_every: int = 10, normalize: bool = True,
                workers: int | None = None, device: str = "cpu") -> Dataset:
    """Read a COLMAP folder (see the module docstring).

    Args:
        path: dataset folder (with ``sparse/0``, ``images``, ``masks``).
        res: optional output resolution (longer side); each view is area-resized as it is
            decoded (after undistortion).
        test_every: view ``i`` (in name order) is a test view when ``i % test_every == 0``.
        normalize: map the masks' visual hull to the unit sphere and the cameras' mean up to
            +Z (``False`` keeps COLMAP's world).
        workers: decoding threads (default :func:`holowarp.data.common.default_workers`).
        device: where the normalising carve runs.
    """
    root = Path(path)
    if int(test_every) < 1:
        raise DatasetError(f"--test-every must be >= 1, got {test_every}")
    model_dir = find_model(root)
    if model_dir is None:
        raise DatasetError(f"{root}: no COLMAP model in sparse/0 or sparse (cameras.bin|txt and images.bin|txt)")
    rec = read_model(model_dir)
    views = _views(rec, root)
    read_one, full = _reader(views)
    arr = read_views(len(views), read_one, full_shape=full[1], size=res, workers=workers)
    n = len(views)
    idx = np.arange(n)
    unregistered = sorted(im.name for im in rec.images.values() if not im.has_pose)
    meta = {"format": "colmap", "model": str(model_dir), "images": [v["name"] for v in views],
            "mask_files": [str(v["mask"].relative_to(root / "masks")) for v in views], "unregistered": unregistered,
            "held_out": {"test_every": int(test_every), "views": idx[idx % test_every == 0].tolist()},
            "cameras": {int(c.camera_id): {"model": c.model.name, "params": [float(x) for x in c.params],
                                           "undistorted": c.model.name not in PINHOLE_MODELS}
                        for c in {v["camera"].camera_id: v["camera"] for v in views}.values()}}
    ds = Dataset(images=arr["image"], masks=arr["mask"],
                 K=scale_intrinsics(np.stack([v["K"] for v in views]), arr["full_shape"], arr["shape"]),
                 viewmats=np.stack([v["viewmat"] for v in views]), train_idx=idx[idx % test_every != 0],
                 test_idx=idx[idx % test_every == 0], root=root,
                 gt_mesh=(root / "gt.obj") if (root / "gt.obj").is_file() else None, name=root.name, meta=meta)
    if normalize:
        from holowarp.data.normalize import normalize_to_unit_sphere

        ds.viewmats, meta["normalization"] = normalize_to_unit_sphere(ds, device=device)
    return ds


def write_colmap(dataset: Dataset, out_dir: str | os.PathLike, *, text: bool = False) -> Path:
    """Write a :class:`Dataset` as a COLMAP folder: ``sparse/0`` (binary, or text with
    ``text=True``) with one PINHOLE camera per distinct K, ``images/<i>.png`` (8-bit RGB) and
    ``masks/<i>.png`` (8-bit), view ``i`` named ``f"{i:04d}.png"``. COLMAP's pinhole models
    have no skew, so a K with ``K[0, 1] != 0`` is refused."""
    import pycolmap
    from PIL import Image

    from holowarp.fileio import atomic_path

    out = Path(out_dir)
    K = np.asarray(dataset.K, dtype=np.float64)
    if np.abs(K[:, 0, 1]).max() > 1e-9 * np.abs(K[:, 0, 0]).max():
        raise DatasetError(f"{out}: COLMAP's PINHOLE camera has no skew; this dataset's K[0, 1] is up to "
                           f"{np.abs(K[:, 0, 1]).max():.3g} px")
    rec, cams = pycolmap.Reconstruction(), {}
    for i in range(dataset.num_views):
        key = tuple(np.round(K[i, [0, 1, 0, 1], [0, 1, 2, 2]], 9))
        if key not in cams:
            cams[key] = len(cams) + 1
            rec.add_camera_with_trivial_rig(pycolmap.Camera(model="PINHOLE", width=dataset.width, height=dataset.height,
                                                            params=list(K[i, [0, 1, 0, 1], [0, 1, 2, 2]]),
                                                            camera_id=cams[key]))
        name = f"{i:04d}.png"
        rec.add_image_with_trivial_frame(pycolmap.Image(name=name, camera_id=cams[key], image_id=i + 1),
                                         pycolmap.Rigid3d(np.asarray(dataset.viewmats[i][:3, :4], dtype=np.float64)))
        for sub, a in (("images", dataset.images[i]), ("masks", dataset.masks[i])):
            with atomic_path(out / sub / name) as tmp:
                Image.fromarray(np.clip(np.rint(a * 255.0), 0, 255).astype(np.uint8)).save(tmp, format="PNG")
    model = out / "sparse" / "0"
    model.mkdir(parents=True, exist_ok=True)
    if text:
        rec.write_text(model)
    else:
        rec.write(model)
    return out
