"""Vertex Block Descent kernels for tetrahedral stable Neo-Hookean solids (Warp only).

One substep of :class:`holowarp.sim.SolverVBDNeoHookean` launches, in order:

1. :func:`vbd_predict` (per particle): the inertial target ``y = x + h v + h^2 g`` of implicit
   Euler (or BDF2's, with ``h_e = 2h/3`` in place of ``h`` in the potential and the
   displacement ``lag = d_n / 3`` that makes no velocity; see
   :mod:`holowarp.sim.solver`) and the substep's start state; :func:`vbd_component_inertia`,
   :func:`vbd_component_motion` and :func:`vbd_rigid_guess`: the initial guess, every
   face-connected piece moved rigidly with its mean and angular velocity (plus the part of
   gravity it accelerated with in the last substep: VBD's adaptive initialisation, Chen et
   al. 2024 §3.5) and a share of each particle's own extrapolation;
   :func:`vbd_guess_depth`, :func:`vbd_land_components` and :func:`vbd_apply_shift`: pieces
   that would enter the ground or a plate land on it rigidly (and slide on it with Coulomb
   friction); :func:`vbd_guess_project`: particles still behind one are pushed out.
2. Only when bodies can touch: :func:`vbd_triangle_bounds` (swept boxes of the surface
   triangles, refitted into a ``wp.Bvh``), :func:`vbd_vertex_normals` and
   :func:`vbd_detect_contacts` (per surface vertex, the closest triangle of every other
   face-connected component whose swept box meets the vertex's swept box),
   :func:`vbd_count_reverse_contacts` and :func:`vbd_fill_reverse_contacts` (each triangle
   corner's list of the contacts it takes part in); :func:`vbd_support_levels`,
   :func:`vbd_body_landing` and :func:`vbd_merge_shift`: the guess of a piece falling on
   another lands on it rigidly, as on the ground.
3. ``iterations`` times :func:`vbd_solve_vertices` over the vertices colour by colour
   (Gauss-Seidel): every vertex moves to the minimiser of a majoriser of the step's
   incremental potential with all other vertices held, subject to the ground and plate
   half-spaces.
4. :func:`vbd_finalize`: position and velocity (``(displacement - lag) / h_e``), restitution,
   damping, the acceleration for the next initial guess, BDF2's history, contact forces.

The iterate is each particle's displacement over the substep, not its position: a float32
position differenced with the start position to get a velocity keeps only
``ulp(x) / h`` of it, which at 0.3 m and 128 substeps of 1/60 s is 2e-4 m/s per substep and
made free fall drift 6 mm in 0.13 s (25 mm at 256 substeps). Positions enter only as the
start positions plus the displacement, differenced separately.

Material: the stable Neo-Hookean energy density of Smith et al. 2018 (eq. 14, with its
log term), ``psi(F) = mu'/2 (I_C - 3) + lambda'/2 (J - alpha)^2 - mu'/2 log(I_C + 1)`` with
``I_C = tr F^T F``, ``J = det F``, ``mu' = 4/3 mu``, ``lambda' = lambda + 5/6 mu`` and
``alpha = 1 + 3 mu' / (4 lambda')`` (``mu``, ``lambda`` the Lamé parameters): it linearises
to linear elasticity with exactly those parameters and ``F = I`` is stress free. The log
term matters: without it (Newton's ``SolverVBD`` drops it) ``F = 0`` is a local minimum
with Hessian ``mu I``, and a soft, compressible body hit hard enough collapses into it and
stays flat (measured: E = 10 kPa, nu = 0 dropped from 0.2 m).

Why the block step is safe at any step length. A vertex ``i`` enters ``F = Ds Dm^-1`` of
each of its tets as the rank-one term ``x_i b_i^T`` (``b_i`` the rest shape-function
gradient: a row of ``Dm^-1``, or minus their sum for corner 0). By the matrix determinant
lemma ``J`` is then *affine* in ``x_i``, with gradient ``c = cof(F) b_i`` independent of
``x_i``, so the volume term ``lambda'/2 (J - alpha)^2`` is an exact quadratic in ``x_i`` with
Hessian ``lambda' c c^T``. The rest, ``phi(I_C) = mu'/2 (I_C - log(I_C + 1))``, has the
Hessian ``2 phi'(I_C) |b|^2 I + 4 phi''(I_C) (F b)(F b)^T`` in ``x_i``, and since
``phi' < mu'/2``, ``phi'' <= mu' / (2 (I_C + 1)^2)`` and ``|F b|^2 <= I_C |b|^2``, that is below
``3/2 mu' |b|^2 I`` everywhere. So the quadratic with the exact gradient of the vertex's
share of the incremental potential

    G_i(x) = m_i / (2 h^2) |x - y_i|^2 + sum_t V_t psi(F_t(x))

and the constant, positive definite Hessian bound

    H_i = m_i / h^2 I + sum_t V_t (3/2 mu' |b|^2 I + lambda' c c^T)

lies above ``G_i`` and touches it at the current position (a majoriser). One Newton step
``x += H_i^-1 (-grad G_i)`` lands on the majoriser's minimiser, so ``G_i`` (and the total
potential, which is bounded below) never increases: the iteration cannot diverge for any
step length, stiffness, Poisson ratio or tet shape, no tet needs softening, and more
iterations only converge further towards the implicit Euler solution (majorise-minimise
block coordinate descent). At rest the bound is 2 mu |b|^2 against the exact mu |b|^2 in
the shear directions; measured, it costs 5-25 % more iterations than exact Newton blocks at
nu = 0.45, which carry no such guarantee. Inverted tets need no special case: ``J`` keeps
its gradient through zero and the ``(J - alpha)^2`` term pushes them back.

Contacts.

- Ground and plates are analytic half-spaces ``dot(x - p_s, n_s) >= 0`` (``p_s`` moves
  linearly over the step). They are hard constraints of the vertex's block problem: the
  unconstrained minimiser is projected onto each violated plane in the ``H_i`` metric,
  which is the exact constrained minimiser for one active plane; the multiplier is the
  normal force (N). Coulomb friction is solved in the same block: the vertex sticks (no
  tangential slip relative to the surface over the substep) when holding it needs at most
  ``mu`` times the normal force, and otherwise slides with its slip shortened by that
  bound (isotropic tangential stiffness, the mean of ``H_i`` over the tangent plane).
- Between bodies and between face-disconnected pieces of one mesh: vertex-triangle
  penalty contact ``k/2 max(0, r - dot(x_v - p, n))^2`` where ``p = sum w_j x_j`` is the
  closest point on the triangle at detection (barycentric ``w`` kept for the substep) and
  ``n`` the unit direction from it to the vertex (the outward face normal when the vertex
  is already behind the face). Fixing ``n`` and ``w`` for the substep makes the contact
  energy a fixed convex function, so the descent argument above still holds; the plane
  through ``p`` with normal ``n`` separates the vertex from a convex neighbour, so a vertex
  cannot tunnel through it however far it moves in one substep. ``r`` is the contact
  radius (bodies rest that far apart), ``k`` a multiple of the stiffer side's elastic
  stiffness. Friction is the smoothed Coulomb friction of IPC (Li et al. 2020) on the
  tangential displacement of the vertex relative to the triangle over the substep, with
  the normal force ``k max(0, r - d)``: force ``-mu f_n u / max(|u|, eps)``, curvature
  ``mu f_n / max(|u|, eps)`` (the majoriser of ``|u|`` that touches it at the current slip,
  so a friction step can stop a slip but not reverse it).
  Both the vertex and the triangle's corners feel every contact (corner ``j`` with weight
  ``w_j``), through each corner's reverse contact list, so Gauss-Seidel sees action and
  reaction.

Parallel Gauss-Seidel. Vertices are coloured so that no two vertices of one tet share a
colour; the vertices of one colour are then independent through the material. On CUDA one
launch per colour is required (vertices of one colour touching through a contact are then
updated together, as in Newton's VBD). Warp's CPU backend runs the threads of a launch one
after the other in index order, so a single launch over the colour-sorted list computes
exactly what the per-colour launches compute, with one launch per iteration.
"""

