"""Warp kernels of the 2D-Gaussian surfel rasteriser (method.md §3).

One code path for CPU and CUDA. The pipeline, launched by ``holowarp.ops.surfels``:

1. :func:`project_surfels` (differentiable by Warp's autodiff, computed in float64 and
   rounded once): each surfel, given by its centre, two scales and a quaternion, becomes the
   splat-to-screen transform of 2DGS (Huang et al. 2024) in a centre-relative form:

   ``H = K [t_u | t_v | p]``                 (rows H0, H1, H2; t_u = s_u R e_x, t_v = s_v R e_y,
                                             p the centre, all in camera coordinates)
   ``m = (H0[2] / H2[2], H1[2] / H2[2])``    (projected centre, pixels)
   ``E0 = m_x H2 - H0``, ``E1 = m_y H2 - H1`` (their third components are exactly 0)
   ``(P, Q, D)``                             (c2 = P dx + Q dy + D, below)

   A pixel centre ``(x, y)`` with offset ``(dx, dy) = (x, y) - m`` defines two planes
   ``a = dx H2 + E0`` and ``b = dy H2 + E1`` (homogeneous, in splat-local ``(u, v, 1)``);
   their intersection ``c = a x b`` is the ray-splat intersection ``(u, v) = (c0, c1) / c2``,
   expanded by hand so that its cancelling ``dx dy`` terms never appear. Together with the
   centre handed on as ``floor(m)`` plus a float64-accurate fraction, this keeps a float32
   evaluation within ~1e-6 of float64 even for thin, nearly edge-on splats, where the plain
   ``x H2 - H0`` form (large pixel coordinates times camera depth) loses about 4 digits.
2. :func:`surfel_bounds`: the conservative pixel box of every pixel where the surfel can reach
   ``alpha >= 1/255`` (the exact box of the projected disk ``u^2 + v^2 <= r^2`` from its dual
   conic, united with the low-pass circle, plus a small rounding margin).
3. Binning. The image is cut into 16x16 tiles (method.md §3), and each tile into sixteen 4x4
   pixel blocks; a list key is ``tile * 16 + block``, so keys sort tile-major and a tile's
   list is the concatenation of its blocks' lists. Surfels are first sorted by the camera
   depth of their centre; :func:`emit_intersections` writes one (key, depth rank) pair per
   block the box touches, in depth order, and a *stable* radix sort on the key keeps every
   list front to back. :func:`block_ranges` finds each list. The 4x4 split matters on the
   CPU, where Warp runs threads one after another: a pixel walks only the surfels whose box
   touches its block instead of its whole tile (in the benchmark scene, 2.5x the (pixel,
   surfel) pairs inside the boxes instead of 16x). A list entry packs the depth rank with
   the box clipped to its block (``rank << 8``, then 2 bits each for x0, x1, y0, y1 in
   block-local pixels), so the per-pixel loops reject a surfel whose box misses the pixel
   from the list they read in order, without fetching anything per surfel: 43% of the
   entries a pixel walks in the pipeline bench's topology views, and the forward and
   backward kernels took 9% and 6% less time than with the box fetched per surfel.
   That box is not the bounding box's corner of the block but the box of the block's pixels
   the splat's cut-off ellipse may reach, found row by row (:func:`_row_span`, exact in
   float64, with slack), and a block it reaches nowhere is filed under one extra key after
   every list: the bounding box of an oblique, thin splat holds many blocks and corners
   its ellipse misses (round splats keep their boxes, :data:`_SPAN_FILL`). The images and
   gradients are bit for bit those of the plain boxes (every pixel left out is one the
   loops skip by the cut-off). On the README job's scenes at 128² (bob's trained stage-0
   surfels; the topology phase's tets at its start and at step 750; the tets after the mesh
   blocks; one thread), the kernels' time per view fell by 14%, 16%, 14% and 9% with it.
   :func:`pack_splats` stores, per depth rank, everything compositing reads in one 96-byte
   record, so the per-pixel loops read memory in increasing order.
4. :func:`rasterize_forward`: one thread per pixel composites its list front to back with the
   rules below and stores, per pixel, the final transmittance, the end of its list and its
   median contributor, so that
5. :func:`rasterize_backward` (hand-written: the compositing loop is data dependent, Warp's
   tape cannot replay it) walks the same list back to front, recovering each transmittance
   by division as 3DGS does, and accumulates per-surfel gradients with ``atomic_add``.

Both per-pixel kernels take a ``tid_offset``, so a driver may launch them on slices of the
tiles (on several CPU threads at once, each backward slice into its own gradient buffers).

Per-pixel rules (method.md §3, 2DGS):
    rho   = min(u^2 + v^2, 2 |pixel - m|^2)          (object-space Gaussian, screen low-pass)
    alpha = min(ALPHA_MAX, o exp(-rho / 2)),  skipped when alpha < ALPHA_MIN
    stop before the transmittance would fall below T_MIN (that surfel is not composited)
    z     = H2 . (u, v, 1) (camera depth of the ray-splat intersection) where the object-space
            term is active, else the centre's depth (the 2DGS rule for edge-on splats).
Outputs per pixel, with w_k = alpha_k T_k: colour sum w c + T bg, opacity sum w, normal sum w n,
depth sum w z, median depth (z of the last contributor entered with T > 0.5, as 2DGS), and the
2DGS distortion sum_k w_k sum_{j<k} w_j (z_k - z_j)^2 on camera depth.

No torch import here (layout rule); arrays are plain Warp arrays.
"""

