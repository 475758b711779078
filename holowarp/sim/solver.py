"""XPBD solver for stable Neo-Hookean tet meshes (Newton's ``Solver`` shape).

``SolverXPBDNeoHookean.step(state_in, state_out, control, contacts, dt)`` advances one step
of ``dt`` seconds in ``substeps`` substeps of ``iterations`` Gauss-Seidel iterations each.
It reads ``state_in`` and ``control`` and writes only ``state_out`` (plus its own scratch
arrays), so the same inputs always give the same output.

Per substep (kernels in :mod:`holowarp.kernels.sim_xpbd`):

1. predict positions with gravity (symplectic Euler);
2. ``iterations`` x: project every tet's coupled deviatoric + hydrostatic stable
   Neo-Hookean constraints (Macklin & Müller 2021) colour by colour, then push its vertices
   out of the ground and plate half-spaces with position-level Coulomb friction; odd
   iterations sweep the colours backwards (symmetric Gauss-Seidel);
3. velocity update, restitution and velocity damping.

Stability. The two constraints have no common zero (``|F| = 0`` and ``det F = gamma`` exclude
each other); the rest state is a balance of two large opposing multipliers, and part of the
material's stiffness lives in the constraints' curvature, which XPBD's linearised update
ignores. The iteration is therefore only stable while the compliance dominates, i.e. while
the substep is below roughly one shear-wave crossing of a tet. Per tet, at rest,
``r = mu V h^2 sum_k w_k |dC_D/dx_k|^2`` must stay below :data:`STABILITY_RATIO` (measured:
the scheme diverges for r of about 0.8 and above on regular and Kuhn-split meshes, whatever the
iteration count). :meth:`SolverXPBDNeoHookean.plan` raises the number of substeps until
every tet (or the ``stability_percentile``-th percentile) is below the limit, up to
``max_substeps``; it keeps the iteration budget per step (``iterations x requested
substeps``, rounded to the nearest whole number of iterations per substep, at least one:
more, smaller steps are more accurate than more iterations, Macklin et al. 2019 "Small
steps in physics simulation"); tets still above
the limit at the cap (slivers) are softened just enough to be stable. The plan reports all
of it (:class:`StepPlan`).

Inverted tets need no special case: the hydrostatic constraint ``det F - gamma`` has the
cofactor as gradient, which stays defined through ``det F = 0`` and pushes an inverted tet
back to positive volume. :meth:`SolverXPBDNeoHookean.tet_stats` counts them.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from holowarp.device import init_warp

__all__ = ["SolverXPBDNeoHookean", "StepPlan", "PAPER_DT", "PAPER_ITERATIONS", "STABILITY_RATIO"]

#: method.md §10 (the paper's Isaac Sim setup): 60 steps per second, 16 solver iterations.
PAPER_DT = 1.0 / 60.0
PAPER_ITERATIONS = 16

#: Largest per-tet ratio r (module docstring) a substep may reach; divergence was measured
#: from about 0.8, so this keeps a margin of 1.6.
STABILITY_RATIO = 0.5

#: Approach speeds below this many g*dt do not bounce (restitution), so resting contact
#: does not jitter (Müller et al. 2020, "Detailed Rigid Body Simulation with XPBD").
_BOUNCE_THRESHOLD_G_DT = 2.0


@dataclass(frozen=True)
class StepPlan:
    """How one step of a given length is split (see :meth:`SolverXPBDNeoHookean.plan`).

    Attributes:
        dt: step length, s.
        substeps: substeps per step actually used.
        iterations: Gauss-Seidel iterations per substep actually used.
        requested_substeps, requested_iterations: what the solver was built with.
        softened_tets: tets whose stiffness is scaled down for stability at this substep.
        min_stiffness_scale: smallest such scale (1 when none).
    """

    dt: float
    substeps: int
    iterations: int
    requested_substeps: int
    requested_iterations: int
    softened_tets: int
    min_stiffness_scale: float

    def as_dict(self) -> dict:
        return dict(self.__dict__)


class SolverXPBDNeoHookean:
    """Extended position-based dynamics with stable Neo-Hookean tet constraints.

    Args:
        model: the :class:`holowarp.sim.Model`.
        iterations: Gauss-Seidel iterations per substep (paper: 16).
        substeps: substeps per :meth:`step`.
        damping: velocity damping rate in 1/s; velocities are scaled by
            ``max(0, 1 - damping * dt_substep)`` each substep.
        stability: ``"auto"``: raise substeps and soften outlier tets as described in the
            module docstring; ``"off"``: use ``substeps`` and ``iterations`` as given.
        stability_percentile: percentile of the per-tet ratio that the substep count must
            bring below :data:`STABILITY_RATIO`; tets above it are softened.
        max_substeps: cap on the automatically raised substep count.
        fuse_colors: launch all colours in one kernel launch per iteration. Only valid where
            a launch runs its threads serially in index order (Warp's CPU backend), where it
            gives bit-identical results to per-colour launches. ``None``: on CPU only.
    """

    def __init__(self, model, *, iterations: int = PAPER_ITERATIONS, substeps: int = 1,
                 damping: float = 0.0, stability: str = "auto", stability_percentile: float = 100.0,
                 max_substeps: int = 64, fuse_colors: bool | None = None):
        wp = init_warp()
        if int(iterations) < 1:
            raise ValueError(f"iterations must be >= 1, got {iterations}")
        if int(substeps) < 1:
            raise ValueError(f"substeps must be >= 1, got {substeps}")
        if not np.isfinite(damping) or damping < 0:
            raise ValueError(f"damping must be >= 0 (1/s), got {damping}")
        self.model = model
        self.iterations = int(iterations)
        self.substeps = int(substeps)
        self.damping = float(damping)
        if stability not in ("auto", "off"):
            raise ValueError(f"stability must be 'auto' or 'off', got {stability!r}")
        if not 0.0 < stability_percentile <= 100.0:
            raise ValueError(f"stability_percentile must lie in (0, 100], got {stability_percentile}")
        self.stability = stability
        self.stability_percentile = float(stability_percentile)
        self.max_substeps = max(int(max_substeps), self.substeps)
        self._ratio1 = _stability_ratio_unit_step(model)  # [M] r at h = 1 s
        self._plans: dict[float, tuple[StepPlan, object]] = {}
        is_cpu = wp.get_device(model.device).is_cpu
        if fuse_colors is None:
            fuse_colors = is_cpu
        if fuse_colors and not is_cpu:
            raise ValueError("fuse_colors=True is only valid on the CPU (serial launches)")
        self.fuse_colors = bool(fuse_colors)
        dev = model.device
        N, M = model.particle_count, model.tet_count
        S = max(model.surface_count, 1)
        self._q_start = wp.zeros(N, dtype=wp.vec3, device=dev)
        self._qd_start = wp.zeros(N, dtype=wp.vec3, device=dev)
        self._depth = wp.zeros((N, S), dtype=float, device=dev)
        self._fric = wp.zeros((N, S), dtype=wp.vec3, device=dev)
        self._lambdas = wp.zeros(M, dtype=wp.vec2, device=dev)
        self._stats = wp.zeros(2, dtype=float, device=dev)
        offs = model.tet_color_offsets
        M = int(offs[-1])
        if self.fuse_colors:
            fwd = [(0, M)]
        else:
            fwd = [(int(offs[c]), int(offs[c + 1] - offs[c])) for c in range(len(offs) - 1)]
        # Symmetric Gauss-Seidel: odd iterations sweep the colours (and the tets in them) in
        # reverse, so no direction of the mesh is favoured by the sweep order.
        rev_order = wp.array(model.tet_color_order.numpy()[::-1].copy(), dtype=wp.int32, device=dev)
        rev = [(M - off - cnt, cnt) for off, cnt in reversed(fwd)]
        self._sweeps = [(model.tet_color_order, fwd), (rev_order, rev)]

    def plan(self, dt: float) -> StepPlan:
        """The substeps, iterations and softened tets used for steps of ``dt`` seconds."""
        return self._plan(dt)[0]

    def _plan(self, dt: float):
        dt = float(dt)
        hit = self._plans.get(dt)
        if hit is not None:
            return hit
        wp = init_warp()
        S, I = self.substeps, self.iterations
        r1 = self._ratio1
        if self.stability == "auto" and len(r1):
            rp = float(np.percentile(r1, self.stability_percentile))
            need = int(np.ceil(dt * np.sqrt(rp / STABILITY_RATIO) - 1e-9)) if rp > 0 else 1
            if need > S:
                S_new = min(need, self.max_substeps)
                I = max(1, int(np.floor(self.iterations * self.substeps / S_new + 0.5)))
                S = S_new
        h = dt / S
        scale = np.ones(len(r1))
        if self.stability == "auto":
            r = r1 * h * h
            over = r > STABILITY_RATIO
            scale[over] = STABILITY_RATIO / r[over]
        plan = StepPlan(dt, S, I, self.substeps, self.iterations, int((scale < 1).sum()),
                        float(scale.min()) if len(scale) else 1.0)
        arr = wp.array(scale.astype(np.float32), dtype=float, device=self.model.device)
        self._plans[dt] = (plan, arr)
        return plan, arr

    def step(self, state_in, state_out, control, contacts, dt: float) -> None:
        """Advance ``state_in`` by ``dt`` seconds into ``state_out``.

        Args:
            state_in: read only.
            state_out: overwritten (may not be ``state_in``).
            control: surface poses for this step (:meth:`Control.set_time`).
            contacts: must be ``None``: the ground and plates are analytic half-spaces whose
                contacts the step generates itself (kept for Newton's signature).
            dt: step length in seconds.
        """
        from holowarp.kernels import sim_xpbd as K

        wp = init_warp()
        if contacts is not None:
            raise ValueError("contacts must be None: ground and plate contacts are generated inside step")
        if state_out is state_in:
            raise ValueError("state_out must be a different State from state_in")
        if not dt > 0:
            raise ValueError(f"dt must be > 0 s, got {dt}")
        m = self.model
        dev = m.device
        plan, stiff = self._plan(dt)
        n_sub = plan.substeps
        h = float(dt) / n_sub
        S = m.surface_count
        damp = max(0.0, 1.0 - self.damping * h)
        thresh = _BOUNCE_THRESHOLD_G_DT * float(np.linalg.norm(m.gravity)) * h
        g = wp.vec3(*map(float, m.gravity))
        state_out.surface_force.zero_()
        for k in range(n_sub):
            src = state_in if k == 0 else state_out
            a0, a1 = k / n_sub, (k + 1) / n_sub
            wp.launch(
                K.sim_predict,
                dim=m.particle_count,
                inputs=[src.particle_q, src.particle_qd, m.particle_inv_mass, g, h, S],
                outputs=[state_out.particle_q, self._q_start, self._qd_start, self._depth, self._fric],
                device=dev,
            )
            for it in range(plan.iterations):
                order, launches = self._sweeps[it % 2]
                for off, cnt in launches:
                    wp.launch(
                        K.sim_solve_tets,
                        dim=cnt,
                        inputs=[
                            order, off, state_out.particle_q, m.particle_inv_mass,
                            m.tet_indices, m.tet_dm_inv, m.tet_volume, m.tet_mu, m.tet_lambda, stiff,
                            self._lambdas, int(it == 0), 1.0 / (h * h), self._q_start, m.surface_normal,
                            control.surface_start, control.surface_end, a0, a1, S, m.surface_friction,
                            self._depth, self._fric,
                        ],
                        device=dev,
                    )
            wp.launch(
                K.sim_finalize,
                dim=m.particle_count,
                inputs=[
                    state_out.particle_q, self._q_start, self._qd_start, m.particle_inv_mass,
                    m.particle_mass, m.surface_normal, control.surface_start, control.surface_end,
                    a0, a1, m.surface_friction, m.surface_restitution, S, self._depth, self._fric, h, thresh,
                    damp, 1.0 / (h * h * n_sub),
                ],
                outputs=[state_out.particle_qd, state_out.surface_force],
                device=dev,
            )

    def tet_stats(self, state) -> tuple[int, float]:
        """(number of tets with signed volume <= 0, total signed volume in m³) of ``state``.
        Synchronises with the device."""
        from holowarp.kernels import sim_xpbd as K

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
        from holowarp.kernels import sim_xpbd as K

        wp = init_warp()
        m = self.model
        f = wp.zeros(m.particle_count, dtype=wp.vec3, device=m.device)
        e = wp.zeros(1, dtype=float, device=m.device)
        wp.launch(
            K.sim_tet_forces,
            dim=m.tet_count,
            inputs=[state.particle_q, m.tet_indices, m.tet_dm_inv, m.tet_volume, m.tet_mu, m.tet_lambda],
            outputs=[f, e],
            device=m.device,
        )
        return f.numpy().astype(np.float64), float(e.numpy()[0])


def _stability_ratio_unit_step(model) -> np.ndarray:
    """Per-tet ``r`` of the module docstring at h = 1 s: ``mu V sum_k w_k |b_k|^2 / 3``, where
    ``b_k`` are the rest shape-function gradients (rows of Dm^-1, b_0 = -sum) and
    ``dC_D/dx_k = b_k / sqrt(3)`` at rest. (M,) float64."""
    T = model.tets
    X = model.rest_positions
    if len(T) == 0:
        return np.zeros(0)
    Dm = np.stack([X[T[:, 1]] - X[T[:, 0]], X[T[:, 2]] - X[T[:, 0]], X[T[:, 3]] - X[T[:, 0]]], axis=2)
    Di = np.linalg.inv(Dm)  # [M, 3, 3]; row k-1 is b_k
    b = np.concatenate([-Di.sum(axis=1, keepdims=True), Di], axis=1)  # [M, 4, 3]
    w = np.where(model.fixed, 0.0, 1.0 / model.masses)[T]  # [M, 4]
    a_dd = (w * (b * b).sum(axis=2)).sum(axis=1) / 3.0
    mu = model.tet_mu_host
    return mu * model.tet_volume_host * a_dd
