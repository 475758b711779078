"""Warp kernels for the tetrahedral energies of the geometry stage (method.md §5, §6).

Every kernel is generic over the scalar type and is compiled for float32 and float64 (the
float64 overloads serve the finite-difference oracle tests; the optimiser runs float32).
Backward passes are hand-written, so all kernels are built without Warp's adjoints
(``enable_backward=False``); the torch autograd wrappers in ``holowarp.ops.tet_energy``
launch them.

Conventions (method.md §1, §6):

- ``tets`` (M,) ``vec4i``; ``Ds = [x1-x0, x2-x0, x3-x0]`` (columns), ``F = Ds Dm^-1`` with
  ``Dm`` the same matrix at the rest positions.
- ``adjacency`` (M,) ``vec4i``: ``adjacency[e][k]`` is the tet across the face opposite local
  vertex ``k``, ``-1`` on the boundary. The face-adjacency graph Laplacian is
  ``L_ee = #neighbours``, ``L_ee' = -1`` for face neighbours; it is symmetric, so the
  backward pass of ``||L F||^2`` applies ``L`` once more.
- Per-element outputs are written to arrays and summed by the caller, so no kernel funnels
  every thread through one atomic scalar (that serialises on GPUs).

No torch import here (style.md: ``kernels/`` is Warp + NumPy only).
"""

from __future__ import annotations

from typing import Any

import warp as wp

__all__ = [
    "deformation_gradient_kernel",
    "deformation_gradient_backward_kernel",
    "biharmonic_forward_kernel",
    "biharmonic_backward_kernel",
    "inversion_penalty_kernel",
    "tet_pass_kernel",
    "signed_volume_kernel",
    "volume_floor_crossing_kernel",
    "incident_floor_crossing_kernel",
    "revert_tet_vertices_kernel",
    "hc_umbrella_kernel",
    "hc_face_normal_kernel",
    "hc_target_kernel",
    "hc_energy_kernel",
    "hc_target_energy_kernel",
    "eikonal_kernel",
    "smoothness_kernel",
    "phi_edge_kernel",
    "scale_vec3_kernel",
    "tet_mean_kernel",
    "tet_mean_backward_kernel",
]


@wp.func
def _ds_matrix(x: wp.array(dtype=Any), t: wp.vec4i):
    x0 = x[t[0]]
    return wp.matrix_from_cols(x[t[1]] - x0, x[t[2]] - x0, x[t[3]] - x0)


@wp.func
def _scatter_ds_grad(grad_x: wp.array(dtype=Any), t: wp.vec4i, g_ds: Any):
    # d(Ds)/dx: column k of Ds is x_{k+1} - x0, so x0 receives minus the column sum.
    gt = wp.transpose(g_ds)
    g1 = gt[0]
    g2 = gt[1]
    g3 = gt[2]
    wp.atomic_add(grad_x, t[1], g1)
    wp.atomic_add(grad_x, t[2], g2)
    wp.atomic_add(grad_x, t[3], g3)
    wp.atomic_sub(grad_x, t[0], g1 + g2 + g3)


@wp.func
def _inversion_term(F: Any, Dinv: Any, t: wp.vec4i, p: Any, with_grad: int, grad_x: wp.array(dtype=Any)):
    # max(-det F, 0)^p; when with_grad, its gradient is accumulated into grad_x.
    d = wp.determinant(F)
    zero = type(d)(0.0)
    if d >= zero:
        return zero
    v = -d
    if with_grad != 0:
        # d det(F)/dF = cofactor(F): column k is the cross product of the other two columns.
        Ft = wp.transpose(F)
        cof = wp.matrix_from_cols(wp.cross(Ft[1], Ft[2]), wp.cross(Ft[2], Ft[0]), wp.cross(Ft[0], Ft[1]))
        dE_dd = -p * wp.pow(v, p - type(p)(1.0))
        _scatter_ds_grad(grad_x, t, (cof * dE_dd) * wp.transpose(Dinv))
    return wp.pow(v, p)


