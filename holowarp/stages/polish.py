"""Silhouette polish: a last fit of the cleaned tet boundary to the masks, several views per
step, before the element improvement (issue 12).

The mesh-only blocks (§6) draw one view per step and balance the masks against the surfels'
normals and the regularisers, so the boundary ends a fraction of a pixel off where the
silhouettes pin it: on the quality suite (128², fast preset) the surface sat 0.001-0.002
outside the ground truth on the silhouette-visible parts, where the visual hull sits within
0.001, and that spread alone kept F@0.005 under the hull's. This stage fits the boundary
vertices to the masks (and the normal maps, where the dataset has them), averaging
``PolishConfig.views`` training views per step, with Adam and a cosine-decayed step:

    L = mean_views (mean_pixels |alpha - mask| + w_prior * mean_covered |n/|n| - n_map|)
        + smooth * mean_edges |d_i - d_j|^2 / h^2

``alpha`` is the boundary's anti-aliased silhouette (:func:`holowarp.ops.rasterize_mesh`),
``d`` the boundary vertices' displacements from their start, ``h`` the mean boundary edge.
The last term keeps the displacement field smooth, so the correction moves patches, not
single vertices, and the surface's normals survive. The prior term, only where the dataset
has normal maps (``n`` the boundary's rendered normals, ``n_map`` the map, over the pixels
both cover), turns the facets the masks leave alone towards the photographed orientation
(``PolishConfig.w_prior`` has the measurements); without normal maps only the masks enter,
and a part of the surface no silhouette sees (a cavity) stays where the main loop put it.
In the first fit the interior vertices do not move (``PolishConfig.interior_follow`` 0); in
the second, those next to the boundary follow it by ``after_interior_follow`` (0.8) of their
boundary neighbours' mean move, so the boundary's layer of tets is carried along rather than
squeezed (the setting has the measurements). After every step, vertices of tets that fell below
``min_volume_fraction`` (0.8) of their volume at the start are put back
(:func:`holowarp.stages.geometry.revert_inverting_moves`), so no tet inverts and the element
improvement (§7b), which runs next, finds the elements much as the main loop left them.

A second, shorter fit follows the element improvement (``PolishConfig.after_steps``, under a
tighter floor), since §7b's boundary flips and cap deletions undo part of the first. Its
moves that would take a tet's smallest dihedral angle below §7b's worst (or below 10°,
§7b's target, where §7b did better) are then put back (:func:`keep_angles`). On data without
normal maps its prior compares with the surfels' rendered normals after their refit
(:class:`SurfelNormals`, ``PolishConfig.after_w_surfels``), as §6's ``L_norm`` does.

Before the fit, :func:`refine_bends` bisects the tets where the boundary turns sharply
(``PolishConfig.refine_bend``, which has the measurements), so that the fits have vertices to
bend the surface with where the main loop's facets are too coarse (horns, ears, handles); the
surfels follow (:meth:`holowarp.tetgs.TetGaussians.apply_refine`). Then :func:`lift_pits`
lifts the one-tet pits (a boundary vertex with three boundary neighbours, most of an edge
below their plane) that the main loop leaves on some runs; no silhouette sees them, and the
deepest set the Hausdorff distance (bob: 0.028).

Measured on the quality suite (fast preset, 128², 60 steps of 8 views, ~3 s each) by
finishing the same main-loop results again with and without the polish: ``holowarp.bench
quality`` numbers in the issue-12 note of 2026-12-05. F@0.005 rose on every object (spot
0.940 -> 0.96, star 0.826 -> 0.88-0.90, fandisk 0.662 -> 0.71, dented box 0.504 -> 0.57,
plate 0.943 -> 0.98), as did normal consistency on six of the eight. With the fit after
§7b instead of before it, the gains were slightly larger but the worst dihedral angles fell
by half (bob 12.9° -> 5.1°). Without the smoothing term F@0.005 rose as much but bob's
normal consistency fell (0.9918 -> 0.9892); with a weight of 0.1-0.3 fandisk's sharp edges
gave back half the gain.

Measured and not adopted (issue 12): a trim before the cleanup that removes the tets whose
centroid the masks show to be empty (carve field under 0.1 with the masks as they are, or
under 0.5 with all but 2% of the views), from the boundary inwards wherever that keeps the
topology and a manifold boundary (whole face-connected groups first, then tet by tet where
each removal alone keeps the topology). It targets webs such as the one the plate keeps in
an inner corner of a hole (its Hausdorff point, 0.029, where the masks say empty). Finishing
the suite's runs again from their checkpoints, it removed 0-68 tets per object (67-315 in
the tolerant variant) and moved F@0.005, normal consistency and Hausdorff by at most 0.006
either way (plate's Hausdorff 0.029 -> 0.025, dented box's 0.065 -> 0.068, bob's 0.0176 ->
0.0185): the web is one or two tets thick, removing it tet by tet pinches the boundary, and
the group removal's guards (one component, the genus, a manifold boundary) kept most of it
too.
"""

