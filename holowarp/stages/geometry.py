"""Geometry optimisation: the mesh-only blocks (method.md §6).

During a block the surfels' attributes are frozen and only the tet vertices move; surfels
follow through their fixed barycentric coordinates. Each step draws one training view and
minimises

    L_geo = w_mask L_mask + w_norm L_norm + max(lam(t), hc_floor) c_hc L_HC + lam(t) c_w L_w + c_barrier L_inv

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
- ``lam(t) = (1 - t / T)^2``, t counting mesh iterations over ALL blocks (T of them);
  ``L_HC`` is weighted by ``max(lam(t), hc_floor)`` (:attr:`GeometryConfig.hc_floor`: 0 in
  the paper, 0.5 in the fast preset, which refines the tets near the surface before its last
  block and needs the smoothing there).

Vertices are optimised with :class:`holowarp.optim.UniformAdam` (per-step displacement cap)
and the cosine lr 2e-4 -> 1e-4. With :attr:`GeometryConfig.depth_pull` and normal maps in the
dataset, each step then moves the vertices its view sees in front of the normal-corrected
depth of a cavity (:meth:`GeometryBlock.pull_to_depth`) back along their rays: no image term
pushes a lid down into a cavity the silhouettes miss, and none can, since the lid shows the
right normals and shading. Orientation is guaranteed, not only penalised: after each
step (and pull), vertices of tets that the step inverted or shrank below ``min_volume_fraction`` of
their block-start volume are put back (repeated until no tet newly crosses that floor), so
no step leaves more inverted tets than it found and no slivers form.

Units: the image terms are per-pixel means; ``L_HC`` is measured in squared mean edge
lengths (of the block-start mesh) and ``L_w`` on dimensionless deformation gradients, so the
balance does not depend on the object's size or the mesh resolution.
"""

from __future__ import annotations

import time
from concurrent.futures import wait
from dataclasses import dataclass

import numpy as np
import torch

from holowarp.config import GeometryConfig
from holowarp.progress import LossBuffer
from holowarp.tetgs import TetGaussians

__all__ = ["BlockResume", "GeometryBlock", "GeometryState", "mesh_lambda", "min_dihedral_deg", "run_geometry_block",
           "signed_volumes_t", "revert_inverting_moves", "revert_sliver_moves"]


def mesh_lambda(t: int, total: int) -> float:
    """lam(t) = (1 - t/T)^2 over the T mesh iterations of the whole run (method.md §6)."""
    return (1.0 - min(max(t, 0), total) / max(total, 1)) ** 2


def signed_volumes_t(x: torch.Tensor, tets: torch.Tensor) -> torch.Tensor:
    """Signed tet volumes (M,) of positions x (N, 3): (b-a) . ((c-a) x (d-a)) / 6 (one Warp pass)."""
    from holowarp.ops.tet_energy import signed_volumes

    return signed_volumes(x, tets)


def revert_inverting_moves(
    x_new: torch.Tensor, x_old: torch.Tensor, tets: torch.Tensor, *, floor=None, max_rounds: int = 20, incidence=None,
    cache=None,
) -> torch.Tensor:
    """Undo, in place, the moves of vertices whose tets this step inverted or collapsed.

    A tet whose volume at ``x_old`` was above its ``floor`` (M,) (default 0) and is not at
    ``x_new`` gets its four vertices put back to ``x_old``; repeated until no tet newly
    crosses its floor (reverting one tet can push a neighbour under), with a full revert as
    the last resort. A positive floor (a fraction of each tet's rest volume) keeps slivers
    from forming: their huge deformation gradients would otherwise dominate the energies.

    ``incidence``: :func:`holowarp.ops.tet_energy.vertex_tets` of ``tets``; with it the
    rounds after the first check only the tets of the vertices just put back. ``cache``: a
    :class:`holowarp.ops._warp.StepCache` of a caller repeating this on the same arrays.

    Returns:
        the number of vertices reverted, as a 0-dim tensor (read it when convenient: on
        CUDA each read is a sync). Each round is one fused Warp pass and one host read of
        its counter (:func:`holowarp.ops.tet_energy.revert_floor_crossings`).
    """
    from holowarp.ops._warp import FRESH
    from holowarp.ops.tet_energy import revert_floor_crossings

    with torch.no_grad():
        if floor is None:
            floor = torch.zeros(tets.shape[0], dtype=x_new.dtype, device=x_new.device)
        elif not torch.is_tensor(floor) or floor.ndim == 0:
            floor = torch.full((tets.shape[0],), float(floor), dtype=x_new.dtype, device=x_new.device)
        return revert_floor_crossings(x_new, x_old, tets, floor, max_rounds=max_rounds, incidence=incidence,
                                      cache=FRESH if cache is None else cache)


