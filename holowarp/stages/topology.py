"""Topology optimisation and the Gaussian phases of the main loop (method.md §5).

Main-loop iteration i draws one training view and renders the bound surfels:

- i < topology_until (topology phase): the per-vertex field phi, the sharpness kappa, and
  the surfels' colours and rotations are learnt with
  ``L_topo = L_render + lam_eik L_eik + lam_smooth L_smooth`` (ablation "w/o continuous
  opacity": free per-tet opacities, no eikonal/smoothness);
- afterwards (Gaussian phase): colours, rotations, scales and free opacities with L_render.

``L_render = w_rgb L_rgb + w_mask L_mask + w_normal L_normal + w_prior L_prior`` with
``L_rgb = 0.8 L1 + 0.2 (1 - SSIM)``, ``L_mask = mean |alpha - mask|``, ``L_normal`` the
ranked (largest-errors) ``1 - cos`` between the surfels' rendered normals and the normals
derived from their rendered depth, and ``L_prior`` the same against the dataset's normal
maps (only when it has them).

Pruning (§5) deletes tets with alpha < 0.1 and then vertices no tet uses; if that splits the
mesh, the largest face-connected component is kept and the rest counted. After the FIRST
prune the surfel scales are recomputed (0.65 x mean centroid-to-vertex distance) and become
learnable, and opacities become free parameters initialised from the field.

The field is initialised SDF-like (method.md leaves this open): ``phi_init="visual_hull"``
labels each vertex inside/outside the masks' visual hull (it projects into every training
mask) and sets phi to the signed graph distance to the label interface along mesh edges
(negative inside), which is what the eikonal term expects; ``"inside"`` starts every vertex
at ``-phi_inside`` (all tets opaque).
"""

from __future__ import annotations

import numpy as np
import torch

from holowarp.config import TopologyConfig
from holowarp.stages.cleanup import restore_until_manifold
from holowarp.tetgs import TetGaussians
from holowarp.tetmesh import TetMesh

__all__ = [
    "GaussianOptimizers",
    "gaussian_step",
    "init_colors",
    "init_phi",
    "prune",
    "sample_masks",
]


def sample_masks(points: np.ndarray, dataset, views) -> np.ndarray:
    """Mask values (P, len(views)) at the projections of world ``points`` (P, 3).

    Bilinear lookup; points behind a camera or outside its frame read 0 (the cameras see
    the whole object, so anything out of frame is background).
    """
    P = np.asarray(points, dtype=np.float64)
    out = np.zeros((len(P), len(views)), dtype=np.float32)
    H, W = dataset.height, dataset.width
    for j, v in enumerate(views):
        Vm, K = dataset.viewmats[v], dataset.K[v]
        pc = P @ Vm[:3, :3].T + Vm[:3, 3]
        z = pc[:, 2]
        ok = z > 1e-6
        u = np.where(ok, K[0, 0] * pc[:, 0] / np.where(ok, z, 1) + K[0, 2], -1.0) - 0.5
        w = np.where(ok, K[1, 1] * pc[:, 1] / np.where(ok, z, 1) + K[1, 2], -1.0) - 0.5
        ok &= (u >= 0) & (u <= W - 1) & (w >= 0) & (w <= H - 1)
        u0 = np.clip(np.floor(u).astype(np.int64), 0, W - 2)
        w0 = np.clip(np.floor(w).astype(np.int64), 0, H - 2)
        fu, fw = np.clip(u - u0, 0, 1), np.clip(w - w0, 0, 1)
        m = dataset.masks[v]
        val = (
            m[w0, u0] * (1 - fu) * (1 - fw)
            + m[w0, u0 + 1] * fu * (1 - fw)
            + m[w0 + 1, u0] * (1 - fu) * fw
            + m[w0 + 1, u0 + 1] * fu * fw
        )
        out[:, j] = np.where(ok, val, 0.0)
    return out