from __future__ import annotations

import math
import time

import numpy as np
import torch

from holowarp.config import PolishConfig
from holowarp.tetmesh import TetMesh, _row_keys, ridge_index

__all__ = ["SurfelNormals", "bend_tets", "keep_angles", "keep_unfolded", "lift_pits", "polish_silhouettes",
           "refine_bends"]


def _boundary_graph(mesh: TetMesh):
    """``mesh``'s boundary vertex ids (B,), boundary faces re-indexed to them (F, 3), unique
    boundary edges (E, 2) and mean boundary edge length h (the unit of every length here)."""
    faces = np.asarray(mesh.boundary_faces())
    ids, local = np.unique(faces, return_inverse=True)
    lf = local.reshape(faces.shape)
    e = np.unique(np.sort(np.concatenate([lf[:, [0, 1]], lf[:, [1, 2]], lf[:, [2, 0]]]), axis=1), axis=0)
    V = np.asarray(mesh.vertices)
    h = float(np.linalg.norm(V[ids[e[:, 0]]] - V[ids[e[:, 1]]], axis=1).mean()) if len(e) else 0.0
    return ids, lf, e, h


def _mask_l1(x, faces, dataset, views, masks) -> float:
    from holowarp.ops import rasterize_mesh

    with torch.no_grad():
        err = [float((rasterize_mesh(x, faces, dataset.viewmats[v], dataset.K[v], dataset.width,
                                     dataset.height)["alpha"] - masks[v]).abs().mean()) for v in views]
    return float(np.mean(err))


def polish_silhouettes(mesh: TetMesh, dataset, config: PolishConfig, *, seed: int = 0,
                       device="cpu", normals=None) -> tuple[np.ndarray, dict]:
    """Fit ``mesh``'s boundary vertices to ``dataset``'s training masks (module docstring).

    Args:
        mesh: the cleaned tet mesh (world units); it is not modified.
        dataset: the run's :class:`holowarp.data.Dataset` (masks (N, H, W) in [0, 1]).
        config: :class:`holowarp.config.PolishConfig`.
        seed: the views each step draws are a function of (seed, step).
        device: where the rasteriser runs.
        normals: the normal maps the prior (``config.w_prior``) compares with, a callable
            ``view -> (H, W, 3)`` tensor on ``device`` (0 where it holds no normal) used
            instead of the dataset's: :class:`SurfelNormals`, for data without normal maps.

    Returns:
        (vertices (V, 3) float64, info) with info ``steps``, ``views_per_step``,
        ``mask_l1_before`` / ``mask_l1_after`` (mean |alpha - mask| over up to
        ``config.check_views`` training views, spread evenly), ``moved_max`` /
        ``moved_mean`` (boundary vertex displacement, in mean boundary edges),
        ``reverted`` (vertex moves put back by the volume floor) and ``seconds``.
    """
    from holowarp.ops.tet_energy import vertex_tets
    from holowarp.stages.geometry import signed_volumes_t

    t0 = time.perf_counter()
    dev = torch.device(device)
    train = np.asarray(dataset.train_idx)
    ids, lfaces, edges, h = _boundary_graph(mesh)
    x0 = torch.tensor(np.asarray(mesh.vertices), dtype=torch.float32, device=dev)
    x = x0.clone()
    tets = torch.tensor(np.asarray(mesh.tets), dtype=torch.int64, device=dev)
    ids_t = torch.tensor(ids, dtype=torch.int64, device=dev)
    faces = torch.tensor(lfaces, dtype=torch.int32, device=dev)
    e = torch.tensor(edges, dtype=torch.int64, device=dev)
    floor = config.min_volume_fraction * signed_volumes_t(x, tets).clamp_min(0.0)
    incidence = vertex_tets(tets, x.shape[0])
    xb0 = x[ids_t].clone()
    # Converted per use: zero-copy on the CPU, and no second copy of every mask on a GPU.
    masks = _Masks(dataset, dev, normals)
    check = train[np.linspace(0, len(train) - 1, min(config.check_views, len(train))).round().astype(int)]
    before = _mask_l1(xb0, faces, dataset, check, masks)

    fit = _Fit(x, xb0, ids_t, faces, e, h, guard=dict(tets=tets, floor=floor, incidence=incidence),
               follow=_interior_ring(mesh, ids, config.interior_follow, dev))
    d, reverted = fit.run(dataset, train, masks, config, seed)
    moved = d.detach().norm(dim=1) / h
    info = {
        "steps": int(config.steps),
        "views_per_step": int(min(config.views, len(train))),
        "mask_l1_before": before,
        "mask_l1_after": _mask_l1(x[ids_t], faces, dataset, check, masks),
        "moved_max": float(moved.max()) if len(moved) else 0.0,
        "moved_mean": float(moved.mean()) if len(moved) else 0.0,
        "reverted": int(reverted),
        "seconds": time.perf_counter() - t0,
    }
    out = np.array(mesh.vertices, dtype=np.float64)
    moved_any = (x != x0).any(dim=1).cpu().numpy()
    out[moved_any] = x[moved_any].cpu().double().numpy()
    return out, info


