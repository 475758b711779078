"""Triangle surfaces in and out: every format a user brings, one welded result.

Reading (:func:`load_surface_mesh`, :func:`read_surface`):

- ``.obj`` with holowarp's own reader, which keeps what the ground-truth renderer needs:
  per-corner UVs, the ``map_Kd`` texture of the first material that names one, and vertex
  colours from the common ``v x y z r g b`` extension; polygons are fan-triangulated;
- every other surface format trimesh reads (``.off``, ``.stl``, ``.ply``, ``.glb``/``.gltf``
  and more, :data:`SURFACE_READ_FORMATS`), with vertex colours or a texture when the file
  has them. Thingi10k, the paper's dataset, is STL.

Textured files index positions and UVs separately, and many exporters duplicate positions
along UV seams, so a textured model is not a closed surface until its coincident positions
are merged. :func:`weld` does that; geometry code (metrics, hulls, ray casting) always works
on welded positions (:meth:`SurfaceMesh.welded`, :func:`read_surface`), while the per-corner
UV indices keep the texture mapping intact.

Writing (:func:`write_surface`): ``.obj`` or binary ``.ply``, atomically.

Every problem raises :class:`SurfaceError` naming the file (and the line for OBJ).
"""

from __future__ import annotations

import os
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from holowarp.errors import InputError
from holowarp.fileio import atomic_path, check_input_file, quiet_stdio

__all__ = [
    "SURFACE_READ_FORMATS",
    "SURFACE_WRITE_FORMATS",
    "SurfaceError",
    "SurfaceMesh",
    "load_obj",
    "load_surface_mesh",
    "read_surface",
    "weld",
    "write_surface",
]

#: Extensions :func:`load_surface_mesh` reads (OBJ natively, the rest through trimesh).
SURFACE_READ_FORMATS = (".obj", ".off", ".stl", ".ply", ".glb", ".gltf")
#: Extensions :func:`write_surface` writes.
SURFACE_WRITE_FORMATS = (".obj", ".ply")


class SurfaceError(InputError):
    """A surface file (or its material/texture) cannot be read or written; the message
    names the file."""


@dataclass
class SurfaceMesh:
    """A triangle mesh read from a surface file.

    Attributes:
        positions: (V, 3) float64 vertex positions.
        faces: (F, 3) int32 position indices, counter-clockwise = outward.
        uvs: optional (T, 2) float64 texture coordinates (v up, OBJ convention).
        face_uvs: optional (F, 3) int32 indices into ``uvs`` per face corner.
        texture: optional (H, W, 3) float32 RGB in [0, 1]; row 0 is the TOP of the image, so
            texture row = (1 - v) * H.
        vertex_colors: optional (V, 3) float32 RGB in [0, 1].
        path: the file it was read from.
    """

    positions: np.ndarray
    faces: np.ndarray
    uvs: np.ndarray | None = None
    face_uvs: np.ndarray | None = None
    texture: np.ndarray | None = None
    vertex_colors: np.ndarray | None = None
    path: Path | None = None

    @property
    def textured(self) -> bool:
        return self.texture is not None and self.uvs is not None and self.face_uvs is not None

    def welded(self, *, tol: float = 1e-7) -> "SurfaceMesh":
        """A copy whose coincident positions are merged (UV corners are untouched).

        ``tol`` is relative to the bounding-box diagonal.
        """
        pos, faces, old_to_new = weld(self.positions, self.faces, tol=tol)
        colors = None
        if self.vertex_colors is not None:
            # Average the colours of merged vertices.
            acc = np.zeros((len(pos), 3))
            cnt = np.zeros(len(pos))
            np.add.at(acc, old_to_new, self.vertex_colors)
            np.add.at(cnt, old_to_new, 1.0)
            colors = (acc / np.maximum(cnt, 1)[:, None]).astype(np.float32)
        return replace(self, positions=pos, faces=faces, vertex_colors=colors)


