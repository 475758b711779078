"""Scene normalisation for captures whose world has an arbitrary origin, scale and up
(structure from motion): the object's visual hull is mapped to the unit sphere, as NeuS's
``scale_mat`` does, and the world is turned so that Z is up (method.md §1).

- Hull: the masks are carved (:func:`holowarp.carve.inside_hull`, every view) on a coarse
  grid over :func:`holowarp.carve.look_region` (the cube every camera looks into), then on a
  finer grid over the box the coarse carve found. The bounding sphere is NeuS's: centred at
  the carved box's centre, radius the farthest carved node plus one cell diagonal (the hull's
  boundary lies within a cell of its nodes).
- Up: the mean of the cameras' up vectors (camera -y in world). People hold cameras upright
  and turntables keep them level, so the mean image "up" is the gravity up for every capture
  holowarp targets; the shortest rotation taking it to +Z is applied.
- ``x_world = R_up (x_in - centre) / radius``; the inverse, ``x_in = scale_mat @ x_world``
  with ``scale_mat = [[radius R_up^T, centre], [0, 1]]``, has NeuS's meaning.
"""

from __future__ import annotations

import numpy as np

from holowarp.data.dataset import DatasetError

__all__ = ["hull_nodes", "hull_sphere", "up_rotation", "mean_camera_up", "normalize_to_unit_sphere", "COARSE_GRID",
           "FINE_GRID"]

#: Carving nodes per side of the coarse (look-region) and fine (hull-box) grids.
COARSE_GRID = 48
FINE_GRID = 64


def _grid(lo: np.ndarray, hi: np.ndarray, n: int) -> tuple[np.ndarray, float]:
    """Nodes (n^3, 3) of a cube grid covering the box [lo, hi] (centred on it), and the spacing."""
    c, side = 0.5 * (lo + hi), float(np.max(hi - lo))
    h = side / (n - 1)
    t = (np.arange(n) - 0.5 * (n - 1)) * h
    X, Y, Z = np.meshgrid(c[0] + t, c[1] + t, c[2] + t, indexing="ij")
    return np.stack([X.ravel(), Y.ravel(), Z.ravel()], 1), h


def hull_nodes(dataset, *, device: str = "cpu") -> tuple[np.ndarray, np.ndarray, float]:
    """The visual hull of every view's mask on a grid: the nodes (n^3, 3) of the
    ``FINE_GRID``-node cube over the box a coarse carve of the look region found (see the
    module docstring; node index ``(i * n + j) * n + k`` along x, y, z), which of them lie
    inside (n^3,) bool, and the spacing, in the dataset's world units. A hull thinner than
    the coarse cells marks every fine node inside."""
    from holowarp.carve import inside_hull, look_region

    views = np.arange(dataset.num_views)
    centre, half = look_region(dataset.viewmats)
    pts, h = _grid(centre - half, centre + half, COARSE_GRID)
    inside = pts[inside_hull(dataset, pts, views, device=device)]
    if len(inside) == 0:
        raise DatasetError(f"{dataset.root or dataset.name}: the masks carve away everything the cameras look at "
                           "(do the masks belong to their images, and the poses to this capture?)")
    pts, h = _grid(inside.min(0) - h, inside.max(0) + h, FINE_GRID)
    fine = inside_hull(dataset, pts, views, device=device)
    return pts, (fine if fine.any() else np.ones(len(pts), dtype=bool)), h


def hull_sphere(dataset, *, device: str = "cpu") -> tuple[np.ndarray, float]:
    """Centre (3,) and radius of the bounding sphere of the visual hull of every view's mask,
    in the dataset's world units (see the module docstring)."""
    pts, inside, h = hull_nodes(dataset, device=device)
    inside = pts[inside]
    c = 0.5 * (inside.min(0) + inside.max(0))
    r = float(np.linalg.norm(inside - c, axis=1).max()) + h * np.sqrt(3.0)
    return c, r


def mean_camera_up(viewmats: np.ndarray) -> np.ndarray:
    """Unit mean (3,) of the cameras' up vectors (OpenCV camera -y, i.e. ``-R[1, :]``, in
    world); world +Z when they cancel out."""
    up = -np.asarray(viewmats)[:, 1, :3].mean(axis=0)
    n = np.linalg.norm(up)
    return up / n if n > 1e-9 else np.array([0.0, 0.0, 1.0])


def up_rotation(up: np.ndarray) -> np.ndarray:
    """The shortest rotation (3, 3) taking the unit vector ``up`` to +Z."""
    up = np.asarray(up, dtype=np.float64)
    z = np.array([0.0, 0.0, 1.0])
    v, c = np.cross(up, z), float(up @ z)
    if c < -1.0 + 1e-12:  # upside down: half a turn about x
        return np.diag([1.0, -1.0, -1.0])
    vx = np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])
    return np.eye(3) + vx + vx @ vx / (1.0 + c)


def normalize_to_unit_sphere(dataset, *, device: str = "cpu"):
    """``(viewmats (N, 4, 4), record)``: the dataset's cameras in the normalised world (hull
    sphere -> unit sphere, Z up), and a JSON-ready record of the transform for
    ``Dataset.meta["normalization"]``. Intrinsics do not change (a similarity only moves and
    scales the scene, and scaling a camera's coordinates does not move its pixels)."""
    centre, radius = hull_sphere(dataset, device=device)
    up = mean_camera_up(dataset.viewmats)
    Rup = up_rotation(up)
    # x_in = radius Rup^T x_world + centre, so x_cam = R x_in + t = radius (R Rup^T x_world +
    # (R centre + t) / radius); the factor radius does not change the projection.
    V = np.array(dataset.viewmats, dtype=np.float64, copy=True)
    R, t = V[:, :3, :3], V[:, :3, 3]
    V[:, :3, 3] = (np.einsum("nij,j->ni", R, centre) + t) / radius
    V[:, :3, :3] = R @ Rup.T
    S = np.eye(4)
    S[:3, :3] = radius * Rup.T
    S[:3, 3] = centre
    record = {
        "method": "visual-hull bounding sphere -> unit sphere (NeuS scale_mat), mean camera up -> +Z",
        "center": centre.tolist(),
        "radius": radius,
        "up": up.tolist(),
        "scale_mat": S.tolist(),  # x_input_world = scale_mat @ x_world (homogeneous)
        "world_from_input": np.linalg.inv(S).tolist(),
    }
    return V, record