def keep_angles(mesh: TetMesh, vertices, floor_deg: float) -> tuple[np.ndarray, int]:
    """Put back the moved vertices of every tet whose smallest dihedral angle at ``vertices``
    fell below ``min(floor_deg, mesh's worst)``, or that inverted, repeatedly, so the fit
    after the element improvement never takes the worst angle below what §7b reached (or
    below ``floor_deg`` where §7b reached more).

    The moved vertices of the tets around every boundary edge whose wedge
    (the sum of its tets' dihedral angles, :meth:`holowarp.tetmesh.TetMesh.boundary_wedges`)
    rose past 360°, or past what it was in ``mesh`` where it was over 360° already, go back
    as well, in the same loop. Past a full turn the tets around the edge overlap in space
    and the surface cuts through itself, although none of them inverts: the fits would
    deepen the overlaps that cleanup peels (step 3 of :mod:`holowarp.stages.cleanup`).

    Args:
        mesh: the tet mesh before the fit (its positions are the ones put back).
        vertices: (V, 3) positions after the fit.
        floor_deg: degrees (method.md §7b's target, 10).

    Returns:
        (vertices (V, 3) float64, number of vertices put back). Terminates: a tet whose
        vertices are all put back has its angles from ``mesh``, none below the floor, and an
        edge whose tets' vertices are all put back has its wedge from ``mesh``.
    """
    V0 = np.asarray(mesh.vertices, dtype=np.float64)
    V = np.array(vertices, dtype=np.float64)
    T = np.asarray(mesh.tets)
    floor = min(float(floor_deg), float(np.nanmin(mesh.dihedral_angles())))
    _, wedge_of, fan_of = ridge_index(mesh, fans=True)
    limit = np.maximum(wedge_of(mesh), 360.0)
    moved = np.any(V != V0, axis=1)
    put_back = 0
    while moved.any():
        cand = np.flatnonzero(moved[T].any(axis=1))  # only tets with a moved vertex changed
        local = TetMesh(V.copy(), T[cand], validate=False)  # TetMesh freezes what it gets
        ang = local.dihedral_angles().min(axis=1)
        bad = cand[~(ang >= floor) | (local.signed_volumes() <= 0)]  # nan (degenerate) and inverted are bad
        bad = np.union1d(bad, fan_of(wedge_of(TetMesh(V.copy(), T, validate=False)) > limit))
        back = np.unique(T[bad])
        back = back[moved[back]]
        if len(back) == 0:
            break
        V[back] = V0[back]
        moved[back] = False
        put_back += len(back)
    return V, put_back


def keep_unfolded(mesh: TetMesh, vertices) -> tuple[np.ndarray, int]:
    """:func:`keep_angles` without an angle floor: the moves that wrap a boundary edge's
    tets past a full turn (or further past it), or that invert or flatten a tet, are put
    back. Returns (vertices (V, 3) float64, number of vertices put back)."""
    return keep_angles(mesh, vertices, 0.0)


def lift_pits(mesh: TetMesh, config: PolishConfig) -> tuple[np.ndarray, int]:
    """Lift ``mesh``'s one-tet pits towards their rims (:func:`_flatten_pits`, with depth
    ``config.pit_depth`` mean boundary edges and volume floor ``config.pit_floor``).

    Runs before the element improvement, which mends the tets a lift flattens. Returns
    (vertices (V, 3) float64, number of vertices lifted)."""
    ids, lfaces, _, h = _boundary_graph(mesh)
    V = np.array(mesh.vertices, dtype=np.float64)
    tets = np.asarray(mesh.tets)
    floor = config.pit_floor * np.clip(mesh.signed_volumes(), 0.0, None)
    return V, _flatten_pits(V, ids, lfaces, config.pit_depth * h, tets, floor)


