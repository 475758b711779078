"""Camera conventions (method.md §1) and the synthetic view protocol (§2).

- OpenCV pinhole: camera x right, y down, z forward (looking along +z).
- ``viewmat`` is the 4x4 world-to-camera matrix: ``x_cam = R @ x_world + t``.
- ``K`` is 3x3; pixel centres sit at ``(x + 0.5, y + 0.5)``, so a point projecting to
  ``u = K[0,0] * x/z + K[0,2]`` lies in pixel column ``floor(u)``.
- World is Z up.

All functions are NumPy float64 and have no Warp/torch dependency.
"""

from __future__ import annotations

import math

import numpy as np

__all__ = [
    "FOV_DEG",
    "fibonacci_sphere",
    "intrinsics_from_fov",
    "look_at",
    "camera_center",
    "axes_focus",
    "opengl_c2w_to_viewmat",
    "viewmat_to_opengl_c2w",
    "project_points",
]

#: Horizontal field of view of the synthetic protocol (TetSphere's renders), method.md §2.
FOV_DEG = 39.3


def fibonacci_sphere(n: int) -> np.ndarray:
    """``n`` near-uniform unit directions on the sphere (golden-angle spiral).

    Returns:
        (n, 3) float64 unit vectors, ordered from z = +1 towards z = -1.
    """
    if n < 1:
        raise ValueError(f"fibonacci_sphere: n must be >= 1, got {n}")
    i = np.arange(n, dtype=np.float64) + 0.5
    z = 1.0 - 2.0 * i / n
    r = np.sqrt(np.clip(1.0 - z * z, 0.0, None))
    phi = i * math.pi * (3.0 - math.sqrt(5.0))
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1)


def intrinsics_from_fov(fov_x_rad: float, width: int, height: int) -> np.ndarray:
    """Pinhole ``K`` (3, 3) with square pixels and the principal point at the image centre."""
    f = 0.5 * width / math.tan(0.5 * fov_x_rad)
    return np.array([[f, 0.0, 0.5 * width], [0.0, f, 0.5 * height], [0.0, 0.0, 1.0]])


def look_at(eye, target=(0.0, 0.0, 0.0), up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """OpenCV world-to-camera ``viewmat`` (4, 4) for a camera at ``eye`` looking at ``target``.

    The image's "up" (-y in camera space) is aligned with ``up`` as closely as possible; when
    the view direction is parallel to ``up`` another world axis is used.
    """
    eye = np.asarray(eye, dtype=np.float64)
    target = np.asarray(target, dtype=np.float64)
    up = np.asarray(up, dtype=np.float64)
    fwd = target - eye
    norm = np.linalg.norm(fwd)
    if norm == 0:
        raise ValueError("look_at: eye and target coincide")
    fwd /= norm
    right = np.cross(fwd, up)
    if np.linalg.norm(right) < 1e-8:
        alt = np.array([0.0, 1.0, 0.0]) if abs(fwd[1]) < 0.9 else np.array([1.0, 0.0, 0.0])
        right = np.cross(fwd, alt)
    right /= np.linalg.norm(right)
    down = np.cross(fwd, right)
    R = np.stack([right, down, fwd], axis=0)
    V = np.eye(4)
    V[:3, :3] = R
    V[:3, 3] = -R @ eye
    return V


def camera_center(viewmat: np.ndarray) -> np.ndarray:
    """World position (3,) of a camera given its world-to-camera matrix (4, 4)."""
    R = viewmat[:3, :3]
    return -R.T @ viewmat[:3, 3]


def axes_focus(viewmats) -> np.ndarray:
    """The point (3,) nearest, in least squares, to every camera's optical axis: where a ring
    of cameras looking at one object is looking. Parallel axes fall back to the mean camera
    centre."""
    A = np.zeros((3, 3))
    b = np.zeros(3)
    centres = []
    for V in np.asarray(viewmats, dtype=np.float64):
        c = camera_center(V)
        d = V[2, :3]  # optical axis (camera +z) in world
        P = np.eye(3) - np.outer(d, d)
        A += P
        b += P @ c
        centres.append(c)
    if np.linalg.matrix_rank(A) < 3:
        return np.mean(centres, axis=0)
    return np.linalg.solve(A, b)


_GL_FLIP = np.diag([1.0, -1.0, -1.0, 1.0])


def opengl_c2w_to_viewmat(c2w: np.ndarray) -> np.ndarray:
    """NeRF-synthetic/Blender camera-to-world (OpenGL axes) -> OpenCV world-to-camera."""
    c2w = np.asarray(c2w, dtype=np.float64)
    return np.linalg.inv(c2w @ _GL_FLIP)


def viewmat_to_opengl_c2w(viewmat: np.ndarray) -> np.ndarray:
    """Inverse of :func:`opengl_c2w_to_viewmat`."""
    return np.linalg.inv(np.asarray(viewmat, dtype=np.float64)) @ _GL_FLIP


def project_points(points: np.ndarray, viewmat: np.ndarray, K: np.ndarray):
    """Project world points (P, 3) to pixel coordinates (P, 2) and camera depth (P,).

    ``u = K[0,0] x/z + K[0,1] y/z + K[0,2]``, ``v = K[1,1] y/z + K[1,2]`` (the skew ``K[0,1]``
    of decomposed projections is honoured). Points behind the camera project through it, as
    the formula says; callers that want visible points test ``z > 0``.
    """
    pc = np.asarray(points, dtype=np.float64) @ viewmat[:3, :3].T + viewmat[:3, 3]
    z = pc[:, 2]
    zs = np.where(np.abs(z) > 1e-12, z, 1e-12)  # points on the camera plane: finite, not NaN
    uv = (pc[:, :2] / zs[:, None]) @ K[:2, :2].T + K[:2, 2]
    return uv, z
