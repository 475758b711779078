"""Warp driver of the element-improvement kernels (:mod:`holowarp.kernels.improve`).

:class:`ImproveKernels` owns the device, uploads what a launch needs and returns NumPy
arrays; the improvement stage (:mod:`holowarp.stages.improve`) calls it and launches
nothing itself. Everything is float64 except the BVH of :meth:`ImproveKernels.
point_surface_distance`, which Warp builds in float32 (the distance to the triangle it
finds is then recomputed exactly in float64 by the caller's NumPy reference).
No torch here: these operators are not differentiated.

The per-tet, per-point and per-vertex launches are cut into pieces run on both CPU threads
(:func:`holowarp.device.run_chunks`): every thread of them writes only its own outputs (and,
in smoothing, its own vertex of an independent set, whose star no other vertex of the set
touches), so the results are those of one launch, bit for bit, on any thread count.
"""

from __future__ import annotations

import numpy as np

from holowarp.device import init_warp, resolve_device, run_chunks, thread_chunks

__all__ = ["ImproveKernels", "SmoothingPass"]


def _i32(wp, a, device):
    return wp.array(np.ascontiguousarray(a, dtype=np.int32), dtype=wp.int32, device=device)


def _in_pieces(kernel, n: int, device: str, launch) -> None:
    """``launch(offset, count)`` over pieces of ``range(n)`` on the CPU threads (one piece
    on a GPU); ``launch`` slices its per-item arrays to the piece."""
    run_chunks(launch, thread_chunks(n, device, align=64), kernel=kernel, device=device)


class ImproveKernels:
    """Launches the improvement kernels on one device.

    Args:
        device: ``"cpu"`` or ``"cuda[:N]"`` (validated).
    """

    def __init__(self, device: str = "cpu"):
        from holowarp.kernels import improve as K

        self.wp = init_warp()
        self.K = K
        self.device = resolve_device(device)
        self._x = None
        self._x_src = None

    def _positions(self, V: np.ndarray):
        # The last uploaded positions are reused while the caller passes the same array.
        if self._x_src is not V:
            self._x = self.wp.array(np.ascontiguousarray(V, dtype=np.float64), dtype=self.wp.vec3d, device=self.device)
            self._x_src = V
        return self._x

    def quality(self, V: np.ndarray, T: np.ndarray, mode: int) -> np.ndarray:
        """Quality (K,) float64 of the tets ``T`` (K, 4) over positions ``V`` (N, 3), by
        measure ``mode`` (:data:`holowarp.kernels.improve.QUALITY_SINE` ...). ``V`` must not
        be modified in place between calls (its upload is cached by identity)."""
        wp = self.wp
        if len(T) == 0:
            return np.zeros(0)
        t = wp.array(np.ascontiguousarray(T, dtype=np.int32), dtype=wp.vec4i, device=self.device)
        out = wp.empty(len(T), dtype=wp.float64, device=self.device)
        x, dev = self._positions(V), self.device
        _in_pieces(self.K.tet_quality_kernel, len(T), dev,
                   lambda a, n: wp.launch(self.K.tet_quality_kernel, dim=n, inputs=[x, t[a:a + n], int(mode)],
                                          outputs=[out[a:a + n]], device=dev))
        return out.numpy()

    def closest_faces(self, points: np.ndarray, V: np.ndarray, F: np.ndarray):
        """For each point (P, 3): the surface (V, F) triangle holding its closest point
        (P,) int64 (-1 if none within reach) and the float32 distance to it (P,)."""
        wp = self.wp
        c = V.mean(axis=0)
        span = float(np.ptp(np.concatenate([V, points]), axis=0).max()) or 1.0
        mesh = wp.Mesh(points=wp.array((V - c).astype(np.float32), dtype=wp.vec3, device=self.device),
                       indices=_i32(wp, np.asarray(F).reshape(-1), self.device))
        pts = wp.array((points - c).astype(np.float32), dtype=wp.vec3, device=self.device)
        dist = wp.empty(len(points), dtype=float, device=self.device)
        face = wp.empty(len(points), dtype=wp.int32, device=self.device)
        K, dev = self.K, self.device
        _in_pieces(K.point_mesh_distance_kernel, len(points), dev,
                   lambda a, n: wp.launch(K.point_mesh_distance_kernel, dim=n,
                                          inputs=[mesh.id, pts[a:a + n], 4.0 * span],
                                          outputs=[dist[a:a + n], face[a:a + n]], device=dev))
        return face.numpy().astype(np.int64), dist.numpy().astype(np.float64)

    def smoothing_pass(self, V, T, star, bfaces, proj, mode: int, params) -> "SmoothingPass":
        """A :class:`SmoothingPass` over positions ``V`` (N, 3) and tets ``T`` (M, 4)."""
        return SmoothingPass(self, V, T, star, bfaces, proj, mode, params)


