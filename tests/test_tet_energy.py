"""Tet energies (method.md §5, §6): Warp kernels against dense torch references and
float64 central finite differences, rigid-motion invariance, HC stage behaviour."""

from __future__ import annotations

import numpy as np
import pytest
import torch
import warp as wp

from holowarp.energies import SURFACE_WEIGHT, TetEnergies, biharmonic_weights, eikonal_loss, smoothness_loss
from holowarp.ops import tet_energy as ops
from holowarp.ops import tet_energy_ref as ref
from holowarp.primitives import box_tetmesh

# One torch thread for the whole module (see conftest.one_torch_thread).
pytestmark = pytest.mark.usefixtures("one_torch_thread")

# float64 central differences of float64 kernels: truncation ~ eps^2, rounding ~ 1e-16/eps
FD_EPS = 1e-6
FD_TOL = 1e-6


def _fd_grad(fn, x: torch.Tensor, eps: float = FD_EPS) -> torch.Tensor:
    g = torch.zeros_like(x)
    flat = x.detach().clone().reshape(-1)
    for i in range(flat.numel()):
        old = flat[i].item()
        flat[i] = old + eps
        fp = fn(flat.view_as(x)).item()
        flat[i] = old - eps
        fm = fn(flat.view_as(x)).item()
        flat[i] = old
        g.view(-1)[i] = (fp - fm) / (2 * eps)
    return g


def _analytic_grad(fn, x: torch.Tensor) -> torch.Tensor:
    x = x.detach().clone().requires_grad_(True)
    fn(x).backward()
    return x.grad


def _rel_err(g, fd) -> float:
    """Largest entry-wise error relative to the largest finite-difference entry."""
    return float((g - fd).abs().max() / fd.abs().max().clamp_min(1e-300))


def _random_rotation(rng):
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    return q * np.sign(np.linalg.det(q))


@pytest.fixture
def setup(rng):
    """A jittered 3x3x3-cell box (162 tets, 6 of them interior), a rest shape and a
    deformed state."""
    mesh = box_tetmesh((3, 3, 3), (1.0, 1.0, 0.8))
    rest = mesh.vertices + rng.normal(scale=0.03, size=mesh.vertices.shape)
    x = torch.tensor(rest + rng.normal(scale=0.06, size=rest.shape))
    weights = biharmonic_weights(mesh.tets, mesh.surface_vertices()) * torch.as_tensor(
        rng.uniform(0.5, 1.5, size=mesh.num_tets)
    )
    energies = TetEnergies(mesh, rest, weights=weights)
    return mesh, torch.tensor(rest), x, energies


def test_face_adjacency_matches_independent_reference(setup):
    mesh, _, _, energies = setup
    want = ref.face_adjacency_ref(mesh.tets)
    assert torch.equal(energies.adjacency.long(), want)
    assert (want >= 0).sum() > 0 and (want < 0).sum() > 0


def test_deformation_gradients_match_reference_and_finite_differences(setup, rng):
    mesh, rest, x, energies = setup
    F = energies.deformation_gradients(x)
    torch.testing.assert_close(F, ref.deformation_gradients_ref(x, mesh.tets, rest), rtol=1e-12, atol=1e-12)
    w = torch.tensor(rng.normal(size=F.shape))

    def f(z):
        return (energies.deformation_gradients(z) * w).sum()

    assert _rel_err(_analytic_grad(f, x), _fd_grad(f, x)) < FD_TOL
    # at rest F is the identity
    torch.testing.assert_close(energies.deformation_gradients(rest), torch.eye(3, dtype=torch.float64).expand_as(F))


def test_biharmonic_matches_dense_reference(setup):
    mesh, rest, x, energies = setup
    e = energies.biharmonic(x)
    assert e.item() == pytest.approx(ref.biharmonic_ref(x, mesh.tets, rest, energies.weights).item(), rel=1e-12)
    g = _analytic_grad(energies.biharmonic, x)
    gr = _analytic_grad(lambda z: ref.biharmonic_ref(z, mesh.tets, rest, energies.weights), x)
    torch.testing.assert_close(g, gr, rtol=1e-10, atol=1e-12)


def test_biharmonic_gradient_matches_float64_finite_differences(setup):
    _, _, x, energies = setup
    assert _rel_err(_analytic_grad(energies.biharmonic, x), _fd_grad(energies.biharmonic, x)) < FD_TOL


