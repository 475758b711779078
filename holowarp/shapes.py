"""Procedural test objects whose concave regions no silhouette sees (the quality suite).

Each object is a signed distance function (negative inside) turned into a closed, manifold
triangle surface by marching cubes (VTK flying edges through pyvista): exact topology by
construction, any resolution, no mesh-boolean library. Sizes are in arbitrary units (the
synthesiser normalises every object to the unit cube).

- ``bowl``: a hemispherical shell, open at the top; its inside is seen by no silhouette.
- ``mug``: a cylindrical cup with a cavity and a torus handle (genus 1).
- ``dented_box``: a box with a deep spherical dent in its top face.
- ``star``: a five-pointed star extruded, with a shallow spherical dish on top.
- ``plate``: a plate with three holes whose bars are about 0.05 of its size thick (genus 3).

:data:`SHAPES` maps each name to ``(sdf, bounds, genus)``; :func:`shape_surface` meshes one
and :func:`write_shape` writes it (OBJ).
"""

from __future__ import annotations

import math

import numpy as np

__all__ = ["SHAPES", "shape_surface", "write_shape", "surface_genus"]


def _box(p, half):
    q = np.abs(p) - np.asarray(half)
    return np.linalg.norm(np.maximum(q, 0.0), axis=-1) + np.minimum(q.max(axis=-1), 0.0)


def _bowl(p):
    r = np.linalg.norm(p, axis=-1)
    shell = np.maximum(r - 0.5, 0.43 - r)
    return np.maximum(shell, p[..., 2] - 0.08)  # cut the top off: open bowl


def _capped_cylinder(p, radius, z0, z1):
    d_r = np.hypot(p[..., 0], p[..., 1]) - radius
    d_z = np.maximum(z0 - p[..., 2], p[..., 2] - z1)
    return np.minimum(np.maximum(d_r, d_z), 0.0) + np.hypot(np.maximum(d_r, 0.0), np.maximum(d_z, 0.0))


def _mug(p):
    cup = np.maximum(_capped_cylinder(p, 0.32, -0.4, 0.4), -_capped_cylinder(p, 0.26, -0.32, 0.6))
    # Handle: a torus in the x-z plane beside the cup, its inner part hidden inside the wall.
    q = p - np.array([0.36, 0.0, 0.0])
    ring = np.hypot(np.hypot(q[..., 0], q[..., 2]) - 0.2, q[..., 1]) - 0.055
    ring = np.maximum(ring, 0.29 - np.hypot(p[..., 0], p[..., 1]))  # ends buried in the wall, not in the cavity
    return np.minimum(cup, ring)


def _dented_box(p):
    box = _box(p, (0.45, 0.4, 0.3))
    dent = np.linalg.norm(p - np.array([0.0, 0.0, 0.42]), axis=-1) - 0.36
    return np.maximum(box, -dent)


def _star(p):
    ang = np.arctan2(p[..., 1], p[..., 0])
    rad = np.hypot(p[..., 0], p[..., 1])
    # Radius of a five-pointed star outline as a function of the angle (sharp arms).
    k = 5
    sector = np.mod(ang, 2 * math.pi / k) - math.pi / k
    outline = 0.22 + 0.28 * (1.0 - np.abs(sector) / (math.pi / k)) ** 1.6
    d2 = (rad - outline) * 0.8  # not exact, but its zero set is the star and it is Lipschitz
    d_z = np.abs(p[..., 2]) - 0.15
    prism = np.minimum(np.maximum(d2, d_z), 0.0) + np.hypot(np.maximum(d2, 0.0), np.maximum(d_z, 0.0))
    dish = np.linalg.norm(p - np.array([0.0, 0.0, 0.35]), axis=-1) - 0.26
    return np.maximum(prism, -dish)


def _plate(p):
    plate = _box(p, (0.5, 0.3, 0.04))
    holes = None
    for cx in (-0.32, 0.0, 0.32):
        h = _box(p - np.array([cx, 0.0, 0.0]), (0.135, 0.25, 0.2))
        holes = h if holes is None else np.minimum(holes, h)
    return np.maximum(plate, -holes)


