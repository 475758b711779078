"""The same scene in Newton's ``SolverVBD``: the independent reference for holowarp's solver.

Newton (``pip install newton``, no extras; it is in holowarp's ``test`` extra) is imported
only here and only when called. The mesh is added with ``ModelBuilder.add_soft_mesh`` with
the same placement, Lamé parameters and density (Newton's Neo-Hookean is Smith et al. 2018
without the log term, with ``lambda' = lambda + mu``; it linearises to the same Lamé
parameters), gravity, ground plane and friction; VBD runs at the ``dt``, substeps and
iterations it is given. Several bodies touch through Newton's particle self-contact.

Contact differs by design: Newton's ground is a penalty contact (stiffness ``contact_ke``
N/m per particle, damping ``contact_kd``, Coulomb ``mu``) around particles of radius
``particle_radius``; holowarp projects positions out of the ground. The radius is kept small
(default 0.1 % of the object's size) so resting heights agree to that much. The penalty
spring returns the contacting particles' normal velocity (restitution 1 at the particle
level; measured: its damping barely changes the rebound), so a like-for-like comparison sets
the holowarp scene's ``restitution = 1``.
"""

from __future__ import annotations

import time

import numpy as np

from holowarp.sim.analysis import center_of_mass
from holowarp.sim.model import lame_parameters
from holowarp.sim.scene import Scene
from holowarp.tetmesh import TetMesh

__all__ = ["NewtonUnavailable", "newton_available", "simulate_newton_vbd", "newton_vbd_model", "newton_vbd_solver"]

#: Particle contact radius as a fraction of the object's largest bbox side.
PARTICLE_RADIUS_FRACTION = 0.001
#: Penalty stiffness of Newton's particle-ground contact, N/m (soft_contact_ke and the
#: ground shape's ke, which Newton averages).
CONTACT_KE = 1.0e5
#: Its damping coefficient (soft_contact_kd and the shape's kd), N s/m.
CONTACT_KD = 0.0


class NewtonUnavailable(RuntimeError):
    """Newton is not installed (it is part of holowarp's ``test`` extra)."""


def newton_available() -> bool:
    try:
        import newton  # noqa: F401
    except Exception:
        return False
    return True


def _quat_from_matrix(R) -> tuple:
    """(x, y, z, w) unit quaternion of a rotation matrix (Newton/Warp convention)."""
    R = np.asarray(R, dtype=np.float64)
    tr = np.trace(R)
    if tr > 0:
        s = 2.0 * np.sqrt(tr + 1.0)
        w, x, y, z = 0.25 * s, (R[2, 1] - R[1, 2]) / s, (R[0, 2] - R[2, 0]) / s, (R[1, 0] - R[0, 1]) / s
    else:
        i = int(np.argmax(np.diag(R)))
        j, k = (i + 1) % 3, (i + 2) % 3
        s = 2.0 * np.sqrt(1.0 + R[i, i] - R[j, j] - R[k, k])
        q = np.zeros(3)
        q[i] = 0.25 * s
        q[j] = (R[j, i] + R[i, j]) / s
        q[k] = (R[k, i] + R[i, k]) / s
        w = (R[k, j] - R[j, k]) / s
        x, y, z = q
    q = np.array([x, y, z, w])
    return tuple(q / np.linalg.norm(q))


def newton_vbd_model(scene: Scene, mesh, transform, *, device: str = "cpu",
                     particle_radius: float | None = None, contact_ke: float = CONTACT_KE,
                     contact_kd: float = CONTACT_KD):
    """Build Newton's model of ``scene``.

    Args:
        scene: the scene (ground only, no plates); one body, or its ``[[bodies]]``.
        mesh: a :class:`TetMesh` (every body) or one per body (unplaced).
        transform: ``(rot, scale, pos)``, or one per body, as holowarp places them.
        particle_radius: contact radius of the particles, m (default
            :data:`PARTICLE_RADIUS_FRACTION` of the first body's size).

    Returns:
        (newton module, model).

    Raises:
        NewtonUnavailable: Newton is not installed.
        ValueError: the scene has plates (this reference models the ground only).
    """
    try:
        import newton
        import warp as wp
    except ImportError as e:
        raise NewtonUnavailable(f"Newton is not installed ({e}); pip install newton") from None
    if scene.plates:
        raise ValueError(f"scene {scene.name!r}: the Newton reference supports the ground only, not plates")
    from holowarp.device import init_warp

    init_warp()
    specs = scene.body_specs()
    meshes = [mesh] * len(specs) if isinstance(mesh, TetMesh) else list(mesh)
    transforms = [transform] * len(specs) if _is_transform(transform) else list(transform)
    g = np.asarray(scene.sim.gravity, dtype=np.float64)
    if particle_radius is None:
        R0, s0, _ = transforms[0]
        particle_radius = PARTICLE_RADIUS_FRACTION * s0 * float(np.ptp(meshes[0].vertices, axis=0).max())
    b = newton.ModelBuilder(up_axis=newton.Axis.Z, gravity=tuple(map(float, g)))
    for sp, m_, (R, s, pos) in zip(specs, meshes, transforms):
        mu, lam = lame_parameters(sp.material.youngs_modulus, sp.material.poissons_ratio)
        b.add_soft_mesh(
            pos=wp.vec3(*map(float, pos)), rot=wp.quat(*_quat_from_matrix(R)), scale=float(s),
            vel=wp.vec3(*map(float, sp.placement.velocity)), vertices=m_.vertices.tolist(),
            indices=m_.tets.reshape(-1).tolist(), density=sp.material.density, k_mu=mu, k_lambda=lam, k_damp=0.0,
            particle_radius=particle_radius, add_surface_mesh_edges=len(specs) > 1,
        )
    mat = scene.material
    if scene.ground:
        cfg = newton.ModelBuilder.ShapeConfig(ke=contact_ke, kd=contact_kd, mu=mat.friction)
        b.add_ground_plane(cfg=cfg)
    b.color()
    model = b.finalize(device=device)
    model.soft_contact_ke = contact_ke
    model.soft_contact_kd = contact_kd
    model.soft_contact_mu = mat.friction
    return newton, model


