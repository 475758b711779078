"""Ray-casting driver: owns the Warp arrays and BVH of one triangle mesh and launches
:func:`holowarp.kernels.raycast.raycast_kernel` (method.md §2).

Not differentiable; :class:`holowarp.render_gt.GTRenderer` builds one from a surface and
turns its outputs into images.
"""

from __future__ import annotations

import numpy as np

from holowarp.device import init_warp, resolve_device

__all__ = ["RayCaster"]


class RayCaster:
    """A triangle mesh uploaded for ray casting, with its shading inputs.

    Args:
        vertices: (V, 3) float32 positions (world units, Z up).
        faces: (F, 3) int32 vertex indices, counter-clockwise seen from outside.
        corner_normals: (F, 3, 3) float32 shading normal per face corner, or None for flat
            face normals.
        color_mode: ``COLOR_ALBEDO``, ``COLOR_VERTEX`` or ``COLOR_TEXTURE`` of
            :mod:`holowarp.kernels.raycast`.
        albedo: RGB used in ``COLOR_ALBEDO`` mode.
        vertex_colors: (V, 3) RGB (``COLOR_VERTEX``), texture (TH, TW, 3) with uvs (T, 2)
            and face_uvs (F, 3) (``COLOR_TEXTURE``); unused ones may be None.
        ambient, light_dirs (L, 3), light_rgb (L, 3): fixed world lighting.
        device: ``"cpu"`` or ``"cuda[:N]"``.
    """

    def __init__(self, vertices, faces, *, corner_normals, color_mode: int, albedo, vertex_colors=None,
                 texture=None, uvs=None, face_uvs=None, ambient, light_dirs, light_rgb, device: str = "cpu"):
        wp = init_warp()
        self._wp = wp
        self.device = dev = resolve_device(device)
        v = np.ascontiguousarray(vertices, dtype=np.float32)
        f = np.ascontiguousarray(faces, dtype=np.int32)
        self._points = wp.array(v, dtype=wp.vec3, device=dev)
        self._indices = wp.array(f.ravel(), dtype=wp.int32, device=dev)
        self._mesh = wp.Mesh(points=self._points, indices=self._indices)
        self._faces = wp.array(f, dtype=wp.int32, device=dev)
        self.smooth = corner_normals is not None
        cn = corner_normals if self.smooth else np.zeros((1, 3, 3), np.float32)
        self._corner_normals = wp.array(np.ascontiguousarray(cn, dtype=np.float32), dtype=wp.vec3, device=dev)

        def arr(x, shape, dtype):
            a = np.zeros(shape, np.float32 if dtype != wp.int32 else np.int32) if x is None else x
            return wp.array(np.ascontiguousarray(a), dtype=dtype, device=dev)

        self.color_mode = int(color_mode)
        self._vertex_colors = arr(vertex_colors, (1, 3), wp.vec3)
        self._texture = arr(texture, (1, 1, 3), wp.vec3)
        self._uvs = arr(uvs, (1, 2), wp.vec2)
        self._face_uvs = arr(face_uvs, (1, 3), wp.int32)
        self._albedo = wp.vec3(*[float(x) for x in albedo])
        self._light_dirs = wp.array(np.asarray(light_dirs, np.float32).reshape(-1, 3), dtype=wp.vec3, device=dev)
        self._light_rgb = wp.array(np.asarray(light_rgb, np.float32).reshape(-1, 3), dtype=wp.vec3, device=dev)
        self._ambient = wp.vec3(*[float(x) for x in ambient])
        self._scene_radius = max(float(np.linalg.norm(v.max(0) - v.min(0))), 1e-6)

    def cast(self, viewmat: np.ndarray, K: np.ndarray, width: int, height: int, supersample: int) -> dict:
        """Cast ``supersample``² stratified rays per pixel for one OpenCV camera
        (``viewmat`` (4, 4) world-to-camera with an orthonormal rotation, ``K`` (3, 3) upper
        triangular: focal lengths, principal point and skew ``K[0, 1]``; the ray through
        image point (u, v) is ``K^-1 [u, v, 1]``).

        Returns the Warp output arrays without a host copy: ``rgba`` (H, W) vec4 (straight RGB,
        coverage), ``normal`` (H, W) vec3 (world, 0 on background), ``depth`` (H, W) camera
        z-depth (0 on background), ``face`` (H, W) int32 (-1 on background).
        """
        from holowarp.kernels import raycast as rk

        wp, dev = self._wp, self.device
        K = np.asarray(K, dtype=np.float64)
        if abs(K[1, 0]) > 0 or abs(K[2, 0]) > 0 or abs(K[2, 1]) > 0 or abs(K[2, 2] - 1.0) > 1e-9:
            raise ValueError(f"RayCaster.cast: K must be upper triangular with K[2, 2] = 1, got {K.tolist()}")
        R = viewmat[:3, :3]
        cam_pos = -R.T @ viewmat[:3, 3]
        rgba = wp.empty((height, width), dtype=wp.vec4, device=dev)
        normal = wp.empty((height, width), dtype=wp.vec3, device=dev)
        depth = wp.empty((height, width), dtype=float, device=dev)
        face = wp.empty((height, width), dtype=wp.int32, device=dev)
        max_t = float(np.linalg.norm(cam_pos) + 4.0 * self._scene_radius + 1.0) * 4.0
        wp.launch(
            rk.raycast_kernel,
            dim=(height, width),
            inputs=[
                self._mesh.id, self._faces, self._corner_normals, int(self.smooth), self.color_mode, self._albedo,
                self._vertex_colors, self._face_uvs, self._uvs, self._texture, self._light_dirs, self._light_rgb,
                self._ambient, wp.vec3(*cam_pos.astype(np.float32)), wp.mat33(*R.T.astype(np.float32).ravel()),
                float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2]), float(K[0, 1]), max(int(supersample), 1),
                max_t,
            ],
            outputs=[rgba, normal, depth, face],
            device=dev,
        )
        return {"rgba": rgba, "normal": normal, "depth": depth, "face": face}
