"""Warp kernels of the tile-binned, anti-aliased triangle rasteriser (method.md §6).

Pipeline (driven by ``holowarp.ops.mesh_raster``):

1. ``project_vertices_kernel``: world -> camera -> pixel coordinates (OpenCV, method.md §1;
   pixel centres at ``(x + 0.5, y + 0.5)``).
2. ``face_setup_kernel``: per face, screen vertices, edge lengths, watertight affine edge
   functions, reciprocal depths, the facing flag and the world-space unit normal. Only front
   faces are drawn: the tet boundary is closed and wound outward, so every back face is
   hidden behind, or projects under, front faces.
3. ``face_bin_count_kernel``: marks each edge of a front face as a *contour* edge when the
   face across it is missing or not front-facing, finds the tiles the face can affect (its
   screen box grown by the one-pixel reach of the anti-aliasing pass) and counts faces per
   tile.
4. ``tile_fill_kernel`` (after an exclusive scan of the counts): per-tile face lists.
5. ``raster_kernel``: one thread per pixel walks only its tile's face list (cost follows
   covered pixels, not faces x pixels) and keeps the nearest front face containing the
   pixel centre, by perspective-correct camera depth: ``face_id``, ``depth``, ``normal``.
6. ``antialias_kernel``: silhouette anti-aliasing (below).

Anti-aliasing (in the spirit of nvdiffrast's antialias op, Laine et al. 2020, with analytic
edge distances): a pixel whose hard coverage differs from one of its 4-neighbours' looks for
the contour edge crossing the segment between the two centres, nearest the uncovered one
(that crossing is on the boundary of the union of the front faces). With ``d`` the distance
of the pixel centre to that edge's line, a covered pixel gets ``min(1, 0.5 + d)`` and an
uncovered one ``max(0, 0.5 - d)``: a one-pixel box filter across the silhouette. Along a
straight edge the covered area is exact; pixels with no differing neighbour keep exactly 0
or 1, so interior edges and occluding contours inside the silhouette leave no seams.
``alpha`` is continuous as an edge sweeps over a pixel centre (0.5 on both sides) and its
gradient flows through ``d`` into the two screen vertices of the edge that set it, whenever
``0 < alpha < 1``, and on to world positions.

``normal`` is the flat world-space normal of the visible face and differentiates through
``normalize(cross(v1 - v0, v2 - v0))``. ``depth`` and ``face_id`` are not differentiable.

float32 only: screen-space geometry needs no more, and the tests check the gradients
against a float64 torch reference and float32 finite differences.
No torch import here (style.md).
"""

from __future__ import annotations

import warp as wp

__all__ = [
    "AA_BAND_PX",
    "project_vertices_kernel",
    "face_setup_kernel",
    "face_bin_count_kernel",
    "tile_fill_kernel",
    "raster_kernel",
    "antialias_kernel",
    "raster_backward_kernel",
    "face_normal_backward_kernel",
    "project_backward_kernel",
]

#: Half-width (pixels) of the anti-aliasing ramp across a contour edge.
AA_BAND_PX = 0.5


@wp.func
def _cross2(a: wp.vec2, b: wp.vec2):
    return a[0] * b[1] - a[1] * b[0]


@wp.func
def _edge_equation(ia: int, ib: int, a: wp.vec2, b: wp.vec2):
    # Coefficients (A, B, C) with A x + B y + C = -cross(b - a, p - a): positive inside a
    # front face. They are built from the edge's canonical orientation (lower vertex id
    # first) and negated exactly for the other orientation, so the two faces sharing an
    # edge evaluate bit-identical values of opposite sign: no pixel centre can fall
    # through the crack between them.
    lo = a
    hi = b
    sgn = float(-1.0)
    if ib < ia:
        lo = b
        hi = a
        sgn = 1.0
    ex = hi[0] - lo[0]
    ey = hi[1] - lo[1]
    return wp.vec3(-ey, ex, ey * lo[0] - ex * lo[1]) * sgn


@wp.kernel(enable_backward=False)
def project_vertices_kernel(
    x: wp.array(dtype=wp.vec3),  # [V] world
    R: wp.mat33,  # world-to-camera rotation
    t: wp.vec3,  # world-to-camera translation
    K: wp.mat33,  # intrinsics
    pc_out: wp.array(dtype=wp.vec3),  # [V] camera coordinates, out
    uv_out: wp.array(dtype=wp.vec2),  # [V] pixel coordinates, out
):
    i = wp.tid()
    pc = R * x[i] + t
    pc_out[i] = pc
    q = K * pc
    if q[2] > 0.0:
        uv_out[i] = wp.vec2(q[0] / q[2], q[1] / q[2])
    else:
        uv_out[i] = wp.vec2(0.0, 0.0)