def weld(positions: np.ndarray, faces: np.ndarray, *, tol: float = 1e-7):
    """Merge vertices closer than ``tol * bbox_diagonal`` and drop faces that collapse.

    Args:
        positions: (V, 3) float positions.
        faces: (F, 3) int vertex indices.
        tol: merge distance relative to the bounding-box diagonal.

    Returns:
        ``(positions (V', 3) float64, faces (F', 3) int32, old_to_new (V,) int64)``; faces
        whose corners merge into fewer than three distinct vertices are removed, and vertices
        no face uses are kept (so ``old_to_new`` is total).
    """
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components
    from scipy.spatial import cKDTree

    positions = np.asarray(positions, dtype=np.float64)
    faces = np.asarray(faces, dtype=np.int64)
    n = len(positions)
    if n == 0:
        return positions.reshape(0, 3), faces.reshape(0, 3).astype(np.int32), np.zeros(0, np.int64)
    diag = float(np.linalg.norm(positions.max(0) - positions.min(0)))
    r = max(tol * diag, 0.0)
    pairs = cKDTree(positions).query_pairs(r, output_type="ndarray") if r > 0 else np.zeros((0, 2), int)
    if r == 0:
        # Exact duplicates only.
        _, first, inv = np.unique(positions, axis=0, return_index=True, return_inverse=True)
        pairs = np.stack([np.arange(n), first[inv.ravel()]], 1)
    g = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(n, n))
    _, labels = connected_components(g, directed=False)
    # Number clusters in order of first appearance, representative = mean position.
    _, first_idx, inv = np.unique(labels, return_index=True, return_inverse=True)
    order = np.argsort(first_idx)
    rank = np.empty_like(order)
    rank[order] = np.arange(len(order))
    old_to_new = rank[inv.ravel()].astype(np.int64)
    m = len(order)
    acc = np.zeros((m, 3))
    cnt = np.zeros(m)
    np.add.at(acc, old_to_new, positions)
    np.add.at(cnt, old_to_new, 1.0)
    new_pos = acc / cnt[:, None]
    f = old_to_new[faces]
    keep = (f[:, 0] != f[:, 1]) & (f[:, 1] != f[:, 2]) & (f[:, 0] != f[:, 2])
    return new_pos, f[keep].astype(np.int32), old_to_new


# ----------------------------------------------------------------------------- OBJ


def _parse_index(tok: str, count: int, path, lineno: int) -> int:
    try:
        i = int(tok)
    except ValueError:
        raise SurfaceError(f"{path}:{lineno}: bad index {tok!r}") from None
    if i == 0:
        raise SurfaceError(f"{path}:{lineno}: OBJ indices start at 1, got 0")
    return i - 1 if i > 0 else count + i


def _read_mtl_texture(mtl_path: Path) -> Path | None:
    if not mtl_path.is_file():
        return None
    for line in mtl_path.read_text(errors="replace").splitlines():
        parts = line.strip().split()
        if len(parts) >= 2 and parts[0] == "map_Kd":
            # Options such as "-s 1 1 1" may precede the file name, which comes last.
            return (mtl_path.parent / parts[-1]).resolve()
    return None


def _floats(parts, path, lineno, what: str) -> list[float]:
    try:
        vals = [float(x) for x in parts]
    except ValueError:
        raise SurfaceError(f"{path}:{lineno}: bad {what} {' '.join(parts)!r}") from None
    if not all(np.isfinite(vals)):
        raise SurfaceError(f"{path}:{lineno}: non-finite {what} {' '.join(parts)!r}")
    return vals


class _ObjLines:
    """What the lines of an OBJ file hold, as Python lists (see :func:`load_obj`)."""

    def __init__(self):
        self.pos, self.cols, self.uvs = [], [], []
        self.fv, self.fuv = [], []
        self.any_uv_missing = False
        self.mtllibs = []

    def add(self, line: str, path, lineno: int) -> None:
        parts = line.split()
        if not parts or parts[0].startswith("#"):
            return
        tag = parts[0]
        if tag == "v":
            vals = _floats(parts[1:], path, lineno, "vertex")
            if len(vals) < 3:
                raise SurfaceError(f"{path}:{lineno}: vertex needs 3 coordinates")
            self.pos.append(vals[:3])
            self.cols.append(vals[3:6] if len(vals) >= 6 else None)
        elif tag == "vt":
            vals = _floats(parts[1:3], path, lineno, "texture coordinate")
            self.uvs.append(vals + [0.0] * (2 - len(vals)))
        elif tag == "f":
            self._face(parts[1:], path, lineno)
        elif tag == "mtllib" and len(parts) > 1:
            self.mtllibs.append(line.split(None, 1)[1].strip())

    def _face(self, corners, path, lineno: int) -> None:
        if len(corners) < 3:
            raise SurfaceError(f"{path}:{lineno}: face with fewer than 3 corners")
        vi, ti = [], []
        for c in corners:
            sub = c.split("/")
            vi.append(_parse_index(sub[0], len(self.pos), path, lineno))
            if len(sub) > 1 and sub[1]:
                ti.append(_parse_index(sub[1], len(self.uvs), path, lineno))
            else:
                ti.append(-1)
                self.any_uv_missing = True
        for k in range(1, len(vi) - 1):  # fan triangulation
            self.fv.append((vi[0], vi[k], vi[k + 1]))
            self.fuv.append((ti[0], ti[k], ti[k + 1]))


