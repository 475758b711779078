"""XPBD kernels for tetrahedral stable Neo-Hookean solids (Warp + NumPy only).

One substep of :class:`holowarp.sim.SolverXPBDNeoHookean` launches, in order:

1. :func:`sim_predict` (per particle): symplectic Euler prediction ``v += g dt``,
   ``x += v dt``; remembers the substep's start position/velocity; clears contact state.
2. ``iterations`` times :func:`sim_solve_tets` (per tet, over the tets of one colour, or over
   all colours at once on the CPU, see below): the coupled deviatoric + hydrostatic XPBD
   projection of one tet, followed by the contact projection and Coulomb friction of its
   four vertices.
3. :func:`sim_finalize` (per particle): last contact/friction pass, velocity from positions,
   restitution, velocity damping, contact forces.

Material model (Macklin & Müller 2021, "A Constraint-based Formulation of Stable Neo-Hookean
Materials"). With the deformation gradient ``F = Ds Dm^-1``:

- deviatoric constraint ``C_D = sqrt(tr(F^T F))``, compliance ``alpha_D = 1 / mu``;
- hydrostatic constraint ``C_H = det(F) - gamma``, compliance ``alpha_H = 1 / lambda'``;

so that the energy density is ``mu/2 tr(F^T F) + lambda'/2 (det F - gamma)^2`` (Smith et al.
2018 without the log term). ``mu`` and ``lambda`` are the Lamé parameters; the kernel uses
``lambda' = lambda + mu`` and ``gamma = 1 + mu / lambda'``. Linearising around ``F = I`` gives
``mu |eps|^2 + (lambda' - mu)/2 tr(eps)^2 = mu |eps|^2 + lambda/2 tr(eps)^2``: exactly linear
elasticity with the Lamé parameters, and ``F = I`` is stress free. Both constraints of a tet
are solved together as one 2x2 system: at rest their gradients are parallel and solving
them one after the other would let the non-zero ``C_D = sqrt(3)`` drift the rest shape.

Parallel Gauss-Seidel. Tets are coloured so that no two tets of one colour share a vertex;
the tets of one colour can then be projected concurrently without races. ``order`` lists
the tets colour by colour. On CUDA one launch per colour is required. Warp's CPU backend
executes the threads of a launch one after the other in index order, so a single launch over
the whole colour-sorted list computes exactly what the per-colour launches compute (tested
in ``tests/test_sim_physics.py``), with one launch per iteration instead of one per colour.

Contacts are analytic half-spaces ("surfaces"): surface ``s`` keeps particles on the side
``dot(x - p_s, n_s) >= 0``. Surface 0 is usually the ground (z = 0, n = +Z); the others are
kinematic plates whose point moves linearly from ``surf_start`` to ``surf_end`` over the
step. ``contact_depth[i, s]`` accumulates the normal correction surface ``s`` applied to
particle ``i`` in this substep (its normal impulse times dt / m); position-level Coulomb
friction bounds the tangential correction ``contact_friction[i, s]`` by ``mu * depth``
(Macklin et al. 2014, "Unified particle physics"). Friction is re-evaluated at every contact
projection inside the iterations, so it converges together with the elastic solve; applying
it once after the iterations instead locks in the unconverged, sweep-order-dependent
tangential state of the contact layer and makes bodies rock on landing. The force reported
per surface is ``m (depth n + friction) / dt^2``, averaged over the substeps.
"""

from __future__ import annotations

import warp as wp

# Forward-only kernels: no adjoints to generate (faster first compile).
wp.set_module_options({"enable_backward": False})

__all__ = [
    "sim_predict",
    "sim_solve_tets",
    "sim_finalize",
    "sim_tet_stats",
    "sim_tet_forces",
]

#: Below this deviatoric value (||F||_F) the deviatoric gradient F/||F|| has no direction:
#: the tet collapsed to a point. Skip the deviatoric part there; the hydrostatic part still
#: acts (its gradient, the cofactor, stays defined).
_MIN_NORM_F = wp.constant(1.0e-6)
#: Determinant of the (scaled) 2x2 system below which the coupled solve falls back to two
#: independent 1x1 solves (only for near-zero compliance with parallel gradients).
_MIN_DET = wp.constant(1.0e-10)


@wp.func
def _surface_point(s: int, surf_start: wp.array(dtype=wp.vec3), surf_end: wp.array(dtype=wp.vec3), alpha: float):
    return surf_start[s] + (surf_end[s] - surf_start[s]) * alpha