def _flatten_pits(X: np.ndarray, ids: np.ndarray, lfaces: np.ndarray, depth: float, tets: np.ndarray,
                  floor: np.ndarray) -> int:
    """Lift every one-tet pit towards its rim, in place: a boundary vertex with exactly three
    boundary neighbours that lies more than ``depth`` below the plane through them (their
    triangle, oriented like the fan of the vertex's boundary faces) moves straight onto that
    plane, or as far towards it as keeps each of its tets above its ``floor`` (M,) volume (a
    tet's volume is linear in one vertex's position, so the largest such fraction of the move
    is exact). Moves ``X`` (V, 3) in place and returns how many vertices moved. ``ids`` (B,)
    are the boundary vertices, ``lfaces`` (F, 3) the boundary faces in indices into ``ids``,
    ``tets`` (M, 4)."""
    deg = np.bincount(lfaces.reshape(-1), minlength=len(ids))
    cand = np.flatnonzero(deg == 3)
    # Each fan face (v, a, b) seen from v: its far edge a -> b. The three far edges of a closed
    # fan chain a -> b -> c -> a, whose triangle (a, b, c) has the fan's orientation.
    far = {}
    for f in lfaces[np.isin(lfaces, cand).any(axis=1)]:
        for k in range(3):
            far.setdefault(int(f[k]), []).append((int(ids[f[(k + 1) % 3]]), int(ids[f[(k + 2) % 3]])))
    moved = 0
    for v in cand:
        nxt = dict(far[int(v)])
        a = next(iter(nxt))
        b, vid = nxt.get(a), int(ids[v])
        c = nxt.get(b)
        if c is None or nxt.get(c) != a:
            continue  # not a closed fan of three
        n = np.cross(X[b] - X[a], X[c] - X[a])
        n /= max(np.linalg.norm(n), 1e-30)
        s = float((X[vid] - (X[a] + X[b] + X[c]) / 3.0) @ n)
        if s >= -depth:
            continue
        inc = np.flatnonzero((tets == vid).any(axis=1))
        # The vertex's tets on their own vertices (a fresh array: TetMesh freezes what it gets).
        used, local = np.unique(tets[inc], return_inverse=True)
        P = X[used]
        v0 = TetMesh(P, local.reshape(-1, 4), validate=False).signed_volumes()
        P = P.copy()
        P[used == vid] -= s * n
        v1 = TetMesh(P, local.reshape(-1, 4), validate=False).signed_volumes()
        shrink = v1 < v0
        t = min(1.0, float(np.min((v0 - floor[inc])[shrink] / (v0 - v1)[shrink]))) if shrink.any() else 1.0
        if t > 0:
            X[vid] -= t * s * n
            moved += 1
    return moved


def _interior_ring(mesh: TetMesh, ids: np.ndarray, factor: float, device):
    """The interior vertices next to the boundary and how they follow the boundary's moves
    (``PolishConfig.interior_follow``): (ring ids (R,), their rest positions (R, 3), the
    pairs (ring index, boundary index) of the tet edges between them (P, 2), ``factor`` /
    the number of boundary neighbours of each pair's ring vertex (P,)); None when ``factor``
    is 0 or no interior vertex touches the boundary."""
    if factor <= 0:
        return None
    ed = np.asarray(mesh.edges(), dtype=np.int64)
    on = np.zeros(mesh.num_vertices, dtype=bool)
    on[ids] = True
    cross = ed[on[ed[:, 0]] != on[ed[:, 1]]]
    if len(cross) == 0:
        return None
    cross = np.where(on[cross[:, 0]][:, None], cross[:, ::-1], cross)  # (interior, boundary)
    ring, r_local = np.unique(cross[:, 0], return_inverse=True)
    b_local = np.searchsorted(ids, cross[:, 1])
    weight = factor / np.bincount(r_local, minlength=len(ring))[r_local]
    T = lambda a, dt: torch.tensor(a, dtype=dt, device=device)  # noqa: E731
    return (T(ring, torch.int64), T(np.asarray(mesh.vertices)[ring], torch.float32),
            T(np.stack([r_local, b_local], 1), torch.int64), T(weight, torch.float32))