def min_dihedral_deg(x: torch.Tensor, tets: torch.Tensor) -> torch.Tensor:
    """(M,) smallest dihedral angle of each tet, degrees: :meth:`holowarp.tetmesh.TetMesh.dihedral_angles`
    on the device, for a step's guard. The angle at the edge shared by the faces opposite
    corners c and d is pi - angle(n_c, n_d) for outward face normals n."""
    P = x[tets]  # (M, 4, 3)
    normals = []
    for i in range(4):
        a, b, c = (P[:, j] for j in range(4) if j != i)
        n = torch.linalg.cross(b - a, c - a)
        n = n * torch.sign(((a - P[:, i]) * n).sum(dim=1, keepdim=True))  # away from the opposite corner
        normals.append(n / n.norm(dim=1, keepdim=True).clamp_min(1e-30))
    cos = torch.stack([-(normals[i] * normals[j]).sum(dim=1) for i in range(4) for j in range(i + 1, 4)], dim=1)
    return torch.rad2deg(torch.arccos(cos.max(dim=1).values.clamp(-1.0, 1.0)))


def revert_sliver_moves(x_new: torch.Tensor, x_old: torch.Tensor, tets: torch.Tensor, *, min_deg: float,
                        max_rounds: int = 5) -> int:
    """Put back, in place, the moved vertices (rows where ``x_new`` differs from ``x_old``) of
    every tet whose smallest dihedral angle the move took below ``min_deg`` degrees, or
    lowered further where it already was; repeated, as putting one tet back can bend a
    neighbour, then everything put back after ``max_rounds``. Returns the vertices put back."""
    with torch.no_grad():
        moved = (x_new != x_old).any(dim=1)
        if not moved.any() or min_deg <= 0:
            return 0
        back = 0
        for _ in range(max_rounds):
            sel = moved[tets].any(dim=1)
            if not sel.any():
                return back
            t = tets[sel]
            old, new = min_dihedral_deg(x_old, t), min_dihedral_deg(x_new, t)
            bad = (new < min_deg) & (new < old)
            if not bad.any():
                return back
            v = torch.unique(t[bad].reshape(-1))
            v = v[moved[v]]
            x_new[v] = x_old[v]
            moved[v] = False
            back += int(v.numel())
        back += int(moved.sum())
        x_new.copy_(x_old)
        return back


#: The thread :meth:`GeometryBlock._ahead` runs work on (made at first use).
_AHEAD = None


@dataclass
class GeometryState:
    """What persists across blocks (and checkpoints): the global mesh-iteration counter."""

    mesh_iter: int = 0


@dataclass
class BlockResume:
    """A mesh block interrupted after ``step`` of its steps: the block's main iteration, its
    rest positions (V, 3) float64 and the UniformAdam state at that step."""

    at: int
    step: int
    rest: np.ndarray
    opt: dict