from __future__ import annotations

import warp as wp

# Forward-only kernels: no adjoints to generate (faster first compile).
wp.set_module_options({"enable_backward": False})

__all__ = [
    "MAX_CONTACTS",
    "TetData",
    "SurfaceData",
    "ContactData",
    "closest_point_triangle",
    "vbd_predict",
    "vbd_component_inertia",
    "vbd_component_motion",
    "vbd_rigid_guess",
    "vbd_guess_depth",
    "vbd_land_components",
    "vbd_apply_shift",
    "vbd_support_levels",
    "vbd_body_landing",
    "vbd_merge_shift",
    "vbd_guess_project",
    "vbd_solve_vertices",
    "vbd_finalize",
    "vbd_triangle_bounds",
    "vbd_vertex_normals",
    "vbd_detect_contacts",
    "vbd_count_reverse_contacts",
    "vbd_fill_reverse_contacts",
    "vbd_tet_bounds",
    "vbd_penetration",
    "sim_tet_stats",
    "sim_tet_forces",
    "vbd_closest_points",
]

#: Contact slots per surface vertex: at most this many other components (the closest) are
#: in contact with one vertex in one substep.
MAX_CONTACTS = 4
_K = wp.constant(MAX_CONTACTS)

#: Below this length (m) the direction from a closest point to the vertex is taken from the
#: triangle's normal instead.
_MIN_DIST = wp.constant(1.0e-9)
#: Active-set rounds of a vertex's contact block problem (module docstring); one more than
#: the usual need (a contact becoming active, then settling), so the set rarely changes in
#: the last round.
_CONTACT_ROUNDS = 3


@wp.struct
class TetData:
    """Static tet data the vertex solve reads (all arrays on one device)."""

    indices: wp.array2d(dtype=wp.int32)  # [M, 4]
    dm_inv: wp.array(dtype=wp.mat33)  # [M] inverse rest edge matrix [b-a, c-a, d-a]^-1
    mu_v: wp.array(dtype=float)  # [M] V mu', J (mu' = 4/3 mu)
    lam_v: wp.array(dtype=float)  # [M] V lambda', J (lambda' = lambda + 5/6 mu)
    alpha: wp.array(dtype=float)  # [M] 1 + 3 mu' / (4 lambda')
    adj_offsets: wp.array(dtype=wp.int32)  # [N + 1] CSR offsets of each vertex's tets
    adj: wp.array(dtype=wp.int32)  # [4 M] packed 4 t + corner


@wp.struct
class SurfaceData:
    """The contact half-spaces (ground, plates) over one step; ``p_s`` moves linearly from
    ``start`` to ``end``; the substep covers the fractions ``alpha0`` to ``alpha1``."""

    count: int
    normal: wp.array(dtype=wp.vec3)  # [S] unit normals pointing into the free side
    start: wp.array(dtype=wp.vec3)  # [S] plane points at the start of the step, m
    end: wp.array(dtype=wp.vec3)  # [S] plane points at the end of the step, m
    friction: wp.array(dtype=float)  # [S] Coulomb coefficient
    alpha0: float
    alpha1: float


@wp.struct
class ContactData:
    """Vertex-triangle contacts of one substep (see the module docstring)."""

    enabled: int
    radius: float  # m, contact distance r
    friction_eps: float  # m, tangential displacement below which friction is viscous
    tri: wp.array2d(dtype=wp.int32)  # [T, 3] surface triangles (outward wound)
    slot_count: wp.array(dtype=wp.int32)  # [N] contacts of each vertex (<= MAX_CONTACTS)
    slot_tri: wp.array2d(dtype=wp.int32)  # [N, K] triangle
    slot_w: wp.array2d(dtype=wp.vec3)  # [N, K] barycentric weights of the closest point
    slot_n: wp.array2d(dtype=wp.vec3)  # [N, K] unit contact normal (towards the vertex)
    slot_k: wp.array2d(dtype=float)  # [N, K] penalty stiffness, N/m
    slot_mu: wp.array2d(dtype=float)  # [N, K] Coulomb coefficient
    rev_offsets: wp.array(dtype=wp.int32)  # [N + 1] CSR offsets of each corner's contacts
    rev: wp.array(dtype=wp.int32)  # [R] packed 3 (K v + slot) + corner


@wp.func
def _surface_point(surf: SurfaceData, s: int, alpha: float):
    return surf.start[s] + (surf.end[s] - surf.start[s]) * alpha


@wp.func
def _gap(qs: wp.array(dtype=wp.vec3), dq: wp.array(dtype=wp.vec3), v: int, ja: int, jb: int, jc: int, w: wp.vec3):
    """x_v - (w_a x_a + w_b x_b + w_c x_c) with x = qs + dq, the start positions and the
    (small) displacements differenced apart so float32 keeps the displacements' digits."""
    return (qs[v] - (qs[ja] * w[0] + qs[jb] * w[1] + qs[jc] * w[2])) + (dq[v] - (dq[ja] * w[0] + dq[jb] * w[1]
                                                                                + dq[jc] * w[2]))


@wp.func
def _slip(dq: wp.array(dtype=wp.vec3), lag: wp.array(dtype=wp.vec3), v: int, ja: int, jb: int, jc: int, w: wp.vec3):
    """The vertex's velocity-making displacement over the substep (``dq - lag``: the
    integrator's velocity is ``(dq - lag) / h_e``) relative to the triangle point's."""
    return (dq[v] - lag[v]) - ((dq[ja] - lag[ja]) * w[0] + (dq[jb] - lag[jb]) * w[1] + (dq[jc] - lag[jc]) * w[2])


@wp.func
def closest_point_triangle(p: wp.vec3, a: wp.vec3, b: wp.vec3, c: wp.vec3):
    """Barycentric weights (wa, wb, wc) of the point of triangle abc closest to p
    (Ericson, Real-Time Collision Detection, 5.1.5)."""
    ab = b - a
    ac = c - a
    ap = p - a
    d1 = wp.dot(ab, ap)
    d2 = wp.dot(ac, ap)
    if d1 <= 0.0 and d2 <= 0.0:
        return wp.vec3(1.0, 0.0, 0.0)
    bp = p - b
    d3 = wp.dot(ab, bp)
    d4 = wp.dot(ac, bp)
    if d3 >= 0.0 and d4 <= d3:
        return wp.vec3(0.0, 1.0, 0.0)
    vc = d1 * d4 - d3 * d2
    if vc <= 0.0 and d1 >= 0.0 and d3 <= 0.0:
        v = d1 / (d1 - d3)
        return wp.vec3(1.0 - v, v, 0.0)
    cp = p - c
    d5 = wp.dot(ab, cp)
    d6 = wp.dot(ac, cp)
    if d6 >= 0.0 and d5 <= d6:
        return wp.vec3(0.0, 0.0, 1.0)
    vb = d5 * d2 - d1 * d6
    if vb <= 0.0 and d2 >= 0.0 and d6 <= 0.0:
        w = d2 / (d2 - d6)
        return wp.vec3(1.0 - w, 0.0, w)
    va = d3 * d6 - d5 * d4
    if va <= 0.0 and (d4 - d3) >= 0.0 and (d5 - d6) >= 0.0:
        w = (d4 - d3) / ((d4 - d3) + (d5 - d6))
        return wp.vec3(0.0, 1.0 - w, w)
    denom = 1.0 / (va + vb + vc)
    v = vb * denom
    w = vc * denom
    return wp.vec3(1.0 - v - w, v, w)