@wp.func
def _contact(
    i: int,
    x: wp.vec3,
    x_start: wp.vec3,
    surf_normal: wp.array(dtype=wp.vec3),
    surf_start: wp.array(dtype=wp.vec3),
    surf_end: wp.array(dtype=wp.vec3),
    alpha0: float,
    alpha1: float,
    n_surf: int,
    surf_friction: wp.array(dtype=float),
    contact_depth: wp.array2d(dtype=float),
    contact_friction: wp.array2d(dtype=wp.vec3),
):
    """Push ``x`` out of every half-space it penetrates and apply Coulomb friction.

    ``contact_depth[i, s]`` accumulates the normal correction of this substep (the normal
    impulse times dt / m). ``contact_friction[i, s]`` is the tangential correction applied so
    far; each call replaces it by the Coulomb-limited cancellation of the slip the particle
    would have without it (static: all of it, kinetic: ``mu * depth`` of it), so repeated
    calls during the iterations converge with the elastic solve instead of piling up.
    """
    y = x
    for s in range(n_surf):
        n = surf_normal[s]
        d = wp.dot(y - _surface_point(s, surf_start, surf_end, alpha1), n)
        if d < 0.0:
            y = y - d * n
            contact_depth[i, s] = contact_depth[i, s] - d
        depth = contact_depth[i, s]
        if depth > 0.0:
            f_old = contact_friction[i, s]
            disp_s = (surf_end[s] - surf_start[s]) * (alpha1 - alpha0)
            rel = (y - x_start) - disp_s
            slip = rel - wp.dot(rel, n) * n - f_old  # tangential slip without friction
            ls = wp.length(slip)
            lim = surf_friction[s] * depth
            f_new = wp.vec3(0.0)
            if ls > 0.0:
                if ls <= lim:
                    f_new = -slip  # static: no slip
                else:
                    f_new = -slip * (lim / ls)  # kinetic: slip reduced by mu * depth
            y = y + (f_new - f_old)
            contact_friction[i, s] = f_new
    return y


@wp.kernel
def sim_predict(
    q_in: wp.array(dtype=wp.vec3),  # [N]
    qd_in: wp.array(dtype=wp.vec3),  # [N]
    inv_mass: wp.array(dtype=float),  # [N]
    gravity: wp.vec3,
    dt: float,
    n_surf: int,
    q_out: wp.array(dtype=wp.vec3),  # [N] (may alias q_in)
    q_start: wp.array(dtype=wp.vec3),  # [N]
    qd_start: wp.array(dtype=wp.vec3),  # [N]
    contact_depth: wp.array2d(dtype=float),  # [N, S]
    contact_friction: wp.array2d(dtype=wp.vec3),  # [N, S]
):
    i = wp.tid()
    x = q_in[i]
    v = qd_in[i]
    q_start[i] = x
    qd_start[i] = v
    if inv_mass[i] > 0.0:
        v = v + gravity * dt
        x = x + v * dt
    q_out[i] = x
    for s in range(n_surf):
        contact_depth[i, s] = 0.0
        contact_friction[i, s] = wp.vec3(0.0)


@wp.func
def _cofactor_cols(f0: wp.vec3, f1: wp.vec3, f2: wp.vec3):
    """Columns of cof(F) = d det(F) / dF for F = [f0 f1 f2]."""
    return wp.cross(f1, f2), wp.cross(f2, f0), wp.cross(f0, f1)