class SmoothingPass:
    """Device state of one smoothing pass: positions, tets, vertex stars, boundary
    triangles per vertex and allowed directions; :meth:`step` smooths one independent set.

    Args:
        V, T: positions (N, 3) float64, tets (M, 4).
        star: (offsets (N+1,), tet ids (4M,), local index (4M,)), the vertex stars in CSR.
        bfaces: (offsets (N+1,), face ids (3F,), faces (F, 3)), boundary triangles per vertex.
        proj: (N, 3, 3) projector onto each vertex's allowed directions.
        mode: quality measure.
        params: the kernel's scalars in order: beta, step_frac, n_steps, fd_frac, min_gain,
            level, margin, mean_guard (see :func:`holowarp.kernels.improve.smooth_vertices_kernel`).
    """

    def __init__(self, k: ImproveKernels, V, T, star, bfaces, proj, mode: int, params):
        wp, dev = k.wp, k.device
        self.k = k
        self.x = wp.array(np.ascontiguousarray(V, dtype=np.float64), dtype=wp.vec3d, device=dev)
        self.tets = wp.array(np.ascontiguousarray(T, dtype=np.int32), dtype=wp.vec4i, device=dev)
        self.star = [_i32(wp, a, dev) for a in star]
        f_offs, f_ids, faces = bfaces
        faces = np.asarray(faces, dtype=np.int32).reshape(-1, 3)
        self.bfaces = [_i32(wp, f_offs, dev), _i32(wp, f_ids, dev),
                       wp.array(faces if len(faces) else np.zeros((1, 3), np.int32), dtype=wp.vec3i, device=dev)]
        self.proj = wp.array(np.ascontiguousarray(proj, dtype=np.float64), dtype=wp.mat33d, device=dev)
        beta, step, n_steps, fd, gain, level, margin, guard = params
        self.consts = [int(mode), wp.float64(beta), wp.float64(step), int(n_steps), wp.float64(fd), wp.float64(gain),
                       int(level), wp.float64(margin), wp.float64(guard)]

    def step(self, verts: np.ndarray, budget: np.ndarray):
        """Smooth the independent vertices ``verts`` (K,) in place, each boundary vertex's
        surface move limited by ``budget`` (N,) metres. Returns (star minimum before (K,),
        after (K,), surface move charged (K,) in metres)."""
        wp, dev = self.k.wp, self.k.device
        n = len(verts)
        qb, qa, hm = (wp.zeros(n, dtype=wp.float64, device=dev) for _ in range(3))
        bud = wp.array(np.ascontiguousarray(budget, dtype=np.float64), dtype=wp.float64, device=dev)
        mode, *scalars = self.consts
        vs, K = _i32(wp, verts, dev), self.k.K
        _in_pieces(K.smooth_vertices_kernel, n, dev,
                   lambda a, m: wp.launch(K.smooth_vertices_kernel, dim=m,
                                          inputs=[self.x, self.tets, *self.star, *self.bfaces, vs[a:a + m], self.proj,
                                                  bud, mode, *scalars],
                                          outputs=[qb[a:a + m], qa[a:a + m], hm[a:a + m]], device=dev))
        return qb.numpy(), qa.numpy(), hm.numpy()

    def positions(self) -> np.ndarray:
        """The current positions (N, 3) float64 (a copy)."""
        return self.x.numpy().astype(np.float64).copy()