@wp.kernel
def vbd_closest_points(
    p: wp.array(dtype=wp.vec3),  # [Q]
    tri_x: wp.array2d(dtype=wp.vec3),  # [Q, 3]
    out: wp.array(dtype=wp.vec3),  # [Q] barycentric weights
):
    """Test hook for :func:`closest_point_triangle`."""
    i = wp.tid()
    out[i] = closest_point_triangle(p[i], tri_x[i, 0], tri_x[i, 1], tri_x[i, 2])


@wp.func
def _target(lag: wp.vec3, v: wp.vec3, acc: wp.vec3, g: wp.vec3, h: float, bdf2: int):
    """The inertial target's displacement ``y - x_n`` over a substep under the acceleration
    ``g``: implicit Euler's ``(v + g h) h``, or BDF2's
    ``d_n / 3 + 2h/3 (4/3 v_n - 1/3 v_(n-1)) + (2h/3)^2 g`` with ``lag = d_n / 3`` and
    ``v_(n-1) = v_n - h acc`` (``acc`` the last substep's acceleration)."""
    if bdf2 != 0:
        return lag + (v + acc * (h / 3.0)) * (2.0 * h / 3.0) + g * (4.0 * h * h / 9.0)
    return (v + g * h) * h


@wp.kernel
def vbd_predict(
    q_in: wp.array(dtype=wp.vec3),  # [N]
    qd_in: wp.array(dtype=wp.vec3),  # [N]
    qdd_in: wp.array(dtype=wp.vec3),  # [N] acceleration of the last substep
    mass: wp.array(dtype=float),  # [N]
    inv_mass: wp.array(dtype=float),  # [N]
    particle_component: wp.array(dtype=wp.int32),  # [N]
    dq_in: wp.array(dtype=wp.vec3),  # [N] displacement over the last substep (BDF2 only)
    gravity: wp.vec3,
    h: float,
    bdf2: int,  # 1: BDF2 (needs the last substep, of the same h), 0: implicit Euler
    surf: SurfaceData,
    q_start: wp.array(dtype=wp.vec3),  # [N]
    qd_start: wp.array(dtype=wp.vec3),  # [N]
    inertia: wp.array(dtype=wp.vec3),  # [N] y - x: the inertial target's displacement
    lag: wp.array(dtype=wp.vec3),  # [N] the part of the displacement that makes no velocity
    surf_force: wp.array2d(dtype=wp.vec3),  # [N, S] cleared
    sum_m: wp.array(dtype=float),  # [C] += mass of each component (zeroed first)
    sum_mx: wp.array(dtype=wp.vec3),  # [C] += m x
    sum_mv: wp.array(dtype=wp.vec3),  # [C] += m v
    sum_ma: wp.array(dtype=wp.vec3),  # [C] += m a (last substep)
    sum_ml: wp.array(dtype=wp.vec3),  # [C] += m lag
):
    i = wp.tid()
    x = q_in[i]
    v = qd_in[i]
    q_start[i] = x
    qd_start[i] = v
    for s in range(surf.count):
        surf_force[i, s] = wp.vec3(0.0)
    if inv_mass[i] == 0.0:
        inertia[i] = wp.vec3(0.0)
        lag[i] = wp.vec3(0.0)
    else:
        # BDF2: the velocity is (dq - d_n / 3) / (2h/3) (solver module docstring).
        d = wp.vec3(0.0)
        if bdf2 != 0:
            d = dq_in[i] * (1.0 / 3.0)
        inertia[i] = _target(d, v, qdd_in[i], gravity, h, bdf2)
        lag[i] = d
    c = particle_component[i]
    m = mass[i]
    wp.atomic_add(sum_m, c, m)
    wp.atomic_add(sum_mx, c, x * m)
    wp.atomic_add(sum_mv, c, v * m)
    wp.atomic_add(sum_ma, c, qdd_in[i] * m)
    wp.atomic_add(sum_ml, c, lag[i] * m)


@wp.kernel
def vbd_component_inertia(
    q: wp.array(dtype=wp.vec3),  # [N]
    qd: wp.array(dtype=wp.vec3),  # [N]
    mass: wp.array(dtype=float),  # [N]
    particle_component: wp.array(dtype=wp.int32),  # [N]
    sum_m: wp.array(dtype=float),  # [C]
    sum_mx: wp.array(dtype=wp.vec3),  # [C]
    ang: wp.array(dtype=wp.vec3),  # [C] += angular momentum about the COM, kg m^2/s
    inertia_tensor: wp.array(dtype=wp.mat33),  # [C] += inertia tensor about the COM, kg m^2
):
    i = wp.tid()
    c = particle_component[i]
    r = q[i] - sum_mx[c] / sum_m[c]
    m = mass[i]
    wp.atomic_add(ang, c, wp.cross(r, qd[i]) * m)
    wp.atomic_add(inertia_tensor, c, (wp.identity(n=3, dtype=float) * wp.dot(r, r) - wp.outer(r, r)) * m)


@wp.func
def _adaptive_gravity(acc: wp.vec3, gravity: wp.vec3):
    """The part of gravity a particle (or piece) accelerated with in the last substep
    (VBD's adaptive initialisation): all of it in free fall, none at rest on the ground."""
    g2 = wp.dot(gravity, gravity)
    if g2 > 0.0:
        return gravity * wp.clamp(wp.dot(acc, gravity) / g2, 0.0, 1.0)
    return wp.vec3(0.0)


@wp.func
def _extrapolate(lag: wp.vec3, v: wp.vec3, acc: wp.vec3, gravity: wp.vec3, h: float, bdf2: int):
    """The initial guess's displacement over a substep: the integrator's inertial target
    with only the adaptive part of gravity (all of it in free flight, so free flight is
    exact after one sweep)."""
    return _target(lag, v, acc, _adaptive_gravity(acc, gravity), h, bdf2)


@wp.kernel
def vbd_component_motion(
    sum_m: wp.array(dtype=float),  # [C]
    sum_mx: wp.array(dtype=wp.vec3),  # [C]
    sum_mv: wp.array(dtype=wp.vec3),  # [C]
    sum_ma: wp.array(dtype=wp.vec3),  # [C]
    sum_ml: wp.array(dtype=wp.vec3),  # [C]
    ang: wp.array(dtype=wp.vec3),  # [C]
    inertia_tensor: wp.array(dtype=wp.mat33),  # [C]
    gravity: wp.vec3,
    h: float,
    bdf2: int,
    com: wp.array(dtype=wp.vec3),  # [C] out: centre of mass
    disp: wp.array(dtype=wp.vec3),  # [C] out: translation of the guess over the substep
    rot: wp.array(dtype=wp.mat33),  # [C] out: rotation of the guess over the substep
):
    """Each piece's rigid motion over the substep: its mean velocity (plus the adaptive part
    of gravity) and its angular velocity I^-1 L, integrated exactly (Rodrigues)."""
    c = wp.tid()
    M = sum_m[c]
    com[c] = sum_mx[c] / M
    disp[c] = _extrapolate(sum_ml[c] / M, sum_mv[c] / M, sum_ma[c] / M, gravity, h, bdf2)
    I = inertia_tensor[c]
    R = wp.identity(n=3, dtype=float)
    scale = I[0, 0] + I[1, 1] + I[2, 2]
    if scale > 0.0 and wp.determinant(I) > 1.0e-9 * scale * scale * scale:
        w = wp.inverse(I) * ang[c]
        th = wp.length(w) * h
        if th > 1.0e-12:
            k = w / wp.length(w)
            K = wp.skew(k)
            R = R + K * wp.sin(th) + K * K * (1.0 - wp.cos(th))
    rot[c] = R


