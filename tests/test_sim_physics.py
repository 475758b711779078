"""Validation of the Vertex Block Descent stable Neo-Hookean simulator (method.md §10)
against independent oracles: float64 NumPy references of the kernels (the block step, the
energy and its gradient, closest points, contact detection, penetration), closed-form
mechanics (free fall, self-weight of a hanging bar, uniaxial stress, Coulomb sliding) and
invariants (rigid motions, descent of the incremental potential, volume, convergence with
iterations, stability at the paper's settings, contact between bodies and pieces).

Every test states the settings it runs at; the paper's are dt = 1/60 s, 1 substep and 16
iterations. Meshes are small structured boxes (``holowarp.primitives.box_tetmesh``) so the
file runs in about a minute on two CPU cores after the first kernel compile.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from holowarp.primitives import box_tetmesh
from holowarp.sim import (
    GRAVITY,
    ModelBuilder,
    NonFiniteStateError,
    SolverVBDNeoHookean,
    lame_parameters,
    load_scene,
    pieces_apart,
)
from holowarp.sim.model import stable_neo_hookean_parameters
from holowarp.sim.run import run_scene
from holowarp.sim.scene import build_model, placement_transform
from holowarp.sim.solver import sweep_phases
from holowarp.tetmesh import TetMesh

wp = pytest.importorskip("warp")

DT = 1.0 / 60.0


@pytest.fixture(scope="module", autouse=True)
def _warp():
    from holowarp.device import init_warp

    init_warp()


def _K():
    from holowarp.kernels import sim_vbd

    return sim_vbd


def _run(model, solver, steps, dt=DT, *, record=None, state=None):
    s0 = state if state is not None else model.state()
    s1, c = model.state(), model.control()
    out = []
    for k in range(steps):
        c.set_time(k * dt, (k + 1) * dt)
        solver.step(s0, s1, c, None, dt)
        s0, s1 = s1, s0
        if record is not None:
            out.append(record(s0))
    return s0, out


def _scene(name, **changes):
    """A built-in scene with ``section.key`` values replaced (``contact`` takes a ContactSettings)."""
    sc = load_scene(name)
    parts = {}
    for sec in ("sim", "material", "placement"):
        upd = {k.split(".", 1)[1]: v for k, v in changes.items() if k.startswith(sec + ".")}
        if upd:
            parts[sec] = dataclasses.replace(getattr(sc, sec), **upd)
    if "contact" in changes:
        parts["contact"] = changes["contact"]
    return dataclasses.replace(sc, **parts)


def _join(*meshes) -> TetMesh:
    """One mesh made of disjoint pieces (vertex indices offset, nothing shared)."""
    V, T, off = [], [], 0
    for m in meshes:
        V.append(m.vertices)
        T.append(m.tets + off)
        off += m.num_vertices
    return TetMesh(np.concatenate(V), np.concatenate(T))


# ------------------------------------------------------------------ NumPy oracles
def _deformation(x, X, tets):
    Dm = np.stack([X[tets[:, k]] - X[tets[:, 0]] for k in (1, 2, 3)], axis=2)
    Ds = np.stack([x[tets[:, k]] - x[tets[:, 0]] for k in (1, 2, 3)], axis=2)
    return Ds @ np.linalg.inv(Dm), np.linalg.det(Dm) / 6.0


def _psi(F, mu, lam):
    """Smith et al. 2018 stable Neo-Hookean energy density minus its rest value, float64."""
    mup, lamp = stable_neo_hookean_parameters(mu, lam)
    alpha = 1.0 + 0.75 * mup / lamp
    ic = np.einsum("tij,tij->t", F, F)
    J = np.linalg.det(F)
    return (0.5 * mup * (ic - 3.0) + 0.5 * lamp * ((J - alpha) ** 2 - (1.0 - alpha) ** 2)
            - 0.5 * mup * (np.log(ic + 1.0) - np.log(4.0)))


def _elastic_energy(model, x):
    F, vol = _deformation(np.asarray(x, np.float64), model.rest_positions, model.tets)
    return float((vol * _psi(F, model.tet_mu_host, model.tet_lambda_host)).sum())


def _contact_energy(solver, x):
    """The substep's vertex-triangle penalty energy (slots as detected by the solver)."""
    if not solver.contacts_enabled:
        return 0.0
    c, m = solver._con, solver.model
    cnt, tri, w, n, k = (a.numpy() for a in (c.slot_count, c.slot_tri, c.slot_w, c.slot_n, c.slot_k))
    e = 0.0
    for v in np.flatnonzero(cnt):
        for s in range(cnt[v]):
            p = (x[m.tris[tri[v, s]]] * w[v, s][:, None]).sum(0)
            pen = solver.contact_radius - np.dot(x[v] - p, n[v, s])
            e += 0.5 * k[v, s] * max(pen, 0.0) ** 2
    return e


def _potential(solver, x, h):
    """Implicit Euler's incremental potential of the substep the solver just took, float64."""
    m = solver.model
    y = solver._q_start.numpy().astype(np.float64) + solver._inertia.numpy().astype(np.float64)
    free = ~m.fixed
    inertia = 0.5 / h**2 * float((m.masses[free] * ((x - y)[free] ** 2).sum(1)).sum())
    return inertia + _elastic_energy(m, x) + _contact_energy(solver, x)


def _mechanical_energy(model, state, g=GRAVITY):
    x, v = state.positions(), state.velocities()
    return float(0.5 * (model.masses * (v**2).sum(1)).sum() + (model.masses * g * x[:, 2]).sum()
                 + _elastic_energy(model, x))


def _closest_point_numpy(p, a, b, c):
    """Closest point of triangle abc to p: the best of the face projection (when inside)
    and the three clamped edge projections."""
    n = np.cross(b - a, c - a)
    n /= np.linalg.norm(n)
    q = p - np.dot(p - a, n) * n
    cands = []
    T = np.stack([b - a, c - a], axis=1)
    uv = np.linalg.lstsq(T, q - a, rcond=None)[0]
    if uv.min() >= 0 and uv.sum() <= 1:
        cands.append(q)
    for s, e in ((a, b), (b, c), (c, a)):
        t = np.clip(np.dot(p - s, e - s) / np.dot(e - s, e - s), 0.0, 1.0)
        cands.append(s + t * (e - s))
    cands = np.asarray(cands)
    return cands[np.argmin(np.linalg.norm(cands - p, axis=1))]


