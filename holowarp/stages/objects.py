"""Scene level (method.md §11): the final mesh of a capture of several objects, split into
one tet mesh per object, and the scene's outputs.

The prunes and the cleanup of a scene keep every face-connected component above a size
threshold (:attr:`holowarp.config.SceneConfig.min_component`). Here the kept tets are
assigned to objects (:func:`assign_objects`):

1. face connectivity: each component is one object;
2. where objects touch they share a component, so there are fewer components than objects
   (known only from the dataset's ``objects/`` folders or ``--objects N``): the extra
   objects go, one at a time, to the component with the most tets per object so far, and
   such a component is split by k-means (:func:`cluster_split`, SciPy's ``kmeans2``) over
   its surfels' positions and colours. A cluster must be face-connected: its smaller
   pieces are regrown from the clusters' largest pieces (:func:`_connected_clusters`);
3. more components than objects: the largest components are the objects; the others stay
   in the whole scene's mesh and are reported as unassigned.

Each object's tets then lose the minority fans around any non-manifold edge or vertex that
the cut left (:func:`holowarp.manifold.repair_manifold`) and keep their largest piece, so
every object is one connected, manifold, inversion-free mesh.

Names (:func:`name_objects`): a dataset written by ``holowarp.synth SCENE.toml`` has
``objects/NAME/gt.obj`` in the dataset's world; each object takes the name of the ground
truth whose bounding-box centre is nearest to its own (a one-to-one assignment, SciPy's
``linear_sum_assignment``). Objects without one are ``object_0``, ``object_1``, ...

Outputs (:func:`write_scene`): ``objects/NAME/tetmesh.vtu`` and ``surface.obj`` per object,
``scene.usda`` with every object as its own deformable body, and ``scene.toml``, a
``[[bodies]]`` scene for ``python -m holowarp.simulate`` in which the objects keep their
reconstructed relative positions (one scale factor for all, so the largest object is
``sim_size`` metres, dropped from ``sim_drop`` metres). The world is the dataset's, Z up
(synth's frame, and the frame :mod:`holowarp.data.normalize` gives a capture).
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from holowarp.config import SceneConfig
from holowarp.manifold import repair_manifold
from holowarp.tetmesh import TetMesh

__all__ = ["cluster_split", "assign_objects", "dataset_objects", "hull_pieces", "largest_side", "measure_object_size",
           "name_objects", "write_scene", "scene_toml"]

#: Hull pieces with fewer grid nodes than this fraction of the hull's are ignored by
#: :func:`hull_pieces` (specks a stray mask pixel leaves).
MIN_PIECE_FRACTION = 0.01


def cluster_split(positions, colors, k: int, *, color_weight: float = 1.0, restarts: int = 8,
                  seed: int = 0) -> np.ndarray:
    """k-means labels (N,) int64 in ``[0, k)`` of points with positions (N, 3) and colours
    (N, 3) in [0, 1].

    Features are the positions centred and divided by their bounding-box diagonal (so a
    spread of about 1 whatever the units) beside ``color_weight`` times the colours: the
    positions part objects that are apart, the colours part touching objects of different
    colours. ``restarts`` k-means++ runs; the one with the lowest distortion (sum of
    squared feature distances to the centres) wins. Deterministic in ``seed``.
    """
    from scipy.cluster.vq import kmeans2

    P = np.asarray(positions, dtype=np.float64)
    C = np.asarray(colors, dtype=np.float64)
    if P.shape != C.shape or P.ndim != 2 or P.shape[1] != 3:
        raise ValueError(f"cluster_split: positions {P.shape} and colors {C.shape} must both be (N, 3)")
    if not 1 <= k <= len(P):
        raise ValueError(f"cluster_split: k = {k} must lie in [1, {len(P)}] (the number of points)")
    if k == 1:
        return np.zeros(len(P), dtype=np.int64)
    diag = float(np.linalg.norm(np.ptp(P, axis=0))) or 1.0
    X = np.concatenate([(P - P.mean(0)) / diag, color_weight * C], axis=1)
    rng = np.random.default_rng(seed)
    best, best_cost = None, np.inf
    for _ in range(restarts):
        centres, labels = kmeans2(X, k, minit="++", seed=rng)
        cost = float(((X - centres[labels]) ** 2).sum())
        if len(np.unique(labels)) == k and cost < best_cost:
            best, best_cost = labels, cost
    if best is None:  # every run left a cluster empty (k close to N): split along the main axis
        order = np.argsort((P - P.mean(0)) @ np.linalg.svd(P - P.mean(0), full_matrices=False)[2][0])
        best = np.empty(len(P), dtype=np.int64)
        best[order] = np.arange(len(P)) * k // len(P)
    return best.astype(np.int64)


def _connected_clusters(adj: np.ndarray, labels: np.ndarray) -> np.ndarray:
    """``labels`` (M,) in ``[0, k)`` with every cluster made face-connected (tet face
    adjacency ``adj`` (M, 4), -1 on the boundary; the tets one connected piece).

    Each cluster keeps its largest piece; the tets of its other pieces are released and
    regrown from the kept pieces, layer by layer through faces: a released tet joins the
    cluster most of its already assigned neighbours belong to (ties: the lower label).
    Every tet joins next to one of its own cluster, so every cluster ends connected."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    M = len(labels)
    rows = np.repeat(np.arange(M), 4)
    cols = adj.reshape(-1)
    inner = cols >= 0
    r, c = rows[inner], cols[inner]
    same = labels[r] == labels[c]
    n, piece = connected_components(coo_matrix((np.ones(int(same.sum())), (r[same], c[same])), shape=(M, M)),
                                    directed=False)
    size = np.bincount(piece, minlength=n)
    main = np.zeros(n, dtype=bool)
    for lab in np.unique(labels):
        ps = np.unique(piece[labels == lab])
        main[ps[np.argmax(size[ps])]] = True
    out = np.where(main[piece], labels, -1)
    k = int(labels.max()) + 1
    while (out < 0).any():
        nb = np.where(adj >= 0, out[np.maximum(adj, 0)], -1)  # (M, 4) neighbours' labels, -1: none yet
        votes = np.stack([(nb == j).sum(axis=1) for j in range(k)], axis=1)
        grow = (out < 0) & (votes.max(axis=1) > 0)
        if not grow.any():  # not reachable from any kept piece (the tets were not one piece)
            break
        out[grow] = np.argmax(votes[grow], axis=1)
    return np.where(out < 0, labels, out)