def init_phi(mesh: TetMesh, dataset, views, config: TopologyConfig) -> np.ndarray:
    """Initial vertex field (V,), see the module docstring."""
    V = mesh.num_vertices
    if config.phi_init == "inside":
        return np.full(V, -config.phi_inside)
    if config.phi_init != "visual_hull":
        raise ValueError(f"phi_init must be 'visual_hull' or 'inside', got {config.phi_init!r}")
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import dijkstra

    inside = sample_masks(mesh.vertices, dataset, views).min(axis=1) > 0.5
    if inside.all() or not inside.any():
        return np.full(V, -config.phi_inside if inside.all() else config.phi_inside)
    E = mesh.edges().astype(np.int64)
    L = np.linalg.norm(mesh.vertices[E[:, 0]] - mesh.vertices[E[:, 1]], axis=1)
    cross = inside[E[:, 0]] != inside[E[:, 1]]
    # A virtual source joined to both ends of every interface edge at half its length: the
    # label boundary is taken at edge midpoints.
    seed = np.full(V, np.inf)
    np.minimum.at(seed, E[cross, 0], 0.5 * L[cross])
    np.minimum.at(seed, E[cross, 1], 0.5 * L[cross])
    src = np.flatnonzero(np.isfinite(seed))
    rows = np.concatenate([E[:, 0], E[:, 1], np.full(len(src), V)])
    cols = np.concatenate([E[:, 1], E[:, 0], src])
    w = np.concatenate([L, L, seed[src]])
    g = coo_matrix((w, (rows, cols)), shape=(V + 1, V + 1)).tocsr()
    d = dijkstra(g, directed=True, indices=V)[:V]
    d = np.where(np.isfinite(d), d, d[np.isfinite(d)].max())
    return np.where(inside, -d, d)