def load_obj(path: str | os.PathLike, *, load_texture: bool = True) -> SurfaceMesh:
    """Read an OBJ file (triangles or polygons; ``v``, ``vt``, ``f``, ``mtllib`` lines).

    Args:
        path: the ``.obj`` file.
        load_texture: read the ``map_Kd`` image of the material library if there is one.

    Raises:
        SurfaceError: the file is missing, has no faces, non-finite coordinates, or
            references vertices that do not exist; the message names the file and line.
    """
    path = check_input_file(path, error=SurfaceError, what="OBJ file")
    obj = _ObjLines()
    with open(path, "r", errors="replace") as fh:
        for lineno, line in enumerate(fh, 1):
            obj.add(line, path, lineno)
    if not obj.fv:
        raise SurfaceError(f"{path}: no faces (is this a point cloud?)")
    positions = np.asarray(obj.pos, dtype=np.float64).reshape(-1, 3)
    faces = np.asarray(obj.fv, dtype=np.int64)
    if faces.min() < 0 or faces.max() >= len(positions):
        raise SurfaceError(f"{path}: a face references vertex {int(faces.max()) + 1} but the file has {len(positions)}")
    vertex_colors = None
    if obj.cols and all(c is not None for c in obj.cols):
        vc = np.asarray(obj.cols, dtype=np.float32)
        if vc.max() > 1.0:  # some exporters write 0..255
            vc = vc / 255.0
        vertex_colors = np.clip(vc, 0.0, 1.0)
    uv_arr = face_uvs = None
    if obj.uvs and not obj.any_uv_missing:
        uv_arr = np.asarray(obj.uvs, dtype=np.float64)
        face_uvs = np.asarray(obj.fuv, dtype=np.int64)
        if face_uvs.min() < 0 or face_uvs.max() >= len(uv_arr):
            raise SurfaceError(f"{path}: a face references a texture coordinate that does not exist")
        face_uvs = face_uvs.astype(np.int32)
    texture = _obj_texture(path, obj.mtllibs) if (load_texture and uv_arr is not None) else None
    return SurfaceMesh(positions=positions, faces=faces.astype(np.int32), uvs=uv_arr, face_uvs=face_uvs,
                       texture=texture, vertex_colors=vertex_colors, path=path)


def _obj_texture(path: Path, mtllibs) -> np.ndarray | None:
    for lib in mtllibs:
        tex_path = _read_mtl_texture(path.parent / lib)
        if tex_path is None:
            continue
        if not tex_path.is_file():
            raise SurfaceError(f"{path}: material {lib} names texture {tex_path}, which does not exist")
        return _read_texture(tex_path)
    return None


def _read_texture(path: Path) -> np.ndarray:
    from PIL import Image

    try:
        with Image.open(path) as im:
            im = im.convert("RGB")
            return np.asarray(im, dtype=np.float32) / 255.0
    except OSError as e:
        raise SurfaceError(f"{path}: cannot read texture image ({e})") from None


# ----------------------------------------------------------------------------- other formats


def _load_with_trimesh(path: Path, *, load_texture: bool) -> SurfaceMesh:
    import trimesh

    try:
        with quiet_stdio():
            tm = trimesh.load(path, force="mesh", process=False)
    except Exception as e:  # trimesh raises many types for malformed files
        raise SurfaceError(f"{path}: cannot read as a surface ({type(e).__name__}: {e})") from None
    faces = getattr(tm, "faces", None)
    if faces is None or len(faces) == 0:
        raise SurfaceError(f"{path}: no faces (is this a point cloud?)")
    V = np.asarray(tm.vertices, dtype=np.float64)
    F = np.asarray(faces, dtype=np.int64)
    colors = uvs = face_uvs = texture = None
    visual = getattr(tm, "visual", None)
    kind = getattr(visual, "kind", None)
    if kind == "vertex":
        colors = np.asarray(visual.vertex_colors, dtype=np.float32)[:, :3] / 255.0
    elif kind == "texture" and load_texture and getattr(visual, "uv", None) is not None:
        image = getattr(getattr(visual, "material", None), "baseColorTexture", None)
        image = image if image is not None else getattr(getattr(visual, "material", None), "image", None)
        if image is not None and len(visual.uv) == len(V):
            texture = np.asarray(image.convert("RGB"), dtype=np.float32) / 255.0
            uvs, face_uvs = np.asarray(visual.uv, dtype=np.float64), F.astype(np.int32)
    return SurfaceMesh(positions=V, faces=F.astype(np.int32), uvs=uvs, face_uvs=face_uvs, texture=texture,
                       vertex_colors=colors, path=path)