@wp.kernel(enable_backward=False)
def face_setup_kernel(
    faces: wp.array(dtype=wp.vec3i),  # [F]
    x: wp.array(dtype=wp.vec3),  # [V] world
    pc: wp.array(dtype=wp.vec3),  # [V] camera
    uv: wp.array(dtype=wp.vec2),  # [V] pixels
    near: float,
    p0: wp.array(dtype=wp.vec2),  # [F] out: screen vertices
    p1: wp.array(dtype=wp.vec2),
    p2: wp.array(dtype=wp.vec2),
    edge_len: wp.array(dtype=wp.vec3),  # [F] out: |p1-p0|, |p2-p1|, |p0-p2|
    inv_z: wp.array(dtype=wp.vec3),  # [F] out: 1 / camera depth per vertex
    inv_area2: wp.array(dtype=float),  # [F] out: 1 / |twice the screen area|
    front: wp.array(dtype=wp.int32),  # [F] out: 1 if drawable front face
    normal: wp.array(dtype=wp.vec3),  # [F] out: world unit normal
    edge_eq: wp.array(dtype=wp.mat33),  # [F] out: row k = affine edge function of edge k
):
    f = wp.tid()
    tri = faces[f]
    a = uv[tri[0]]
    b = uv[tri[1]]
    c = uv[tri[2]]
    p0[f] = a
    p1[f] = b
    p2[f] = c
    edge_len[f] = wp.vec3(wp.length(b - a), wp.length(c - b), wp.length(a - c))
    za = pc[tri[0]][2]
    zb = pc[tri[1]][2]
    zc = pc[tri[2]][2]
    xa = x[tri[0]]
    m = wp.cross(x[tri[1]] - xa, x[tri[2]] - xa)
    lm = wp.length(m)
    if lm > 0.0:
        normal[f] = m / lm
    else:
        normal[f] = wp.vec3(0.0, 0.0, 0.0)
    a2 = _cross2(b - a, c - a)
    # With image y pointing down, a face whose outward normal points at the camera has
    # clockwise screen winding, i.e. a negative signed area.
    if za > near and zb > near and zc > near and a2 < -1.0e-12:
        front[f] = 1
        inv_z[f] = wp.vec3(1.0 / za, 1.0 / zb, 1.0 / zc)
        inv_area2[f] = -1.0 / a2
        edge_eq[f] = wp.matrix_from_rows(
            _edge_equation(tri[0], tri[1], a, b),
            _edge_equation(tri[1], tri[2], b, c),
            _edge_equation(tri[2], tri[0], c, a),
        )
    else:
        edge_eq[f] = wp.mat33(0.0)
        front[f] = 0
        inv_z[f] = wp.vec3(0.0, 0.0, 0.0)
        inv_area2[f] = 0.0


@wp.kernel(enable_backward=False)
def face_bin_count_kernel(
    front: wp.array(dtype=wp.int32),  # [F]
    neighbors: wp.array(dtype=wp.vec3i),  # [F] face across edge k (v_k -> v_k+1), -1 if none
    p0: wp.array(dtype=wp.vec2),
    p1: wp.array(dtype=wp.vec2),
    p2: wp.array(dtype=wp.vec2),
    width: int,
    height: int,
    tile_size: int,
    tiles_x: int,
    contour: wp.array(dtype=wp.int32),  # [F] out: bit k set if edge k is a contour edge
    tile_rect: wp.array(dtype=wp.vec4i),  # [F] out: tile x0, y0, x1, y1 (inclusive), x1 < x0 if none
    tile_counts: wp.array(dtype=wp.int32),  # [T] accumulated
):
    f = wp.tid()
    if front[f] == 0:
        contour[f] = 0
        tile_rect[f] = wp.vec4i(0, 0, -1, -1)
        return
    nb = neighbors[f]
    mask = int(0)
    for k in range(3):
        n = nb[k]
        if n < 0:
            mask = mask | (1 << k)
        elif front[n] == 0:
            mask = mask | (1 << k)
    contour[f] = mask
    a = p0[f]
    b = p1[f]
    c = p2[f]
    umin = wp.min(wp.min(a[0], b[0]), c[0])
    umax = wp.max(wp.max(a[0], b[0]), c[0])
    vmin = wp.min(wp.min(a[1], b[1]), c[1])
    vmax = wp.max(wp.max(a[1], b[1]), c[1])
    # The anti-aliasing pass looks for edges crossing the segment from a pixel centre to
    # its 4-neighbours' centres, so a face matters to pixel x when its box meets
    # [x + 0.5 - 1, x + 0.5 + 1]: x in [umin - 1.5, umax + 0.5].
    if umax < -1.0 or vmax < -1.0 or umin > float(width) + 1.0 or vmin > float(height) + 1.0:
        tile_rect[f] = wp.vec4i(0, 0, -1, -1)
        return
    # clamp before the int conversion: a vertex just past the near plane projects far away
    umin = wp.max(umin, -2.0)
    vmin = wp.max(vmin, -2.0)
    umax = wp.min(umax, float(width) + 2.0)
    vmax = wp.min(vmax, float(height) + 2.0)
    x0 = wp.max(int(wp.floor(umin - 1.5)), 0)
    x1 = wp.min(int(wp.floor(umax + 0.5)), width - 1)
    y0 = wp.max(int(wp.floor(vmin - 1.5)), 0)
    y1 = wp.min(int(wp.floor(vmax + 0.5)), height - 1)
    if x1 < x0 or y1 < y0:
        tile_rect[f] = wp.vec4i(0, 0, -1, -1)
        return
    tx0 = x0 // tile_size
    tx1 = x1 // tile_size
    ty0 = y0 // tile_size
    ty1 = y1 // tile_size
    tile_rect[f] = wp.vec4i(tx0, ty0, tx1, ty1)
    for ty in range(ty0, ty1 + 1):
        for tx in range(tx0, tx1 + 1):
            wp.atomic_add(tile_counts, ty * tiles_x + tx, 1)


