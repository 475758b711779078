"""UniformAdam and the cosine schedule (method.md §6)."""

from __future__ import annotations

import copy
import math

import numpy as np
import pytest
import torch

from holowarp.optim import LR_END, LR_START, UniformAdam, cosine_lr


def _reference_steps(p0s, grads, lr, b1, b2, eps, max_step):
    """NumPy transcription of the documented update, for a single group."""
    ps = [p.copy() for p in p0s]
    ms = [np.zeros_like(p) for p in p0s]
    vs = [np.zeros_like(p) for p in p0s]
    for t, gs in enumerate(grads, start=1):
        for i, g in enumerate(gs):
            ms[i] = b1 * ms[i] + (1 - b1) * g
            vs[i] = b2 * vs[i] + (1 - b2) * g * g
        denom = math.sqrt(max(v.max() / (1 - b2**t) for v in vs)) + eps
        for i in range(len(ps)):
            upd = lr * (ms[i] / (1 - b1**t)) / denom
            if max_step is not None:
                n = np.linalg.norm(upd, axis=-1, keepdims=True) if upd.ndim >= 2 else np.abs(upd)
                upd = upd * np.minimum(1.0, max_step / np.maximum(n, 1e-300))
            ps[i] = ps[i] - upd
    return ps


@pytest.mark.parametrize("max_step", [None, 2e-3])
def test_uniform_adam_matches_documented_update(rng, max_step):
    p0s = [rng.normal(size=(7, 3)), rng.normal(size=(5,))]
    grads = [[rng.normal(size=(7, 3)) * 10.0, rng.normal(size=(5,))] for _ in range(4)]
    params = [torch.tensor(p, requires_grad=True) for p in p0s]
    opt = UniformAdam(params, lr=1e-2, betas=(0.8, 0.95), eps=1e-8, max_step=max_step)
    for gs in grads:
        for p, g in zip(params, gs):
            p.grad = torch.tensor(g)
        opt.step()
    want = _reference_steps(p0s, grads, 1e-2, 0.8, 0.95, 1e-8, max_step)
    for p, w in zip(params, want):
        np.testing.assert_allclose(p.detach().numpy(), w, rtol=1e-12, atol=1e-14)


@pytest.mark.parametrize("dtype, max_step", [(torch.float64, None), (torch.float64, 2e-3), (torch.float32, 2e-3)])
def test_rows_take_the_warp_path_and_match_documented_update(rng, dtype, max_step):
    """One (N, 3) parameter (the geometry stage's vertices) is stepped by the Warp kernels
    (holowarp.kernels.optim); the same NumPy transcription is the oracle, from random
    positions and gradients of mixed magnitude (so the cap and the shared normaliser act)."""
    from holowarp.ops import adam

    p0 = rng.normal(size=(300, 3))
    grads = [rng.normal(size=(300, 3)) * rng.uniform(0.01, 10.0, size=(300, 1)) for _ in range(5)]
    x = torch.tensor(p0, dtype=dtype, requires_grad=True)
    opt = UniformAdam([x], lr=1e-2, betas=(0.8, 0.95), eps=1e-8, max_step=max_step)
    calls = []
    real = adam.uniform_adam_rows_
    try:
        adam.uniform_adam_rows_ = lambda *a, **k: (calls.append(1), real(*a, **k))
        for g in grads:
            x.grad = torch.tensor(g, dtype=dtype)
            opt.step()
    finally:
        adam.uniform_adam_rows_ = real
    assert len(calls) == len(grads)
    want = _reference_steps([p0], [[g] for g in grads], 1e-2, 0.8, 0.95, 1e-8, max_step)[0]
    tol = dict(rtol=1e-12, atol=1e-14) if dtype == torch.float64 else dict(rtol=2e-6, atol=2e-7)
    np.testing.assert_allclose(x.detach().double().numpy(), want, **tol)
    # the state holds what the torch path keeps (a checkpoint resumes on either path)
    st = opt.state[x]
    assert st["step"] == len(grads)
    m = np.zeros((300, 3))
    for g in grads:
        m = 0.8 * m + 0.2 * g
    np.testing.assert_allclose(st["exp_avg"].double().numpy(), m, **tol)