def init_colors(mesh: TetMesh, dataset, views, *, max_views: int = 24) -> np.ndarray:
    """Initial surfel colours (M, 3): mean image colour at the tet centroid's projection over
    the views where it falls inside the mask (grey where none)."""
    T = mesh.tets
    c = mesh.vertices[T].mean(axis=1)
    views = np.asarray(views)[:: max(1, len(views) // max_views)]
    acc = np.zeros((len(c), 3))
    cnt = np.zeros(len(c))
    H, W = dataset.height, dataset.width
    for v in views:
        Vm, K = dataset.viewmats[v], dataset.K[v]
        pc = c @ Vm[:3, :3].T + Vm[:3, 3]
        z = np.maximum(pc[:, 2], 1e-9)
        u = np.floor(K[0, 0] * pc[:, 0] / z + K[0, 2]).astype(np.int64)
        w = np.floor(K[1, 1] * pc[:, 1] / z + K[1, 2]).astype(np.int64)
        ok = (pc[:, 2] > 1e-6) & (u >= 0) & (u < W) & (w >= 0) & (w < H)
        ok[ok] &= dataset.masks[v][w[ok], u[ok]] > 0.5
        acc[ok] += dataset.images[v][w[ok], u[ok]]
        cnt[ok] += 1
    return np.where(cnt[:, None] > 0, acc / np.maximum(cnt, 1)[:, None], 0.5).clip(0.02, 0.98)


class GaussianOptimizers:
    """The Adam instances of the Gaussian phases, rebuilt after every topology change.

    - topology phase, continuous field: phi, colours, rotations + kappa (own Adam, lr 0.01);
    - free opacities (after the first prune, or the ablation): colours, rotations, opacity
      logits (0.05) and, after the first prune, log-scales (0.005).
    """

    def __init__(self, model: TetGaussians, config: TopologyConfig, *, learn_scales: bool):
        groups = [
            {"params": [model.color_logit], "lr": config.color_lr, "name": "color"},
            {"params": [model.quats], "lr": config.rotation_lr, "name": "rotation"},
        ]
        self.kappa = None
        if model.free_opacity:
            groups.append({"params": [model.opacity_logit], "lr": config.opacity_lr, "name": "opacity"})
        else:
            groups.append({"params": [model.phi], "lr": config.phi_lr, "name": "phi"})
            self.kappa = torch.optim.Adam([model.kappa], lr=config.kappa_lr)
        if learn_scales:
            groups.append({"params": [model.log_scales], "lr": config.scale_lr, "name": "scale"})
        self.main = torch.optim.Adam(groups, eps=1e-15)

    def zero_grad(self):
        self.main.zero_grad(set_to_none=True)
        if self.kappa is not None:
            self.kappa.zero_grad(set_to_none=True)

    def step(self):
        self.main.step()
        if self.kappa is not None:
            self.kappa.step()

    def state_dict(self) -> dict:
        return {"main": self.main.state_dict(), "kappa": None if self.kappa is None else self.kappa.state_dict()}

    def load_state_dict(self, d: dict):
        self.main.load_state_dict(d["main"])
        if self.kappa is not None and d.get("kappa") is not None:
            self.kappa.load_state_dict(d["kappa"])


def gaussian_step(
    model: TetGaussians,
    dataset,
    view: int,
    config: TopologyConfig,
    optimizers: GaussianOptimizers,
    *,
    topology_phase: bool,
    edges: torch.Tensor | None,
    images: torch.Tensor,
    masks: torch.Tensor,
    normals: torch.Tensor | None,
    background: torch.Tensor,
) -> dict:
    """One main-loop step on view ``view``; returns the loss terms as floats.

    ``images`` (N, H, W, 3) must already be composited on ``background``.
    """
    from holowarp import losses

    H, W = dataset.height, dataset.width
    vm = torch.as_tensor(dataset.viewmats[view], dtype=torch.float32, device=model.device)
    Kt = torch.as_tensor(dataset.K[view], dtype=torch.float32, device=model.device)
    out = model.render(vm, Kt, W, H, background=background)
    gt = images[view]
    m = masks[view]
    l_rgb = losses.l1_dssim_loss(out["rgb"], gt, lambda_dssim=config.dssim_weight)
    l_mask = losses.mask_loss(out["alpha"], m)
    # Depth-derived normals from the median depth (robust at silhouettes, as 2DGS does for
    # bounded objects), compared where the surfels are opaque.
    n_depth = losses.depth_to_normal(out["median_depth"], Kt, vm)
    opaque = out["alpha"].detach() > 0.5
    frac = config.normal_rank_fraction
    l_normal = losses.ranked_normal_loss(out["normal"], n_depth, mask=opaque, top_fraction=frac)
    loss = config.w_rgb * l_rgb + config.w_mask * l_mask + config.w_normal * l_normal
    terms = {"rgb": float(l_rgb.detach()), "mask": float(l_mask.detach()), "normal": float(l_normal.detach())}
    if normals is not None and config.w_prior > 0:
        prior = normals[view]
        has = opaque & (prior.norm(dim=-1) > 0.5) & (n_depth.norm(dim=-1) > 0.5)
        e = _one_minus_cos(prior, out["normal"]) + _one_minus_cos(prior, n_depth)
        l_prior = losses.ranked_loss(e, mask=has, top_fraction=frac)
        loss = loss + config.w_prior * l_prior
        terms["prior"] = float(l_prior.detach())
    if topology_phase and not model.free_opacity and edges is not None:
        from holowarp.energies import eikonal_loss, smoothness_loss

        x = model.vertices.detach()
        l_eik = eikonal_loss(model.phi, edges, x)
        l_smooth = smoothness_loss(model.phi, edges)
        loss = loss + config.lam_eik * l_eik + config.lam_smooth * l_smooth
        terms.update(eik=float(l_eik.detach()), smooth=float(l_smooth.detach()))
    if not torch.isfinite(loss):
        raise FloatingPointError(f"main-loop step on view {view}: non-finite loss {terms}")
    optimizers.zero_grad()
    loss.backward()
    optimizers.step()
    with torch.no_grad():
        # Keep rotations unit and kappa inside its clamp range (method.md §5).
        model.quats.data /= model.quats.data.norm(dim=1, keepdim=True).clamp_min(1e-12)
        lo, hi = model.kappa_clamp
        model.kappa.data.clamp_(lo / model.s, hi / model.s)
    terms["loss"] = float(loss.detach())
    return terms


def _one_minus_cos(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Per-pixel ``1 - cos(a, b)`` of two normal maps [H, W, 3] (need not be unit length)."""
    return 1.0 - (a * b).sum(-1) / (a.norm(dim=-1) * b.norm(dim=-1)).clamp_min(1e-12)


def prune(model: TetGaussians, config: TopologyConfig) -> dict:
    """Delete tets with alpha < prune_alpha and the vertices no tet uses (method.md §5).

    Two rules keep the result a simulation-ready solid (method.md §0: one connected,
    boundary-manifold mesh):

    - pruning never opens a sealed cavity: low-alpha tets that do not connect, through other
      low-alpha tets, to the current boundary are invisible in every view and stay;
    - pruning never digs one-tet dents: a low-alpha tet with three or four faces on kept
      tets stays (repeated a few times);
    - pruning never makes the boundary non-manifold: the pruned tets around any
      non-manifold edge or vertex are restored, repeatedly, until the boundary is a
      manifold. Restoring every pruned tet gives back the (manifold) mesh before the
      prune, so this terminates with a manifold boundary whenever the input had one.

    If pruning would empty the mesh, nothing is pruned (and the report says so). If it
    splits the mesh, the largest face-connected component is kept and the rest counted.

    Returns:
        dict: ``tets_before``, ``pruned`` (removed for low alpha), ``low_alpha``,
        ``raw_components`` and ``raw_non_manifold`` (face-connected pieces and non-manifold
        boundary edges + vertices the plain rule would have left, before the guards below),
        ``kept_cavity`` (low-alpha tets kept because sealed), ``kept_dents`` (low-alpha tets
        kept because three or more of their faces meet kept tets), ``restored_for_manifold``,
        ``removed_components``, ``tets_removed_by_component``, ``tets_after``, ``emptied``.
    """
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    with torch.no_grad():
        alpha = model.opacities().cpu().numpy()
    mesh = model.mesh()
    T = mesh.tets
    M = model.num_tets
    low = alpha < config.prune_alpha
    info = {"tets_before": M, "low_alpha": int(low.sum()), "emptied": False}
    if low.all():
        info.update(emptied=True, pruned=0, kept_cavity=0, kept_dents=0, restored_for_manifold=0, removed_components=0,
                    raw_components=0, raw_non_manifold=0,
                    tets_removed_by_component=0, tets_after=M)
        return info
    # Sealed cavities: components of the low-alpha set (through shared faces) that never
    # reach a boundary face of the current mesh.
    adj = mesh.face_adjacency()
    rows = np.repeat(np.arange(M), 4)
    cols = adj.reshape(-1)
    both = (cols >= 0) & low[rows] & low[np.maximum(cols, 0)]
    g = coo_matrix((np.ones(int(both.sum())), (rows[both], cols[both])), shape=(M, M))
    _, lab = connected_components(g, directed=False)
    open_comp = np.zeros(lab.max() + 1, dtype=bool)
    touches_outside = low & np.any(adj < 0, axis=1)
    open_comp[lab[touches_outside]] = True
    drop = low & open_comp[lab]
    info["kept_cavity"] = int((low & ~drop).sum())
    # What the plain rule (delete every open low-alpha tet) would leave: the measure of how
    # coherent the opacities are (the paper's "Num. components" of its ablation).
    raw = TetMesh(mesh.vertices, T[~drop], validate=False)
    info["raw_components"] = int(raw.num_components())
    info["raw_non_manifold"] = int(len(raw.non_manifold_edges()) + len(raw.non_manifold_vertices()))
    # Dents: a tet whose faces (>= 3 of 4) all meet kept tets would leave a one-tet pit in
    # the surface. A single transparent surfel among opaque neighbours is a rendering
    # artefact (it is redundant where its neighbours already cover its pixels), not
    # evidence of empty space, so such tets stay; pruning keeps removing coherent regions.
    filled = 0
    for _ in range(3):
        kept_nb = np.where(adj >= 0, ~drop[np.maximum(adj, 0)], False).sum(axis=1)
        dent = drop & (kept_nb >= 3)
        if not dent.any():
            break
        drop &= ~dent
        filled += int(dent.sum())
    info["kept_dents"] = filled
    keep, restored = restore_until_manifold(mesh.vertices, T, ~drop, drop)
    info["restored_for_manifold"] = restored
    info["pruned"] = int((~keep).sum())
    sub = TetMesh(mesh.vertices, T[keep], validate=False)
    labels, n = sub.components()
    ids = np.flatnonzero(keep)
    removed = 0
    if n > 1:
        largest = labels == np.argmax(np.bincount(labels))
        removed = int((~largest).sum())
        ids = ids[largest]
    model.keep(ids)
    info.update(removed_components=max(n - 1, 0), tets_removed_by_component=removed, tets_after=model.num_tets)
    return info