@wp.kernel(enable_backward=False)
def tile_fill_kernel(
    tile_rect: wp.array(dtype=wp.vec4i),  # [F]
    tiles_x: int,
    tile_offsets: wp.array(dtype=wp.int32),  # [T] exclusive scan of the counts
    tile_fill: wp.array(dtype=wp.int32),  # [T] zeroed, accumulated
    tile_faces: wp.array(dtype=wp.int32),  # [P] out
):
    f = wp.tid()
    r = tile_rect[f]
    for ty in range(r[1], r[3] + 1):
        for tx in range(r[0], r[2] + 1):
            tile = ty * tiles_x + tx
            slot = wp.atomic_add(tile_fill, tile, 1)
            tile_faces[tile_offsets[tile] + slot] = f


@wp.kernel(enable_backward=False)
def raster_kernel(
    tile_offsets: wp.array(dtype=wp.int32),  # [T]
    tile_counts: wp.array(dtype=wp.int32),  # [T]
    tile_faces: wp.array(dtype=wp.int32),  # [P]
    edge_eq: wp.array(dtype=wp.mat33),  # [F]
    inv_z: wp.array(dtype=wp.vec3),
    inv_area2: wp.array(dtype=float),
    face_normal: wp.array(dtype=wp.vec3),
    width: int,
    tile_size: int,
    tiles_x: int,
    row_offset: int,  # first image row of this launch (a launch may cover a band of rows)
    depth: wp.array(dtype=float),  # [H*W] out, 0 where empty
    face_id: wp.array(dtype=wp.int32),  # [H*W] out, -1 where empty
    normal: wp.array(dtype=wp.vec3),  # [H*W] out
):
    # Hard visibility at the pixel centre: nearest front face by perspective-correct depth.
    py, px = wp.tid()
    py = py + row_offset
    pix = py * width + px
    ph = wp.vec3(float(px) + 0.5, float(py) + 0.5, 1.0)
    tile = (py // tile_size) * tiles_x + px // tile_size
    start = tile_offsets[tile]
    end = start + tile_counts[tile]
    best_iz = float(0.0)
    best_f = int(-1)
    for i in range(start, end):
        f = tile_faces[i]
        c = edge_eq[f] * ph  # edge functions, >= 0 inside
        if c[0] >= 0.0 and c[1] >= 0.0 and c[2] >= 0.0:
            # 1/z is affine in screen space; the barycentric weight of a vertex is the
            # (doubled) area opposite it over the (doubled) face area
            iz = inv_area2[f] * wp.dot(wp.vec3(c[1], c[2], c[0]), inv_z[f])
            # ties (a centre on a shared edge) go to the lower face id: on GPUs the tile
            # lists are filled in atomic order, and the output must not depend on it
            if iz > best_iz or (iz == best_iz and best_f >= 0 and f < best_f):
                best_iz = iz
                best_f = f
    face_id[pix] = best_f
    if best_f >= 0:
        depth[pix] = 1.0 / best_iz
        normal[pix] = face_normal[best_f]
    else:
        depth[pix] = 0.0
        normal[pix] = wp.vec3(0.0, 0.0, 0.0)


@wp.func
def _crossing(
    p: wp.vec2,
    d: wp.vec2,
    a: wp.vec2,
    b: wp.vec2,
):
    # Parameter s in [0, 1] where segment p -> p + d crosses segment a -> b, or -1.
    e = b - a
    den = _cross2(d, e)
    if den == 0.0:
        return float(-1.0)
    ap = a - p
    s = _cross2(ap, e) / den
    t = _cross2(ap, d) / den
    if s < 0.0 or s > 1.0 or t < 0.0 or t > 1.0:
        return float(-1.0)
    return s


@wp.kernel(enable_backward=False)
def antialias_kernel(
    tile_offsets: wp.array(dtype=wp.int32),  # [T]
    tile_counts: wp.array(dtype=wp.int32),  # [T]
    tile_faces: wp.array(dtype=wp.int32),  # [P]
    p0: wp.array(dtype=wp.vec2),
    p1: wp.array(dtype=wp.vec2),
    p2: wp.array(dtype=wp.vec2),
    edge_len: wp.array(dtype=wp.vec3),
    contour: wp.array(dtype=wp.int32),
    face_id: wp.array(dtype=wp.int32),  # [H*W] from raster_kernel
    width: int,
    height: int,
    tile_size: int,
    tiles_x: int,
    row_offset: int,  # first image row of this launch
    alpha: wp.array(dtype=float),  # [H*W] out
    winner: wp.array(dtype=wp.int32),  # [H*W] out: 4 f + k of the edge setting alpha, or -1
):
    # Silhouette anti-aliasing. Between two 4-neighbour pixel centres of which exactly one is
    # covered, the silhouette is the contour edge crossing their segment nearest the
    # uncovered centre. A covered pixel gets min(1, 0.5 + d), an uncovered one
    # max(0, 0.5 - d), d the distance of its centre to that edge's line: a one-pixel box
    # filter across the silhouette. Every other pixel keeps its hard coverage.
    py, px = wp.tid()
    py = py + row_offset
    pix = py * width + px
    inside = int(0)
    if face_id[pix] >= 0:
        inside = 1
    n_diff = int(0)
    for j in range(4):
        qx = px
        qy = py
        if j == 0:
            qx = px + 1
        elif j == 1:
            qx = px - 1
        elif j == 2:
            qy = py + 1
        else:
            qy = py - 1
        if qx >= 0 and qx < width and qy >= 0 and qy < height:
            q_in = int(0)
            if face_id[qy * width + qx] >= 0:
                q_in = 1
            if q_in != inside:
                n_diff += 1
    base = float(inside)
    if n_diff == 0:
        alpha[pix] = base
        winner[pix] = -1
        return
    p = wp.vec2(float(px) + 0.5, float(py) + 0.5)
    tile = (py // tile_size) * tiles_x + px // tile_size
    start = tile_offsets[tile]
    end = start + tile_counts[tile]
    result = base
    result_w = int(-1)
    for j in range(4):
        qx = px
        qy = py
        d = wp.vec2(0.0, 0.0)
        if j == 0:
            qx = px + 1
            d = wp.vec2(1.0, 0.0)
        elif j == 1:
            qx = px - 1
            d = wp.vec2(-1.0, 0.0)
        elif j == 2:
            qy = py + 1
            d = wp.vec2(0.0, 1.0)
        else:
            qy = py - 1
            d = wp.vec2(0.0, -1.0)
        if qx < 0 or qx >= width or qy < 0 or qy >= height:
            continue
        q_in = int(0)
        if face_id[qy * width + qx] >= 0:
            q_in = 1
        if q_in == inside:
            continue
        # nearest crossing to the uncovered end: largest s if p is covered, else smallest
        best_s = float(-1.0)
        if inside == 0:
            best_s = float(2.0)
        best_code = int(-1)
        best_sd = float(0.0)
        for i in range(start, end):
            f = tile_faces[i]
            m = contour[f]
            if m == 0:
                continue
            for k in range(3):
                if (m & (1 << k)) != 0:
                    a = p0[f]
                    b = p1[f]
                    if k == 1:
                        a = p1[f]
                        b = p2[f]
                    elif k == 2:
                        a = p2[f]
                        b = p0[f]
                    s = _crossing(p, d, a, b)
                    if s >= 0.0:
                        better = int(0)
                        if inside == 1 and s > best_s:
                            better = 1
                        if inside == 0 and s < best_s:
                            better = 1
                        if s == best_s and f * 4 + k < best_code:  # order-independent ties
                            better = 1
                        if better != 0:
                            best_s = s
                            best_code = f * 4 + k
                            best_sd = -_cross2(b - a, p - a) / edge_len[f][k]
        if best_code >= 0:
            v = wp.clamp(AA_BAND_PX + best_sd, 0.0, 1.0)
            if inside == 1:
                if v < result:
                    result = v
                    result_w = best_code
            else:
                if v > result:
                    result = v
                    result_w = best_code
    alpha[pix] = result
    if result > 0.0 and result < 1.0:
        winner[pix] = result_w
    else:
        winner[pix] = -1


@wp.kernel(enable_backward=False)
def raster_backward_kernel(
    faces: wp.array(dtype=wp.vec3i),  # [F]
    uv: wp.array(dtype=wp.vec2),  # [V]
    winner: wp.array(dtype=wp.int32),  # [H*W]
    face_id: wp.array(dtype=wp.int32),  # [H*W]
    grad_alpha: wp.array(dtype=float),  # [H*W]
    grad_normal: wp.array(dtype=wp.vec3),  # [H*W]
    width: int,
    row_offset: int,  # first image row of this launch
    grad_uv: wp.array(dtype=wp.vec2),  # [V] accumulated
    grad_face_normal: wp.array(dtype=wp.vec3),  # [F] accumulated
):
    py, px = wp.tid()
    py = py + row_offset
    pix = py * width + px
    w = winner[pix]
    if w >= 0:
        g = grad_alpha[pix]
        if g != 0.0:
            f = w // 4
            k = w - 4 * f
            tri = faces[f]
            ia = tri[k]
            ib = tri[(k + 1) % 3]
            a = uv[ia]
            b = uv[ib]
            p = wp.vec2(float(px) + 0.5, float(py) + 0.5)
            e = b - a
            r = p - a
            L = wp.length(e)
            cr = _cross2(e, r)
            # sd = -cross(e, r) / |e|, alpha = 0.5 + sd on the unsaturated ramp
            dc_db = wp.vec2(r[1], -r[0])
            dc_da = wp.vec2(e[1] - r[1], r[0] - e[0])
            dL_db = e / L
            s = cr / (L * L)
            gsd_a = -dc_da / L - dL_db * s
            gsd_b = -dc_db / L + dL_db * s
            wp.atomic_add(grad_uv, ia, gsd_a * g)
            wp.atomic_add(grad_uv, ib, gsd_b * g)
    f = face_id[pix]
    if f >= 0:
        wp.atomic_add(grad_face_normal, f, grad_normal[pix])


@wp.kernel(enable_backward=False)
def face_normal_backward_kernel(
    faces: wp.array(dtype=wp.vec3i),  # [F]
    x: wp.array(dtype=wp.vec3),  # [V] world
    grad_face_normal: wp.array(dtype=wp.vec3),  # [F]
    grad_x: wp.array(dtype=wp.vec3),  # [V] accumulated
):
    f = wp.tid()
    g = grad_face_normal[f]
    if g[0] == 0.0 and g[1] == 0.0 and g[2] == 0.0:
        return
    tri = faces[f]
    x0 = x[tri[0]]
    e1 = x[tri[1]] - x0
    e2 = x[tri[2]] - x0
    m = wp.cross(e1, e2)
    lm = wp.length(m)
    if lm <= 0.0:
        return
    n = m / lm
    gm = (g - n * wp.dot(n, g)) / lm  # through normalize
    g1 = wp.cross(e2, gm)  # through m = e1 x e2
    g2 = wp.cross(gm, e1)
    wp.atomic_add(grad_x, tri[1], g1)
    wp.atomic_add(grad_x, tri[2], g2)
    wp.atomic_sub(grad_x, tri[0], g1 + g2)


@wp.kernel(enable_backward=False)
def project_backward_kernel(
    pc: wp.array(dtype=wp.vec3),  # [V] camera
    R: wp.mat33,
    K: wp.mat33,
    grad_uv: wp.array(dtype=wp.vec2),  # [V]
    grad_x: wp.array(dtype=wp.vec3),  # [V] accumulated
):
    i = wp.tid()
    g = grad_uv[i]
    if g[0] == 0.0 and g[1] == 0.0:
        return
    q = K * pc[i]
    iz = 1.0 / q[2]
    gq = wp.vec3(g[0] * iz, g[1] * iz, -(g[0] * q[0] + g[1] * q[1]) * iz * iz)
    grad_x[i] = grad_x[i] + wp.transpose(R) * (wp.transpose(K) * gq)
