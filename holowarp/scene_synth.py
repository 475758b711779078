"""Several objects in one capture: ``python -m holowarp.synth SCENE.toml --out DIR`` (method.md §11).

A scene file places meshes (or plain boxes) in one world; :func:`synthesize_scene` renders
them together with the protocol of :func:`holowarp.synthesis.synthesize` (method.md §2), so
a dataset of one capture with two to four separated objects can be made. The format::

    [[objects]]
    mesh = "path/to/spot.obj"       # or: box = [0.3, 0.3, 0.3]  (metres, an untextured box)
    position = [0.6, 0.0, 0.0]      # where the object's bounding-box centre goes
    scale = 1.0                     # optional: largest side after scaling
    rotation = [0.0, 0.0, 0.0]      # optional: degrees, X then Y then Z
    name = "spot"                   # optional: default the mesh file stem, else box0, box1, ...
    up_axis = "y"                   # optional: the mesh's up axis (default: the command's --up-axis)
    color = [0.8, 0.3, 0.2]         # optional: RGB in [0, 1] for an untextured object

Relative mesh paths are relative to the scene file's folder.

Placement of one object, in this order: its mesh is rotated to Z up (``up_axis``, as synth
does); uniformly scaled so the largest side of its bounding box is ``scale`` (default 1, the
unit-cube size of synth; a box keeps its own size unless ``scale`` is given); rotated by
``rotation`` (extrinsic X, then Y, then Z, as the simulator's placements); and translated so
the centre of its (world axis-aligned) bounding box is ``position``. The whole scene is then
normalised as synth normalises one object: the scene's bounding box centred at the origin
with largest side 1. The dataset's world is that frame; ``DIR/gt.obj`` is every object's
welded surface (not welded across objects, so touching objects stay separate closed
surfaces) and ``DIR/objects/NAME/gt.obj`` each object's own, in the same frame.

Colours. The ground-truth renderer shades one mesh with one colour source, so the objects
are merged into one mesh and their colours into that one source, exactly: without any
texture, per-vertex colours (an object's own, or its ``color`` / the fixed albedo on every
vertex); with a texture anywhere, one texture atlas in which each texture keeps its pixels
(padded with its own wrapped pixels, so the renderer's bilinear repeat lookup near a seam
reads what it reads on the object alone), a flat colour is a small uniform patch, and
vertex colours become one 2 x 2 texel block per face whose fourth texel ``c1 + c2 - c0``
makes the bilinear lookup equal to the barycentric interpolation of the three corner
colours. A scene renders as its objects would, each in its own colours.
"""

from __future__ import annotations

import hashlib
import math
import os
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from holowarp.camera import FOV_DEG
from holowarp.fileio import check_input_file, check_output_dir
from holowarp.synthesis import (
    DISTANCE_MARGIN,
    NUM_VIEWS,
    TEST_EVERY,
    SynthError,
    check_synth_args,
    normalisation,
    up_axis_rotation,
    write_dataset,
)

__all__ = ["SceneFileError", "SceneObject", "load_scene_file", "place_object", "merge_objects", "synthesize_scene",
           "OBJECT_KEYS"]

#: Keys of one ``[[objects]]`` entry.
OBJECT_KEYS = ("mesh", "box", "position", "scale", "rotation", "name", "up_axis", "color")
#: Least wrapped border (texels) around each texture in the atlas (the bilinear lookup's reach and more).
ATLAS_PAD = 8
_NAME = re.compile(r"^[A-Za-z0-9_][A-Za-z0-9_.-]*$")


class SceneFileError(SynthError):
    """A scene file cannot be used; the message names the file and the key."""


@dataclass(frozen=True)
class SceneObject:
    """One ``[[objects]]`` entry, checked. Lengths in scene units (metres), angles in degrees."""

    name: str
    mesh: Path | None  # the surface file, or None for a box
    box: tuple | None  # (3,) box sides
    position: tuple  # (3,) bounding-box centre
    scale: float | None  # largest side after scaling; None = the default (1 for a mesh, the box's own size)
    rotation: tuple = (0.0, 0.0, 0.0)
    up_axis: str | None = None
    color: tuple | None = None


