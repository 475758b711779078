"""Warp kernels of the element-improvement stage (method.md §7b), Warp + NumPy only.

Two kernels, both float64 (the stage works in float64 throughout: qualities of slivers are
differences of nearly equal numbers, and a smoothing step that is accepted in float32 can
be an inversion in float64):

- :func:`tet_quality_kernel` (one thread per tet): the per-tet quality of
  :func:`tet_quality`, for whole meshes or for candidate tets of a flip.
- :func:`point_mesh_distance_kernel` (one thread per point): exact distance from points
  to a triangle surface through Warp's mesh BVH (float32), for the measured Hausdorff
  distance between the surfaces before and after.
- :func:`smooth_vertices_kernel` (one thread per vertex of one independent set): one step
  of optimisation-based smoothing (Freitag & Ollivier-Gooch 1997; Klingner & Shewchuk 2007,
  "Aggressive Tetrahedral Mesh Improvement", §3): ascend the soft minimum of the star's
  qualities along its finite-difference gradient, restricted to the vertex's allowed
  directions, try ``n_steps`` step lengths and keep the best position, but only if it raises
  the star's hard minimum quality by more than ``min_gain`` and, unless that minimum is
  below ``mean_guard`` (a bad star: its worst tet comes first), without lowering the star's
  mean quality (polishing must not cost the average). A boundary vertex's trial
  position is admissible only if its boundary triangles move (two-sided Hausdorff,
  :func:`umbrella_move`) by at most the vertex's ``budget``. A vertex of the set moves only
  its own position and reads only its star's other vertices (and its boundary triangles'),
  which are in other sets, so the positions can be updated in place.

Quality measures (``mode``), all 1 for the regular tetrahedron, 0 for a degenerate one, and
negative for an inverted one (so "quality > 0" implies positive orientation):

- ``QUALITY_SINE`` (0): the smallest of the six dihedral-angle sines, each signed like the
  volume, divided by the regular tet's: ``sin(theta_ij) = 6V l_ij / (|n_k| |n_l|)`` with
  ``n_k``, ``n_l`` the doubled area vectors of the two faces meeting at edge ``ij``
  (Klingner & Shewchuk's "sine measure": it penalises both small and large dihedral
  angles);
- ``QUALITY_ETA`` (1): ``eta = 12 (3|V|)^(2/3) / sum l^2`` (the volume-length shape measure
  of Newton's ``validate_tet_mesh``), signed like the volume;
- ``QUALITY_SINE_ETA`` (2): the smaller of the two.

Conventions: ``x`` (N,) ``vec3d`` positions in metres; ``tets`` (M,) ``vec4i`` positively
oriented (``det[b-a, c-a, d-a] > 0``); stars as CSR ``star_offsets`` (N+1,) into
``star_tets``/``star_local`` (the tet and the vertex's local index 0..3 in it).
"""

from __future__ import annotations

import warp as wp

# Forward-only kernels: no adjoints to generate (faster first compile).
wp.set_module_options({"enable_backward": False})

__all__ = [
    "QUALITY_SINE",
    "QUALITY_ETA",
    "QUALITY_SINE_ETA",
    "SIN_REGULAR",
    "tet_quality",
    "tet_quality_kernel",
    "point_triangle_distance",
    "umbrella_move",
    "smooth_vertices_kernel",
    "point_mesh_distance_kernel",
]

QUALITY_SINE = wp.constant(0)
QUALITY_ETA = wp.constant(1)
QUALITY_SINE_ETA = wp.constant(2)

#: Sine of the regular tetrahedron's dihedral angle arccos(1/3): 2 sqrt(2) / 3.
SIN_REGULAR = 0.9428090415820634
_SIN_REG = wp.constant(wp.float64(0.9428090415820634))


@wp.func
def _sin_ratio(vol6: wp.float64, l: wp.float64, na: wp.float64, nb: wp.float64) -> wp.float64:
    den = na * nb
    if den <= wp.float64(0.0):
        return wp.float64(0.0)
    return vol6 * l / den