# ------------------------------------------------------------------ kernels vs oracles
def test_vertex_block_step_lands_on_the_minimiser_of_the_quadratic_majoriser(rng):
    """One block step of one vertex is x - H^-1 grad G with the exact gradient of the NumPy
    potential G (central differences, float64) and the majoriser's Hessian
    m/h^2 + sum V (3/2 mu' |b|^2 I + lambda' c c^T); that quadratic lies above G at random
    points around the start (the bound the stability argument rests on), so G decreased."""
    K = _K()
    mesh = box_tetmesh((2, 2, 2), (0.1, 0.1, 0.1))
    b = ModelBuilder()
    b.add_soft_mesh(mesh, youngs_modulus=3e5, poissons_ratio=0.4)
    m = b.finalize()
    sol = SolverVBDNeoHookean(m, iterations=1)
    i = 13  # the centre vertex: 24 tets around it
    x = m.rest_positions + rng.normal(size=m.rest_positions.shape) * 0.006
    y = x + rng.normal(size=x.shape) * 0.003
    h = 1.0 / 60.0
    x32 = x.astype(np.float32).astype(np.float64)
    y32 = x32 + (y - x32).astype(np.float32).astype(np.float64)
    dq = wp.zeros(m.particle_count, dtype=wp.vec3)  # the iterate: displacements from the start
    wp.launch(K.vbd_solve_vertices, dim=1, inputs=[
        wp.array([i], dtype=wp.int32), 0, dq, wp.array(x32.astype(np.float32), dtype=wp.vec3),
        wp.array((y32 - x32).astype(np.float32), dtype=wp.vec3), wp.zeros(m.particle_count, dtype=wp.vec3),
        m.particle_mass, m.particle_inv_mass, 1.0 / h**2, 1.0, sol._tets, sol._surf, sol._con, sol._surf_force])
    got = x32[i] + dq.numpy()[i].astype(np.float64)
    corner = np.flatnonzero(np.any(m.tets == i, axis=1))
    tets = m.tets[corner]
    mu, lam = m.tet_mu_host[0], m.tet_lambda_host[0]
    mup, lamp = stable_neo_hookean_parameters(mu, lam)

    def G(p):
        z = x32.copy()
        z[i] = p
        F, v = _deformation(z, m.rest_positions, tets)
        return 0.5 * m.masses[i] / h**2 * np.sum((p - y32[i]) ** 2) + float((v * _psi(F, mu, lam)).sum())

    p0, e = x32[i], 1e-6
    grad = np.array([(G(p0 + e * d) - G(p0 - e * d)) / (2 * e) for d in np.eye(3)])
    F0, vol = _deformation(x32, m.rest_positions, tets)
    Dinv = np.linalg.inv(np.stack([m.rest_positions[tets[:, k]] - m.rest_positions[tets[:, 0]] for k in (1, 2, 3)], 2))
    grads = np.concatenate([-Dinv.sum(axis=1, keepdims=True), Dinv], axis=1)  # [T, 4, 3]
    k_of = np.argmax(tets == i, axis=1)
    bvec = grads[np.arange(len(tets)), k_of]  # [T, 3]
    cof = np.linalg.det(F0)[:, None, None] * np.linalg.inv(F0).transpose(0, 2, 1)
    c = np.einsum("tij,tj->ti", cof, bvec)
    H = m.masses[i] / h**2 * np.eye(3) + np.einsum("t,tij->ij", vol * 1.5 * mup * (bvec**2).sum(1),
                                                   np.broadcast_to(np.eye(3), (len(tets), 3, 3)))
    H += np.einsum("t,ti,tj->ij", vol * lamp, c, c)
    want = p0 - np.linalg.solve(H, grad)
    step = np.linalg.norm(want - p0)
    assert step > 1e-4
    assert np.linalg.norm(got - want) < 2e-3 * step
    for scale in (0.002, 0.01, 0.03):  # majorisation, near and far
        for _ in range(5):
            d = rng.normal(size=3) * scale
            assert G(p0) + grad @ d + 0.5 * d @ H @ d >= G(p0 + d) - 1e-9 * abs(G(p0))
    assert G(got) < G(p0)


@pytest.mark.parametrize("bdf2", [0, 1])
def test_inertial_target_matches_numpy(rng, bdf2):
    """vbd_predict's target displacement y - x_n and its velocity-free part, against the
    float64 formulas: implicit Euler h v + h^2 g; BDF2 d/3 + 2h/3 (4/3 v_n - 1/3 v_(n-1))
    + (2h/3)^2 g with v_(n-1) = v_n - h a_n, and lag d/3 (0 for fixed particles)."""
    K = _K()
    mesh = box_tetmesh((2, 2, 2), (0.1, 0.1, 0.1))
    b = ModelBuilder()
    b.add_soft_mesh(mesh, youngs_modulus=2e5, poissons_ratio=0.3, fixed=mesh.vertices[:, 2] > 0.1 - 1e-9)
    m = b.finalize()
    sol = SolverVBDNeoHookean(m)
    N, h = m.particle_count, 1.0 / 600.0
    x, v, a, d = (rng.normal(size=(N, 3)) * s for s in (0.1, 0.5, 9.0, 1e-3))
    g = np.array([0.3, -0.2, -9.81])
    arr = [wp.array(z.astype(np.float32), dtype=wp.vec3) for z in (x, v, a, d)]
    out = [wp.zeros(N, dtype=wp.vec3) for _ in range(4)]
    C = m.component_count
    sums = [wp.zeros(C, dtype=float)] + [wp.zeros(C, dtype=wp.vec3) for _ in range(4)]
    wp.launch(K.vbd_predict, dim=N, inputs=[arr[0], arr[1], arr[2], m.particle_mass, m.particle_inv_mass,
                                            m.particle_component, arr[3], wp.vec3(*g), h, bdf2, sol._surf],
              outputs=[*out[:3], out[3], sol._surf_force, *sums])
    v32, a32, d32 = (z.astype(np.float32).astype(np.float64) for z in (v, a, d))
    if bdf2:
        v_prev = v32 - h * a32
        want = d32 / 3 + 2 * h / 3 * (4 / 3 * v32 - v_prev / 3) + (2 * h / 3) ** 2 * g
        lag = d32 / 3
    else:
        want, lag = h * v32 + h * h * g, np.zeros_like(d32)
    free = m.particle_inv_mass.numpy() > 0
    assert (~free).any() and free.any()
    np.testing.assert_allclose(out[2].numpy()[free], want[free], rtol=1e-5, atol=1e-9)
    np.testing.assert_allclose(out[3].numpy()[free], lag[free], rtol=1e-5, atol=1e-10)
    assert np.abs(out[2].numpy()[~free]).max() == 0 and np.abs(out[3].numpy()[~free]).max() == 0
    np.testing.assert_allclose(sums[4].numpy()[0], (m.masses[:, None] * np.where(free[:, None], lag, 0)).sum(0),
                               rtol=1e-4, atol=1e-12)


def test_closest_point_on_triangle_matches_numpy(rng):
    K = _K()
    n = 200
    tri = rng.normal(size=(n, 3, 3))
    p = rng.normal(size=(n, 3)) * 1.5
    out = wp.zeros(n, dtype=wp.vec3)
    wp.launch(K.vbd_closest_points, dim=n, inputs=[wp.array(p.astype(np.float32), dtype=wp.vec3),
                                                    wp.array(tri.astype(np.float32), dtype=wp.vec3)], outputs=[out])
    w = out.numpy().astype(np.float64)
    assert np.all(w >= -1e-6) and np.allclose(w.sum(1), 1.0, atol=1e-5)
    got = np.einsum("nk,nkd->nd", w, tri)
    want = np.stack([_closest_point_numpy(p[k], *tri[k]) for k in range(n)])
    np.testing.assert_allclose(got, want, atol=2e-5)