@wp.kernel(enable_backward=False)
def deformation_gradient_kernel(
    x: wp.array(dtype=Any),  # [N] vec3
    tets: wp.array(dtype=wp.vec4i),  # [M]
    dm_inv: wp.array(dtype=Any),  # [M] mat33
    F: wp.array(dtype=Any),  # [M] mat33, out
):
    e = wp.tid()
    F[e] = _ds_matrix(x, tets[e]) * dm_inv[e]


@wp.kernel(enable_backward=False)
def deformation_gradient_backward_kernel(
    tets: wp.array(dtype=wp.vec4i),  # [M]
    dm_inv: wp.array(dtype=Any),  # [M] mat33
    grad_F: wp.array(dtype=Any),  # [M] mat33
    grad_x: wp.array(dtype=Any),  # [N] vec3, accumulated
):
    e = wp.tid()
    # F = Ds Dm^-1  =>  dE/dDs = dE/dF Dm^-T
    _scatter_ds_grad(grad_x, tets[e], grad_F[e] * wp.transpose(dm_inv[e]))


@wp.kernel(enable_backward=False)
def biharmonic_forward_kernel(
    F: wp.array(dtype=Any),  # [M] mat33
    adjacency: wp.array(dtype=wp.vec4i),  # [M]
    weights: wp.array(dtype=Any),  # [M]
    wLF: wp.array(dtype=Any),  # [M] mat33, out: w_e (L F)_e, what the backward pass reads
    energy: wp.array(dtype=Any),  # [M], out: w_e ||(L F)_e||_F^2
):
    e = wp.tid()
    fe = F[e]
    acc = fe - fe
    a = adjacency[e]
    deg = int(0)
    for k in range(4):
        n = a[k]
        if n >= 0:
            acc = acc + F[n]
            deg += 1
    w = weights[e]
    g = fe * type(w)(deg) - acc
    wLF[e] = g * w
    energy[e] = w * wp.ddot(g, g)


@wp.kernel(enable_backward=False)
def biharmonic_backward_kernel(
    tets: wp.array(dtype=wp.vec4i),  # [M]
    adjacency: wp.array(dtype=wp.vec4i),  # [M]
    wLF: wp.array(dtype=Any),  # [M] mat33 w_e (L F)_e from the forward pass
    dm_inv: wp.array(dtype=Any),  # [M] mat33
    grad_out: wp.array(dtype=Any),  # [1] dLoss/dEnergy
    grad_x: wp.array(dtype=Any),  # [N] vec3, accumulated
):
    # E = sum_e w_e ||G_e||^2, G = L F  =>  dE/dF = 2 L^T (w G) = 2 L (w G) (L symmetric).
    # The forward pass stores w G, so each neighbour costs a load, not a load and a rescale.
    e = wp.tid()
    go = grad_out[0]
    wg = wLF[e]
    acc = wg - wg
    a = adjacency[e]
    deg = int(0)
    for k in range(4):
        n = a[k]
        if n >= 0:
            acc = acc + wLF[n]
            deg += 1
    g_F = (wg * type(go)(deg) - acc) * (type(go)(2.0) * go)
    _scatter_ds_grad(grad_x, tets[e], g_F * wp.transpose(dm_inv[e]))


@wp.kernel(enable_backward=False)
def inversion_penalty_kernel(
    x: wp.array(dtype=Any),  # [N] vec3
    tets: wp.array(dtype=wp.vec4i),  # [M]
    dm_inv: wp.array(dtype=Any),  # [M] mat33
    p: Any,  # exponent, >= 1
    with_grad: int,
    energy: wp.array(dtype=Any),  # [M], out: max(-det F, 0)^p
    grad_x: wp.array(dtype=Any),  # [N] vec3, accumulated when with_grad
):
    # Value and gradient in one pass: the energy is local to each tet, so the backward pass
    # is only a rescale by dLoss/dEnergy (done by the caller).
    e = wp.tid()
    t = tets[e]
    Dinv = dm_inv[e]
    energy[e] = _inversion_term(_ds_matrix(x, t) * Dinv, Dinv, t, p, with_grad, grad_x)


