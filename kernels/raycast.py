"""Ground-truth ray casting on a ``wp.Mesh`` BVH (method.md §2).

One thread per pixel casts ``ss x ss`` stratified rays through the pixel (pixel centres at
``(x + 0.5, y + 0.5)``, OpenCV camera: x right, y down, z forward; the ray through image point
``(u, v)`` is ``K^-1 [u, v, 1]``, skew ``K[0, 1]`` included), finds the closest hit with
``wp.mesh_query_ray`` and accumulates

- coverage (alpha = fraction of the pixel's rays that hit),
- straight (un-premultiplied) RGB of the hits: albedo x (ambient + sum_l I_l max(0, n.l)),
  world-fixed lights so the radiance is view independent; albedo from a bilinear texture
  lookup at the interpolated UV, interpolated vertex colours, or one fixed colour,
- the world-space unit normal (per-corner shading normals interpolated, or the flat face
  normal), and the camera z-depth of the hits.

Barycentric convention (Warp's ``mesh_query_ray``/``mesh_eval_position``): the hit point is
``u * p0 + v * p1 + (1 - u - v) * p2`` for face corners ``p0, p1, p2``.

Warp + NumPy only: no torch below ``kernels/``.
"""

from __future__ import annotations

import warp as wp

__all__ = [
    "COLOR_ALBEDO",
    "COLOR_VERTEX",
    "COLOR_TEXTURE",
    "raycast_kernel",
    "sample_texture_bilinear",
    "texture_lookup_kernel",
]

#: Colour source selector of :func:`raycast_kernel`.
COLOR_ALBEDO = wp.constant(0)
COLOR_VERTEX = wp.constant(1)
COLOR_TEXTURE = wp.constant(2)


@wp.func
def sample_texture_bilinear(tex: wp.array2d(dtype=wp.vec3), uv: wp.vec2):
    """Bilinear lookup with repeat wrapping; ``uv`` in OBJ convention (v up, row 0 = top)."""
    h = tex.shape[0]
    w = tex.shape[1]
    # Texel centres sit at (i + 0.5) / size.
    x = (uv[0] - wp.floor(uv[0])) * float(w) - 0.5
    y = (1.0 - (uv[1] - wp.floor(uv[1]))) * float(h) - 0.5
    x0f = wp.floor(x)
    y0f = wp.floor(y)
    fx = x - x0f
    fy = y - y0f
    x0 = ((int(x0f) % w) + w) % w
    y0 = ((int(y0f) % h) + h) % h
    x1 = (x0 + 1) % w
    y1 = (y0 + 1) % h
    top = tex[y0, x0] * (1.0 - fx) + tex[y0, x1] * fx
    bot = tex[y1, x0] * (1.0 - fx) + tex[y1, x1] * fx
    return top * (1.0 - fy) + bot * fy


@wp.kernel
def texture_lookup_kernel(
    tex: wp.array2d(dtype=wp.vec3),
    uvs: wp.array(dtype=wp.vec2),
    out: wp.array(dtype=wp.vec3),
):
    """``out[i] = sample_texture_bilinear(tex, uvs[i])`` (exposes the lookup to tests)."""
    i = wp.tid()
    out[i] = sample_texture_bilinear(tex, uvs[i])