@wp.kernel
def vbd_rigid_guess(
    q_start: wp.array(dtype=wp.vec3),  # [N]
    qd_start: wp.array(dtype=wp.vec3),  # [N]
    qdd_in: wp.array(dtype=wp.vec3),  # [N]
    inv_mass: wp.array(dtype=float),  # [N]
    particle_component: wp.array(dtype=wp.int32),  # [N]
    component_free: wp.array(dtype=wp.int32),  # [C] 1: no fixed particle
    com: wp.array(dtype=wp.vec3),  # [C]
    disp: wp.array(dtype=wp.vec3),  # [C]
    rot: wp.array(dtype=wp.mat33),  # [C]
    lag: wp.array(dtype=wp.vec3),  # [N] (vbd_predict)
    gravity: wp.vec3,
    h: float,
    bdf2: int,
    beta: float,  # in [0, 1]: how much of each particle's own deformation rate to carry on
    dq: wp.array(dtype=wp.vec3),  # [N] out: the guess's displacement from q_start
):
    """The initial guess: each free piece moved rigidly over the substep, plus ``beta`` of
    the particle's own extrapolation beyond that. Extrapolating every particle fully carries
    the deformation rate forward; when an elastic wave crosses many tets in one substep, the
    elastic energy that a few sweeps cannot take back out becomes a bounce. The rigid part
    leaves the elastic energy where it was and is exact in free flight; ``beta`` (the
    solver's: about one tet crossed per substep) keeps waves alive at small substeps."""
    i = wp.tid()
    if inv_mass[i] == 0.0:
        dq[i] = wp.vec3(0.0)
        return
    c = particle_component[i]
    own = _extrapolate(lag[i], qd_start[i], qdd_in[i], gravity, h, bdf2)
    if component_free[c] != 0:
        r = q_start[i] - com[c]
        rigid = rot[c] * r - r + disp[c]
        dq[i] = rigid + (own - rigid) * beta
    else:
        dq[i] = own


@wp.kernel
def vbd_guess_depth(
    q_start: wp.array(dtype=wp.vec3),  # [N]
    dq: wp.array(dtype=wp.vec3),  # [N] the guess's displacement
    particle_component: wp.array(dtype=wp.int32),  # [N]
    surf: SurfaceData,
    depth: wp.array2d(dtype=float),  # [C, S] max over the piece of the depth behind surface s
):
    """How deep each piece's guess lies behind each half-space (negative: its closest
    particle's clearance). ``depth`` starts at -1e30."""
    i = wp.tid()
    c = particle_component[i]
    for s in range(surf.count):
        n = surf.normal[s]
        d = wp.dot(q_start[i] - _surface_point(surf, s, surf.alpha1), n) + wp.dot(dq[i], n)
        wp.atomic_max(depth, c, s, -d)


@wp.kernel
def vbd_land_components(
    component_free: wp.array(dtype=wp.int32),  # [C] 1: no fixed particle (may move rigidly)
    disp: wp.array(dtype=wp.vec3),  # [C] rigid translation of the guess
    sum_m: wp.array(dtype=float),  # [C] mass of each piece, kg
    sum_ma: wp.array(dtype=wp.vec3),  # [C] its momentum change rate in the last substep, N
    gravity: wp.vec3,
    h: float,
    surf: SurfaceData,
    depth: wp.array2d(dtype=float),  # [C, S]
    touch: float,  # m: a piece this close to a half-space counts as supported by it
    shift: wp.array(dtype=wp.vec3),  # [C] out: rigid correction of each piece
    eff_disp: wp.array(dtype=wp.vec3),  # [C] out: translation of the guess after landing
    level: wp.array(dtype=wp.int32),  # [C] out: 0 on a half-space, else "unsupported"
):
    """Land each free piece's guess rigidly on the ground and plates it would enter (an
    inelastic rigid landing), and slow its sliding on the ones it rests on by Coulomb's
    ``mu f_n h`` (``f_n`` per unit mass: the support the piece got in the last substep).
    The lift never exceeds the piece's own approach towards the surface, so a rotating
    piece that dips a corner in does not jump. Sweeps pass a surface's friction to the
    piece only through the elastic coupling, slowly; this gives the rigid part at once."""
    c = wp.tid()
    corr = wp.vec3(0.0)
    lv = int(1000000)
    for s in range(surf.count):
        dep = depth[c, s]
        if dep > -touch and component_free[c] != 0:
            lv = 0
            n = surf.normal[s]
            rel = disp[c] - (surf.end[s] - surf.start[s]) * (surf.alpha1 - surf.alpha0)
            if dep > 0.0:
                corr = corr + n * wp.min(dep, wp.max(-wp.dot(rel, n), 0.0))
            # support per unit mass: last substep's, and at least gravity's share normal to
            # the surface (a piece just set down has no last-substep support yet)
            fn = wp.max(wp.dot(sum_ma[c] / sum_m[c] - gravity, n), -wp.dot(gravity, n))
            tang = rel - n * wp.dot(rel, n)
            lt = wp.length(tang)
            if fn > 0.0 and lt > 0.0:
                corr = corr - tang * (wp.min(lt, surf.friction[s] * fn * h * h) / lt)
        elif dep > -touch:
            lv = 0
    shift[c] = corr
    eff_disp[c] = disp[c] + corr
    level[c] = lv


@wp.kernel
def vbd_apply_shift(
    dq: wp.array(dtype=wp.vec3),  # [N] in/out: the guess's displacement
    inv_mass: wp.array(dtype=float),  # [N]
    particle_component: wp.array(dtype=wp.int32),  # [N]
    component_free: wp.array(dtype=wp.int32),  # [C]
    shift: wp.array(dtype=wp.vec3),  # [C]
):
    i = wp.tid()
    c = particle_component[i]
    if inv_mass[i] > 0.0 and component_free[c] != 0:
        dq[i] = dq[i] + shift[c]


@wp.kernel
def vbd_support_levels(
    surface_vertices: wp.array(dtype=wp.int32),  # [Vs]
    particle_component: wp.array(dtype=wp.int32),  # [N]
    slot_count: wp.array(dtype=wp.int32),  # [N]
    slot_tri: wp.array2d(dtype=wp.int32),  # [N, K]
    tri_component: wp.array(dtype=wp.int32),  # [T]
    level: wp.array(dtype=wp.int32),  # [C] in/out: contact hops to a supported piece
):
    """One relaxation of each piece's support level (0: on the ground or a plate; k: in
    contact with a piece of level k - 1) over this substep's contacts."""
    v = surface_vertices[wp.tid()]
    a = particle_component[v]
    for s in range(slot_count[v]):
        b = tri_component[slot_tri[v, s]]
        if a != b:
            wp.atomic_min(level, a, level[b] + 1)
            wp.atomic_min(level, b, level[a] + 1)


@wp.kernel
def vbd_body_landing(
    surface_vertices: wp.array(dtype=wp.int32),  # [Vs]
    q_start: wp.array(dtype=wp.vec3),  # [N]
    dq: wp.array(dtype=wp.vec3),  # [N] the guess's displacement
    particle_component: wp.array(dtype=wp.int32),  # [N]
    component_free: wp.array(dtype=wp.int32),  # [C]
    component_mass: wp.array(dtype=float),  # [C] kg
    level: wp.array(dtype=wp.int32),  # [C]
    eff_disp: wp.array(dtype=wp.vec3),  # [C]
    con: ContactData,
    tri_component: wp.array(dtype=wp.int32),  # [T]
    shift_pos: wp.array(dtype=wp.vec3),  # [C] += per-axis max of positive shifts (zeroed)
    shift_neg: wp.array(dtype=wp.vec3),  # [C] += per-axis min of negative shifts (zeroed)
):
    """Rigid landing of one piece's guess on another: where a vertex's guess would lie
    inside its contact plane, the less supported piece (higher level; both by mass when
    level) moves back along the pieces' relative approach, by at most that approach (along
    it rather than along each contact normal, so tilted normals at edges push no piece
    sideways)."""
    v = surface_vertices[wp.tid()]
    a = particle_component[v]
    for s in range(con.slot_count[v]):
        tri = con.slot_tri[v, s]
        b = tri_component[tri]
        d_rel = eff_disp[a] - eff_disp[b]
        L = wp.length(d_rel)
        if a != b and L > 0.0:
            w = con.slot_w[v, s]
            n = con.slot_n[v, s]
            u = -d_rel / L
            pen = con.radius - wp.dot(_gap(q_start, dq, v, con.tri[tri, 0], con.tri[tri, 1], con.tri[tri, 2], w), n)
            nu = wp.dot(n, u)
            sep = float(0.0)
            if pen > 0.0 and nu > 0.1:
                sep = wp.min(pen / nu, L)
            if sep > 0.0:
                fa = float(0.0)
                if component_free[a] != 0 and component_free[b] != 0:
                    if level[a] > level[b]:
                        fa = 1.0
                    elif level[a] == level[b]:
                        fa = component_mass[b] / (component_mass[a] + component_mass[b])
                elif component_free[a] != 0:
                    fa = 1.0
                sa = u * (sep * fa)
                sb = u * (-sep * (1.0 - fa))
                if component_free[b] == 0:
                    sb = wp.vec3(0.0)
                wp.atomic_max(shift_pos, a, wp.max(sa, wp.vec3(0.0)))
                wp.atomic_min(shift_neg, a, wp.min(sa, wp.vec3(0.0)))
                wp.atomic_max(shift_pos, b, wp.max(sb, wp.vec3(0.0)))
                wp.atomic_min(shift_neg, b, wp.min(sb, wp.vec3(0.0)))