@wp.kernel(enable_backward=False)
def tet_pass_kernel(
    x: wp.array(dtype=Any),  # [N] vec3
    tets: wp.array(dtype=wp.vec4i),  # [M]
    dm_inv: wp.array(dtype=Any),  # [M] mat33
    p: Any,  # inversion exponent, >= 1
    with_grad: int,
    F: wp.array(dtype=Any),  # [M] mat33, out (read by biharmonic_forward_kernel)
    inv_energy: wp.array(dtype=Any),  # [M], out: max(-det F, 0)^p
    inv_grad_x: wp.array(dtype=Any),  # [N] vec3, accumulated d inversion / d x when with_grad
):
    # One pass over the tets for everything that needs F alone: F itself (for the
    # bi-harmonic term, whose Laplacian needs the neighbours' F and so a second pass), det F
    # and the inversion penalty with its gradient. Same arithmetic as
    # deformation_gradient_kernel and inversion_penalty_kernel.
    e = wp.tid()
    t = tets[e]
    Dinv = dm_inv[e]
    Fe = _ds_matrix(x, t) * Dinv
    F[e] = Fe
    inv_energy[e] = _inversion_term(Fe, Dinv, t, p, with_grad, inv_grad_x)


@wp.func
def _signed_volume(x: wp.array(dtype=Any), t: wp.vec4i):
    a = x[t[0]]
    return wp.dot(x[t[1]] - a, wp.cross(x[t[2]] - a, x[t[3]] - a)) / type(a[0])(6.0)


@wp.kernel(enable_backward=False)
def signed_volume_kernel(
    x: wp.array(dtype=Any),  # [N] vec3
    tets: wp.array(dtype=wp.vec4i),  # [M]
    vol: wp.array(dtype=Any),  # [M], out: (b - a) . ((c - a) x (d - a)) / 6
):
    e = wp.tid()
    vol[e] = _signed_volume(x, tets[e])


@wp.kernel(enable_backward=False)
def volume_floor_crossing_kernel(
    x_new: wp.array(dtype=Any),  # [N] vec3, positions after the step
    x_old: wp.array(dtype=Any),  # [N] vec3, positions before it
    tets: wp.array(dtype=wp.vec4i),  # [M]
    floor: wp.array(dtype=Any),  # [M] volume floor of each tet
    bad: wp.array(dtype=wp.int32),  # [M] out: 1 where the volume was above the floor and is not (NaN included)
    count: wp.array(dtype=wp.int32),  # [1] += the number of such tets
):
    # Both volumes in one pass: the geometry step's inversion guard reads one counter
    # instead of two volume passes and a reduction (issue 17).
    e = wp.tid()
    t = tets[e]
    f = floor[e]
    crossed = 0
    if _signed_volume(x_old, t) > f:
        if not (_signed_volume(x_new, t) > f):
            crossed = 1
            wp.atomic_add(count, 0, 1)
    bad[e] = crossed


@wp.kernel(enable_backward=False)
def incident_floor_crossing_kernel(
    x_new: wp.array(dtype=Any),  # [N] vec3, positions after the step (some put back)
    x_old: wp.array(dtype=Any),  # [N] vec3, positions before it
    tets: wp.array(dtype=wp.vec4i),  # [M]
    floor: wp.array(dtype=Any),  # [M] volume floor of each tet
    offsets: wp.array(dtype=wp.int32),  # [N + 1] CSR offsets of each vertex's tets
    incident: wp.array(dtype=wp.int32),  # [4 M] tet ids, grouped by vertex
    stamp: wp.array(dtype=wp.int32),  # [N] the round in which each vertex was last put back (0: never)
    last_round: int,  # the round whose put-backs are checked
    bad: wp.array(dtype=wp.int32),  # [M] in/out: set to 1 for each tet that now crosses its floor
    count: wp.array(dtype=wp.int32),  # [1] += one per (vertex, crossing tet) pair found
):
    # After a round of put-backs only the tets of the vertices it put back can have changed
    # volume, so later rounds check those alone instead of every tet (issue 17). A tet seen
    # from several such vertices is flagged several times, which is benign.
    v = wp.tid()
    if stamp[v] != last_round:
        return
    for j in range(offsets[v], offsets[v + 1]):
        e = incident[j]
        t = tets[e]
        f = floor[e]
        if _signed_volume(x_old, t) > f:
            if not (_signed_volume(x_new, t) > f):
                bad[e] = 1
                wp.atomic_add(count, 0, 1)


