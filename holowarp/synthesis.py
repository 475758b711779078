"""Synthetic ground-truth views of a mesh in the NeRF-synthetic layout (method.md §2).

:func:`synthesize` turns one surface (any format of :mod:`holowarp.surface_io`) into a
dataset folder::

    DIR/transforms_train.json   camera_angle_x, frames[{file_path, transform_matrix, ...}]
    DIR/transforms_test.json
    DIR/train/r_<view>.png          RGBA, 8 bit, straight alpha = coverage (the mask)
    DIR/train/r_<view>_normal.png   world-space normal encoded (n + 1) / 2, alpha = mask
    DIR/train/r_<view>_depth.png    camera z-depth, 16 bit, depth = value * depth_png_scale
    DIR/train/r_<view>_geom.npz     exact float32 ``normal`` (H, W, 3) and ``depth`` (H, W)
    DIR/test/...                    the same for the test views
    DIR/gt.obj                      welded, Z-up, normalised ground-truth surface

Protocol: ``views`` cameras on a Fibonacci sphere (``holowarp.camera.fibonacci_sphere``)
looking at the origin with Z up, horizontal fov 39.3 degrees, square images; view ``i`` is a
test view when ``i % test_every == 0`` (0, 10, ..., 110 for 120 views). ``<view>`` in the
file names is the ORIGINAL view index, and every frame also carries ``view_index``, so the
split and the ordering are recoverable; ``holowarp.view_order`` lists them.

Frames. The mesh is first rotated to Z up (``up_axis="y"``: (x, y, z) -> (x, -z, y), the
usual OBJ convention of spot and bob) and then translated and uniformly scaled so its
bounding box is centred at the origin with largest side 1 -- the evaluation frame of
method.md §1. The dataset's world IS therefore the evaluation frame, and ``gt.obj`` lives in
it. The transform ``p_world = scale * (R @ p_obj) + translation`` is recorded under the
extra key ``"holowarp"`` of both transforms files (NeRF tools ignore unknown keys).

Cameras sit at distance ``r / sin(fov / 2) * margin`` from the origin, ``r`` the radius of
the object's bounding sphere about the origin, so the object fills most of the frame.
Shading: texture from the OBJ's UVs and ``map_Kd`` image when it has them, else vertex
colours, else a fixed albedo; fixed world lights (:class:`holowarp.render_gt.Lighting`);
transparent background; 2 x 2 stratified supersampling by default so masks have soft,
antialiased edges (alpha = coverage).
"""

from __future__ import annotations

import math
import os
from pathlib import Path

import numpy as np

from holowarp.camera import FOV_DEG, fibonacci_sphere, intrinsics_from_fov, look_at, viewmat_to_opengl_c2w
from holowarp.errors import InputError
from holowarp.fileio import atomic_path, atomic_save_npz, atomic_write_json, check_output_dir
from holowarp.frame import FrameError, unit_cube_transform

__all__ = [
    "SynthError",
    "synthesize",
    "write_dataset",
    "source_meta",
    "check_synth_args",
    "default_dataset",
    "up_axis_rotation",
    "normalisation",
    "protocol_cameras",
    "TEST_EVERY",
    "NUM_VIEWS",
    "DEFAULT_OBJECT",
]

#: Views per object and test-view stride of the paper's protocol (method.md §2).
NUM_VIEWS = 120
TEST_EVERY = 10
#: Camera distance margin over the tight bounding-sphere distance ("fills most of the frame").
DISTANCE_MARGIN = 1.1
#: Version of the layout written under the "holowarp" key.
LAYOUT_VERSION = 1


#: The built-in default object: bob (genus 1, CC0), shipped with the package.
DEFAULT_OBJECT = Path(__file__).resolve().parent / "assets" / "bob" / "bob_tri.obj"


class SynthError(InputError):
    """Bad arguments to :func:`synthesize`; the message names the argument or file."""


def up_axis_rotation(up_axis: str) -> np.ndarray:
    """Rotation (3, 3) taking a model with the given up axis to Z up.

    ``"y"``: (x, y, z) -> (x, -z, y), a proper rotation of +90 degrees about x;
    ``"z"``: identity.
    """
    up = str(up_axis).lower()
    if up == "y":
        return np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])
    if up == "z":
        return np.eye(3)
    raise SynthError(f"--up-axis {up_axis!r}: expected 'y' or 'z'")