class GeometryBlock:
    """One mesh-only block (see the module docstring): the rest shape, energies, optimiser
    and per-view caches, and :meth:`step`, one optimisation step.

    Args:
        model: the tet/surfel model; only ``model.vertices`` changes.
        dataset: training data (images at the working resolution); ``views`` the train ids.
        config: :class:`GeometryConfig`.
        block_iters: steps in this block; ``total_mesh_iters``: T of lam(t) (all blocks).
        rest_vertices: (V, 3) positions at the block's start (a resumed block passes the
            saved ones; default: the model's current positions).
        optimizer_state: the UniformAdam state to continue from (resume).
        depth_maps: ``{view: (stage-0 depth, alpha, corrected depth)}`` (H, W) maps of the
            depth carve (:func:`holowarp.stages.topology.surfel_depth_maps`) for the depth
            pull (:meth:`pull_to_depth`); None, or ``config.depth_pull`` 0, for none.
    """

    def __init__(self, model: TetGaussians, dataset, views, config: GeometryConfig, *, block_iters: int,
                 total_mesh_iters: int, rest_vertices=None, optimizer_state: dict | None = None,
                 depth_maps: dict | None = None):
        from holowarp.energies import TetEnergies
        from holowarp.ops._warp import StepCache
        from holowarp.ops.tet_energy import vertex_tets
        from holowarp.optim import UniformAdam

        self.model, self.dataset, self.views, self.cfg = model, dataset, np.asarray(views), config
        self.block_iters, self.total = int(block_iters), int(total_mesh_iters)
        dev = model.device
        mesh = model.mesh()
        if rest_vertices is not None:
            mesh = mesh.with_vertices(np.asarray(rest_vertices, dtype=np.float64))
        self.rest_np = np.asarray(mesh.vertices, dtype=np.float64)
        self.rest = torch.tensor(np.array(mesh.vertices), dtype=torch.float32, device=dev)
        self.bf_np = mesh.boundary_faces()
        self.faces = torch.tensor(np.array(self.bf_np), dtype=torch.int32, device=dev)
        self.energies = TetEnergies(mesh, weights=None if config.uniform_biharmonic else "surface", device=dev)
        edges = mesh.edges()
        self.mean_edge = float(np.linalg.norm(mesh.vertices[edges[:, 0]] - mesh.vertices[edges[:, 1]], axis=1).mean())
        self.x = model.vertices
        self.x.requires_grad_(True)
        self.opt = UniformAdam([self.x], lr=config.lr_start, max_step=config.max_step * self.mean_edge)
        if optimizer_state is not None:
            self.opt.load_state_dict(optimizer_state)
        self.masks = torch.as_tensor(dataset.masks, dtype=torch.float32, device=dev)
        self.normals = (torch.as_tensor(dataset.normals, dtype=torch.float32, device=dev)
                        if dataset.normals is not None and config.w_prior > 0 else None)
        self.cache: dict = {}
        with torch.no_grad():
            self.floor = config.min_volume_fraction * signed_volumes_t(self.rest, model.tets).clamp_min(0)
        self.incidence = vertex_tets(model.tets, model.num_vertices)
        self.tets32 = model.tets.to(torch.int32).contiguous()  # the tets do not change within a block
        # Every step works on the same arrays: buffers, Warp views and launches are kept
        # (about 20 launches a step; issue 17's loop overhead).
        self.step_cache = StepCache()
        self._warm = False  # a step has run: the energies' rest shape and kernels are in place
        #: L_geo's weights of (L_mask, L_norm, L_prior, L_HC, L_w, L_inv); a step sets the two
        #: that follow lam(t)
        self.coef = torch.tensor([config.w_mask, config.w_norm, config.w_prior if self.normals is not None else 0.0,
                                  0.0, 0.0, config.c_barrier], dtype=self.x.dtype, device=dev)
        self.reverted = 0
        self.depth_maps = depth_maps if config.depth_pull > 0 else None
        self.targets: dict = {}
        self.pulled = 0
        if self.depth_maps is not None:
            # A pull squeezes the tets under a lid; its own, higher floor keeps slivers from forming there.
            with torch.no_grad():
                self.pull_floor = config.depth_pull_min_volume * signed_volumes_t(self.rest, model.tets).clamp_min(0)
            self.pull_cache = StepCache()

    def depth_target(self, view: int):
        """(H, W) float32 tensor: the camera depth behind which the depth pull puts every
        vertex seen at that pixel, NaN where it does not act; None without a map for ``view``.

        From the depth carve's maps of ``view`` (stage-0 depth, alpha, normal-corrected
        depth): less the pull's margin, the corrected depth where it lies behind the stage-0
        surface by more than that margin (a lid stage 0 left over a cavity,
        :func:`holowarp.carve.depth_from_normals`), each depth the nearest of its 3x3
        neighbourhood and every pixel of it opaque, as the carve takes them (a rim's vertices
        next to a deeper floor are not pulled). Under a deep lid (the corrected depth more
        than ``depth_pull_own_gap`` mean edges behind the stage-0 one) where the pixel's own
        corrected depth lies within one mean edge of that nearest one (no rim in the window,
        only the floor's slope) the target is the pixel's own: on the bowl's slanted floor
        (fast, 128²) the nearest of the window sat a median 0.012 in front of the pixel's
        own depth, and the pulled floor stopped there, 0.008 in front of the true one, where
        F@0.005 does not count it."""
        if self.depth_maps is None or view not in self.depth_maps:
            return None
        if view not in self.targets:
            from holowarp.carve import nearest_depths

            margin = self.cfg.depth_pull_margin * self.mean_edge
            opaque, near0, nearc = nearest_depths(*self.depth_maps[view])
            own = np.asarray(self.depth_maps[view][2], dtype=np.float64)
            with np.errstate(invalid="ignore"):  # inf - inf off the opaque region, masked out
                behind = np.where(opaque & np.isfinite(nearc), nearc - near0, -np.inf)  # how deep the lid is
                smooth = (behind > self.cfg.depth_pull_own_gap * self.mean_edge) & (own - nearc < self.mean_edge)
            target = np.where(smooth, own, nearc) - margin
            self.targets[view] = torch.tensor(np.where(behind > margin, target, np.nan), dtype=torch.float32,
                                              device=self.x.device)
        return self.targets[view]

    def pull_to_depth(self, x: torch.Tensor, view: int) -> int:
        """Move, in place, every vertex of ``x`` (V, 3) that ``view`` sees in front of its
        :meth:`depth_target` back along its view ray by ``depth_pull`` of the gap (at most
        ``max_step`` mean edges); returns how many moved. :meth:`step` then puts back the
        moves that take a tet below ``depth_pull_min_volume`` of its block-start volume."""
        tgt = self.depth_target(view)
        if tgt is None:
            return 0
        ds = self.dataset
        vm = torch.as_tensor(ds.viewmats[view], dtype=x.dtype, device=x.device)
        K = torch.as_tensor(ds.K[view], dtype=x.dtype, device=x.device)
        R, t = vm[:3, :3], vm[:3, 3]
        with torch.no_grad():
            # holowarp.camera.project_points on the device (skew K[0, 1] included)
            pc = x @ R.T + t
            z = pc[:, 2]
            zs = torch.where(z > 1e-6, z, torch.ones_like(z))
            uv = (pc[:, :2] / zs[:, None]) @ K[:2, :2].T + K[:2, 2]
            col, row = torch.floor(uv[:, 0]).long(), torch.floor(uv[:, 1]).long()
            H, W = tgt.shape
            ok = (z > 1e-6) & (col >= 0) & (col < W) & (row >= 0) & (row < H)
            T = tgt[row.clamp(0, H - 1), col.clamp(0, W - 1)]
            gap = torch.where(ok & torch.isfinite(T), T - z, torch.zeros_like(z)).clamp_min(0)
            ray = x - (-R.T @ t)  # camera centre to vertex: a depth change dz moves it by |ray| dz / z
            cap = self.cfg.max_step * self.mean_edge * zs / ray.norm(dim=1).clamp_min(1e-12)
            delta = torch.minimum(self.cfg.depth_pull * gap, cap)
            x += ray * (delta / zs)[:, None]
            return int((delta > 0).sum())

    def surfel_normals(self, view: int):
        """The frozen surfels' rendered normal (H, W, 3, unit) and coverage (H, W) in ``view``,
        float16, with the surfels at the block's rest positions (so a resumed block sees the
        same picture); rendered once per view and block."""
        if view not in self.cache:
            ds = self.dataset
            with torch.no_grad():
                out = self.model.render(ds.viewmats[view], ds.K[view], ds.width, ds.height, vertices=self.rest)
                n = out["normal"]
                n = n / n.norm(dim=-1, keepdim=True).clamp_min(1e-8)
                self.cache[view] = (n.to(torch.float16).contiguous(), out["alpha"].to(torch.float16).contiguous())
        return self.cache[view]

    def view_losses(self, out: dict, view: int) -> torch.Tensor:
        """``(L_mask, L_norm, L_prior)`` of the mesh render ``out`` (:func:`holowarp.ops.rasterize_mesh`)
        in ``view`` as a (3,) tensor from one fused pass (:func:`holowarp.ops.mesh_losses.mesh_view_losses`):
        the silhouette L1 against the mask, the mean ``1 - cos`` against the frozen surfels'
        normals where both cover the pixel, and against the dataset's normal map (``L_prior``,
        0 without normal maps or with ``w_prior`` 0)."""
        from holowarp.ops.mesh_losses import mesh_view_losses

        n_gs, a_gs = self.surfel_normals(view)
        prior = self.normals[view] if self.normals is not None else None
        return mesh_view_losses(out["alpha"], out["normal"], self.masks[view], n_gs, a_gs, prior,
                                cache=self.step_cache)

    def _ahead(self, work):
        """``work()`` started on a second thread (a future), or None where that does not pay:
        on a device other than the CPU (launches are asynchronous there), on one CPU thread
        (:func:`holowarp.device.cpu_threads`: another run shares the cores) and in a block's
        first step, which captures what the later ones share.

        The tet energies' and the HC term's kernels, gradients included (about a third of a
        step's own work, issue 17), run there while the rasteriser's serial set-up runs
        here; the autograd graph is still built on this thread, in the same order, so the
        results do not depend on it."""
        from holowarp.device import cpu_threads

        if not self._warm or self.x.device.type != "cpu" or cpu_threads() < 2:
            self._warm = True
            return None
        global _AHEAD
        if _AHEAD is None:
            from concurrent.futures import ThreadPoolExecutor

            _AHEAD = ThreadPoolExecutor(max_workers=1, thread_name_prefix="holowarp-ahead")
        return _AHEAD.submit(work)

    def view_of(self, t: int, seed: int) -> int:
        """The training view of global mesh iteration ``t``: drawn from ``default_rng([seed, 1, t])``."""
        return int(self.views[np.random.default_rng([seed, 1, t]).integers(len(self.views))])

    def step(self, k: int, t: int, seed: int) -> dict:
        """Block step ``k`` (global mesh iteration ``t``) on the view drawn from
        ``default_rng([seed, 1, t])``; returns its loss terms as detached 0-dim tensors
        (plus ``lam`` and ``lam_cond`` as floats)."""
        from holowarp.ops import rasterize_mesh
        from holowarp.optim import cosine_lr

        cfg, ds, x, en = self.cfg, self.dataset, self.x, self.energies
        lr = cosine_lr(k, self.block_iters, cfg.lr_start, cfg.lr_end)
        for g in self.opt.param_groups:
            g["lr"] = lr
        view = self.view_of(t, seed)
        H, W = ds.height, ds.width
        c = self.step_cache
        p0, p1 = cfg.barrier_p
        p_inv = p0 + (p1 - p0) * (t / max(self.total - 1, 1))
        lam_cond = 1.0 if (not cfg.two_stage_hc or k >= self.block_iters // 2) else 0.0
        ahead = self._ahead(lambda: (en.prepare_biharmonic_and_inversion(x, p_inv, cache=c),
                                     en.prepare_hc_laplacian(x, self.bf_np, lam_cond=lam_cond, cache=c)))
        try:
            out = rasterize_mesh(x, self.faces, ds.viewmats[view], ds.K[view], W, H)
            l_view = self.view_losses(out, view)
        finally:  # the other thread is done with the step's buffers before anything else runs
            if ahead is not None:
                wait([ahead])
        if ahead is not None:
            ahead.result()  # its error, if it raised one
        lam = mesh_lambda(t, self.total)
        l_hc = en.hc_laplacian(x, self.bf_np, lam_cond=lam_cond, cache=c)  # squared metres
        l_w, l_inv = en.biharmonic_and_inversion(x, p=p_inv, cache=c)
        # L_geo's weights: L_HC is measured in squared mean edges, so its weight takes 1 / mean_edge^2.
        w_hc = (cfg.hc_floor if cfg.hc_floor > lam else lam) * cfg.c_hc / self.mean_edge**2
        has_prior = self.normals is not None
        coef = self.coef.clone()  # written on the device: no upload per step
        coef[3] = w_hc
        coef[4] = lam * cfg.c_w
        x.grad = None
        # One backward from the terms with their weights as the seeds: no graph of scalar products and sums.
        torch.autograd.backward([l_view, l_hc, l_w, l_inv], [coef[:3], coef[3], coef[4], coef[5]])
        with torch.no_grad():
            terms = torch.cat([l_view, torch.stack([l_hc, l_w, l_inv])])
            loss = terms @ coef
        x_old = c.buffer("step.x_old", x.shape, x.dtype, x.device).copy_(x.detach())
        self.opt.step()
        if self.depth_maps is not None and self.depth_target(view) is not None:
            x_mid = c.buffer("step.x_mid", x.shape, x.dtype, x.device).copy_(x.detach())
            if self.pull_to_depth(x.data, view):
                revert_inverting_moves(x.data, x_mid, self.tets32, floor=self.pull_floor, incidence=self.incidence,
                                       cache=self.pull_cache)
                revert_sliver_moves(x.data, x_mid, self.model.tets, min_deg=self.cfg.depth_pull_min_dihedral)
                self.pulled += int((x.data != x_mid).any(dim=1).sum())
        self.reverted = self.reverted + revert_inverting_moves(x.data, x_old, self.tets32, floor=self.floor,
                                                                 incidence=self.incidence, cache=c)
        logged = {"loss": loss, "mask": terms[0], "norm": terms[1], "hc": terms[3] / self.mean_edge**2, "w": terms[4],
                  "inv": terms[5]}
        if has_prior:
            logged["prior"] = terms[2]
        return {**logged, "lam": lam, "lam_cond": lam_cond}

    def finish(self) -> int:
        """Stop optimising the vertices; returns the number of inverted tets (volume <= 0)."""
        self.x.requires_grad_(False)
        with torch.no_grad():
            return int((signed_volumes_t(self.x, self.model.tets) <= 0).sum())


def run_geometry_block(
    model: TetGaussians,
    dataset,
    views: np.ndarray,
    config: GeometryConfig,
    *,
    block_iters: int,
    total_mesh_iters: int,
    state: GeometryState,
    at: int = 0,
    seed: int = 0,
    resume: BlockResume | None = None,
    progress=None,
    checkpoint=None,
    checkpoint_every: int = 0,
    log=None,
    depth_maps: dict | None = None,
) -> dict:
    """Run one mesh-only block of ``block_iters`` steps, inserted at main iteration ``at``.

    Args:
        model, dataset, views, config, block_iters, total_mesh_iters: see :class:`GeometryBlock`.
        state: the global mesh counter (advanced in place).
        seed: view choice of mesh step t is ``default_rng([seed, 1, t])``, so a resumed
            run draws the same views.
        resume: continue this block from an interrupted state (its ``at`` must match).
        progress: optional tqdm bar (updated once per step, postfix shows the losses).
        checkpoint: callable(:class:`BlockResume`) saving a resumable state; called every
            ``checkpoint_every`` steps.
        log: optional callable(record) given each step's ``{"mesh_iter": t, **losses}``.
        depth_maps: the depth pull's maps by view (see :class:`GeometryBlock`).

    Returns:
        summary dict: ``steps``, ``seconds``, ``reverted_vertices``, ``pulled_vertices`` (vertex
        moves of the depth pull, summed over the steps), ``final`` losses,
        ``inverted`` (tets with volume <= 0 at the end), ``mean_edge``.
    """
    if resume is not None and resume.at != at:
        resume = None
    blk = GeometryBlock(model, dataset, views, config, block_iters=block_iters, total_mesh_iters=total_mesh_iters,
                        rest_vertices=resume.rest if resume else None, optimizer_state=resume.opt if resume else None,
                        depth_maps=depth_maps)
    start = resume.step if resume else 0
    t0 = time.perf_counter()
    shown = {}

    def written(records):
        # Loss values reach the host in batches (LossBuffer); show the latest on the bar.
        if records and progress is not None:
            r = records[-1][1]
            progress.set_postfix(mask=f"{r['mask']:.4f}", norm=f"{r['norm']:.3f}", refresh=False)
        if records:
            shown.update(records[-1][1])

    losses = LossBuffer(lambda _stage, rec: log(rec) if log is not None else None)
    for k in range(start, block_iters):
        written(losses.add("geometry", {"mesh_iter": state.mesh_iter}, blk.step(k, state.mesh_iter, seed)))
        state.mesh_iter += 1
        if progress is not None:
            progress.update(1)
        if checkpoint is not None and checkpoint_every and (k + 1) % checkpoint_every == 0 and k + 1 < block_iters:
            written(losses.flush())
            checkpoint(BlockResume(at, k + 1, blk.rest_np, blk.opt.state_dict()))
    written(losses.flush())
    return {
        "steps": block_iters - start,
        "seconds": time.perf_counter() - t0,
        "reverted_vertices": int(blk.reverted),
        "pulled_vertices": int(blk.pulled),
        "final": {k: v for k, v in shown.items() if k != "mesh_iter"},
        "inverted": blk.finish(),
        "mean_edge": blk.mean_edge,
    }