@wp.kernel(enable_backward=False)
def revert_tet_vertices_kernel(
    bad: wp.array(dtype=wp.int32),  # [M] in/out: cleared after its tet is put back
    tets: wp.array(dtype=wp.vec4i),  # [M]
    x_old: wp.array(dtype=Any),  # [N] vec3
    round_: int,  # this round's number, >= 1
    x_new: wp.array(dtype=Any),  # [N] vec3, in/out: the four vertices of each bad tet put back to x_old
    stamp: wp.array(dtype=wp.int32),  # [N] in/out: set to round_ for every vertex put back
):
    # Several bad tets may share a vertex; they all write the same values, so the race is benign.
    e = wp.tid()
    if bad[e] != 0:
        t = tets[e]
        for k in range(4):
            x_new[t[k]] = x_old[t[k]]
            stamp[t[k]] = round_
        bad[e] = 0


# --- HC-Laplacian (Vollmer et al. 1999) on the boundary surface -------------------------
# Surface vertices are addressed by a local index s in [0, S); ``surf_ids[s]`` is the global
# vertex id, ``nbr_offsets``/``nbr_ids`` a CSR list of local surface neighbours.


@wp.kernel(enable_backward=False)
def hc_umbrella_kernel(
    x: wp.array(dtype=Any),  # [N] vec3
    x_orig: wp.array(dtype=Any),  # [N] vec3, o_i of Vollmer (the rest positions)
    surf_ids: wp.array(dtype=wp.int32),  # [S]
    nbr_offsets: wp.array(dtype=wp.int32),  # [S + 1]
    nbr_ids: wp.array(dtype=wp.int32),  # [nnz] local ids
    alpha: Any,
    p_out: wp.array(dtype=Any),  # [S] vec3, umbrella average of neighbours
    b_out: wp.array(dtype=Any),  # [S] vec3, b_i = p_i - (alpha o_i + (1 - alpha) q_i)
):
    s = wp.tid()
    q = x[surf_ids[s]]
    acc = q - q
    start = nbr_offsets[s]
    end = nbr_offsets[s + 1]
    for j in range(start, end):
        acc = acc + x[surf_ids[nbr_ids[j]]]
    pavg = q
    if end > start:
        pavg = acc / type(alpha)(end - start)
    one = type(alpha)(1.0)
    p_out[s] = pavg
    b_out[s] = pavg - (x_orig[surf_ids[s]] * alpha + q * (one - alpha))


@wp.kernel(enable_backward=False)
def hc_face_normal_kernel(
    x: wp.array(dtype=Any),  # [N] vec3
    faces_global: wp.array(dtype=wp.vec3i),  # [B] boundary faces, global ids, wound outward
    faces_local: wp.array(dtype=wp.vec3i),  # [B] same faces, local surface ids
    normal_acc: wp.array(dtype=Any),  # [S] vec3, accumulated area vectors
):
    f = wp.tid()
    g = faces_global[f]
    x0 = x[g[0]]
    m = wp.cross(x[g[1]] - x0, x[g[2]] - x0)  # twice the area vector: area weighting
    lf = faces_local[f]
    wp.atomic_add(normal_acc, lf[0], m)
    wp.atomic_add(normal_acc, lf[1], m)
    wp.atomic_add(normal_acc, lf[2], m)


@wp.func
def _hc_target(s: int, p_in: wp.array(dtype=Any), b_in: wp.array(dtype=Any), nbr_offsets: wp.array(dtype=wp.int32),
               nbr_ids: wp.array(dtype=wp.int32), beta: Any):
    # target_s = p_s - (beta b_s + (1 - beta) mean_{j in N(s)} b_j)
    bs = b_in[s]
    acc = bs - bs
    start = nbr_offsets[s]
    end = nbr_offsets[s + 1]
    for j in range(start, end):
        acc = acc + b_in[nbr_ids[j]]
    bbar = bs
    if end > start:
        bbar = acc / type(beta)(end - start)
    one = type(beta)(1.0)
    return p_in[s] - (bs * beta + bbar * (one - beta))


@wp.func
def _unit_or_zero(m: Any):
    ln = wp.length(m)
    if ln > type(ln)(0.0):
        return m / ln
    return m


