"""Simulate a scene in memory: place the meshes, step the solver, record frames and measures.

:func:`run_scene` writes no files; :mod:`holowarp.simulation` (the ``simulate`` application)
adds file loading, USD, reports and renders on top of it.

Frames are recorded at :data:`FPS` per second (frame k = time k / FPS s); the step ``dt`` of
the scene must divide 1 / FPS s.
"""

from __future__ import annotations

import time

import numpy as np

from holowarp.sim.analysis import center_of_mass
from holowarp.sim.scene import Scene, build_model
from holowarp.sim.solver import SolverXPBDNeoHookean
from holowarp.tetmesh import TetMesh

__all__ = ["FPS", "run_scene"]

#: Output frame rate (frames per second) of recorded frames, USD time samples and renders.
FPS = 60


def run_scene(scene: Scene, mesh: TetMesh, *, transform=None, device: str = "cpu", progress=None,
              desc: str = "simulate") -> dict:
    """Simulate ``mesh`` in ``scene``; return frames and measurements (no files written).

    Returns a dict with ``model``, ``solver``, ``plan`` (:class:`StepPlan`), ``frames``
    (F, N, 3) float32 positions at 60 fps, ``surface_points`` (F, S, 3), ``surface_force``
    (F, S, 3) N, ``inverted`` (F,), ``volume`` (F,) m³, ``com`` (F, 3), ``nan`` (bool),
    ``steps`` run, ``seconds`` (wall time of the stepping loop), ``transform``, ``bbox``.
    """
    from holowarp.device import init_warp

    wp = init_warp()
    model, transform, bbox = build_model(scene, mesh, transform=transform, device=device)
    sim = scene.sim
    solver = SolverXPBDNeoHookean(model, iterations=sim.iterations, substeps=sim.substeps, damping=sim.damping)
    plan = solver.plan(sim.dt)
    steps_per_frame = int(round(1.0 / (FPS * sim.dt)))
    n_steps = scene.num_steps
    s0, s1, control = model.state(), model.state(), model.control()

    frames, surf_pts, surf_f, inverted, volume, com = [], [], [], [], [], []

    def record(state, t):
        x = state.positions()
        inv, vol = solver.tet_stats(state)
        frames.append(x.astype(np.float32))
        surf_pts.append(model.surface_points(t))
        surf_f.append(state.surface_force.numpy()[: model.surface_count].astype(np.float64))
        inverted.append(inv)
        volume.append(vol)
        com.append(center_of_mass(x, model.masses))
        return bool(np.all(np.isfinite(x)))

    record(s0, 0.0)
    nan = False
    steps = 0
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
            if not record(s0, tb):
                nan = True
                break
    wp.synchronize_device(model.device)
    seconds = time.perf_counter() - t0
    return {
        "model": model, "solver": solver, "plan": plan, "frames": np.stack(frames),
        "surface_points": np.stack(surf_pts), "surface_force": np.stack(surf_f),
        "inverted": np.asarray(inverted), "volume": np.asarray(volume), "com": np.stack(com),
        "nan": nan, "steps": steps, "seconds": seconds, "transform": transform, "bbox": bbox,
    }
