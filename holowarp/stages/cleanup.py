"""Cleanup of the optimised tet mesh (method.md §7).

In order:

1. **flip**: tets whose signed volume is negative but whose geometry is fine (their
   |volume| is above the degeneracy threshold) are reordered (swap of two vertices), which
   makes them positive without moving anything;
2. **drop**: genuinely degenerate tets (|volume| below ``degenerate_rel`` times the median
   tet volume) are removed, and so are boundary "caps": tets with a boundary face whose
   minimum dihedral angle is below ``cap_dihedral_deg`` (four nearly coplanar surface
   vertices, flattened while the surface was fitted). Caps hold almost no volume, so the
   surface barely moves, while their near-singular deformation gradients would stiffen or
   destabilise an FEM solve. *Flaps* go too: tets with three boundary faces (their apex
   belongs to no other tet) whose minimum dihedral angle is below ``flap_dihedral_deg``.
   Such a tet is a sheet of almost no thickness sticking out of the surface (its two
   faces are both outside), which the element improvement (§7b) cannot fix within its
   surface bound: deleting it moves the surface sideways by the flap's width, not by its
   thickness. Measured on bob and spot at 128² (fast preset): flaps were 6 of the 13 and 7
   of the 11 tets left under 10° after §7b, and with them gone §7b leaves none (worst
   2.6° → 12.3° and 6.6° → 13.2°) at an unchanged Chamfer-L1 (-0.2%, +0.4%), where
   raising ``cap_dihedral_deg`` to 10° instead drops four times the tets and costs 2%.
   Removal repeats while newly exposed caps and flaps appear;
3. **cap restoration**: dropping a cap can pinch the boundary (two fans of tets meeting at
   an edge or a vertex that the cap used to join). The dropped caps around every
   non-manifold edge or vertex are put back, repeatedly, until the boundary is manifold
   again. Putting back every cap gives back the input, so this ends with a manifold
   boundary whenever the input had one, and it costs a few slivers instead of the deep
   pits that removing whole fans digs (measured on bob: Chamfer-L1 of a pitted run
   0.0041 → 0.0037, at the level of the mesh before cleanup). Flaps put back this way are
   then dropped on their own, which never pinches. **Folds**: a dropped cap (not a flap)
   that holds a boundary edge whose wedge (:meth:`~holowarp.tetmesh.TetMesh.boundary_wedges`) is now a knife ridge
   (under ``blunt_wedge_deg``) or a slit (over 360° minus it) is put back too, with the
   manifold restoration after each round, until no dropped cap holds one. A cap whose
   fourth vertex does not lie over its boundary face exposes a surface folded onto itself
   when it goes (a fin of a few degrees beside a slit), and every tet at a fin has a
   dihedral angle below the fin's wedge, which neither the blunting nor §7b could open
   within their bounds. Measured on the quality suite (fast preset, 128², the finish redone
   from the seed-0 runs' checkpoints): cleanup had left fins down to 0.07° on spot, and §7b's
   worst angle (after the touch-up) was 2.2-9.4° on all eight objects; with the folds put
   back it is 10.4-17.9° (spot 2.2 → 17.9°, bob 9.4 → 13.2°, fandisk 6.1 → 11.6°, star
   5.8 → 16.1°, dented box 6.0 → 10.7°, plate 2.7 → 10.4°, mug 7.8 → 12.5°, bowl 5.5 →
   14.4°), with Chamfer-L1 lower on seven objects (-0.3% to -2.3%) and +0.3% on the
   bowl. Dropping no caps at all (``cap_dihedral_deg`` 0) also lifts every worst angle
   above 10°, but costs fandisk and the dented box 1.2 and 1.6 points of F@0.005.
   A cap put back for a fold must leave its edges less sharp (``min(wedge, 360 - wedge)``)
   than its removal would; one that does not (a thin tet standing in a slit, which makes a
   knife of its free edge) is dropped again. With the depth pull of the mesh blocks the bowl
   kept one such tet (a 6.2° ridge beside 4.9° slits, 15.9° without it) and the mug another:
   §7b's worst angle rose from 8.4° to 19.3° and from 12.0° to 19.5°, the finish redone
   from the same checkpoints (fast, 128², seed 0), with Chamfer-L1 unchanged (0.00858,
   0.0181) and the six other objects of the quality suite identical.
   **Overlaps**: at a boundary edge whose wedge is over 360° the tets around it wrap past a
   full turn, so they overlap in space and the surface cuts through itself there, although
   every tet is positive (the main loop leaves a few: 0-4 per run on the quality suite).
   Every round drops, at each such edge, the end tet of its fan with the larger dihedral
   angle there (usually an almost flat tet lying across the edge), with the manifold
   restoration after it; an end tet that restoration puts back is not tried again, so an
   overlap whose two end tets both pinch the boundary stays (the report's
   ``overlapping_edges`` counts what is left). On the thin plate at seed 1 (fast, 128²)
   two tets went, and §7b's worst angle after the touch-up rose from 7.6° to 11.3°, the
   flat tet at the 406° edge having been the worst;
4. **sealed voids**: every removed tet that no longer connects to the outside through other
   removed tets is put back (oriented positively), so that dropping a degenerate interior
   tet leaves no void that no image sees (a second boundary shell, which would also pinch
   the boundary where it touches the surface at a vertex). An almost flat tet put back is
   left to §7b's interior flips, which replace slivers without touching the boundary;
5. **components**: only the largest face-connected component is kept (with
   ``config.min_component``, scene level, method.md §11: every component with at least
   that fraction of the tets);
6. **manifold repair** (only for inputs that were not manifold to begin with): where the
   boundary is not a manifold (an edge in more than two boundary faces, or a vertex whose
   boundary star is several fans), the tets around that edge/vertex are grouped into fans
   connected through faces containing it, and all but the largest fan are removed; a vertex
   whose tets form one fan while empty space reaches it from separate sides loses its
   whole star; repeated until the boundary is manifold;
7. unused vertices are removed;
8. **blunting** (:func:`blunt_ridges`): knife ridges of the boundary, edges where the
   solid's wedge angle is under ``blunt_wedge_deg`` (30°), are opened by moving their
   vertices along the surface towards their neighbours' centroid, by at most
   ``blunt_max_move`` (half a mean boundary edge) each. Such ridges are fitting artefacts
   at this resolution (a thin rim, a fold left by a carved-out tet), and every tet at one
   has a dihedral angle no larger than the wedge: §7b, bound to 0.1 mean edges of surface
   move and barred from opening a feature crease, cannot fix them. Measured on the quality
   suite (fast preset, 128², whole finish redone from the runs' checkpoints): the worst
   angle after §7b rose on all eight objects (bob 12.9° → 16.4°, spot 12.2° → 16.4°,
   fandisk 13.6° → 16.1°, bowl 13.9° → 16.1°, dented box 6.3° → 13.2°, mug 7.8° → 8.1°,
   star 7.1° → 9.7°, plate 4.3° → 9.9°). Chamfer-L1 against a finish without the flap
   rule, the blunting and §7b changed by -0.1% to +0.8%, and by +2.2% (star) and +2.7%
   (plate).

Every count is reported, so a user sees exactly what cleanup changed.
"""

