"""Autograd wrappers of the tetrahedral energy kernels (method.md §5, §6).

Each function takes torch tensors and returns a differentiable torch result computed by the
Warp kernels in ``holowarp.kernels.tet_energy`` with hand-written backward passes. float32
and float64 inputs are both supported (the float64 path is what the finite-difference tests
use). The domain API with rest-shape capture and weights is ``holowarp.energies``;
``holowarp.ops.tet_energy_ref`` is the dense torch reference the tests compare against.

Shapes: ``x`` (N, 3) vertex positions (metres); ``tets`` (M, 4) int32; ``dm_inv`` (M, 3, 3)
inverse rest edge matrices; ``adjacency`` (M, 4) int32 face neighbours (-1 on the boundary);
``weights`` (M,).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import torch
import warp as wp

from holowarp.kernels import tet_energy as K_
from holowarp.ops._warp import FRESH, to_wp, torch_stream, wp_device

__all__ = [
    "HCTopology",
    "hc_topology",
    "deformation_gradients",
    "biharmonic_energy",
    "inversion_penalty",
    "tet_energies",
    "prepare_tet_energies",
    "prepare_hc_laplacian",
    "signed_volumes",
    "tet_mean",
    "revert_floor_crossings",
    "vertex_tets",
    "hc_targets",
    "hc_energy",
    "hc_laplacian_energy",
    "eikonal_loss",
    "smoothness_loss",
    "phi_edge_losses",
]

_TYPES = {
    torch.float32: (wp.float32, wp.vec3f, wp.mat33f),
    torch.float64: (wp.float64, wp.vec3d, wp.mat33d),
}



def _types(t: torch.Tensor):
    try:
        return _TYPES[t.dtype]
    except KeyError:
        raise TypeError(f"tet energies support float32 and float64 tensors, got {t.dtype}") from None


#: The concrete overload of each generic (``Any``-typed) kernel per argument signature.
#: ``wp.launch`` infers it from the arguments on every call (about 14 us of the 25 us a
#: small launch costs on the CPU); the geometry step makes about a dozen such launches.
_OVERLOADS: dict = {}


def _launch(kernel, dim, inputs=(), outputs=(), device=None, *, cache=FRESH, site: str = ""):
    """``wp.launch`` of a generic tet kernel, its overload resolved once per signature;
    through ``cache`` (:class:`holowarp.ops._warp.StepCache`) at call site ``site``."""
    args = (*inputs, *outputs)
    key = (kernel, *(a.dtype if isinstance(a, wp.array) else type(a) for a in args))
    k = _OVERLOADS.get(key)
    if k is None:
        k = _OVERLOADS[key] = kernel.get_overload(kernel.infer_argument_types(list(args)))
    cache.launch(site, k, dim, inputs, outputs, device)


def _vec(t, V):
    return to_wp(t, V)


def _mat(t, M):
    return to_wp(t, M)


def _i(t, dtype=None):
    return to_wp(t.to(torch.int32), dtype)


def _check_x(x: torch.Tensor, name: str = "x"):
    if not isinstance(x, torch.Tensor) or x.ndim != 2 or x.shape[1] != 3:
        raise ValueError(f"{name} must be a (N, 3) float tensor, got {getattr(x, 'shape', type(x))}")
    _types(x)


# --- deformation gradients -------------------------------------------------------------


class _DeformationGradient(torch.autograd.Function):
    @staticmethod
    def forward(ctx, x, tets, dm_inv):
        T, V, M = _types(x)
        dev = wp_device(x)
        F = torch.empty((tets.shape[0], 3, 3), dtype=x.dtype, device=x.device)
        with torch_stream(x):
            _launch(
                K_.deformation_gradient_kernel,
                dim=tets.shape[0],
                inputs=[_vec(x, V), _i(tets, wp.vec4i), _mat(dm_inv, M)],
                outputs=[_mat(F, M)],
                device=dev,
            )
        ctx.save_for_backward(tets, dm_inv)
        ctx.num_vertices = x.shape[0]
        return F

    @staticmethod
    def backward(ctx, grad_F):
        tets, dm_inv = ctx.saved_tensors
        T, V, M = _types(dm_inv)
        grad_x = torch.zeros((ctx.num_vertices, 3), dtype=dm_inv.dtype, device=dm_inv.device)
        with torch_stream(dm_inv):
            _launch(
                K_.deformation_gradient_backward_kernel,
                dim=tets.shape[0],
                inputs=[_i(tets, wp.vec4i), _mat(dm_inv, M), _mat(grad_F.to(dm_inv.dtype).contiguous(), M)],
                outputs=[_vec(grad_x, V)],
                device=wp_device(dm_inv),
            )
        return grad_x, None, None


def deformation_gradients(x: torch.Tensor, tets: torch.Tensor, dm_inv: torch.Tensor) -> torch.Tensor:
    """Per-tet deformation gradients ``F = Ds Dm^-1`` (M, 3, 3), differentiable in ``x``.

    ``Ds = [x1 - x0, x2 - x0, x3 - x0]`` (columns) of each tet in the current positions.
    """
    _check_x(x)
    return _DeformationGradient.apply(x.contiguous(), tets.contiguous(), dm_inv.to(x.dtype).contiguous())


# --- weighted bi-harmonic ---------------------------------------------------------------


class _Biharmonic(torch.autograd.Function):
    @staticmethod
    def forward(ctx, x, tets, dm_inv, adjacency, weights):
        T, V, M = _types(x)
        dev = wp_device(x)
        m = tets.shape[0]
        F = torch.empty((m, 3, 3), dtype=x.dtype, device=x.device)
        LF = torch.empty_like(F)
        energy = torch.empty(m, dtype=x.dtype, device=x.device)
        tets_wp, adj_wp = _i(tets, wp.vec4i), _i(adjacency, wp.vec4i)
        with torch_stream(x):
            _launch(
                K_.deformation_gradient_kernel, dim=m,
                inputs=[_vec(x, V), tets_wp, _mat(dm_inv, M)], outputs=[_mat(F, M)], device=dev,
            )
            _launch(
                K_.biharmonic_forward_kernel, dim=m,
                inputs=[_mat(F, M), adj_wp, to_wp(weights)], outputs=[_mat(LF, M), to_wp(energy)], device=dev,
            )
        ctx.save_for_backward(tets, adjacency, LF, dm_inv)  # LF holds w (L F)
        ctx.num_vertices = x.shape[0]
        return energy.sum()

    @staticmethod
    def backward(ctx, grad_E):
        tets, adjacency, LF, dm_inv = ctx.saved_tensors
        T, V, M = _types(LF)
        grad_x = torch.zeros((ctx.num_vertices, 3), dtype=LF.dtype, device=LF.device)
        g = grad_E.reshape(1).to(LF.dtype).contiguous()
        with torch_stream(LF):
            _launch(
                K_.biharmonic_backward_kernel,
                dim=tets.shape[0],
                inputs=[_i(tets, wp.vec4i), _i(adjacency, wp.vec4i), _mat(LF, M), _mat(dm_inv, M), to_wp(g)],
                outputs=[_vec(grad_x, V)],
                device=wp_device(LF),
            )
        return grad_x, None, None, None, None


def biharmonic_energy(x, tets, dm_inv, adjacency, weights) -> torch.Tensor:
    """Weighted bi-harmonic energy ``sum_e w_e ||(L F)_e||_F^2`` (method.md §6), a scalar.

    ``L`` is the tet face-adjacency graph Laplacian given by ``adjacency``:
    ``(L F)_e = deg_e F_e - sum_{e' ~ e} F_e'``. A rigid motion gives the same ``F`` on every
    tet, so both the energy and its gradient vanish.
    """
    _check_x(x)
    return _Biharmonic.apply(
        x.contiguous(), tets.contiguous(), dm_inv.to(x.dtype).contiguous(),
        adjacency.contiguous(), weights.to(x.dtype).contiguous(),
    )


# --- inversion penalty -------------------------------------------------------------------


def _fused(value: torch.Tensor, pairs):
    """Attach precomputed gradients to ``value``.

    pairs: [(input tensor, d value / d input or None)]. Used for energies whose value and
    gradient come out of one fused kernel pass; backward only rescales by dLoss/dvalue.
    """
    grads = [g for _, g in pairs]
    inputs = [t for t, _ in pairs]
    return _FusedEnergy.apply(value, len(pairs), *grads, *inputs)


class _FusedEnergy(torch.autograd.Function):
    @staticmethod
    def forward(ctx, value, n, *rest):
        grads = rest[:n]
        ctx.n = n
        ctx.has = [g is not None for g in grads]
        ctx.save_for_backward(*[g for g in grads if g is not None])
        return value.clone()

    @staticmethod
    def backward(ctx, grad_E):
        saved = iter(ctx.saved_tensors)
        grads = [next(saved) * grad_E if h else None for h in ctx.has]
        return (None, None, *(None for _ in range(ctx.n)), *grads)


def inversion_penalty(x, tets, dm_inv, p: float = 2.0) -> torch.Tensor:
    """Non-inversion penalty ``sum_e max(-det F_e, 0)^p`` (method.md §6), a scalar.

    A SUM over tets (not a mean), so one inverted tet costs the same whatever the mesh
    size. ``p >= 1``; ``p > 1`` makes it continuously differentiable at ``det F = 0``.
    """
    _check_x(x)
    p = float(p)
    if not p >= 1.0:
        raise ValueError(f"inversion_penalty: p must be >= 1, got {p}")
    T, V, M = _types(x)
    x = x.contiguous()
    m = tets.shape[0]
    energy = torch.empty(m, dtype=x.dtype, device=x.device)
    need = x.requires_grad and torch.is_grad_enabled()
    grad_x = torch.zeros_like(x) if need else torch.zeros((1, 3), dtype=x.dtype, device=x.device)
    with torch_stream(x):
        _launch(
            K_.inversion_penalty_kernel,
            dim=m,
            inputs=[_vec(x, V), _i(tets.contiguous(), wp.vec4i), _mat(dm_inv.to(x.dtype).contiguous(), M), T(p), int(need)],
            outputs=[to_wp(energy), _vec(grad_x, V)],
            device=wp_device(x),
        )
    value = energy.sum()
    if not need:
        return value
    return _fused(value, [(x, grad_x)])


# --- fused pass: bi-harmonic + inversion from one F ---------------------------------------


def _tet_pass(x, tets, dm_inv, adjacency, weights, p: float, need: bool, c):
    """The kernels of :func:`tet_energies` into ``c``'s buffers ``te.*``: F, w (L F), the
    per-tet energies and, when ``need``, the gradients of both sums (the bi-harmonic one
    seeded with 1: the backward pass only scales them, so all the work can run ahead of
    it). Returns ``(bi-harmonic gradient, inversion gradient, bi-harmonic energies,
    inversion energies)``; the gradients are (1, 3) placeholders without ``need``."""
    T, V, M = _types(x)
    dev = wp_device(x)
    m = tets.shape[0]
    F = c.buffer("te.F", (m, 3, 3), x.dtype, x.device)
    LF = c.buffer("te.LF", (m, 3, 3), x.dtype, x.device)
    e_bih = c.buffer("te.e_bih", (m,), x.dtype, x.device)
    e_inv = c.buffer("te.e_inv", (m,), x.dtype, x.device)
    g_shape = x.shape if need else (1, 3)
    g_inv = c.buffer("te.g_inv", g_shape, x.dtype, x.device, zero=True)
    g_bih = c.buffer("te.g_bih", g_shape, x.dtype, x.device, zero=True)
    tets_wp, F_wp, LF_wp = c.view("te.tets", tets, wp.vec4i), c.view("te.F", F, M), c.view("te.LF", LF, M)
    adj_wp, dm_wp = c.view("te.adjacency", adjacency, wp.vec4i), c.view("te.dm_inv", dm_inv, M)
    with torch_stream(x):
        _launch(K_.tet_pass_kernel, dim=m, inputs=[c.view("te.x", x.detach(), V), tets_wp, dm_wp, T(p), int(need)],
                outputs=[F_wp, c.view("te.e_inv", e_inv), c.view("te.g_inv", g_inv, V)], device=dev,
                cache=c, site="te.tet_pass")
        _launch(K_.biharmonic_forward_kernel, dim=m, inputs=[F_wp, adj_wp, c.view("te.weights", weights)],
                outputs=[LF_wp, c.view("te.e_bih", e_bih)], device=dev, cache=c, site="te.biharmonic_forward")
        if need:
            one = c.buffer("te.one", (1,), x.dtype, x.device).fill_(1.0)
            _launch(K_.biharmonic_backward_kernel, dim=m, inputs=[tets_wp, adj_wp, LF_wp, dm_wp, c.view("te.one", one)],
                    outputs=[c.view("te.g_bih", g_bih, V)], device=dev, cache=c, site="te.biharmonic_backward")
    return g_bih, g_inv, e_bih, e_inv


def _pass_key(x, tets, p: float, need: bool):
    return (x.data_ptr(), tuple(x.shape), x.dtype, tets.data_ptr(), tets.shape[0], float(p), bool(need))


class _TetEnergies(torch.autograd.Function):
    @staticmethod
    def forward(ctx, x, tets, dm_inv, adjacency, weights, p, cache):
        c = cache
        need = bool(ctx.needs_input_grad[0])  # grad mode is off inside forward
        # A pass that prepare_tet_energies ran for these arrays (the geometry step runs it on
        # another thread while the rasteriser works) is taken as it is, once.
        done = c.take_ahead("te.pass", _pass_key(x, tets, p, need))
        g_bih, g_inv, e_bih, e_inv = done or _tet_pass(x, tets, dm_inv, adjacency, weights, p, need, c)
        ctx.save_for_backward(g_bih, g_inv)
        return e_bih.sum(), e_inv.sum()

    @staticmethod
    def backward(ctx, g_bih_out, g_inv_out):
        # Both gradients were computed with the energies; the chain rule only scales them.
        g_bih, g_inv = ctx.saved_tensors
        grad = None
        for g, scale in ((g_bih, g_bih_out), (g_inv, g_inv_out)):
            if scale is not None:
                grad = g * scale if grad is None else grad + g * scale
        return grad, None, None, None, None, None, None


def tet_energies(x, tets, dm_inv, adjacency, weights, p: float = 2.0, *, cache=FRESH):
    """``(biharmonic_energy(...), inversion_penalty(..., p))`` from one pass over the tets:
    F and det F are computed once (kernel ``tet_pass_kernel``), the bi-harmonic Laplacian
    reads that F. When ``x`` wants a gradient, both sums' gradients are computed with the
    values (the bi-harmonic one seeded with 1, kernel ``biharmonic_backward_kernel``) and
    the backward pass only scales them. Same values and gradients as the two functions
    called separately.

    ``cache``: a :class:`holowarp.ops._warp.StepCache` for a caller that repeats this on the
    same arrays (the geometry step); its buffers hold what the backward pass reads, so run
    the backward before the next forward through the same cache."""
    _check_x(x)
    p = float(p)
    if not p >= 1.0:
        raise ValueError(f"tet_energies: p must be >= 1, got {p}")
    return _TetEnergies.apply(x.contiguous(), _int32(tets), dm_inv.to(x.dtype).contiguous(),
                              _int32(adjacency), weights.to(x.dtype).contiguous(), p, cache)


def prepare_tet_energies(x, tets, dm_inv, adjacency, weights, p: float = 2.0, *, cache, need: bool = True) -> None:
    """Run :func:`tet_energies`' kernels (the energies and their gradients) now, into
    ``cache`` (a :class:`holowarp.ops._warp.StepCache`), so that the next
    :func:`tet_energies` call with the same arrays, ``p`` and gradient need only sums
    their results and its backward pass only scales the gradients: the geometry
    step runs this on a second thread while the rasteriser runs. No autograd here: the
    graph is built by that call, on the caller's thread, in the order it always was. The
    arguments are those of :func:`tet_energies` (converted the same way); ``need``: whether
    that call will want the gradient (``x.requires_grad`` with grad mode on)."""
    _check_x(x)
    if not hasattr(cache, "put_ahead"):
        raise TypeError("prepare_tet_energies: cache must be a holowarp.ops._warp.StepCache")
    x, tets = x.contiguous(), _int32(tets)
    with torch.no_grad():
        done = _tet_pass(x, tets, dm_inv.to(x.dtype).contiguous(), _int32(adjacency),
                         weights.to(x.dtype).contiguous(), float(p), bool(need), cache)
    cache.put_ahead("te.pass", _pass_key(x, tets, p, need), done)


def _int32(t: torch.Tensor) -> torch.Tensor:
    return t.to(torch.int32).contiguous()


# --- per-tet means (the surfels' centres and field opacities) -----------------------------


class _TetMean(torch.autograd.Function):
    @staticmethod
    def forward(ctx, values, tets):
        T, V, M = _types(values)
        W = V if values.ndim == 2 else None
        out = torch.empty((tets.shape[0], *values.shape[1:]), dtype=values.dtype, device=values.device)
        with torch_stream(values):
            _launch(K_.tet_mean_kernel, dim=tets.shape[0], inputs=[to_wp(values, W), _i(tets, wp.vec4i), T(0.25)],
                    outputs=[to_wp(out, W)], device=wp_device(values))
        ctx.save_for_backward(tets)
        ctx.shape = values.shape
        return out

    @staticmethod
    def backward(ctx, grad):
        (tets,) = ctx.saved_tensors
        T, V, M = _types(grad)
        W = V if grad.ndim == 2 else None
        grad_values = torch.zeros(ctx.shape, dtype=grad.dtype, device=grad.device)
        with torch_stream(grad):
            _launch(K_.tet_mean_backward_kernel, dim=tets.shape[0],
                    inputs=[to_wp(grad.contiguous(), W), _i(tets, wp.vec4i), T(0.25)], outputs=[to_wp(grad_values, W)],
                    device=wp_device(grad))
        return grad_values, None


def tet_mean(values: torch.Tensor, tets: torch.Tensor) -> torch.Tensor:
    """``values[tets].mean(dim=1)``, differentiable in ``values``: the mean over each tet's
    four vertices of per-vertex ``values`` (N, 3) positions or (N,) scalars, float32 or
    float64, giving (M, 3) or (M,) for ``tets`` (M, 4) int32.

    One Warp pass each way instead of torch's gather, sum, divide and scatter-add (forward
    and backward of the surfel model's centres and field opacities at 21k tets on the CPU:
    3.7 ms in torch, 0.7 ms here); the same rounding: the four values are summed in
    vertex order and scaled by 1/4, and the backward adds each tet's share to its vertices
    tet by tet (on the CPU in order, so bit for bit the torch result)."""
    if not isinstance(values, torch.Tensor) or values.ndim not in (1, 2) or (values.ndim == 2 and values.shape[1] != 3):
        got = getattr(values, "shape", type(values))
        raise ValueError(f"tet_mean: values must be a (N, 3) or (N,) float tensor, got {got}")
    _types(values)
    if tets.ndim != 2 or tets.shape[1] != 4 or tets.dtype != torch.int32:
        raise ValueError(f"tet_mean: tets must be a (M, 4) int32 tensor, got {tuple(tets.shape)} {tets.dtype}")
    return _TetMean.apply(values.contiguous(), tets.contiguous())


def signed_volumes(x: torch.Tensor, tets: torch.Tensor) -> torch.Tensor:
    """Signed tet volumes (M,) ``(b - a) . ((c - a) x (d - a)) / 6`` of positions ``x``
    (N, 3) float32/float64; not differentiable (a check, not an energy)."""
    _check_x(x)
    T, V, M = _types(x)
    x = x.detach().contiguous()
    vol = torch.empty(tets.shape[0], dtype=x.dtype, device=x.device)
    if tets.shape[0]:
        with torch_stream(x):
            _launch(K_.signed_volume_kernel, dim=tets.shape[0], inputs=[_vec(x, V), _i(tets.contiguous(), wp.vec4i)],
                   outputs=[to_wp(vol)], device=wp_device(x))
    return vol


def vertex_tets(tets: torch.Tensor, num_vertices: int) -> tuple[torch.Tensor, torch.Tensor]:
    """The tets of each vertex as CSR: ``offsets`` (N + 1,) int32 and ``incident`` (4 M,)
    int32 tet ids, vertex ``v``'s in ``incident[offsets[v]:offsets[v + 1]]`` in increasing
    order; for :func:`revert_floor_crossings` (build it once per mesh)."""
    flat = tets.reshape(-1).long()
    order = torch.argsort(flat, stable=True)
    counts = torch.bincount(flat, minlength=int(num_vertices))
    offsets = torch.zeros(int(num_vertices) + 1, dtype=torch.int64, device=tets.device)
    offsets[1:] = torch.cumsum(counts, 0)
    return offsets.to(torch.int32), (order // 4).to(torch.int32)


def revert_floor_crossings(x_new: torch.Tensor, x_old: torch.Tensor, tets: torch.Tensor, floor: torch.Tensor,
                           *, max_rounds: int = 20, incidence=None, cache=FRESH) -> torch.Tensor:
    """Put back, in place, the four vertices of every tet whose signed volume was above its
    ``floor`` (M,) at ``x_old`` (N, 3) and is not at ``x_new`` (N, 3; NaN counts as not);
    repeated until no tet crosses (putting one tet back can push a neighbour under), with a
    full revert (``x_new = x_old``) after ``max_rounds``.

    The first round is one Warp pass over all tets computing both volumes (kernel
    ``volume_floor_crossing_kernel``); with ``incidence`` (:func:`vertex_tets` of ``tets``)
    each later round checks only the tets of the vertices the round before put back
    (``incident_floor_crossing_kernel``, the same tets found: no other tet's volume
    changed), else every tet again. Each round reads its crossing counter once; a round
    that finds crossings adds one pass putting their vertices back. Returns the number of
    vertices put back as a 0-dim int tensor (all N after a full revert).

    ``cache``: a :class:`holowarp.ops._warp.StepCache` for a caller that repeats this on the
    same arrays (the geometry step: the same ``x_new``, ``x_old``, ``tets`` and ``floor``)."""
    _check_x(x_new, "x_new")
    _check_x(x_old, "x_old")
    T, V, M = _types(x_new)
    if not (x_new.is_contiguous() and x_old.dtype == x_new.dtype and floor.shape == (tets.shape[0],)):
        raise ValueError("revert_floor_crossings: x_new must be contiguous (it is written in place), x_old of its "
                         f"dtype, floor (M,) = ({tets.shape[0]},); got floor {tuple(floor.shape)}")
    dev, c = wp_device(x_new), cache
    m = tets.shape[0]
    stamp = c.buffer("rv.stamp", (x_new.shape[0],), torch.int32, x_new.device, zero=True)
    if m == 0:
        return stamp.sum()
    w_new, w_old = c.view("rv.x_new", x_new, V), c.view("rv.x_old", x_old.detach(), V)
    w_tets = c.view("rv.tets", _int32(tets), wp.vec4i)
    w_floor = c.view("rv.floor", floor.to(x_new.dtype))
    bad = c.buffer("rv.bad", (m,), torch.int32, x_new.device)
    count = c.buffer("rv.count", (1,), torch.int32, x_new.device, zero=True)
    w_bad, w_count, w_stamp = c.view("rv.bad", bad), c.view("rv.count", count), c.view("rv.stamp", stamp)
    local = None if incidence is None else (c.view("rv.offsets", incidence[0]), c.view("rv.incident", incidence[1]))
    with torch_stream(x_new):
        for r in range(1, max_rounds + 1):
            if r == 1 or local is None:
                _launch(K_.volume_floor_crossing_kernel, dim=m, inputs=[w_new, w_old, w_tets, w_floor],
                        outputs=[w_bad, w_count], device=dev, cache=c, site="rv.all")
            else:
                _launch(K_.incident_floor_crossing_kernel, dim=x_new.shape[0],
                        inputs=[w_new, w_old, w_tets, w_floor, *local, w_stamp, r - 1], outputs=[w_bad, w_count],
                        device=dev, cache=c, site="rv.incident")
            if int(count[0]) == 0:
                return (stamp > 0).sum()
            count.zero_()
            _launch(K_.revert_tet_vertices_kernel, dim=m, inputs=[w_bad, w_tets, w_old, r], outputs=[w_new, w_stamp],
                    device=dev, cache=c, site="rv.revert")
    x_new.copy_(x_old)
    return torch.tensor(x_new.shape[0], device=x_new.device)


# --- HC-Laplacian -----------------------------------------------------------------------


@dataclass(frozen=True)
class HCTopology:
    """Boundary-surface connectivity used by the HC-Laplacian energy.

    Attributes:
        surf_ids: (S,) int32 global ids of the surface vertices (sorted).
        nbr_offsets: (S + 1,) int32 CSR offsets into ``nbr_ids``.
        nbr_ids: (nnz,) int32 local ids of each surface vertex's umbrella neighbours
            (vertices sharing a boundary edge).
        faces_global: (B, 3) int32 boundary faces in global ids (outward winding).
        faces_local: (B, 3) int32 the same faces in local surface ids.
    """

    surf_ids: torch.Tensor
    nbr_offsets: torch.Tensor
    nbr_ids: torch.Tensor
    faces_global: torch.Tensor
    faces_local: torch.Tensor
    _views: dict = field(default_factory=dict, init=False, repr=False, compare=False)

    @property
    def num_surface_vertices(self) -> int:
        return int(self.surf_ids.shape[0])

    def views(self) -> tuple:
        """Warp views ``(surf_ids, nbr_offsets, nbr_ids, faces_global, faces_local)`` of the
        index arrays (the faces as ``vec3i``), made once: a geometry step uses them on every
        step, and each view costs a few microseconds of Python."""
        v = self._views.get("all")
        if v is None:
            v = self._views["all"] = (_i(self.surf_ids), _i(self.nbr_offsets), _i(self.nbr_ids),
                                      _i(self.faces_global, wp.vec3i), _i(self.faces_local, wp.vec3i))
        return v


def hc_topology(boundary_faces, *, device=None) -> HCTopology:
    """Build :class:`HCTopology` from boundary faces (B, 3) (outward-wound, global ids)."""
    f = boundary_faces
    if isinstance(f, torch.Tensor):
        device = f.device if device is None else device
        f = f.detach().cpu().numpy()
    f = np.asarray(f)
    if f.ndim != 2 or f.shape[1] != 3 or not np.issubdtype(f.dtype, np.integer):
        raise ValueError(f"boundary_faces must be a (B, 3) integer array, got {f.shape} {f.dtype}")
    if f.size and f.min() < 0:
        raise ValueError("boundary_faces has negative vertex ids")
    f = f.astype(np.int64)
    surf, local = np.unique(f.reshape(-1), return_inverse=True)
    local = local.reshape(-1, 3)
    e = np.concatenate([local[:, [0, 1]], local[:, [1, 2]], local[:, [2, 0]]])
    e = np.concatenate([e, e[:, ::-1]])
    e = np.unique(e, axis=0)  # directed, each undirected edge both ways, sorted by source
    counts = np.bincount(e[:, 0], minlength=len(surf)) if len(e) else np.zeros(len(surf), np.int64)
    offsets = np.concatenate([[0], np.cumsum(counts)]).astype(np.int32)
    dev = torch.device("cpu") if device is None else torch.device(device)

    def T(a):
        return torch.as_tensor(np.ascontiguousarray(a, dtype=np.int32), device=dev)

    return HCTopology(
        surf_ids=T(surf), nbr_offsets=T(offsets), nbr_ids=T(e[:, 1] if len(e) else np.zeros(0)),
        faces_global=T(f.reshape(-1, 3)), faces_local=T(local),
    )


@torch.no_grad()
def hc_targets(x, topo: HCTopology, *, x_orig=None, alpha: float = 0.0, beta: float = 0.5):
    """HC-Laplacian targets and outward unit normals of the surface vertices (no gradient).

    Vollmer et al. 1999, with ``q = x`` the current and ``o = x_orig`` the original positions:
    ``p_i = mean_{j in N(i)} q_j``, ``b_i = p_i - (alpha o_i + (1 - alpha) q_i)``,
    ``target_i = p_i - (beta b_i + (1 - beta) mean_{j in N(i)} b_j)``. Normals are the
    normalised sums of the (area-weighted) boundary face normals around each vertex.

    Returns:
        target (S, 3), normal (S, 3) in ``x``'s dtype, ordered as ``topo.surf_ids``.
    """
    _check_x(x)
    T, V, M = _types(x)
    dev = wp_device(x)
    S = topo.num_surface_vertices
    x = x.detach().contiguous()
    xo = x if x_orig is None else x_orig.detach().to(x.dtype).contiguous()
    p = torch.empty((S, 3), dtype=x.dtype, device=x.device)
    b = torch.empty_like(p)
    nacc = torch.zeros_like(p)
    target = torch.empty_like(p)
    normal = torch.empty_like(p)
    p_wp, b_wp, n_wp, _ = _hc_umbrella(x, xo, topo, alpha, p, b, nacc)
    sid, off, nid, _, _ = topo.views()
    with torch_stream(x):
        _launch(K_.hc_target_kernel, dim=S, inputs=[p_wp, b_wp, off, nid, n_wp, T(beta)],
               outputs=[_vec(target, V), _vec(normal, V)], device=dev)
    return target, normal


def _hc_umbrella(x, xo, topo: HCTopology, alpha: float, p, b, nacc, *, cache=FRESH):
    """The first two passes of the HC targets: umbrella averages ``p`` and corrections ``b``
    (S, 3), and the area-weighted normal sums ``nacc`` (S, 3, zero on entry); returns their
    Warp views and that of ``x``."""
    T, V, M = _types(x)
    dev, c = wp_device(x), cache
    sid, off, nid, fg, fl = topo.views()
    x_wp = c.view("hc.x", x, V)
    p_wp, b_wp, n_wp = c.view("hc.p", p, V), c.view("hc.b", b, V), c.view("hc.nacc", nacc, V)
    with torch_stream(x):
        _launch(K_.hc_umbrella_kernel, dim=topo.num_surface_vertices,
                inputs=[x_wp, c.view("hc.xo", xo, V), sid, off, nid, T(alpha)], outputs=[p_wp, b_wp], device=dev,
                cache=c, site="hc.umbrella")
        _launch(K_.hc_face_normal_kernel, dim=topo.faces_global.shape[0], inputs=[x_wp, fg, fl], outputs=[n_wp],
                device=dev, cache=c, site="hc.face_normal")
    return p_wp, b_wp, n_wp, x_wp


def _hc_pass(x, xo, topo: HCTopology, lam_cond: float, alpha: float, beta: float, need: bool, c):
    """The kernels of :func:`hc_laplacian_energy` into ``c``'s buffers ``hc.*``; returns the
    per-vertex energies (S,) and the gradient (N, 3; a (1, 3) placeholder without ``need``)."""
    T, V, M = _types(x)
    dev = wp_device(x)
    S = topo.num_surface_vertices
    p = c.buffer("hc.p", (S, 3), x.dtype, x.device)
    b = c.buffer("hc.b", (S, 3), x.dtype, x.device)
    nacc = c.buffer("hc.nacc", (S, 3), x.dtype, x.device, zero=True)
    energy = c.buffer("hc.energy", (S,), x.dtype, x.device)
    grad_x = c.buffer("hc.grad_x", x.shape if need else (1, 3), x.dtype, x.device, zero=True)
    with torch.no_grad():
        p_wp, b_wp, n_wp, x_wp = _hc_umbrella(x, xo, topo, alpha, p, b, nacc, cache=c)
        sid, off, nid, _, _ = topo.views()
        with torch_stream(x):
            _launch(K_.hc_target_energy_kernel, dim=S,
                    inputs=[p_wp, b_wp, off, nid, n_wp, T(beta), x_wp, sid, T(float(lam_cond)), int(need)],
                    outputs=[c.view("hc.energy", energy), c.view("hc.grad_x", grad_x, V)], device=dev,
                    cache=c, site="hc.target_energy")
    return energy, grad_x


def _hc_inputs(x, x_orig):
    xd = x.detach().contiguous()
    return xd, (xd if x_orig is None else x_orig.detach().to(x.dtype).contiguous())


def _hc_key(xd, xo, topo, lam_cond, alpha, beta, need):
    return (xd.data_ptr(), tuple(xd.shape), xd.dtype, xo.data_ptr(), id(topo), float(lam_cond), float(alpha),
            float(beta), bool(need))


def hc_laplacian_energy(x, topo: HCTopology, lam_cond: float, *, x_orig=None, alpha: float = 0.0,
                        beta: float = 0.5, cache=FRESH) -> torch.Tensor:
    """:func:`hc_energy` of the targets and normals :func:`hc_targets` gives, the last pass of
    each fused (kernel ``hc_target_energy_kernel``): three launches instead of four, and no
    target or normal arrays. The same value and gradient, bit for bit (tests/test_tet_energy.py).

    ``cache``: a :class:`holowarp.ops._warp.StepCache` for a caller that repeats this on the
    same arrays; the gradient the result carries lives in its buffer until the next call.
    Work :func:`prepare_hc_laplacian` ran ahead into it for the same inputs is taken, once."""
    _check_x(x)
    xd, xo = _hc_inputs(x, x_orig)
    need = x.requires_grad and torch.is_grad_enabled()
    done = cache.take_ahead("hc.pass", _hc_key(xd, xo, topo, lam_cond, alpha, beta, need))
    energy, grad_x = done or _hc_pass(xd, xo, topo, lam_cond, alpha, beta, need, cache)
    value = energy.sum()
    if not need:
        return value
    return _fused(value, [(x.contiguous(), grad_x)])


def prepare_hc_laplacian(x, topo: HCTopology, lam_cond: float, *, x_orig=None, alpha: float = 0.0,
                         beta: float = 0.5, cache, need: bool = True) -> None:
    """Run :func:`hc_laplacian_energy`'s kernels now, into ``cache`` (a
    :class:`holowarp.ops._warp.StepCache`), for its next call with the same inputs and
    gradient need to take (see :func:`prepare_tet_energies`, whose thread it shares)."""
    _check_x(x)
    if not hasattr(cache, "put_ahead"):
        raise TypeError("prepare_hc_laplacian: cache must be a holowarp.ops._warp.StepCache")
    xd, xo = _hc_inputs(x, x_orig)
    done = _hc_pass(xd, xo, topo, lam_cond, alpha, beta, need, cache)
    cache.put_ahead("hc.pass", _hc_key(xd, xo, topo, lam_cond, alpha, beta, need), done)


def hc_energy(x, topo: HCTopology, target, normal, lam_cond: float) -> torch.Tensor:
    """Two-stage HC-Laplacian energy (method.md §6) for given targets and normals, a scalar.

    ``d_i = target_i - x_i`` (the move that would bring vertex i onto its HC target),
    ``d_n = d_i . n_i`` with ``n_i`` the OUTWARD normal, ``d_t = d_i - d_n n_i``;
    ``E = sum_S ||d_t||^2 + lam_cond min(d_n, 0)^2 + max(d_n, 0)^2``.
    So ``max(d_n, 0)`` is the outward part: a vertex lying inside its target (a dent, a
    concavity) is always pulled out, while a vertex outside its target (a bump) is pulled
    in only when ``lam_cond > 0``. Stage 1 (``lam_cond = 0``) pushes concavities out without
    shrinking the surface; stage 2 (``lam_cond = 1``) smooths both ways.

    ``target`` and ``normal`` are constants (stop-gradient, e.g. from :func:`hc_targets`):
    the gradient is ``-2 (d_t + (lam_cond min(d_n,0) + max(d_n,0)) n)`` per vertex, i.e. the
    gradient flow moves each vertex towards its HC target, as Vollmer's smoothing step does.
    """
    _check_x(x)
    T, V, M = _types(x)
    x = x.contiguous()
    S = topo.num_surface_vertices
    energy = torch.empty(S, dtype=x.dtype, device=x.device)
    need = x.requires_grad and torch.is_grad_enabled()
    grad_x = torch.zeros_like(x) if need else torch.zeros((1, 3), dtype=x.dtype, device=x.device)
    with torch_stream(x):
        _launch(
            K_.hc_energy_kernel,
            dim=S,
            inputs=[_vec(x, V), topo.views()[0], _vec(target.detach().to(x.dtype).contiguous(), V),
                    _vec(normal.detach().to(x.dtype).contiguous(), V), T(float(lam_cond)), int(need)],
            outputs=[to_wp(energy), _vec(grad_x, V)],
            device=wp_device(x),
        )
    value = energy.sum()
    if not need:
        return value
    return _fused(value, [(x, grad_x)])


# --- eikonal / smoothness (method.md §5) -----------------------------------------------


def _check_edges(edges, n, name):
    if not isinstance(edges, torch.Tensor) or edges.ndim != 2 or edges.shape[1] != 2 or edges.is_floating_point():
        raise ValueError(f"{name}: edges must be a (E, 2) integer tensor, got {getattr(edges, 'shape', type(edges))}")


def eikonal_loss(phi: torch.Tensor, edges: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
    """``mean_E (|phi_u - phi_v| / l_uv - 1)^2`` with ``l_uv = |x_u - x_v|`` (method.md §5).

    Differentiable in ``phi`` (N,) and in ``x`` (N, 3) (the edge lengths follow the
    vertices). ``|.|`` has derivative 0 at 0. An empty edge set gives 0.
    """
    _check_x(x, "eikonal_loss: x")
    _check_edges(edges, x.shape[0], "eikonal_loss")
    if phi.ndim != 1 or phi.shape[0] != x.shape[0]:
        raise ValueError(f"eikonal_loss: phi must have shape ({x.shape[0]},), got {tuple(phi.shape)}")
    T, V, M = _types(x)
    phi = phi.to(x.dtype).contiguous()
    x = x.contiguous()
    E = edges.shape[0]
    if E == 0:
        return (phi.sum() + x.sum()) * 0.0
    energy = torch.empty(E, dtype=x.dtype, device=x.device)
    need_phi = phi.requires_grad and torch.is_grad_enabled()
    need_x = x.requires_grad and torch.is_grad_enabled()
    need = need_phi or need_x
    gphi = torch.zeros_like(phi) if need else torch.zeros(1, dtype=x.dtype, device=x.device)
    gx = torch.zeros_like(x) if need else torch.zeros((1, 3), dtype=x.dtype, device=x.device)
    with torch_stream(x):
        _launch(
            K_.eikonal_kernel,
            dim=E,
            inputs=[to_wp(phi), _vec(x, V), _i(edges.contiguous(), wp.vec2i), T(1.0 / E), int(need)],
            outputs=[to_wp(energy), to_wp(gphi), _vec(gx, V)],
            device=wp_device(x),
        )
    value = energy.mean()
    if not need:
        return value
    return _fused(value, [(phi, gphi if need_phi else None), (x, gx if need_x else None)])


def smoothness_loss(phi: torch.Tensor, edges: torch.Tensor) -> torch.Tensor:
    """``mean_E (phi_u - phi_v)^2`` (method.md §5), differentiable in ``phi`` (N,)."""
    if not isinstance(phi, torch.Tensor) or phi.ndim != 1:
        raise ValueError(f"smoothness_loss: phi must be a (N,) float tensor, got {getattr(phi, 'shape', type(phi))}")
    _check_edges(edges, phi.shape[0], "smoothness_loss")
    T, V, M = _types(phi)
    phi = phi.contiguous()
    E = edges.shape[0]
    if E == 0:
        return phi.sum() * 0.0
    energy = torch.empty(E, dtype=phi.dtype, device=phi.device)
    need = phi.requires_grad and torch.is_grad_enabled()
    g = torch.zeros_like(phi) if need else torch.zeros(1, dtype=phi.dtype, device=phi.device)
    with torch_stream(phi):
        _launch(
            K_.smoothness_kernel,
            dim=E,
            inputs=[to_wp(phi), _i(edges.contiguous(), wp.vec2i), T(1.0 / E), int(need)],
            outputs=[to_wp(energy), to_wp(g)],
            device=wp_device(phi),
        )
    value = energy.mean()
    if not need:
        return value
    return _fused(value, [(phi, g)])


def phi_edge_losses(phi: torch.Tensor, edges: torch.Tensor, x: torch.Tensor):
    """``(eikonal_loss(phi, edges, x), smoothness_loss(phi, edges))`` from one pass over the
    edges (kernel ``phi_edge_kernel``), differentiable in ``phi`` only: ``x`` is held
    constant, as in the topology phase (method.md §5)."""
    _check_x(x, "phi_edge_losses: x")
    _check_edges(edges, x.shape[0], "phi_edge_losses")
    if phi.ndim != 1 or phi.shape[0] != x.shape[0]:
        raise ValueError(f"phi_edge_losses: phi must have shape ({x.shape[0]},), got {tuple(phi.shape)}")
    T, V, M = _types(x)
    phi_c = phi.to(x.dtype).contiguous()
    E = edges.shape[0]
    if E == 0:
        z = phi_c.sum() * 0.0
        return z, z
    eik = torch.empty(E, dtype=x.dtype, device=x.device)
    smooth = torch.empty(E, dtype=x.dtype, device=x.device)
    need = phi.requires_grad and torch.is_grad_enabled()
    n = phi_c.shape[0] if need else 1
    g_eik = torch.zeros(n, dtype=x.dtype, device=x.device)
    g_smooth = torch.zeros(n, dtype=x.dtype, device=x.device)
    with torch_stream(x):
        _launch(K_.phi_edge_kernel, dim=E,
               inputs=[to_wp(phi_c), _vec(x.detach().contiguous(), V), _i(edges.contiguous(), wp.vec2i), T(1.0 / E),
                       int(need)],
               outputs=[to_wp(eik), to_wp(smooth), to_wp(g_eik), to_wp(g_smooth)], device=wp_device(x))
    l_eik, l_smooth = eik.mean(), smooth.mean()
    if not need:
        return l_eik, l_smooth
    return _fused(l_eik, [(phi_c, g_eik)]), _fused(l_smooth, [(phi_c, g_smooth)])