def normalisation(points: np.ndarray):
    """``(scale, translation)`` mapping ``points`` (P, 3) to the evaluation frame of method.md
    §1: bounding box centred at the origin, largest side 1 (``p' = scale * p + translation``)."""
    try:
        return unit_cube_transform(points)
    except FrameError as e:
        raise SynthError(f"mesh: {e}") from None


def protocol_cameras(num_views: int, distance: float, res: int, *, fov_deg: float = FOV_DEG):
    """Cameras of the synthetic protocol: ``(viewmats (N, 4, 4), K (3, 3))``, OpenCV, Z up."""
    dirs = fibonacci_sphere(num_views)
    K = intrinsics_from_fov(math.radians(fov_deg), res, res)
    viewmats = np.stack([look_at(d * distance, (0.0, 0.0, 0.0), (0.0, 0.0, 1.0)) for d in dirs])
    return viewmats, K


def _save_png(path: Path, arr: np.ndarray):
    """PNG of a uint8 (H, W[, C]) or uint16 (H, W) array, written atomically."""
    from PIL import Image

    with atomic_path(path) as tmp:
        Image.fromarray(arr).save(tmp, format="PNG")


def _to_u8(x: np.ndarray) -> np.ndarray:
    return np.clip(np.rint(np.asarray(x) * 255.0), 0, 255).astype(np.uint8)


def _view_files(out: Path, split: str, i: int) -> dict:
    base = out / split / f"r_{i}"
    return {
        "rgba": base.with_name(base.name + ".png"),
        "normal": base.with_name(base.name + "_normal.png"),
        "depth": base.with_name(base.name + "_depth.png"),
        "geom": base.with_name(base.name + "_geom.npz"),
    }


def check_synth_args(out: Path, *, views, res, test_every, supersample, fov_deg, resume, overwrite, up_axis):
    if views < 1:
        raise SynthError(f"--views must be >= 1, got {views}")
    if res < 8:
        raise SynthError(f"--res must be >= 8 pixels, got {res}")
    if test_every < 1:
        raise SynthError(f"--test-every must be >= 1, got {test_every}")
    n_train = sum(i % test_every != 0 for i in range(views))
    if n_train == 0:
        raise SynthError(f"--views {views} with --test-every {test_every} leaves no training view "
                         f"(view i is a test view when i % {test_every} == 0); use more views")
    if supersample < 1:
        raise SynthError(f"--supersample must be >= 1, got {supersample}")
    if not (0.0 < fov_deg < 180.0):
        raise SynthError(f"fov must lie in (0, 180) degrees, got {fov_deg}")
    if (out / "transforms_train.json").exists() and not (resume or overwrite):
        raise SynthError(f"{out} already holds a dataset; pass --resume to continue it or --overwrite to replace it")
    if resume and (out / "transforms_train.json").exists():
        import json

        try:
            prev = json.loads((out / "transforms_train.json").read_text()).get("holowarp", {})
        except (OSError, ValueError):
            prev = {}
        want = {"num_views": views, "resolution": res, "supersample": supersample, "up_axis": str(up_axis).lower(),
                "test_every": test_every}
        diff = {k: (prev.get(k), v) for k, v in want.items() if k in prev and prev.get(k) != v}
        if diff:
            raise SynthError(
                f"{out}: --resume with settings that differ from the existing dataset "
                + ", ".join(f"{k}: {a} -> {b}" for k, (a, b) in diff.items())
                + "; use --overwrite to replace it"
            )


def _normalised_mesh(mesh_path: Path, up_axis: str):
    """The welded surface in the evaluation frame, with the rotation, scale and translation
    that put it there."""
    from holowarp.surface_io import load_surface_mesh

    obj = load_surface_mesh(mesh_path).welded()
    R = up_axis_rotation(up_axis)
    rotated = obj.positions @ R.T
    scale, translation = normalisation(rotated)
    obj.positions = rotated * scale + translation
    return obj, R, scale, translation


def _render_views(renderer, out: Path, todo, split_of, viewmats, K, res: int, depth_scale: float, bar) -> None:
    for j, r in renderer.render_views(viewmats[todo], [K] * len(todo), res, res):
        i = todo[j]
        files = _view_files(out, split_of[i], i)
        rgba, mask = r["rgba"], r["mask"]
        _save_png(files["rgba"], _to_u8(rgba))
        n = r["normal"]
        n_rgba = np.concatenate([(n + 1.0) * 0.5 * (mask[..., None] > 0), mask[..., None]], axis=-1)
        _save_png(files["normal"], _to_u8(n_rgba))
        d16 = np.clip(np.rint(r["depth"] / depth_scale), 0, 65535).astype(np.uint16)
        _save_png(files["depth"], d16)
        atomic_save_npz(files["geom"], normal=n.astype(np.float32), depth=r["depth"].astype(np.float32))
        bar.update(1)