class _Fit:
    """The Adam fit of the boundary displacements ``d`` (B, 3) to the masks (module
    docstring); ``x`` (V, 3) follows every step, under the volume floor of ``guard``, and
    so do the interior vertices next to the boundary, by ``follow`` (:func:`_interior_ring`)."""

    def __init__(self, x, xb0, ids_t, faces, edges, h, *, guard, follow=None):
        self.x, self.xb0, self.ids_t, self.faces, self.e, self.h, self.guard = x, xb0, ids_t, faces, edges, h, guard
        self.follow = follow

    def _place(self, d):
        """Put the boundary at ``xb0 + d`` and its interior ring at its rest positions plus
        the weighted mean of its boundary neighbours' displacements."""
        self.x[self.ids_t] = self.xb0 + d
        if self.follow is not None:
            ring, r0, pairs, w = self.follow
            moved = torch.zeros_like(r0).index_add_(0, pairs[:, 0], d[pairs[:, 1]] * w[:, None])
            self.x[ring] = r0 + moved

    def run(self, dataset, train, masks, config: PolishConfig, seed: int):
        from holowarp.stages.geometry import revert_inverting_moves

        x, xb0, ids_t, e, h = self.x, self.xb0, self.ids_t, self.e, self.h
        d = torch.zeros_like(xb0, requires_grad=True)
        opt = torch.optim.Adam([d], lr=config.lr * h)
        k = min(config.views, len(train))
        reverted = torch.zeros((), dtype=torch.int64, device=x.device)
        for step in range(config.steps):
            for g in opt.param_groups:
                g["lr"] = config.lr * h * 0.5 * (1.0 + math.cos(math.pi * step / config.steps))
            opt.zero_grad(set_to_none=True)
            xb = xb0 + d
            views = np.random.default_rng([seed, 7, step]).choice(train, k, replace=False)
            loss = sum(_view_loss(xb, self.faces, dataset, int(v), masks[int(v)],
                                  masks.normal(int(v)) if config.w_prior > 0 else None, config.w_prior)
                       for v in views) / k
            if config.smooth > 0:
                dd = d[e[:, 0]] - d[e[:, 1]]
                loss = loss + config.smooth * (dd * dd).sum(dim=1).mean() / (h * h)
            loss.backward()
            opt.step()
            with torch.no_grad():
                x_old = x.clone()
                self._place(d)
                reverted = reverted + revert_inverting_moves(x, x_old, **self.guard)
                d.copy_(x[ids_t] - xb0)
        return d.detach(), reverted


class _Masks:
    """``masks[v]``: view ``v``'s mask as a float32 (H, W) tensor on ``device``;
    ``masks.normal(v)`` its normal map (H, W, 3): ``normals(v)`` when a source is given
    (:class:`SurfelNormals`), else the dataset's, None when it has none. Each view goes to
    the device once (the fits draw every view many times; on CUDA each draw would otherwise
    be an upload)."""

    def __init__(self, dataset, device, normals=None):
        self.dataset, self.device, self.normals = dataset, device, normals
        self._masks: dict[int, torch.Tensor] = {}
        self._normals: dict[int, torch.Tensor] = {}

    def __getitem__(self, v) -> torch.Tensor:
        return self._get(self._masks, self.dataset.masks, int(v))

    def normal(self, v) -> torch.Tensor | None:
        if self.normals is not None:
            return self.normals(int(v))
        return None if self.dataset.normals is None else self._get(self._normals, self.dataset.normals, int(v))

    def _get(self, cache: dict, images, v: int) -> torch.Tensor:
        if v not in cache:
            cache[v] = torch.as_tensor(np.asarray(images[v]), dtype=torch.float32, device=self.device)
        return cache[v]


class SurfelNormals:
    """The surfels' rendered normals as normal maps, for the second fit on data without normal
    maps (:attr:`holowarp.config.PolishConfig.after_w_surfels`): the stand-in §6's ``L_norm``
    uses, the surfels as the photographs left them after the refit.

    ``source(v)``: view ``v``'s (H, W, 3) float32 map on ``device``, the blended normal made
    unit where the surfels' opacity exceeds 0.5 and 0 elsewhere (no normal there); rendered
    on first use with the model's current vertices, then kept.
    """

    def __init__(self, model, dataset, device):
        self.model, self.dataset, self.device = model, dataset, torch.device(device)
        self._maps: dict[int, torch.Tensor] = {}

    def __call__(self, v: int) -> torch.Tensor:
        v = int(v)
        if v not in self._maps:
            ds = self.dataset
            with torch.no_grad():
                out = self.model.render(ds.viewmats[v], ds.K[v], ds.width, ds.height)
                n = out["normal"] / out["normal"].norm(dim=-1, keepdim=True).clamp_min(1e-8)
                n = torch.where((out["alpha"] > 0.5)[..., None], n, torch.zeros_like(n))
            self._maps[v] = n.to(device=self.device, dtype=torch.float32).contiguous()
        return self._maps[v]