@wp.kernel
def sim_solve_tets(
    order: wp.array(dtype=wp.int32),  # [M] tets sorted by colour
    offset: int,
    q: wp.array(dtype=wp.vec3),  # [N] in/out
    inv_mass: wp.array(dtype=float),  # [N]
    tet_indices: wp.array2d(dtype=wp.int32),  # [M, 4]
    tet_dm_inv: wp.array(dtype=wp.mat33),  # [M]
    tet_volume: wp.array(dtype=float),  # [M] rest volume, m^3
    tet_mu: wp.array(dtype=float),  # [M] Lamé mu, Pa
    tet_lambda: wp.array(dtype=float),  # [M] Lamé lambda, Pa
    tet_stiffness_scale: wp.array(dtype=float),  # [M] in (0, 1]: stability limiter (solver.py)
    lambdas: wp.array(dtype=wp.vec2),  # [M] accumulated XPBD multipliers (dev, hyd)
    first_iteration: int,
    inv_dt2: float,
    q_start: wp.array(dtype=wp.vec3),  # [N] positions at the substep's start
    surf_normal: wp.array(dtype=wp.vec3),  # [S]
    surf_start: wp.array(dtype=wp.vec3),  # [S] surface points at the start of the STEP
    surf_end: wp.array(dtype=wp.vec3),  # [S] surface points at the end of the STEP
    alpha0: float,  # fraction of the step at the substep's start
    alpha1: float,  # fraction of the step at the substep's end
    n_surf: int,
    surf_friction: wp.array(dtype=float),  # [S]
    contact_depth: wp.array2d(dtype=float),  # [N, S]
    contact_friction: wp.array2d(dtype=wp.vec3),  # [N, S]
):
    t = order[offset + wp.tid()]
    i0 = tet_indices[t, 0]
    i1 = tet_indices[t, 1]
    i2 = tet_indices[t, 2]
    i3 = tet_indices[t, 3]
    x0 = q[i0]
    x1 = q[i1]
    x2 = q[i2]
    x3 = q[i3]
    w0 = inv_mass[i0]
    w1 = inv_mass[i1]
    w2 = inv_mass[i2]
    w3 = inv_mass[i3]

    Dinv = tet_dm_inv[t]
    F = wp.matrix_from_cols(x1 - x0, x2 - x0, x3 - x0) * Dinv
    f0 = wp.vec3(F[0, 0], F[1, 0], F[2, 0])
    f1 = wp.vec3(F[0, 1], F[1, 1], F[2, 1])
    f2 = wp.vec3(F[0, 2], F[1, 2], F[2, 2])

    mu = tet_mu[t]
    lam = tet_lambda[t] + mu  # stable Neo-Hookean lambda' (module docstring)
    gamma = 1.0 + mu / lam
    vol = tet_volume[t]

    # Deviatoric: C_D = ||F||_F, dC_D/dF = F / ||F||_F.
    c_dev = wp.sqrt(wp.dot(f0, f0) + wp.dot(f1, f1) + wp.dot(f2, f2))
    P_dev = wp.mat33(0.0)
    if c_dev > _MIN_NORM_F:
        P_dev = F * (1.0 / c_dev)
    # Hydrostatic: C_H = det F - gamma, dC_H/dF = cof F.
    c0, c1, c2 = _cofactor_cols(f0, f1, f2)
    c_hyd = wp.dot(f0, c0) - gamma
    P_hyd = wp.matrix_from_cols(c0, c1, c2)

    # dC/dx_k for k = 1..3 are the columns of P Dm^-T; vertex 0 gets minus their sum.
    G_dev = P_dev * wp.transpose(Dinv)
    G_hyd = P_hyd * wp.transpose(Dinv)
    d1 = wp.vec3(G_dev[0, 0], G_dev[1, 0], G_dev[2, 0])
    d2 = wp.vec3(G_dev[0, 1], G_dev[1, 1], G_dev[2, 1])
    d3 = wp.vec3(G_dev[0, 2], G_dev[1, 2], G_dev[2, 2])
    d0 = -(d1 + d2 + d3)
    h1 = wp.vec3(G_hyd[0, 0], G_hyd[1, 0], G_hyd[2, 0])
    h2 = wp.vec3(G_hyd[0, 1], G_hyd[1, 1], G_hyd[2, 1])
    h3 = wp.vec3(G_hyd[0, 2], G_hyd[1, 2], G_hyd[2, 2])
    h0 = -(h1 + h2 + h3)

    a_dd = w0 * wp.dot(d0, d0) + w1 * wp.dot(d1, d1) + w2 * wp.dot(d2, d2) + w3 * wp.dot(d3, d3)
    a_dh = w0 * wp.dot(d0, h0) + w1 * wp.dot(d1, h1) + w2 * wp.dot(d2, h2) + w3 * wp.dot(d3, h3)
    a_hh = w0 * wp.dot(h0, h0) + w1 * wp.dot(h1, h1) + w2 * wp.dot(h2, h2) + w3 * wp.dot(h3, h3)

    lam_acc = wp.vec2(0.0, 0.0)
    if first_iteration == 0:
        lam_acc = lambdas[t]
    # XPBD time-scaled compliances alpha~ = alpha / (V dt^2).
    ks = tet_stiffness_scale[t]
    comp_dev = inv_dt2 / (ks * mu * vol)
    comp_hyd = inv_dt2 / (ks * lam * vol)

    a00 = a_dd + comp_dev
    a11 = a_hh + comp_hyd
    a01 = a_dh
    b0 = -c_dev - comp_dev * lam_acc[0]
    b1 = -c_hyd - comp_hyd * lam_acc[1]
    if c_dev <= _MIN_NORM_F:
        b0 = 0.0
        a01 = 0.0
    # Scale the system to O(1) so that float32 products cannot overflow.
    sc = 1.0 / wp.max(wp.max(a00, a11), 1.0e-30)
    a00 = a00 * sc
    a11 = a11 * sc
    a01 = a01 * sc
    b0 = b0 * sc
    b1 = b1 * sc
    det = a00 * a11 - a01 * a01
    dl_dev = float(0.0)
    dl_hyd = float(0.0)
    if det > _MIN_DET:
        dl_dev = (b0 * a11 - a01 * b1) / det
        dl_hyd = (a00 * b1 - a01 * b0) / det
    else:
        if a00 > 0.0:
            dl_dev = b0 / a00
        if a11 > 0.0:
            dl_hyd = b1 / a11
    lambdas[t] = wp.vec2(lam_acc[0] + dl_dev, lam_acc[1] + dl_hyd)

    x0 = x0 + w0 * (d0 * dl_dev + h0 * dl_hyd)
    x1 = x1 + w1 * (d1 * dl_dev + h1 * dl_hyd)
    x2 = x2 + w2 * (d2 * dl_dev + h2 * dl_hyd)
    x3 = x3 + w3 * (d3 * dl_dev + h3 * dl_hyd)

    if n_surf > 0:
        if w0 > 0.0:
            x0 = _contact(i0, x0, q_start[i0], surf_normal, surf_start, surf_end, alpha0, alpha1, n_surf,
                          surf_friction, contact_depth, contact_friction)
        if w1 > 0.0:
            x1 = _contact(i1, x1, q_start[i1], surf_normal, surf_start, surf_end, alpha0, alpha1, n_surf,
                          surf_friction, contact_depth, contact_friction)
        if w2 > 0.0:
            x2 = _contact(i2, x2, q_start[i2], surf_normal, surf_start, surf_end, alpha0, alpha1, n_surf,
                          surf_friction, contact_depth, contact_friction)
        if w3 > 0.0:
            x3 = _contact(i3, x3, q_start[i3], surf_normal, surf_start, surf_end, alpha0, alpha1, n_surf,
                          surf_friction, contact_depth, contact_friction)

    q[i0] = x0
    q[i1] = x1
    q[i2] = x2
    q[i3] = x3


