"""Independent NumPy references the tests check holowarp's kernels against."""

from __future__ import annotations

import numpy as np


def bilinear_masks(points: np.ndarray, dataset, views):
    """Mask values (P, len(views)) at the projections of world ``points`` (P, 3), bilinear with
    pixel centres at x + 0.5, and (P, len(views)) bool: the view sees the point (in front of
    the camera, inside the image). The reference of :mod:`holowarp.ops.carve`."""
    P = np.asarray(points, dtype=np.float64)
    vals = np.zeros((len(P), len(views)))
    seen = np.zeros((len(P), len(views)), dtype=bool)
    H, W = dataset.height, dataset.width
    for j, v in enumerate(views):
        Vm, K = dataset.viewmats[v], dataset.K[v]
        pc = P @ Vm[:3, :3].T + Vm[:3, 3]
        z = pc[:, 2]
        ok = z > 1e-6
        zs = np.where(ok, z, 1.0)
        x = K[0, 0] * pc[:, 0] / zs + K[0, 1] * pc[:, 1] / zs + K[0, 2]
        y = K[1, 1] * pc[:, 1] / zs + K[1, 2]
        ok &= (x >= 0) & (x <= W) & (y >= 0) & (y <= H)
        fx = np.clip(x - 0.5, 0, W - 1)
        fy = np.clip(y - 0.5, 0, H - 1)
        x0 = np.floor(fx).astype(np.int64)
        y0 = np.floor(fy).astype(np.int64)
        x1, y1 = np.minimum(x0 + 1, W - 1), np.minimum(y0 + 1, H - 1)
        ax, ay = fx - x0, fy - y0
        m = dataset.masks[v]
        top = m[y0, x0] * (1 - ax) + m[y0, x1] * ax
        bot = m[y1, x0] * (1 - ax) + m[y1, x1] * ax
        vals[:, j] = np.where(ok, top * (1 - ay) + bot * ay, 0.0)
        seen[:, j] = ok
    return vals, seen


def pixel_rays(viewmat: np.ndarray, K: np.ndarray, width: int, height: int):
    """World-space rays through every pixel centre of an OpenCV camera.

    Returns:
        origin (3,), directions (H, W, 3) unit vectors, and ``z_per_t`` (H, W): camera depth
        gained per unit distance along the ray (so depth = t * z_per_t).
    """
    xs = np.arange(width) + 0.5
    ys = np.arange(height) + 0.5
    u, v = np.meshgrid(xs, ys)
    d_cam = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], axis=-1)
    d_cam = d_cam / np.linalg.norm(d_cam, axis=-1, keepdims=True)
    R = viewmat[:3, :3]
    origin = -R.T @ viewmat[:3, 3]
    return origin, d_cam @ R, d_cam[..., 2]


