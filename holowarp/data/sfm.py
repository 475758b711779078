"""Camera poses from photos: pycolmap's structure from motion on the CPU, photos + masks in,
the COLMAP folder :mod:`holowarp.data.colmap` reads out (``python -m holowarp.poses``).

Steps, one progress line each:

1. copy the photos to ``OUT/images`` and their masks (matched by file stem) to ``OUT/masks``;
2. SIFT features (``pycolmap.extract_features``), one shared camera of ``camera_model`` by
   default (one camera per photo with ``single_camera=False``);
3. exhaustive matching with geometric verification (``pycolmap.match_exhaustive``);
4. incremental mapping (``pycolmap.incremental_mapping``); the model with the most
   registered photos goes to ``OUT/sparse/0`` (binary), a summary to ``OUT/poses.json``;
   the feature database stays in ``OUT/database.db``.

Defaults are COLMAP's except where object captures differ from the scenes COLMAP is tuned
for: an object fills only part of each photo and neighbouring views are often 20-30 degrees
apart, so a photo pair needs fewer verified matches to start a model (50, COLMAP 100) and a
photo fewer inliers to register (15 and 10 %, COLMAP 30 and 25 %). Features are taken from
the whole photo, background included (a static background constrains the poses best); use
``mask_features`` for turntable captures, where the background does not move with the object.
"""

from __future__ import annotations

import math
import os
import shutil
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from holowarp.data.colmap import PINHOLE_MODELS, UNDISTORTED_MODELS, match_masks
from holowarp.data.common import IMAGE_EXTS, image_size
from holowarp.errors import InputError, RunError

__all__ = ["SfMSettings", "SfMError", "CAMERA_MODELS", "list_photos", "run_sfm", "align_cameras"]

#: Camera models the mapper may estimate (the ones :mod:`holowarp.data.colmap` loads).
CAMERA_MODELS = PINHOLE_MODELS + UNDISTORTED_MODELS


class SfMError(RunError):
    """Structure from motion ran but could not pose enough of the photos."""


@dataclass(frozen=True)
class SfMSettings:
    """Settings of :func:`run_sfm` (see the module docstring for the non-COLMAP defaults).

    Attributes:
        camera_model: COLMAP model the mapper estimates, one of :data:`CAMERA_MODELS`.
        single_camera: all photos share one camera (one phone or camera, fixed zoom).
        max_features: SIFT features per photo.
        mask_features: keep only features inside the masks.
        min_registered: fail unless at least this fraction of the photos is posed (0..1].
        init_min_inliers: verified matches a photo pair needs to start a model.
        abs_pose_min_inliers: inlier matches a photo needs to be registered.
        abs_pose_min_inlier_ratio: inlier fraction a photo needs to be registered.
        seed: random seed of RANSAC and the mapper (runs are repeatable up to threading).
        threads: CPU threads (-1: all).
    """

    camera_model: str = "SIMPLE_RADIAL"
    single_camera: bool = True
    max_features: int = 8192
    mask_features: bool = False
    min_registered: float = 0.5
    init_min_inliers: int = 50
    abs_pose_min_inliers: int = 15
    abs_pose_min_inlier_ratio: float = 0.1
    seed: int = 0
    threads: int = -1

    def check(self) -> None:
        if self.camera_model not in CAMERA_MODELS:
            raise InputError(f"--camera-model {self.camera_model!r}: choose one of {', '.join(CAMERA_MODELS)}")
        if not 0.0 < self.min_registered <= 1.0:
            raise InputError(f"--min-registered must lie in (0, 1], got {self.min_registered}")
        for name in ("max_features", "init_min_inliers", "abs_pose_min_inliers"):
            if int(getattr(self, name)) < 1:
                raise InputError(f"{name} must be >= 1, got {getattr(self, name)}")
        if self.threads == 0 or self.threads < -1:
            raise InputError(f"--threads must be >= 1 (or -1 for all cores), got {self.threads}")


def list_photos(folder: Path) -> list[str]:
    """Image files under ``folder`` (subfolders too), as sorted POSIX paths relative to it."""
    if not folder.is_dir():
        raise InputError(f"{folder}: photo folder not found")
    names = sorted(p.relative_to(folder).as_posix() for p in folder.rglob("*")
                   if p.is_file() and p.suffix.lower() in IMAGE_EXTS and not p.name.startswith("."))
    if len(names) < 3:
        raise InputError(f"{folder}: {len(names)} photos ({', '.join(IMAGE_EXTS)}); structure from motion needs at least 3")
    return names