@wp.func
def tet_quality(a: wp.vec3d, b: wp.vec3d, c: wp.vec3d, d: wp.vec3d, mode: int) -> wp.float64:
    """Quality of the tet (a, b, c, d) by measure ``mode`` (module docstring)."""
    vol6 = wp.dot(b - a, wp.cross(c - a, d - a))
    # Doubled outward area vectors of the faces opposite a, b, c, d (TET_FACES).
    n0 = wp.length(wp.cross(c - b, d - b))
    n1 = wp.length(wp.cross(d - a, c - a))
    n2 = wp.length(wp.cross(b - a, d - a))
    n3 = wp.length(wp.cross(c - a, b - a))
    l01 = wp.length(b - a)
    l02 = wp.length(c - a)
    l03 = wp.length(d - a)
    l12 = wp.length(c - b)
    l13 = wp.length(d - b)
    l23 = wp.length(d - c)
    q = wp.float64(1.0e30)
    if mode != QUALITY_ETA:
        # Edge ij lies on the faces opposite the two other vertices.
        s = _sin_ratio(vol6, l01, n2, n3)
        s = wp.min(s, _sin_ratio(vol6, l02, n1, n3))
        s = wp.min(s, _sin_ratio(vol6, l03, n1, n2))
        s = wp.min(s, _sin_ratio(vol6, l12, n0, n3))
        s = wp.min(s, _sin_ratio(vol6, l13, n0, n2))
        s = wp.min(s, _sin_ratio(vol6, l23, n0, n1))
        q = s / _SIN_REG
    if mode != QUALITY_SINE:
        sl2 = l01 * l01 + l02 * l02 + l03 * l03 + l12 * l12 + l13 * l13 + l23 * l23
        eta = wp.float64(0.0)
        if sl2 > wp.float64(0.0):
            eta = wp.float64(12.0) * wp.pow(wp.abs(vol6) * wp.float64(0.5), wp.float64(2.0) / wp.float64(3.0)) / sl2
            if vol6 < wp.float64(0.0):
                eta = -eta
        q = wp.min(q, eta)
    return q


@wp.kernel
def tet_quality_kernel(
    x: wp.array(dtype=wp.vec3d),  # [N]
    tets: wp.array(dtype=wp.vec4i),  # [M]
    mode: int,
    quality: wp.array(dtype=wp.float64),  # [M] out
):
    e = wp.tid()
    t = tets[e]
    quality[e] = tet_quality(x[t[0]], x[t[1]], x[t[2]], x[t[3]], mode)


@wp.func
def _star_tet_quality(
    x: wp.array(dtype=wp.vec3d), t: wp.vec4i, local: int, y: wp.vec3d, mode: int
) -> wp.float64:
    # The star's tet with its vertex ``local`` placed at y.
    a = x[t[0]]
    b = x[t[1]]
    c = x[t[2]]
    d = x[t[3]]
    if local == 0:
        a = y
    elif local == 1:
        b = y
    elif local == 2:
        c = y
    else:
        d = y
    return tet_quality(a, b, c, d, mode)


@wp.func
def _star_min(
    x: wp.array(dtype=wp.vec3d),
    tets: wp.array(dtype=wp.vec4i),
    star_tets: wp.array(dtype=wp.int32),
    star_local: wp.array(dtype=wp.int32),
    s0: int,
    s1: int,
    y: wp.vec3d,
    mode: int,
) -> wp.float64:
    m = wp.float64(1.0e30)
    for s in range(s0, s1):
        m = wp.min(m, _star_tet_quality(x, tets[star_tets[s]], star_local[s], y, mode))
    return m


@wp.func
def _star_mean(
    x: wp.array(dtype=wp.vec3d),
    tets: wp.array(dtype=wp.vec4i),
    star_tets: wp.array(dtype=wp.int32),
    star_local: wp.array(dtype=wp.int32),
    s0: int,
    s1: int,
    y: wp.vec3d,
    mode: int,
) -> wp.float64:
    acc = wp.float64(0.0)
    for s in range(s0, s1):
        acc += _star_tet_quality(x, tets[star_tets[s]], star_local[s], y, mode)
    return acc / wp.float64(s1 - s0)


@wp.func
def _star_softmin(
    x: wp.array(dtype=wp.vec3d),
    tets: wp.array(dtype=wp.vec4i),
    star_tets: wp.array(dtype=wp.int32),
    star_local: wp.array(dtype=wp.int32),
    s0: int,
    s1: int,
    y: wp.vec3d,
    mode: int,
    beta: wp.float64,
) -> wp.float64:
    # -1/beta log sum exp(-beta q_i), shifted by the hard minimum for stability.
    m = _star_min(x, tets, star_tets, star_local, s0, s1, y, mode)
    acc = wp.float64(0.0)
    for s in range(s0, s1):
        q = _star_tet_quality(x, tets[star_tets[s]], star_local[s], y, mode)
        acc += wp.exp(-beta * (q - m))
    return m - wp.log(acc) / beta