def point_triangle_distance(points: np.ndarray, a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    """(P, F) exact distances from points (P, 3) to triangles (F, 3 corners each), float64,
    by Ericson's Voronoi-region test ("Real-Time Collision Detection", 5.1.5)."""
    p = points[:, None, :]
    a, b, c = a[None], b[None], c[None]
    ab, ac, ap = b - a, c - a, p - a
    d1, d2 = (ab * ap).sum(-1), (ac * ap).sum(-1)
    bp = p - b
    d3, d4 = (ab * bp).sum(-1), (ac * bp).sum(-1)
    cp = p - c
    d5, d6 = (ab * cp).sum(-1), (ac * cp).sum(-1)
    va = d3 * d6 - d5 * d4
    vb = d5 * d2 - d1 * d6
    vc = d1 * d4 - d3 * d2
    with np.errstate(divide="ignore", invalid="ignore"):
        denom = 1.0 / (va + vb + vc)
        v_in, w_in = vb * denom, vc * denom
        t_ab = d1 / (d1 - d3)
        t_ac = d2 / (d2 - d6)
        t_bc = (d4 - d3) / ((d4 - d3) + (d5 - d6))
    q = a + ab * v_in[..., None] + ac * w_in[..., None]  # inside the face
    q = np.where(((va <= 0) & (d4 - d3 >= 0) & (d5 - d6 >= 0))[..., None], b + (c - b) * t_bc[..., None], q)
    q = np.where(((vb <= 0) & (d2 >= 0) & (d6 <= 0))[..., None], a + ac * t_ac[..., None], q)
    q = np.where(((vc <= 0) & (d1 >= 0) & (d3 <= 0))[..., None], a + ab * t_ab[..., None], q)
    q = np.where(((d6 >= 0) & (d5 <= d6))[..., None], c, q)
    q = np.where(((d3 >= 0) & (d4 <= d3))[..., None], b, q)
    q = np.where(((d1 <= 0) & (d2 <= 0))[..., None], a, q)
    return np.linalg.norm(p - q, axis=-1)


def min_dihedral_deg(V: np.ndarray, T: np.ndarray) -> np.ndarray:
    """Smallest interior dihedral angle (M,) in degrees of each tet, from the two other
    vertices' directions perpendicular to each edge (not from face normals, as the library
    does)."""
    P = np.asarray(V, dtype=np.float64)[np.asarray(T)]
    out = np.full(len(P), np.inf)
    for i, j, k, l in ((0, 1, 2, 3), (0, 2, 1, 3), (0, 3, 1, 2), (1, 2, 0, 3), (1, 3, 0, 2), (2, 3, 0, 1)):
        e = P[:, j] - P[:, i]
        e /= np.linalg.norm(e, axis=1, keepdims=True)
        u, w = P[:, k] - P[:, i], P[:, l] - P[:, i]
        u -= (u * e).sum(1, keepdims=True) * e
        w -= (w * e).sum(1, keepdims=True) * e
        c = (u * w).sum(1) / (np.linalg.norm(u, axis=1) * np.linalg.norm(w, axis=1))
        out = np.minimum(out, np.degrees(np.arccos(np.clip(c, -1.0, 1.0))))
    return out


def edge_fan(sectors_deg, *, spiral: float = 0.0):
    """A tet mesh whose boundary wedge (:meth:`holowarp.tetmesh.TetMesh.boundary_wedges`) at
    the z-axis edge (0,0,0)-(0,0,1), vertices 0 and 1, is known by construction: the sum of
    the sectors. One prism per (a, b) sector in degrees (height 1, 3 tets each) with
    shared rim vertices welded; the rim's radius is 1 + ``spiral`` * angle / 360, so a fan
    past a full turn has no coincident vertices. Returns (positively oriented mesh, owner
    (M,): the sector of each tet)."""
    from holowarp.tetmesh import TetMesh

    angles = sorted({a for s in sectors_deg for a in s})
    rim = {a: i for i, a in enumerate(angles)}
    n = len(angles)
    V = [[0.0, 0.0, 0.0], [0.0, 0.0, 1.0]]
    for z in (0.0, 1.0):
        for a in angles:
            r = 1.0 + spiral * a / 360.0
            V.append([r * np.cos(np.radians(a)), r * np.sin(np.radians(a)), z])
    T, owner = [], []
    for k, (a, b) in enumerate(sectors_deg):
        p, q = 2 + rim[a], 2 + rim[b]
        P, Q = p + n, q + n
        # Prism (0, p, q) x (1, P, Q) split into three tets.
        for tet in ([0, p, q, 1], [p, q, 1, Q], [p, 1, P, Q]):
            T.append(tet)
            owner.append(k)
    mesh, _ = TetMesh(np.array(V), np.array(T), validate=False).oriented()
    return mesh, np.array(owner)


def turn_rim(mesh, rows, factor):
    """:func:`edge_fan` ``mesh``'s vertices (V, 3) with the azimuths of each row of vertices
    in ``rows`` (index arrays in the order :func:`edge_fan` numbers them, azimuth rising)
    scaled by ``factor``: the axis's wedge scales with the bottom row."""
    V = np.asarray(mesh.vertices, dtype=np.float64).copy()
    for row in rows:
        r = np.linalg.norm(V[row, :2], axis=1)
        a = np.unwrap(np.arctan2(V[row, 1], V[row, 0])) * factor
        V[row, 0], V[row, 1] = r * np.cos(a), r * np.sin(a)
    return V


def axis_wedge(mesh, V):
    """The wedge in degrees at :func:`edge_fan`'s axis edge (vertices 0 and 1) with positions ``V``."""
    edges, wedge = mesh.with_vertices(V).boundary_wedges()
    return float(wedge[(np.sort(edges, axis=1) == [0, 1]).all(axis=1)][0])


def surface_area(mesh) -> float:
    """Total area of a tet mesh's boundary triangles (float64)."""
    V, F = mesh.surface_mesh()
    return float(0.5 * np.linalg.norm(np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]]), axis=1).sum())