def _write_transforms(out: Path, meta: dict, split_of, viewmats, K, res: int, fov_deg: float) -> None:
    for split in ("train", "test"):
        idx = [i for i in range(len(split_of)) if split_of[i] == split]
        frames = []
        for i in idx:
            files = _view_files(out, split, i)
            frames.append({
                "file_path": f"./{split}/r_{i}",
                "transform_matrix": viewmat_to_opengl_c2w(viewmats[i]).tolist(),
                "view_index": i,
                "normal_path": f"./{split}/{files['normal'].name}",
                "depth_path": f"./{split}/{files['depth'].name}",
                "geometry_path": f"./{split}/{files['geom'].name}",
            })  # fmt: skip
        doc = {
            "camera_angle_x": math.radians(fov_deg),
            "w": res,
            "h": res,
            "fl_x": float(K[0, 0]),
            "fl_y": float(K[1, 1]),
            "cx": float(K[0, 2]),
            "cy": float(K[1, 2]),
            "frames": frames,
            "holowarp": dict(meta, split=split, view_order=idx),
        }
        atomic_write_json(out / f"transforms_{split}.json", doc)


def source_meta(mesh_path: Path, up_axis, R, scale, translation) -> dict:
    """Where the dataset's world comes from: the first keys of the ``"holowarp"`` block
    (``source``, ``up_axis`` and the object-to-world ``transform``)."""
    return {
        "source": str(Path(mesh_path).resolve()),
        "up_axis": str(up_axis).lower(),
        "transform": {"doc": "p_world = scale * (rotation @ p_obj) + translation", "rotation": np.asarray(R).tolist(),
                      "scale": scale, "translation": np.asarray(translation).tolist()},
    }


def _meta(source: dict, *, views, test_every, res, supersample, distance, radius, depth_scale, shading, lighting,
          obj) -> dict:
    """The ``"holowarp"`` block of the transforms files (see the module docstring); ``source``
    is :func:`source_meta`'s dict (or a scene's)."""
    return {
        "version": LAYOUT_VERSION,
        **source,
        "frame": "evaluation frame (method.md 1): GT bbox centred at the origin, largest side 1, Z up",
        "num_views": views, "test_every": test_every, "resolution": res, "supersample": supersample,
        "camera_distance": distance, "bounding_radius": radius,
        "depth": "camera z-depth in world units; *_depth.png value * depth_png_scale, exact in *_geom.npz",
        "depth_png_scale": depth_scale,
        "normal": "world-space unit normal; *_normal.png stores (n + 1) / 2, exact in *_geom.npz",
        "shading": shading,
        "lighting": {"ambient": list(lighting.ambient), "directions": [list(d) for d in lighting.directions],
                     "colors": [list(c) for c in lighting.colors]},
        "gt_mesh": "gt.obj", "num_gt_vertices": int(len(obj.positions)), "num_gt_faces": int(len(obj.faces)),
    }  # fmt: skip