@wp.func
def _hc_energy_at(s: int, i: int, target: Any, n: Any, x: wp.array(dtype=Any), lam_cond: Any, with_grad: int,
                  energy: wp.array(dtype=Any), grad_x: wp.array(dtype=Any)):
    # d = target - x; d_n = d . n (n outward); d_t = d - d_n n.
    # E = |d_t|^2 + lam_cond min(d_n, 0)^2 + max(d_n, 0)^2, written to energy[s]; with_grad:
    # dE/dx_i = -(2 d_t + 2 (lam neg + pos) n) to grad_x[i] (target and n are constants).
    d = target - x[i]
    dn = wp.dot(d, n)
    dt = d - n * dn
    zero = type(lam_cond)(0.0)
    neg = wp.min(dn, zero)
    pos = wp.max(dn, zero)
    energy[s] = wp.dot(dt, dt) + lam_cond * neg * neg + pos * pos
    if with_grad != 0:
        two = type(lam_cond)(2.0)
        grad_x[i] = -(dt * two + n * (two * (lam_cond * neg + pos)))


@wp.kernel(enable_backward=False)
def hc_target_kernel(
    p_in: wp.array(dtype=Any),  # [S] vec3
    b_in: wp.array(dtype=Any),  # [S] vec3
    nbr_offsets: wp.array(dtype=wp.int32),  # [S + 1]
    nbr_ids: wp.array(dtype=wp.int32),  # [nnz]
    normal_acc: wp.array(dtype=Any),  # [S] vec3 area vectors
    beta: Any,
    target: wp.array(dtype=Any),  # [S] vec3, out
    normal: wp.array(dtype=Any),  # [S] vec3, out: unit outward normal
):
    s = wp.tid()
    target[s] = _hc_target(s, p_in, b_in, nbr_offsets, nbr_ids, beta)
    normal[s] = _unit_or_zero(normal_acc[s])


@wp.kernel(enable_backward=False)
def hc_energy_kernel(
    x: wp.array(dtype=Any),  # [N] vec3
    surf_ids: wp.array(dtype=wp.int32),  # [S]
    target: wp.array(dtype=Any),  # [S] vec3 (held constant)
    normal: wp.array(dtype=Any),  # [S] vec3 (held constant)
    lam_cond: Any,
    with_grad: int,
    energy: wp.array(dtype=Any),  # [S], out
    grad_x: wp.array(dtype=Any),  # [N] vec3, out (each surface vertex written once)
):
    s = wp.tid()
    _hc_energy_at(s, surf_ids[s], target[s], normal[s], x, lam_cond, with_grad, energy, grad_x)


@wp.kernel(enable_backward=False)
def hc_target_energy_kernel(
    p_in: wp.array(dtype=Any),  # [S] vec3 from hc_umbrella_kernel
    b_in: wp.array(dtype=Any),  # [S] vec3 from hc_umbrella_kernel
    nbr_offsets: wp.array(dtype=wp.int32),  # [S + 1]
    nbr_ids: wp.array(dtype=wp.int32),  # [nnz]
    normal_acc: wp.array(dtype=Any),  # [S] vec3 area vectors from hc_face_normal_kernel
    beta: Any,
    x: wp.array(dtype=Any),  # [N] vec3
    surf_ids: wp.array(dtype=wp.int32),  # [S]
    lam_cond: Any,
    with_grad: int,
    energy: wp.array(dtype=Any),  # [S], out
    grad_x: wp.array(dtype=Any),  # [N] vec3, out (each surface vertex written once)
):
    # hc_target_kernel and hc_energy_kernel in one pass: the same arithmetic, without the
    # round trip of the targets and normals through memory (bit for bit the same result).
    s = wp.tid()
    _hc_energy_at(s, surf_ids[s], _hc_target(s, p_in, b_in, nbr_offsets, nbr_ids, beta), _unit_or_zero(normal_acc[s]),
                  x, lam_cond, with_grad, energy, grad_x)