def _numbers(src, where, key, v, n, *, lo=None, lo_open=False, hi=None) -> tuple:
    """``v`` as ``n`` finite floats (a number when ``n`` is 0), each within the bounds."""
    items = [v] if n == 0 else v
    ok = (n == 0 or (isinstance(v, list) and len(v) == n)) and all(
        isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x) for x in items)
    what = "a finite number" if n == 0 else f"a list of {n} finite numbers"
    if ok and lo is not None:
        ok = all(x > lo if lo_open else x >= lo for x in items)
        what += f" {'>' if lo_open else '>='} {lo:g}"
    if ok and hi is not None:
        ok, what = all(x <= hi for x in items), what + f" <= {hi:g}"
    if not ok:
        raise SceneFileError(f"{src}: {where}.{key} = {v!r}: expected {what}")
    return float(items[0]) if n == 0 else tuple(float(x) for x in items)


def _parse_object(src: Path, i: int, t, boxes: int) -> SceneObject:
    where = f"objects[{i}]"
    if not isinstance(t, dict):
        raise SceneFileError(f"{src}: {where}: expected a table ([[objects]]), got {type(t).__name__}")
    unknown = sorted(set(t) - set(OBJECT_KEYS))
    if unknown:
        raise SceneFileError(f"{src}: {where}: unknown key {unknown[0]!r} (known: {', '.join(OBJECT_KEYS)})")
    if ("mesh" in t) == ("box" in t):
        raise SceneFileError(f"{src}: {where}: give exactly one of mesh = \"path\" or box = [x, y, z]")
    if "position" not in t:
        raise SceneFileError(f"{src}: {where}.position: missing (where the object's bounding-box centre goes)")
    mesh = box = None
    if "mesh" in t:
        if not isinstance(t["mesh"], str) or not t["mesh"]:
            raise SceneFileError(f"{src}: {where}.mesh = {t['mesh']!r}: expected a file path")
        try:
            mesh = Path(os.path.abspath(check_input_file(src.parent / t["mesh"], error=SceneFileError,
                                                         what="surface file")))
        except SceneFileError as e:
            raise SceneFileError(f"{src}: {where}.mesh: {e}") from None
    else:
        box = _numbers(src, where, "box", t["box"], 3, lo=0.0, lo_open=True)
    name = t.get("name", mesh.stem if mesh is not None else f"box{boxes}")
    if not isinstance(name, str) or not _NAME.match(name):
        raise SceneFileError(f"{src}: {where}.name = {name!r}: expected letters, digits, '_', '.', '-' "
                             "(it names the object's folder)")
    up = t.get("up_axis")
    if up is not None and up not in ("y", "z"):
        raise SceneFileError(f"{src}: {where}.up_axis = {up!r}: expected 'y' or 'z'")
    return SceneObject(
        name=name, mesh=mesh, box=box, position=_numbers(src, where, "position", t["position"], 3),
        scale=_numbers(src, where, "scale", t["scale"], 0, lo=0.0, lo_open=True) if "scale" in t else None,
        rotation=_numbers(src, where, "rotation", t.get("rotation", [0.0, 0.0, 0.0]), 3), up_axis=up,
        color=_numbers(src, where, "color", t["color"], 3, lo=0.0, hi=1.0) if "color" in t else None)


def load_scene_file(path: str | os.PathLike) -> list[SceneObject]:
    """The checked objects of a scene file (see the module docstring).

    Raises:
        SceneFileError: unreadable file, TOML syntax error, unknown or bad key, missing mesh
            file, duplicate name; one line naming the file and the key.
    """
    try:
        import tomllib
    except ModuleNotFoundError:  # Python 3.10
        import tomli as tomllib

    src = check_input_file(path, error=SceneFileError, what="scene file")
    try:
        data = tomllib.loads(src.read_text(encoding="utf-8"))
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as e:
        raise SceneFileError(f"{src}: not valid TOML ({e})") from None
    unknown = sorted(set(data) - {"objects"})
    if unknown:
        raise SceneFileError(f"{src}: unknown key {unknown[0]!r} (a scene file holds [[objects]] tables only)")
    raw = data.get("objects")
    if not isinstance(raw, list) or not raw:
        raise SceneFileError(f"{src}: objects: expected one or more [[objects]] tables")
    objects, seen = [], {}
    for i, t in enumerate(raw):
        # Unnamed boxes are box0, box1, ... in file order.
        boxes = sum(1 for u in raw[:i] if isinstance(u, dict) and "box" in u and "mesh" not in u and "name" not in u)
        o = _parse_object(src, i, t, boxes)
        if o.name in seen:
            raise SceneFileError(f"{src}: objects[{i}].name: {o.name!r} is already the name of objects[{seen[o.name]}]; "
                                 "give one of them a name = \"...\"")
        seen[o.name] = i
        objects.append(o)
    return objects