def test_elastic_forces_match_finite_differences_of_energy(rng):
    """sim_tet_forces: energy equals the float64 NumPy Smith energy and forces are minus its
    central-difference gradient."""
    mesh = box_tetmesh((2, 1, 1), (0.2, 0.1, 0.1))
    b = ModelBuilder(gravity=(0, 0, 0))
    b.add_soft_mesh(mesh, youngs_modulus=1e5, poissons_ratio=0.3)
    m = b.finalize()
    sol = SolverVBDNeoHookean(m)
    s = m.state()
    x = m.rest_positions + rng.normal(size=m.rest_positions.shape) * 0.01
    s.particle_q.assign(x.astype(np.float32))
    f, e = sol.elastic_forces(s)
    x32 = x.astype(np.float32).astype(np.float64)
    e_ref = _elastic_energy(m, x32)
    assert abs(e - e_ref) <= 2e-3 * abs(e_ref)
    g = np.zeros_like(x32)
    eps = 1e-6
    for i in range(len(x32)):
        for d in range(3):
            xp, xm = x32.copy(), x32.copy()
            xp[i, d] += eps
            xm[i, d] -= eps
            g[i, d] = (_elastic_energy(m, xp) - _elastic_energy(m, xm)) / (2 * eps)
    assert np.abs(f + g).max() / np.abs(g).max() < 2e-3


def test_stable_neo_hookean_linearises_to_the_lame_parameters(rng):
    """The Hessian of psi at F = I (central differences, float64) is the linear-elastic
    tensor lambda d_ij d_kl + mu (d_ik d_jl + d_il d_jk) for the Lamé parameters of E, nu."""
    for E, nu in ((1e5, 0.0), (2e5, 0.3), (1e6, 0.45)):
        mu, lam = lame_parameters(E, nu)
        e = 1e-4
        C = np.zeros((9, 9))
        for a in range(9):
            for c in range(9):
                da, dc = np.eye(9)[a] * e, np.eye(9)[c] * e

                def psi(d):
                    return _psi((np.eye(3) + d.reshape(3, 3))[None], mu, lam)[0]

                C[a, c] = (psi(da + dc) - psi(da - dc) - psi(dc - da) + psi(-da - dc)) / (4 * e * e)
        d = np.eye(3)
        want = (lam * np.einsum("ij,kl->ijkl", d, d) + mu * (np.einsum("ik,jl->ijkl", d, d)
                                                             + np.einsum("il,jk->ijkl", d, d))).reshape(9, 9)
        np.testing.assert_allclose(C, want, atol=1e-4 * (mu + lam))


def test_vertex_colours_never_share_a_tet():
    m = build_model(load_scene("drop"), box_tetmesh((3, 3, 3), (1.0, 1.0, 1.0), split=5))[0]
    order, offs = m.particle_color_order.numpy(), m.particle_color_offsets
    colour = np.empty(m.particle_count, np.int64)
    for c in range(m.color_count):
        colour[order[offs[c]:offs[c + 1]]] = c
    assert sorted(order.tolist()) == list(range(m.particle_count))
    t = colour[m.tets]
    assert all(len(set(row)) == 4 for row in t.tolist())


def test_fused_colour_sweep_equals_per_colour_launches():
    """On the CPU one launch over the colour-sorted vertices computes exactly what one
    launch per colour computes (Warp's CPU backend runs a launch's threads in index order)."""
    mesh = box_tetmesh((3, 3, 3), (0.1, 0.1, 0.1))
    b = ModelBuilder()
    b.add_soft_mesh(mesh, pos=(0, 0, 0.05), youngs_modulus=2e5, poissons_ratio=0.4)
    b.add_ground_plane()
    m = b.finalize()
    outs = []
    for fuse in (True, False):
        sol = SolverVBDNeoHookean(m, iterations=5, substeps=3, fuse_colors=fuse)
        s, _ = _run(m, sol, 12)
        outs.append((s.positions(), s.velocities()))
    assert np.array_equal(outs[0][0], outs[1][0])
    assert np.array_equal(outs[0][1], outs[1][1])


def test_sweep_phases_domains_share_no_tet():
    """Nested dissection (sweep_phases): a permutation of the particles whose concurrent
    domains never share a tet, keeping the serial order inside each domain."""
    rng = np.random.default_rng()
    mesh = box_tetmesh((9, 7, 8), (1.0, 0.7, 0.8))
    n = mesh.num_vertices
    order = rng.permutation(n)
    new, phases = sweep_phases(order, mesh.tets, mesh.vertices + rng.normal(0, 1e-3, (n, 3)), 2)
    assert sorted(new.tolist()) == list(range(n))
    assert len(phases) >= 2 and len(phases[0]) == 2
    rank = np.empty(n, np.int64)
    rank[order] = np.arange(n)
    covered = 0
    for phase in phases:
        dom = np.full(n, -1)
        for d, (off, cnt) in enumerate(phase):
            assert off == covered
            covered += cnt
            ids = new[off:off + cnt]
            dom[ids] = d
            assert np.all(np.diff(rank[ids]) > 0)  # serial order kept within the domain
        t = dom[mesh.tets]
        lo = np.where(t >= 0, t, 99).min(1)
        assert not np.any((t.max(1) >= 0) & (lo < t.max(1)))
    assert covered == n
    # The two halves are balanced, and the separators shrink.
    (_, a), (_, b) = phases[0]
    assert abs(a - b) <= 0.05 * n and a + b >= 0.7 * n


def test_parallel_sweep_is_thread_independent_and_converges_with_the_serial_one():
    """The domain-parallel CPU sweep gives the same bits on one thread and on two, and with
    enough iterations the same implicit Euler solution as the serial colour-order sweep."""
    from holowarp.device import set_cpu_threads

    mesh = box_tetmesh((9, 9, 9), (0.1, 0.1, 0.1))
    b = ModelBuilder()
    b.add_soft_mesh(mesh, pos=(0, 0, 0.02), youngs_modulus=2e5, poissons_ratio=0.4)
    b.add_ground_plane()
    m = b.finalize()
    assert SolverVBDNeoHookean(m).sweep_parts == 1  # small meshes sweep serially
    out = {}
    try:
        for parts, threads, iters in ((2, 1, 4), (2, 2, 4), (2, 2, 64), (1, 1, 64)):
            set_cpu_threads(threads)
            sol = SolverVBDNeoHookean(m, iterations=iters, substeps=2, sweep_parts=parts)
            assert len(sol._sweeps[0][1]) >= (2 if parts > 1 else 1)
            s, _ = _run(m, sol, 10)
            out[parts, threads, iters] = s.positions()
    finally:
        set_cpu_threads(None)
    assert np.array_equal(out[2, 1, 4], out[2, 2, 4])
    moved = np.abs(out[1, 1, 64] - m.rest_positions).max()
    assert moved > 0.01
    assert np.abs(out[2, 2, 64] - out[1, 1, 64]).max() < 1e-3 * moved
    with pytest.raises(ValueError, match="fuse_colors"):
        SolverVBDNeoHookean(m, fuse_colors=False, sweep_parts=2)


