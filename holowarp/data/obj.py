"""Wavefront OBJ reading for ground-truth objects: positions, triangles, UVs, texture, colours.

Textured OBJs index positions and UVs separately (``f v/vt/vn``); many exporters also
duplicate positions along UV seams, so a textured model is not a closed surface until its
coincident positions are merged. :func:`weld` does that; geometry code (metrics, hulls,
ray casting) always works on welded positions, while the per-corner UV indices keep the
texture mapping intact.

Polygons with more than three corners are fan-triangulated. Vertex colours are read from the
common ``v x y z r g b`` extension. The texture is the ``map_Kd`` image of the first material
that names one.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

__all__ = ["ObjError", "ObjMesh", "load_obj", "weld", "write_obj"]


class ObjError(ValueError):
    """An OBJ (or its material/texture) cannot be read; the message names the file."""


@dataclass
class ObjMesh:
    """A triangle mesh read from an OBJ file.

    Attributes:
        positions: (V, 3) float64 vertex positions.
        faces: (F, 3) int32 position indices, counter-clockwise = outward (OBJ convention).
        uvs: optional (T, 2) float64 texture coordinates (v up, OBJ convention).
        face_uvs: optional (F, 3) int32 indices into ``uvs`` per face corner.
        texture: optional (H, W, 3) float32 RGB in [0, 1] from the material's ``map_Kd``;
            row 0 is the TOP of the image, so texture row = (1 - v) * H.
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

    def welded(self, *, tol: float = 1e-7) -> "ObjMesh":
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


def _parse_index(tok: str, count: int, path, lineno: int) -> int:
    try:
        i = int(tok)
    except ValueError as e:
        raise ObjError(f"{path}:{lineno}: bad index {tok!r}") from e
    if i == 0:
        raise ObjError(f"{path}:{lineno}: OBJ indices start at 1, got 0")
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


def load_obj(path: str | os.PathLike, *, load_texture: bool = True) -> ObjMesh:
    """Read an OBJ file (triangles or polygons; ``v``, ``vt``, ``f``, ``mtllib`` lines).

    Args:
        path: the ``.obj`` file.
        load_texture: read the ``map_Kd`` image of the material library if there is one.

    Raises:
        ObjError: the file is missing, has no faces, or references vertices that do not
            exist; the message names the file and line.
    """
    path = Path(path)
    if not path.is_file():
        raise ObjError(f"{path}: no such OBJ file")
    pos, cols, uvs = [], [], []
    fv, fuv = [], []
    any_uv_missing = False
    mtllibs = []
    with open(path, "r", errors="replace") as fh:
        for lineno, line in enumerate(fh, 1):
            if not line or line[0] == "#":
                continue
            parts = line.split()
            if not parts:
                continue
            tag = parts[0]
            if tag == "v":
                try:
                    vals = [float(x) for x in parts[1:]]
                except ValueError as e:
                    raise ObjError(f"{path}:{lineno}: bad vertex {line.strip()!r}") from e
                if len(vals) < 3:
                    raise ObjError(f"{path}:{lineno}: vertex needs 3 coordinates")
                pos.append(vals[:3])
                cols.append(vals[3:6] if len(vals) >= 6 else None)
            elif tag == "vt":
                try:
                    vals = [float(x) for x in parts[1:3]]
                except ValueError as e:
                    raise ObjError(f"{path}:{lineno}: bad texture coordinate") from e
                uvs.append(vals + [0.0] * (2 - len(vals)))
            elif tag == "f":
                corners = parts[1:]
                if len(corners) < 3:
                    raise ObjError(f"{path}:{lineno}: face with fewer than 3 corners")
                vi, ti = [], []
                for c in corners:
                    sub = c.split("/")
                    vi.append(_parse_index(sub[0], len(pos), path, lineno))
                    if len(sub) > 1 and sub[1]:
                        ti.append(_parse_index(sub[1], len(uvs), path, lineno))
                    else:
                        ti.append(-1)
                        any_uv_missing = True
                for k in range(1, len(vi) - 1):  # fan triangulation
                    fv.append((vi[0], vi[k], vi[k + 1]))
                    fuv.append((ti[0], ti[k], ti[k + 1]))
            elif tag == "mtllib":
                mtllibs.append(line.split(None, 1)[1].strip())
    if not fv:
        raise ObjError(f"{path}: no faces (is this a point cloud?)")
    positions = np.asarray(pos, dtype=np.float64).reshape(-1, 3)
    faces = np.asarray(fv, dtype=np.int64)
    if faces.min() < 0 or faces.max() >= len(positions):
        raise ObjError(f"{path}: a face references vertex {int(faces.max()) + 1} but the file has {len(positions)}")
    vertex_colors = None
    if all(c is not None for c in cols) and cols:
        vc = np.asarray(cols, dtype=np.float32)
        if vc.max() > 1.0:  # some exporters write 0..255
            vc = vc / 255.0
        vertex_colors = np.clip(vc, 0.0, 1.0)
    uv_arr = face_uvs = None
    if uvs and not any_uv_missing:
        uv_arr = np.asarray(uvs, dtype=np.float64)
        face_uvs = np.asarray(fuv, dtype=np.int64)
        if face_uvs.min() < 0 or face_uvs.max() >= len(uv_arr):
            raise ObjError(f"{path}: a face references a texture coordinate that does not exist")
        face_uvs = face_uvs.astype(np.int32)
    texture = None
    if load_texture and uv_arr is not None:
        for lib in mtllibs:
            tex_path = _read_mtl_texture(path.parent / lib)
            if tex_path is None:
                continue
            if not tex_path.is_file():
                raise ObjError(f"{path}: material {lib} names texture {tex_path}, which does not exist")
            texture = _read_texture(tex_path)
            break
    return ObjMesh(
        positions=positions,
        faces=faces.astype(np.int32),
        uvs=uv_arr,
        face_uvs=face_uvs,
        texture=texture,
        vertex_colors=vertex_colors,
        path=path,
    )


def _read_texture(path: Path) -> np.ndarray:
    from PIL import Image

    try:
        with Image.open(path) as im:
            im = im.convert("RGB")
            return np.asarray(im, dtype=np.float32) / 255.0
    except OSError as e:
        raise ObjError(f"{path}: cannot read texture image ({e})") from e


def write_obj(path: str | os.PathLike, vertices: np.ndarray, faces: np.ndarray, *, header: str = "") -> Path:
    """Write a plain triangle OBJ (positions and faces only) atomically."""
    from holowarp.fileio import atomic_path

    vertices = np.asarray(vertices, dtype=np.float64)
    faces = np.asarray(faces, dtype=np.int64)
    with atomic_path(path) as tmp:
        with open(tmp, "w") as fh:
            for line in header.splitlines():
                fh.write(f"# {line}\n")
            np.savetxt(fh, vertices, fmt="v %.9g %.9g %.9g")
            np.savetxt(fh, faces + 1, fmt="f %d %d %d")
    return Path(path)