def _check_inputs(images: Path, masks: Path, out: Path, settings: SfMSettings, overwrite: bool):
    """(photo names, their masks): every problem is an InputError before any work."""
    from holowarp.data.dataset import DatasetError
    from holowarp.fileio import check_output_dir

    settings.check()
    check_output_dir(out)
    if (out / "sparse").exists() and not overwrite:
        raise InputError(f"--out {out}: already holds a COLMAP model (sparse/); pass --overwrite to replace it")
    names = list_photos(images)
    try:
        mask_files = match_masks(names, masks)
    except DatasetError as e:
        raise InputError(str(e)) from None
    sizes = {n: image_size(images / n) for n in names}
    first = names[0]
    for n, m in zip(names, mask_files):
        if image_size(m) != sizes[n]:
            raise InputError(f"{m}: mask size {image_size(m)[1]}x{image_size(m)[0]} differs from its photo {n} "
                             f"({sizes[n][1]}x{sizes[n][0]})")
        if settings.single_camera and sizes[n] != sizes[first]:
            raise InputError(f"{images / n}: size {sizes[n][1]}x{sizes[n][0]} differs from {first} "
                             f"({sizes[first][1]}x{sizes[first][0]}); one shared camera needs one size "
                             "(use --camera-per-image)")
    return names, mask_files


def _copy(src: Path, dst: Path) -> None:
    from holowarp.fileio import atomic_path

    if src.resolve() == dst.resolve():
        return
    with atomic_path(dst) as tmp:
        shutil.copyfile(src, tmp)


def _feature_masks(names, mask_files, folder: Path) -> None:
    """COLMAP's feature masks: ``folder/<name>.png``, 0 where features are ignored."""
    from PIL import Image

    for n, m in zip(names, mask_files):
        p = folder / f"{n}.png"
        p.parent.mkdir(parents=True, exist_ok=True)
        with Image.open(m) as im:
            im.convert("L").point(lambda x: 255 if x > 0 else 0).save(p)


def _options(pycolmap, settings: SfMSettings):
    """(reader, extraction, matching, mapping) options of pycolmap."""
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = settings.camera_model
    extraction = pycolmap.FeatureExtractionOptions()
    extraction.num_threads = settings.threads
    extraction.sift.max_num_features = int(settings.max_features)
    matching = pycolmap.FeatureMatchingOptions()
    matching.num_threads = settings.threads
    mapping = pycolmap.IncrementalPipelineOptions()
    mapping.num_threads = settings.threads
    mapping.random_seed = mapping.mapper.random_seed = mapping.triangulation.random_seed = int(settings.seed)
    mapping.mapper.init_min_num_inliers = int(settings.init_min_inliers)
    mapping.mapper.abs_pose_min_num_inliers = int(settings.abs_pose_min_inliers)
    mapping.mapper.abs_pose_min_inlier_ratio = float(settings.abs_pose_min_inlier_ratio)
    mapping.min_model_size = 3
    return reader, extraction, matching, mapping


def _camera_summary(rec) -> list[dict]:
    return [{"camera_id": int(c.camera_id), "model": c.model.name, "width": int(c.width), "height": int(c.height),
             "params": [float(x) for x in c.params]} for c in rec.cameras.values()]


def run_sfm(images, masks, out, *, settings: SfMSettings = SfMSettings(), overwrite: bool = False,
            progress: bool = True) -> dict:
    """Pose the photos in ``images`` (masks in ``masks``) and write the COLMAP folder ``out``
    (see the module docstring). Returns the summary also written to ``out/poses.json``.

    Raises:
        InputError: bad folders or settings (before any work).
        SfMError: fewer than ``settings.min_registered`` of the photos (or fewer than 3)
            could be posed; the message says how many of how many.
    """
    import pycolmap

    from holowarp.fileio import atomic_write_json
    from holowarp.progress import say

    images, masks, out = Path(images), Path(masks), Path(out)
    names, mask_files = _check_inputs(images, masks, out, settings, overwrite)
    n, t0, seconds = len(names), time.perf_counter(), {}
    say(f"[1/4] copying {n} photos and their masks to {out}", progress)
    shutil.rmtree(out / "sparse", ignore_errors=True)
    for name, m in zip(names, mask_files):
        _copy(images / name, out / "images" / name)
        _copy(m, out / "masks" / m.relative_to(masks))
    db = out / "database.db"
    db.unlink(missing_ok=True)
    reader, extraction, matching, mapping = _options(pycolmap, settings)
    level, pycolmap.logging.minloglevel = pycolmap.logging.minloglevel, 2  # our lines replace glog's
    try:
        pycolmap.set_random_seed(int(settings.seed))
        rec, seconds = _pose(pycolmap, db, out, names, mask_files, settings, (reader, extraction, matching, mapping),
                             progress)
    finally:
        pycolmap.logging.minloglevel = level
    k = rec.num_reg_images() if rec is not None else 0
    need = max(3, math.ceil(settings.min_registered * n))
    if k < need:
        hint = ("drop --mask-features if the background is static (its features help)" if settings.mask_features
                else "use --mask-features if the object turned in front of a fixed camera")
        raise SfMError(f"structure from motion posed only {k} of {n} photos (need {need}: --min-registered "
                       f"{settings.min_registered:g}); neighbouring photos need more overlap or texture, or {hint}")
    _write_model(rec, out / "sparse" / "0")
    posed = {im.name for im in rec.images.values() if im.has_pose}
    summary = {"photos": n, "registered": k, "unregistered": [x for x in names if x not in posed],
               "points3D": int(rec.num_points3D()), "mean_reprojection_error_px": float(rec.compute_mean_reprojection_error()),
               "cameras": _camera_summary(rec), "settings": asdict(settings), "seconds": seconds,
               "total_seconds": round(time.perf_counter() - t0, 2), "model": str(out / "sparse" / "0")}
    atomic_write_json(out / "poses.json", summary)
    say(f"posed {k} of {n} photos, {summary['points3D']} points, mean reprojection error "
        f"{summary['mean_reprojection_error_px']:.3f} px -> {out / 'sparse' / '0'}", progress)
    return summary