def test_biharmonic_weights_down_weight_surface_tets_and_uniform_is_the_ablation(setup):
    mesh, rest, x, _ = setup
    w = biharmonic_weights(mesh.tets, mesh.surface_vertices())
    touches = np.isin(mesh.tets, mesh.surface_vertices()).any(axis=1)
    assert SURFACE_WEIGHT == 5e-4
    np.testing.assert_array_equal(w.numpy(), np.where(touches, 5e-4, 1.0))
    assert (~touches).any()  # the fixture has interior tets
    uniform = TetEnergies(mesh, rest)  # weights=None
    ones = TetEnergies(mesh, rest, weights=np.ones(mesh.num_tets))
    assert uniform.biharmonic(x).item() == pytest.approx(ones.biharmonic(x).item(), rel=1e-14)
    surface = TetEnergies(mesh, rest, weights="surface")
    assert surface.biharmonic(x).item() == pytest.approx(
        ref.biharmonic_ref(x, mesh.tets, rest, w).item(), rel=1e-12
    )


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_rigid_motion_of_rest_gives_zero_biharmonic_energy_and_gradient(setup, rng, dtype):
    _, rest, _, energies = setup
    Q = torch.tensor(_random_rotation(rng))
    moved = (rest @ Q.T + torch.tensor(rng.normal(size=3))).to(dtype).requires_grad_(True)
    e = energies.biharmonic(moved)
    e.backward()
    tol = 1e-20 if dtype == torch.float64 else 1e-8
    assert abs(e.item()) < tol
    assert moved.grad.abs().max().item() < (1e-12 if dtype == torch.float64 else 1e-4)
    # and a deformed state keeps zero inversion penalty when no tet flips
    assert energies.inversion_penalty(moved, 2.0).item() == 0.0


def test_every_energy_is_invariant_to_rigid_motion_of_the_state(setup, rng):
    mesh, rest, x, energies = setup
    Q = torch.tensor(_random_rotation(rng))
    t = torch.tensor(rng.normal(size=3))
    y = x @ Q.T + t
    x = x.clone()
    x[3] += torch.tensor([0.0, 0.0, -0.8])  # invert a few tets so the penalty is non-zero
    y = x @ Q.T + t
    edges = torch.as_tensor(np.array(mesh.edges()))
    phi = torch.tensor(rng.normal(size=mesh.num_vertices))
    pairs = [
        (energies.biharmonic(x), energies.biharmonic(y)),
        (energies.inversion_penalty(x, 3.0), energies.inversion_penalty(y, 3.0)),
        (energies.hc_laplacian(x, lam_cond=0.0), energies.hc_laplacian(y, lam_cond=0.0)),
        (energies.hc_laplacian(x, lam_cond=1.0), energies.hc_laplacian(y, lam_cond=1.0)),
        (eikonal_loss(phi, edges, x), eikonal_loss(phi, edges, y)),
    ]
    assert pairs[1][0].item() > 0
    for a, b in pairs:
        assert a.item() == pytest.approx(b.item(), rel=1e-10)


@pytest.mark.parametrize("p", [2.0, 3.5, 4.0])
def test_inversion_penalty_matches_reference_and_finite_differences(setup, p):
    mesh, rest, x, energies = setup
    x = x.clone()
    x[5] += torch.tensor([0.0, 0.6, -0.7])
    x[20] += torch.tensor([0.5, 0.0, 0.4])
    F = ref.deformation_gradients_ref(x, mesh.tets, rest)
    assert (torch.linalg.det(F) < 0).sum() >= 2
    e = energies.inversion_penalty(x, p)
    assert e.item() == pytest.approx(ref.inversion_penalty_ref(x, mesh.tets, rest, p).item(), rel=1e-12)

    def f(z):
        return energies.inversion_penalty(z, p)

    g = _analytic_grad(f, x)
    assert _rel_err(g, _fd_grad(f, x)) < FD_TOL
    torch.testing.assert_close(g, _analytic_grad(lambda z: ref.inversion_penalty_ref(z, mesh.tets, rest, p), x))


