"""Vertex Block Descent solver for stable Neo-Hookean tet meshes (Newton's ``Solver`` shape).

``SolverVBDNeoHookean.step(state_in, state_out, control, contacts, dt)`` advances one step
of ``dt`` seconds in ``substeps`` implicit Euler (or BDF2, see "Integrators") substeps,
each solved by ``iterations`` Gauss-Seidel sweeps of Vertex Block Descent (Chen et al. 2024,
"Vertex Block Descent").
It reads ``state_in`` and ``control`` and writes only ``state_out`` (plus its own scratch
arrays), so the same inputs always give the same output. Kernels and the maths are in
:mod:`holowarp.kernels.sim_vbd`.

Why VBD, and why it needs no stability plan. The solver it replaces (XPBD with the two
stable Neo-Hookean constraints of Macklin & Müller 2021) diverged above a per-tet ratio
``mu V h^2 sum w |grad C|^2`` of about 0.8 whatever the iteration count, because its two
constraints have no common zero and part of the stiffness lives in their curvature, which
XPBD's linearised update ignores; it had to add substeps with resolution and stiffness and
soften slivers. The candidates were:

- a corrected XPBD (one constraint per energy term that vanishes at rest, e.g. ARAP plus
  volume): still a linearised projection per constraint, so still conditionally
  convergent for stiff nonlinear terms, and it changes the material;
- projective dynamics: unconditionally stable but needs a prefactored global system
  (no sparse Cholesky in Warp) and replaces Neo-Hookean by a projection energy;
- Newton-type implicit Euler (global Newton, PCG, line search): stable and the most
  accurate per iteration, but each of the 16 iterations is an assembly plus a long PCG
  solve (the paper's stiffest cases have condition numbers near 10^5 at 1/60 s);
- Vertex Block Descent: Gauss-Seidel over vertices on the implicit Euler incremental
  potential, the method Newton's ``SolverVBD`` implements. For the stable Neo-Hookean
  energy a vertex's block problem has a quadratic majoriser in closed form (``det F`` is
  affine in one vertex; the rest has bounded curvature), so every block step provably
  lowers the potential and the iteration cannot diverge for any dt, E, nu or tet shape
  (Newton takes a Newton block step, without that guarantee).

VBD it is. Its block Hessian is ``m/h^2 I + sum V (3/2 mu' |b|^2 I + lambda' c c^T)``
(``c = cof(F) b``), a handful of cross products per tet where Newton assembles and contracts
a 9 x 9 Hessian. Two more choices keep it well behaved with few iterations:

- the initial guess moves every face-connected piece rigidly (its mean and angular
  velocity), adds each particle's own extrapolation only as far as a pressure wave gets
  through one tet in the substep (:meth:`SolverVBDNeoHookean.guess_blend`: all of it at
  small substeps, almost none at 1/60 s), and lands pieces that would enter the ground, a
  plate or another piece rigidly on it. A full per-particle extrapolation carries the
  deformation rate forward and a per-particle projection strains the contact layer; at
  1/60 s both plant more elastic energy than 16 sweeps can take out, and the velocity
  update turns it into bounces many times the drop energy (measured: 23 J became 530 J
  for a 5k-tet cube). With the rigid guess the potential's descent bounds a step's
  elastic energy by what it had plus the deformational kinetic energy;
- contacts between pieces are solved inside the block problem as a convex piecewise
  quadratic (active set), so a contact that only engages during the move is not skipped.

Substeps may still be added for accuracy (implicit Euler lags free fall by ``g t h / 2``
and damps vibrations with ``omega h > 1``; unconverged sweeps damp more), never to avoid
divergence; :class:`StepPlan` reports what was used, and no tet is ever softened.

Integrators. Implicit Euler converges at first order in the substep, and slowly: a soft
0.2 m cube dropped 0.2 m (5k tets) still loses 3 % of the drop height of its rebound at 512
substeps. BDF2 is second order and, like implicit Euler, L-stable, and it keeps VBD's
form: with ``h_e = 2h/3`` it minimises the same incremental potential

    m / (2 h_e^2) |x - y|^2 + E(x),   y = x_n + d_n / 3 + h_e (v_n + h a_n / 3) + h_e^2 g,

(``d_n = x_n - x_(n-1)``, ``a_n = (v_n - v_(n-1)) / h``; :class:`State` keeps ``d_n``), then
sets ``v = (x - x_n - d_n / 3) / h_e``, so every block step and its majoriser are unchanged.
On that drop it matches the converged trajectory within 0.3 % at 32 substeps of 4 sweeps,
where implicit Euler needs over a thousand. Two details keep it consistent with contact:
the initial guess extrapolates with BDF2's own target (so free flight is exact after one
sweep), and a vertex whose velocity jumps at an impact restarts its history as steady
motion at the new velocity; otherwise the pre-impact history lifts it off the ground again
(a bounce of about half the approach speed that no substep count removes). BDF2 is the
choice once a substep resolves a pressure wave crossing one edge (``"auto"``,
:meth:`SolverVBDNeoHookean.integrator_for`); at longer substeps such as the paper's 1/60 s,
implicit Euler's damping of the modes the step cannot resolve is what a few sweeps need
(BDF2 there gained 0.7 % angular momentum on a spinning block in 10 steps, and on a 50k-tet
drop at 1.6 wave crossings per substep its centre of mass ended 44 % of the drop height
off the converged one, with 4 sweeps or 8), so ``"auto"`` keeps it. A run's first
substep, and any after a change of substep length, is implicit Euler.

CPU sweeps. Warp's CPU backend runs a launch on one thread in index order, so one launch
over the colour-sorted particles is an exact serial Gauss-Seidel sweep (``fuse_colors``). A
mesh of at least :data:`SWEEP_PARTS_MIN_VERTICES` particles without body contacts is swept
as :data:`SWEEP_PARTS` domains at once (:func:`sweep_phases`, a nested dissection whose
domains share no tet), on the threads of :func:`holowarp.device.cpu_threads`: a 50k-tet
cube's sweep runs 1.5-1.8x as fast on two cores, and the result is the same on any number
of threads.

Contacts: the ground and plates are hard half-space constraints of each vertex's block
problem with in-block Coulomb friction; bodies, and face-disconnected pieces of one mesh,
touch through vertex-triangle penalty contacts with IPC-style friction, detected once per
substep with a ``wp.Bvh`` over the surface triangles' swept boxes. Self-collision inside a
connected piece is an option (off by default, as in the paper's setup).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from holowarp.device import init_warp, run_chunks
from holowarp.errors import InputError
from holowarp.ops.launches import LaunchCache

__all__ = [
    "SolverVBDNeoHookean",
    "StepPlan",
    "PAPER_DT",
    "PAPER_ITERATIONS",
    "CONTACT_RADIUS_FRACTION",
    "CONTACT_MARGIN_FRACTION",
    "CONTACT_STIFFNESS",
    "FRICTION_EPSILON",
    "SWEEP_PARTS",
    "sweep_phases",
]

#: method.md §10 (the paper's Isaac Sim setup): 60 steps per second, 16 solver iterations.
PAPER_DT = 1.0 / 60.0
PAPER_ITERATIONS = 16

#: Time integrators (module docstring): ``"auto"`` is BDF2 where a substep resolves a
#: pressure wave crossing one boundary edge and implicit Euler where it does not.
INTEGRATORS = ("auto", "euler", "bdf2")
DEFAULT_INTEGRATOR = "auto"

#: Default contact radius r as a fraction of the median boundary edge: touching bodies rest
#: this far apart.
CONTACT_RADIUS_FRACTION = 0.05
#: Default detection margin beyond the predicted motion, as a fraction of the median
#: boundary edge (covers what the elastic response adds to the inertial prediction).
CONTACT_MARGIN_FRACTION = 0.5
#: Default penalty stiffness as a multiple of the stiffer side's rest elastic stiffness:
#: a contact yields 1/10 of what the material next to it would under the same load.
CONTACT_STIFFNESS = 10.0
#: Default friction smoothing, m/s: relative tangential speeds below it are resisted
#: viscously (IPC's eps_v); above it friction is Coulomb's.
FRICTION_EPSILON = 1.0e-3
#: Default self-collision exclusion, in median boundary edges: points of one connected
#: piece closer than this at rest never collide with each other.
SELF_EXCLUSION_EDGES = 1.5

#: Domains a CPU sweep is cut into (:func:`sweep_phases`): fixed, so that a run's result does
#: not depend on how many threads sweep them (:func:`holowarp.device.cpu_threads`).
SWEEP_PARTS = 2
#: Fewest vertices a mesh needs before its CPU sweeps are cut into domains: below it one
#: domain sweeps in well under a millisecond, and the threads' hand-over would cost more than
#: the second core saves.
SWEEP_PARTS_MIN_VERTICES = 2048
#: Dissection levels: the vertices left after this many cuts are swept serially.
_SWEEP_LEVELS = 3
#: A separator smaller than this is swept serially rather than cut again (one more phase's
#: hand-over costs about what sweeping it takes).
_SWEEP_SERIAL_VERTICES = 512

#: Contact hops over which pieces learn they rest on a supported piece (stack height the
#: rigid landing of the initial guess handles in order).
_SUPPORT_HOPS = 4
#: Rounds of piece-on-piece landing of the initial guess (each lets a stack settle one
#: more level).
_BODY_LANDING_ROUNDS = 3

#: Approach speeds below this many g*dt do not bounce (restitution), so resting contact
#: does not jitter (Müller et al. 2020, "Detailed Rigid Body Simulation with XPBD").
_BOUNCE_THRESHOLD_G_DT = 2.0


@dataclass(frozen=True)
class StepPlan:
    """How one step of a given length is split (see :meth:`SolverVBDNeoHookean.plan`).

    Attributes:
        dt: step length, s.
        substeps: substeps per step.
        iterations: Gauss-Seidel iterations per substep.
        softened_tets: tets whose stiffness was changed for stability: always 0 (the
            solver is unconditionally stable; kept so reports say so).
        solver: ``"vbd"``.
        integrator: ``"bdf2"`` or ``"euler"`` (:meth:`SolverVBDNeoHookean.integrator_for`).
    """

    dt: float
    substeps: int
    iterations: int
    softened_tets: int = 0
    solver: str = "vbd"
    integrator: str = "euler"

    def as_dict(self) -> dict:
        return dict(self.__dict__)


class SolverVBDNeoHookean:
    """Implicit Euler by Vertex Block Descent with stable Neo-Hookean tets and contacts.

    Args:
        model: the :class:`holowarp.sim.Model`.
        iterations: Gauss-Seidel sweeps per substep (paper: 16).
        substeps: substeps per :meth:`step` (paper: 1).
        damping: velocity damping rate in 1/s; velocities are scaled by
            ``max(0, 1 - damping * h)`` each substep of length h.
        contact_radius: body-body contact distance r in m (default
            :data:`CONTACT_RADIUS_FRACTION` of the median boundary edge). 0 is allowed
            (bodies then rest in exact contact, penetrating by their load over the penalty
            stiffness).
        contact_margin: extra detection distance in m (default
            :data:`CONTACT_MARGIN_FRACTION` of the median boundary edge).
        contact_stiffness: penalty stiffness as a multiple of the particles' rest elastic
            stiffness (:data:`CONTACT_STIFFNESS`).
        self_collision: also collide a connected piece with itself (pairs farther apart
            than ``self_collision_exclusion`` at rest).
        self_collision_exclusion: m (default :data:`SELF_EXCLUSION_EDGES` median edges).
        friction_epsilon: friction smoothing speed in m/s (:data:`FRICTION_EPSILON`).
        fuse_colors: sweep all colours in one kernel launch per iteration. Only valid where
            a launch runs its threads serially in index order (Warp's CPU backend), where it
            gives the per-colour result. ``None``: on CPU only.
        sweep_parts: on the CPU, sweep this many domains of the mesh at once on the kernel
            thread pool (:func:`sweep_phases`; 1: one serial sweep in colour order). ``None``:
            :data:`SWEEP_PARTS` for a fused sweep of at least
            :data:`SWEEP_PARTS_MIN_VERTICES` particles without body contacts (a contact
            couples vertices that share no tet, so the domains would race), else 1. The
            result does not depend on the thread count.
        integrator: ``"euler"`` (implicit Euler, first order), ``"bdf2"`` (second order) or
            ``"auto"`` (BDF2 at substeps no longer than :meth:`wave_time`, else implicit
            Euler; see the module docstring and :meth:`integrator_for`).
    """

    def __init__(self, model, *, iterations: int = PAPER_ITERATIONS, substeps: int = 1, damping: float = 0.0,
                 contact_radius: float | None = None, contact_margin: float | None = None,
                 contact_stiffness: float = CONTACT_STIFFNESS, self_collision: bool = False,
                 self_collision_exclusion: float | None = None, friction_epsilon: float = FRICTION_EPSILON,
                 fuse_colors: bool | None = None, integrator: str = DEFAULT_INTEGRATOR,
                 sweep_parts: int | None = None):
        wp = init_warp()
        if integrator not in INTEGRATORS:
            raise InputError(f"integrator must be one of {', '.join(INTEGRATORS)}, got {integrator!r}")
        if int(iterations) != iterations or int(iterations) < 1:
            raise InputError(f"iterations must be an integer >= 1, got {iterations}")
        if int(substeps) != substeps or int(substeps) < 1:
            raise InputError(f"substeps must be an integer >= 1, got {substeps}")
        if not np.isfinite(damping) or damping < 0:
            raise InputError(f"damping must be >= 0 (1/s), got {damping}")
        edge = model.median_surface_edge()
        r = CONTACT_RADIUS_FRACTION * edge if contact_radius is None else float(contact_radius)
        margin = CONTACT_MARGIN_FRACTION * edge if contact_margin is None else float(contact_margin)
        excl = SELF_EXCLUSION_EDGES * edge if self_collision_exclusion is None else float(self_collision_exclusion)
        for name, v in (("contact_radius", r), ("contact_margin", margin), ("self_collision_exclusion", excl)):
            if not np.isfinite(v) or v < 0:
                raise InputError(f"{name} must be >= 0 m, got {v}")
        if not np.isfinite(contact_stiffness) or contact_stiffness <= 0:
            raise InputError(f"contact_stiffness must be > 0, got {contact_stiffness}")
        if not np.isfinite(friction_epsilon) or friction_epsilon <= 0:
            raise InputError(f"friction_epsilon must be > 0 m/s, got {friction_epsilon}")
        self.model = model
        self.integrator = integrator
        self.iterations = int(iterations)
        self.substeps = int(substeps)
        self.damping = float(damping)
        self.contact_radius = r
        self.contact_margin = margin
        self.contact_stiffness = float(contact_stiffness)
        self.self_collision = bool(self_collision)
        self.self_collision_exclusion = excl
        self.friction_epsilon = float(friction_epsilon)
        is_cpu = wp.get_device(model.device).is_cpu
        if fuse_colors is None:
            fuse_colors = is_cpu
        if fuse_colors and not is_cpu:
            raise ValueError("fuse_colors=True is only valid on the CPU (serial launches)")
        self.fuse_colors = bool(fuse_colors)
        if sweep_parts is not None and (int(sweep_parts) != sweep_parts or int(sweep_parts) < 1):
            raise InputError(f"sweep_parts must be an integer >= 1, got {sweep_parts}")
        if sweep_parts is not None and sweep_parts > 1 and not self.fuse_colors:
            raise ValueError("sweep_parts > 1 needs a fused CPU sweep (fuse_colors=True)")
        self.contacts_enabled = model.component_count >= 2 or bool(self_collision)
        if sweep_parts is None:
            eligible = self.fuse_colors and not self.contacts_enabled
            sweep_parts = SWEEP_PARTS if eligible and model.particle_count >= SWEEP_PARTS_MIN_VERTICES else 1
        elif sweep_parts > 1 and self.contacts_enabled:
            raise ValueError("sweep_parts > 1 is only valid without body contacts")
        self.sweep_parts = int(sweep_parts)

        m = model
        c = np.sqrt((m.tet_lambda_host + 2.0 * m.tet_mu_host) / m.tet_density_host).max()
        self._wave_time = edge / float(c)  # s: a pressure wave crossing one boundary edge
        # A substep launches a few dozen kernels on the same arrays; recorded launches
        # replay them without re-packing their arguments (issue 17: a two-body frame at 64
        # substeps made about 1,900 launches).
        self._launches = LaunchCache()
        self._init_arrays()
        self._init_contacts()

    def _init_arrays(self) -> None:
        """Scratch arrays, sweeps and the kernels' structs."""
        from holowarp.kernels import sim_vbd as K

        wp = init_warp()
        model = self.model
        dev = model.device
        N = model.particle_count
        S = max(model.surface_count, 1)
        self._q_start = wp.zeros(N, dtype=wp.vec3, device=dev)
        self._dq = wp.zeros(N, dtype=wp.vec3, device=dev)
        self._qd_start = wp.zeros(N, dtype=wp.vec3, device=dev)
        self._inertia = wp.zeros(N, dtype=wp.vec3, device=dev)
        self._lag = wp.zeros(N, dtype=wp.vec3, device=dev)
        self._surf_force = wp.zeros((N, S), dtype=wp.vec3, device=dev)
        self._stats = wp.zeros(2, dtype=wp.float64, device=dev)
        C = max(model.component_count, 1)
        self._depth_cs = wp.zeros((C, S), dtype=float, device=dev)
        self._shift = wp.zeros(C, dtype=wp.vec3, device=dev)
        self._shift_pos = wp.zeros(C, dtype=wp.vec3, device=dev)
        self._shift_neg = wp.zeros(C, dtype=wp.vec3, device=dev)
        self._eff_disp = wp.zeros(C, dtype=wp.vec3, device=dev)
        self._level = wp.zeros(C, dtype=wp.int32, device=dev)
        free = np.ones(C, np.int32)
        free[np.unique(model.components[model.fixed])] = 0
        self._component_free = wp.array(free, dtype=wp.int32, device=dev)
        self._sum_m = wp.zeros(C, dtype=float, device=dev)
        self._sum_mx = wp.zeros(C, dtype=wp.vec3, device=dev)
        self._sum_mv = wp.zeros(C, dtype=wp.vec3, device=dev)
        self._sum_ma = wp.zeros(C, dtype=wp.vec3, device=dev)
        self._sum_ml = wp.zeros(C, dtype=wp.vec3, device=dev)
        self._ang = wp.zeros(C, dtype=wp.vec3, device=dev)
        self._inertia_tensor = wp.zeros(C, dtype=wp.mat33, device=dev)
        self._com = wp.zeros(C, dtype=wp.vec3, device=dev)
        self._disp = wp.zeros(C, dtype=wp.vec3, device=dev)
        self._rot = wp.zeros(C, dtype=wp.mat33, device=dev)

        # A sweep is a list of phases, each a list of (offset, count) ranges of the order that
        # may run at once (one launch each).
        offs = model.particle_color_offsets
        order = model.particle_color_order.numpy()
        if self.sweep_parts > 1:
            order, fwd = sweep_phases(order, model.tets, model.rest_positions, self.sweep_parts)
        elif self.fuse_colors:
            fwd = [[(0, N)]]
        else:
            fwd = [[(int(offs[c]), int(offs[c + 1] - offs[c]))] for c in range(len(offs) - 1)]
        # Symmetric Gauss-Seidel: odd iterations sweep the phases (and the vertices in them)
        # in reverse, so no direction of the mesh is favoured by the sweep order.
        rev_order = wp.array(order[::-1].copy(), dtype=wp.int32, device=dev)
        rev = [[(N - off - cnt, cnt) for off, cnt in phase] for phase in reversed(fwd)]
        self._sweeps = [(wp.array(order.astype(np.int32), dtype=wp.int32, device=dev), fwd), (rev_order, rev)]

        t = K.TetData()
        t.indices = model.tet_indices
        t.dm_inv = model.tet_dm_inv
        t.mu_v = model.tet_mu_v
        t.lam_v = model.tet_lam_v
        t.alpha = model.tet_alpha
        t.adj_offsets = model.particle_adj_offsets
        t.adj = model.particle_adj
        self._tets = t

        s = K.SurfaceData()
        s.count = model.surface_count
        s.normal = model.surface_normal
        s.friction = model.surface_friction
        s.start = s.end = model.surface_normal  # replaced by the control's arrays each step
        s.alpha0, s.alpha1 = 0.0, 1.0
        self._surf = s

    # ------------------------------------------------------------------ contacts
    def _init_contacts(self) -> None:
        from holowarp.kernels import sim_vbd as K

        wp = init_warp()
        m = self.model
        dev = m.device
        N = m.particle_count
        Kc = K.MAX_CONTACTS
        c = K.ContactData()
        c.enabled = int(self.contacts_enabled)
        c.radius = self.contact_radius
        c.friction_eps = self.friction_epsilon / 60.0
        c.tri = m.tri_indices
        if not self.contacts_enabled:
            z = wp.zeros(1, dtype=wp.int32, device=dev)
            c.slot_count = wp.zeros(N, dtype=wp.int32, device=dev)
            c.slot_tri = wp.zeros((1, Kc), dtype=wp.int32, device=dev)
            c.slot_w = wp.zeros((1, Kc), dtype=wp.vec3, device=dev)
            c.slot_n = wp.zeros((1, Kc), dtype=wp.vec3, device=dev)
            c.slot_k = wp.zeros((1, Kc), dtype=float, device=dev)
            c.slot_mu = wp.zeros((1, Kc), dtype=float, device=dev)
            c.rev_offsets = wp.zeros(N + 1, dtype=wp.int32, device=dev)
            c.rev = z
            self._con = c
            return
        T = len(m.tris)
        Vs = m.surface_vertices.shape[0]
        c.slot_count = wp.zeros(N, dtype=wp.int32, device=dev)
        c.slot_tri = wp.zeros((N, Kc), dtype=wp.int32, device=dev)
        c.slot_w = wp.zeros((N, Kc), dtype=wp.vec3, device=dev)
        c.slot_n = wp.zeros((N, Kc), dtype=wp.vec3, device=dev)
        c.slot_k = wp.zeros((N, Kc), dtype=float, device=dev)
        c.slot_mu = wp.zeros((N, Kc), dtype=float, device=dev)
        c.rev_offsets = wp.zeros(N + 1, dtype=wp.int32, device=dev)
        c.rev = wp.zeros(max(Vs * Kc * 3, 1), dtype=wp.int32, device=dev)
        self._con = c
        self._slot_comp = wp.zeros((N, Kc), dtype=wp.int32, device=dev)
        self._slot_d2 = wp.zeros((N, Kc), dtype=float, device=dev)
        self._rev_count = wp.zeros(N + 1, dtype=wp.int32, device=dev)
        self._rev_cursor = wp.zeros(N, dtype=wp.int32, device=dev)
        self._contact_k = wp.array((self.contact_stiffness * m.particle_stiffness_host).astype(np.float32),
                                   dtype=float, device=dev)
        self._rest = wp.array(m.rest_positions.astype(np.float32), dtype=wp.vec3, device=dev)
        self._vnormal = wp.zeros(N, dtype=wp.vec3, device=dev)
        self._tri_adj = wp.array(_triangle_neighbours(m.tris), dtype=wp.int32, device=dev)
        self._tri_lo = wp.zeros(T, dtype=wp.vec3, device=dev)
        self._tri_hi = wp.zeros(T, dtype=wp.vec3, device=dev)
        wp.launch(K.vbd_triangle_bounds, dim=T, inputs=[m.particle_q, wp.zeros(N, dtype=wp.vec3, device=dev),
                                                         m.tri_indices, 0.0],
                  outputs=[self._tri_lo, self._tri_hi], device=dev)
        self._bvh = wp.Bvh(self._tri_lo, self._tri_hi)

    def _detect(self) -> None:
        """Contacts of this substep from the start positions and the initial guess."""
        from holowarp.kernels import sim_vbd as K

        wp = init_warp()
        m = self.model
        dev = m.device
        c = self._con
        pad = self.contact_radius + self.contact_margin
        self._launch("vbd_triangle_bounds", K.vbd_triangle_bounds, dim=len(m.tris),
                     inputs=[self._q_start, self._dq, m.tri_indices, pad], outputs=[self._tri_lo, self._tri_hi],
                     device=dev)
        self._bvh.refit()
        self._vnormal.zero_()
        self._launch("vbd_vertex_normals", K.vbd_vertex_normals, dim=len(m.tris),
                     inputs=[self._q_start, m.tri_indices], outputs=[self._vnormal], device=dev)
        Vs = m.surface_vertices.shape[0]
        self._launch("vbd_detect_contacts", K.vbd_detect_contacts, dim=Vs, inputs=[
            self._bvh.id, m.surface_vertices, self._q_start, self._dq, self._rest, m.particle_component,
            m.tri_indices, m.tri_component, self._tri_adj, self._vnormal, int(self.self_collision),
            self.self_collision_exclusion,
            self._contact_k, m.particle_friction, self._slot_comp, self._slot_d2,
        ], outputs=[c.slot_count, c.slot_tri, c.slot_w, c.slot_n, c.slot_k, c.slot_mu], device=dev)
        self._rev_count.zero_()
        self._launch("vbd_count_reverse_contacts", K.vbd_count_reverse_contacts, dim=Vs,
                     inputs=[m.surface_vertices, c.slot_count, c.slot_tri, m.tri_indices], outputs=[self._rev_count],
                     device=dev)
        wp.utils.array_scan(self._rev_count, c.rev_offsets, inclusive=False)
        self._rev_cursor.zero_()
        self._launch("vbd_fill_reverse_contacts", K.vbd_fill_reverse_contacts, dim=Vs,
                     inputs=[m.surface_vertices, c.slot_count, c.slot_tri, m.tri_indices, c.rev_offsets,
                             self._rev_cursor], outputs=[c.rev], device=dev)

    def _land(self, h: float) -> None:
        """Land the rigid initial guess on the ground, the plates and other pieces (see the
        kernels), then detect this substep's body contacts."""
        from holowarp.kernels import sim_vbd as K

        wp = init_warp()
        m = self.model
        dev = m.device
        N = m.particle_count
        C = self._shift.shape[0]
        surf = self._surf
        self._depth_cs.fill_(-1.0e30)
        if m.surface_count:
            self._launch("vbd_guess_depth", K.vbd_guess_depth, dim=N,
                         inputs=[self._q_start, self._dq, m.particle_component, surf], outputs=[self._depth_cs],
                         device=dev)
        touch = self.contact_radius + self.contact_margin
        self._launch("vbd_land_components", K.vbd_land_components, dim=C,
                     inputs=[self._component_free, self._disp, self._sum_m, self._sum_ma,
                             wp.vec3(*map(float, m.gravity)), h, surf, self._depth_cs, touch],
                     outputs=[self._shift, self._eff_disp, self._level], device=dev)
        shift = [self._dq, m.particle_inv_mass, m.particle_component, self._component_free, self._shift]
        self._launch("vbd_apply_shift", K.vbd_apply_shift, dim=N, inputs=shift, device=dev)
        if self.contacts_enabled:
            self._detect()
            Vs = m.surface_vertices.shape[0]
            c = self._con
            for _ in range(_SUPPORT_HOPS):
                self._launch("vbd_support_levels", K.vbd_support_levels, dim=Vs, inputs=[
                    m.surface_vertices, m.particle_component, c.slot_count, c.slot_tri, m.tri_component,
                ], outputs=[self._level], device=dev)
            for _ in range(_BODY_LANDING_ROUNDS):
                self._shift_pos.zero_()
                self._shift_neg.zero_()
                self._launch("vbd_body_landing", K.vbd_body_landing, dim=Vs, inputs=[
                    m.surface_vertices, self._q_start, self._dq, m.particle_component, self._component_free,
                    self._sum_m, self._level, self._eff_disp, c, m.tri_component,
                ], outputs=[self._shift_pos, self._shift_neg], device=dev)
                self._launch("vbd_merge_shift", K.vbd_merge_shift, dim=C, inputs=[self._shift_pos, self._shift_neg],
                             outputs=[self._shift, self._eff_disp], device=dev)
                self._launch("vbd_apply_shift", K.vbd_apply_shift, dim=N, inputs=shift, device=dev)
        if m.surface_count:
            self._launch("vbd_guess_project", K.vbd_guess_project, dim=N,
                         inputs=[self._q_start, self._dq, m.particle_inv_mass, surf], device=dev)

    # ------------------------------------------------------------------ stepping
    @property
    def wave_time(self) -> float:
        """Seconds a pressure wave ``sqrt((lambda + 2 mu) / rho)`` takes to cross the median
        boundary edge (the fastest material's)."""
        return self._wave_time

    def integrator_for(self, h: float) -> str:
        """The integrator of substeps of ``h`` seconds: ``"bdf2"`` or ``"euler"``."""
        if self.integrator != "auto":
            return self.integrator
        return "bdf2" if h <= self._wave_time else "euler"

    def guess_blend(self, h: float) -> float:
        """Share of each particle's own extrapolation in the initial guess for substeps of
        ``h`` s: ``min(1, L / (c h))`` with ``L`` the median boundary edge and ``c`` the
        fastest pressure-wave speed ``sqrt((lambda + 2 mu) / rho)`` (kernels: vbd_rigid_guess)."""
        return float(min(1.0, self._wave_time / h)) if h > 0 else 1.0

    def plan(self, dt: float) -> StepPlan:
        """The substeps and iterations used for steps of ``dt`` seconds."""
        if not dt > 0:
            raise ValueError(f"dt must be > 0 s, got {dt}")
        return StepPlan(float(dt), self.substeps, self.iterations,
                        integrator=self.integrator_for(float(dt) / self.substeps))

    def step(self, state_in, state_out, control, contacts, dt: float) -> None:
        """Advance ``state_in`` by ``dt`` seconds into ``state_out``.

        Args:
            state_in: read only.
            state_out: overwritten (may not be ``state_in``).
            control: surface poses for this step (:meth:`Control.set_time`).
            contacts: must be ``None``: ground, plate and body contacts are generated inside
                the step (kept for Newton's signature).
            dt: step length in seconds.
        """
        from holowarp.kernels import sim_vbd as K

        wp = init_warp()
        if contacts is not None:
            raise ValueError("contacts must be None: contacts are generated inside step")
        if state_out is state_in:
            raise ValueError("state_out must be a different State from state_in")
        if not dt > 0:
            raise ValueError(f"dt must be > 0 s, got {dt}")
        m = self.model
        dev = m.device
        n_sub = self.substeps
        h = float(dt) / n_sub
        damp = max(0.0, 1.0 - self.damping * h)
        thresh = _BOUNCE_THRESHOLD_G_DT * float(np.linalg.norm(m.gravity)) * h
        g = wp.vec3(*map(float, m.gravity))
        surf = self._surf
        surf.start = control.surface_start
        surf.end = control.surface_end
        con = self._con
        state_out.surface_force.zero_()
        N = m.particle_count
        use_bdf2 = self.integrator_for(h) == "bdf2"
        for k in range(n_sub):
            src = state_in if k == 0 else state_out
            # BDF2 needs the last substep, of this length: a new run (or a changed dt)
            # starts with one implicit Euler substep.
            bdf2 = use_bdf2 and abs(src.substep_length - h) <= 1e-9 * h
            h_eff = 2.0 * h / 3.0 if bdf2 else h
            con.friction_eps = self.friction_epsilon * h_eff
            surf.alpha0, surf.alpha1 = k / n_sub, (k + 1) / n_sub
            for a in (self._sum_m, self._sum_mx, self._sum_mv, self._sum_ma, self._sum_ml, self._ang,
                      self._inertia_tensor):
                a.zero_()
            self._launch("vbd_predict", K.vbd_predict, dim=N, inputs=[
                src.particle_q, src.particle_qd, src.particle_qdd, m.particle_mass, m.particle_inv_mass,
                m.particle_component, src.particle_dq, g, h, int(bdf2), surf,
            ], outputs=[self._q_start, self._qd_start, self._inertia, self._lag, self._surf_force, self._sum_m,
                        self._sum_mx, self._sum_mv, self._sum_ma, self._sum_ml], device=dev)
            self._launch("vbd_component_inertia", K.vbd_component_inertia, dim=N, inputs=[
                self._q_start, self._qd_start, m.particle_mass, m.particle_component, self._sum_m, self._sum_mx,
            ], outputs=[self._ang, self._inertia_tensor], device=dev)
            self._launch("vbd_component_motion", K.vbd_component_motion, dim=self._sum_m.shape[0], inputs=[
                self._sum_m, self._sum_mx, self._sum_mv, self._sum_ma, self._sum_ml, self._ang, self._inertia_tensor,
                g, h, int(bdf2),
            ], outputs=[self._com, self._disp, self._rot], device=dev)
            self._launch("vbd_rigid_guess", K.vbd_rigid_guess, dim=N, inputs=[
                self._q_start, self._qd_start, src.particle_qdd, m.particle_inv_mass, m.particle_component,
                self._component_free, self._com, self._disp, self._rot, self._lag, g, h, int(bdf2),
                self.guess_blend(h),
            ], outputs=[self._dq], device=dev)
            self._land(h)
            for it in range(self.iterations):
                self._sweep(self._sweeps[it % 2], h, h_eff)
            self._launch("vbd_finalize", K.vbd_finalize, dim=N, inputs=[
                self._dq, self._lag, self._q_start, self._qd_start, m.particle_inv_mass, surf,
                m.surface_restitution, self._surf_force, h, h_eff, int(use_bdf2), thresh, damp,
                1.0 / n_sub,
            ], outputs=[state_out.particle_q, state_out.particle_qd, state_out.particle_qdd, state_out.particle_dq,
                        state_out.surface_force], device=dev)
            state_out.substep_length = h

    def _launch(self, site, kernel, *, dim, inputs=(), outputs=(), device=None) -> None:
        """``wp.launch`` through the solver's :class:`holowarp.ops.launches.LaunchCache`."""
        self._launches.launch(site, kernel, dim, inputs, outputs, device)

    def _sweep(self, sweep, h: float, h_eff: float) -> None:
        """One Gauss-Seidel sweep ``(order, phases)`` of the block steps: the phases one
        after another, the domains of a phase at once on the kernel thread pool."""
        from holowarp.kernels import sim_vbd as K

        m = self.model
        order, phases = sweep

        def solve(off, cnt):
            self._launch(("vbd_solve_vertices", id(order), off), K.vbd_solve_vertices, dim=cnt, inputs=[
                order, off, self._dq, self._q_start, self._inertia, self._lag, m.particle_mass,
                m.particle_inv_mass, 1.0 / (h_eff * h_eff), h_eff / h, self._tets, self._surf, self._con,
                self._surf_force,
            ], device=m.device)

        for phase in phases:
            run_chunks(solve, phase, kernel=K.vbd_solve_vertices, device=m.device)

    # ------------------------------------------------------------------ measurements
    def tet_stats(self, state) -> tuple[int, float]:
        """(number of tets with signed volume <= 0, total signed volume in m³) of ``state``.
        Synchronises with the device."""
        from holowarp.kernels import sim_vbd as K

        wp = init_warp()
        m = self.model
        self._stats.zero_()
        wp.launch(K.sim_tet_stats, dim=m.tet_count, inputs=[state.particle_q, m.tet_indices],
                  outputs=[self._stats], device=m.device)
        inv, vol = self._stats.numpy()
        return int(round(float(inv))), float(vol)

    def elastic_forces(self, state) -> tuple[np.ndarray, float]:
        """Elastic forces (N, 3) in N and energy in J of the stable Neo-Hookean material at
        ``state``'s positions (zero forces and energy at rest and under rigid motions)."""
        from holowarp.kernels import sim_vbd as K

        wp = init_warp()
        m = self.model
        f = wp.zeros(m.particle_count, dtype=wp.vec3, device=m.device)
        e = wp.zeros(1, dtype=float, device=m.device)
        wp.launch(K.sim_tet_forces, dim=m.tet_count,
                  inputs=[state.particle_q, m.tet_indices, m.tet_dm_inv, m.tet_volume, m.tet_mu, m.tet_lambda],
                  outputs=[f, e], device=m.device)
        return f.numpy().astype(np.float64), float(e.numpy()[0])

    def penetration(self, state, surface_points=None) -> dict:
        """How far ``state`` violates the contacts, in metres.

        Args:
            state: the state to measure.
            surface_points: (S, 3) contact-plane points at the state's time (default: the
                model's at t = 0).

        Returns:
            ``{"bodies": the deepest a surface vertex lies inside another face-connected
            component (inside one of its tets, measured to its surface; 0 for a single
            piece), "surfaces": the deepest a particle lies behind the ground or a plate,
            "max": the larger of the two, "vertices_inside": how many surface vertices are
            inside another component}``. Synchronises with the device.
        """
        from holowarp.kernels import sim_vbd as K

        wp = init_warp()
        m = self.model
        dev = m.device
        x = state.positions()
        pen_s = 0.0
        if m.surface_count:
            pts = m.surface_points(0.0) if surface_points is None else np.asarray(surface_points, np.float64)
            dist = np.einsum("nsk,sk->ns", x[:, None, :] - pts[None], m.surface_normals())
            pen_s = float(max(0.0, -dist.min()))
        pen_b, inside = 0.0, 0
        if m.component_count >= 2:
            if not hasattr(self, "_tet_bvh"):
                self._tet_lo = wp.zeros(m.tet_count, dtype=wp.vec3, device=dev)
                self._tet_hi = wp.zeros(m.tet_count, dtype=wp.vec3, device=dev)
                wp.launch(K.vbd_tet_bounds, dim=m.tet_count, inputs=[state.particle_q, m.tet_indices],
                          outputs=[self._tet_lo, self._tet_hi], device=dev)
                self._tet_bvh = wp.Bvh(self._tet_lo, self._tet_hi)
                self._mtri_lo = wp.zeros(len(m.tris), dtype=wp.vec3, device=dev)
                self._mtri_hi = wp.zeros(len(m.tris), dtype=wp.vec3, device=dev)
                self._zero_dq = wp.zeros(m.particle_count, dtype=wp.vec3, device=dev)
                wp.launch(K.vbd_triangle_bounds, dim=len(m.tris),
                          inputs=[state.particle_q, self._zero_dq, m.tri_indices, 0.0],
                          outputs=[self._mtri_lo, self._mtri_hi], device=dev)
                self._mtri_bvh = wp.Bvh(self._mtri_lo, self._mtri_hi)
                self._depth = wp.zeros(m.surface_vertices.shape[0], dtype=float, device=dev)
            wp.launch(K.vbd_tet_bounds, dim=m.tet_count, inputs=[state.particle_q, m.tet_indices],
                      outputs=[self._tet_lo, self._tet_hi], device=dev)
            self._tet_bvh.refit()
            wp.launch(K.vbd_triangle_bounds, dim=len(m.tris),
                      inputs=[state.particle_q, self._zero_dq, m.tri_indices, 0.0],
                      outputs=[self._mtri_lo, self._mtri_hi], device=dev)
            self._mtri_bvh.refit()
            wp.launch(K.vbd_penetration, dim=m.surface_vertices.shape[0], inputs=[
                self._tet_bvh.id, self._mtri_bvh.id, m.surface_vertices, state.particle_q, m.particle_component,
                m.tet_indices, m.tet_component, m.tri_indices, m.tri_component, m.median_surface_edge(),
            ], outputs=[self._depth], device=dev)
            dep = self._depth.numpy()
            pen_b = float(dep.max()) if len(dep) else 0.0
            inside = int((dep > 0).sum())
        return {"bodies": pen_b, "surfaces": pen_s, "max": max(pen_b, pen_s), "vertices_inside": inside}


def sweep_phases(order: np.ndarray, tets: np.ndarray, points: np.ndarray, parts: int,
                 levels: int = _SWEEP_LEVELS) -> tuple[np.ndarray, list]:
    """A Gauss-Seidel sweep order whose phases sweep ``parts`` domains at once.

    Nested dissection: the particles are cut into ``parts`` slabs of equal count across the
    longest extent of ``points``; the particles of the tets that span two slabs (the
    separator) are left for the next level, which cuts them the same way, and what remains
    after ``levels`` cuts (or once fewer than 512 are left) forms one serial phase. No two
    particles of different domains of a phase share a tet (a shared tet would span their
    slabs and put both in the separator), and a phase writes only its own particles, so the
    domains' sweeps are independent and the result equals the serial sweep of the returned
    order, on any number of threads.
    Within a domain the particles keep their place in ``order``.

    Why: Warp's CPU backend runs a launch on one thread, so a serial sweep uses one core.
    On a 50k-tet cube the two-slab separator holds 9 % of the particles and the next level
    leaves about 1 % serial, so two cores sweep it 1.5-1.8x as fast (measured).

    Args:
        order: (N,) the serial order (particle ids).
        tets: (M, 4) particle ids.
        points: (N, 3) rest positions (only their spread matters).
        parts: domains per phase (>= 2).
        levels: dissection levels.

    Returns:
        (order (N,) int32, phases): ``phases[k]`` is a list of ``(offset, count)`` ranges of
        the returned order, swept at once; the phases run one after another.
    """
    order = np.asarray(order, np.int64)
    tets = np.asarray(tets, np.int64)
    points = np.asarray(points, np.float64)
    N = len(order)
    side = np.full(N, -1, np.int64)
    remaining = order
    out, phases, off = [], [], 0
    for _ in range(levels):
        if len(remaining) < max(2 * parts, _SWEEP_SERIAL_VERTICES):
            break
        p = points[remaining]
        axis = int(np.argmax(p.max(0) - p.min(0)))
        rank = np.empty(len(remaining), np.int64)
        rank[np.argsort(p[:, axis], kind="stable")] = np.arange(len(remaining))
        side[:] = -1
        side[remaining] = rank * parts // len(remaining)
        st = side[tets]
        live = st >= 0
        lo = np.where(live, st, parts).min(1)
        spans = lo < st.max(1)
        sep = np.zeros(N, bool)
        sep[tets[spans][live[spans]]] = True
        phase = []
        for d in range(parts):
            dom = remaining[(side[remaining] == d) & ~sep[remaining]]
            if len(dom):
                out.append(dom)
                phase.append((off, len(dom)))
                off += len(dom)
        phases.append(phase)
        remaining = remaining[sep[remaining]]
    if len(remaining):
        out.append(remaining)
        phases.append([(off, len(remaining))])
    return np.concatenate(out).astype(np.int32), phases


def _triangle_neighbours(tris: np.ndarray) -> np.ndarray:
    """(T, 3) int32: the triangle sharing edge (k, k+1) of each triangle, -1 where the edge
    has no other triangle or more than one (non-manifold)."""
    T = len(tris)
    out = np.full((T, 3), -1, np.int32)
    if T == 0:
        return out
    e = np.stack([tris, np.roll(tris, -1, axis=1)], axis=2).reshape(-1, 2).astype(np.int64)  # [3T, 2]
    key = np.minimum(e[:, 0], e[:, 1]) * (int(tris.max()) + 1) + np.maximum(e[:, 0], e[:, 1])
    order = np.argsort(key, kind="stable")
    sk = key[order]
    counts = np.bincount(np.unique(sk, return_inverse=True)[1])
    grp = np.unique(sk, return_inverse=True)[1]
    pair = (counts[grp] == 2)
    first = pair & np.r_[True, sk[1:] != sk[:-1]]
    a, b = order[np.flatnonzero(first)], order[np.flatnonzero(first) + 1]
    flat = out.reshape(-1)
    flat[a] = b // 3
    flat[b] = a // 3
    return out
