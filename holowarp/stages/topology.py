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
mesh, the largest face-connected component is kept and the rest counted (scene level,
``TopologyConfig.min_component``: every component above a size threshold). After the FIRST
prune the surfel scales are recomputed (0.65 x mean centroid-to-vertex distance) and become
learnable, and opacities become free parameters initialised from the field. With
``TopologyConfig.refine_rings`` > 0, the prune ``refine_at_prune`` is followed by a bisection
of the tets near the boundary (:func:`refine_near_surface`; the fast preset: after its last
prune): the surfels follow their parent tets, so what follows (the last Gaussian steps and
mesh-only block) works finer than the initial edge length alone allows (issues 12 and 16).

The field is initialised SDF-like (method.md leaves this open): ``phi_init="visual_hull"``
labels each vertex inside/outside the masks' visual hull (:func:`holowarp.carve.inside_hull`)
and sets phi to the signed graph distance to the label interface along mesh edges
(negative inside), which is what the eikonal term expects; ``"depth_hull"`` (the default)
also labels outside the vertices some views see in front of the stage-0 surfels' surface,
so the start already holds the concavities the silhouettes miss (without stage-0 depth maps
it is the visual hull); ``"inside"`` starts every vertex at ``-phi_inside`` (all tets opaque). :func:`init_model` builds the §4 model (one surfel per
tet) with that field and colours sampled from the images.
"""

from __future__ import annotations

import numpy as np
import torch

from holowarp.camera import project_points
from holowarp.carve import depth_from_normals, hull_genus, in_front_of_surface, inside_hull
from holowarp.config import TopologyConfig, kept_components
from holowarp.manifold import fill_sealed, open_to_outside, restore_elsewhere, restore_until_manifold
from holowarp.tetgs import TetGaussians
from holowarp.tetmesh import TetMesh

__all__ = [
    "refit_appearance",
    "refine_near_surface",
    "GaussianOptimizers",
    "ViewTensors",
    "EmptyEvidence",
    "depth_carved",
    "surfel_depth_maps",
    "after_first_prune",
    "gaussian_step",
    "init_colors",
    "init_model",
    "init_model_from_surfels",
    "init_phi",
    "prune",
    "prune_message",
]


def surfel_depth_maps(gaussians_ply, dataset, views, *, device="cpu", config: TopologyConfig | None = None):
    """What the depth carve tests against: ``(depths, alphas, corrected)``, the median depth
    and opacity maps (len(views), H, W) of the stage-0 surfels in ``gaussians_ply`` seen by
    ``views`` (the 2DGS surface), and those depths corrected by the dataset's normal maps
    (:func:`holowarp.carve.depth_from_normals` with ``config``'s ``depth_normals_*``), or
    None (no normal maps, no ``config``, or ``config.depth_carve_normals`` off)."""
    from holowarp.gaussians import GaussianModel

    g = GaussianModel.from_ply(gaussians_ply, device=device)
    depths = np.empty((len(views), dataset.height, dataset.width), np.float32)
    alphas = np.empty_like(depths)
    with torch.no_grad():
        for j, v in enumerate(views):
            out = g.render(dataset.viewmats[v], dataset.K[v], dataset.width, dataset.height)
            depths[j] = out["median_depth"].cpu().numpy()
            alphas[j] = out["alpha"].cpu().numpy()
    corrected = None
    if config is not None and config.depth_carve_normals and dataset.normals is not None:
        corrected = np.stack([depth_from_normals(depths[j], alphas[j], dataset.normals[v], dataset.viewmats[v],
                                                 dataset.K[v], jump=config.depth_normals_jump,
                                                 crease=config.depth_normals_crease,
                                                 grazing=config.depth_normals_grazing, rim=config.depth_normals_rim)
                              for j, v in enumerate(views)])
    return depths, alphas, corrected


def depth_carved(dataset, points, views, depth_maps, config: TopologyConfig, *, tol: float,
                 lid: tuple[float, float] | None = None) -> np.ndarray:
    """(P,) bool: ``points`` the depth maps show empty: in front of the stage-0 surface
    (``depth_maps[:2]``, depths and alphas) in ``config.depth_carve_min_views`` of ``views``,
    or in front of the normal-corrected surface (``depth_maps[2]`` when present and not None)
    in ``config.depth_normals_min_views`` (:attr:`TopologyConfig.depth_carve_normals`), by
    more than ``tol``. ``lid`` = ``(gap, lid_tol)``: against the corrected surface, pixels
    whose corrected depth lies more than ``gap`` behind the stage-0 depth
    (:func:`holowarp.carve.lid_pixels`, a lid over a cavity) use ``lid_tol`` instead."""
    depths, alphas, *rest = depth_maps
    carved = in_front_of_surface(dataset, points, views, depths, alphas, tol=tol, min_views=config.depth_carve_min_views,
                                 window=config.depth_carve_window)
    if rest and rest[0] is not None:
        t = tol
        if lid is not None:
            from holowarp.carve import lid_pixels

            t = np.stack([np.where(lid_pixels(depths[j], alphas[j], rest[0][j], gap=lid[0],
                                              window=config.depth_carve_window)[0], lid[1], tol)
                          for j in range(len(views))])
        carved |= in_front_of_surface(dataset, points, views, rest[0], alphas, tol=t,
                                      min_views=config.depth_normals_min_views, window=config.depth_carve_window)
    return carved


class EmptyEvidence:
    """Which tets some training view shows to be empty space: their centroid projects outside
    a silhouette (outside the visual hull), or lies in front of the stage-0 surfels' surface
    in enough views (:func:`depth_carved`; the prune's topology guards). The surfels' depth
    maps (:meth:`maps`) are rendered and corrected once, on first use, and the pipeline hands
    the same maps to the vertex field's start (:func:`init_model_from_surfels`); a run without
    stage-0 surfels (a checkpoint made without stage 0) has the silhouettes' evidence only."""

    def __init__(self, gaussians_ply, dataset, config: TopologyConfig, *, device="cpu"):
        self.ply, self.ds, self.cfg, self.device = gaussians_ply, dataset, config, device
        self.views = _carve_views(dataset.train_idx, config)
        self._maps = None
        self._hull_genus = None

    def hull_genus(self, mesh: TetMesh) -> int:
        """The genus of the training masks' visual hull around ``mesh`` (its box grown by a
        tenth of its size on every side, so a hull a little larger than the mesh is not cut;
        :func:`holowarp.carve.hull_genus`), computed on the first call and kept: the most
        tunnels the views can show, the bound of the prune's genus guard."""
        if self._hull_genus is None:
            lo, hi = mesh.vertices.min(axis=0), mesh.vertices.max(axis=0)
            pad = 0.1 * float((hi - lo).max())
            self._hull_genus = hull_genus(self.ds, lo - pad, hi + pad, self.ds.train_idx, device=self.device)
        return self._hull_genus

    def __call__(self, mesh: TetMesh) -> np.ndarray:
        """(M,) bool: the tets some view shows empty, ``outside | in_front`` of :meth:`parts`."""
        outside, in_front = self.parts(mesh)
        return outside | in_front

    def maps(self):
        """:func:`surfel_depth_maps` of the carve views (computed on the first call and kept),
        or None without stage-0 surfels."""
        from pathlib import Path

        if self._maps is None and Path(self.ply).is_file():
            self._maps = surfel_depth_maps(self.ply, self.ds, self.views, device=self.device, config=self.cfg)
        return self._maps

    def parts(self, mesh: TetMesh) -> tuple[np.ndarray, np.ndarray]:
        """The evidence by its source, two (M,) bool: ``outside`` (the centroid projects
        outside some training silhouette: exact where the masks are) and ``in_front`` (in
        front of the stage-0 surface in enough views, :meth:`in_front`)."""
        c = mesh.vertices[mesh.tets].mean(axis=1)
        return ~inside_hull(self.ds, c, self.ds.train_idx, device=self.device), self.in_front(mesh)

    def in_front(self, mesh: TetMesh, *, tol: float | None = None, lid: tuple[float, float] | None = None) -> np.ndarray:
        """(M,) bool: the tets whose centroid lies in front of the stage-0 surface (or of its
        normal-corrected depth) in enough views by more than ``tol`` mean edge lengths of
        ``mesh`` (default ``depth_carve_tol``; :func:`depth_carved`, whose ``lid`` (gap,
        tolerance) this takes in mean edges too): as good as the surfels' depth; all False
        without stage-0 surfels."""
        maps = self.maps()
        if maps is None:
            return np.zeros(mesh.num_tets, dtype=bool)
        edge = _carve_tol(mesh, 1.0)
        tol = edge * (self.cfg.depth_carve_tol if tol is None else tol)
        lid = None if lid is None else (edge * lid[0], edge * lid[1])
        return depth_carved(self.ds, mesh.vertices[mesh.tets].mean(axis=1), self.views, maps, self.cfg, tol=tol,
                            lid=lid)


def _carve_tol(mesh: TetMesh, factor: float) -> float:
    """The depth carve's margin: ``factor`` mean edge lengths of ``mesh``."""
    E = mesh.edges()
    return factor * float(np.linalg.norm(mesh.vertices[E[:, 0]] - mesh.vertices[E[:, 1]], axis=1).mean())


def _carve_views(views, config: TopologyConfig) -> np.ndarray:
    views = np.asarray(views)
    return views[:: max(1, len(views) // config.depth_carve_views)]


def init_phi(mesh: TetMesh, dataset, views, config: TopologyConfig, *, depth_maps=None) -> np.ndarray:
    """Initial vertex field (V,), see the module docstring. ``depth_maps`` (the stage-0
    surfels' ``(depths, alphas[, corrected])`` at ``_carve_views(views)``,
    :func:`surfel_depth_maps`) is what ``"depth_hull"`` carves with (:func:`depth_carved`);
    without them it gives the visual hull's field."""
    V = mesh.num_vertices
    if config.phi_init == "inside":
        return np.full(V, -config.phi_inside)
    if config.phi_init not in ("visual_hull", "depth_hull"):
        raise ValueError(f"phi_init must be 'visual_hull', 'depth_hull' or 'inside', got {config.phi_init!r}")
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import dijkstra

    inside = inside_hull(dataset, mesh.vertices, views, tolerance=config.hull)
    if config.phi_init == "depth_hull" and depth_maps is not None:
        inside &= ~depth_carved(dataset, mesh.vertices, _carve_views(views, config), depth_maps, config,
                                tol=_carve_tol(mesh, config.depth_carve_tol))
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


def init_colors(mesh: TetMesh, dataset, views, config: TopologyConfig) -> np.ndarray:
    """Initial surfel colours (M, 3): mean image colour at the tet centroid's projection over
    every k-th training view (at most ``color_init_views``) where it falls inside the mask
    (grey where none), clipped to ``[color_init_clip, 1 - color_init_clip]``."""
    c = mesh.vertices[mesh.tets].mean(axis=1)
    views = np.asarray(views)[:: max(1, len(views) // config.color_init_views)]
    acc = np.zeros((len(c), 3))
    cnt = np.zeros(len(c))
    H, W = dataset.height, dataset.width
    for v in views:
        uv, z = project_points(c, dataset.viewmats[v], dataset.K[v])
        u = np.floor(uv[:, 0]).astype(np.int64)
        w = np.floor(uv[:, 1]).astype(np.int64)
        ok = (z > 1e-6) & (u >= 0) & (u < W) & (w >= 0) & (w < H)
        ok[ok] &= dataset.masks[v][w[ok], u[ok]] > 0.5
        acc[ok] += dataset.images[v][w[ok], u[ok]]
        cnt[ok] += 1
    lo = config.color_init_clip
    return np.where(cnt[:, None] > 0, acc / np.maximum(cnt, 1)[:, None], 0.5).clip(lo, 1.0 - lo)


def init_model(mesh: TetMesh, dataset, views, config: TopologyConfig, *, seed: int = 0, device="cpu",
               depth_maps=None) -> TetGaussians:
    """The §4/§5 model of ``mesh``: one surfel per tet, the initial field and colours.

    In the ablation "w/o continuous opacity" the per-tet opacities start from the same field,
    so the comparison isolates the parameterisation (no shared vertices, no eik/smooth)."""
    model = TetGaussians(mesh, colors=init_colors(mesh, dataset, views, config),
                         phi=init_phi(mesh, dataset, views, config, depth_maps=depth_maps), config=config,
                         device=device, seed=seed)
    if not config.continuous_opacity:
        model.freeze_opacity_from_field()
    return model


def init_model_from_surfels(gaussians_ply, dataset, tet_config, config: TopologyConfig, *, seed: int = 0,
                            device="cpu", progress: bool = True, pieces=None, depth_maps=None) -> TetGaussians:
    """§4 then the start of §5: the scaled convex hull of the stage-0 surfels in
    ``gaussians_ply``, tetrahedralised with fTetWild (:func:`holowarp.stages.tet_init.initial_tetmesh`;
    ``pieces``: a scene's objects' bounding boxes, each meshed at its own edge length),
    and its model (:func:`init_model`) on the training views. ``depth_maps``: the carve's
    :func:`surfel_depth_maps` when the caller has them (:meth:`EmptyEvidence.maps`), else
    they are made here (with ``phi_init`` "depth_hull")."""
    from holowarp.gaussians import load_gaussians_ply
    from holowarp.progress import say
    from holowarp.stages.tet_init import initial_tetmesh

    say(f"tetrahedralising the {tet_config.hull_scale}x convex hull of the stage-0 surfels with fTetWild "
        f"(edge length {tet_config.edge_length_fac} x bbox diagonal"
        f"{f' of each of the {len(pieces)} objects' if pieces else ''})", progress)
    g = load_gaussians_ply(gaussians_ply)
    mesh = initial_tetmesh(g["means"], g["opacities"], tet_config, pieces=pieces, seed=seed)
    say(f"initial tet mesh: {mesh.num_tets} tets, {mesh.num_vertices} vertices", progress)
    maps = depth_maps
    if maps is None and config.phi_init == "depth_hull":
        maps = surfel_depth_maps(gaussians_ply, dataset, _carve_views(dataset.train_idx, config), device=device,
                                 config=config)
    return init_model(mesh, dataset, dataset.train_idx, config, seed=seed, device=device, depth_maps=maps)


def refine_near_surface(model: TetGaussians, config: TopologyConfig, dataset=None) -> dict | None:
    """Bisect the tets near the boundary (``config.refine_rings``, ``refine_factor``,
    ``refine_where``; :mod:`holowarp.refine`), the surfels following
    (:meth:`TetGaussians.apply_refine`). ``dataset`` (its training masks) is needed by
    ``refine_where="silhouette"``. Returns None when off, else ``{"band", "target",
    "tets_before", "tets_after"}`` (``band``: the tets marked; target in scene units).
    Topology, boundary and field are unchanged by construction."""
    if config.refine_rings <= 0 or model.num_tets == 0:
        return None
    from holowarp.refine import bisect_longest_edges, boundary_band, edge_table

    mesh = model.mesh()
    band = boundary_band(mesh.tets, mesh.num_vertices, mesh.surface_vertices(), config.refine_rings)
    if config.refine_where == "silhouette":
        if dataset is None:
            raise ValueError("refine_near_surface: refine_where='silhouette' needs the dataset's masks")
        inside = inside_hull(dataset, mesh.vertices, dataset.train_idx, tolerance=config.hull)
        band &= ~inside[mesh.tets].all(axis=1)
        if not band.any():
            return {"band": 0, "target": 0.0, "tets_before": model.num_tets, "tets_after": model.num_tets}
    _, _, length, longest = edge_table(mesh.vertices, mesh.tets)
    target = float(config.refine_factor * np.median(length[longest[band]]))
    V, T, parent, new = bisect_longest_edges(mesh.vertices, mesh.tets, band, target)
    before = model.num_tets
    model.apply_refine(V, T, parent, new)
    return {"band": int(band.sum()), "target": target, "tets_before": before, "tets_after": model.num_tets}


def after_first_prune(model: TetGaussians) -> None:
    """§5: after the first prune, scales are recomputed from the tets and become learnable,
    and opacities become free parameters initialised from the current field."""
    model.reset_scales()
    model.freeze_opacity_from_field()


class ViewTensors:
    """The training images composited on ``background`` (N, H, W, 3), the masks (N, H, W),
    the optional normal maps (N, H, W, 3) and the cameras on the model's device, uploaded once.

    ``pieces`` (a scene, method.md §11): the objects' boxes ``[(lo (3,), hi (3,)), ...]``
    (:func:`holowarp.stages.objects.hull_pieces`), kept as ``boxes`` (P, 2, 3); the ranked
    normal losses then rank each object's pixels apart (:func:`pixel_objects`). Else None."""

    def __init__(self, dataset, device, background=(0.0, 0.0, 0.0), *, pieces=None):
        self.background = torch.as_tensor(background, dtype=torch.float32, device=device)
        self.images = torch.as_tensor(dataset.composite(background), device=device)
        self.masks = torch.as_tensor(dataset.masks, device=device)
        self.boxes = (None if pieces is None else
                      torch.as_tensor(np.array([[lo, hi] for lo, hi in pieces]), dtype=torch.float32, device=device))
        self.normals = torch.as_tensor(dataset.normals, device=device) if dataset.normals is not None else None
        # Cameras: (N, 4, 4) and (N, 3, 3) float32 on the device for the losses, and float64
        # on the host for the rasteriser, which reads them there (no per-step upload or read-back).
        self.viewmats = torch.as_tensor(dataset.viewmats, dtype=torch.float32, device=device)
        self.K = torch.as_tensor(dataset.K, dtype=torch.float32, device=device)
        self.viewmats_host = torch.as_tensor(dataset.viewmats, dtype=torch.float64)
        self.K_host = torch.as_tensor(dataset.K, dtype=torch.float64)


def pixel_objects(depth: torch.Tensor, K: torch.Tensor, viewmat: torch.Tensor, boxes: torch.Tensor | None):
    """``(labels (H, W), P)``: for each pixel, the object (index into ``boxes`` (P, 2, 3)) whose
    box is nearest the surface point its camera-z ``depth`` [H, W] places there; None without
    boxes (one object). Pixels without depth get some label; the losses skip them anyway."""
    if boxes is None:
        return None
    from holowarp.losses import depth_to_points, nearest_box

    return nearest_box(depth_to_points(depth.detach(), K, viewmat), boxes), int(boxes.shape[0])


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
    tensors: ViewTensors,
) -> dict:
    """One main-loop step on view ``view``; returns the loss terms as detached 0-dim tensors
    (read them in batches: :class:`holowarp.progress.LossBuffer`, which also stops a run
    whose loss is not finite)."""
    from holowarp import losses

    H, W = dataset.height, dataset.width
    vm, Kt = tensors.viewmats[view], tensors.K[view]
    out = model.render(tensors.viewmats_host[view], tensors.K_host[view], W, H, background=tensors.background)
    gt = tensors.images[view]
    m = tensors.masks[view]
    l_rgb = losses.l1_dssim_loss(out["rgb"], gt, lambda_dssim=config.dssim_weight)
    l_mask = losses.mask_loss(out["alpha"], m)
    # Depth-derived normals from the median depth (robust at silhouettes, as 2DGS does for
    # bounded objects), compared where the surfels are opaque.
    n_depth = losses.depth_to_normal(out["median_depth"], Kt, vm)
    opaque = out["alpha"].detach() > 0.5
    frac = config.normal_rank_fraction
    groups = pixel_objects(out["median_depth"], Kt, vm, tensors.boxes)
    l_normal = losses.ranked_normal_loss(out["normal"], n_depth, mask=opaque, top_fraction=frac, groups=groups)
    loss = config.w_rgb * l_rgb + config.w_mask * l_mask + config.w_normal * l_normal
    terms = {"rgb": l_rgb, "mask": l_mask, "normal": l_normal}
    if tensors.normals is not None and config.w_prior > 0:
        prior = tensors.normals[view]
        e, has = losses.prior_error(prior, out["normal"], n_depth)
        has = opaque & has & (n_depth.norm(dim=-1) > 0.5)
        l_prior = losses.ranked_loss(e, mask=has, top_fraction=frac, groups=groups)
        loss = loss + config.w_prior * l_prior
        terms["prior"] = l_prior
    if topology_phase and not model.free_opacity and edges is not None:
        from holowarp.energies import phi_edge_losses

        l_eik, l_smooth = phi_edge_losses(model.phi, edges, model.vertices.detach())
        loss = loss + config.lam_eik * l_eik + config.lam_smooth * l_smooth
        terms.update(eik=l_eik, smooth=l_smooth)
    optimizers.zero_grad()
    loss.backward()
    optimizers.step()
    with torch.no_grad():
        # Keep rotations unit and kappa inside its clamp range (method.md §5).
        model.quats.data /= model.quats.data.norm(dim=1, keepdim=True).clamp_min(1e-12)
        lo, hi = model.kappa_clamp
        model.kappa.data.clamp_(lo / model.s, hi / model.s)
    terms["loss"] = loss
    return {k: v.detach() for k, v in terms.items()}


def refit_appearance(model: TetGaussians, dataset, config: TopologyConfig, steps: int, *, seed: int = 0,
                     device="cpu") -> dict:
    """``steps`` Gaussian-only steps on random training views (colours, rotations, opacities
    and log-scales; the vertices and tets stay as they are), after an operation that moved
    surfels without refitting them (the element improvement, method.md §7b).

    Returns ``{"steps", "rgb_before", "rgb_after"}``: the mean L1+D-SSIM colour loss of the
    first and last tenth of the steps (None when ``steps`` is 0).
    """
    if steps <= 0:
        return {"steps": 0, "rgb_before": None, "rgb_after": None}
    tensors = ViewTensors(dataset, device)
    opts = GaussianOptimizers(model, config, learn_scales=True)
    train = np.asarray(dataset.train_idx)
    # Seeded apart from the main loop's views (its stream is [seed, 0, i]).
    views = train[np.random.default_rng([seed, 7]).integers(len(train), size=steps)]
    rgb = [gaussian_step(model, dataset, int(v), config, opts, topology_phase=False, edges=None,
                         tensors=tensors)["rgb"] for v in views]
    tenth = max(1, steps // 10)
    rgb = torch.stack(rgb).cpu().numpy()
    return {"steps": int(steps), "rgb_before": float(rgb[:tenth].mean()), "rgb_after": float(rgb[-tenth:].mean())}


#: The counts of :func:`prune`'s report, all 0 when it prunes nothing because it would empty the mesh.
_PRUNE_COUNTS = ("pruned", "kept_cavity", "kept_dents", "kept_pits", "restored_for_manifold", "restored_elsewhere",
                 "filled_sealed", "kept_for_genus", "kept_for_split", "genus_over_bound", "removed_components",
                 "raw_components", "raw_non_manifold", "tets_removed_by_component")


def prune(model: TetGaussians, config: TopologyConfig, *, evidence=None, outside=None, genus_bound=None, in_front=None) -> dict:
    """Delete tets with alpha < prune_alpha and the vertices no tet uses (method.md §5).

    Guards keep the result a simulation-ready solid whose topology follows the images
    (method.md §0: one connected, boundary-manifold mesh):

    - pruning never opens a sealed cavity: low-alpha tets that do not connect, through other
      low-alpha tets, to the current boundary are invisible in every view and stay;
    - pruning never digs one-tet dents: a low-alpha tet with three or four faces on kept
      tets stays (repeated a few times);
    - pruning never digs pits: a vertex the prune would expose while its kept tets still
      fill more than ``pit_solid_fraction`` of the full solid angle around it keeps its
      tets (a multi-tet dent the face rule misses), except tets ``evidence`` shows empty;
    - pruning never makes the boundary non-manifold: the pruned tets around any
      non-manifold edge or vertex are restored, repeatedly, until the boundary is a
      manifold. Restoring every pruned tet gives back the (manifold) mesh before the
      prune, so this terminates with a manifold boundary whenever the input had one;
      with ``outside`` (M,) bool (the tets whose centroid projects outside a training
      silhouette, :meth:`EmptyEvidence.parts`) and ``config.restore_elsewhere``, restored
      tets among them go again wherever restoring other pruned tets mends the boundary
      instead, with the same topology (:func:`holowarp.manifold.restore_elsewhere`);
    - pruning never leaves a sealed void (:func:`_fill_sealed_voids`);
    - with ``evidence`` (M,) bool, the tets some view shows to be empty space (outside a
      silhouette, or in front of the rendered surface): if the tets no view shows empty
      decide the topology (the prune with them and the prune without them leave different
      genera, ``config.genus_guard``, or only the first cuts off a piece of more than
      ``config.split_guard`` of the kept tets), the prune is the second: every such blind
      tet stays, so topology follows the images, never the thickness of the tets (the
      later prunes still take blind tets wherever they leave the topology as it is);
    - ``in_front`` (M,) bool tets (:meth:`EmptyEvidence.in_front`) are pruned whatever their
      opacity, under the same guards (:attr:`TopologyConfig.prune_in_front`);
    - the genus guard never takes the genus above ``genus_bound`` (an int, or a callable
      giving it: the visual hull's genus, :func:`_guarded_by_evidence`).

    If pruning would empty the mesh, nothing is pruned (and the report says so). If it
    splits the mesh, the largest face-connected component is kept and the rest counted;
    with ``config.min_component`` (scene level, method.md §11) every component with at
    least that fraction of the kept tets stays.

    Returns:
        dict: ``tets_before``, ``pruned`` (removed), ``low_alpha``, ``in_front`` (the opaque
        tets ``in_front`` adds, when given), ``raw_components`` and ``raw_non_manifold`` (face-connected pieces and non-manifold
        boundary edges + vertices the plain rule would have left, before the guards below),
        ``kept_cavity`` (low-alpha tets kept because sealed), ``kept_dents`` (low-alpha tets
        kept because three or more of their faces meet kept tets), ``kept_pits``,
        ``restored_for_manifold``, ``restored_elsewhere`` (restored tets outside a silhouette
        swapped for other pruned ones), ``kept_for_genus``, ``kept_for_split`` (low-alpha tets kept
        by the guards), ``genus_over_bound``, ``filled_sealed`` (put back: sealed),
        ``genus_before``, ``genus_after``, ``removed_components``, ``tets_removed_by_component``,
        ``tets_after``, ``emptied``, and with ``config.min_component`` ``kept_components``.
    """
    mesh = model.mesh()
    M = model.num_tets
    info = {"tets_before": M, "low_alpha": 0, "emptied": False}
    low = _prune_candidates(model, config, in_front, info)
    if low.all():
        return {**info, **dict.fromkeys(_PRUNE_COUNTS, 0), "emptied": True, "tets_after": M}
    adj = mesh.face_adjacency()
    drop = open_to_outside(low, adj)
    info["kept_cavity"] = int((low & ~drop).sum())
    info.update(_raw_counts(mesh, drop))
    info["kept_dents"] = _keep_dents(drop, adj, config)
    info["kept_pits"] = _keep_pits(mesh, drop, config, evidence if config.uses_evidence else None)
    seen = np.asarray(outside, dtype=bool) if outside is not None and config.restore_elsewhere else None
    keep, ids, n, removed, n_kept = _guarded_keep(mesh, drop, info, config.min_component, seen=seen)
    info["genus_before"] = int(mesh.genus())
    info["kept_for_genus"] = info["kept_for_split"] = info["genus_over_bound"] = 0
    if evidence is not None and config.uses_evidence:
        evidence = np.asarray(evidence, dtype=bool)
        guarded = _guarded_by_evidence(mesh, drop, evidence, (ids, removed), info, config, genus_bound)
        if guarded is not None:
            ids, n, removed, n_kept = guarded
    ids, removed = _fill_sealed_voids(ids, removed, drop, adj, info)
    info["pruned"] = int(M - len(ids) - removed)
    model.keep(ids)
    info.update(removed_components=max(n - n_kept, 0), tets_removed_by_component=removed, tets_after=model.num_tets,
                genus_after=int(model.mesh().genus()))
    if config.min_component is not None:
        info["kept_components"] = n_kept
    return info


def _prune_candidates(model: TetGaussians, config: TopologyConfig, in_front, info: dict) -> np.ndarray:
    """(M,) bool: the tets below ``prune_alpha``, and the ``in_front`` ones (None: none);
    counted in ``info`` as ``low_alpha`` and ``in_front`` (the opaque ones it adds)."""
    with torch.no_grad():
        low = model.opacities().cpu().numpy() < config.prune_alpha
    info["low_alpha"] = int(low.sum())
    if in_front is not None:
        in_front = np.asarray(in_front, dtype=bool)
        info["in_front"] = int((in_front & ~low).sum())
        low = low | in_front
    return low


def _raw_counts(mesh: TetMesh, drop: np.ndarray) -> dict:
    """What the plain rule (delete every open low-alpha tet) would leave, the measure of how
    coherent the opacities are (the paper's "Num. components" of its ablation):
    ``raw_components`` and ``raw_non_manifold`` (non-manifold boundary edges + vertices)."""
    raw = TetMesh(mesh.vertices, mesh.tets[~drop], validate=False)
    return {"raw_components": int(raw.num_components()),
            "raw_non_manifold": int(len(raw.non_manifold_edges()) + len(raw.non_manifold_vertices()))}


def _fill_sealed_voids(ids: np.ndarray, removed: int, drop: np.ndarray, adj: np.ndarray, info: dict):
    """The guards put tets back, and one at the mouth of a pruned region seals what lies
    behind it: a void no view sees, a second boundary shell (the mug of the quality suite,
    fast preset, had two, of 14 and 8 faces). After the guards, every pruned tet that no
    longer connects to the outside through other pruned tets is put back
    (:func:`holowarp.manifold.fill_sealed`). Returns (kept ids, tets removed with cut-off
    pieces) and sets ``info["filled_sealed"]``."""
    kept = np.zeros(len(drop), dtype=bool)
    kept[ids] = True
    kept, info["filled_sealed"] = fill_sealed(kept, adj)
    if not info["filled_sealed"]:
        return ids, removed
    # Tets neither kept nor dropped for low alpha went with cut-off pieces.
    return np.flatnonzero(kept), int((~kept & ~drop).sum())


def _guarded_by_evidence(mesh: TetMesh, drop, evidence, plain: tuple, info: dict, config: TopologyConfig,
                         genus_bound=None):
    """The prune's topology guards (:func:`prune`, :func:`_topology_guard`): None when the
    tets no view shows empty (``drop & ~evidence``) do not decide the topology, else the
    guarded prune as (kept ids, components, tets removed with cut-off pieces, components
    kept): the evidence-only prune, every blind tet kept. Sets the tripped guard's ``info``
    key to the blind tets kept.

    Every blind tet, not only those whose removal would change the topology. Removing the
    others one at a time wherever each removal kept the topology (lowest alpha first, as
    the prune did before 2026-12-06) dug the blind regions out down to membranes one tet
    short of the cut: the quality suite's plate, whose first prune cuts its thin bars (two
    tets across) unless the split guard trips, kept its bars as slit membranes that way.
    Fast, 128², hull in brackets, seed 0 / seed 1: Chamfer-L1 0.00216 / 0.00206 -> 0.00196
    / 0.00199 (0.00230), F@0.005 0.973 / 0.982 -> 0.987 / 0.986 (0.984), normal consistency
    0.954 / 0.963 -> 0.972 / 0.968 (0.960), volume IoU 0.932 / 0.941 -> 0.945 / 0.948
    (0.914), Hausdorff 0.025 / 0.025 (at a slit) -> 0.022 / 0.012 (0.009; seed 0's is now a
    web in a hole's corner). Removing whole face-connected groups of blind tets wherever a
    group's removal kept the topology was worse (seed 0: F@0.005 0.963, normal consistency
    0.955, worst dihedral 2.7°): a group that ends inside a bar still cuts a notch into it.

    ``genus_bound`` (an int, or a callable giving it, called only when needed): the genus
    guard does not keep an evidence-only prune whose genus exceeds both the plain prune's
    and this bound, the genus of the masks' visual hull
    (:meth:`EmptyEvidence.hull_genus`); the prune then goes ahead unguarded and
    ``info["genus_over_bound"]`` is the genus refused. A tunnel some view sees through is a
    tunnel of the visual hull, so such a prune would add a handle no view shows. That
    happens where the evidence removes part of a skin of low-alpha tets outside a wall and
    keeps the rest, whose centroids sit just inside the silhouettes: the plate of the
    quality suite (fast, 128², seed 0) came out with genus 4 instead of 3 that way at its
    last prune."""
    blind = drop & ~evidence
    if not blind.any():
        return None
    alt: dict = {}
    _, ids, n, removed, n_kept = _guarded_keep(mesh, drop & ~blind, alt, config.min_component)
    guard = _topology_guard(mesh, plain, (ids, removed), config, genus_bound, info)
    if guard is None:
        return None
    info["restored_for_manifold"], info["restored_elsewhere"] = alt["restored_for_manifold"], 0
    info[guard] = int(blind[ids].sum())
    return ids, n, removed, n_kept


def _topology_guard(mesh: TetMesh, plain: tuple, seen: tuple, config: TopologyConfig, genus_bound=None,
                    info: dict | None = None) -> str | None:
    """Which guard a prune trips, as its report key, or None: the plain prune (``plain``:
    kept tet ids, tets removed with cut-off pieces) against the one that prunes only tets
    some view shows to be empty (``seen``, the same pair).

    ``"kept_for_split"`` (``config.split_guard``): the plain prune cuts off pieces holding
    more than that fraction of the tets it keeps, and the images keep more of them.
    ``"kept_for_genus"`` (``config.genus_guard``): the two leave different genera, so tets
    no view shows empty decide a tunnel or a handle (the plain prune's genus may even equal
    the one before: three handles cut while three tunnels open); unless the second's genus
    exceeds both the first's and ``genus_bound`` (:func:`_guarded_by_evidence`), which then
    goes to ``info["genus_over_bound"]``."""
    if config.split_guard is not None and plain[1] > config.split_guard * len(plain[0]) and seen[1] < plain[1]:
        return "kept_for_split"
    if config.genus_guard:
        g_plain = TetMesh(mesh.vertices, mesh.tets[plain[0]], validate=False).genus()
        g_seen = TetMesh(mesh.vertices, mesh.tets[seen[0]], validate=False).genus()
        if g_plain == g_seen:
            return None
        if genus_bound is not None and g_seen > g_plain:
            if g_seen > (genus_bound() if callable(genus_bound) else int(genus_bound)):
                if info is not None:
                    info["genus_over_bound"] = int(g_seen)
                return None
        return "kept_for_genus"
    return None


def _guarded_keep(mesh: TetMesh, drop: np.ndarray, info: dict, min_component: float | None = None, seen=None):
    """The manifold guard and the component rule (:func:`holowarp.config.kept_components`:
    the largest only, or every one above ``min_component`` of the kept tets): (keep mask,
    kept ids, components, tets removed with the dropped components, components kept);
    ``info["restored_for_manifold"]`` is set.

    With ``seen`` (M,) bool, the tets outside a silhouette, the restored ones among them
    go again wherever restoring other dropped tets mends the boundary instead
    (:func:`holowarp.manifold.restore_elsewhere`); ``info["restored_elsewhere"]`` counts
    them (see ``TopologyConfig.restore_elsewhere``)."""
    T = mesh.tets
    keep, _ = restore_until_manifold(mesh.vertices, T, ~drop, drop)
    info["restored_elsewhere"] = 0
    if seen is not None:
        keep, info["restored_elsewhere"] = restore_elsewhere(mesh.vertices, T, keep, drop & seen, drop & ~seen)
    info["restored_for_manifold"] = int((keep & drop).sum())
    labels, n = TetMesh(mesh.vertices, T[keep], validate=False).components()
    ids = np.flatnonzero(keep)
    removed, n_kept = 0, min(n, 1)
    if n > 1:
        kept = kept_components(labels, n, min_component)
        removed = int((~kept).sum())
        n_kept = len(np.unique(labels[kept]))
        ids = ids[kept]
    return keep, ids, n, removed, n_kept


def _corner_solid_angles(V: np.ndarray, T: np.ndarray) -> np.ndarray:
    """(M, 4) solid angle (steradians) of each tet at each of its corners (Van Oosterom and
    Strackee 1983)."""
    out = np.empty(T.shape, dtype=np.float64)
    for k in range(4):
        o = [(k + 1) % 4, (k + 2) % 4, (k + 3) % 4]
        a, b, c = (V[T[:, j]] - V[T[:, k]] for j in o)
        la, lb, lc = (np.linalg.norm(x, axis=1) for x in (a, b, c))
        num = np.abs(np.einsum("ij,ij->i", a, np.cross(b, c)))
        den = la * lb * lc + np.einsum("ij,ij->i", a, b) * lc + np.einsum("ij,ij->i", a, c) * lb \
            + np.einsum("ij,ij->i", b, c) * la
        out[:, k] = 2.0 * np.arctan2(num, den)
    return out


def _keep_pits(mesh: TetMesh, drop: np.ndarray, config: TopologyConfig, seen_empty: np.ndarray | None = None) -> int:
    """Take out of ``drop`` (in place) the tets around vertices the prune would leave in a
    pit; returns how many. A vertex is in a pit when it is interior now, would be on the
    boundary after the prune, and its kept tets fill more than ``pit_solid_fraction`` of the
    4 pi steradians around it (the bottom of a hole one or two tets deep). A tet some view
    shows to be empty (``seen_empty`` (M,) bool, the prune's evidence) is never kept: a dent
    the images show (the dented box's, in front of the stage-0 surface) is carved, a pit
    only low opacities dig is not."""
    if config.pit_solid_fraction >= 1.0:
        return 0
    T, N = mesh.tets, mesh.num_vertices
    if seen_empty is not None:
        seen_empty = np.asarray(seen_empty, dtype=bool)
    omega = _corner_solid_angles(mesh.vertices, T)
    interior = np.ones(N, dtype=bool)
    interior[mesh.surface_vertices()] = False
    filled = 0
    for _ in range(config.pit_rounds):
        kept = np.zeros(N)
        np.add.at(kept, T[~drop].ravel(), omega[~drop].ravel())
        exposed = np.zeros(N, dtype=bool)
        exposed[T[drop].ravel()] = True
        pit = interior & exposed & (kept > config.pit_solid_fraction * 4.0 * np.pi)
        back = drop & pit[T].any(axis=1)
        if seen_empty is not None:
            back &= ~seen_empty
        if not back.any():
            break
        drop &= ~back
        filled += int(back.sum())
    return filled


def _keep_dents(drop: np.ndarray, adj: np.ndarray, config: TopologyConfig) -> int:
    """Take tets that would leave one-tet pits out of ``drop`` (in place); returns how many.

    A tet with ``dent_faces`` or more of its faces on kept tets would leave a one-tet pit in
    the surface. A single transparent surfel among opaque neighbours is a rendering artefact
    (it is redundant where its neighbours already cover its pixels), not evidence of empty
    space, so such tets stay; pruning keeps removing coherent regions."""
    filled = 0
    for _ in range(config.dent_rounds):
        kept_nb = np.where(adj >= 0, ~drop[np.maximum(adj, 0)], False).sum(axis=1)
        dent = drop & (kept_nb >= config.dent_faces)
        if not dent.any():
            break
        drop &= ~dent
        filled += int(dent.sum())
    return filled


def prune_message(info: dict, alpha: float) -> str:
    """One status line describing a prune's report ``info`` (:func:`prune`)."""
    if info.get("emptied"):
        return (f"prune at iteration {info['iteration']}: every tet is below alpha {alpha}; "
                "pruning would empty the mesh, so nothing was pruned")
    why = f"below alpha {alpha}" + (f" or in front of the surface ({info['in_front']} opaque)" if info.get("in_front") else "")
    msg = f"prune at iteration {info['iteration']}: {info['pruned']} tets {why} removed, {info['tets_after']} remain"
    if info.get("filled_sealed"):
        msg += f"; {info['filled_sealed']} tets put back where the guards had sealed a void"
    if info.get("removed_components"):
        kept = ("the largest component" if "kept_components" not in info
                else f"{info['kept_components']} component(s) above the size threshold")
        msg += (f"; pruning split the mesh, kept {kept} and removed {info['removed_components']} "
                f"other component(s) ({info['tets_removed_by_component']} tets)")
    return msg