@wp.kernel
def vbd_merge_shift(
    shift_pos: wp.array(dtype=wp.vec3),  # [C]
    shift_neg: wp.array(dtype=wp.vec3),  # [C]
    shift: wp.array(dtype=wp.vec3),  # [C] out
    eff_disp: wp.array(dtype=wp.vec3),  # [C] in/out
):
    c = wp.tid()
    d = shift_pos[c] + shift_neg[c]
    shift[c] = d
    eff_disp[c] = eff_disp[c] + d


@wp.kernel
def vbd_guess_project(
    q_start: wp.array(dtype=wp.vec3),  # [N]
    dq: wp.array(dtype=wp.vec3),  # [N] in/out: the guess's displacement
    inv_mass: wp.array(dtype=float),  # [N]
    surf: SurfaceData,
):
    """Push the particles of the guess still behind a half-space out, one by one."""
    i = wp.tid()
    if inv_mass[i] == 0.0:
        return
    u = dq[i]
    for s in range(surf.count):
        n = surf.normal[s]
        d = wp.dot(q_start[i] - _surface_point(surf, s, surf.alpha1), n) + wp.dot(u, n)
        if d < 0.0:
            u = u - d * n
    dq[i] = u


@wp.func
def _friction(mu_fn: float, ut: wp.vec3, n: wp.vec3, eps: float):
    """Smoothed Coulomb friction force on a tangential displacement ``ut`` (IPC's
    dissipative potential ``mu f_n f0(|u|)`` with a linear ramp below ``eps``) and the
    Hessian of its quadratic majoriser ``mu f_n |u|^2 / (2 max(|u|, eps))`` (isotropic in the
    tangent plane: the step can cancel the slip but never reverse it)."""
    s = wp.length(ut)
    c = mu_fn / wp.max(s, eps)
    return ut * (-c), (wp.identity(n=3, dtype=float) - wp.outer(n, n)) * c


@wp.kernel
def vbd_solve_vertices(
    order: wp.array(dtype=wp.int32),  # [N] vertices sorted by colour
    offset: int,
    dq: wp.array(dtype=wp.vec3),  # [N] in/out: displacements from q_start (the iterate)
    q_start: wp.array(dtype=wp.vec3),  # [N] positions at the substep's start
    inertia: wp.array(dtype=wp.vec3),  # [N] y - q_start
    lag: wp.array(dtype=wp.vec3),  # [N] displacement that makes no velocity (vbd_predict)
    mass: wp.array(dtype=float),  # [N]
    inv_mass: wp.array(dtype=float),  # [N]
    inv_h2: float,  # 1 / h_eff^2 (h_eff = h, or 2h/3 for BDF2)
    kappa: float,  # h_eff / h
    tets: TetData,
    surf: SurfaceData,
    con: ContactData,
    surf_force: wp.array2d(dtype=wp.vec3),  # [N, S] force of each surface on each vertex, N
):
    """One block step of each vertex of a colour (module docstring). The iterate is the
    displacement over the substep, so velocities (displacement / h) keep float32's digits
    at any substep count; positions are start + displacement."""
    i = order[offset + wp.tid()]
    if inv_mass[i] == 0.0:
        return
    u = dq[i]
    mh = mass[i] * inv_h2
    f = (inertia[i] - u) * mh  # minus the gradient of G_i, N
    H = wp.identity(n=3, dtype=float) * mh

    # ---- elasticity: exact gradient, majoriser curvature (module docstring)
    for a in range(tets.adj_offsets[i], tets.adj_offsets[i + 1]):
        packed = tets.adj[a]
        t = packed >> 2
        k = packed & 3
        i0 = tets.indices[t, 0]
        e0 = q_start[i0]
        d0 = dq[i0]
        i1 = tets.indices[t, 1]
        i2 = tets.indices[t, 2]
        i3 = tets.indices[t, 3]
        Dinv = tets.dm_inv[t]
        F = wp.matrix_from_cols((q_start[i1] - e0) + (dq[i1] - d0), (q_start[i2] - e0) + (dq[i2] - d0),
                                (q_start[i3] - e0) + (dq[i3] - d0)) * Dinv
        f0 = wp.vec3(F[0, 0], F[1, 0], F[2, 0])
        f1 = wp.vec3(F[0, 1], F[1, 1], F[2, 1])
        f2 = wp.vec3(F[0, 2], F[1, 2], F[2, 2])
        b = wp.vec3(0.0)
        if k == 0:
            b = -(Dinv[0] + Dinv[1] + Dinv[2])
        else:
            b = Dinv[k - 1]
        c0 = wp.cross(f1, f2)
        c1 = wp.cross(f2, f0)
        c2 = wp.cross(f0, f1)
        J = wp.dot(f0, c0)
        Fb = f0 * b[0] + f1 * b[1] + f2 * b[2]
        cb = c0 * b[0] + c1 * b[1] + c2 * b[2]
        ic = wp.dot(f0, f0) + wp.dot(f1, f1) + wp.dot(f2, f2)
        mu_v = tets.mu_v[t]
        lam_v = tets.lam_v[t]
        f = f - (Fb * (mu_v * ic / (ic + 1.0)) + cb * (lam_v * (J - tets.alpha[t])))
        H = H + wp.identity(n=3, dtype=float) * (1.5 * mu_v * wp.dot(b, b)) + wp.outer(cb, cb) * lam_v

    # ---- vertex-triangle penalty contacts (fixed normal and weights for the substep).
    # Each contact is a hinge max(0, pen0 + a . dx)^2 in this vertex's move dx, so the block
    # problem is a convex piecewise quadratic: solve it with the contacts active at the
    # trial move and repeat until the active set settles (a contact that only becomes
    # active during the move must not be skipped, or the move overshoots through it).
    if con.enabled != 0:
        n_own = con.slot_count[i]
        r0 = con.rev_offsets[i]
        r1 = con.rev_offsets[i + 1]
        if n_own > 0 or r1 > r0:
            # Friction of the contacts active now, with their current normal force
            # (lagged through the move).
            for s in range(n_own):
                tri = con.slot_tri[i, s]
                ja = con.tri[tri, 0]
                jb = con.tri[tri, 1]
                jc = con.tri[tri, 2]
                w = con.slot_w[i, s]
                n = con.slot_n[i, s]
                pen = con.radius - wp.dot(_gap(q_start, dq, i, ja, jb, jc, w), n)
                if pen > 0.0:
                    sl = _slip(dq, lag, i, ja, jb, jc, w)
                    ff, Hf = _friction(con.slot_mu[i, s] * con.slot_k[i, s] * pen, sl - n * wp.dot(sl, n), n,
                                       con.friction_eps)
                    f = f + ff
                    H = H + Hf
            for r in range(r0, r1):
                packed = con.rev[r]
                corner = packed % 3
                vs = packed // 3
                v = vs // _K
                s = vs - v * _K
                tri = con.slot_tri[v, s]
                ja = con.tri[tri, 0]
                jb = con.tri[tri, 1]
                jc = con.tri[tri, 2]
                w = con.slot_w[v, s]
                n = con.slot_n[v, s]
                pen = con.radius - wp.dot(_gap(q_start, dq, v, ja, jb, jc, w), n)
                if pen > 0.0:
                    wc = w[corner]
                    sl = _slip(dq, lag, v, ja, jb, jc, w)
                    ff, Hf = _friction(con.slot_mu[v, s] * con.slot_k[v, s] * pen, sl - n * wp.dot(sl, n), n,
                                       con.friction_eps)
                    f = f - ff * wc
                    H = H + Hf * (wc * wc)
            H0 = H
            f0 = f
            dx = wp.vec3(0.0)
            for _rnd in range(_CONTACT_ROUNDS):
                Hc = H0
                fc = f0
                for s in range(n_own):
                    tri = con.slot_tri[i, s]
                    w = con.slot_w[i, s]
                    n = con.slot_n[i, s]
                    pen = con.radius - wp.dot(_gap(q_start, dq, i, con.tri[tri, 0], con.tri[tri, 1],
                                                   con.tri[tri, 2], w), n)
                    if pen - wp.dot(n, dx) > 0.0:
                        kc = con.slot_k[i, s]
                        Hc = Hc + wp.outer(n, n) * kc
                        fc = fc + n * (kc * pen)
                for r in range(r0, r1):
                    packed = con.rev[r]
                    corner = packed % 3
                    vs = packed // 3
                    v = vs // _K
                    s = vs - v * _K
                    tri = con.slot_tri[v, s]
                    w = con.slot_w[v, s]
                    n = con.slot_n[v, s]
                    pen = con.radius - wp.dot(_gap(q_start, dq, v, con.tri[tri, 0], con.tri[tri, 1],
                                                   con.tri[tri, 2], w), n)
                    wc = w[corner]
                    if pen + wc * wp.dot(n, dx) > 0.0:
                        kc = con.slot_k[v, s]
                        Hc = Hc + wp.outer(n, n) * (kc * wc * wc)
                        fc = fc - n * (kc * pen * wc)
                H = Hc
                f = fc
                dx = wp.inverse(H) * f

    Hinv = wp.inverse(H)
    u_new = u + Hinv * f

    # ---- ground and plates: exact projection in the H metric, Coulomb friction in-block
    xs = q_start[i]
    for s in range(surf.count):
        n = surf.normal[s]
        d = wp.dot(xs - _surface_point(surf, s, surf.alpha1), n) + wp.dot(u_new, n)
        force = wp.vec3(0.0)
        if d < 0.0:
            Hn = Hinv * n
            lam = -d / wp.dot(n, Hn)  # normal force, N
            u_c = u_new + Hn * lam
            disp_s = (surf.end[s] - surf.start[s]) * (surf.alpha1 - surf.alpha0)
            rel = u_c - lag[i] - disp_s * kappa  # velocity-making slip, times h_eff
            delta = wp.dot(rel, n) * n - rel  # move that cancels the tangential slip
            h_t = 0.5 * (H[0, 0] + H[1, 1] + H[2, 2] - wp.dot(n, H * n))
            need = h_t * wp.length(delta)
            lim = surf.friction[s] * lam
            ft = wp.vec3(0.0)
            if need <= lim:
                u_new = u_c + delta  # static: no slip
                ft = delta * h_t
            else:
                sc = lim / need
                u_new = u_c + delta * sc  # kinetic: slip shortened by mu f_n / h_t
                ft = delta * (h_t * sc)
            force = n * lam + ft
        surf_force[i, s] = force
    dq[i] = u_new


