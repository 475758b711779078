"""What changes from step to step (Newton's ``State``): particle positions and velocities."""

from __future__ import annotations

import numpy as np

__all__ = ["State"]


class State:
    """Time-varying simulation data on the model's device.

    Attributes:
        particle_q: [N] wp.vec3 positions, m.
        particle_qd: [N] wp.vec3 velocities, m/s.
        particle_qdd: [N] wp.vec3 accelerations over the last substep, m/s² (the solver's
            initial guess for the next one uses it; starts at gravity, i.e. free fall).
        surface_force: [S] wp.vec3 mean force each contact surface (ground, then plates)
            exerted on the bodies during the step that produced this state, N.
        particle_dq: [N] wp.vec3 displacements over the last substep, m (BDF2's second
            history point, ``x_n - x_(n-1)``).
        substep_length: length of the substep that produced ``particle_dq``, s; 0 when
            there is none yet (the solver's BDF2 then starts with an implicit Euler substep).

    Create one with :meth:`holowarp.sim.Model.state`; it starts at the model's initial
    positions and velocities.
    """

    def __init__(self, model):
        import warp as wp

        self.particle_q = wp.clone(model.particle_q)
        self.particle_qd = wp.clone(model.particle_qd)
        g = np.broadcast_to(np.asarray(model.gravity, np.float32), (model.particle_count, 3))
        self.particle_qdd = wp.array(np.ascontiguousarray(g), dtype=wp.vec3, device=model.device)
        self.surface_force = wp.zeros(max(model.surface_count, 1), dtype=wp.vec3, device=model.device)
        self.particle_dq = wp.zeros(model.particle_count, dtype=wp.vec3, device=model.device)
        self.substep_length = 0.0

    def positions(self) -> np.ndarray:
        """Positions (N, 3) float64 on the host (synchronises)."""
        return self.particle_q.numpy().astype(np.float64)

    def velocities(self) -> np.ndarray:
        """Velocities (N, 3) float64 on the host (synchronises)."""
        return self.particle_qd.numpy().astype(np.float64)

    def assign(self, other: "State") -> None:
        """Copy ``other``'s arrays into this state."""
        self.particle_q.assign(other.particle_q)
        self.particle_qd.assign(other.particle_qd)
        self.particle_qdd.assign(other.particle_qdd)
        self.surface_force.assign(other.surface_force)
        self.particle_dq.assign(other.particle_dq)
        self.substep_length = other.substep_length