def _split_plan(sizes: np.ndarray, num_objects: int) -> np.ndarray:
    """Objects per component (n,) for ``num_objects`` > n components: one each, then every
    extra object to the component with the most tets per object so far."""
    per = np.ones(len(sizes), dtype=np.int64)
    for _ in range(num_objects - len(sizes)):
        per[int(np.argmax(sizes / per))] += 1
    return per


def assign_objects(mesh: TetMesh, positions, colors, num_objects: int | None = None,
                   config: SceneConfig = SceneConfig(), *, seed: int = 0) -> tuple[list[np.ndarray], dict]:
    """Assign the tets of ``mesh`` to objects (see the module docstring).

    Args:
        mesh: the scene's final tet mesh (M tets).
        positions, colors: (M, 3) its surfels' centres (world units) and RGB in [0, 1].
        num_objects: how many objects there are; ``None``: one per face-connected component.
        config: the clustering settings.

    Returns:
        (objects, info): ``objects`` a list of int64 arrays of tet indices, largest object
        first, each one face-connected and boundary-manifold; ``info`` with ``components``
        (of ``mesh``), ``objects_expected``, ``split_components`` (the components clustered
        and into how many objects), ``unassigned_tets`` (in no object: components beyond
        ``num_objects`` and what the manifold repair removed) and ``source_component`` (per
        object, the component it came from).
    """
    labels, n = mesh.components()
    sizes = np.bincount(labels, minlength=n)
    order = np.argsort(-sizes, kind="stable")
    k = n if num_objects is None else int(num_objects)
    if k < 1:
        raise ValueError(f"assign_objects: num_objects must be >= 1, got {num_objects}")
    groups, source, split = [], [], []
    if k <= n:
        for c in order[:k]:
            groups.append(np.flatnonzero(labels == c))
            source.append(int(c))
    else:
        adj = mesh.face_adjacency()
        for c, per in zip(order, _split_plan(sizes[order], k)):
            ids = np.flatnonzero(labels == c)
            if per == 1:
                groups.append(ids)
                source.append(int(c))
                continue
            lab = cluster_split(positions[ids], colors[ids], int(per), color_weight=config.color_weight,
                                restarts=config.cluster_restarts, seed=seed)
            sub_adj = _local_adjacency(adj, ids)
            lab = _connected_clusters(sub_adj, lab)
            split.append({"component": int(c), "tets": int(len(ids)), "objects": int(len(np.unique(lab)))})
            for j in np.unique(lab):
                groups.append(ids[lab == j])
                source.append(int(c))
    objects = [_manifold_piece(mesh, g) for g in groups]
    keep = [i for i, o in enumerate(objects) if len(o)]
    objects, source = [objects[i] for i in keep], [source[i] for i in keep]
    by_size = np.argsort([-len(o) for o in objects], kind="stable")
    objects, source = [objects[i] for i in by_size], [source[i] for i in by_size]
    info = {"components": int(n), "objects_expected": num_objects, "split_components": split,
            "unassigned_tets": int(mesh.num_tets - sum(len(o) for o in objects)), "source_component": source}
    return objects, info