@wp.kernel
def vbd_finalize(
    dq: wp.array(dtype=wp.vec3),  # [N] the substep's displacements
    lag: wp.array(dtype=wp.vec3),  # [N] displacement that makes no velocity (vbd_predict)
    q_start: wp.array(dtype=wp.vec3),  # [N]
    qd_start: wp.array(dtype=wp.vec3),  # [N]
    inv_mass: wp.array(dtype=float),  # [N]
    surf: SurfaceData,
    restitution: wp.array(dtype=float),  # [S]
    surf_force: wp.array2d(dtype=wp.vec3),  # [N, S]
    h: float,
    h_eff: float,  # h, or 2h/3 for BDF2
    restart_history: int,  # 1: the next substep may be BDF2, restart its history at impacts
    bounce_threshold: float,  # m/s: slower approach speeds do not bounce
    damping_factor: float,  # velocity scale per substep, in (0, 1]
    force_scale: float,  # 1 / substeps: mean force over the step
    q_out: wp.array(dtype=wp.vec3),  # [N] q_start + dq
    qd_out: wp.array(dtype=wp.vec3),  # [N]
    qdd_out: wp.array(dtype=wp.vec3),  # [N]
    dq_out: wp.array(dtype=wp.vec3),  # [N] the substep's displacement (the next BDF2 step's d_n)
    surf_total: wp.array(dtype=wp.vec3),  # [S] += mean force of surface s on the bodies, N
):
    i = wp.tid()
    q_out[i] = q_start[i] + dq[i]
    dq_out[i] = dq[i] * damping_factor  # BDF2's history is damped with the velocity
    if inv_mass[i] == 0.0:
        qd_out[i] = wp.vec3(0.0)
        qdd_out[i] = wp.vec3(0.0)
        return
    inv_h = 1.0 / h
    v = (dq[i] - lag[i]) * (1.0 / h_eff)
    v0 = qd_start[i]
    jumped = int(0)
    for s in range(surf.count):
        fs = surf_force[i, s]
        n = surf.normal[s]
        if wp.dot(fs, n) > 0.0:
            wp.atomic_add(surf_total, s, fs * force_scale)
            # Restitution on the normal velocity relative to the surface (Müller et al. 2020).
            vs = (surf.end[s] - surf.start[s]) * ((surf.alpha1 - surf.alpha0) * inv_h)
            vn_pre = wp.dot(v0 - vs, n)
            if vn_pre < -bounce_threshold:
                v = v + n * (-restitution[s] * vn_pre - wp.dot(v - vs, n))
                jumped = 1
    v = v * damping_factor
    qd_out[i] = v
    if jumped != 0 and restart_history != 0:
        # An impact is a velocity jump: BDF2's history (the last displacement and velocity)
        # from before it would carry the approach on and lift the vertex off again. Restart
        # it as steady motion at the new velocity (the target is then x + h v + (2h/3)^2 g).
        dq_out[i] = v * h
        qdd_out[i] = wp.vec3(0.0)
    else:
        qdd_out[i] = (v - v0) * inv_h


# ---------------------------------------------------------------------------- contacts
@wp.kernel
def vbd_triangle_bounds(
    q: wp.array(dtype=wp.vec3),  # [N] substep start
    dq: wp.array(dtype=wp.vec3),  # [N] the initial guess's displacement (predicted motion)
    tri: wp.array2d(dtype=wp.int32),  # [T, 3]
    pad: float,  # m
    lowers: wp.array(dtype=wp.vec3),  # [T]
    uppers: wp.array(dtype=wp.vec3),  # [T]
):
    t = wp.tid()
    lo = q[tri[t, 0]]
    hi = lo
    for j in range(3):
        a = q[tri[t, j]]
        b = a + dq[tri[t, j]]
        lo = wp.min(lo, wp.min(a, b))
        hi = wp.max(hi, wp.max(a, b))
    lowers[t] = lo - wp.vec3(pad)
    uppers[t] = hi + wp.vec3(pad)