def synthesize(
    mesh_path: str | os.PathLike,
    out_dir: str | os.PathLike,
    *,
    views: int = NUM_VIEWS,
    res: int = 512,
    device: str = "cpu",
    up_axis: str = "y",
    test_every: int = TEST_EVERY,
    fov_deg: float = FOV_DEG,
    supersample: int = 2,
    margin: float = DISTANCE_MARGIN,
    albedo=(0.72, 0.72, 0.72),
    resume: bool = False,
    overwrite: bool = False,
    progress: bool = True,
) -> dict:
    """Render the ground-truth views of ``mesh_path`` into ``out_dir`` (see module docstring).

    Args:
        mesh_path: a surface file (OBJ textured or not, OFF, STL, PLY, GLB...).
        out_dir: dataset folder to write.
        views: number of Fibonacci-sphere views.
        res: image width = height in pixels.
        device: ``"cpu"`` or ``"cuda[:N]"``.
        up_axis: the model's up axis, ``"y"`` (OBJ convention) or ``"z"``.
        test_every: view ``i`` is a test view when ``i % test_every == 0``.
        supersample: stratified rays per pixel along each axis (antialiasing).
        margin: camera distance factor over the tight bounding-sphere distance.
        resume: keep views whose files already exist (an interrupted run continues).
        overwrite: allow writing into a folder that already holds a dataset.
        progress: show a progress bar.

    Returns:
        A summary dict (views, train/test counts, camera distance, transform, seconds).

    Raises:
        SynthError / SurfaceError: bad argument, unreadable mesh, or an existing dataset in
            ``out_dir`` without ``resume``/``overwrite``.
    """
    import time

    from holowarp.render_gt import GTRenderer

    t0 = time.perf_counter()
    mesh_path, out = Path(mesh_path), check_output_dir(out_dir)
    check_synth_args(out, views=views, res=res, test_every=test_every, supersample=supersample, fov_deg=fov_deg,
                resume=resume, overwrite=overwrite, up_axis=up_axis)
    obj, R, scale, translation = _normalised_mesh(mesh_path, up_axis)
    renderer = GTRenderer.from_obj(obj, albedo=albedo, supersample=supersample, device=device)
    return write_dataset(renderer, obj, out, source_meta(mesh_path, up_axis, R, scale, translation), views=views,
                         res=res, test_every=test_every, fov_deg=fov_deg, supersample=supersample, margin=margin,
                         resume=resume, progress=progress, desc=f"synth {mesh_path.stem}", t0=t0,
                         gt_header=f"holowarp ground truth from {mesh_path.name}: welded, Z up, bbox centred at origin, "
                                   "largest side 1")


def write_dataset(renderer, obj, out: Path, source: dict, *, views: int, res: int, test_every: int, fov_deg: float,
                  supersample: int, margin: float, resume: bool, progress: bool, desc: str, gt_header: str,
                  t0: float | None = None) -> dict:
    """Render ``renderer``'s surface from the protocol cameras and write the dataset folder
    ``out`` (views, both transforms files, ``gt.obj`` = ``obj``'s geometry), for a surface
    ALREADY in the evaluation frame.

    ``obj`` (:class:`holowarp.surface_io.SurfaceMesh`) gives the geometry of ``gt.obj``, the
    camera distance and the shading name; ``source`` is the first keys of the ``"holowarp"``
    block (:func:`source_meta`). Arguments were checked by the caller; returns the summary
    of :func:`synthesize`.
    """
    import time

    from holowarp.progress import bar as progress_bar
    from holowarp.surface_io import write_surface

    t0 = time.perf_counter() if t0 is None else t0
    verts = obj.positions
    radius = float(np.linalg.norm(verts, axis=1).max())
    distance = radius / math.sin(math.radians(fov_deg) / 2.0) * margin
    viewmats, K = protocol_cameras(views, distance, res, fov_deg=fov_deg)
    depth_scale = (distance + radius) * 1.5 / 65535.0
    split_of = ["test" if i % test_every == 0 else "train" for i in range(views)]
    todo = [i for i in range(views)
            if not (resume and all(p.is_file() for p in _view_files(out, split_of[i], i).values()))]
    for s in ("train", "test"):
        (out / s).mkdir(parents=True, exist_ok=True)
    shading = "texture" if obj.textured else ("vertex_colors" if obj.vertex_colors is not None else "albedo")
    bar = progress_bar(views, initial=views - len(todo), desc=desc, unit="view", progress=progress)
    _render_views(renderer, out, todo, split_of, viewmats, K, res, depth_scale, bar)
    bar.close()
    meta = _meta(source, views=views, test_every=test_every, res=res, supersample=supersample, distance=distance,
                 radius=radius, depth_scale=depth_scale, shading=shading, lighting=renderer.lighting, obj=obj)
    _write_transforms(out, meta, split_of, viewmats, K, res, fov_deg)
    write_surface(out / "gt.obj", (verts, obj.faces), header=gt_header)
    return {"out": str(out), "views": views, "train": split_of.count("train"), "test": split_of.count("test"),
            "rendered": len(todo), "resolution": res, "camera_distance": distance, "shading": shading,
            "seconds": time.perf_counter() - t0}


def default_dataset(out_dir: str | os.PathLike, *, res: int, device: str = "cpu", progress: bool = True) -> Path:
    """The built-in default object (:data:`DEFAULT_OBJECT`) synthesised into ``out_dir`` at
    ``res`` (120 Fibonacci views, method.md §2), unless it is there already."""
    out = Path(out_dir)
    if not ((out / "transforms_train.json").is_file() and (out / "transforms_test.json").is_file()):
        synthesize(DEFAULT_OBJECT, out, res=res, device=device, up_axis="y", resume=True, progress=progress)
    return out