def _local_adjacency(adj: np.ndarray, ids: np.ndarray) -> np.ndarray:
    """The face adjacency (len(ids), 4) among the tets ``ids`` only, in their local numbering."""
    local = np.full(len(adj), -1, dtype=np.int64)
    local[ids] = np.arange(len(ids))
    a = adj[ids]
    return np.where(a >= 0, local[np.maximum(a, 0)], -1)


def _manifold_piece(mesh: TetMesh, ids: np.ndarray) -> np.ndarray:
    """``ids`` less the minority fans around non-manifold boundary edges and vertices, then
    its largest face-connected piece: the tets of one manifold, connected object."""
    sub = TetMesh(mesh.vertices, mesh.tets[ids], validate=False)
    keep, _ = repair_manifold(sub)
    ids = ids[keep]
    if len(ids) == 0:
        return ids
    lab, n = TetMesh(mesh.vertices, mesh.tets[ids], validate=False).components()
    return ids[lab == np.argmax(np.bincount(lab))] if n > 1 else ids


def hull_pieces(dataset, *, device: str = "cpu") -> list[tuple[np.ndarray, np.ndarray]]:
    """The objects of a capture as its masks see them: the visual hull on a grid
    (:func:`holowarp.data.normalize.hull_nodes`) split into 6-connected pieces (SciPy's
    ``ndimage.label``), each piece with at least :data:`MIN_PIECE_FRACTION` of the hull's
    nodes as its bounding box ``(lo (3,), hi (3,))`` in world units, grown by half a grid
    cell on every side (the hull's boundary lies within a cell beyond its outermost nodes;
    spot in the three-object test scene: largest side 0.433 against its ground truth's
    0.440). Largest piece first. Objects that touch, or whose hulls merge, are one piece."""
    from scipy import ndimage

    from holowarp.data.normalize import FINE_GRID, hull_nodes

    pts, inside, h = hull_nodes(dataset, device=device)
    n = FINE_GRID
    labels, count = ndimage.label(inside.reshape(n, n, n))
    labels = labels.ravel()
    sizes = np.bincount(labels, minlength=count + 1)
    sizes[0] = 0
    pieces = []
    for lab in np.argsort(-sizes, kind="stable"):
        if sizes[lab] < max(1, MIN_PIECE_FRACTION * inside.sum()):
            break
        p = pts[labels == lab]
        pieces.append((p.min(0) - 0.5 * h, p.max(0) + 0.5 * h))
    return pieces


def largest_side(pieces) -> float:
    """Largest bounding-box side of any of ``pieces`` (:func:`hull_pieces`)."""
    return max(float((hi - lo).max()) for lo, hi in pieces)


def measure_object_size(dataset, *, device: str = "cpu") -> float:
    """Largest side of the largest object of a capture, in its world units: the
    :func:`largest_side` of its :func:`hull_pieces`. Objects that touch, or whose hulls
    merge, count as one, so the size errs towards the larger (the single-object settings).
    Sets :attr:`holowarp.config.SceneConfig.object_size` of a scene run."""
    return largest_side(hull_pieces(dataset, device=device))


def dataset_objects(data_dir) -> dict:
    """``{name: gt.obj path}`` of ``data_dir/objects/NAME/gt.obj`` (empty without that folder)."""
    root = Path(data_dir) / "objects"
    if not root.is_dir():
        return {}
    return {p.parent.name: p for p in sorted(root.glob("*/gt.obj"))}


def _bbox_centre(v: np.ndarray) -> np.ndarray:
    return 0.5 * (v.min(0) + v.max(0))


def name_objects(centres, gt_centres: dict) -> list[str]:
    """Names of objects whose bounding-box centres are ``centres`` (K, 3): the one-to-one
    assignment to ``gt_centres`` (``{name: (3,)}``) of least total distance; objects left
    over are ``object_0``, ``object_1``, ... (numbered in order, skipping taken names)."""
    from scipy.optimize import linear_sum_assignment

    centres = np.asarray(centres, dtype=np.float64).reshape(-1, 3)
    names: list[str | None] = [None] * len(centres)
    if gt_centres and len(centres):
        gn = list(gt_centres)
        G = np.asarray([gt_centres[g] for g in gn], dtype=np.float64).reshape(-1, 3)
        r, c = linear_sum_assignment(np.linalg.norm(centres[:, None] - G[None], axis=2))
        for i, j in zip(r, c):
            names[i] = gn[j]
    taken, k = set(n for n in names if n), 0
    for i, n in enumerate(names):
        if n is None:
            while f"object_{k}" in taken:
                k += 1
            names[i] = f"object_{k}"
            taken.add(names[i])
    return names


def _float(x: float) -> str:
    """``x`` as a TOML float (always with a point or exponent, so never read as an integer)."""
    s = f"{float(x):.9g}"
    return s if any(ch in s for ch in ".en") else s + ".0"