def test_recorded_launches_give_the_bits_of_fresh_ones():
    """The solver replays its substep launches (holowarp.ops.launches.LaunchCache). Through an
    impact of two bodies with gravity, a ground and friction, over steps of changing length
    (so the substep length, the BDF2/Euler switch and the structs' fields changed in place,
    the surfaces' interpolation weights and friction_eps, all change), on one and two
    threads, the states must be those of fresh launches bit for bit: a stale struct or
    scalar in a recorded launch would show here. A block on its own, whose sweep is split
    into domains, checks the chunked launches the same way."""
    from holowarp.device import set_cpu_threads
    from holowarp.ops._warp import FRESH  # every launch anew

    lower = box_tetmesh((3, 3, 2), (0.1, 0.1, 0.05))
    upper = box_tetmesh((3, 3, 2), (0.1, 0.1, 0.05), (0.02, 0.0, 0.06))
    b = ModelBuilder()
    b.add_soft_mesh(lower, pos=(0, 0, 0.0), youngs_modulus=2e5, poissons_ratio=0.45, friction=0.5)
    b.add_soft_mesh(upper, vel=(0.3, 0, -1.5), youngs_modulus=2e5, poissons_ratio=0.45, friction=0.5)
    b.add_ground_plane()
    m = b.finalize()
    out = {}
    try:
        for threads in (1, 2):
            set_cpu_threads(threads)
            for recorded in (True, False):
                sol = SolverVBDNeoHookean(m, iterations=3, substeps=4, integrator="bdf2")
                if not recorded:
                    sol._launches = FRESH
                s0, s1, c, t = m.state(), m.state(), m.control(), 0.0
                for k in range(12):  # steps of changing length: every scalar of the substep changes
                    dt = DT if k % 3 else DT / 2
                    c.set_time(t, t + dt)
                    sol.step(s0, s1, c, None, dt)
                    s0, s1, t = s1, s0, t + dt
                out[threads, recorded] = (s0.positions(), s0.velocities())
    finally:
        set_cpu_threads(None)
    for threads in (1, 2):
        assert all(np.array_equal(a, f) for a, f in zip(out[threads, True], out[threads, False]))
    moved = np.abs(out[1, True][0] - m.rest_positions).max()
    assert moved > 0.005  # the upper body fell onto the lower one (0.01 m gap)
    b = ModelBuilder()
    b.add_soft_mesh(box_tetmesh((9, 9, 9), (0.1, 0.1, 0.1)), pos=(0, 0, 0.02), youngs_modulus=2e5, poissons_ratio=0.4)
    b.add_ground_plane()
    single = b.finalize()
    try:
        set_cpu_threads(2)
        got = []
        for recorded in (True, False):
            sol = SolverVBDNeoHookean(single, iterations=2, substeps=3, sweep_parts=2)
            assert len(sol._sweeps[0][1][0]) >= 2  # a phase of several domains: chunked launches
            if not recorded:
                sol._launches = FRESH
            got.append(_run(single, sol, 6)[0].positions())
    finally:
        set_cpu_threads(None)
    assert np.array_equal(got[0], got[1]) and np.abs(got[0] - single.rest_positions).max() > 1e-3


def test_tet_stats_count_inverted_tets_and_total_volume():
    mesh = box_tetmesh((2, 2, 2), (1.0, 1.0, 1.0))
    b = ModelBuilder()
    b.add_soft_mesh(mesh)
    m = b.finalize()
    sol = SolverVBDNeoHookean(m)
    s = m.state()
    x = m.rest_positions.copy()
    x[13] = [0.5, 0.5, 1.6]  # the centre vertex pulled out through the top: inverts tets
    s.particle_q.assign(x.astype(np.float32))
    inv, vol = sol.tet_stats(s)
    a = x[m.tets[:, 0]]
    v = np.einsum("ij,ij->i", x[m.tets[:, 1]] - a, np.cross(x[m.tets[:, 2]] - a, x[m.tets[:, 3]] - a)) / 6
    assert inv == int((v <= 0).sum()) > 0
    assert vol == pytest.approx(v.sum(), rel=1e-5)


def test_tet_stats_total_volume_does_not_drift_on_large_meshes():
    """The total is summed in float64: 69k float32 tet volumes summed in float32 read as a
    volume change of about 1e-4 of a body at rest (1e-3 at 200k tets)."""
    mesh = box_tetmesh((24, 24, 24), (1.0, 1.0, 1.0), split=5)
    b = ModelBuilder()
    b.add_soft_mesh(mesh)
    m = b.finalize()
    inv, vol = SolverVBDNeoHookean(m).tet_stats(m.state())
    assert inv == 0
    assert vol == pytest.approx(m.rest_volume(), rel=2e-6)


def _falling_pair(gap=0.004, v=-2.0, cells=(2, 2, 1)):
    """A block falling at ``v`` m/s onto a resting one ``gap`` m below it (no gravity, no
    ground, frictionless): the contact-only situation of an impact."""
    lower = box_tetmesh(cells, (0.1, 0.1, 0.05))
    upper = box_tetmesh(cells, (0.1, 0.1, 0.05), (0.0, 0.0, 0.05 + gap))
    b = ModelBuilder(gravity=(0, 0, 0))
    b.add_soft_mesh(lower, youngs_modulus=2e5, poissons_ratio=0.45, friction=0.0)
    b.add_soft_mesh(upper, vel=(0, 0, v), youngs_modulus=2e5, poissons_ratio=0.45, friction=0.0)
    return b.finalize(), lower.num_vertices


def test_every_iteration_lowers_the_incremental_potential():
    """Block coordinate descent with exact block minimisers (of a majoriser): the NumPy
    potential of the substep (inertia + elasticity + contact penalty) after k iterations
    never rises with k, with an impact under way (contacts of two bodies) and at rest."""
    m, nl = _falling_pair()
    s0 = m.state()
    for _ in range(3):
        Gs = []
        for k in (1, 2, 3, 4, 6, 8, 12):
            sol = SolverVBDNeoHookean(m, iterations=k)
            s1 = m.state()
            sol.step(s0, s1, m.control(), None, DT)
            Gs.append(_potential(sol, s1.positions(), DT))
        assert np.all(np.diff(Gs) <= 1e-6 * abs(Gs[0])), Gs
        SolverVBDNeoHookean(m, iterations=16).step(s0, s1, m.control(), None, DT)
        s0 = s1


def test_contact_detection_finds_each_vertex_the_closest_triangle_of_the_other_body():
    """Every surface vertex of one block within the detection distance of the other finds
    that block's closest triangle (brute force over all of its triangles)."""
    m, nl = _falling_pair(gap=0.004, v=-0.1)
    sol = SolverVBDNeoHookean(m, iterations=1)
    sol.step(m.state(), m.state(), m.control(), None, DT)
    x = m.rest_positions
    c = sol._con
    cnt, tri, w = c.slot_count.numpy(), c.slot_tri.numpy(), c.slot_w.numpy()
    pad = sol.contact_radius + sol.contact_margin
    checked = 0
    for v in m.surface_vertices.numpy():
        other = m.tris[m.components[m.tris[:, 0]] != m.components[v]]
        d = min(np.linalg.norm(_closest_point_numpy(x[v], *x[t]) - x[v]) for t in other)
        if d < pad:
            assert cnt[v] == 1
            p = (x[m.tris[tri[v, 0]]] * w[v, 0][:, None]).sum(0)
            assert np.linalg.norm(p - x[v]) == pytest.approx(d, abs=1e-6)
            checked += 1
    assert checked >= 18  # the facing faces of both blocks