@wp.kernel
def sim_finalize(
    q: wp.array(dtype=wp.vec3),  # [N] in/out
    q_start: wp.array(dtype=wp.vec3),  # [N]
    qd_start: wp.array(dtype=wp.vec3),  # [N]
    inv_mass: wp.array(dtype=float),  # [N]
    mass: wp.array(dtype=float),  # [N]
    surf_normal: wp.array(dtype=wp.vec3),  # [S]
    surf_start: wp.array(dtype=wp.vec3),  # [S] surface point at the start of the STEP
    surf_end: wp.array(dtype=wp.vec3),  # [S] surface point at the end of the STEP
    alpha0: float,  # fraction of the step at the substep's start
    alpha1: float,  # fraction of the step at the substep's end
    surf_friction: wp.array(dtype=float),  # [S] Coulomb coefficient
    surf_restitution: wp.array(dtype=float),  # [S]
    n_surf: int,
    contact_depth: wp.array2d(dtype=float),  # [N, S]
    contact_friction: wp.array2d(dtype=wp.vec3),  # [N, S]
    dt: float,
    bounce_threshold: float,  # m/s: slower approach speeds do not bounce
    damping_factor: float,  # velocity scale per substep, in (0, 1]
    force_scale: float,  # 1 / (dt^2 * substeps): turns m * displacement into mean force
    qd_out: wp.array(dtype=wp.vec3),  # [N]
    surf_force: wp.array(dtype=wp.vec3),  # [S] += force on the bodies from surface s, N
):
    i = wp.tid()
    if inv_mass[i] == 0.0:
        qd_out[i] = wp.vec3(0.0)
        return
    x_start = q_start[i]
    # Last contact + friction pass: particles that belong to no tet, and the final state.
    x = _contact(i, q[i], x_start, surf_normal, surf_start, surf_end, alpha0, alpha1, n_surf,
                 surf_friction, contact_depth, contact_friction)
    m = mass[i]
    inv_dt = 1.0 / dt
    for s in range(n_surf):
        depth = contact_depth[i, s]
        if depth > 0.0:
            wp.atomic_add(surf_force, s, (surf_normal[s] * depth + contact_friction[i, s]) * (m * force_scale))
    v = (x - x_start) * inv_dt
    # Restitution on the normal velocity relative to the surface (Müller et al. 2020).
    for s in range(n_surf):
        if contact_depth[i, s] > 0.0:
            n = surf_normal[s]
            vs = (surf_end[s] - surf_start[s]) * ((alpha1 - alpha0) * inv_dt)
            vn_pre = wp.dot(qd_start[i] - vs, n)
            if vn_pre < -bounce_threshold:
                vn = wp.dot(v - vs, n)
                v = v + n * (-surf_restitution[s] * vn_pre - vn)
    q[i] = x
    qd_out[i] = v * damping_factor


