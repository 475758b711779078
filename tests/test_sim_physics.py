"""Validation of the XPBD stable Neo-Hookean simulator (method.md §10) against independent
oracles: NumPy references of the kernels, finite differences of the energy, closed-form
mechanics (free fall, self-weight of a hanging bar, uniaxial stress, Coulomb sliding) and
invariants (rigid motions, volume, inversion recovery, pieces that hold together).

Meshes are small structured boxes (``holowarp.primitives.box_tetmesh``) so the whole file
runs in well under a minute on two CPU cores after the first kernel compile.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from holowarp.primitives import box_tetmesh
from holowarp.sim import (
    GRAVITY,
    ModelBuilder,
    SolverXPBDNeoHookean,
    lame_parameters,
    load_scene,
    pieces_apart,
)
from holowarp.sim.run import run_scene
from holowarp.sim.scene import placement_transform
from holowarp.tetmesh import TetMesh

wp = pytest.importorskip("warp")


@pytest.fixture(scope="module", autouse=True)
def _warp():
    from holowarp.device import init_warp

    init_warp()


def _K():
    from holowarp.kernels import sim_xpbd

    return sim_xpbd


def _run(model, solver, steps, dt=1.0 / 60.0, *, record=None):
    s0, s1, c = model.state(), model.state(), model.control()
    out = []
    for k in range(steps):
        c.set_time(k * dt, (k + 1) * dt)
        solver.step(s0, s1, c, None, dt)
        s0, s1 = s1, s0
        if record is not None:
            out.append(record(s0))
    return s0, out


def _scene(name, **changes):
    sc = load_scene(name)
    parts = {}
    for sec in ("sim", "material", "placement"):
        upd = {k.split(".", 1)[1]: v for k, v in changes.items() if k.startswith(sec + ".")}
        if upd:
            parts[sec] = dataclasses.replace(getattr(sc, sec), **upd)
    return dataclasses.replace(sc, **parts)


# ------------------------------------------------------------------ NumPy oracles
def _np_grads(x, Dinv, gamma):
    """C_D, C_H and their (4, 3) vertex gradients for one tet, float64."""
    Ds = np.stack([x[1] - x[0], x[2] - x[0], x[3] - x[0]], axis=1)
    F = Ds @ Dinv
    cD = np.linalg.norm(F)
    J = np.linalg.det(F)
    cof = np.stack([np.cross(F[:, 1], F[:, 2]), np.cross(F[:, 2], F[:, 0]), np.cross(F[:, 0], F[:, 1])], axis=1)
    GD = (F / cD) @ Dinv.T
    GH = cof @ Dinv.T
    gD = np.vstack([-GD.sum(1), GD.T])
    gH = np.vstack([-GH.sum(1), GH.T])
    return cD, J - gamma, gD, gH


def _np_energy(x, tets, Dinv, vol, mu, lam):
    lamp = lam + mu
    gamma = 1.0 + mu / lamp
    e = 0.0
    for t in range(len(tets)):
        xt = x[tets[t]]
        F = np.stack([xt[1] - xt[0], xt[2] - xt[0], xt[3] - xt[0]], axis=1) @ Dinv[t]
        J = np.linalg.det(F)
        psi = 0.5 * mu[t] * (np.sum(F * F) - 3.0) + 0.5 * lamp[t] * ((J - gamma[t]) ** 2 - (1 - gamma[t]) ** 2)
        e += vol[t] * psi
    return e


def _random_tets(rng, n):
    """n random well-shaped tets (rest) and a random deformation of each."""
    X = []
    for _ in range(n):
        while True:
            p = rng.normal(size=(4, 3)) * 0.05
            v = np.linalg.det(np.stack([p[1] - p[0], p[2] - p[0], p[3] - p[0]], 1)) / 6
            if v > 2e-5:
                X.append(p)
                break
    X = np.stack(X)
    x = X + rng.normal(size=X.shape) * 0.004
    return X, x


def test_constraint_projection_matches_numpy_reference(rng):
    """One coupled deviatoric + hydrostatic XPBD projection per tet equals the NumPy 2x2
    solve with gradients that are themselves checked by central differences."""
    K = _K()
    n = 6
    X, x = _random_tets(rng, n)
    mu = rng.uniform(2e4, 8e4, n)
    lam = rng.uniform(1e4, 3e5, n)
    w = rng.uniform(10, 60, (n, 4))
    h = 1.0 / 240.0
    lam_prev = rng.normal(size=(n, 2)) * 1e-6
    for t in range(n):
        Dinv = np.linalg.inv(np.stack([X[t, 1] - X[t, 0], X[t, 2] - X[t, 0], X[t, 3] - X[t, 0]], 1))
        V = 1.0 / (6.0 * np.linalg.det(Dinv))
        lamp = lam[t] + mu[t]
        gamma = 1 + mu[t] / lamp
        cD, cH, gD, gH = _np_grads(x[t], Dinv, gamma)
        eps = 1e-7
        for k in range(4):
            for d in range(3):
                xp, xm = x[t].copy(), x[t].copy()
                xp[k, d] += eps
                xm[k, d] -= eps
                a, b = _np_grads(xp, Dinv, gamma), _np_grads(xm, Dinv, gamma)
                assert abs((a[0] - b[0]) / (2 * eps) - gD[k, d]) < 1e-5 * max(1, abs(gD[k, d]))
                assert abs((a[1] - b[1]) / (2 * eps) - gH[k, d]) < 1e-5 * max(1, abs(gH[k, d]))
        aD, aH = 1 / (mu[t] * V * h * h), 1 / (lamp * V * h * h)
        W = w[t][:, None]
        A = np.array([[np.sum(W * gD * gD) + aD, np.sum(W * gD * gH)], [np.sum(W * gD * gH), np.sum(W * gH * gH) + aH]])
        b = np.array([-cD - aD * lam_prev[t, 0], -cH - aH * lam_prev[t, 1]])
        dl = np.linalg.solve(A, b)
        x_ref = x[t] + W * (gD * dl[0] + gH * dl[1])

        q = wp.array(x[t].astype(np.float32), dtype=wp.vec3)
        lams = wp.array(lam_prev[t : t + 1].astype(np.float32), dtype=wp.vec2)
        z = wp.zeros(1, dtype=wp.vec3)
        wp.launch(K.sim_solve_tets, dim=1, inputs=[
            wp.array([0], dtype=wp.int32), 0, q, wp.array(w[t].astype(np.float32), dtype=float),
            wp.array(np.array([[0, 1, 2, 3]], np.int32), dtype=wp.int32),
            wp.array(Dinv[None].astype(np.float32), dtype=wp.mat33), wp.array([V], dtype=float),
            wp.array([mu[t]], dtype=float), wp.array([lam[t]], dtype=float), wp.array([1.0], dtype=float),
            lams, 0, 1 / h / h, q, z, z, z, 0.0, 1.0, 0, wp.zeros(1, dtype=float),
            wp.zeros((4, 1), dtype=float), wp.zeros((4, 1), dtype=wp.vec3)])
        step = np.abs(x_ref - x[t]).max()
        assert np.abs(q.numpy() - x_ref).max() <= 2e-3 * step + 1e-7
        np.testing.assert_allclose(lams.numpy()[0], lam_prev[t] + dl, rtol=2e-3, atol=1e-12)


def test_fused_colour_sweep_equals_per_colour_launches():
    """On the CPU one launch over the colour-sorted tets computes exactly what one launch
    per colour computes (Warp's CPU backend runs a launch's threads in index order)."""
    mesh = box_tetmesh((3, 3, 3), (0.1, 0.1, 0.1))
    b = ModelBuilder()
    b.add_soft_mesh(mesh, pos=(0, 0, 0.05), youngs_modulus=2e5, poissons_ratio=0.4)
    b.add_ground_plane()
    m = b.finalize()
    assert m.color_count > 5
    # no two tets of one colour share a vertex
    order, offs = m.tet_color_order.numpy(), m.tet_color_offsets
    for c in range(m.color_count):
        verts = m.tets[order[offs[c]:offs[c + 1]]].reshape(-1)
        assert len(np.unique(verts)) == len(verts)
    outs = []
    for fuse in (True, False):
        sol = SolverXPBDNeoHookean(m, iterations=5, substeps=3, fuse_colors=fuse)
        s, _ = _run(m, sol, 12)
        outs.append((s.positions(), s.velocities()))
    assert np.array_equal(outs[0][0], outs[1][0])
    assert np.array_equal(outs[0][1], outs[1][1])


def test_elastic_forces_match_finite_differences_of_energy(rng):
    """sim_tet_forces: energy equals a float64 NumPy evaluation and forces are minus its
    central-difference gradient."""
    mesh = box_tetmesh((2, 1, 1), (0.2, 0.1, 0.1))
    b = ModelBuilder(gravity=(0, 0, 0))
    b.add_soft_mesh(mesh, youngs_modulus=1e5, poissons_ratio=0.3)
    m = b.finalize()
    sol = SolverXPBDNeoHookean(m)
    s = m.state()
    x = m.rest_positions + rng.normal(size=m.rest_positions.shape) * 0.01
    s.particle_q.assign(x.astype(np.float32))
    f, e = sol.elastic_forces(s)
    x32 = x.astype(np.float32).astype(np.float64)
    T = m.tets
    X = m.rest_positions
    Dinv = np.linalg.inv(np.stack([X[T[:, 1]] - X[T[:, 0]], X[T[:, 2]] - X[T[:, 0]], X[T[:, 3]] - X[T[:, 0]]], 2))
    args = (T, Dinv, m.tet_volume_host, m.tet_mu_host, m.tet_lambda_host)
    e_ref = _np_energy(x32, *args)
    assert abs(e - e_ref) <= 1e-3 * abs(e_ref)
    g = np.zeros_like(x32)
    eps = 1e-6
    for i in range(len(x32)):
        for d in range(3):
            xp, xm = x32.copy(), x32.copy()
            xp[i, d] += eps
            xm[i, d] -= eps
            g[i, d] = (_np_energy(xp, *args) - _np_energy(xm, *args)) / (2 * eps)
    err = np.abs(f + g).max() / np.abs(g).max()
    assert err < 2e-3, err


def test_tet_stats_count_inverted_tets_and_total_volume(rng):
    mesh = box_tetmesh((2, 2, 2), (1.0, 1.0, 1.0))
    b = ModelBuilder()
    b.add_soft_mesh(mesh)
    m = b.finalize()
    sol = SolverXPBDNeoHookean(m)
    s = m.state()
    x = m.rest_positions.copy()
    x[13] = [0.5, 0.5, 1.6]  # the centre vertex pulled out through the top: inverts tets
    s.particle_q.assign(x.astype(np.float32))
    inv, vol = sol.tet_stats(s)
    a = x[m.tets[:, 0]]
    v = np.einsum("ij,ij->i", x[m.tets[:, 1]] - a, np.cross(x[m.tets[:, 2]] - a, x[m.tets[:, 3]] - a)) / 6
    assert inv == int((v <= 0).sum()) > 0
    assert vol == pytest.approx(v.sum(), rel=1e-5)


def test_finalize_applies_coulomb_friction_and_restitution():
    """sim_finalize on hand-made particles: static friction cancels small slip, kinetic
    friction removes mu * depth of a large slip, restitution reverses e * approach speed."""
    K = _K()
    h = 0.01
    mu, e = 0.5, 0.5
    # particle 0: slip 1 mm with depth 4 mm -> static; 1: slip 10 mm, depth 4 mm -> kinetic;
    # 2: approach at -2 m/s, projected onto the ground -> bounce at +1 m/s.
    q_start = np.array([[0, 0, 0], [0, 0, 0], [0, 0, 0.02]], np.float32)
    q = np.array([[0.001, 0, 0], [0.010, 0, 0], [0, 0, 0.0]], np.float32)
    qd_start = np.array([[0.1, 0, 0], [1.0, 0, 0], [0, 0, -2.0]], np.float32)
    depth = np.array([[0.004], [0.004], [0.0]], np.float32)
    qa = wp.array(q, dtype=wp.vec3)
    qd_out = wp.zeros(3, dtype=wp.vec3)
    force = wp.zeros(1, dtype=wp.vec3)
    ground = wp.array(np.zeros((1, 3), np.float32), dtype=wp.vec3)
    depth_a = wp.array(depth, dtype=float)
    # particle 2 is 0 m above ground after prediction; put it 5 mm below to get a depth
    q[2, 2] = -0.005
    qa.assign(q)
    wp.launch(K.sim_finalize, dim=3, inputs=[
        qa, wp.array(q_start, dtype=wp.vec3), wp.array(qd_start, dtype=wp.vec3),
        wp.array(np.ones(3, np.float32), dtype=float), wp.array(np.ones(3, np.float32), dtype=float),
        wp.array(np.array([[0, 0, 1]], np.float32), dtype=wp.vec3), ground, ground, 0.0, 1.0,
        wp.array([mu], dtype=float), wp.array([e], dtype=float), 1, depth_a, wp.zeros((3, 1), dtype=wp.vec3),
        h, 0.2, 1.0, 1.0 / (h * h),
    ], outputs=[qd_out, force])
    x = qa.numpy()
    v = qd_out.numpy()
    np.testing.assert_allclose(x[0], [0, 0, 0], atol=1e-7)  # static: slip cancelled
    np.testing.assert_allclose(x[1], [0.010 - mu * 0.004, 0, 0], atol=1e-7)  # kinetic
    np.testing.assert_allclose(v[1], [(0.010 - mu * 0.004) / h, 0, 0], rtol=1e-5)
    assert x[2, 2] == pytest.approx(0.0, abs=1e-7)
    assert v[2, 2] == pytest.approx(e * 2.0, rel=1e-5)  # bounce
    # contact force = m * (normal + friction corrections) / h^2 summed over particles
    f = force.numpy()[0]
    assert f[2] == pytest.approx((0.004 + 0.004 + 0.005) / h**2, rel=1e-4)
    assert f[0] == pytest.approx(-(0.001 + mu * 0.004) / h**2, rel=1e-4)


# ------------------------------------------------------------------ mechanics
def test_rigid_motion_gives_zero_force(rng):
    """A rotated and translated rest shape has zero elastic force and energy, and one solver
    step at zero gravity moving rigidly keeps it rigid (no spurious deformation)."""
    mesh = box_tetmesh((2, 2, 3), (0.1, 0.1, 0.15))
    b = ModelBuilder(gravity=(0, 0, 0))
    b.add_soft_mesh(mesh, youngs_modulus=2e5, poissons_ratio=0.45)
    m = b.finalize()
    sol = SolverXPBDNeoHookean(m, iterations=16, substeps=4)
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    R = q * np.sign(np.linalg.det(q))
    x = m.rest_positions @ R.T + rng.normal(size=3)
    s0 = m.state()
    s0.particle_q.assign(x.astype(np.float32))
    f, e = sol.elastic_forces(s0)
    fs = m.tet_mu_host.max() * np.ptp(m.rest_positions, axis=0).max() ** 2  # N, a force of the material's scale
    assert np.abs(f).max() < 1e-4 * fs
    assert abs(e) < 1e-6 * fs * 0.1
    # rigid translation velocity: after a step the shape is still the rigidly moved rest shape
    v = np.tile(rng.normal(size=3), (m.particle_count, 1))
    s0.particle_qd.assign(v.astype(np.float32))
    s1 = m.state()
    sol.step(s0, s1, m.control(), None, 1 / 60)
    np.testing.assert_allclose(s1.positions(), x + v / 60, atol=2e-6)
    np.testing.assert_allclose(s1.velocities(), v, atol=2e-4)


def test_free_fall_follows_parabola_before_contact():
    """The centre of mass follows z0 - g t^2 / 2 to 1 % of the drop height until contact.

    Symplectic Euler lags by g t h / 2 (h the substep), i.e. h / T of the drop height at
    contact time T; 16 substeps make that 0.4 %.
    """
    sc = _scene("drop", **{"sim.substeps": 16, "sim.iterations": 4, "sim.duration": 0.25})
    mesh = box_tetmesh((2, 2, 2), (1.0, 1.0, 1.0))
    r = run_scene(sc, mesh, transform=placement_transform(mesh.vertices, sc.placement))
    H = sc.placement.height
    z0 = r["com"][0, 2]
    t = np.arange(len(r["com"])) / 60.0
    zmin = r["frames"][:, :, 2].min(axis=1)
    n_free = int(np.argmax(zmin <= 1e-6))  # frames before the first contact
    free = np.arange(len(zmin)) < n_free
    assert n_free >= 10
    err = np.abs(r["com"][free, 2] - (z0 - 0.5 * GRAVITY * t[free] ** 2)).max() / H
    assert err < 0.01, err
    np.testing.assert_allclose(r["com"][free, :2], 0.0, atol=1e-6)  # straight down


def test_hanging_column_sags_by_rho_g_h2_over_2e():
    """A bar of height H clamped at its top stretches under its own weight by
    rho g H^2 / (2 E) (1D elasticity), within 10 % on a 3 x 3 x 30 cell mesh."""
    W, H, E, rho = 0.1, 1.0, 1e5, 1000.0
    mesh = box_tetmesh((3, 3, 30), (W, W, H))
    b = ModelBuilder()
    b.add_soft_mesh(mesh, density=rho, youngs_modulus=E, poissons_ratio=0.3, fixed=mesh.vertices[:, 2] > H - 1e-9)
    m = b.finalize()
    sol = SolverXPBDNeoHookean(m, iterations=16, substeps=2, damping=5.0)
    s, _ = _run(m, sol, 120)
    bottom = np.abs(mesh.vertices[:, 2]) < 1e-9
    sag = -s.positions()[bottom, 2].mean()
    exact = rho * GRAVITY * H**2 / (2 * E)
    assert abs(sag / exact - 1) < 0.10, (sag, exact)
    assert np.abs(s.velocities()).max() < 1e-2  # at rest


def test_uniaxial_compression_stress_over_strain_equals_youngs_modulus():
    """A block between a frictionless ground and a frictionless plate pressed down by 1 %:
    the plate force over the area, divided by the strain, is E within 5 %."""
    L, E, nu, eps = 0.1, 1e5, 0.3, 0.01
    mesh = box_tetmesh((4, 4, 4), (L, L, L))
    b = ModelBuilder(gravity=(0, 0, 0))
    b.add_soft_mesh(mesh, youngs_modulus=E, poissons_ratio=nu)
    b.add_ground_plane(friction=0.0)
    b.add_plate("Top", normal=(0, 0, -1), path=[[0, L / 2, L / 2, L], [0.5, L / 2, L / 2, L * (1 - eps)]], friction=0.0)
    m = b.finalize()
    sol = SolverXPBDNeoHookean(m, iterations=16, substeps=1, damping=5.0)
    s, forces = _run(m, sol, 90, record=lambda st: st.surface_force.numpy().copy())
    f_plate = -np.mean([f[1, 2] for f in forces[-15:]])
    x = s.positions()
    strain = 1 - np.ptp(x[:, 2]) / L
    assert strain == pytest.approx(eps, rel=1e-3)
    assert abs(f_plate / (L * L) / strain / E - 1) < 0.05
    # the ground carries the same load
    assert -np.mean([f[0, 2] for f in forces[-15:]]) == pytest.approx(-f_plate, rel=0.02)


def test_sliding_block_stops_at_coulomb_distance():
    """A stiff block launched along the ground at v0 decelerates at mu g and stops after
    v0^2 / (2 mu g)."""
    mesh = box_tetmesh((2, 2, 1), (0.1, 0.1, 0.05))
    mu, v0 = 0.4, 1.0
    b = ModelBuilder()
    b.add_soft_mesh(mesh, vel=(v0, 0, 0), youngs_modulus=1e6, poissons_ratio=0.3)
    b.add_ground_plane(friction=mu)
    m = b.finalize()
    sol = SolverXPBDNeoHookean(m, iterations=8, substeps=4)
    s, com = _run(m, sol, 30, record=lambda st: st.positions()[:, 0].mean())
    expected = v0**2 / (2 * mu * GRAVITY)
    assert com[-1] - mesh.vertices[:, 0].mean() == pytest.approx(expected, rel=0.03)
    assert np.abs(s.velocities()).max() < 1e-3


def test_drop_keeps_volume_within_two_percent_at_nu_045():
    sc = load_scene("drop")
    assert sc.material.poissons_ratio == 0.45
    mesh = box_tetmesh((4, 4, 4), (1.0, 1.0, 1.0))
    r = run_scene(sc, mesh)
    ratio = r["volume"] / r["model"].rest_volume()
    assert not r["nan"]
    assert r["frames"][:, :, 2].min() > -1e-6  # never below the ground
    assert np.abs(ratio - 1).max() < 0.02, np.abs(ratio - 1).max()
    assert r["com"][-1, 2] == pytest.approx(0.1, abs=0.003)  # came to rest on the ground


def test_squeeze_to_half_height_and_release_leaves_no_nan_and_no_inverted_tets():
    sc = load_scene("compress")
    mesh = box_tetmesh((3, 3, 3), (1.0, 1.0, 1.0))
    r = run_scene(sc, mesh)
    assert not r["nan"]
    h = np.ptp(r["frames"][:, :, 2], axis=1)
    assert h.min() == pytest.approx(0.5 * h[0], rel=0.02)  # squeezed to 50 %
    assert r["inverted"][-1] == 0
    assert abs(r["volume"][-1] / r["model"].rest_volume() - 1) < 0.01
    assert h[-1] == pytest.approx(h[0], rel=0.02)  # recovered its height
    top = r["surface_force"][:, 1, 2]
    assert top.min() < -10.0  # the plate pushed down while squeezing


def test_inverted_tets_recover_without_nan():
    """Tets turned inside out at t = 0 are pushed back by the hydrostatic constraint."""
    mesh = box_tetmesh((2, 2, 2), (0.2, 0.2, 0.2))
    b = ModelBuilder()
    b.add_soft_mesh(mesh, pos=(0, 0, 0.01), youngs_modulus=2e5, poissons_ratio=0.45)
    b.add_ground_plane()
    m = b.finalize()
    sol = SolverXPBDNeoHookean(m, iterations=16, substeps=4, damping=2.0)
    s0 = m.state()
    x = m.rest_positions.copy()
    centre = np.argmin(np.linalg.norm(x - x.mean(0), axis=1))
    x[centre, 2] += 0.25  # through the top face
    s0.particle_q.assign(x.astype(np.float32))
    inv0, _ = sol.tet_stats(s0)
    assert inv0 >= 4
    s1, c = m.state(), m.control()
    counts = []
    for k in range(60):
        sol.step(s0, s1, c, None, 1 / 60)
        s0, s1 = s1, s0
        counts.append(sol.tet_stats(s0)[0])
    assert np.all(np.isfinite(s0.positions()))
    assert counts[-1] == 0
    _, vol = sol.tet_stats(s0)
    assert vol == pytest.approx(m.rest_volume(), rel=0.02)


def test_disjoint_blocks_separate_under_compression_one_block_does_not():
    """Two blocks stacked face to face (two face-connected pieces, as TetSphere's union of
    spheres) fall apart in the compress scene: with no collision between pieces (self
    collision off, as in the paper) nothing holds the upper one. The same shape as one
    connected mesh stays one piece (method.md §10)."""
    sc = load_scene("compress")
    lower = box_tetmesh((2, 2, 1), (1.0, 1.0, 0.5))
    upper = box_tetmesh((2, 2, 1), (1.0, 1.0, 0.5), (0.0, 0.0, 0.5))
    two = TetMesh(np.concatenate([lower.vertices, upper.vertices]),
                  np.concatenate([lower.tets, upper.tets + lower.num_vertices]))
    one = box_tetmesh((2, 2, 2), (1.0, 1.0, 1.0))
    assert two.components()[1] == 2 and one.components()[1] == 1
    ends = {}
    for label, mesh in (("two", two), ("one", one)):
        r = run_scene(sc, mesh)
        assert not r["nan"]
        placed = mesh.with_vertices(r["model"].rest_positions)
        ends[label] = pieces_apart(placed, r["frames"][-1])[0]
    assert ends == {"two": 2, "one": 1}


def test_pieces_that_stay_in_contact_count_as_one():
    """pieces_apart: two touching blocks that did not move relative to each other hold
    together; moving one away by a block's height separates them."""
    lower = box_tetmesh((1, 1, 1), (1.0, 1.0, 1.0))
    upper = box_tetmesh((1, 1, 1), (1.0, 1.0, 1.0), (0.0, 0.0, 1.0))
    two = TetMesh(np.concatenate([lower.vertices, upper.vertices]),
                  np.concatenate([lower.tets, upper.tets + 8]))
    assert pieces_apart(two, two.vertices + 0.3)[0] == 1
    moved = two.vertices.copy()
    moved[8:, 0] += 1.0
    n, info = pieces_apart(two, moved)
    assert n == 2 and info["opened_pairs"][0]["interface_pairs"] == 4