from __future__ import annotations

import warp as wp

__all__ = [
    "TILE_SIZE",
    "BLOCK_SIZE",
    "BLOCKS_PER_TILE",
    "ALPHA_MIN",
    "ALPHA_MAX",
    "T_MIN",
    "MEDIAN_T",
    "NEAR_PLANE",
    "MAX_SURFELS",
    "splat_record",
    "quat_wxyz_to_matrix",
    "project_surfels",
    "surfel_bounds",
    "gather_counts",
    "emit_intersections",
    "block_ranges",
    "pack_splats",
    "rasterize_forward",
    "rasterize_backward",
]

#: Tile edge in pixels (method.md §3).
TILE_SIZE = 16
#: Edge of the pixel blocks a tile's list is split into (see module docstring, step 3).
BLOCK_SIZE = 4
BLOCKS_PER_TILE = (TILE_SIZE // BLOCK_SIZE) ** 2
#: Contributions below this alpha are skipped (method.md §3).
ALPHA_MIN = 1.0 / 255.0
#: Alpha is capped here (method.md §3).
ALPHA_MAX = 0.99
#: Compositing stops before the transmittance would drop below this (method.md §3).
T_MIN = 1e-4
#: The median contributor is the last one entered while the transmittance is above this (2DGS).
MEDIAN_T = 0.5
#: A list entry is ``depth rank << 8 | block-local box`` (:func:`emit_intersections`), so one
#: call takes at most 2^23 surfels.
MAX_SURFELS = (1 << 23) - 1
#: Surfels whose cut-off disk reaches closer to the camera than this (metres) are culled.
NEAR_PLANE = 0.01

_TILE = wp.constant(TILE_SIZE)
_BLOCK = wp.constant(BLOCK_SIZE)
_BLOCKS_X = wp.constant(TILE_SIZE // BLOCK_SIZE)  # blocks per tile row
_ALPHA_MIN = wp.constant(ALPHA_MIN)
_ALPHA_MAX = wp.constant(ALPHA_MAX)
_T_MIN = wp.constant(T_MIN)
_MEDIAN_T = wp.constant(MEDIAN_T)
_BIG = wp.constant(1.0e30)
#: Margin (pixels, plus a relative part) around each box: float32 rounding of the box must
#: never cut a pixel where alpha >= ALPHA_MIN, or the kernels would disagree with the dense
#: reference. The box's own rounding error is ~1e-6 of its size.
_BOX_MARGIN = wp.constant(1.0e-3)
_BOX_MARGIN_REL = wp.constant(1.0e-4)
#: Slack on the cut-off r2 when binning leaves out the pixels of a block that a surfel cannot
#: reach (:func:`emit_intersections`): relative and absolute, far above the float32 rounding
#: of the compositing loops' own evaluation, which the binning's float64 one must contain.
_CUT_SLACK = wp.constant(1.0 + 1.0e-4)
_CUT_SLACK_ABS = wp.constant(1.0e-4)
#: A splat's box is shrunk row by row only when its cut-off ellipse fills less than this
#: share of it (:func:`emit_intersections`). Measured on the README job's scenes (bob's
#: stage-0 surfels; the topology phase's tets at its start and at step 750; the tets after
#: the mesh blocks), 20 views at 128², one thread, forward + backward + binning, against
#: no shrinking: 0.3 -> -13/-13/-14/-8%, 0.5 -> -13/-16/-14/-9%, 0.7 -> -12/-14/-14/-8%,
#: every splat -> -9/-9/-14/-8%.
_SPAN_FILL = wp.constant(0.5)
#: Margin (pixels) of a row's reachable columns (:func:`_row_span`).
_SPAN_TOL = wp.constant(1.0e-3)

#: Everything the compositing loop reads about one surfel, contiguous: (floor(m_x), floor(m_y),
#: frac(m_x), frac(m_y), H2[0..2], E0[0..1], E1[0..1], P, Q, D, opacity, colour[0..2],
#: normal[0..2], rho cut-off 2 ln(255 o), 2 unused). The centre is split so that
#: (x + 0.5 - floor(m)) is exact and the pixel offset keeps float32's full relative precision.
splat_record = wp.types.vector(length=24, dtype=wp.float32)
_vec5 = wp.types.vector(length=5, dtype=wp.float32)
_vec6d = wp.types.vector(length=6, dtype=wp.float64)


@wp.func
def quat_wxyz_to_matrix(q: wp.vec4d):
    """Rotation matrix of a (not necessarily unit) wxyz quaternion, in float64."""
    qn = q / wp.length(q)
    w = qn[0]
    x = qn[1]
    y = qn[2]
    z = qn[3]
    one = wp.float64(1.0)
    two = wp.float64(2.0)
    return wp.mat33d(
        one - two * (y * y + z * z), two * (x * y - w * z), two * (x * z + w * y),
        two * (x * y + w * z), one - two * (x * x + z * z), two * (y * z - w * x),
        two * (x * z - w * y), two * (y * z + w * x), one - two * (x * x + y * y),
    )  # fmt: skip


@wp.kernel
def project_surfels(
    means: wp.array(dtype=wp.vec3),  # [N] world
    quats: wp.array(dtype=wp.vec4),  # [N] wxyz
    scales: wp.array(dtype=wp.vec2),  # [N] linear, world units
    viewmat: wp.mat44d,  # world-to-camera, OpenCV
    K: wp.mat33d,  # [[fx, s, cx], [0, fy, cy], [0, 0, 1]]
    h2: wp.array(dtype=wp.vec3),  # [N] (t_u.z, t_v.z, p.z)
    e0: wp.array(dtype=wp.vec2),  # [N] first two entries of m_x H2 - H0
    e1: wp.array(dtype=wp.vec2),  # [N] first two entries of m_y H2 - H1
    pqd: wp.array(dtype=wp.vec3),  # [N] coefficients of c2 = P dx + Q dy + D
    centers: wp.array(dtype=wp.vec2),  # [N] projected centre m, pixels
    center_frac: wp.array(dtype=wp.vec2),  # [N] m - floor(m), from the float64 m
    normals: wp.array(dtype=wp.vec3),  # [N] world normal, flipped to face the camera
):
    # Computed in float64 and rounded once: a thin splat (edge-on, or with one small scale)
    # changes alpha by more than 1e-5 when its centre moves by one float32 ulp of a pixel
    # coordinate (~4e-6 px at 50 px), so m is also handed on split as floor(m) + fraction.
    i = wp.tid()
    R = quat_wxyz_to_matrix(wp.vec4d(quats[i]))
    Rcw = wp.mat33d(
        viewmat[0, 0], viewmat[0, 1], viewmat[0, 2],
        viewmat[1, 0], viewmat[1, 1], viewmat[1, 2],
        viewmat[2, 0], viewmat[2, 1], viewmat[2, 2],
    )  # fmt: skip
    tcw = wp.vec3d(viewmat[0, 3], viewmat[1, 3], viewmat[2, 3])
    s = wp.vec2d(scales[i])
    p = Rcw @ wp.vec3d(means[i]) + tcw
    tu = Rcw @ wp.vec3d(R[0, 0], R[1, 0], R[2, 0]) * s[0]
    tv = Rcw @ wp.vec3d(R[0, 1], R[1, 1], R[2, 1]) * s[1]
    nw = wp.vec3d(R[0, 2], R[1, 2], R[2, 2])
    fx = K[0, 0]
    sk = K[0, 1]
    fy = K[1, 1]
    pz = p[2]
    if pz == wp.float64(0.0):
        # Undefined projection; surfel_bounds culls it (pz <= near).
        pz = wp.float64(1.0)
    # Everything below is written in camera-space vectors so that no term is a difference of
    # large pixel-scaled quantities: g(t) = t.z p / p.z - t, E0 = (K g)_x, E1 = (K g)_y, and
    # with n' = t_u x t_v the plane-intersection denominator is
    # c2 = fy n'.x dx + (fx n'.y - s n'.x) dy + fx fy (p . n') / p.z.
    gu = p * (tu[2] / pz) - tu
    gv = p * (tv[2] / pz) - tv
    nn = wp.cross(tu, tv)
    h2[i] = wp.vec3(wp.vec3d(tu[2], tv[2], p[2]))
    e0[i] = wp.vec2(wp.vec2d(fx * gu[0] + sk * gu[1], fx * gv[0] + sk * gv[1]))
    e1[i] = wp.vec2(wp.vec2d(fy * gu[1], fy * gv[1]))
    pqd[i] = wp.vec3(wp.vec3d(fy * nn[0], fx * nn[1] - sk * nn[0], fx * fy * wp.dot(p, nn) / pz))
    m = wp.vec2d(fx * p[0] / pz + sk * p[1] / pz + K[0, 2], fy * p[1] / pz + K[1, 2])
    centers[i] = wp.vec2(m)
    center_frac[i] = wp.vec2(wp.vec2d(m[0] - wp.floor(m[0]), m[1] - wp.floor(m[1])))
    # Face the camera: n . (camera - centre) > 0, i.e. (R_cw n) . p < 0 in camera space.
    if wp.dot(Rcw @ nw, p) > wp.float64(0.0):
        nw = -nw
    normals[i] = wp.vec3(nw)


@wp.kernel(enable_backward=False)
def surfel_bounds(
    h2: wp.array(dtype=wp.vec3),
    e0: wp.array(dtype=wp.vec2),
    e1: wp.array(dtype=wp.vec2),
    centers: wp.array(dtype=wp.vec2),
    opacities: wp.array(dtype=float),
    near: float,
    width: int,
    height: int,
    boxes: wp.array(dtype=wp.vec4i),  # [N] inclusive pixel box (x0, y0, x1, y1); x1 < x0 if culled
    counts: wp.array(dtype=wp.int32),  # [N] number of pixel blocks the box touches
    depths: wp.array(dtype=float),  # [N] camera depth of the centre (sort key)
):
    i = wp.tid()
    boxes[i] = wp.vec4i(0, 0, -1, -1)
    counts[i] = 0
    depths[i] = _BIG
    o = opacities[i]
    if not (o * 255.0 >= 1.0):  # also catches NaN
        return
    # alpha >= ALPHA_MIN  <=>  rho <= r2 (the cap only lowers alpha).
    r2 = 2.0 * wp.log(o * 255.0)
    H2 = h2[i]
    pz = H2[2]
    tz2 = H2[0] * H2[0] + H2[1] * H2[1]
    # The cut-off disk must lie wholly beyond the near plane: its depth spans pz +- r |tz|.
    if pz <= near or (pz - near) * (pz - near) <= r2 * tz2:
        return
    c22 = r2 * tz2 - pz * pz  # < 0 here
    m = centers[i]
    E0 = e0[i]
    E1 = e1[i]
    # Box of the projected disk relative to m, from the dual conic H diag(r2, r2, -1) H^T
    # with rows H0 - m_x H2 = -E0, H1 - m_y H2 = -E1.
    cx = -r2 * (E0[0] * H2[0] + E0[1] * H2[1]) / c22
    cy = -r2 * (E1[0] * H2[0] + E1[1] * H2[1]) / c22
    hx = wp.sqrt(wp.max(cx * cx - r2 * (E0[0] * E0[0] + E0[1] * E0[1]) / c22, 0.0))
    hy = wp.sqrt(wp.max(cy * cy - r2 * (E1[0] * E1[0] + E1[1] * E1[1]) / c22, 0.0))
    r2d = wp.sqrt(0.5 * r2)  # low-pass term: 2 |d|^2 <= r2
    xmin = m[0] + wp.min(cx - hx, -r2d)
    xmax = m[0] + wp.max(cx + hx, r2d)
    ymin = m[1] + wp.min(cy - hy, -r2d)
    ymax = m[1] + wp.max(cy + hy, r2d)
    # Pixel column j has its centre at j + 0.5, so the columns inside [xmin, xmax] run from
    # ceil(xmin - 0.5) to floor(xmax - 0.5). Clamp before int conversion (huge boxes).
    tx = _BOX_MARGIN + _BOX_MARGIN_REL * (xmax - xmin)
    ty = _BOX_MARGIN + _BOX_MARGIN_REL * (ymax - ymin)
    lim = float(4 * (width + height) + 64)
    x0 = wp.max(int(wp.ceil(wp.clamp(xmin - 0.5 - tx, -lim, lim))), 0)
    x1 = wp.min(int(wp.floor(wp.clamp(xmax - 0.5 + tx, -lim, lim))), width - 1)
    y0 = wp.max(int(wp.ceil(wp.clamp(ymin - 0.5 - ty, -lim, lim))), 0)
    y1 = wp.min(int(wp.floor(wp.clamp(ymax - 0.5 + ty, -lim, lim))), height - 1)
    if x1 < x0 or y1 < y0:
        return
    boxes[i] = wp.vec4i(x0, y0, x1, y1)
    counts[i] = (x1 // _BLOCK - x0 // _BLOCK + 1) * (y1 // _BLOCK - y0 // _BLOCK + 1)
    depths[i] = pz


@wp.kernel(enable_backward=False)
def gather_counts(
    order: wp.array(dtype=wp.int32),  # [N] surfel ids sorted by depth
    counts: wp.array(dtype=wp.int32),  # [N] per surfel
    sorted_counts: wp.array(dtype=wp.int32),  # [N] per depth rank
):
    j = wp.tid()
    sorted_counts[j] = counts[order[j]]


@wp.func
def _block_key(bx: int, by: int, tiles_x: int):
    """List key of pixel block (bx, by): tile-major, then block within the tile."""
    tile = (by // _BLOCKS_X) * tiles_x + bx // _BLOCKS_X
    return tile * (_BLOCKS_X * _BLOCKS_X) + (by % _BLOCKS_X) * _BLOCKS_X + bx % _BLOCKS_X


@wp.func
def _row_conic(r: splat_record, lim: float):
    """The coefficients of :func:`_row_span`'s quadratic as polynomials in the row offset dy,
    in float64: (qa, qb1, qb0, qc2, qc1, qc0) with qb = qb1 dy + qb0, qc = qc2 dy^2 + qc1 dy
    + qc0.

    Along a row, c0, c1 and c2 (:func:`_splat_at`) are affine in dx: c0 = pz E0y dy - pz E1y
    dx, c1 = pz E1x dx - pz E0x dy, c2 = P dx + (Q dy + D). So u^2 + v^2 <= lim is the
    quadratic qa dx^2 + qb dx + qc = c0^2 + c1^2 - lim c2^2 <= 0; float64, as its terms cancel
    for thin, oblique splats."""
    pz = wp.float64(r[6])
    e0x = wp.float64(r[7])
    e0y = wp.float64(r[8])
    b0 = -pz * wp.float64(r[10])
    b1 = pz * wp.float64(r[9])
    b2 = wp.float64(r[11])
    q = wp.float64(r[12])
    d = wp.float64(r[13])
    L = wp.float64(lim)
    two = wp.float64(2.0)
    return _vec6d(
        b0 * b0 + b1 * b1 - L * b2 * b2,
        two * (pz * e0y * b0 - pz * e0x * b1 - L * q * b2),
        -two * L * d * b2,
        pz * pz * (e0x * e0x + e0y * e0y) - L * q * q,
        -two * L * q * d,
        -L * d * d,
    )


@wp.func
def _row_span(r: splat_record, conic: _vec6d, y: int, lim: float):
    """(first, last) pixel column of row ``y`` where the splat's rho = min(u^2 + v^2,
    2 |d|^2) may reach the cut-off ``lim``: a superset of the columns the compositing loops
    composite (last < first: none). ``conic`` is :func:`_row_conic`'s.

    The quadratic's leading coefficient is > 0 for a disk wholly in front of the camera (else
    the whole row counts); the low-pass disk adds |dx| <= sqrt(lim / 2 - dy^2). The two
    intervals are joined into their hull; columns within _SPAN_TOL pixels of it count."""
    dy = wp.float64((float(y) + 0.5 - r[1]) - r[3])  # the compositing loops' own offset
    qa = conic[0]
    qb = conic[1] * dy + conic[2]
    qc = (conic[3] * dy + conic[4]) * dy + conic[5]
    far = wp.float64(1.0e7)
    lo = far
    hi = -far
    if qa > wp.float64(0.0):
        disc = qb * qb - wp.float64(4.0) * qa * qc
        if disc >= wp.float64(0.0):
            sq = wp.sqrt(disc)
            inv = wp.float64(0.5) / qa
            lo = (-qb - sq) * inv
            hi = (-qb + sq) * inv
    else:
        lo = -far
        hi = far
    w2 = wp.float64(0.5 * lim) - dy * dy
    if w2 >= wp.float64(0.0):
        w = wp.sqrt(w2)
        lo = wp.min(lo, -w)
        hi = wp.max(hi, w)
    # dx = (x + 0.5 - floor(m)) - frac(m)  <=>  x = dx + floor(m) + frac(m) - 0.5.
    shift = wp.float64(r[0]) + wp.float64(r[2]) - wp.float64(0.5)
    tol = wp.float64(_SPAN_TOL)
    x0 = wp.ceil(wp.clamp(lo - tol + shift, -far, far))
    x1 = wp.floor(wp.clamp(hi + tol + shift, -far, far))
    return wp.vec2i(int(x0), int(x1))


@wp.kernel(enable_backward=False)
def emit_intersections(
    order: wp.array(dtype=wp.int32),  # [N] surfel ids sorted by depth
    boxes: wp.array(dtype=wp.vec4i),
    offsets: wp.array(dtype=wp.int32),  # [N] exclusive scan of sorted counts
    sorted_counts: wp.array(dtype=wp.int32),
    ranked_splats: wp.array(dtype=splat_record),  # [N] by depth rank (pack_splats)
    tiles_x: int,
    empty_key: int,  # key of a block the surfel reaches at no pixel (sorts after every list)
    rank_offset: int,  # first depth rank of this launch (a launch may cover a slice of them)
    keys: wp.array(dtype=wp.int32),  # [>= 2 * total] list key of each pair
    ranks: wp.array(dtype=wp.int32),  # [>= 2 * total] list entry of each pair (see _outside)
):
    j = wp.tid() + rank_offset
    if sorted_counts[j] == 0:
        return
    b = boxes[order[j]]
    r = ranked_splats[j]
    lim = r[21] * _CUT_SLACK + _CUT_SLACK_ABS
    conic = _row_conic(r, lim)
    off = offsets[j]
    # Spans pay for a splat whose ellipse fills little of its box (thin, oblique); a round
    # one only loses its box's corners, which cost more rows to find than they save.
    # Area of the ellipse qa dx^2 + qb1 dx dy + qc2 dy^2 + qb0 dx + qc1 dy + qc0 <= 0:
    # 2 pi |det M| / (4 qa qc2 - qb1^2)^(3/2), M its 3x3 symmetric matrix.
    disc = wp.float64(4.0) * conic[0] * conic[3] - conic[1] * conic[1]
    spans = True
    if disc > wp.float64(0.0):
        h = wp.float64(0.5)
        det = (conic[0] * (conic[3] * conic[5] - h * conic[4] * h * conic[4])
               - h * conic[1] * (h * conic[1] * conic[5] - h * conic[4] * h * conic[2])
               + h * conic[2] * (h * conic[1] * h * conic[4] - conic[3] * h * conic[2]))
        area = wp.float64(2.0 * 3.141592653589793) * wp.abs(det) / (disc * wp.sqrt(disc))
        box = wp.float64((b[2] - b[0] + 1) * (b[3] - b[1] + 1))
        spans = area < wp.float64(_SPAN_FILL) * box
    for by in range(b[1] // _BLOCK, b[3] // _BLOCK + 1):
        ly0 = wp.max(b[1] - by * _BLOCK, 0)
        ly1 = wp.min(b[3] - by * _BLOCK, _BLOCK - 1)
        first = wp.vec4i(0)
        last = wp.vec4i(-1)
        # Columns every row of this block row reaches (inner) and some row reaches (outer).
        inner0 = int(-(1 << 30))
        inner1 = int(1 << 30)
        outer0 = int(1 << 30)
        outer1 = int(-(1 << 30))
        if spans:
            for ly in range(ly0, ly1 + 1):
                span = _row_span(r, conic, by * _BLOCK + ly, lim)
                first[ly] = span[0]
                last[ly] = span[1]
                inner0 = wp.max(inner0, span[0])
                inner1 = wp.min(inner1, span[1])
                outer0 = wp.min(outer0, span[0])
                outer1 = wp.max(outer1, span[1])
        for bx in range(b[0] // _BLOCK, b[2] // _BLOCK + 1):
            lx0 = wp.max(b[0] - bx * _BLOCK, 0)
            lx1 = wp.min(b[2] - bx * _BLOCK, _BLOCK - 1)
            # The box clipped to the block, shrunk to the pixels the splat may reach: an
            # oblique, thin splat's box holds many blocks and corners that its ellipse misses.
            # Blocks wholly inside every row's span keep it, blocks outside all spans go;
            # only the blocks the ellipse's outline crosses are looked at row by row.
            x0 = bx * _BLOCK + lx0
            x1 = bx * _BLOCK + lx1
            tx0 = lx0
            tx1 = lx1
            ty0 = ly0
            ty1 = ly1
            if spans:
                if x1 < outer0 or x0 > outer1:
                    tx1 = -1
                elif x0 < inner0 or x1 > inner1:
                    tx0 = int(_BLOCK)
                    tx1 = int(-1)
                    ty0 = int(_BLOCK)
                    ty1 = int(-1)
                    for ly in range(ly0, ly1 + 1):
                        c0 = wp.max(first[ly] - bx * _BLOCK, lx0)
                        c1 = wp.min(last[ly] - bx * _BLOCK, lx1)
                        if c0 <= c1:
                            tx0 = wp.min(tx0, c0)
                            tx1 = wp.max(tx1, c1)
                            ty0 = wp.min(ty0, ly)
                            ty1 = wp.max(ty1, ly)
            if tx1 < 0:
                keys[off] = empty_key
                ranks[off] = 0
            else:
                keys[off] = _block_key(bx, by, tiles_x)
                ranks[off] = (j << 8) | tx0 | (tx1 << 2) | (ty0 << 4) | (ty1 << 6)
            off += 1


@wp.kernel(enable_backward=False)
def block_ranges(
    keys: wp.array(dtype=wp.int32),  # sorted
    count: int,
    list_start: wp.array(dtype=wp.int32),  # [num_keys + 1], zero-initialised (the last: empty blocks)
    list_end: wp.array(dtype=wp.int32),  # [num_keys + 1], zero-initialised
):
    k = wp.tid()
    t = keys[k]
    if k == 0:
        list_start[t] = 0
    elif keys[k - 1] != t:
        list_start[t] = k
    if k == count - 1:
        list_end[t] = count
    elif keys[k + 1] != t:
        list_end[t] = k + 1


@wp.kernel(enable_backward=False)
def pack_splats(
    order: wp.array(dtype=wp.int32),  # [N] surfel ids sorted by depth
    h2: wp.array(dtype=wp.vec3),
    e0: wp.array(dtype=wp.vec2),
    e1: wp.array(dtype=wp.vec2),
    pqd: wp.array(dtype=wp.vec3),
    centers: wp.array(dtype=wp.vec2),
    center_frac: wp.array(dtype=wp.vec2),
    normals: wp.array(dtype=wp.vec3),
    opacities: wp.array(dtype=float),
    colors: wp.array(dtype=wp.vec3),
    ranked_splats: wp.array(dtype=splat_record),  # [N] by depth rank
):
    j = wp.tid()
    i = order[j]
    m = centers[i]
    f = center_frac[i]
    # floor(m) of the float64 centre: m32 - frac is within an ulp of that integer.
    mi = wp.vec2(wp.round(m[0] - f[0]), wp.round(m[1] - f[1]))
    H2 = h2[i]
    E0 = e0[i]
    E1 = e1[i]
    c2 = pqd[i]
    c = colors[i]
    n = normals[i]
    ranked_splats[j] = splat_record(
        mi[0], mi[1], f[0], f[1], H2[0], H2[1], H2[2], E0[0], E0[1], E1[0], E1[1], c2[0], c2[1], c2[2],
        opacities[i], c[0], c[1], c[2], n[0], n[1], n[2], 2.0 * wp.log(opacities[i] * 255.0), 0.0, 0.0,
    )  # fmt: skip


@wp.func
def _pixel_of_thread(tid: int, width: int, tiles_x: int):
    """(x, y, list key) of a thread. Threads are ordered like the keys (tile-major, then
    block), so the threads that share a list run back to back."""
    per_tile = _TILE * _TILE
    tile = tid // per_tile
    local = tid - tile * per_tile
    block = local // (_BLOCK * _BLOCK)
    within = local - block * (_BLOCK * _BLOCK)
    x = (tile % tiles_x) * _TILE + (block % _BLOCKS_X) * _BLOCK + within % _BLOCK
    y = (tile // tiles_x) * _TILE + (block // _BLOCKS_X) * _BLOCK + within // _BLOCK
    return wp.vec3i(x, y, tile * (_BLOCKS_X * _BLOCKS_X) + block)


@wp.func
def _outside(lx: int, ly: int, entry: int):
    """Whether block-local pixel (lx, ly) lies outside the box packed in a list entry
    (:func:`emit_intersections`: bits 0-1 x0, 2-3 x1, 4-5 y0, 6-7 y1 of the box clipped to
    the block). Branch-free: any negative difference sets the sign bit of the OR."""
    return ((lx - (entry & 3)) | (((entry >> 2) & 3) - lx) | (ly - ((entry >> 4) & 3)) | (((entry >> 6) & 3) - ly)) < 0


@wp.func
def _splat_at(r: splat_record, dx: float, dy: float):
    """(rho, z, u, v, 1 if the object-space term is active else 0) of a splat at a pixel
    offset (dx, dy) from its centre; shared by forward and backward so both take the same
    branch and the same alpha.

    The intersection c = a x b of the planes a = dx H2 + E0, b = dy H2 + E1 is expanded by
    hand: its dx dy terms cancel exactly, so c0 = pz (dy E0y - dx E1y),
    c1 = pz (dx E1x - dy E0x), c2 = P dx + Q dy + D."""
    c0 = r[6] * (dy * r[8] - dx * r[10])
    c1 = r[6] * (dx * r[9] - dy * r[7])
    c2 = dx * r[11] + dy * r[12] + r[13]
    rho2d = 2.0 * (dx * dx + dy * dy)
    out = _vec5(rho2d, r[6], 0.0, 0.0, 0.0)
    if c2 != 0.0:
        inv = 1.0 / c2
        u = c0 * inv
        v = c1 * inv
        rho3d = u * u + v * v
        if rho3d <= rho2d:
            out = _vec5(rho3d, r[4] * u + r[5] * v + r[6], u, v, 1.0)
    return out


@wp.kernel(enable_backward=False)
def rasterize_forward(
    list_start: wp.array(dtype=wp.int32),  # [num_keys]
    list_end: wp.array(dtype=wp.int32),  # [num_keys]
    list_ranks: wp.array(dtype=wp.int32),  # [total] list entries: depth rank << 8 | block-local box
    ranked_splats: wp.array(dtype=splat_record),  # [N]
    background: wp.vec3,
    width: int,
    height: int,
    tiles_x: int,
    tid_offset: int,  # first thread of this launch (a launch may cover a slice of the tiles)
    out_rgb: wp.array(dtype=wp.vec3),  # [H*W]
    out_alpha: wp.array(dtype=float),  # [H*W]
    out_normal: wp.array(dtype=wp.vec3),  # [H*W]
    out_depth: wp.array(dtype=float),  # [H*W]
    out_median: wp.array(dtype=float),  # [H*W]
    out_dist: wp.array(dtype=float),  # [H*W]
    out_trans: wp.array(dtype=float),  # [H*W] final transmittance
    out_last: wp.array(dtype=wp.int32),  # [H*W] end (exclusive) of the composited list
    out_median_pos: wp.array(dtype=wp.int32),  # [H*W] list position of the median, -1 if none
    out_m2: wp.array(dtype=float),  # [H*W] sum w z^2 (for the distortion gradient)
):
    pxy = _pixel_of_thread(wp.tid() + tid_offset, width, tiles_x)
    x = pxy[0]
    y = pxy[1]
    if x >= width or y >= height:
        return
    pix = y * width + x
    start = list_start[pxy[2]]
    end = list_end[pxy[2]]
    px = float(x) + 0.5
    py = float(y) + 0.5

    T = float(1.0)
    rgb = wp.vec3(0.0)
    nrm = wp.vec3(0.0)
    acc_w = float(0.0)
    acc_wz = float(0.0)
    acc_wz2 = float(0.0)
    dist = float(0.0)
    median = float(0.0)
    median_pos = int(-1)
    last = start
    lx = x & (_BLOCK - 1)
    ly = y & (_BLOCK - 1)
    for k in range(start, end):
        entry = list_ranks[k]
        if _outside(lx, ly, entry):
            continue
        j = entry >> 8
        r = ranked_splats[j]
        e = _splat_at(r, (px - r[0]) - r[2], (py - r[1]) - r[3])
        if e[0] > r[21]:  # alpha < ALPHA_MIN for sure: skip the exp
            continue
        alpha = wp.min(_ALPHA_MAX, r[14] * wp.exp(-0.5 * e[0]))
        if alpha < _ALPHA_MIN:
            continue
        t_next = T * (1.0 - alpha)
        if t_next < _T_MIN:
            break
        z = e[1]
        w = alpha * T
        rgb += w * wp.vec3(r[15], r[16], r[17])
        nrm += w * wp.vec3(r[18], r[19], r[20])
        dist += w * (z * z * acc_w - 2.0 * z * acc_wz + acc_wz2)
        acc_w += w
        acc_wz += w * z
        acc_wz2 += w * z * z
        if T > _MEDIAN_T:
            median = z
            median_pos = k
        T = t_next
        last = k + 1

    out_rgb[pix] = rgb + T * background
    out_alpha[pix] = acc_w
    out_normal[pix] = nrm
    out_depth[pix] = acc_wz
    out_median[pix] = median
    out_dist[pix] = dist
    out_trans[pix] = T
    out_last[pix] = last
    out_median_pos[pix] = median_pos
    out_m2[pix] = acc_wz2


@wp.kernel(enable_backward=False)
def rasterize_backward(
    list_start: wp.array(dtype=wp.int32),
    list_ranks: wp.array(dtype=wp.int32),
    order: wp.array(dtype=wp.int32),  # [N] surfel id of each depth rank
    ranked_splats: wp.array(dtype=splat_record),
    background: wp.vec3,
    width: int,
    height: int,
    tiles_x: int,
    tid_offset: int,  # first thread of this launch (a launch may cover a slice of the tiles)
    out_alpha: wp.array(dtype=float),
    out_depth: wp.array(dtype=float),
    out_trans: wp.array(dtype=float),
    out_last: wp.array(dtype=wp.int32),
    out_median_pos: wp.array(dtype=wp.int32),
    out_m2: wp.array(dtype=float),
    g_rgb: wp.array(dtype=wp.vec3),  # [H*W] dL/d outputs
    g_alpha: wp.array(dtype=float),
    g_normal: wp.array(dtype=wp.vec3),
    g_depth: wp.array(dtype=float),
    g_median: wp.array(dtype=float),
    g_dist: wp.array(dtype=float),
    d_h2: wp.array(dtype=wp.vec3),  # [N] accumulated dL/d per-surfel quantities
    d_e0: wp.array(dtype=wp.vec2),
    d_e1: wp.array(dtype=wp.vec2),
    d_pqd: wp.array(dtype=wp.vec3),
    d_centers: wp.array(dtype=wp.vec2),
    d_normals: wp.array(dtype=wp.vec3),
    d_opacities: wp.array(dtype=float),
    d_colors: wp.array(dtype=wp.vec3),
):
    pxy = _pixel_of_thread(wp.tid() + tid_offset, width, tiles_x)
    x = pxy[0]
    y = pxy[1]
    if x >= width or y >= height:
        return
    pix = y * width + x
    start = list_start[pxy[2]]
    last = out_last[pix]
    px = float(x) + 0.5
    py = float(y) + 0.5

    dC = g_rgb[pix]
    dA = g_alpha[pix]
    dN = g_normal[pix]
    dD = g_depth[pix]
    dMed = g_median[pix]
    dDist = g_dist[pix]
    A = out_alpha[pix]
    D = out_depth[pix]
    M2 = out_m2[pix]
    median_pos = out_median_pos[pix]
    T = out_trans[pix]
    # S = sum over later contributors j of w_j dL/dw_j, plus the background's T_final dL/dT_final.
    S = T * wp.dot(dC, background)

    lx = x & (_BLOCK - 1)
    ly = y & (_BLOCK - 1)
    for k in range(last - 1, start - 1, -1):
        entry = list_ranks[k]
        if _outside(lx, ly, entry):
            continue
        j = entry >> 8
        r = ranked_splats[j]
        dx = (px - r[0]) - r[2]
        dy = (py - r[1]) - r[3]
        e = _splat_at(r, dx, dy)
        if e[0] > r[21]:
            continue
        o = r[14]
        G = wp.exp(-0.5 * e[0])
        alpha = wp.min(_ALPHA_MAX, o * G)
        if alpha < _ALPHA_MIN:
            continue
        i = order[j]
        z = e[1]
        one_minus = 1.0 - alpha
        T = T / one_minus  # transmittance in front of this surfel
        w = alpha * T
        col = wp.vec3(r[15], r[16], r[17])
        n = wp.vec3(r[18], r[19], r[20])
        # d loss / d w_k: every output is linear in w_k except the distortion.
        g = wp.dot(dC, col) + dA + wp.dot(dN, n) + dD * z + dDist * (z * z * A - 2.0 * z * D + M2)
        d_alpha = T * g - S / one_minus
        S += w * g

        wp.atomic_add(d_colors, i, w * dC)
        wp.atomic_add(d_normals, i, w * dN)
        dz = w * dD + dDist * 2.0 * w * (z * A - D)
        if k == median_pos:
            dz += dMed
        dG = float(0.0)
        if o * G < _ALPHA_MAX:
            wp.atomic_add(d_opacities, i, d_alpha * G)
            dG = d_alpha * o
        d_rho = -0.5 * G * dG
        if e[4] > 0.0:
            # rho = u^2 + v^2, z = H2 . (u, v, 1), (u, v) = (c0, c1) / c2.
            u = e[2]
            v = e[3]
            pz = r[6]
            inv_c2 = 1.0 / (dx * r[11] + dy * r[12] + r[13])
            du = d_rho * 2.0 * u + dz * r[4]
            dv = d_rho * 2.0 * v + dz * r[5]
            gc0 = du * inv_c2
            gc1 = dv * inv_c2
            gc2 = -(du * u + dv * v) * inv_c2
            # c0 = pz (dy E0y - dx E1y), c1 = pz (dx E1x - dy E0x), c2 = P dx + Q dy + D.
            d_pz = dz + gc0 * (dy * r[8] - dx * r[10]) + gc1 * (dx * r[9] - dy * r[7])
            wp.atomic_add(d_h2, i, wp.vec3(dz * u, dz * v, d_pz))
            wp.atomic_add(d_e0, i, wp.vec2(-gc1 * pz * dy, gc0 * pz * dy))
            wp.atomic_add(d_e1, i, wp.vec2(gc1 * pz * dx, -gc0 * pz * dx))
            wp.atomic_add(d_pqd, i, wp.vec3(gc2 * dx, gc2 * dy, gc2))
            d_dx = pz * (gc1 * r[9] - gc0 * r[10]) + gc2 * r[11]
            d_dy = pz * (gc0 * r[8] - gc1 * r[7]) + gc2 * r[12]
            wp.atomic_add(d_centers, i, wp.vec2(-d_dx, -d_dy))
        else:
            # rho = 2 (dx^2 + dy^2), z = pz.
            wp.atomic_add(d_h2, i, wp.vec3(0.0, 0.0, dz))
            wp.atomic_add(d_centers, i, wp.vec2(-4.0 * d_rho * dx, -4.0 * d_rho * dy))
