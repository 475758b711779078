"""Geometry optimisation: the mesh-only blocks (method.md §6).

During a block the surfels' attributes are frozen and only the tet vertices move; surfels
follow through their fixed barycentric coordinates. Each step draws one training view and
minimises

    L_geo = w_mask L_mask + w_norm L_norm + lam(t) (c_hc L_HC + c_w L_w) + c_barrier L_inv

- ``L_mask``: mean |alpha_tet - mask| over the image, alpha_tet the anti-aliased silhouette
  of the boundary triangles (``holowarp.ops.rasterize_mesh``);
- ``L_norm``: mean over pixels covered by both the tet boundary and the frozen surfels of
  ``1 - <n_GS, n_Tet>``; n_GS are the frozen surfels' rendered normals, rendered once per
  view at the start of the block (the surfels' rotations are frozen, only their centres
  drift with the mesh, so the cache is the block-start picture);
- ``L_HC``: the HC-Laplacian energy of the boundary vertices, lam_cond = 0 in the first half
  of each block (concavities may be pushed out) and 1 in the second (the ablation
  ``two_stage_hc=False`` uses 1 throughout);
- ``L_w``: the weighted bi-harmonic energy against the rest shape captured at block start,
  gamma = 5e-4 for tets touching surface vertices (uniform in the ablation);
- ``L_inv``: sum max(-det F, 0)^p with p rising linearly 2 -> 4 over all mesh iterations;
- ``lam(t) = (1 - t / T)^2``, t counting mesh iterations over ALL blocks (T of them).

Vertices are optimised with :class:`holowarp.optim.UniformAdam` (per-step displacement cap)
and the cosine lr 2e-4 -> 1e-4. Orientation is guaranteed, not only penalised: after each
step, vertices of tets that the step inverted or shrank below ``min_volume_fraction`` of
their block-start volume are put back (repeated until no tet newly crosses that floor), so
no step leaves more inverted tets than it found and no slivers form.

Units: the image terms are per-pixel means; ``L_HC`` is measured in squared mean edge
lengths (of the block-start mesh) and ``L_w`` on dimensionless deformation gradients, so the
balance does not depend on the object's size or the mesh resolution.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import numpy as np
import torch

from holowarp.config import GeometryConfig
from holowarp.tetgs import TetGaussians

__all__ = ["GeometryState", "mesh_lambda", "run_geometry_block", "signed_volumes_t", "revert_inverting_moves"]


def mesh_lambda(t: int, total: int) -> float:
    """lam(t) = (1 - t/T)^2 over the T mesh iterations of the whole run (method.md §6)."""
    return (1.0 - min(max(t, 0), total) / max(total, 1)) ** 2


def signed_volumes_t(x: torch.Tensor, tets: torch.Tensor) -> torch.Tensor:
    """Signed tet volumes (M,) of positions x (N, 3): det[b-a, c-a, d-a] / 6."""
    a, b, c, d = (x[tets[:, i]] for i in range(4))
    return torch.linalg.det(torch.stack([b - a, c - a, d - a], dim=-1)) / 6.0


def revert_inverting_moves(
    x_new: torch.Tensor, x_old: torch.Tensor, tets: torch.Tensor, *, floor=None, max_rounds: int = 20
) -> int:
    """Undo, in place, the moves of vertices whose tets this step inverted or collapsed.

    A tet whose volume at ``x_old`` was above its ``floor`` (M,) (default 0) and is not at
    ``x_new`` gets its four vertices put back to ``x_old``; repeated until no tet newly
    crosses its floor (reverting one tet can push a neighbour under), with a full revert as
    the last resort. A positive floor (a fraction of each tet's rest volume) keeps slivers
    from forming: their huge deformation gradients would otherwise dominate the energies.

    Returns:
        the number of vertices reverted.
    """
    with torch.no_grad():
        f = 0.0 if floor is None else floor
        was_ok = signed_volumes_t(x_old, tets) > f
        reverted = torch.zeros(x_new.shape[0], dtype=torch.bool, device=x_new.device)
        for _ in range(max_rounds):
            bad = was_ok & ~(signed_volumes_t(x_new, tets) > f)
            if not bool(bad.any()):
                return int(reverted.sum())
            idx = tets[bad].reshape(-1)
            x_new[idx] = x_old[idx]
            reverted[idx] = True
        x_new.copy_(x_old)
        return int(x_new.shape[0])


@dataclass
class GeometryState:
    """What persists across blocks (and checkpoints): the global mesh-iteration counter
    and the loss history."""

    mesh_iter: int = 0
    history: list = field(default_factory=list)


def _gs_normals(model: TetGaussians, dataset, view: int, width: int, height: int, cache: dict, rest: torch.Tensor):
    """Frozen surfels' rendered normal (H, W, 3, unit) and coverage (H, W) of one view, with
    the surfels at the block's rest positions (so a resumed block sees the same picture)."""
    if view not in cache:
        with torch.no_grad():
            out = model.render(dataset.viewmats[view], dataset.K[view], width, height, vertices=rest)
            n = out["normal"]
            n = n / n.norm(dim=-1, keepdim=True).clamp_min(1e-8)
            cache[view] = (n.to(torch.float16), out["alpha"].to(torch.float16))
    n, a = cache[view]
    return n.float(), a.float()


def run_geometry_block(
    model: TetGaussians,
    dataset,
    views: np.ndarray,
    config: GeometryConfig,
    *,
    block_iters: int,
    total_mesh_iters: int,
    state: GeometryState,
    seed: int = 0,
    start: int = 0,
    rest_vertices=None,
    optimizer_state: dict | None = None,
    progress=None,
    checkpoint=None,
    checkpoint_every: int = 0,
) -> dict:
    """Run one mesh-only block of ``block_iters`` steps (resumable from ``start``).

    Args:
        model: the tet/surfel model; only ``model.vertices`` changes.
        dataset: training data (images at the working resolution); ``views`` the train ids.
        config: :class:`GeometryConfig`.
        block_iters: steps in this block; ``total_mesh_iters``: T of lam(t) (all blocks).
        state: global mesh counter and history (advanced in place).
        seed: view choice of mesh step t is ``default_rng([seed, 1, t])``, so a resumed
            run draws the same views.
        start: first step of this block to run (resume), with ``rest_vertices`` (V, 3) the
            positions at the block's start and ``optimizer_state`` the UniformAdam state
            saved at that step.
        progress: optional tqdm bar (updated once per step, postfix shows the losses).
        checkpoint: callable(block_step, optimizer_state) saving a resumable state; called
            every ``checkpoint_every`` steps.

    Returns:
        summary dict: ``steps``, ``seconds``, ``reverted_vertices``, ``final`` losses,
        ``inverted`` (tets with volume <= 0 at the end).
    """
    from holowarp.energies import TetEnergies
    from holowarp.ops import rasterize_mesh
    from holowarp.optim import UniformAdam, cosine_lr

    dev = model.device
    mesh = model.mesh()
    if rest_vertices is not None:
        mesh = mesh.with_vertices(np.asarray(rest_vertices, dtype=np.float64))
    rest = torch.tensor(np.array(mesh.vertices), dtype=torch.float32, device=dev)
    bf_np = mesh.boundary_faces()
    faces = torch.tensor(np.array(bf_np), dtype=torch.int32, device=dev)
    energies = TetEnergies(mesh, weights=None if config.uniform_biharmonic else "surface", device=dev)
    edges = mesh.edges()
    mean_edge = float(np.linalg.norm(mesh.vertices[edges[:, 0]] - mesh.vertices[edges[:, 1]], axis=1).mean())
    x = model.vertices
    x.requires_grad_(True)
    opt = UniformAdam([x], lr=config.lr_start, max_step=config.max_step * mean_edge)
    if optimizer_state is not None:
        opt.load_state_dict(optimizer_state)
    H, W = dataset.height, dataset.width
    masks = torch.as_tensor(dataset.masks, device=dev)
    cache: dict = {}
    tets = model.tets
    with torch.no_grad():
        floor = config.min_volume_fraction * signed_volumes_t(rest, tets).clamp_min(0)
    reverted_total = 0
    t0 = time.perf_counter()
    last = {}
    p0, p1 = config.barrier_p
    for k in range(start, block_iters):
        t = state.mesh_iter
        lr = cosine_lr(k, block_iters, config.lr_start, config.lr_end)
        for g in opt.param_groups:
            g["lr"] = lr
        view = int(views[np.random.default_rng([seed, 1, t]).integers(len(views))])
        out = rasterize_mesh(x, faces, dataset.viewmats[view], dataset.K[view], W, H)
        l_mask = (out["alpha"] - masks[view]).abs().mean()
        n_gs, a_gs = _gs_normals(model, dataset, view, W, H, cache, rest)
        sel = (out["alpha"] > 0) & (a_gs > 0.5)
        if bool(sel.any()):
            cos = (out["normal"] * n_gs).sum(-1)
            l_norm = (1.0 - cos)[sel].mean()
        else:
            l_norm = x.sum() * 0.0
        lam = mesh_lambda(t, total_mesh_iters)
        second_half = k >= block_iters // 2
        lam_cond = 1.0 if (not config.two_stage_hc or second_half) else 0.0
        l_hc = energies.hc_laplacian(x, bf_np, lam_cond=lam_cond) / mean_edge**2
        l_w = energies.biharmonic(x)
        p = p0 + (p1 - p0) * (t / max(total_mesh_iters - 1, 1))
        l_inv = energies.inversion_penalty(x, p=p)
        loss = (
            config.w_mask * l_mask
            + config.w_norm * l_norm
            + lam * (config.c_hc * l_hc + config.c_w * l_w)
            + config.c_barrier * l_inv
        )
        if not torch.isfinite(loss):
            raise FloatingPointError(f"geometry step {t}: non-finite loss (mask {l_mask.item()}, norm {l_norm.item()})")
        opt.zero_grad(set_to_none=True)
        loss.backward()
        x_old = x.detach().clone()
        opt.step()
        reverted_total += revert_inverting_moves(x.data, x_old, tets, floor=floor)
        last = {
            "loss": float(loss.detach()),
            "mask": float(l_mask.detach()),
            "norm": float(l_norm.detach()),
            "hc": float(l_hc.detach()),
            "w": float(l_w.detach()),
            "inv": float(l_inv.detach()),
            "lam": lam,
            "lam_cond": lam_cond,
        }
        state.history.append({"mesh_iter": t, **last})
        state.mesh_iter += 1
        if progress is not None:
            progress.update(1)
            progress.set_postfix(mask=f"{last['mask']:.4f}", norm=f"{last['norm']:.3f}", refresh=False)
        if checkpoint is not None and checkpoint_every and (k + 1) % checkpoint_every == 0 and k + 1 < block_iters:
            checkpoint(k + 1, opt.state_dict())
    x.requires_grad_(False)
    with torch.no_grad():
        inverted = int((signed_volumes_t(x, tets) <= 0).sum())
    return {
        "steps": block_iters - start,
        "seconds": time.perf_counter() - t0,
        "reverted_vertices": reverted_total,
        "final": last,
        "inverted": inverted,
        "mean_edge": mean_edge,
    }