def test_stability_plan_raises_substeps_for_fine_stiff_meshes():
    """The step plan keeps every tet below the stability ratio by adding substeps (keeping
    the iteration budget) and reports it; the coarse mesh needs no change."""
    from holowarp.sim import STABILITY_RATIO
    from holowarp.sim.solver import _stability_ratio_unit_step

    coarse = box_tetmesh((2, 2, 2), (0.2, 0.2, 0.2))
    fine = box_tetmesh((8, 8, 8), (0.2, 0.2, 0.2))
    plans = {}
    for label, mesh in (("coarse", coarse), ("fine", fine)):
        b = ModelBuilder()
        b.add_soft_mesh(mesh, youngs_modulus=2e5, poissons_ratio=0.45)
        m = b.finalize()
        sol = SolverXPBDNeoHookean(m, iterations=16, substeps=4)
        p = sol.plan(1 / 60)
        h = p.dt / p.substeps
        assert (_stability_ratio_unit_step(m) * h * h).max() <= STABILITY_RATIO * (1 + 1e-9) or p.softened_tets
        plans[label] = p
    assert plans["coarse"].substeps == 4 and plans["coarse"].iterations == 16
    assert plans["fine"].substeps > 4
    assert plans["fine"].iterations == max(1, int(np.floor(64 / plans["fine"].substeps + 0.5)))
    assert plans["fine"].softened_tets == 0


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