@wp.kernel
def sim_tet_stats(
    q: wp.array(dtype=wp.vec3),  # [N]
    tet_indices: wp.array2d(dtype=wp.int32),  # [M, 4]
    stats: wp.array(dtype=float),  # [2] += (inverted count, total signed volume m^3)
):
    t = wp.tid()
    x0 = q[tet_indices[t, 0]]
    vol = wp.dot(q[tet_indices[t, 1]] - x0, wp.cross(q[tet_indices[t, 2]] - x0, q[tet_indices[t, 3]] - x0)) / 6.0
    if vol <= 0.0:
        wp.atomic_add(stats, 0, 1.0)
    wp.atomic_add(stats, 1, vol)


@wp.kernel
def sim_tet_forces(
    q: wp.array(dtype=wp.vec3),  # [N]
    tet_indices: wp.array2d(dtype=wp.int32),  # [M, 4]
    tet_dm_inv: wp.array(dtype=wp.mat33),  # [M]
    tet_volume: wp.array(dtype=float),  # [M]
    tet_mu: wp.array(dtype=float),  # [M]
    tet_lambda: wp.array(dtype=float),  # [M]
    forces: wp.array(dtype=wp.vec3),  # [N] += elastic force, N
    energy: wp.array(dtype=float),  # [1] += elastic energy relative to rest, J
):
    """Elastic forces ``-dE/dx`` of the energy the XPBD constraints encode (diagnostics
    and tests: a rigid motion must give zero force)."""
    t = wp.tid()
    i0 = tet_indices[t, 0]
    i1 = tet_indices[t, 1]
    i2 = tet_indices[t, 2]
    i3 = tet_indices[t, 3]
    x0 = q[i0]
    Dinv = tet_dm_inv[t]
    F = wp.matrix_from_cols(q[i1] - x0, q[i2] - x0, q[i3] - x0) * Dinv
    f0 = wp.vec3(F[0, 0], F[1, 0], F[2, 0])
    f1 = wp.vec3(F[0, 1], F[1, 1], F[2, 1])
    f2 = wp.vec3(F[0, 2], F[1, 2], F[2, 2])
    mu = tet_mu[t]
    lam = tet_lambda[t] + mu
    gamma = 1.0 + mu / lam
    vol = tet_volume[t]
    c0, c1, c2 = _cofactor_cols(f0, f1, f2)
    J = wp.dot(f0, c0)
    # Psi = mu/2 (tr F^T F - 3) + lambda'/2 ((J - gamma)^2 - (1 - gamma)^2): zero at rest.
    psi = 0.5 * mu * (wp.dot(f0, f0) + wp.dot(f1, f1) + wp.dot(f2, f2) - 3.0)
    psi = psi + 0.5 * lam * ((J - gamma) * (J - gamma) - (1.0 - gamma) * (1.0 - gamma))
    wp.atomic_add(energy, 0, vol * psi)
    P = F * mu + wp.matrix_from_cols(c0, c1, c2) * (lam * (J - gamma))
    G = P * wp.transpose(Dinv) * vol
    g1 = wp.vec3(G[0, 0], G[1, 0], G[2, 0])
    g2 = wp.vec3(G[0, 1], G[1, 1], G[2, 1])
    g3 = wp.vec3(G[0, 2], G[1, 2], G[2, 2])
    wp.atomic_add(forces, i0, g1 + g2 + g3)
    wp.atomic_sub(forces, i1, g1)
    wp.atomic_sub(forces, i2, g2)
    wp.atomic_sub(forces, i3, g3)