def test_penetration_is_the_depth_inside_the_other_body():
    """Two axis-aligned blocks overlapping by 7 mm: the deepest surface vertex of one inside
    the other lies 7 mm deep (analytic: distance to the box's nearest face)."""
    lower = box_tetmesh((2, 2, 2), (0.1, 0.1, 0.1))
    upper = box_tetmesh((3, 3, 2), (0.06, 0.06, 0.1), (0.02, 0.02, 0.093))
    b = ModelBuilder()
    b.add_soft_mesh(lower)
    b.add_soft_mesh(upper)
    b.add_ground_plane()
    m = b.finalize()
    s = m.state()
    x = m.rest_positions.copy()
    x[0, 2] = -0.002  # one particle 2 mm below the ground
    s.particle_q.assign(x.astype(np.float32))
    pen = SolverVBDNeoHookean(m).penetration(s)
    nl = lower.num_vertices
    lo_a, hi_a = np.zeros(3), np.full(3, 0.1)  # the lower block
    lo_b, hi_b = np.array([0.02, 0.02, 0.093]), np.array([0.08, 0.08, 0.193])  # the upper block
    depths = []
    for z, lo, hi in ((x[nl:], lo_a, hi_a), (x[:nl], lo_b, hi_b)):
        inside = np.all((z > lo + 1e-9) & (z < hi - 1e-9), axis=1)
        depths += np.minimum(z[inside] - lo, hi - z[inside]).min(axis=1).tolist()
    assert max(depths) == pytest.approx(0.007, abs=1e-9)
    assert pen["bodies"] == pytest.approx(max(depths), abs=1e-6)
    assert pen["surfaces"] == pytest.approx(0.002, abs=1e-6)
    assert pen["max"] == pytest.approx(0.007, abs=1e-6) and pen["vertices_inside"] == len(depths)


# ------------------------------------------------------------------ mechanics
def test_rigid_motion_gives_zero_force_and_keeps_momentum(rng, record_property):
    """A rotated and translated rest shape has zero elastic force and energy; at zero
    gravity a translating body stays exactly rigid and a spinning one keeps its linear
    momentum, loses no more angular momentum than implicit Euler does and deforms only by
    its centrifugal stretch (paper settings)."""
    mesh = box_tetmesh((2, 2, 3), (0.1, 0.1, 0.15))
    b = ModelBuilder(gravity=(0, 0, 0))
    b.add_soft_mesh(mesh, youngs_modulus=2e5, poissons_ratio=0.45)
    m = b.finalize()
    sol = SolverVBDNeoHookean(m, iterations=16, substeps=1)
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    R = q * np.sign(np.linalg.det(q))
    x = m.rest_positions @ R.T + rng.normal(size=3) * 0.1
    s0 = m.state()
    s0.particle_q.assign(x.astype(np.float32))
    f, e = sol.elastic_forces(s0)
    fs = m.tet_mu_host.max() * np.ptp(m.rest_positions, axis=0).max() ** 2  # a force of the material's scale
    record_property("rigid_force_rel", float(np.abs(f).max() / fs))
    assert np.abs(f).max() < 1e-4 * fs
    assert abs(e) < 1e-6 * fs * 0.1

    def dist(z):
        return np.linalg.norm(z[:, None] - z[None], axis=2)

    v = np.tile(rng.normal(size=3), (m.particle_count, 1))
    s0.particle_qd.assign(v.astype(np.float32))
    s, _ = _run(m, sol, 10, state=s0)
    np.testing.assert_allclose(s.positions(), x + v * 10 * DT, atol=1e-5)  # float32 positions
    np.testing.assert_allclose(dist(s.positions()), dist(x), atol=2e-6)

    com = (m.masses[:, None] * x).sum(0) / m.masses.sum()
    w = rng.normal(size=3) * 3.0  # rad/s
    v = np.cross(w, x - com)
    s0 = m.state()
    s0.particle_q.assign(x.astype(np.float32))
    s0.particle_qd.assign(v.astype(np.float32))

    def momenta(st):
        z, u = st.positions(), st.velocities()
        c = (m.masses[:, None] * z).sum(0) / m.masses.sum()
        return (m.masses[:, None] * u).sum(0), (m.masses[:, None] * np.cross(z - c, u)).sum(0)

    p0, L0 = momenta(s0)
    s, _ = _run(m, sol, 10, state=s0)
    p1, L1 = momenta(s)
    assert np.linalg.norm(p1 - p0) < 2e-3 * m.masses.sum() * np.abs(v).max()  # unconverged sweeps: not exact
    # implicit Euler bleeds rotation (L changes by h sum v_{n+1} x m v_n per step) but never adds any
    cos = L1 @ L0 / (np.linalg.norm(L1) * np.linalg.norm(L0))
    assert 0.9 * np.linalg.norm(L0) < np.linalg.norm(L1) <= np.linalg.norm(L0) * (1 + 1e-4) and cos > 0.999
    stretch = 1000.0 * np.dot(w, w) * 0.1**2 / 2e5  # rho w^2 L^2 / E: the centrifugal strain scale
    assert np.abs(dist(s.positions()) - dist(x)).max() < 10 * stretch * 0.1


@pytest.mark.parametrize("integrator, tol", [("euler", 0.01), ("bdf2", 1e-4)])
def test_free_fall_follows_parabola_before_contact(integrator, tol, record_property):
    """The centre of mass follows z0 - g t^2 / 2 until contact: to 1 % of the drop height by
    implicit Euler, to 0.01 % by BDF2 (exact for a parabola but for its first, implicit
    Euler substep: a lag of g h^2 / 2).

    Implicit Euler lags by g t h / 2 (h the substep), i.e. h / T of the drop height at
    contact time T = 0.2 s: 8 % at the paper's 1 substep, 0.5 % at the 16 substeps used here
    (4 iterations each; free flight needs none beyond the rigid initial guess).
    """
    sc = _scene("drop", **{"sim.substeps": 16, "sim.iterations": 4, "sim.duration": 0.25,
                           "sim.integrator": integrator})
    mesh = box_tetmesh((2, 2, 2), (1.0, 1.0, 1.0))
    r = run_scene(sc, mesh, transform=placement_transform(mesh.vertices, sc.placement))
    H = sc.placement.height
    z0 = r["com"][0, 2]
    t = np.arange(len(r["com"])) / 60.0
    zmin = r["frames"][:, :, 2].min(axis=1)
    n_free = int(np.argmax(zmin <= 1e-6))  # frames before the first contact
    free = np.arange(len(zmin)) < n_free
    assert n_free >= 10
    assert r["plan"].integrator == integrator
    err = np.abs(r["com"][free, 2] - (z0 - 0.5 * GRAVITY * t[free] ** 2)).max() / H
    record_property("free_fall_rel_error", float(err))
    assert err < tol, err
    np.testing.assert_allclose(r["com"][free, :2], 0.0, atol=1e-6)  # straight down


def test_hanging_column_sags_by_rho_g_h2_over_2e(record_property):
    """A bar of height H clamped at its top stretches under its own weight by
    rho g H^2 / (2 E) (1D elasticity), within 10 % on a 3 x 3 x 30 cell mesh (paper settings:
    1 substep, 16 iterations; 2 s with 5 /s damping to come to rest)."""
    W, H, E, rho = 0.1, 1.0, 1e5, 1000.0
    mesh = box_tetmesh((3, 3, 30), (W, W, H))
    b = ModelBuilder()
    b.add_soft_mesh(mesh, density=rho, youngs_modulus=E, poissons_ratio=0.3, fixed=mesh.vertices[:, 2] > H - 1e-9)
    m = b.finalize()
    sol = SolverVBDNeoHookean(m, iterations=16, substeps=1, damping=5.0)
    s, _ = _run(m, sol, 120)
    bottom = np.abs(mesh.vertices[:, 2]) < 1e-9
    sag = -s.positions()[bottom, 2].mean()
    exact = rho * GRAVITY * H**2 / (2 * E)
    record_property("sag_rel_error", float(sag / exact - 1))
    assert abs(sag / exact - 1) < 0.10, (sag, exact)
    assert np.abs(s.velocities()).max() < 1e-2  # at rest