from __future__ import annotations

import numpy as np

from holowarp.config import CleanupConfig, kept_components
from holowarp.manifold import fill_sealed, repair_manifold, restore_until_manifold
from holowarp.tetmesh import TetMesh, ridge_index

__all__ = ["cleanup", "overlap_ends"]


def cleanup(mesh: TetMesh, config: CleanupConfig = CleanupConfig()) -> tuple[TetMesh, np.ndarray, dict]:
    """Run the §7 cleanup.

    Returns:
        (mesh, kept, info): the clean mesh (unused vertices removed), ``kept`` (K,) int64
        the indices of its tets in the input (tet i of the output is input tet kept[i],
        possibly with two vertices swapped), and a report of every count:
        ``inverted_before_cleanup`` (signed volume <= 0 on entry), ``flipped``, ``dropped``
        (degenerate, net of those put back), ``dropped_caps`` (boundary slivers, flaps and
        overlaps, net of those put back), ``dropped_flaps`` (the flaps among them),
        ``caps_restored_for_manifold``, ``caps_restored_for_folds`` (caps put back because
        their removal left a knife ridge or a slit, step 3), ``dropped_overlaps`` (tets
        dropped where their fan wrapped past a full turn, step 3), ``components_before``,
        ``components_removed``, ``tets_removed_by_component``, ``tets_removed_for_manifold``, ``filled_sealed``
        (removed tets put back because they sealed a void), ``manifold``,
        ``components``, ``inverted_after_cleanup``, ``tets_before``, ``tets_after``, and
        ``blunt`` (:func:`blunt_ridges`' report).
    """
    if mesh.num_tets == 0:
        raise ValueError("cleanup: the mesh has no tetrahedra")
    info = {"tets_before": mesh.num_tets}
    vol = mesh.signed_volumes()
    info["inverted_before_cleanup"] = int(np.count_nonzero(vol <= 0))
    thresh = config.degenerate_rel * float(np.median(np.abs(vol)))
    degenerate = np.abs(vol) < thresh
    flip = (vol < 0) & ~degenerate
    t = mesh.tets.copy()
    t[flip, 2], t[flip, 3] = mesh.tets[flip, 3], mesh.tets[flip, 2]
    info["flipped"] = int(flip.sum())
    keep, capped, flaps, folds, peeled = _drop_caps_and_flaps(mesh.vertices, t, ~degenerate, config)
    restored = int(np.count_nonzero(capped & keep & ~folds))
    keep, info["filled_sealed"] = _fill_sealed_voids(mesh, t, vol, keep)
    info["dropped_overlaps"] = int(np.count_nonzero(peeled & ~keep))
    caps = int(np.count_nonzero(capped & ~keep))
    info["dropped"] = int(np.count_nonzero(degenerate & ~keep)) + caps
    info["dropped_caps"] = caps
    info["dropped_flaps"] = int(np.count_nonzero(flaps & ~keep))
    info["caps_restored_for_manifold"] = restored
    info["caps_restored_for_folds"] = int(folds.sum())
    kept = np.flatnonzero(keep)
    work = TetMesh(mesh.vertices, t[kept], validate=False)
    labels, n = work.components()
    info["components_before"] = n
    info["components_removed"] = max(n - 1, 0)
    if n > 1:
        survive = kept_components(labels, n, config.min_component)
        info["components_removed"] = n - len(np.unique(labels[survive]))
        info["tets_removed_by_component"] = int((~survive).sum())
        kept = kept[survive]
        work = TetMesh(mesh.vertices, t[kept], validate=False)
    else:
        info["tets_removed_by_component"] = 0
    keep, rep = repair_manifold(work, max_rounds=config.max_repair_rounds, min_component=config.min_component)
    kept = kept[keep]
    info["tets_removed_for_manifold"] = rep["removed_tets"]
    out, _ = TetMesh(mesh.vertices, t[kept], validate=False).remove_unused_vertices()
    out, info["blunt"] = blunt_ridges(out, config, thresh)
    info["manifold"] = rep["manifold"]
    info["components"] = out.num_components()
    info["inverted_after_cleanup"] = int(np.count_nonzero(out.signed_volumes() <= 0))
    info["tets_after"] = out.num_tets
    return out, kept.astype(np.int64), info