@wp.kernel
def raycast_kernel(
    mesh: wp.uint64,
    faces: wp.array2d(dtype=wp.int32),  # [F, 3]
    corner_normals: wp.array2d(dtype=wp.vec3),  # [F, 3] shading normal per face corner
    smooth: int,
    color_mode: int,
    albedo: wp.vec3,
    vertex_colors: wp.array(dtype=wp.vec3),  # [V]
    face_uvs: wp.array2d(dtype=wp.int32),  # [F, 3]
    uvs: wp.array(dtype=wp.vec2),  # [T]
    texture: wp.array2d(dtype=wp.vec3),  # [TH, TW]
    light_dirs: wp.array(dtype=wp.vec3),  # [L] unit vectors towards the lights
    light_rgb: wp.array(dtype=wp.vec3),  # [L]
    ambient: wp.vec3,
    cam_pos: wp.vec3,  # camera centre in world
    cam_rot: wp.mat33,  # camera-to-world rotation (columns: camera x, y, z in world)
    fx: float,
    fy: float,
    cx: float,
    cy: float,
    skew: float,  # K[0, 1]: the skew of decomposed projections (NeuS/IDR)
    ss: int,
    max_t: float,
    rgba: wp.array2d(dtype=wp.vec4),  # [H, W] straight RGB + coverage
    normal: wp.array2d(dtype=wp.vec3),  # [H, W] world-space unit normal, 0 on background
    depth: wp.array2d(dtype=float),  # [H, W] camera z-depth, 0 on background
    face_id: wp.array2d(dtype=wp.int32),  # [H, W] nearest hit face, -1 on background
):
    row, col = wp.tid()
    inv_ss = 1.0 / float(ss)
    hits = int(0)
    col_acc = wp.vec3(0.0)
    n_acc = wp.vec3(0.0)
    z_acc = float(0.0)
    best_t = max_t
    best_face = int(-1)
    for sy in range(ss):
        for sx in range(ss):
            px = float(col) + (float(sx) + 0.5) * inv_ss
            py = float(row) + (float(sy) + 0.5) * inv_ss
            # K^-1 [px, py, 1] for K = [[fx, skew, cx], [0, fy, cy], [0, 0, 1]]
            y_cam = (py - cy) / fy
            d_cam = wp.normalize(wp.vec3((px - cx - skew * y_cam) / fx, y_cam, 1.0))
            d = cam_rot * d_cam
            q = wp.mesh_query_ray(mesh, cam_pos, d, max_t)
            if q.result:
                f = q.face
                b0 = q.u
                b1 = q.v
                b2 = 1.0 - b0 - b1
                i0 = faces[f, 0]
                i1 = faces[f, 1]
                i2 = faces[f, 2]
                n = wp.vec3(0.0)
                if smooth != 0:
                    n = corner_normals[f, 0] * b0 + corner_normals[f, 1] * b1 + corner_normals[f, 2] * b2
                    if wp.length(n) < 1.0e-12:
                        n = wp.mesh_eval_face_normal(mesh, f)
                    n = wp.normalize(n)
                else:
                    n = wp.mesh_eval_face_normal(mesh, f)
                # Shade the side facing the camera (open meshes show back faces).
                ns = n
                if wp.dot(ns, d) > 0.0:
                    ns = -ns
                a = albedo
                if color_mode == COLOR_VERTEX:
                    a = vertex_colors[i0] * b0 + vertex_colors[i1] * b1 + vertex_colors[i2] * b2
                elif color_mode == COLOR_TEXTURE:
                    uv = uvs[face_uvs[f, 0]] * b0 + uvs[face_uvs[f, 1]] * b1 + uvs[face_uvs[f, 2]] * b2
                    a = sample_texture_bilinear(texture, uv)
                light = ambient
                for l in range(light_dirs.shape[0]):
                    light = light + light_rgb[l] * wp.max(wp.dot(ns, light_dirs[l]), 0.0)
                c = wp.cw_mul(a, light)
                col_acc = col_acc + wp.vec3(wp.min(c[0], 1.0), wp.min(c[1], 1.0), wp.min(c[2], 1.0))
                n_acc = n_acc + n
                z_acc = z_acc + q.t * d_cam[2]
                hits = hits + 1
                if q.t < best_t:
                    best_t = q.t
                    best_face = f
    if hits > 0:
        inv = 1.0 / float(hits)
        c = col_acc * inv
        rgba[row, col] = wp.vec4(c[0], c[1], c[2], float(hits) * inv_ss * inv_ss)
        ln = wp.length(n_acc)
        if ln > 1.0e-12:
            normal[row, col] = n_acc / ln
        else:
            normal[row, col] = wp.vec3(0.0)
        depth[row, col] = z_acc * inv
    else:
        rgba[row, col] = wp.vec4(0.0)
        normal[row, col] = wp.vec3(0.0)
        depth[row, col] = 0.0
    face_id[row, col] = best_face