@wp.func
def point_triangle_distance(p: wp.vec3d, a: wp.vec3d, b: wp.vec3d, c: wp.vec3d) -> wp.float64:
    """Exact distance from p to triangle abc (Ericson, Real-Time Collision Detection §5.1.5)."""
    zero = wp.float64(0.0)
    ab = b - a
    ac = c - a
    ap = p - a
    d1 = wp.dot(ab, ap)
    d2 = wp.dot(ac, ap)
    if d1 <= zero and d2 <= zero:
        return wp.length(p - a)
    bp = p - b
    d3 = wp.dot(ab, bp)
    d4 = wp.dot(ac, bp)
    if d3 >= zero and d4 <= d3:
        return wp.length(p - b)
    vc = d1 * d4 - d3 * d2
    if vc <= zero and d1 >= zero and d3 <= zero:
        return wp.length(p - (a + ab * (d1 / (d1 - d3))))
    cp = p - c
    d5 = wp.dot(ab, cp)
    d6 = wp.dot(ac, cp)
    if d6 >= zero and d5 <= d6:
        return wp.length(p - c)
    vb = d5 * d2 - d1 * d6
    if vb <= zero and d2 >= zero and d6 <= zero:
        return wp.length(p - (a + ac * (d2 / (d2 - d6))))
    va = d3 * d6 - d5 * d4
    if va <= zero and (d4 - d3) >= zero and (d5 - d6) >= zero:
        return wp.length(p - (b + (c - b) * ((d4 - d3) / ((d4 - d3) + (d5 - d6)))))
    den = va + vb + vc
    if den == zero:
        return wp.min(wp.length(p - a), wp.min(wp.length(p - b), wp.length(p - c)))
    return wp.length(p - (a + ab * (vb / den) + ac * (vc / den)))


@wp.func
def _corner(x: wp.array(dtype=wp.vec3d), f: wp.vec3i, j: int, v: int, y: wp.vec3d) -> wp.vec3d:
    # Corner j of face f, with vertex v placed at y.
    i = f[j]
    if i == v:
        return y
    return x[i]


@wp.func
def _patch_one_way(
    x: wp.array(dtype=wp.vec3d),
    bfaces: wp.array(dtype=wp.vec3i),
    bface_ids: wp.array(dtype=wp.int32),
    f0: int,
    f1: int,
    v: int,
    y_src: wp.vec3d,
    y_dst: wp.vec3d,
    level: int,
) -> wp.float64:
    # Largest distance from the umbrella of v (v at y_src), sampled on a barycentric grid,
    # to the same umbrella with v at y_dst.
    worst = wp.float64(0.0)
    inv = wp.float64(1.0) / wp.float64(level)
    for fi in range(f0, f1):
        f = bfaces[bface_ids[fi]]
        a = _corner(x, f, 0, v, y_src)
        b = _corner(x, f, 1, v, y_src)
        c = _corner(x, f, 2, v, y_src)
        for i in range(level + 1):
            for j in range(level + 1 - i):
                wb = wp.float64(i) * inv
                wc = wp.float64(j) * inv
                p = a + (b - a) * wb + (c - a) * wc
                best = wp.float64(1.0e30)
                for gi in range(f0, f1):
                    g = bfaces[bface_ids[gi]]
                    best = wp.min(best, point_triangle_distance(
                        p, _corner(x, g, 0, v, y_dst), _corner(x, g, 1, v, y_dst), _corner(x, g, 2, v, y_dst)))
                worst = wp.max(worst, best)
    return worst


@wp.func
def umbrella_move(
    x: wp.array(dtype=wp.vec3d),
    bfaces: wp.array(dtype=wp.vec3i),
    bface_ids: wp.array(dtype=wp.int32),
    f0: int,
    f1: int,
    v: int,
    y: wp.vec3d,
    level: int,
) -> wp.float64:
    """Two-sided Hausdorff distance between vertex v's boundary triangles with v where it
    is and with v at y, sampled on a barycentric grid of ``level`` steps per triangle with
    each sample measured exactly to the other patch (so it approaches the true distance
    from below as ``level`` grows). The true distance never exceeds |y - x[v]|: every
    point of the patch keeps its barycentric coordinates and moves at most that much."""
    x0 = x[v]
    return wp.max(
        _patch_one_way(x, bfaces, bface_ids, f0, f1, v, x0, y, level),
        _patch_one_way(x, bfaces, bface_ids, f0, f1, v, y, x0, level),
    )