def _fill_sealed_voids(mesh: TetMesh, t: np.ndarray, vol: np.ndarray, keep: np.ndarray) -> tuple[np.ndarray, int]:
    """Step 4 of the module docstring: (keep (M,) bool with the sealed removed tets added,
    how many were added). ``t`` (M, 4) is modified in place: an added tet of negative
    signed volume ``vol`` (M,) gets two vertices swapped."""
    out, filled = fill_sealed(keep, mesh.face_adjacency())
    if filled:
        neg = out & ~keep & (vol < 0)
        t[neg, 2], t[neg, 3] = mesh.tets[neg, 3], mesh.tets[neg, 2]
    return out, filled


def blunt_ridges(mesh: TetMesh, config: CleanupConfig, min_volume: float = 0.0) -> tuple[TetMesh, dict]:
    """Step 8 of the module docstring: open the knife ridges of the boundary.

    A boundary edge whose wedge angle (:meth:`~holowarp.tetmesh.TetMesh.boundary_wedges`) is below
    ``config.blunt_wedge_deg`` can only be cut by tets whose dihedral angle at that edge is
    smaller still. Its two vertices move ``config.blunt_step`` of the way to the centroid
    of their boundary neighbours (an umbrella step along the surface, which pulls a ridge
    back into the body), for at most ``config.blunt_rounds`` rounds and
    ``config.blunt_max_move`` mean boundary edges in all. A vertex whose move would leave a
    tet of its star with a signed volume at or below ``min_volume`` tries half the step,
    three times, then stays where it is for that round.

    Returns (mesh with the moved vertices, report): ``sharp_edges_before``,
    ``sharp_edges_after``, ``vertices_moved``, ``max_move_mean_edges``, ``rounds``.
    """
    V = np.asarray(mesh.vertices, dtype=np.float64).copy()
    T = mesh.tets.astype(np.int64)
    bf = mesh.boundary_faces().astype(np.int64)
    info = {"sharp_edges_before": 0, "sharp_edges_after": 0, "vertices_moved": 0, "max_move_mean_edges": 0.0,
            "rounds": 0}
    if config.blunt_wedge_deg <= 0 or len(bf) == 0:
        return mesh, info
    edges, wedge_of = ridge_index(mesh)
    wedge = wedge_of(mesh)
    L = float(np.linalg.norm(V[edges[:, 0]] - V[edges[:, 1]], axis=1).mean())
    allowance = np.full(len(V), config.blunt_max_move * L)
    he = np.concatenate([bf[:, [0, 1]], bf[:, [1, 2]], bf[:, [2, 0]]])
    he = np.concatenate([he, he[:, ::-1]])  # each neighbour twice (two faces share an edge): uniform weights
    count = np.bincount(he[:, 0], minlength=len(V)).astype(np.float64)
    sharp = wedge < config.blunt_wedge_deg
    info["sharp_edges_before"] = int(sharp.sum())
    work = mesh
    for _ in range(config.blunt_rounds):
        if not sharp.any():
            break
        verts = np.unique(edges[sharp])
        centroid = np.zeros((len(verts), 3))
        lookup = np.full(len(V), -1)
        lookup[verts] = np.arange(len(verts))
        mine = lookup[he[:, 0]] >= 0
        np.add.at(centroid, lookup[he[mine, 0]], V[he[mine, 1]])
        step = config.blunt_step * (centroid / count[verts, None] - V[verts])
        length = np.linalg.norm(step, axis=1)
        step *= np.minimum(1.0, allowance[verts] / np.maximum(length, 1e-300))[:, None]
        tries = np.zeros(len(verts), dtype=np.int64)
        while True:  # halve (three times, then drop) the moves that would flatten or invert a tet
            Vn = V.copy()
            Vn[verts] += step
            bad = TetMesh(Vn, T, validate=False).signed_volumes() <= min_volume
            stop = np.isin(verts, T[bad]) & np.any(step != 0, axis=1)
            if not stop.any():
                break
            tries[stop] += 1
            step[stop] *= np.where(tries[stop] > 3, 0.0, 0.5)[:, None]
        moved = np.linalg.norm(step, axis=1)
        if not np.any(moved > 0):
            break
        allowance[verts] -= moved
        V = Vn
        info["rounds"] += 1
        work = mesh.with_vertices(V.astype(mesh.vertices.dtype))
        sharp = wedge_of(work) < config.blunt_wedge_deg
    total = config.blunt_max_move * L - allowance
    info["sharp_edges_after"] = int(sharp.sum())
    info["vertices_moved"] = int(np.count_nonzero(total > 0))
    info["max_move_mean_edges"] = float(total.max() / L) if L > 0 else 0.0
    return work, info