@wp.kernel(enable_backward=False)
def eikonal_kernel(
    phi: wp.array(dtype=Any),  # [N]
    x: wp.array(dtype=Any),  # [N] vec3
    edges: wp.array(dtype=wp.vec2i),  # [E]
    inv_count: Any,  # 1 / E (the loss is a mean)
    with_grad: int,
    energy: wp.array(dtype=Any),  # [E], out: (|dphi| / l - 1)^2
    grad_phi: wp.array(dtype=Any),  # [N], accumulated, already divided by E
    grad_x: wp.array(dtype=Any),  # [N] vec3, accumulated, already divided by E
):
    k = wp.tid()
    uv = edges[k]
    u = uv[0]
    v = uv[1]
    dphi = phi[u] - phi[v]
    dx = x[u] - x[v]
    zero = type(inv_count)(0.0)
    l = wp.max(wp.length(dx), type(inv_count)(1.0e-12))
    a = wp.abs(dphi)
    r = a / l - type(inv_count)(1.0)
    energy[k] = r * r
    if with_grad == 0:
        return
    c = type(inv_count)(2.0) * r * inv_count
    sgn = zero
    if dphi > zero:
        sgn = type(inv_count)(1.0)
    elif dphi < zero:
        sgn = type(inv_count)(-1.0)
    gp = c * sgn / l
    wp.atomic_add(grad_phi, u, gp)
    wp.atomic_sub(grad_phi, v, gp)
    # d(a / l)/d x_u = -a / l^2 * dx / l
    gx = dx * (-c * a / (l * l * l))
    wp.atomic_add(grad_x, u, gx)
    wp.atomic_sub(grad_x, v, gx)


@wp.kernel(enable_backward=False)
def smoothness_kernel(
    phi: wp.array(dtype=Any),  # [N]
    edges: wp.array(dtype=wp.vec2i),  # [E]
    inv_count: Any,
    with_grad: int,
    energy: wp.array(dtype=Any),  # [E], out: (phi_u - phi_v)^2
    grad_phi: wp.array(dtype=Any),  # [N], accumulated, already divided by E
):
    k = wp.tid()
    uv = edges[k]
    d = phi[uv[0]] - phi[uv[1]]
    energy[k] = d * d
    if with_grad != 0:
        g = type(inv_count)(2.0) * d * inv_count
        wp.atomic_add(grad_phi, uv[0], g)
        wp.atomic_sub(grad_phi, uv[1], g)


@wp.kernel(enable_backward=False)
def phi_edge_kernel(
    phi: wp.array(dtype=Any),  # [N]
    x: wp.array(dtype=Any),  # [N] vec3 (constant: no gradient)
    edges: wp.array(dtype=wp.vec2i),  # [E]
    inv_count: Any,  # 1 / E (both losses are means)
    with_grad: int,
    eik: wp.array(dtype=Any),  # [E], out: (|dphi| / l - 1)^2
    smooth: wp.array(dtype=Any),  # [E], out: dphi^2
    grad_eik: wp.array(dtype=Any),  # [N], accumulated d mean(eik) / d phi
    grad_smooth: wp.array(dtype=Any),  # [N], accumulated d mean(smooth) / d phi
):
    # The eikonal and smoothness terms of the topology phase in one pass over the edges
    # (same arithmetic as eikonal_kernel and smoothness_kernel), with x held constant.
    k = wp.tid()
    uv = edges[k]
    u = uv[0]
    v = uv[1]
    dphi = phi[u] - phi[v]
    zero = type(inv_count)(0.0)
    one = type(inv_count)(1.0)
    l = wp.max(wp.length(x[u] - x[v]), type(inv_count)(1.0e-12))
    r = wp.abs(dphi) / l - one
    eik[k] = r * r
    smooth[k] = dphi * dphi
    if with_grad == 0:
        return
    two = type(inv_count)(2.0)
    sgn = zero
    if dphi > zero:
        sgn = one
    elif dphi < zero:
        sgn = -one
    gp = two * r * inv_count * sgn / l
    wp.atomic_add(grad_eik, u, gp)
    wp.atomic_sub(grad_eik, v, gp)
    gs = two * dphi * inv_count
    wp.atomic_add(grad_smooth, u, gs)
    wp.atomic_sub(grad_smooth, v, gs)


@wp.kernel(enable_backward=False)
def scale_vec3_kernel(
    src: wp.array(dtype=Any),  # [N] vec3
    scale: wp.array(dtype=Any),  # [1]
    dst: wp.array(dtype=Any),  # [N] vec3, out
):
    i = wp.tid()
    dst[i] = src[i] * scale[0]