#: name -> (sdf(points (..., 3)) -> (...,), (lo (3,), hi (3,)) bounds, genus).
SHAPES = {
    "bowl": (_bowl, ((-0.55, -0.55, -0.55), (0.55, 0.55, 0.15)), 0),
    "mug": (_mug, ((-0.4, -0.4, -0.45), (0.66, 0.4, 0.45)), 1),
    "dented_box": (_dented_box, ((-0.5, -0.45, -0.35), (0.5, 0.45, 0.35)), 0),
    "star": (_star, ((-0.55, -0.55, -0.2), (0.55, 0.55, 0.2)), 0),
    "plate": (_plate, ((-0.55, -0.35, -0.08), (0.55, 0.35, 0.08)), 3),
}


def _triangles_only(poly):
    """A PolyData holding only the triangles of ``poly`` (VTK filters leave stray lines/points)."""
    import pyvista as pv

    cells = np.asarray(poly.faces)
    if len(cells) % 4 == 0 and (cells[::4] == 3).all():
        tri = cells.reshape(-1, 4)[:, 1:]
    else:
        out, i = [], 0
        while i < len(cells):  # faces is a flat [n, i0, ..., i_{n-1}, n, ...] array
            n = int(cells[i])
            if n == 3:
                out.append(cells[i + 1 : i + 4])
            i += n + 1
        tri = np.asarray(out, dtype=np.int64).reshape(-1, 3)
    return pv.PolyData(np.asarray(poly.points), np.hstack([np.full((len(tri), 1), 3), tri]).ravel())


def surface_genus(vertices: np.ndarray, faces: np.ndarray) -> int:
    """Genus of a closed, connected triangle surface from its Euler characteristic."""
    e = np.sort(np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]), axis=1)
    n_edges = len(np.unique(e, axis=0))
    chi = len(np.unique(faces)) - n_edges + len(faces)
    return (2 - chi) // 2


def shape_surface(name: str, *, resolution: int = 160, max_faces: int | None = 60_000):
    """``(vertices (V, 3) float64, faces (F, 3) int32)`` of a closed, outward-wound surface of
    the shape ``name`` (see :data:`SHAPES`), marched on ``resolution`` nodes along its longest
    side, decimated to about ``max_faces`` triangles (None: not decimated)."""
    import pyvista as pv

    if name not in SHAPES:
        raise KeyError(f"unknown shape {name!r}; choose one of {', '.join(SHAPES)}")
    sdf, (lo, hi), _ = SHAPES[name]
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    h = float((hi - lo).max()) / (resolution - 1)
    lo, hi = lo - 3 * h, hi + 3 * h
    n = np.ceil((hi - lo) / h).astype(int) + 1
    axes = [lo[i] + h * np.arange(n[i]) for i in range(3)]
    P = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1)
    img = pv.ImageData(dimensions=tuple(int(x) for x in n), spacing=(h, h, h), origin=tuple(lo))
    img.point_data["sdf"] = sdf(P).ravel(order="F")
    surf = img.contour([0.0], scalars="sdf", method="flying_edges").triangulate()
    surf = _triangles_only(surf).extract_largest().clean()
    surf = _triangles_only(surf)
    if max_faces is not None and surf.n_cells > max_faces:
        surf = _triangles_only(surf.decimate(1.0 - max_faces / surf.n_cells, volume_preservation=True).clean())
    V = np.asarray(surf.points, dtype=np.float64)
    F = surf.faces.reshape(-1, 4)[:, 1:].astype(np.int32)
    vol = np.einsum("ij,ij->i", V[F[:, 0]], np.cross(V[F[:, 1]], V[F[:, 2]])).sum() / 6.0
    if vol < 0:  # contour normals point towards increasing sdf (outwards); make sure
        F = F[:, [0, 2, 1]]
    return V, F


def write_shape(name: str, path, **kwargs):
    """Mesh the shape ``name`` and write it as an OBJ (atomically); returns the path."""
    from holowarp.surface_io import write_surface

    return write_surface(path, shape_surface(name, **kwargs), header=f"holowarp procedural shape {name!r}")