def test_inversion_penalty_is_zero_without_inverted_tets_and_rejects_p_below_one(setup):
    _, rest, _, energies = setup
    z = rest.clone().requires_grad_(True)
    e = energies.inversion_penalty(z, 2.0)
    e.backward()
    assert e.item() == 0.0 and z.grad.abs().max().item() == 0.0
    with pytest.raises(ValueError, match="p must be >= 1"):
        energies.inversion_penalty(rest, 0.5)


@pytest.mark.parametrize("lam_cond", [0.0, 1.0])
def test_hc_laplacian_matches_reference_and_fd_with_targets_held(setup, lam_cond):
    mesh, _, x, energies = setup
    bf = mesh.boundary_faces()
    e = energies.hc_laplacian(x, bf, lam_cond)
    assert e.item() == pytest.approx(ref.hc_energy_ref(x, bf, lam_cond).item(), rel=1e-12)
    # the op treats targets and normals as constants: check exactly that function
    topo = energies.hc_topology(bf)
    target, normal = ops.hc_targets(x, topo)
    t_ref, n_ref, surf = ref.hc_targets_ref(x, bf)
    ids = topo.surf_ids.long()
    assert torch.equal(torch.nonzero(surf).squeeze(1), ids)
    torch.testing.assert_close(target, t_ref[ids], rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(normal, n_ref[ids], rtol=1e-12, atol=1e-12)

    def frozen(z):
        return ops.hc_energy(z, topo, target, normal, lam_cond)

    g = _analytic_grad(lambda z: energies.hc_laplacian(z, bf, lam_cond), x)
    torch.testing.assert_close(g, _analytic_grad(frozen, x))
    assert _rel_err(g, _fd_grad(frozen, x)) < FD_TOL
    full_t = torch.zeros_like(x)
    full_n = torch.zeros_like(x)
    full_t[ids], full_n[ids] = target, normal
    torch.testing.assert_close(g, _analytic_grad(lambda z: ref.hc_energy_ref(z, bf, lam_cond, target=full_t, normal=full_n), x))


def test_hc_targets_with_original_positions_match_reference(setup):
    mesh, rest, x, energies = setup
    bf = mesh.boundary_faces()
    topo = energies.hc_topology(bf)
    target, _ = ops.hc_targets(x, topo, x_orig=rest, alpha=0.3, beta=0.7)
    t_ref, _, _ = ref.hc_targets_ref(x, bf, x_orig=rest, alpha=0.3, beta=0.7)
    torch.testing.assert_close(target, t_ref[topo.surf_ids.long()], rtol=1e-12, atol=1e-12)
    e = energies.hc_laplacian(x, bf, 1.0, alpha=0.3, beta=0.7)
    assert e.item() == pytest.approx(ref.hc_energy_ref(x, bf, 1.0, x_orig=rest, alpha=0.3, beta=0.7).item(), rel=1e-12)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_fused_hc_pass_is_bitwise_the_two_step_one(setup, dtype):
    # hc_laplacian_energy fuses the target and energy kernels: the same arithmetic, so the
    # same bits as hc_energy(hc_targets(...)), in the optimiser's float32 as in float64.
    mesh, rest, x, energies = setup
    topo = energies.hc_topology(mesh.boundary_faces())
    x = x.to(dtype)
    for lam_cond, kw in ((0.0, {}), (1.0, {"x_orig": torch.as_tensor(rest, dtype=dtype), "alpha": 0.3, "beta": 0.7})):
        target, normal = ops.hc_targets(x, topo, **kw)
        a = x.clone().requires_grad_(True)
        b = x.clone().requires_grad_(True)
        e_two = ops.hc_energy(a, topo, target, normal, lam_cond)
        e_one = ops.hc_laplacian_energy(b, topo, lam_cond, **kw)
        e_two.backward()
        e_one.backward()
        assert torch.equal(e_one, e_two) and e_one > 0
        assert torch.equal(a.grad, b.grad) and a.grad.abs().sum() > 0
    assert not ops.hc_laplacian_energy(x, topo, 1.0).requires_grad


def test_hc_stage_one_pushes_dents_out_and_only_stage_two_pulls_bumps_in():
    mesh = box_tetmesh((4, 4, 2), (1.0, 1.0, 0.5))
    energies = TetEnergies(mesh)
    top = np.flatnonzero(
        np.isclose(mesh.vertices[:, 2], 0.5)
        & np.isclose(mesh.vertices[:, 0], 0.5)
        & np.isclose(mesh.vertices[:, 1], 0.5)
    )
    assert len(top) == 1  # centre of the top face, outward normal +z
    i = int(top[0])
    for dz, kind in ((-0.05, "dent"), (0.05, "bump")):
        for lam in (0.0, 1.0):
            x = torch.tensor(mesh.vertices)
            x[i, 2] += dz
            x.requires_grad_(True)
            energies.hc_laplacian(x, lam_cond=lam).backward()
            descent_z = -x.grad[i, 2].item()
            if kind == "dent":
                assert descent_z > 1e-3  # pushed back out in both stages
            elif lam == 0.0:
                assert descent_z == 0.0  # stage 1 leaves the bump alone: no shrinking
            else:
                assert descent_z < -1e-3  # stage 2 smooths it in


def test_eikonal_and_smoothness_match_reference_and_finite_differences(setup, rng):
    mesh, _, x, _ = setup
    edges = torch.as_tensor(np.array(mesh.edges()))
    phi = torch.tensor(rng.normal(scale=0.3, size=mesh.num_vertices))
    assert eikonal_loss(phi, edges, x).item() == pytest.approx(ref.eikonal_ref(phi, edges, x).item(), rel=1e-12)
    assert smoothness_loss(phi, edges).item() == pytest.approx(ref.smoothness_ref(phi, edges).item(), rel=1e-12)
    checks = [
        (lambda p: eikonal_loss(p, edges, x), phi),
        (lambda z: eikonal_loss(phi, edges, z), x),
        (lambda p: smoothness_loss(p, edges), phi),
    ]
    for fn, arg in checks:
        assert _rel_err(_analytic_grad(fn, arg), _fd_grad(fn, arg)) < FD_TOL
    # both inputs at once, against the reference's autograd
    p1 = phi.clone().requires_grad_(True)
    x1 = x.clone().requires_grad_(True)
    eikonal_loss(p1, edges, x1).backward()
    p2 = phi.clone().requires_grad_(True)
    x2 = x.clone().requires_grad_(True)
    ref.eikonal_ref(p2, edges, x2).backward()
    torch.testing.assert_close(p1.grad, p2.grad)
    torch.testing.assert_close(x1.grad, x2.grad)


def test_float32_energies_agree_with_float64(setup):
    mesh, rest, x, energies = setup
    x32 = x.float()
    edges = torch.as_tensor(np.array(mesh.edges()))
    phi = torch.linspace(-1, 1, mesh.num_vertices, dtype=torch.float64)
    for f in (energies.biharmonic, lambda z: energies.inversion_penalty(z - 0.3 * (z == z.max()), 2.0),
              lambda z: energies.hc_laplacian(z, lam_cond=0.0), lambda z: eikonal_loss(phi.to(z.dtype), edges, z)):
        a, b = f(x32), f(x)
        assert a.dtype == torch.float32
        assert a.item() == pytest.approx(b.item(), rel=1e-4, abs=1e-7)
        g32, g64 = _analytic_grad(f, x32), _analytic_grad(f, x)
        assert float((g32.double() - g64).abs().max() / g64.abs().max().clamp_min(1e-12)) < 1e-3


def test_degenerate_rest_tets_are_left_out_and_rigid_motion_still_costs_nothing(rng):
    mesh = box_tetmesh((2, 2, 2))
    rest = mesh.vertices.copy()
    # collapse one interior-ish vertex onto a neighbour's plane: flattens the tets around it
    energies_ok = TetEnergies(mesh, rest)
    assert energies_ok.num_degenerate_rest == 0
    flat = rest.copy()
    t0 = mesh.tets[0]
    a, b, c = flat[t0[0]], flat[t0[1]], flat[t0[2]]
    n = np.cross(b - a, c - a)
    n /= np.linalg.norm(n)
    flat[t0[3]] -= n * np.dot(flat[t0[3]] - a, n)  # tet 0 now has zero volume
    energies = TetEnergies(mesh, flat)
    assert energies.num_degenerate_rest >= 1
    assert energies.weights[0].item() == 0.0
    assert not (energies.adjacency.long() == 0).any()  # nobody sees tet 0 as a neighbour
    Q = torch.tensor(_random_rotation(rng))
    moved = (torch.tensor(flat) @ Q.T + 1.0).requires_grad_(True)
    e = energies.biharmonic(moved)
    e.backward()
    assert abs(e.item()) < 1e-20 and moved.grad.abs().max().item() < 1e-12


def test_rest_is_captured_on_demand_and_bad_inputs_name_the_argument(setup):
    mesh, rest, x, _ = setup
    lazy = TetEnergies(torch.as_tensor(np.array(mesh.tets)))
    assert lazy.dm_inv is None
    assert lazy.biharmonic(rest).item() == pytest.approx(0.0, abs=1e-20)  # captured from rest
    assert lazy.biharmonic(x).item() > 0
    lazy.capture_rest(x)
    assert lazy.biharmonic(x).item() == pytest.approx(0.0, abs=1e-20)
    with pytest.raises(ValueError, match="x must be"):
        lazy.biharmonic(x[:-1])
    with pytest.raises(ValueError, match="capture_rest"):
        lazy.capture_rest(np.zeros((3, 3)))
    with pytest.raises(ValueError, match="weights"):
        TetEnergies(mesh, rest, weights=np.ones(3))
    with pytest.raises(ValueError, match="edges"):
        eikonal_loss(torch.zeros(mesh.num_vertices, dtype=torch.float64), torch.zeros((4, 3)), x)
    with pytest.raises(TypeError, match="float32 and float64"):
        lazy.biharmonic(x.half())


def test_hand_written_backward_passes_warp_gradcheck(setup):
    """Warp's own gradcheck, fed our kernels with the hand-written backward on its tape."""
    from holowarp.kernels import tet_energy as K

    _, _, x, energies = setup
    tets, dm_inv, adj, w = energies._rest_for(x)
    M = tets.shape[0]
    tets_wp = wp.from_torch(tets, dtype=wp.vec4i)
    adj_wp = wp.from_torch(adj, dtype=wp.vec4i)
    dm_wp = wp.from_torch(dm_inv, dtype=wp.mat33d)
    w_wp = wp.from_torch(w)
    import warp.autograd

    try:  # the tape being recorded; Warp has no public accessor for it
        from warp._src import context as runtime
    except ImportError:
        pytest.skip("this Warp version does not expose the active tape")
    if not hasattr(runtime.runtime, "tape"):
        pytest.skip("this Warp version does not expose the active tape")

    def energy(x_wp):
        F = wp.empty(M, dtype=wp.mat33d)
        LF = wp.empty(M, dtype=wp.mat33d)
        per_tet = wp.empty(M, dtype=wp.float64)
        wp.launch(K.deformation_gradient_kernel, M, inputs=[x_wp, tets_wp, dm_wp], outputs=[F], record_tape=False)
        wp.launch(K.biharmonic_forward_kernel, M, inputs=[F, adj_wp, w_wp], outputs=[LF, per_tet], record_tape=False)
        total = wp.array([per_tet.numpy().sum()], dtype=wp.float64, requires_grad=True)
        tape = runtime.runtime.tape
        if tape is not None:

            def backward():
                wp.launch(K.biharmonic_backward_kernel, M, inputs=[tets_wp, adj_wp, LF, dm_wp, total.grad],
                          outputs=[x_wp.grad], record_tape=False)

            tape.record_func(backward, [x_wp, total])
        return total

    x_wp = wp.array(x.numpy(), dtype=wp.vec3d, requires_grad=True)
    assert warp.autograd.gradcheck(energy, inputs=[x_wp], eps=1e-6, atol=1e-7, rtol=1e-6,
                                 raise_exception=False, show_summary=False)


# --- fused passes (issue 17): the same values and gradients as the separate energies -----


@pytest.mark.parametrize("p", [2.0, 3.5])
def test_fused_biharmonic_and_inversion_match_references_and_finite_differences(setup, rng, p):
    mesh, rest, x, energies = setup
    x = x.clone()
    x[5] += torch.tensor([0.0, 0.6, -0.7])  # invert a few tets so both terms are active
    x[20] += torch.tensor([0.5, 0.0, 0.4])
    w_bih, w_inv = rng.uniform(0.5, 2.0, size=2)
    e_bih, e_inv = energies.biharmonic_and_inversion(x, p)
    assert e_inv.item() > 0
    assert e_bih.item() == pytest.approx(ref.biharmonic_ref(x, mesh.tets, rest, energies.weights).item(), rel=1e-12)
    assert e_inv.item() == pytest.approx(ref.inversion_penalty_ref(x, mesh.tets, rest, p).item(), rel=1e-12)

    def fused(z):
        b, i = energies.biharmonic_and_inversion(z, p)
        return w_bih * b + w_inv * i

    def separate(z):
        return w_bih * ref.biharmonic_ref(z, mesh.tets, rest, energies.weights) + w_inv * ref.inversion_penalty_ref(
            z, mesh.tets, rest, p)

    g = _analytic_grad(fused, x)
    torch.testing.assert_close(g, _analytic_grad(separate, x), rtol=1e-10, atol=1e-12)
    assert _rel_err(g, _fd_grad(fused, x)) < FD_TOL
    # only one of the two outputs in the loss: the other gets no gradient
    gb = _analytic_grad(lambda z: energies.biharmonic_and_inversion(z, p)[0], x)
    torch.testing.assert_close(gb, _analytic_grad(energies.biharmonic, x), rtol=1e-10, atol=1e-12)


def test_signed_volumes_match_numpy_triple_products(setup, rng):
    mesh, _, x, _ = setup
    tets = torch.as_tensor(np.array(mesh.tets, dtype=np.int32))
    v = x.numpy()
    t = np.array(mesh.tets)
    want = np.einsum("ij,ij->i", v[t[:, 1]] - v[t[:, 0]], np.cross(v[t[:, 2]] - v[t[:, 0]], v[t[:, 3]] - v[t[:, 0]])) / 6
    np.testing.assert_allclose(ops.signed_volumes(x, tets).numpy(), want, rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(ops.signed_volumes(x.float(), tets).numpy(), want, rtol=1e-4, atol=1e-7)
    swapped = tets[:, [1, 0, 2, 3]].contiguous()  # odd permutation: the sign flips
    np.testing.assert_allclose(ops.signed_volumes(x, swapped).numpy(), -want, rtol=1e-12, atol=1e-15)


def test_fused_eikonal_and_smoothness_match_the_separate_losses_and_finite_differences(setup, rng):
    mesh, _, x, _ = setup
    edges = torch.as_tensor(np.array(mesh.edges()))
    phi = torch.tensor(rng.normal(scale=0.3, size=mesh.num_vertices))
    a, b = rng.uniform(0.1, 2.0, size=2)
    l_eik, l_smooth = ops.phi_edge_losses(phi, edges, x)
    assert l_eik.item() == pytest.approx(ref.eikonal_ref(phi, edges, x).item(), rel=1e-12)
    assert l_smooth.item() == pytest.approx(ref.smoothness_ref(phi, edges).item(), rel=1e-12)

    def fused(p):
        e, s = ops.phi_edge_losses(p, edges, x)
        return a * e + b * s

    g = _analytic_grad(fused, phi)
    want = _analytic_grad(lambda p: a * ref.eikonal_ref(p, edges, x) + b * ref.smoothness_ref(p, edges), phi)
    torch.testing.assert_close(g, want, rtol=1e-10, atol=1e-12)
    assert _rel_err(g, _fd_grad(fused, phi)) < FD_TOL
    # float32 phi with float32 positions, as the topology phase runs it
    e32, s32 = ops.phi_edge_losses(phi.float(), edges, x.float())
    assert e32.item() == pytest.approx(l_eik.item(), rel=1e-5)
    assert s32.item() == pytest.approx(l_smooth.item(), rel=1e-5)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("width", [3, 1])
def test_tet_mean_is_torch_gather_mean_bit_for_bit_with_its_gradient(rng, dtype, width):
    """The surfel model's centres (positions) and field opacities (scalars) come from
    ops.tet_mean: the same values and gradients as ``values[tets].mean(dim=1)``, bit for bit
    on the CPU (sum in vertex order, exact 1/4, scatter tet by tet), with vertices shared by
    many tets and some used by none."""
    n, m = 300, 2000
    tets = torch.tensor(rng.integers(0, n - 20, size=(m, 4)))
    shape = (n, 3) if width == 3 else (n,)
    values = torch.tensor(rng.normal(size=shape) * 10.0 ** rng.uniform(-3, 3, size=shape), dtype=dtype,
                          requires_grad=True)
    g = torch.tensor(rng.normal(size=(m, *shape[1:])), dtype=dtype)
    got = ops.tet_mean(values, tets.to(torch.int32))
    want = values[tets].mean(dim=1)
    assert got.shape == want.shape and torch.equal(got, want)
    (g_got,) = torch.autograd.grad(got, values, g)
    (g_want,) = torch.autograd.grad(want, values, g)
    assert torch.equal(g_got, g_want)
    assert (g_got[n - 20:] == 0).all() and (g_got[: n - 20] != 0).any()


def test_tet_mean_refuses_bad_shapes_by_name():
    x = torch.zeros(5, 3)
    with pytest.raises(ValueError, match="tet_mean: tets must be a .M, 4. int32"):
        ops.tet_mean(x, torch.zeros((2, 4), dtype=torch.int64))
    with pytest.raises(ValueError, match="tet_mean: values must be"):
        ops.tet_mean(torch.zeros(5, 2), torch.zeros((2, 4), dtype=torch.int32))
    with pytest.raises(TypeError, match="float32 and float64"):
        ops.tet_mean(torch.zeros(5, 3, dtype=torch.float16), torch.zeros((2, 4), dtype=torch.int32))


# --- a StepCache (the geometry step's reused buffers, views and launches) ------------------


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_cached_energies_repeat_the_fresh_values_and_gradients_bit_for_bit(setup, rng, dtype):
    # The geometry step runs both fused energies through one StepCache on the same leaf
    # tensor, moved in place each step, with a changing barrier exponent and lam_cond. Each
    # step must give the bits of a cache-less call, which the dense references check; a new
    # tensor, then a mesh of another size, must re-pack the launches, not replay stale ones.
    from holowarp.ops._warp import StepCache

    mesh, rest, x0, energies = setup
    bf = mesh.boundary_faces()
    cache = StepCache()
    x = x0.to(dtype).clone().requires_grad_(True)
    first = None
    for step, p in enumerate((2.0, 3.5, 2.0, 4.0)):
        with torch.no_grad():
            x.copy_(torch.as_tensor(x0.numpy() + rng.normal(scale=0.05, size=x0.shape), dtype=dtype))
            x[5] += torch.tensor([0.0, 0.6, -0.7], dtype=dtype)  # some inverted tets: both terms active
        if step == 3:  # a new leaf: other storage for every view of x
            x = x.detach().clone().requires_grad_(True)
        lam_cond = float(step % 2)
        w = rng.uniform(0.5, 2.0, size=3)
        b, i = energies.biharmonic_and_inversion(x, p, cache=cache)
        h = energies.hc_laplacian(x, bf, lam_cond, cache=cache)
        x.grad = None
        (w[0] * b + w[1] * i + w[2] * h).backward()
        xf = x.detach().clone().requires_grad_(True)
        bf_, if_ = energies.biharmonic_and_inversion(xf, p)
        hf = energies.hc_laplacian(xf, bf, lam_cond)
        (w[0] * bf_ + w[1] * if_ + w[2] * hf).backward()
        assert torch.equal(b, bf_) and torch.equal(i, if_) and torch.equal(h, hf) and i > 0
        assert torch.equal(x.grad, xf.grad) and x.grad.abs().sum() > 0
        assert b.item() == pytest.approx(ref.biharmonic_ref(x.detach(), mesh.tets, rest, energies.weights).item(),
                                         rel=1e-5 if dtype == torch.float32 else 1e-12)
        if first is None:
            first = (b.clone(), x.grad.clone(), b, x.grad)
    # what a step returned stays as it was after later steps reuse the buffers
    assert torch.equal(first[0], first[2]) and torch.equal(first[1], first[3])
    big = box_tetmesh((4, 3, 3), (1.0, 0.8, 0.8))
    e_big = TetEnergies(big, np.asarray(big.vertices) + rng.normal(scale=0.02, size=big.vertices.shape))
    xb = torch.as_tensor(np.asarray(big.vertices) + rng.normal(scale=0.04, size=big.vertices.shape), dtype=dtype)
    got = e_big.biharmonic_and_inversion(xb, 2.0, cache=cache)
    want = e_big.biharmonic_and_inversion(xb, 2.0)
    assert all(torch.equal(a, b_) for a, b_ in zip(got, want))
    assert torch.equal(e_big.hc_laplacian(xb, big.boundary_faces(), 1.0, cache=cache),
                       e_big.hc_laplacian(xb, big.boundary_faces(), 1.0))