def test_shared_normaliser_keeps_relative_step_sizes(rng):
    # Adam would move both entries by ~lr; the shared normaliser keeps their 1000:1 ratio.
    x = torch.zeros(2, dtype=torch.float64, requires_grad=True)
    opt = UniformAdam([x], lr=0.1)
    x.grad = torch.tensor([1e-3, 1.0], dtype=torch.float64)
    opt.step()
    step = -x.detach().numpy()
    assert step[1] == pytest.approx(0.1, rel=1e-6)
    assert step[0] / step[1] == pytest.approx(1e-3, rel=1e-6)


def test_normaliser_is_shared_within_a_group_but_not_across_groups():
    a = torch.zeros(3, dtype=torch.float64, requires_grad=True)
    b = torch.zeros(3, dtype=torch.float64, requires_grad=True)
    c = torch.zeros(3, dtype=torch.float64, requires_grad=True)
    opt = UniformAdam([{"params": [a, b]}, {"params": [c]}], lr=1.0)
    a.grad = torch.full((3,), 0.01, dtype=torch.float64)
    b.grad = torch.full((3,), 1.0, dtype=torch.float64)
    c.grad = torch.full((3,), 0.01, dtype=torch.float64)
    opt.step()
    assert -a[0].item() == pytest.approx(0.01, rel=1e-6)  # normalised by b's moment
    assert -c[0].item() == pytest.approx(1.0, rel=1e-6)  # its own group


def test_max_step_caps_each_vertex_displacement_and_keeps_direction(rng):
    x0 = rng.normal(size=(50, 3))
    x = torch.tensor(x0, requires_grad=True)
    g = rng.normal(size=(50, 3)) * rng.uniform(0.01, 10.0, size=(50, 1))
    opt = UniformAdam([x], lr=1.0, max_step=0.05)
    x.grad = torch.tensor(g)
    opt.step()
    d = x0 - x.detach().numpy()
    n = np.linalg.norm(d, axis=1)
    assert n.max() <= 0.05 * (1 + 1e-12)
    cos = (d * g).sum(1) / (n * np.linalg.norm(g, axis=1))
    np.testing.assert_allclose(cos, 1.0, atol=1e-12)
    free = UniformAdam([torch.zeros(1, requires_grad=True)], lr=1.0)  # no cap: no clipping
    assert free.param_groups[0]["max_step"] is None


def test_uniform_adam_minimises_a_quadratic(rng):
    target = torch.tensor(rng.normal(size=(20, 3)))
    x = torch.zeros((20, 3), dtype=torch.float64, requires_grad=True)
    opt = UniformAdam([x], lr=0.05)
    start = ((x - target) ** 2).sum().item()
    for _ in range(400):
        opt.zero_grad()
        loss = ((x - target) ** 2).sum()
        loss.backward()
        opt.step()
    assert ((x - target) ** 2).sum().item() < 1e-3 * start


def test_state_dict_round_trip_continues_identically(rng):
    g = [torch.tensor(rng.normal(size=(4, 3))) for _ in range(6)]
    x1 = torch.tensor(rng.normal(size=(4, 3)), requires_grad=True)
    o1 = UniformAdam([x1], lr=1e-2, max_step=1e-2)
    for k in range(3):
        x1.grad = g[k]
        o1.step()
    x2 = x1.detach().clone().requires_grad_(True)
    o2 = UniformAdam([x2], lr=1e-2, max_step=1e-2)
    o2.load_state_dict(copy.deepcopy(o1.state_dict()))
    for k in range(3, 6):
        x1.grad = g[k]
        x2.grad = g[k].clone()
        o1.step()
        o2.step()
    assert torch.equal(x1, x2)


def test_cosine_lr_runs_from_start_to_end_monotonically():
    total = 1000
    lrs = [cosine_lr(t, total) for t in range(total + 1)]
    assert lrs[0] == pytest.approx(LR_START) and lrs[-1] == pytest.approx(LR_END)
    assert LR_START == 2e-4 and LR_END == 1e-4  # method.md §6
    assert lrs[total // 2] == pytest.approx(0.5 * (LR_START + LR_END))
    assert all(a >= b for a, b in zip(lrs, lrs[1:]))
    assert cosine_lr(5 * total, total) == pytest.approx(LR_END)


@pytest.mark.parametrize(
    "kwargs", [dict(lr=-1.0), dict(betas=(1.0, 0.9)), dict(eps=-1.0), dict(max_step=0.0)]
)
def test_bad_optimiser_arguments_are_rejected(kwargs):
    with pytest.raises(ValueError):
        UniformAdam([torch.zeros(1, requires_grad=True)], **kwargs)
    with pytest.raises(ValueError):
        cosine_lr(0, 0)