# --- per-tet means (the surfel model's centres and field opacities) ---------------------


@wp.kernel(enable_backward=False)
def tet_mean_kernel(
    values: wp.array(dtype=Any),  # [N] per-vertex values (vec3 positions or scalars)
    tets: wp.array(dtype=wp.vec4i),  # [M]
    quarter: Any,  # 0.25 in the values' precision
    out: wp.array(dtype=Any),  # [M] out: the mean over each tet's four vertices
):
    # Summed in vertex order, then scaled by 1/4 (exact): the rounding of torch's
    # values[tets].mean(dim=1), which this replaces in the surfel model.
    e = wp.tid()
    t = tets[e]
    out[e] = (((values[t[0]] + values[t[1]]) + values[t[2]]) + values[t[3]]) * quarter


@wp.kernel(enable_backward=False)
def tet_mean_backward_kernel(
    grad_out: wp.array(dtype=Any),  # [M] dLoss/d mean
    tets: wp.array(dtype=wp.vec4i),  # [M]
    quarter: Any,  # 0.25 in the values' precision
    grad_values: wp.array(dtype=Any),  # [N] accumulated, tet by tet in order
):
    e = wp.tid()
    t = tets[e]
    g = grad_out[e] * quarter
    for j in range(4):
        wp.atomic_add(grad_values, t[j], g)


# --- explicit float32 / float64 overloads (compiled together with the module) -----------


def _register_overloads():
    for T, V, M in ((wp.float32, wp.vec3f, wp.mat33f), (wp.float64, wp.vec3d, wp.mat33d)):
        aV, aM, aT = wp.array(dtype=V), wp.array(dtype=M), wp.array(dtype=T)
        a4, a3, a2, ai = (
            wp.array(dtype=wp.vec4i),
            wp.array(dtype=wp.vec3i),
            wp.array(dtype=wp.vec2i),
            wp.array(dtype=wp.int32),
        )
        wp.overload(deformation_gradient_kernel, [aV, a4, aM, aM])
        wp.overload(deformation_gradient_backward_kernel, [a4, aM, aM, aV])
        wp.overload(biharmonic_forward_kernel, [aM, a4, aT, aM, aT])
        wp.overload(biharmonic_backward_kernel, [a4, a4, aM, aM, aT, aV])
        wp.overload(inversion_penalty_kernel, [aV, a4, aM, T, wp.int32, aT, aV])
        wp.overload(tet_pass_kernel, [aV, a4, aM, T, wp.int32, aM, aT, aV])
        wp.overload(signed_volume_kernel, [aV, a4, aT])
        wp.overload(volume_floor_crossing_kernel, [aV, aV, a4, aT, ai, ai])
        wp.overload(incident_floor_crossing_kernel, [aV, aV, a4, aT, ai, ai, ai, wp.int32, ai, ai])
        wp.overload(revert_tet_vertices_kernel, [ai, a4, aV, wp.int32, aV, ai])
        wp.overload(hc_umbrella_kernel, [aV, aV, ai, ai, ai, T, aV, aV])
        wp.overload(hc_face_normal_kernel, [aV, a3, a3, aV])
        wp.overload(hc_target_kernel, [aV, aV, ai, ai, aV, T, aV, aV])
        wp.overload(hc_energy_kernel, [aV, ai, aV, aV, T, wp.int32, aT, aV])
        wp.overload(hc_target_energy_kernel, [aV, aV, ai, ai, aV, T, aV, ai, T, wp.int32, aT, aV])
        wp.overload(eikonal_kernel, [aT, aV, a2, T, wp.int32, aT, aT, aV])
        wp.overload(smoothness_kernel, [aT, a2, T, wp.int32, aT, aT])
        wp.overload(phi_edge_kernel, [aT, aV, a2, T, wp.int32, aT, aT, aT, aT])
        wp.overload(scale_vec3_kernel, [aV, aT, aV])
        for a in (aV, aT):
            wp.overload(tet_mean_kernel, [a, a4, T, a])
            wp.overload(tet_mean_backward_kernel, [a, a4, T, a])


_register_overloads()
