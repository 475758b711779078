"""Simulate a scene in memory: place the meshes, step the solver, record frames and measures.

:func:`run_scene` writes no files; :mod:`holowarp.simulation` (the ``simulate`` application)
adds file loading, USD, reports and renders on top of it.

Frames are recorded at :data:`FPS` per second (frame k = time k / FPS s); the step ``dt`` of
the scene must divide 1 / FPS s.
"""

from __future__ import annotations

import time

import numpy as np

from holowarp.errors import RunError
from holowarp.sim.analysis import center_of_mass
from holowarp.sim.scene import Scene, build_model, solver_options
from holowarp.sim.solver import SolverVBDNeoHookean

__all__ = ["FPS", "NonFiniteStateError", "run_scene"]

#: Output frame rate (frames per second) of recorded frames, USD time samples and renders.
FPS = 60


class NonFiniteStateError(RunError):
    """The simulation produced non-finite positions; the message names the step."""


def run_scene(scene: Scene, mesh, *, transform=None, device: str = "cpu", progress=None,
              desc: str = "simulate", measure_penetration: bool = True) -> dict:
    """Simulate ``scene`` with ``mesh``; return frames and measurements (no files written).

    Args:
        scene: the scene.
        mesh: one :class:`TetMesh` for every body, or a list with one per body of
            ``scene.body_specs()`` (see :func:`holowarp.sim.scene.build_model`).
        transform: placement(s), as :func:`~holowarp.sim.scene.build_model` takes them.
        device: Warp device.
        progress: object with ``update(n)`` called once per step (a tqdm bar), or None.
        measure_penetration: measure contact penetration at every frame.

    Returns:
        A dict with ``model``, ``solver``, ``plan`` (:class:`StepPlan`), ``frames`` (F, N, 3)
        float32 positions at 60 fps, ``surface_points`` (F, S, 3), ``surface_force``
        (F, S, 3) N, ``inverted`` (F,) inverted tets per frame, ``volume`` (F,) m³,
        ``com`` (F, 3) m, ``penetration`` (F,) m (see
        :meth:`SolverVBDNeoHookean.penetration`, ``max``), ``nan`` (always False: see
        Raises), ``steps`` run, ``seconds`` (wall time of the stepping loop),
        ``transforms`` (one per body), ``transform`` (the first) and ``bbox``.

    Raises:
        NonFiniteStateError: positions became non-finite; names the step and time.
    """
    from holowarp.device import init_warp

    wp = init_warp()
    model, transforms, bbox = build_model(scene, mesh, transform=transform, device=device)
    sim = scene.sim
    solver = SolverVBDNeoHookean(model, **solver_options(scene))
    plan = solver.plan(sim.dt)
    steps_per_frame = int(round(1.0 / (FPS * sim.dt)))
    n_steps = scene.num_steps
    s0, s1, control = model.state(), model.state(), model.control()

    rec = _Recorder(model, solver, measure_penetration)
    record = rec.record
    record(s0, 0.0)
    steps = 0
    seconds = 0.0
    t0 = time.perf_counter()
    for k in range(n_steps):
        ta, tb = k * sim.dt, (k + 1) * sim.dt
        control.set_time(ta, tb)
        solver.step(s0, s1, control, None, sim.dt)
        s0, s1 = s1, s0
        steps += 1
        if progress is not None:
            progress.update(1)
        if steps % steps_per_frame == 0:
            wp.synchronize_device(model.device)
            seconds += time.perf_counter() - t0
            ok = record(s0, tb)
            t0 = time.perf_counter()
            if not ok:
                raise NonFiniteStateError(
                    f"scene {scene.name!r}: non-finite positions after step {steps} (t = {tb:.4f} s); "
                    f"the inputs are likely out of range (youngs_modulus {_materials(scene)} Pa, dt {sim.dt:g} s, "
                    f"gravity {list(sim.gravity)} m/s^2, {_placements(scene)}) or the mesh has degenerate tets")
    wp.synchronize_device(model.device)
    seconds += time.perf_counter() - t0
    return {
        "model": model, "solver": solver, "plan": plan, **rec.arrays(), "nan": False, "steps": steps,
        "seconds": seconds, "transforms": transforms, "transform": transforms[0], "bbox": bbox,
    }


class _Recorder:
    """Per-frame measurements of a run (positions, surfaces, forces, tets, penetration)."""

    def __init__(self, model, solver, measure_penetration: bool):
        self.model, self.solver, self.measure = model, solver, measure_penetration
        self.frames, self.surf_pts, self.surf_f, self.inverted, self.volume, self.com, self.pen = ([] for _ in range(7))

    def record(self, state, t: float) -> bool:
        """Record ``state`` at time ``t``; False if its positions are not finite."""
        m = self.model
        x = state.positions()
        self.frames.append(x.astype(np.float32))
        if not np.all(np.isfinite(x)):
            return False
        inv, vol = self.solver.tet_stats(state)
        pts = m.surface_points(t)
        self.surf_pts.append(pts)
        self.surf_f.append(state.surface_force.numpy()[: m.surface_count].astype(np.float64))
        self.inverted.append(inv)
        self.volume.append(vol)
        self.com.append(center_of_mass(x, m.masses))
        self.pen.append(self.solver.penetration(state, pts)["max"] if self.measure else 0.0)
        return True

    def arrays(self) -> dict:
        return {"frames": np.stack(self.frames), "surface_points": np.stack(self.surf_pts),
                "surface_force": np.stack(self.surf_f), "inverted": np.asarray(self.inverted),
                "volume": np.asarray(self.volume), "com": np.stack(self.com), "penetration": np.asarray(self.pen)}


def _placements(scene: Scene) -> str:
    sizes = sorted({b.placement.size for b in scene.body_specs()})
    speeds = sorted({float(np.linalg.norm(b.placement.velocity)) for b in scene.body_specs()})
    return f"size {', '.join(f'{v:g}' for v in sizes)} m, initial speed {', '.join(f'{v:g}' for v in speeds)} m/s"


def _materials(scene: Scene) -> str:
    es = sorted({b.material.youngs_modulus for b in scene.body_specs()})
    return ", ".join(f"{e:g}" for e in es)