def _box_surface(size) -> tuple[np.ndarray, np.ndarray]:
    """A closed box centred at the origin: ``(V (8, 3), F (12, 3))``, outward-wound."""
    corners = np.array([[x, y, z] for x in (-0.5, 0.5) for y in (-0.5, 0.5) for z in (-0.5, 0.5)]) * np.asarray(size)
    # Corner index = 4 x + 2 y + z (x, y, z in {0, 1}); two triangles per face, counter-clockwise from outside.
    faces = np.array([[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1],
                      [2, 3, 7], [2, 7, 6], [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3]], dtype=np.int32)
    return corners, faces


def place_object(o: SceneObject, *, up_axis: str = "y"):
    """``(surface, rotation (3, 3), scale, translation (3,))``: the object's welded
    :class:`holowarp.surface_io.SurfaceMesh` placed in the scene (before the scene's
    normalisation) and the map ``p_scene = scale * (rotation @ p_file) + translation``."""
    from holowarp.sim.model import euler_xyz_to_matrix
    from holowarp.surface_io import SurfaceMesh, load_surface_mesh

    if o.mesh is not None:
        surf = load_surface_mesh(o.mesh).welded()
        R_up = up_axis_rotation(o.up_axis or up_axis)
    else:
        surf = SurfaceMesh(*_box_surface(o.box))
        R_up = np.eye(3)
    upright = surf.positions @ R_up.T
    side = float(np.ptp(upright, axis=0).max())
    if not side > 0:
        raise SceneFileError(f"{o.mesh}: the mesh has no extent (all vertices coincide)")
    target = (1.0 if o.mesh is not None else side) if o.scale is None else o.scale
    s = target / side
    R_rot = euler_xyz_to_matrix(o.rotation)
    p = (upright @ R_rot.T) * s
    t = np.asarray(o.position) - 0.5 * (p.min(axis=0) + p.max(axis=0))
    surf.positions = p + t
    R = R_rot @ R_up
    return surf, R, s, t


def _flat(color, n: int) -> np.ndarray:
    return np.tile(np.asarray(color, np.float32), (n, 1))


def _texture_patch(surf):
    """``(patch, corner UVs (F, 3, 2), pad (x, y) in texels)``: the texture with a border of its
    own wrapped pixels wide enough for every face's UVs (each face shifted by whole periods
    to sit near [0, 1], which repeat wrapping does not see), at least ``ATLAS_PAD``."""
    tex = np.asarray(surf.texture, np.float32)
    h, w = tex.shape[:2]
    uv = np.asarray(surf.uvs, np.float64)[surf.face_uvs]  # [F, 3, 2]
    uv = uv - np.floor(uv.mean(axis=1, keepdims=True))
    past = np.maximum(np.maximum(-uv.min(axis=(0, 1)), uv.max(axis=(0, 1)) - 1.0), 0.0)  # [2] in periods
    px, py = (int(math.ceil(e * n)) + ATLAS_PAD for e, n in zip(past, (w, h)))
    patch = np.pad(tex, ((py, py), (px, px), (0, 0)), mode="wrap")
    return patch, uv, (px, py)