@wp.kernel
def vbd_vertex_normals(
    q: wp.array(dtype=wp.vec3),  # [N]
    tri: wp.array2d(dtype=wp.int32),  # [T, 3]
    normals: wp.array(dtype=wp.vec3),  # [N] += angle-weighted face normals (zeroed first)
):
    """Angle-weighted pseudo-normals of the surface vertices (Baerentzen & Aanaes 2005):
    with them the side of a point whose closest surface point is a vertex is exact."""
    t = wp.tid()
    for j in range(3):
        a = q[tri[t, j]]
        b = q[tri[t, (j + 1) % 3]]
        c = q[tri[t, (j + 2) % 3]]
        nf = wp.cross(b - a, c - a)
        ln = wp.length(nf)
        eb = wp.length(b - a)
        ec = wp.length(c - a)
        if ln > 0.0 and eb > 0.0 and ec > 0.0:
            ang = wp.acos(wp.clamp(wp.dot(b - a, c - a) / (eb * ec), -1.0, 1.0))
            wp.atomic_add(normals, tri[t, j], nf * (ang / ln))


@wp.func
def _face_normal(q: wp.array(dtype=wp.vec3), tri: wp.array2d(dtype=wp.int32), t: int):
    nf = wp.cross(q[tri[t, 1]] - q[tri[t, 0]], q[tri[t, 2]] - q[tri[t, 0]])
    ln = wp.length(nf)
    if ln > 0.0:
        return nf / ln
    return nf


@wp.func
def _feature_normal(q: wp.array(dtype=wp.vec3), tri: wp.array2d(dtype=wp.int32),
                    tri_adj: wp.array2d(dtype=wp.int32), vnormal: wp.array(dtype=wp.vec3), t: int, w: wp.vec3):
    """Pseudo-normal of the feature of triangle t that holds the barycentric point w: the
    face normal inside, the sum of both faces' normals on an edge, the vertex's
    angle-weighted normal at a corner. Its sign tells inside from outside exactly for a
    closed surface."""
    nz = int(0)
    for j in range(3):
        if w[j] > 0.0:
            nz += 1
    if nz == 3:
        return _face_normal(q, tri, t)
    if nz == 1:
        for j in range(3):
            if w[j] > 0.0:
                return vnormal[tri[t, j]]
    # on the edge opposite the corner with zero weight
    for j in range(3):
        if w[j] <= 0.0:
            # edge (j+1, j+2) is the local edge j+1 in tri_adj's convention (edge k = (k, k+1))
            nb = tri_adj[t, (j + 1) % 3]
            if nb >= 0:
                return _face_normal(q, tri, t) + _face_normal(q, tri, nb)
    return _face_normal(q, tri, t)


@wp.kernel
def vbd_detect_contacts(
    bvh: wp.uint64,  # triangles' swept boxes
    surface_vertices: wp.array(dtype=wp.int32),  # [Vs]
    q: wp.array(dtype=wp.vec3),  # [N] substep start
    dq: wp.array(dtype=wp.vec3),  # [N] the initial guess's displacement
    rest: wp.array(dtype=wp.vec3),  # [N] rest positions (self-collision filter)
    particle_component: wp.array(dtype=wp.int32),  # [N]
    tri: wp.array2d(dtype=wp.int32),  # [T, 3]
    tri_component: wp.array(dtype=wp.int32),  # [T]
    tri_adj: wp.array2d(dtype=wp.int32),  # [T, 3] triangle across edge (k, k+1), -1 if none
    vnormal: wp.array(dtype=wp.vec3),  # [N] vertex pseudo-normals at q
    self_collision: int,
    self_exclusion: float,  # m: same-component pairs closer than this at rest never collide
    stiffness: wp.array(dtype=float),  # [N] contact stiffness of each vertex, N/m
    friction: wp.array(dtype=float),  # [N] Coulomb coefficient of each vertex's body
    slot_comp: wp.array2d(dtype=wp.int32),  # [N, K] scratch: component of each slot
    slot_d2: wp.array2d(dtype=float),  # [N, K] scratch: squared distance
    slot_count: wp.array(dtype=wp.int32),  # [N]
    slot_tri: wp.array2d(dtype=wp.int32),  # [N, K]
    slot_w: wp.array2d(dtype=wp.vec3),  # [N, K]
    slot_n: wp.array2d(dtype=wp.vec3),  # [N, K]
    slot_k: wp.array2d(dtype=float),  # [N, K]
    slot_mu: wp.array2d(dtype=float),  # [N, K]
):
    v = surface_vertices[wp.tid()]
    x = q[v]
    cv = particle_component[v]
    query = wp.bvh_query_aabb(bvh, wp.min(x, x + dq[v]), wp.max(x, x + dq[v]))
    t = int(0)
    count = int(0)
    while wp.bvh_query_next(query, t):
        ja = tri[t, 0]
        jb = tri[t, 1]
        jc = tri[t, 2]
        ct = tri_component[t]
        ok = ja != v and jb != v and jc != v
        if ok and ct == cv:
            ok = self_collision != 0
            if ok:
                wr = closest_point_triangle(rest[v], rest[ja], rest[jb], rest[jc])
                pr = rest[ja] * wr[0] + rest[jb] * wr[1] + rest[jc] * wr[2]
                ok = wp.length(rest[v] - pr) >= self_exclusion
        if ok:
            w = closest_point_triangle(x, q[ja], q[jb], q[jc])
            p = q[ja] * w[0] + q[jb] * w[1] + q[jc] * w[2]
            d2 = wp.length_sq(x - p)
            # One slot per component (its closest triangle), the K closest components.
            slot = int(-1)
            for s in range(count):
                if slot_comp[v, s] == ct:
                    slot = s
            if slot >= 0:
                if d2 >= slot_d2[v, slot]:
                    slot = -2
            elif count < _K:
                slot = count
                count += 1
            else:
                worst = int(0)
                for s in range(_K):
                    if slot_d2[v, s] > slot_d2[v, worst]:
                        worst = s
                if d2 < slot_d2[v, worst]:
                    slot = worst
                else:
                    slot = -2
            if slot >= 0:
                slot_comp[v, slot] = ct
                slot_d2[v, slot] = d2
                slot_tri[v, slot] = t
                slot_w[v, slot] = w
    slot_count[v] = count
    for s in range(count):
        t2 = slot_tri[v, s]
        ja = tri[t2, 0]
        jb = tri[t2, 1]
        jc = tri[t2, 2]
        w = slot_w[v, s]
        p = q[ja] * w[0] + q[jb] * w[1] + q[jc] * w[2]
        pn = _feature_normal(q, tri, tri_adj, vnormal, t2, w)
        e = x - p
        dist = wp.length(e)
        n = _face_normal(q, tri, t2)
        if dist > _MIN_DIST:
            if wp.dot(e, pn) >= 0.0:
                n = e / dist  # outside: from the closest point to the vertex
            else:
                n = -e / dist  # inside the other piece: out through the closest point
        slot_n[v, s] = n
        kc = wp.max(wp.max(stiffness[v], stiffness[ja]), wp.max(stiffness[jb], stiffness[jc]))
        slot_k[v, s] = kc
        slot_mu[v, s] = 0.5 * (friction[v] + friction[ja])


@wp.kernel
def vbd_count_reverse_contacts(
    surface_vertices: wp.array(dtype=wp.int32),  # [Vs]
    slot_count: wp.array(dtype=wp.int32),  # [N]
    slot_tri: wp.array2d(dtype=wp.int32),  # [N, K]
    tri: wp.array2d(dtype=wp.int32),  # [T, 3]
    rev_count: wp.array(dtype=wp.int32),  # [N + 1] += contacts per corner
):
    v = surface_vertices[wp.tid()]
    for s in range(slot_count[v]):
        t = slot_tri[v, s]
        for j in range(3):
            wp.atomic_add(rev_count, tri[t, j], 1)