def _flaps(work: TetMesh, angle: np.ndarray, config: CleanupConfig) -> np.ndarray:
    """(M,) bool: the tets of ``work`` with three boundary faces and a minimum dihedral angle
    ``angle`` (M,) below ``flap_dihedral_deg``."""
    return (work.boundary_mask().sum(axis=1) >= 3) & (angle < config.flap_dihedral_deg)


def _drop_caps_and_flaps(vertices, t, keep, config: CleanupConfig):
    """Steps 2-3 of the module docstring for the tets ``t`` (M, 4) still in ``keep`` (M,):
    drop caps and flaps (repeatedly), put back the caps around pinches, then drop the
    flaps left on their own. Returns (keep, capped: every tet dropped as a cap or flap at
    some point, flaps: those dropped as flaps), each (M,) bool."""
    start, keep = keep, keep.copy()
    flaps = np.zeros(len(t), dtype=bool)
    for _ in range(config.max_cap_rounds):
        ids = np.flatnonzero(keep)
        work = TetMesh(vertices, t[ids], validate=False)
        angle = work.quality()["min_dihedral_deg"]
        flap = _flaps(work, angle, config)
        cap = (work.boundary_mask().any(axis=1) & (angle < config.cap_dihedral_deg)) | flap
        if not cap.any() or cap.all():
            break
        keep[ids[cap]] = False
        flaps[ids[flap]] = True
    capped = start & ~keep
    keep, _ = restore_until_manifold(vertices, t, keep, capped)
    keep, folds = _put_back_folding_caps(vertices, t, keep, capped & ~flaps, capped, config)
    keep, peeled = _peel_overlaps(vertices, t, keep, config)
    capped |= peeled
    # A flap dropped next to a cap whose removal pinched came back with it. On its own a
    # flap never pinches (its apex goes with it, and its inner face takes the place of its
    # three outer ones on the surface), so the flaps left are dropped again by themselves.
    for _ in range(config.max_cap_rounds):
        ids = np.flatnonzero(keep)
        work = TetMesh(vertices, t[ids], validate=False)
        flap = _flaps(work, work.quality()["min_dihedral_deg"], config)
        if not flap.any() or flap.all():
            break
        drop = np.zeros(len(t), dtype=bool)
        drop[ids[flap]] = True
        after, back = restore_until_manifold(vertices, t, keep & ~drop, drop)
        if back == int(flap.sum()):
            break
        keep, capped, flaps = after, capped | drop, flaps | drop
    return keep, capped, flaps, folds & keep, peeled & ~keep


