"""The fused per-view losses of the mesh blocks (``holowarp.ops.mesh_losses``) against the
torch expressions they replace (dense float64 reference), values and gradients."""

from __future__ import annotations

import pytest
import torch

from holowarp.losses import covered_prior_loss
from holowarp.ops.mesh_losses import mesh_view_losses


def _unit(v):
    return v / v.norm(dim=-1, keepdim=True)


def _inputs(seed, H=13, W=17, with_prior=True):
    g = torch.Generator().manual_seed(seed)
    u = lambda *s: torch.rand(*s, generator=g)  # noqa: E731
    # alpha: exact 0 and 1 regions (ties with the mask), a ramp in between.
    alpha = u(H, W)
    alpha = torch.where(alpha < 0.3, torch.zeros_like(alpha), torch.where(alpha > 0.7, torch.ones_like(alpha), alpha))
    normal = _unit(torch.randn(H, W, 3, generator=g)) * (alpha > 0).unsqueeze(-1)
    mask = (u(H, W) > 0.4).float()
    mask[u(H, W) > 0.8] = 0.5
    ref_normal = _unit(torch.randn(H, W, 3, generator=g)).half()
    ref_alpha = u(H, W).half()
    prior = None
    if with_prior:
        prior = torch.randn(H, W, 3, generator=g) * (0.3 + u(H, W, 1))
        prior[u(H, W) < 0.2] = 0.0
    return alpha, normal, mask, ref_normal, ref_alpha, prior


def _reference(alpha, normal, mask, ref_normal, ref_alpha, prior):
    """The geometry step's torch expressions, in float64."""
    n_gs, a_gs = ref_normal.double(), ref_alpha.double()
    l_mask = (alpha - mask.double()).abs().mean()
    sel = ((alpha > 0) & (a_gs > 0.5)).double()
    l_norm = ((1.0 - (normal * n_gs).sum(-1)) * sel).sum() / sel.sum().clamp_min(1.0)
    l_prior = covered_prior_loss(prior.double(), normal, alpha) if prior is not None else torch.zeros((), dtype=torch.float64)
    return torch.stack([l_mask, l_norm, l_prior])


@pytest.mark.parametrize("seed,with_prior", [(0, True), (1, True), (2, False)])
def test_values_and_gradients_match_torch(seed, with_prior):
    alpha, normal, mask, ref_normal, ref_alpha, prior = _inputs(seed, with_prior=with_prior)
    a = alpha.clone().requires_grad_(True)
    n = normal.clone().requires_grad_(True)
    out = mesh_view_losses(a, n, mask, ref_normal, ref_alpha, prior)
    a64 = alpha.double().requires_grad_(True)
    n64 = normal.double().requires_grad_(True)
    ref = _reference(a64, n64, mask, ref_normal, ref_alpha, prior)
    torch.testing.assert_close(out.double(), ref.detach(), rtol=1e-5, atol=1e-7)
    assert ref[1] > 0 and (not with_prior or ref[2] > 0)
    w = torch.rand(3, generator=torch.Generator().manual_seed(seed + 10)) + 0.5
    (out * w).sum().backward()
    (ref * w.double()).sum().backward()
    torch.testing.assert_close(a.grad.double(), a64.grad, rtol=1e-5, atol=1e-8)
    torch.testing.assert_close(n.grad.double(), n64.grad, rtol=1e-4, atol=1e-8)
    assert a.grad.abs().sum() > 0 and n.grad.abs().sum() > 0


def test_empty_selection_gives_zero():
    alpha, normal, mask, ref_normal, ref_alpha, prior = _inputs(3)
    out = mesh_view_losses(torch.zeros_like(alpha), torch.zeros_like(normal), mask, ref_normal,
                           torch.zeros_like(ref_alpha), prior)
    assert out[1] == 0 and out[2] == 0
    torch.testing.assert_close(out[0], mask.mean())


def test_bad_inputs_name_the_argument():
    alpha, normal, mask, ref_normal, ref_alpha, prior = _inputs(4)
    with pytest.raises(ValueError, match="ref_normal"):
        mesh_view_losses(alpha, normal, mask, ref_normal.float(), ref_alpha, prior)
    with pytest.raises(ValueError, match="prior"):
        mesh_view_losses(alpha, normal, mask, ref_normal, ref_alpha, prior[:-1])


def test_a_step_cache_gives_the_fresh_values_and_gradients_bit_for_bit():
    # The geometry step passes one StepCache for every view: new images each call (other
    # storage), the prior on and off, and other sizes must all give the cache-less bits, and
    # a returned loss must not change when the next call reuses the buffers.
    from holowarp.ops._warp import StepCache

    cache = StepCache()
    kept = None
    for seed, with_prior, (H, W) in ((3, True, (13, 17)), (4, True, (13, 17)), (5, False, (13, 17)), (6, True, (9, 11))):
        alpha, normal, mask, ref_normal, ref_alpha, prior = _inputs(seed, H=H, W=W, with_prior=with_prior)
        outs, grads = [], []
        for c in (cache, None):
            a = alpha.clone().requires_grad_(True)
            n = normal.clone().requires_grad_(True)
            kw = {"cache": c} if c is not None else {}
            out = mesh_view_losses(a, n, mask, ref_normal, ref_alpha, prior, **kw)
            (out * torch.tensor([0.7, 1.3, 0.9])).sum().backward()
            outs.append(out)
            grads.append((a.grad, n.grad))
        assert torch.equal(outs[0], outs[1]) and outs[0][1] > 0
        assert torch.equal(grads[0][0], grads[1][0]) and torch.equal(grads[0][1], grads[1][1])
        if kept is None:
            kept = (outs[0], outs[0].clone())
    assert torch.equal(*kept)