@wp.kernel
def smooth_vertices_kernel(
    x: wp.array(dtype=wp.vec3d),  # [N] positions, updated in place at ``verts``
    tets: wp.array(dtype=wp.vec4i),  # [M]
    star_offsets: wp.array(dtype=wp.int32),  # [N+1]
    star_tets: wp.array(dtype=wp.int32),  # [S]
    star_local: wp.array(dtype=wp.int32),  # [S]
    bface_offsets: wp.array(dtype=wp.int32),  # [N+1] boundary triangles per vertex (CSR)
    bface_ids: wp.array(dtype=wp.int32),  # [3F]
    bfaces: wp.array(dtype=wp.vec3i),  # [F]
    verts: wp.array(dtype=wp.int32),  # [K] one independent set
    proj: wp.array(dtype=wp.mat33d),  # [N] projector onto the allowed directions
    budget: wp.array(dtype=wp.float64),  # [N] largest surface move allowed at the vertex, m
    mode: int,
    beta: wp.float64,  # soft-min sharpness, 1/quality units
    step_frac: wp.float64,  # first trial step, in units of the star's mean edge length
    n_steps: int,  # trial steps, halving each time
    fd_frac: wp.float64,  # finite-difference step, in units of the mean edge length
    min_gain: wp.float64,  # least rise of the star's minimum quality for a move
    level: int,  # barycentric grid steps of the surface-move samples
    margin: wp.float64,  # factor on the sampled surface move (sampling under-estimates)
    mean_guard: wp.float64,  # stars whose minimum is at least this must not lose mean quality
    q_before: wp.array(dtype=wp.float64),  # [K] out: star minimum before
    q_after: wp.array(dtype=wp.float64),  # [K] out: star minimum after (= before if not moved)
    moved_by: wp.array(dtype=wp.float64),  # [K] out: surface move of the step taken, m
):
    k = wp.tid()
    v = verts[k]
    s0 = star_offsets[v]
    s1 = star_offsets[v + 1]
    x0 = x[v]
    # Mean distance to the star's other vertices: the length scale of every step.
    lsum = wp.float64(0.0)
    cnt = wp.float64(0.0)
    for s in range(s0, s1):
        t = tets[star_tets[s]]
        for j in range(4):
            lsum += wp.length(x[t[j]] - x0)
        cnt += wp.float64(3.0)
    q0 = _star_min(x, tets, star_tets, star_local, s0, s1, x0, mode)
    mean0 = _star_mean(x, tets, star_tets, star_local, s0, s1, x0, mode)
    q_before[k] = q0
    q_after[k] = q0
    moved_by[k] = wp.float64(0.0)
    if cnt == wp.float64(0.0):
        return
    h = lsum / cnt
    # Central finite differences of the soft minimum.
    fd = fd_frac * h
    g = wp.vec3d(wp.float64(0.0), wp.float64(0.0), wp.float64(0.0))
    for j in range(3):
        e = wp.vec3d(wp.float64(0.0), wp.float64(0.0), wp.float64(0.0))
        e[j] = fd
        fp = _star_softmin(x, tets, star_tets, star_local, s0, s1, x0 + e, mode, beta)
        fm = _star_softmin(x, tets, star_tets, star_local, s0, s1, x0 - e, mode, beta)
        g[j] = (fp - fm) / (wp.float64(2.0) * fd)
    dvec = proj[v] * g
    dn = wp.length(dvec)
    if dn <= wp.float64(0.0):
        return
    dvec = dvec / dn
    f0 = bface_offsets[v]
    f1 = bface_offsets[v + 1]
    lim = budget[v]
    best = q0
    best_y = x0
    best_h = wp.float64(0.0)
    alpha = step_frac * h
    for i in range(n_steps):
        y = x0 + alpha * dvec
        alpha = alpha * wp.float64(0.5)
        q = _star_min(x, tets, star_tets, star_local, s0, s1, y, mode)
        if q > best and (q0 < mean_guard or _star_mean(x, tets, star_tets, star_local, s0, s1, y, mode) >= mean0):
            hm = wp.float64(0.0)
            if f1 > f0:
                hm = wp.min(margin * umbrella_move(x, bfaces, bface_ids, f0, f1, v, y, level), wp.length(y - x0))
            if hm <= lim:
                best = q
                best_y = y
                best_h = hm
    if best > q0 + min_gain:
        x[v] = best_y
        q_after[k] = best
        moved_by[k] = best_h


@wp.kernel
def point_mesh_distance_kernel(
    mesh: wp.uint64,  # wp.Mesh id of the target triangle surface (float32 BVH)
    points: wp.array(dtype=wp.vec3),  # [P]
    max_dist: float,  # search radius; points farther away report it and face -1
    dist: wp.array(dtype=float),  # [P] out: distance to the closest surface point
    face: wp.array(dtype=wp.int32),  # [P] out: the triangle holding it
):
    i = wp.tid()
    p = points[i]
    hit = wp.mesh_query_point_no_sign(mesh, p, max_dist)
    if hit.result:
        dist[i] = wp.length(wp.mesh_eval_position(mesh, hit.face, hit.u, hit.v) - p)
        face[i] = hit.face
    else:
        dist[i] = max_dist
        face[i] = -1