def _body_name(name: str, used: set) -> str:
    """A unique Python identifier for a scene body (the simulator's rule) from ``name``."""
    s = re.sub(r"\W", "_", name)
    s = s if s and not s[0].isdigit() else "_" + s
    base, k = s, 1
    while s in used:
        s, k = f"{base}_{k}", k + 1
    used.add(s)
    return s


def scene_toml(meshes: list[TetMesh], paths: list[str], names: list[str], config: SceneConfig = SceneConfig()) -> str:
    """A ``[[bodies]]`` scene (:mod:`holowarp.sim.scene`) holding the objects ``meshes`` (in
    the dataset's world, Z up) from the mesh files ``paths`` (relative to the scene file)
    at their reconstructed relative positions.

    One factor ``k = sim_size / (largest side of the largest object)`` scales every object,
    and each body's placement (no rotation) is ``size = k * its largest side``, ``center_xy
    = k * (its bbox centre - the scene's)``, ``height = sim_drop + k * (its lowest z - the
    scene's)``; :func:`holowarp.sim.scene.placement_transform` then maps each mesh with
    scale ``k`` to exactly those places, so the bodies keep the scene's layout.
    """
    ext = [float(np.ptp(m.vertices, axis=0).max()) for m in meshes]
    k = config.sim_size / max(ext)
    allv = np.concatenate([m.vertices for m in meshes])
    centre, floor = _bbox_centre(allv), float(allv[:, 2].min())
    lines = [
        "# holowarp scene written by reconstruct --scene-level (method.md §11): every reconstructed object",
        "# is one body at its reconstructed place, all scaled by one factor, dropped onto the ground:",
        "#     python -m holowarp.simulate tetmesh.vtu --scene scene.toml --out sim",
        f"# scale: {k:.6g} m per dataset unit (the largest object is {config.sim_size:g} m).",
        "", 'name = "scene"', "",
        "[sim]", "dt = 0.016666666666666666", "substeps = 1", "iterations = 16", "duration = 1.5",
        "gravity = [0.0, 0.0, -9.81]", "damping = 0.0", "",
        "[material]", "youngs_modulus = 2.0e5", "poissons_ratio = 0.45", "density = 1000.0", "friction = 0.5",
        "restitution = 0.0", "",
        "[ground]", "enabled = true", "",
        "[contact]", "stiffness = 10.0", "self_collision = false",
    ]
    used: set = set()
    for m, p, n, e in zip(meshes, paths, names, ext):
        c = _bbox_centre(m.vertices)
        xy = k * (c[:2] - centre[:2])
        h = config.sim_drop + k * (float(m.vertices[:, 2].min()) - floor)
        lines += ["", "[[bodies]]", f'name = "{_body_name(n, used)}"', f'mesh = "{p}"', "[bodies.placement]",
                  f"size = {_float(k * e)}", f"center_xy = [{_float(xy[0])}, {_float(xy[1])}]",
                  f"height = {_float(h)}"]
    return "\n".join(lines) + "\n"


def write_scene(out_dir, mesh: TetMesh, objects: list[np.ndarray], names: list[str], colors=None, *,
                config: SceneConfig = SceneConfig(), material=None) -> dict:
    """Write the per-object outputs of a scene (see the module docstring); returns the paths
    (``scene_usda``, ``scene_toml`` and per object ``objects``: ``{name: tetmesh.vtu}``).

    Args:
        out_dir: the run's folder.
        mesh: the scene's final tet mesh; ``objects`` its tet indices per object.
        names: the objects' folder names.
        colors: optional (M, 3) surfel colours, averaged into each body's display colour.
    """
    from holowarp.fileio import atomic_write_text
    from holowarp.mesh_io import write_tetmesh
    from holowarp.surface_io import write_surface
    from holowarp.usd import PhysicsMaterial, UsdSceneWriter

    out = Path(out_dir)
    w = UsdSceneWriter(out / "scene.usda")
    meshes, paths, files = [], [], {}
    for ids, name in zip(objects, names):
        m = mesh.submesh(ids)
        meshes.append(m)
        d = out / "objects" / name
        d.mkdir(parents=True, exist_ok=True)
        files[name] = str(write_tetmesh(d / "tetmesh.vtu", m))
        write_surface(d / "surface.obj", m)
        paths.append(f"objects/{name}/tetmesh.vtu")
        col = (0.8, 0.55, 0.35) if colors is None else tuple(float(x) for x in np.asarray(colors)[ids].mean(0))
        w.add_tetmesh(name, m, material=material or PhysicsMaterial(), color=col)
    usda = w.save()
    toml = atomic_write_text(out / "scene.toml", scene_toml(meshes, paths, names, config))
    return {"scene_usda": str(usda), "scene_toml": str(toml), "objects": files}