def _is_transform(t) -> bool:
    return isinstance(t, tuple) and len(t) == 3 and np.ndim(t[1]) == 0


def newton_vbd_solver(newton, model, *, iterations: int, bodies: int = 1, contact_radius: float | None = None,
                      contact_margin: float | None = None):
    """Newton's ``SolverVBD`` for a model of :func:`newton_vbd_model`; with several bodies its
    particle self-contact (vertex-triangle and edge-edge) is on, with holowarp's contact
    radius as margin and its detection margin as gap."""
    if bodies <= 1:
        return newton.solvers.SolverVBD(model, iterations=int(iterations), particle_enable_self_contact=False,
                                        particle_enable_tile_solve=False)
    return newton.solvers.SolverVBD(model, iterations=int(iterations), particle_enable_self_contact=True,
                                    particle_self_contact_margin=float(contact_radius),
                                    particle_self_contact_gap=float(contact_margin), particle_enable_tile_solve=False)


def simulate_newton_vbd(scene: Scene, mesh, transform, *, substeps: int, iterations: int,
                        device: str = "cpu", steps: int | None = None, record: bool = True,
                        contact_radius: float | None = None, contact_margin: float | None = None,
                        abort=None, **model_kwargs) -> dict:
    """Run ``scene`` with Newton ``SolverVBD``; frames are recorded every 1/60 s.

    Args:
        scene: the scene (ground only).
        mesh: the tet mesh, or one per body (unplaced; ``transform`` places them as holowarp does).
        transform: ``(rot, scale, pos)`` from :func:`holowarp.sim.scene.placement_transform`,
            or one per body.
        substeps: substeps per step of ``scene.sim.dt``.
        iterations: VBD iterations per substep.
        steps: steps to run (default: the scene's duration).
        record: copy positions to the host every frame (off for timing).
        contact_radius, contact_margin: body-body contact distances (m), several bodies only.
        abort: optional ``abort(frame_index, positions) -> bool``; True stops the run.

    Returns:
        ``frames`` (F, N, 3), ``com`` (F, 3), ``steps``, ``seconds`` (wall time of the loop),
        ``masses``, ``aborted``.
    """
    newton, model = newton_vbd_model(scene, mesh, transform, device=device, **model_kwargs)
    import warp as wp

    solver = newton_vbd_solver(newton, model, iterations=iterations, bodies=len(scene.body_specs()),
                               contact_radius=contact_radius, contact_margin=contact_margin)
    s0, s1 = model.state(), model.state()
    control = model.control()
    pipeline = newton.CollisionPipeline(model)
    contacts = pipeline.contacts()
    masses = model.particle_mass.numpy().astype(np.float64)
    h = scene.sim.dt / substeps
    steps = scene.num_steps if steps is None else int(steps)
    per_frame = int(round(1.0 / (60.0 * scene.sim.dt)))
    frames, com = [], []
    aborted = False

    def rec(state):
        x = state.particle_q.numpy().astype(np.float64)
        frames.append(x.astype(np.float32))
        com.append(center_of_mass(x, masses))
        return x

    if record:
        rec(s0)
    done = 0
    t0 = time.perf_counter()
    for _k in range(steps):
        for _ in range(substeps):
            s0.clear_forces()
            pipeline.collide(s0, contacts)
            solver.step(s0, s1, control, contacts, h)
            s0, s1 = s1, s0
        done += 1
        if record and done % per_frame == 0:
            x = rec(s0)
            if abort is not None and abort(len(frames) - 1, x):
                aborted = True
                break
    wp.synchronize_device(model.device)
    seconds = time.perf_counter() - t0
    out = {"steps": done, "seconds": seconds, "masses": masses, "aborted": aborted}
    if record:
        out["frames"] = np.stack(frames)
        out["com"] = np.stack(com)
    return out