def test_uniaxial_compression_stress_over_strain_equals_youngs_modulus(record_property):
    """A block between a frictionless ground and a frictionless plate pressed down by 1 %:
    the plate force over the area, divided by the strain, is E within 5 % (paper settings)."""
    L, E, nu, eps = 0.1, 1e5, 0.3, 0.01
    mesh = box_tetmesh((4, 4, 4), (L, L, L))
    b = ModelBuilder(gravity=(0, 0, 0))
    b.add_soft_mesh(mesh, youngs_modulus=E, poissons_ratio=nu)
    b.add_ground_plane(friction=0.0)
    b.add_plate("Top", normal=(0, 0, -1), path=[[0, L / 2, L / 2, L], [0.5, L / 2, L / 2, L * (1 - eps)]], friction=0.0)
    m = b.finalize()
    sol = SolverVBDNeoHookean(m, iterations=16, substeps=1, damping=5.0)
    s, forces = _run(m, sol, 90, record=lambda st: st.surface_force.numpy().copy())
    f_plate = -np.mean([f[1, 2] for f in forces[-15:]])
    strain = 1 - np.ptp(s.positions()[:, 2]) / L
    assert strain == pytest.approx(eps, rel=1e-3)
    record_property("uniaxial_rel_error", float(f_plate / (L * L) / strain / E - 1))
    assert abs(f_plate / (L * L) / strain / E - 1) < 0.05
    assert np.mean([f[0, 2] for f in forces[-15:]]) == pytest.approx(f_plate, rel=0.02)  # the ground carries it


def test_sliding_block_stops_at_coulomb_distance():
    """A stiff block launched along the ground at v0 decelerates at mu g and stops after
    v0^2 / (2 mu g), within 3 %. Implicit Euler stops short by mu g h / v0 (6.5 % at the
    paper's 1 substep), so this runs 4 substeps of 16 iterations (1.6 %)."""
    mesh = box_tetmesh((2, 2, 1), (0.1, 0.1, 0.05))
    mu, v0 = 0.4, 1.0
    b = ModelBuilder()
    b.add_soft_mesh(mesh, vel=(v0, 0, 0), youngs_modulus=1e6, poissons_ratio=0.3)
    b.add_ground_plane(friction=mu)
    m = b.finalize()
    sol = SolverVBDNeoHookean(m, iterations=16, substeps=4)
    s, com = _run(m, sol, 30, record=lambda st: st.positions()[:, 0].mean())
    expected = v0**2 / (2 * mu * GRAVITY)
    assert com[-1] - mesh.vertices[:, 0].mean() == pytest.approx(expected, rel=0.03)
    assert np.abs(s.velocities()).max() < 1e-3


def test_drop_keeps_volume_within_two_percent_at_nu_045(record_property):
    """The drop scene as shipped (paper settings, E = 200 kPa, nu = 0.45)."""
    sc = load_scene("drop")
    assert (sc.material.poissons_ratio, sc.sim.substeps, sc.sim.iterations) == (0.45, 1, 16)
    mesh = box_tetmesh((4, 4, 4), (1.0, 1.0, 1.0))
    r = run_scene(sc, mesh)
    ratio = r["volume"] / r["model"].rest_volume()
    assert r["frames"][:, :, 2].min() > -1e-6  # never below the ground
    record_property("volume_max_rel_change", float(np.abs(ratio - 1).max()))
    assert np.abs(ratio - 1).max() < 0.02, np.abs(ratio - 1).max()
    assert r["com"][-1, 2] == pytest.approx(0.1, abs=0.003)  # came to rest on the ground
    assert r["plan"].softened_tets == 0


def test_trajectory_converges_with_iterations(record_property):
    """At 1 substep the drop's trajectory approaches the converged implicit Euler one as
    iterations grow: the largest position difference to the 256-iteration run shrinks
    with every doubling of 4 -> 16 -> 64 and is within 2 mm (1 % of the cube) at 64."""
    mesh = box_tetmesh((4, 4, 4), (1.0, 1.0, 1.0), split=5)
    runs = {}
    for it in (4, 16, 64, 256):
        sc = _scene("drop", **{"sim.iterations": it, "sim.duration": 0.5})
        runs[it] = run_scene(sc, mesh, measure_penetration=False)["frames"]
    err = [np.abs(runs[it] - runs[256]).max() for it in (4, 16, 64)]
    record_property("max_diff_to_256_iterations_at_4_16_64", [float(e) for e in err])
    assert err[0] > err[1] > err[2], err
    assert err[2] < 0.002, err


def _vibration(integrator, substeps, iterations=16, steps=3):
    """Positions (N, 3) after ``steps`` steps of 1/60 s of a free block (no gravity, no
    contact) released 10 % stretched along z, so every mode rings."""
    mesh = box_tetmesh((2, 2, 3), (0.1, 0.1, 0.15))
    b = ModelBuilder(gravity=(0, 0, 0))
    b.add_soft_mesh(mesh, youngs_modulus=2e5, poissons_ratio=0.3)
    m = b.finalize()
    sol = SolverVBDNeoHookean(m, iterations=iterations, substeps=substeps, integrator=integrator)
    s0 = m.state()
    s0.particle_q.assign((m.rest_positions * np.array([1.0, 1.0, 1.1])).astype(np.float32))
    s, _ = _run(m, sol, steps, state=s0)
    return s.positions()


def test_bdf2_converges_at_second_order_and_implicit_euler_at_first():
    """Against a 1024-substep run of the same integrator (16 iterations: converged at these
    substeps), a vibrating block's largest position error falls about 4x per halving of the
    substep by BDF2 (measured 3.2x, then 4.0x from 64 -> 128 -> 256 substeps) and about 2x by
    implicit Euler (1.8x), so at 256 substeps BDF2 is over 10x closer."""
    err = {}
    for integ in ("bdf2", "euler"):
        ref = _vibration(integ, 1024)
        subs = (64, 128, 256) if integ == "bdf2" else (256,)
        err[integ] = [np.abs(_vibration(integ, S) - ref).max() for S in subs]
    e64, e128, e256 = err["bdf2"]
    assert e64 / e128 > 2.6 and e128 / e256 > 3.3, err
    assert err["euler"][0] > 10 * e256, err