def load_surface_mesh(path: str | os.PathLike, *, load_texture: bool = True) -> SurfaceMesh:
    """Read any surface format of :data:`SURFACE_READ_FORMATS` (not welded; see the module
    docstring).

    Raises:
        SurfaceError: missing, empty or unreadable file, unknown extension, no faces,
            non-finite coordinates, out-of-range indices.
    """
    path = check_input_file(path, error=SurfaceError, what="surface file")
    ext = path.suffix.lower()
    if ext not in SURFACE_READ_FORMATS:
        raise SurfaceError(f"{path}: unknown surface extension {ext!r}; readable: {', '.join(SURFACE_READ_FORMATS)}")
    mesh = load_obj(path, load_texture=load_texture) if ext == ".obj" else _load_with_trimesh(path, load_texture=load_texture)
    finite = np.isfinite(mesh.positions).all(axis=1)
    if not finite.all():
        i = int(np.flatnonzero(~finite)[0])
        raise SurfaceError(f"{path}: vertex {i + 1} has non-finite coordinates {mesh.positions[i].tolist()}")
    return mesh


def read_surface(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray]:
    """The welded geometry of a surface file: ``(V (N, 3) float64, F (F, 3) int32)``."""
    m = load_surface_mesh(path, load_texture=False).welded()
    return m.positions, m.faces


def write_surface(path: str | os.PathLike, surface, *, header: str | None = None, colors=None) -> Path:
    """Write a triangle surface as ``.obj`` or binary ``.ply``, atomically.

    Args:
        surface: an object with ``surface_mesh()`` (a :class:`holowarp.TetMesh`: its outward
            boundary, vertices compacted) or a ``(vertices (V, 3), faces (F, 3))`` pair.
        header: comment written at the top of the file (each line prefixed); default: what
            the surface is.
        colors: optional (V, 3) RGB per vertex, floats in [0, 1] or uint8 (``.ply`` only:
            ``red green blue`` uchar properties, which every mesh viewer shows).
    """
    path = Path(path)
    ext = path.suffix.lower()
    if ext not in SURFACE_WRITE_FORMATS:
        raise SurfaceError(f"{path}: surface output must be one of {', '.join(SURFACE_WRITE_FORMATS)}, got {ext!r}")
    boundary = hasattr(surface, "surface_mesh")
    if header is None:
        header = f"holowarp {'boundary ' if boundary else ''}surface (outward-wound triangles)"
    V, F = surface.surface_mesh() if boundary else surface
    V = np.asarray(V, dtype=np.float64)
    F = np.asarray(F, dtype=np.int64)
    comments = [line for line in header.splitlines() if line.strip()]
    rgb = None
    if colors is not None:
        if ext != ".ply":
            raise SurfaceError(f"{path}: vertex colours need a .ply output")
        rgb = np.asarray(colors)
        rgb = rgb if rgb.dtype == np.uint8 else np.clip(np.rint(rgb * 255.0), 0, 255).astype(np.uint8)
        if rgb.shape != (len(V), 3):
            raise SurfaceError(f"{path}: colors must be ({len(V)}, 3), got {rgb.shape}")
    with atomic_path(path) as tmp:
        if ext == ".obj":
            with open(tmp, "w", encoding="utf-8") as f:
                for line in comments:
                    f.write(f"# {line}\n")
                np.savetxt(f, V, fmt="v %.9g %.9g %.9g")
                np.savetxt(f, F + 1, fmt="f %d %d %d")
        else:
            head = "".join(f"comment {line}\n" for line in comments)
            props = "property uchar red\nproperty uchar green\nproperty uchar blue\n" if rgb is not None else ""
            text = (
                f"ply\nformat binary_little_endian 1.0\n{head}"
                f"element vertex {len(V)}\nproperty float x\nproperty float y\nproperty float z\n{props}"
                f"element face {len(F)}\nproperty list uchar int vertex_indices\nend_header\n"
            )
            vt = [("p", "<f4", (3,))] + ([("c", "u1", (3,))] if rgb is not None else [])
            vr = np.empty(len(V), dtype=vt)
            vr["p"] = V
            if rgb is not None:
                vr["c"] = rgb
            fr = np.empty(len(F), dtype=[("n", "u1"), ("i", "<i4", (3,))])
            fr["n"] = 3
            fr["i"] = F
            with open(tmp, "wb") as f:
                f.write(text.encode("utf-8"))
                f.write(vr.tobytes())
                f.write(fr.tobytes())
    return path
