"""What the user drives (Newton's ``Control``): kinematic contact-surface poses per step."""

from __future__ import annotations

import numpy as np

__all__ = ["Control"]


class Control:
    """Poses of the contact surfaces at the start and end of the current step.

    The solver moves each surface point linearly from ``surface_start`` to ``surface_end``
    over the step (substeps see intermediate poses). Surface order is the model's: the
    ground first when present, then the plates.

    Attributes:
        surface_start: [S] wp.vec3 surface points at the start of the step, m.
        surface_end: [S] wp.vec3 surface points at the end of the step, m.

    Use :meth:`set_time` to follow the plates' schedules from the scene, or
    :meth:`set_surface_points` to drive them yourself.
    """

    def __init__(self, model):
        import warp as wp

        self._model = model
        S = max(model.surface_count, 1)
        p0 = np.zeros((S, 3), np.float32)
        if model.surface_count:
            p0[:] = model.surface_points(0.0)
        self.surface_start = wp.array(p0, dtype=wp.vec3, device=model.device)
        self.surface_end = wp.array(p0, dtype=wp.vec3, device=model.device)

    def set_time(self, t0: float, t1: float) -> None:
        """Poses for a step from ``t0`` to ``t1`` seconds from the model's plate paths."""
        m = self._model
        if m.surface_count == 0:
            return
        self.set_surface_points(m.surface_points(t0), m.surface_points(t1))

    def set_surface_points(self, start, end) -> None:
        """Set (S, 3) surface points (m) at the start and end of the next step."""
        S = self._model.surface_count
        start = np.asarray(start, np.float32).reshape(S, 3)
        end = np.asarray(end, np.float32).reshape(S, 3)
        self.surface_start.assign(start)
        self.surface_end.assign(end)