def test_bdf2_drop_agrees_with_extrapolated_implicit_euler():
    """Through an impact (restitution 0) BDF2 restarts each landing vertex's history, so it
    converges to the same trajectory as implicit Euler: at 128 substeps its centre of mass
    stays within 1.5 % of the drop height of the Richardson extrapolation 2 E(512) - E(256)
    of implicit Euler (measured 0.8 %; without the restart the landing vertices lift off
    again and the rebound peaks 4 mm higher, about 2.4 % off), where implicit Euler's own
    512 substeps are 2.8 % off."""
    mesh = box_tetmesh((3, 3, 3), (1.0, 1.0, 1.0), split=5)
    com = {}
    for integ, S in (("bdf2", 128), ("euler", 256), ("euler", 512)):
        sc = _scene("drop", **{"sim.substeps": S, "sim.iterations": 8, "sim.duration": 0.45, "sim.integrator": integ})
        r = run_scene(sc, mesh, transform=placement_transform(mesh.vertices, sc.placement), measure_penetration=False)
        com[(integ, S)] = r["com"][:, 2]
    H = 0.2
    rich = 2 * com[("euler", 512)] - com[("euler", 256)]
    bdf2 = com[("bdf2", 128)]
    assert bdf2.max() - bdf2[len(bdf2) // 2:].min() > 0.3 * H  # it did bounce
    assert np.abs(bdf2 - rich).max() / H < 0.015
    assert np.abs(com[("euler", 512)] - rich).max() / H > 0.02


def test_auto_integrator_is_bdf2_only_where_a_substep_resolves_a_wave():
    """``"auto"``: BDF2 at substeps no longer than a pressure wave takes to cross the median
    boundary edge, implicit Euler above (the paper's 1/60 s on any ordinary mesh)."""
    mesh = box_tetmesh((2, 2, 2), (0.2, 0.2, 0.2))
    b = ModelBuilder()
    b.add_soft_mesh(mesh, youngs_modulus=2e5, poissons_ratio=0.45, density=1000.0)
    m = b.finalize()
    sol = SolverVBDNeoHookean(m)
    mu, lam = lame_parameters(2e5, 0.45)
    assert sol.wave_time == pytest.approx(m.median_surface_edge() / np.sqrt((lam + 2 * mu) / 1000.0), rel=1e-5)
    assert sol.integrator_for(0.99 * sol.wave_time) == "bdf2"
    assert sol.integrator_for(1.01 * sol.wave_time) == "euler"
    assert sol.plan(DT).integrator == "euler"
    assert SolverVBDNeoHookean(m, integrator="bdf2").plan(DT).integrator == "bdf2"
    with pytest.raises(ValueError, match="integrator must be one of auto, euler, bdf2"):
        SolverVBDNeoHookean(m, integrator="rk4")


def _jittered_cube(rng, cells=5, jitter=0.4):
    """A cube mesh with interior vertices moved at random by ``jitter`` cells: uneven tets
    with slivers, all positively oriented."""
    mesh = box_tetmesh((cells, cells, cells), (1.0, 1.0, 1.0), split=5)
    for _ in range(20):
        X = mesh.vertices.copy()
        inner = np.all((X > 1e-9) & (X < 1 - 1e-9), axis=1)
        X[inner] += rng.uniform(-jitter, jitter, size=(inner.sum(), 3)) / cells
        cand = mesh.with_vertices(X)
        if (cand.signed_volumes() > 0).all():
            return cand
    raise AssertionError("no valid jittered mesh")


@pytest.mark.parametrize("E, nu", [(1e4, 0.0), (1e4, 0.45), (1e7, 0.0), (1e7, 0.45)])
def test_paper_settings_are_stable_for_any_stiffness(rng, E, nu, record_property):
    """dt = 1/60 s, 1 substep, 16 iterations: dropping a sliver-laden cube (jittered 625-tet
    mesh) never gains energy (total mechanical energy stays at or below its start), stays
    finite and softens no tet, from 10 kPa to 10 MPa and nu from 0 to 0.45."""
    mesh = _jittered_cube(rng)
    q = mesh.quality_summary()
    assert q["min_dihedral_worst"] < 12.0  # slivers present
    sc = _scene("drop", **{"material.youngs_modulus": E, "material.poissons_ratio": nu})
    m, _, _ = build_model(sc, mesh)
    sol = SolverVBDNeoHookean(m, iterations=16, substeps=1)
    assert sol.plan(DT).softened_tets == 0
    e0 = _mechanical_energy(m, m.state())
    s, energies = _run(m, sol, 60, record=lambda st: _mechanical_energy(m, st))
    assert np.all(np.isfinite(s.positions()))
    record_property("max_energy_over_start", float(max(energies) / e0))
    assert max(energies) <= e0 * 1.001, (max(energies), e0)
    assert s.positions()[:, 2].min() > -1e-6


def test_squeeze_to_half_height_and_release_leaves_no_inverted_tets():
    """The compress scene as shipped (paper settings)."""
    sc = load_scene("compress")
    mesh = box_tetmesh((3, 3, 3), (1.0, 1.0, 1.0))
    r = run_scene(sc, mesh)
    h = np.ptp(r["frames"][:, :, 2], axis=1)
    assert h.min() == pytest.approx(0.5 * h[0], rel=0.02)  # squeezed to 50 %
    assert r["inverted"].max() == 0
    assert abs(r["volume"][-1] / r["model"].rest_volume() - 1) < 0.01
    assert h[-1] == pytest.approx(h[0], rel=0.02)  # recovered its height
    assert r["surface_force"][:, 1, 2].min() < -10.0  # the plate pushed down while squeezing


def test_inverted_tets_recover():
    """Tets turned inside out at t = 0 are pushed back by the volume term (paper settings)."""
    mesh = box_tetmesh((2, 2, 2), (0.2, 0.2, 0.2))
    b = ModelBuilder()
    b.add_soft_mesh(mesh, pos=(0, 0, 0.01), youngs_modulus=2e5, poissons_ratio=0.45)
    b.add_ground_plane()
    m = b.finalize()
    sol = SolverVBDNeoHookean(m, iterations=16, substeps=1, damping=2.0)
    s0 = m.state()
    x = m.rest_positions.copy()
    centre = np.argmin(np.linalg.norm(x - x.mean(0), axis=1))
    x[centre, 2] += 0.25  # through the top face
    s0.particle_q.assign(x.astype(np.float32))
    assert sol.tet_stats(s0)[0] >= 4
    s, counts = _run(m, sol, 60, state=s0, record=lambda st: sol.tet_stats(st)[0])
    assert np.all(np.isfinite(s.positions()))
    assert counts[-1] == 0
    assert sol.tet_stats(s)[1] == pytest.approx(m.rest_volume(), rel=0.02)


def test_non_finite_state_stops_with_the_step_named():
    sc = _scene("drop", **{"sim.gravity": (0.0, 0.0, -3.0e38), "sim.duration": 0.5})
    with pytest.raises(NonFiniteStateError, match=r"after step \d+ \(t = [0-9.]+ s\)"):
        run_scene(sc, box_tetmesh((1, 1, 1), (1.0, 1.0, 1.0)))


# ------------------------------------------------------------------ contact
def test_stacked_blocks_dropped_come_to_rest_on_each_other(record_property):
    """Two blocks, one 1 cm above the other, dropped together 0.2 m (paper settings): the
    upper one lands on the lower one and both rest, stacked, with at most 1 % of the block
    size of penetration at any frame."""
    sc = _scene("drop", **{"sim.duration": 1.2})
    lower = box_tetmesh((4, 4, 2), (1.0, 1.0, 0.5))
    upper = box_tetmesh((4, 4, 2), (1.0, 1.0, 0.5), (0.0, 0.0, 0.55))
    r = run_scene(sc, [lower, upper])
    m, x = r["model"], r["frames"]
    size = 0.2 / 1.05 * 0.5  # block height after placement, m
    nl = lower.num_vertices
    record_property("max_penetration_over_block_size", float(r["penetration"].max() / size))
    assert r["penetration"].max() < 0.01 * size
    assert x[-1, :nl, 2].min() == pytest.approx(0.0, abs=1e-6)
    gap = x[-1, nl:, 2].min() - x[-1, :nl, 2].max()
    assert 0.0 <= gap < 3 * SolverVBDNeoHookean(m).contact_radius + 1e-3  # resting on it
    np.testing.assert_allclose(x[-1, nl:, :2].mean(0), 0.0, atol=2e-3)  # still on top
    v = (x[-1] - x[-2]) * 60.0
    assert np.abs(v).max() < 0.01


def test_disjoint_pair_under_compression_separates_and_one_block_stays_whole(record_property):
    """Two cubes side by side in one mesh (two face-connected pieces, as TetSphere's union of
    spheres) squeezed to half height between greased plates (friction 0.1) and released:
    contact pushes them apart (components_end 2) without interpenetration; the same shape
    as one connected mesh stays one piece (method.md §10; paper settings)."""
    sc = _scene("compress", **{"material.friction": 0.1})
    two = _join(box_tetmesh((3, 3, 3), (1.0, 1.0, 1.0)), box_tetmesh((3, 3, 3), (1.0, 1.0, 1.0), (1.0, 0.0, 0.0)))
    one = box_tetmesh((6, 3, 3), (2.0, 1.0, 1.0))
    assert two.components()[1] == 2 and one.components()[1] == 1
    ends = {}
    for label, mesh in (("two", two), ("one", one)):
        r = run_scene(sc, mesh)
        placed = mesh.with_vertices(r["model"].rest_positions)
        ends[label] = pieces_apart(placed, r["frames"][-1])[0]
        record_property(f"max_penetration_over_cube_side_{label}", float(r["penetration"].max() / 0.1))
        assert r["penetration"].max() < 0.01 * 0.1  # 1 % of a cube's side
    assert ends == {"two": 2, "one": 1}


def test_self_collision_keeps_the_arms_of_one_body_apart():
    """A C-shaped connected body whose upper arm is pushed down onto the lower one by a
    plate (paper settings): with self-collision the arms stop at the contact distance;
    without it (the default, as in the paper) the upper arm passes into the lower one."""
    mask = np.ones((5, 1, 5), bool)
    mask[1:, 0, 2:4] = False  # a gap of two cells between the arms, open towards +x
    mesh, _ = box_tetmesh((5, 1, 5), (0.3, 0.06, 0.3), cell_mask=mask).remove_unused_vertices()
    assert mesh.components()[1] == 1
    X = mesh.vertices
    # Facing vertex pairs across the gap: the upper arm's underside above the lower arm's top
    # (not at the open end, where the tip may slide past the lower arm's end face).
    under = np.flatnonzero((X[:, 0] > 0.12 - 1e-9) & (X[:, 0] < 0.3 - 1e-9) & (np.abs(X[:, 2] - 0.24) < 1e-9))
    top = np.array([np.flatnonzero(np.all(np.abs(X - X[u] + [0, 0, 0.12]) < 1e-9, axis=1))[0] for u in under])
    gaps = {}
    for self_collision in (False, True):
        b = ModelBuilder(gravity=(0, 0, 0))
        b.add_soft_mesh(mesh, youngs_modulus=1e5, poissons_ratio=0.3)
        b.add_ground_plane(friction=0.5)
        b.add_plate("Top", normal=(0, 0, -1), path=[[0.0, 0.2, 0.03, 0.3], [0.5, 0.2, 0.03, 0.165]], friction=0.5)
        m = b.finalize()
        sol = SolverVBDNeoHookean(m, iterations=16, substeps=1, self_collision=self_collision)
        s, _ = _run(m, sol, 30)
        x = s.positions()
        gaps[self_collision] = (x[under, 2] - x[top, 2]).min()
    assert gaps[False] < -0.005, gaps  # passed into it
    assert gaps[True] > 0.0, gaps


def test_pieces_that_stay_in_contact_count_as_one():
    """pieces_apart: two touching blocks that did not move relative to each other hold
    together; moving one away by a block's height separates them."""
    lower = box_tetmesh((1, 1, 1), (1.0, 1.0, 1.0))
    upper = box_tetmesh((1, 1, 1), (1.0, 1.0, 1.0), (0.0, 0.0, 1.0))
    two = _join(lower, upper)
    assert pieces_apart(two, two.vertices + 0.3)[0] == 1
    moved = two.vertices.copy()
    moved[8:, 0] += 1.0
    n, info = pieces_apart(two, moved)
    assert n == 2 and info["opened_pairs"][0]["interface_pairs"] == 4


def test_scene_bodies_take_their_own_placement_and_material():
    """A [[bodies]] scene: each body is placed and made of what its entry says, the rest
    from [placement] and [material]; plates use the bounding box of all bodies."""
    from holowarp.sim.scene import parse_scene

    data = {
        "placement": {"size": 0.1, "height": 0.0},
        "material": {"youngs_modulus": 2e5},
        "bodies": [{"name": "A"}, {"name": "B", "placement": {"height": 0.3, "center_xy": [0.5, 0.0]},
                                   "material": {"youngs_modulus": 1e6, "friction": 0.2}}],
        "contact": {"radius": 0.0, "self_collision": True},
    }
    sc = parse_scene(data, source="test.toml")
    assert sc.contact.radius == 0.0 and sc.contact.self_collision  # an explicit 0 is kept
    m, transforms, bbox = build_model(sc, box_tetmesh((1, 1, 1), (2.0, 2.0, 2.0)))
    x = m.rest_positions
    a, b = m.bodies
    assert np.ptp(x[a.particle_start:a.particle_end], axis=0).max() == pytest.approx(0.1)
    assert x[b.particle_start:b.particle_end, 2].min() == pytest.approx(0.3)
    assert x[b.particle_start:b.particle_end, 0].mean() == pytest.approx(0.5)
    assert m.tet_mu_host[b.tet_start] == pytest.approx(lame_parameters(1e6, 0.45)[0])
    assert m.tet_mu_host[a.tet_start] == pytest.approx(lame_parameters(2e5, 0.45)[0])
    assert m.particle_friction.numpy()[b.particle_start] == pytest.approx(0.2)
    assert m.component_count == 2
    np.testing.assert_allclose(bbox, [[-0.05, -0.05, 0.0], [0.55, 0.05, 0.4]], atol=1e-9)


def test_lame_parameters_and_material_errors():
    mu, lam = lame_parameters(2.6e5, 0.3)
    assert mu == pytest.approx(1e5) and lam == pytest.approx(1.5e5)
    from holowarp.sim import ModelError

    with pytest.raises(ModelError, match="poissons_ratio"):
        lame_parameters(1e5, 0.5)
    with pytest.raises(ModelError, match="youngs_modulus"):
        lame_parameters(-1.0, 0.3)
    b = ModelBuilder()
    mesh = TetMesh(np.vstack([np.eye(3), [[0, 0, 0], [5, 5, 5]]]), [[3, 0, 1, 2]])
    with pytest.raises(ModelError, match="belong to no tet"):
        b.add_soft_mesh(mesh)