def _view_loss(xb, faces, dataset, v: int, mask, prior=None, w_prior: float = 0.0) -> torch.Tensor:
    """``mean |alpha - mask|`` of view ``v``, plus ``w_prior`` times the mean chord
    ``sqrt(2 (1 - cos))`` between the rendered normals and the normal map ``prior`` (H, W, 3)
    over the pixels the boundary covers (alpha > 0.5) where the map holds a normal (when
    given and w_prior > 0; :func:`holowarp.losses.covered_prior_loss` with ``chord``)."""
    from holowarp.losses import covered_prior_loss
    from holowarp.ops import rasterize_mesh

    out = rasterize_mesh(xb, faces, dataset.viewmats[v], dataset.K[v], dataset.width, dataset.height)
    loss = (out["alpha"] - mask).abs().mean()
    if prior is not None and w_prior > 0:
        loss = loss + w_prior * covered_prior_loss(prior, out["normal"], out["alpha"], chord=True)
    return loss



def bend_tets(mesh: TetMesh, lo_deg: float, hi_deg: float = 180.0) -> np.ndarray:
    """(M,) bool: the tets owning a boundary face that meets a neighbouring boundary face at
    an edge bent by more than ``lo_deg`` and less than ``hi_deg`` degrees (the angle between
    the two faces' outward normals: 0 flat, 90 a box's edge). Edges of a non-manifold
    boundary (three or more faces) are skipped."""
    faces = np.asarray(mesh.boundary_faces())
    owner = np.asarray(mesh.boundary_face_tets())
    V = np.asarray(mesh.vertices, dtype=np.float64)
    n = np.cross(V[faces[:, 1]] - V[faces[:, 0]], V[faces[:, 2]] - V[faces[:, 0]])
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300)
    half = np.sort(np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]), axis=1)
    _, edge, count = np.unique(_row_keys(half, max(mesh.num_vertices, 1)), return_inverse=True, return_counts=True)
    two = np.flatnonzero(count[edge] == 2)  # half-edges of edges with exactly two faces
    fid = np.tile(np.arange(len(faces)), 3)[two][np.argsort(edge[two], kind="stable")]
    a, b = fid[0::2], fid[1::2]
    c = np.einsum("ij,ij->i", n[a], n[b])
    bent = (c < np.cos(np.radians(lo_deg))) & (c > np.cos(np.radians(hi_deg)))
    marked = np.zeros(mesh.num_tets, bool)
    marked[owner[a[bent]]] = True
    marked[owner[b[bent]]] = True
    return marked


def refine_bends(mesh: TetMesh, config: PolishConfig):
    """Bisect the tets at ``mesh``'s sharply turning boundary edges (:func:`bend_tets` with
    ``config.refine_bend``) until their longest edge is at most ``config.refine_factor``
    times the median of their longest edges (:func:`holowarp.refine.bisect_longest_edges`:
    conforming, every child positive, the boundary unchanged as a point set).

    Returns:
        ``(vertices (N', 3), tets (K, 4), parent (K,), ends (N' - N, 2), info)`` as
        :meth:`holowarp.tetgs.TetGaussians.apply_refine` takes them, or None when off or when
        no edge bends that much. ``info``: ``marked`` tets, ``target`` edge (scene units),
        ``tets_before``, ``tets_after``.
    """
    if config.refine_bend is None or mesh.num_tets == 0:
        return None
    from holowarp.refine import bisect_longest_edges, edge_table

    marked = bend_tets(mesh, *config.refine_bend)
    if not marked.any():
        return None
    _, _, length, longest = edge_table(mesh.vertices, mesh.tets)
    target = float(config.refine_factor * np.median(length[longest[marked]]))
    V, T, parent, ends = bisect_longest_edges(mesh.vertices, mesh.tets, marked, target)
    info = {"marked": int(marked.sum()), "target": target, "tets_before": mesh.num_tets, "tets_after": int(len(T))}
    return V, T, parent, ends, info