def overlap_ends(mesh: TetMesh, skip=None) -> np.ndarray:
    """The tets to drop where ``mesh``'s boundary overlaps itself (step 3's overlaps).

    At a boundary edge whose wedge (:meth:`holowarp.tetmesh.TetMesh.boundary_wedges`) is
    over 360° the tets around the edge wrap past a full turn: they overlap in space and the
    surface cuts through itself there, although every tet is positive. For each such edge
    this picks the end tet of its fan (the owner of one of the edge's two boundary faces)
    with the larger dihedral angle at the edge (usually an almost flat tet lying across
    it), or the other end where ``skip`` rules the first out.

    Args:
        mesh: the tet mesh.
        skip: optional ``skip(tets) -> (K,) bool`` for candidate tet ids (K,) of ``mesh``.

    Returns:
        (J,) int64 unique tet ids of ``mesh``, at most one per overlapping edge.
    """
    from holowarp.tetmesh import TET_EDGES, _row_keys

    n = max(mesh.num_vertices, 1)
    edges, wedge = mesh.boundary_wedges()
    over = _row_keys(edges[wedge > 360.0], n)
    if len(over) == 0:
        return np.zeros(0, dtype=np.int64)
    bf = mesh.boundary_faces().astype(np.int64)
    fe = _row_keys(np.sort(np.stack([bf[:, [0, 1]], bf[:, [1, 2]], bf[:, [2, 0]]], 1), axis=2).reshape(-1, 2), n)
    hit = np.flatnonzero(np.isin(fe, over))
    tet = mesh.boundary_face_tets()[hit // 3].astype(np.int64)
    if skip is not None:
        ok = ~skip(tet)
        hit, tet = hit[ok], tet[ok]
    if len(hit) == 0:
        return np.zeros(0, dtype=np.int64)
    te = _row_keys(np.sort(mesh.tets[tet][:, TET_EDGES], axis=2).reshape(-1, 2), n).reshape(-1, 6)
    local = np.argmax(te == fe[hit, None], axis=1)
    angle = np.nan_to_num(TetMesh(mesh.vertices, mesh.tets[tet], validate=False).dihedral_angles())
    order = np.lexsort((-angle[np.arange(len(tet)), local], fe[hit]))  # per edge, the larger angle first
    first = order[np.r_[True, fe[hit][order][1:] != fe[hit][order][:-1]]]
    return np.unique(tet[first])


def _peel_overlaps(vertices, t, keep, config: CleanupConfig):
    """Step 3's overlaps: each round drops the tets :func:`overlap_ends` picks in
    ``t[keep]``, then runs the manifold restoration; an end tet it puts back is not tried
    again. Returns (keep, the tets dropped here), each (M,) bool."""
    peeled = np.zeros(len(t), dtype=bool)
    tried = np.zeros(len(t), dtype=bool)
    for _ in range(config.max_repair_rounds):
        ids = np.flatnonzero(keep)
        ends = overlap_ends(TetMesh(vertices, t[ids], validate=False), skip=lambda tt: tried[ids[tt]])
        if len(ends) == 0:
            break
        drop = np.zeros(len(t), dtype=bool)
        drop[ids[ends]] = True
        keep, _ = restore_until_manifold(vertices, t, keep & ~drop, drop)
        tried |= drop & keep
        peeled |= drop & ~keep
    return keep, peeled


def _put_back_folding_caps(vertices, t, keep, caps, capped, config: CleanupConfig):
    """Step 3's folds: put back the dropped caps ``caps`` (M,) bool that hold a boundary edge
    of ``t[keep]`` whose wedge is a knife ridge (under ``blunt_wedge_deg``) or a slit (over
    360° minus it), with the manifold restoration (candidates ``capped``) after each round,
    until none does. Returns (keep, the caps put back here), each (M,) bool; nothing is put
    back when ``blunt_wedge_deg`` is 0."""
    from holowarp.tetmesh import TET_EDGES, _row_keys

    folds = np.zeros(len(t), dtype=bool)
    if config.blunt_wedge_deg <= 0:
        return keep, folds
    n = max(len(vertices), 1)
    for _ in range(config.max_repair_rounds):
        cand = np.flatnonzero(caps & ~keep)
        if len(cand) == 0:
            break
        edges, wedge = TetMesh(vertices, t[keep], validate=False).boundary_wedges()
        sharp = (wedge < config.blunt_wedge_deg) | (wedge > 360.0 - config.blunt_wedge_deg)
        if not sharp.any():
            break
        ce = _row_keys(np.sort(t[cand][:, TET_EDGES].reshape(-1, 2), axis=1).astype(np.int64), n)
        hit = np.isin(ce, _row_keys(np.sort(edges[sharp], axis=1).astype(np.int64), n)).reshape(-1, 6).any(axis=1)
        if not hit.any():
            break
        keep = keep.copy()
        keep[cand[hit]] = True
        folds[cand[hit]] = True
        keep, _ = restore_until_manifold(vertices, t, keep, capped & ~keep)
    return _drop_fin_folds(vertices, t, keep, folds, capped, config)


def _sharpest_at(mesh: TetMesh, tets: np.ndarray, n: int) -> np.ndarray:
    """(K,) how sharp ``mesh``'s boundary is at the edges of ``tets`` (K, 4): the smallest
    ``min(wedge, 360 - wedge)`` in degrees (a knife ridge or a slit,
    :meth:`~holowarp.tetmesh.TetMesh.boundary_wedges`); 180 where none of a tet's edges is on
    the boundary."""
    from holowarp.tetmesh import TET_EDGES, _row_keys

    edges, wedge = mesh.boundary_wedges()
    if len(edges) == 0:
        return np.full(len(tets), 180.0)
    keys = _row_keys(np.sort(edges, axis=1).astype(np.int64), n)
    order = np.argsort(keys)
    keys, sharp = keys[order], np.minimum(wedge, 360.0 - wedge)[order]
    te = _row_keys(np.sort(tets[:, TET_EDGES].reshape(-1, 2), axis=1).astype(np.int64), n)
    at = np.clip(np.searchsorted(keys, te), 0, len(keys) - 1)
    return np.where(keys[at] == te, sharp[at], 180.0).reshape(-1, 6).min(axis=1)


def _drop_fin_folds(vertices, t, keep, folds, capped, config: CleanupConfig):
    """Step 3's folds, second look: a cap put back for a fold whose own edges are sharper
    (:func:`_sharpest_at`) than what its removal leaves there is dropped again, one at a
    time, unless the manifold restoration puts it back. A thin tet standing in a slit makes
    a knife of its free edge: on the bowl at 128² (fast, seed 0) one such tet held a 6.2°
    ridge beside 4.9° slits, against a 15.9° ridge without it, and §7b's worst angle was
    8.4°. Returns (keep, folds), each (M,) bool."""
    n = max(len(vertices), 1)
    cand = np.flatnonzero(folds & keep)
    if len(cand) == 0 or config.blunt_wedge_deg <= 0:
        return keep, folds
    mesh = TetMesh(vertices, t[keep], validate=False)
    held = _sharpest_at(mesh, t[cand], n)
    for c in cand[np.argsort(held)][: config.max_repair_rounds]:
        now = _sharpest_at(mesh, t[[c]], n)[0]
        if now >= config.blunt_wedge_deg:
            continue
        trial = keep.copy()
        trial[c] = False
        trial, _ = restore_until_manifold(vertices, t, trial, capped & ~trial)
        if trial[c]:
            continue
        after = TetMesh(vertices, t[trial], validate=False)
        if _sharpest_at(after, t[[c]], n)[0] > now:
            keep, mesh = trial, after
            folds = folds & keep
    return keep, folds