@wp.kernel
def vbd_fill_reverse_contacts(
    surface_vertices: wp.array(dtype=wp.int32),  # [Vs]
    slot_count: wp.array(dtype=wp.int32),  # [N]
    slot_tri: wp.array2d(dtype=wp.int32),  # [N, K]
    tri: wp.array2d(dtype=wp.int32),  # [T, 3]
    rev_offsets: wp.array(dtype=wp.int32),  # [N + 1]
    rev_cursor: wp.array(dtype=wp.int32),  # [N] zeroed
    rev: wp.array(dtype=wp.int32),  # [R]
):
    v = surface_vertices[wp.tid()]
    for s in range(slot_count[v]):
        t = slot_tri[v, s]
        for j in range(3):
            c = tri[t, j]
            k = wp.atomic_add(rev_cursor, c, 1)
            rev[rev_offsets[c] + k] = (v * _K + s) * 3 + j


# ---------------------------------------------------------------------------- measurements
@wp.kernel
def vbd_tet_bounds(
    q: wp.array(dtype=wp.vec3),  # [N]
    tet_indices: wp.array2d(dtype=wp.int32),  # [M, 4]
    lowers: wp.array(dtype=wp.vec3),  # [M]
    uppers: wp.array(dtype=wp.vec3),  # [M]
):
    t = wp.tid()
    lo = q[tet_indices[t, 0]]
    hi = lo
    for j in range(1, 4):
        lo = wp.min(lo, q[tet_indices[t, j]])
        hi = wp.max(hi, q[tet_indices[t, j]])
    lowers[t] = lo
    uppers[t] = hi


@wp.func
def _signed_vol6(a: wp.vec3, b: wp.vec3, c: wp.vec3, d: wp.vec3):
    return wp.dot(b - a, wp.cross(c - a, d - a))


@wp.kernel
def vbd_penetration(
    tet_bvh: wp.uint64,  # tets' boxes at q
    tri_bvh: wp.uint64,  # triangles' boxes at q (no padding)
    surface_vertices: wp.array(dtype=wp.int32),  # [Vs]
    q: wp.array(dtype=wp.vec3),  # [N]
    particle_component: wp.array(dtype=wp.int32),  # [N]
    tet_indices: wp.array2d(dtype=wp.int32),  # [M, 4]
    tet_component: wp.array(dtype=wp.int32),  # [M]
    tri: wp.array2d(dtype=wp.int32),  # [T, 3]
    tri_component: wp.array(dtype=wp.int32),  # [T]
    probe: float,  # m, first search radius for the depth
    depth: wp.array(dtype=float),  # [Vs] out: depth of each surface vertex inside another component, m
):
    """How deep each surface vertex lies inside another face-connected component: 0 unless
    it is inside one of that component's tets, then its distance to that component's
    surface (searched in boxes of growing size)."""
    tid = wp.tid()
    v = surface_vertices[tid]
    x = q[v]
    cv = particle_component[v]
    inside = int(-1)
    query = wp.bvh_query_aabb(tet_bvh, x, x)
    t = int(0)
    while wp.bvh_query_next(query, t):
        if inside < 0 and tet_component[t] != cv:
            i0 = tet_indices[t, 0]
            i1 = tet_indices[t, 1]
            i2 = tet_indices[t, 2]
            i3 = tet_indices[t, 3]
            if i0 != v and i1 != v and i2 != v and i3 != v:
                a = q[i0]
                b = q[i1]
                c = q[i2]
                d = q[i3]
                vol = _signed_vol6(a, b, c, d)
                s0 = _signed_vol6(x, b, c, d)
                s1 = _signed_vol6(a, x, c, d)
                s2 = _signed_vol6(a, b, x, d)
                s3 = _signed_vol6(a, b, c, x)
                tol = -1.0e-6 * wp.abs(vol)  # on a face shared by two tets counts as inside
                if vol > 0.0 and s0 >= tol and s1 >= tol and s2 >= tol and s3 >= tol:
                    inside = tet_component[t]
    result = float(0.0)
    if inside >= 0:
        rad = probe
        found = float(-1.0)
        for it in range(24):
            if found < 0.0:
                best = float(1.0e30)
                q2 = wp.bvh_query_aabb(tri_bvh, x - wp.vec3(rad), x + wp.vec3(rad))
                k = int(0)
                while wp.bvh_query_next(q2, k):
                    if tri_component[k] == inside:
                        w = closest_point_triangle(x, q[tri[k, 0]], q[tri[k, 1]], q[tri[k, 2]])
                        p = q[tri[k, 0]] * w[0] + q[tri[k, 1]] * w[1] + q[tri[k, 2]] * w[2]
                        best = wp.min(best, wp.length(x - p))
                if best <= rad:
                    found = best
                rad = rad * 2.0
        result = wp.max(found, 0.0)
    depth[tid] = result


@wp.kernel
def sim_tet_stats(
    q: wp.array(dtype=wp.vec3),  # [N]
    tet_indices: wp.array2d(dtype=wp.int32),  # [M, 4]
    stats: wp.array(dtype=wp.float64),  # [2] += (inverted count, total signed volume m^3)
):
    # float64 sums: 200k float32 volumes summed in float32 drift by ~1e-3 of the total,
    # which would read as a volume change of the body
    t = wp.tid()
    x0 = q[tet_indices[t, 0]]
    vol = wp.dot(q[tet_indices[t, 1]] - x0, wp.cross(q[tet_indices[t, 2]] - x0, q[tet_indices[t, 3]] - x0)) / 6.0
    if vol <= 0.0:
        wp.atomic_add(stats, 0, wp.float64(1.0))
    wp.atomic_add(stats, 1, wp.float64(vol))


@wp.kernel
def sim_tet_forces(
    q: wp.array(dtype=wp.vec3),  # [N]
    tet_indices: wp.array2d(dtype=wp.int32),  # [M, 4]
    tet_dm_inv: wp.array(dtype=wp.mat33),  # [M]
    tet_volume: wp.array(dtype=float),  # [M]
    tet_mu: wp.array(dtype=float),  # [M]
    tet_lambda: wp.array(dtype=float),  # [M] Lamé lambda
    forces: wp.array(dtype=wp.vec3),  # [N] += elastic force, N
    energy: wp.array(dtype=float),  # [1] += elastic energy relative to rest, J
):
    """Elastic forces ``-dE/dx`` and energy of the material (diagnostics and tests: a rigid
    motion must give zero force)."""
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
    mu = tet_mu[t] * (4.0 / 3.0)  # Smith et al.'s mu'
    lam = tet_lambda[t] + tet_mu[t] * (5.0 / 6.0)  # lambda'
    alpha = 1.0 + 0.75 * mu / lam
    vol = tet_volume[t]
    c0 = wp.cross(f1, f2)
    c1 = wp.cross(f2, f0)
    c2 = wp.cross(f0, f1)
    J = wp.dot(f0, c0)
    ic = wp.dot(f0, f0) + wp.dot(f1, f1) + wp.dot(f2, f2)
    # psi(F) - psi(I): zero at rest (module docstring)
    psi = 0.5 * mu * (ic - 3.0) + 0.5 * lam * ((J - alpha) * (J - alpha) - (1.0 - alpha) * (1.0 - alpha))
    psi = psi - 0.5 * mu * (wp.log(ic + 1.0) - wp.log(4.0))
    wp.atomic_add(energy, 0, vol * psi)
    P = F * (mu * ic / (ic + 1.0)) + wp.matrix_from_cols(c0, c1, c2) * (lam * (J - alpha))
    G = P * wp.transpose(Dinv) * vol
    g1 = wp.vec3(G[0, 0], G[1, 0], G[2, 0])
    g2 = wp.vec3(G[0, 1], G[1, 1], G[2, 1])
    g3 = wp.vec3(G[0, 2], G[1, 2], G[2, 2])
    wp.atomic_add(forces, i0, g1 + g2 + g3)
    wp.atomic_sub(forces, i1, g1)
    wp.atomic_sub(forces, i2, g2)
    wp.atomic_sub(forces, i3, g3)