def _vertex_color_blocks(surf, colors):
    """One 2 x 2 texel block per face (see the module docstring): (patch, corner texel
    positions (F, 3, 2) as (column, row) of texel centres)."""
    f = np.asarray(surf.faces)
    cols = int(math.ceil(math.sqrt(len(f))))
    rows = int(math.ceil(len(f) / cols))
    patch = np.zeros((2 * rows, 2 * cols, 3), np.float32)
    k = np.arange(len(f))
    bx, by = 2 * (k % cols), 2 * (k // cols)
    c0, c1, c2 = colors[f[:, 0]], colors[f[:, 1]], colors[f[:, 2]]
    patch[by, bx], patch[by, bx + 1], patch[by + 1, bx], patch[by + 1, bx + 1] = c0, c1, c2, c1 + c2 - c0
    texel = np.stack([np.stack([bx, by], 1), np.stack([bx + 1, by], 1), np.stack([bx, by + 1], 1)], 1) + 0.5
    return patch, texel.astype(np.float64)


def _atlas(surfaces, colors):
    """One texture holding every object's colours: ``(texture (H, W, 3), uvs (3 F_total, 2))``
    with corner ``3 f + k`` of the merged face ``f``."""
    patches, places = [], []  # places: per object, a function of (row0, H, W) -> corner UVs
    for surf, color in zip(surfaces, colors):
        if surf.textured:
            patch, uv, (px, py) = _texture_patch(surf)
            h, w = np.asarray(surf.texture).shape[:2]
            col = px + uv[..., 0] * w
            row = py + (1.0 - uv[..., 1]) * h
        elif surf.vertex_colors is not None:
            patch, texel = _vertex_color_blocks(surf, np.asarray(surf.vertex_colors, np.float32))
            col, row = texel[..., 0], texel[..., 1]
        else:
            patch = np.tile(np.asarray(color, np.float32), (4, 4, 1))
            col = row = np.full((len(surf.faces), 3), 2.0)
        patches.append(patch)
        places.append((col, row))
    W = max(p.shape[1] for p in patches)
    H = sum(p.shape[0] for p in patches)
    tex = np.zeros((H, W, 3), np.float32)
    uvs, row0 = [], 0
    for patch, (col, row) in zip(patches, places):
        tex[row0:row0 + patch.shape[0], :patch.shape[1]] = patch
        uvs.append(np.stack([col / W, 1.0 - (row0 + row) / H], axis=-1).reshape(-1, 2))
        row0 += patch.shape[0]
    return tex, np.concatenate(uvs)


def merge_objects(surfaces, colors, albedo=(0.72, 0.72, 0.72)):
    """One :class:`holowarp.surface_io.SurfaceMesh` of all ``surfaces`` (placed, welded each),
    coloured as the module docstring says; ``colors`` is each object's flat colour (its
    ``color`` or the albedo), used where it has neither texture nor vertex colours. Without
    textures, vertex colours or a colour other than ``albedo`` the merged mesh has no colour
    of its own (the renderer's albedo shades it, as synth shades one untextured object)."""
    from holowarp.surface_io import SurfaceMesh

    offsets = np.cumsum([0] + [len(s.positions) for s in surfaces])
    V = np.concatenate([s.positions for s in surfaces])
    F = np.concatenate([np.asarray(s.faces) + o for s, o in zip(surfaces, offsets)]).astype(np.int32)
    merged = SurfaceMesh(positions=V, faces=F)
    if any(s.textured for s in surfaces):
        merged.texture, merged.uvs = _atlas(surfaces, colors)
        merged.face_uvs = np.arange(3 * len(F), dtype=np.int32).reshape(-1, 3)
    elif any(s.vertex_colors is not None for s in surfaces) or any(tuple(c) != tuple(albedo) for c in colors):
        merged.vertex_colors = np.concatenate([
            np.asarray(s.vertex_colors, np.float32) if s.vertex_colors is not None else _flat(c, len(s.positions))
            for s, c in zip(surfaces, colors)])
    return merged


def _object_meta(o: SceneObject, surf, R, s, t, scene_s, scene_t) -> dict:
    shading = ("texture" if surf.textured else "vertex_colors" if surf.vertex_colors is not None
               else "color" if o.color is not None else "albedo")
    return {"name": o.name, "source": str(o.mesh) if o.mesh is not None else "box",
            "box": list(o.box) if o.box is not None else None, "up_axis": o.up_axis,
            "position": list(o.position), "scale": o.scale, "rotation": list(o.rotation), "shading": shading,
            "gt_mesh": f"objects/{o.name}/gt.obj", "num_gt_faces": int(len(surf.faces)),
            "transform": {"doc": "p_world = scale * (rotation @ p_obj) + translation", "rotation": R.tolist(),
                          "scale": float(s * scene_s), "translation": (np.asarray(t) * scene_s + scene_t).tolist()}}


def _overlap_warnings(objects, surfaces) -> None:
    import warnings

    lo = [s.positions.min(axis=0) for s in surfaces]
    hi = [s.positions.max(axis=0) for s in surfaces]
    for i in range(len(surfaces)):
        for j in range(i + 1, len(surfaces)):
            if (np.minimum(hi[i], hi[j]) - np.maximum(lo[i], lo[j]) > 0).all():
                warnings.warn(f"scene objects {objects[i].name!r} and {objects[j].name!r}: their bounding boxes overlap; "
                              "the objects must not intersect for the combined gt.obj to be a closed surface",
                              stacklevel=3)


def _check_resume_digest(out: Path, digest: str, resume: bool) -> None:
    import json

    prev = out / "transforms_train.json"
    if not (resume and prev.is_file()):
        return
    try:
        old = (json.loads(prev.read_text()).get("holowarp", {}).get("scene") or {}).get("digest")
    except (OSError, ValueError):
        old = None
    if old != digest:
        raise SynthError(f"{out}: --resume with a scene that differs from the one rendered there (other objects, "
                         "placements or meshes); use --overwrite to replace it")


def _scene_digest(surfaces, merged) -> str:
    h = hashlib.sha256()
    for s in surfaces:
        h.update(np.ascontiguousarray(s.positions, np.float64).tobytes())
        h.update(np.ascontiguousarray(s.faces, np.int64).tobytes())
    if merged.texture is not None:
        h.update(np.ascontiguousarray(merged.texture).tobytes())
    if merged.vertex_colors is not None:
        h.update(np.ascontiguousarray(merged.vertex_colors).tobytes())
    return h.hexdigest()


def synthesize_scene(scene_path, out_dir, *, views: int = NUM_VIEWS, res: int = 512, device: str = "cpu",
                     up_axis: str = "y", test_every: int = TEST_EVERY, fov_deg: float = FOV_DEG, supersample: int = 2,
                     margin: float = DISTANCE_MARGIN, albedo=(0.72, 0.72, 0.72), resume: bool = False,
                     overwrite: bool = False, progress: bool = True) -> dict:
    """Render a scene file's objects together into the dataset folder ``out_dir``.

    The arguments are those of :func:`holowarp.synthesis.synthesize` (``up_axis`` is the
    default of objects without their own); the layout is synth's plus
    ``objects/NAME/gt.obj`` per object, and the ``"holowarp"`` block of the transforms files
    carries ``scene`` (its ``digest`` and every object's name, source, placement and
    object-to-world transform). Returns synth's summary with ``objects`` (the names).

    Raises:
        SceneFileError: a bad scene file (before any work). SynthError / SurfaceError as synth.
    """
    import time

    from holowarp.render_gt import GTRenderer
    from holowarp.surface_io import write_surface

    t0 = time.perf_counter()
    objects = load_scene_file(scene_path)
    up_axis_rotation(up_axis)  # checks the default up axis
    out = check_output_dir(out_dir)
    check_synth_args(out, views=views, res=res, test_every=test_every, supersample=supersample, fov_deg=fov_deg,
                     resume=resume, overwrite=overwrite, up_axis=up_axis)
    placed = [place_object(o, up_axis=up_axis) for o in objects]
    surfaces = [p[0] for p in placed]
    _overlap_warnings(objects, surfaces)
    scene_s, scene_t = normalisation(np.concatenate([s.positions for s in surfaces]))
    for s in surfaces:
        s.positions = s.positions * scene_s + scene_t
    merged = merge_objects(surfaces, [o.color if o.color is not None else albedo for o in objects], albedo)
    digest = _scene_digest(surfaces, merged)
    _check_resume_digest(out, digest, resume)
    source = {"source": str(Path(scene_path).resolve()), "up_axis": str(up_axis).lower(),
              "transform": {"doc": "p_world = scale * (rotation @ p_scene) + translation, p_scene: the objects "
                                   "placed as the scene file says", "rotation": np.eye(3).tolist(),
                            "scale": scene_s, "translation": np.asarray(scene_t).tolist()},
              "scene": {"digest": digest, "objects": [_object_meta(o, s, *p[1:], scene_s, scene_t)
                                                      for o, s, p in zip(objects, surfaces, placed)]}}
    # Built from the merged arrays directly: GTRenderer.from_obj would weld across touching objects.
    renderer = GTRenderer(merged.positions, merged.faces, uvs=merged.uvs, face_uvs=merged.face_uvs,
                          texture=merged.texture, vertex_colors=merged.vertex_colors, albedo=albedo,
                          supersample=supersample, device=device)
    for o, s in zip(objects, surfaces):
        write_surface(out / "objects" / o.name / "gt.obj", (s.positions, s.faces),
                      header=f"holowarp ground truth of scene object {o.name} ({Path(scene_path).name}): welded, Z up, "
                             "in the scene's frame (scene bbox centred at origin, largest side 1)")
    summary = write_dataset(renderer, merged, out, source, views=views, res=res, test_every=test_every,
                            fov_deg=fov_deg, supersample=supersample, margin=margin, resume=resume, progress=progress,
                            desc=f"synth {Path(scene_path).stem}", t0=t0,
                            gt_header=f"holowarp ground truth of scene {Path(scene_path).name}: {len(objects)} objects, "
                                      "each welded, Z up, scene bbox centred at origin, largest side 1")
    return dict(summary, objects=[o.name for o in objects])