def _pose(pycolmap, db: Path, out: Path, names, mask_files, settings, options, progress):
    """Steps 2-4; (largest reconstruction or None, seconds per step)."""
    import tempfile

    from holowarp.progress import say

    reader, extraction, matching, mapping = options
    seconds, n = {}, len(names)
    mode = pycolmap.CameraMode.SINGLE if settings.single_camera else pycolmap.CameraMode.PER_IMAGE
    threads = os.cpu_count() if settings.threads == -1 else settings.threads
    with tempfile.TemporaryDirectory(prefix="holowarp-sfm-") as tmp:
        if settings.mask_features:
            _feature_masks(names, mask_files, Path(tmp) / "masks")
            reader.mask_path = str(Path(tmp) / "masks")
        say(f"[2/4] SIFT features of {n} photos ({settings.camera_model}, "
            f"{'one camera' if settings.single_camera else 'a camera per photo'}, CPU, {threads} threads)", progress)
        t = time.perf_counter()
        pycolmap.extract_features(db, out / "images", image_names=names, camera_mode=mode, reader_options=reader,
                                  extraction_options=extraction, device=pycolmap.Device.cpu)
        seconds["features"] = round(time.perf_counter() - t, 2)
        say(f"[3/4] matching {n * (n - 1) // 2} photo pairs (exhaustive, geometric verification)", progress)
        t = time.perf_counter()
        pycolmap.match_exhaustive(db, matching_options=matching, device=pycolmap.Device.cpu)
        seconds["matching"] = round(time.perf_counter() - t, 2)
        say("[4/4] incremental mapping and bundle adjustment", progress)
        t = time.perf_counter()
        recs = pycolmap.incremental_mapping(db, out / "images", Path(tmp) / "sparse", options=mapping)
        seconds["mapping"] = round(time.perf_counter() - t, 2)
    best = max(recs.values(), key=lambda r: r.num_reg_images(), default=None)
    return best, seconds


def _write_model(rec, folder: Path) -> None:
    """Write ``rec`` (binary) to ``folder`` through a temporary sibling renamed into place."""
    import tempfile

    folder.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=".sparse-", dir=folder.parent))
    try:
        rec.write(tmp)
        if folder.exists():
            shutil.rmtree(folder)
        os.replace(tmp, folder)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise


def align_cameras(viewmats, reference) -> dict:
    """Compare cameras with reference cameras of the same views, up to a similarity.

    The similarity taking the camera centres onto the reference centres is fitted in least
    squares (Umeyama, ``pycolmap.estimate_sim3d``); each camera is then moved by it and
    compared with its reference.

    Args:
        viewmats: (N, 4, 4) world-to-camera matrices (any world).
        reference: (N, 4, 4) world-to-camera matrices of the same views.

    Returns:
        dict: ``rotation_deg`` (N,) angle between each aligned camera's rotation and its
        reference's, ``center_error`` (N,) distance between the centres in reference units,
        ``scene_size`` the largest distance between two reference centres, ``scale`` of the
        similarity, and the max / mean of both errors.
    """
    import pycolmap

    from holowarp.camera import camera_center

    V, Vr = np.asarray(viewmats, np.float64), np.asarray(reference, np.float64)
    c = np.stack([camera_center(v) for v in V])
    cr = np.stack([camera_center(v) for v in Vr])
    sim = pycolmap.estimate_sim3d(c, cr)
    if sim is None:
        raise RunError("align_cameras: the camera centres are degenerate (collinear or coincident)")
    M = sim.matrix()  # 3x4, x_ref = s Ra x + t
    s = float(np.cbrt(np.linalg.det(M[:, :3])))
    Ra = M[:, :3] / s
    moved = c @ M[:, :3].T + M[:, 3]
    rel = np.einsum("nij,kj,nlk->nil", V[:, :3, :3], Ra, Vr[:, :3, :3])  # (R Ra^T) R_ref^T
    cos = np.clip((np.trace(rel, axis1=1, axis2=2) - 1.0) / 2.0, -1.0, 1.0)
    rot = np.degrees(np.arccos(cos))
    err = np.linalg.norm(moved - cr, axis=1)
    size = float(max(np.linalg.norm(cr[:, None] - cr[None], axis=-1).max(), 1e-12))
    return {"rotation_deg": rot, "center_error": err, "scene_size": size, "scale": s,
            "rotation_deg_max": float(rot.max()), "rotation_deg_mean": float(rot.mean()),
            "center_error_max": float(err.max()), "center_error_mean": float(err.mean())}
