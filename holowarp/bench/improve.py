"""``python -m holowarp.bench improve [--tets 200000] [--slivers 0.01] [--json]``: the
element-improvement stage (method.md §7b) at scale.

The input is a structured box of about ``--tets`` tetrahedra (Kuhn split) whose interior
vertices are jittered, with slivers planted: a ``--slivers`` fraction of the interior
vertices is pushed to within a few percent of the plane of an opposite face in its star,
which leaves those tets nearly flat but positive (:func:`planted_sliver_mesh`). The stage
runs ``--repeat`` times on it; the JSON gives the median seconds, the before/after quality
(worst and mean minimum dihedral, mean aspect ratio, minimum eta), the flip counts, the
measured surface Hausdorff distance, and peak memory.
"""

from __future__ import annotations

import argparse
import json
import statistics
import time

import numpy as np

from holowarp.bench import peak_rss_mb
from holowarp.primitives import box_tetmesh
from holowarp.tetmesh import TET_FACES, TetMesh

__all__ = ["main", "planted_sliver_mesh", "plant_slivers"]


def plant_slivers(mesh: TetMesh, fraction: float, rng, *, jitter: float = 0.25) -> TetMesh:
    """Jitter the interior vertices of ``mesh`` by up to ``jitter`` of the mean edge, then
    flatten tets: an independent set (no two in a tet) of ``fraction`` of the interior
    vertices is moved towards the plane of the face opposite it in one random star tet,
    by the largest of 98 %, 95 %, 90 % or 80 % of its height that keeps its star positive.

    Returns a positively oriented mesh with the same connectivity. Vectorised throughout.
    """
    V = mesh.vertices.copy()
    T = mesh.tets.astype(np.int64)
    N = len(V)
    inner = np.ones(N, dtype=bool)
    inner[mesh.boundary_faces().reshape(-1)] = False
    e = mesh.edges()
    L = float(np.linalg.norm(V[e[:, 0]] - V[e[:, 1]], axis=1).mean())
    # Jitter interior vertices; undo the moves that would invert a tet, until none does.
    V1 = V + np.where(inner[:, None], rng.uniform(-jitter, jitter, V.shape) * L, 0.0)
    while True:
        bad = TetMesh(V1.copy(), T, validate=False).signed_volumes() <= 1e-3 * L**3
        if not bad.any():
            break
        back = np.zeros(N, dtype=bool)
        back[T[bad].reshape(-1)] = True
        V1[back] = V[back]
    V = V1
    # Independent interior vertices: random priority beats every neighbour's.
    pri = np.where(inner, rng.random(N), -1.0)
    best = np.full(N, -1.0)
    np.maximum.at(best, e[:, 0], pri[e[:, 1]])
    np.maximum.at(best, e[:, 1], pri[e[:, 0]])
    cand = np.flatnonzero(inner & (pri > best))
    cand = rng.permutation(cand)[: max(1, int(fraction * inner.sum()))]
    # One random star tet per chosen vertex, and the plane of the face opposite it.
    flat = T.reshape(-1)
    order = np.argsort(flat, kind="stable")
    offs = np.r_[0, np.cumsum(np.bincount(flat, minlength=N))]
    pick = offs[cand] + (rng.random(len(cand)) * (offs[cand + 1] - offs[cand])).astype(np.int64)
    tet, loc = order[pick] // 4, order[pick] % 4
    face = T[tet[:, None], TET_FACES[loc]]
    a, b, c = V[face[:, 0]], V[face[:, 1]], V[face[:, 2]]
    n = np.cross(b - a, c - a)
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    h = np.einsum("ij,ij->i", V[cand] - a, n)
    cnt = offs[cand + 1] - offs[cand]
    owner = np.repeat(np.arange(len(cand)), cnt)
    star = order[np.repeat(offs[cand], cnt) + np.arange(int(cnt.sum())) - np.repeat(np.cumsum(cnt) - cnt, cnt)] // 4
    todo = np.ones(len(cand), dtype=bool)
    for f in (0.98, 0.95, 0.9, 0.8):
        trial = V.copy()
        trial[cand[todo]] = V[cand[todo]] - (f * h[todo])[:, None] * n[todo]
        vol = TetMesh(trial, T[star], validate=False).signed_volumes()
        ok = np.ones(len(cand), dtype=bool)
        np.logical_and.at(ok, owner, vol > 0)
        done = todo & ok
        V[cand[done]] = trial[cand[done]]
        todo &= ~ok
        if not todo.any():
            break
    return TetMesh(V, T)


def planted_sliver_mesh(tets: int = 200_000, fraction: float = 0.01, seed: int = 0) -> TetMesh:
    """A jittered Kuhn-split box of about ``tets`` tets with planted slivers (:func:`plant_slivers`)."""
    n = max(2, round((tets / 6) ** (1 / 3)))
    return plant_slivers(box_tetmesh((n, n, n)), fraction, np.random.default_rng(seed))


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m holowarp.bench improve")
    p.add_argument("--tets", type=int, default=200_000, help="approximate number of tets")
    p.add_argument("--slivers", type=float, default=0.01, help="fraction of interior vertices flattened")
    p.add_argument("--repeat", type=int, default=1, help="timed runs (the median is reported)")
    p.add_argument("--device", default="cpu")
    p.add_argument("--json", action="store_true", help="print JSON only")
    args = p.parse_args(argv)

    from holowarp.device import resolve_device
    from holowarp.stages.improve import improve

    device = resolve_device(args.device)
    mesh = planted_sliver_mesh(args.tets, args.slivers)
    # Load (or compile) the kernels outside the timing.
    improve(TetMesh([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], [[0, 1, 2, 3]]), device=device)
    times, info = [], None
    for _ in range(max(1, args.repeat)):
        t0 = time.perf_counter()
        _, _, info = improve(mesh, device=device)
        times.append(time.perf_counter() - t0)
    keys = ("tets", "min_dihedral_worst", "min_dihedral_mean", "aspect_ratio_mean", "eta_min", "inverted")
    res = {
        "benchmark": "improve",
        "device": device,
        "tets": mesh.num_tets,
        "vertices": mesh.num_vertices,
        "median_s": round(statistics.median(times), 2),
        "before": {k: info["before"][k] for k in keys},
        "after": {k: info["after"][k] for k in keys},
        "flips": info["flips"],
        "splits": info["splits"],
        "vertices_smoothed": info["vertices_smoothed"],
        "surface_hausdorff_mean_edges": info["surface_hausdorff_mean_edges"],
        "rounds": info["rounds"],
        "refinement": info["refinement"],
        "peak_rss_mb": round(peak_rss_mb(), 1),
    }
    if args.json:
        print(json.dumps(res, indent=2))
    else:
        b, a = res["before"], res["after"]
        print(f"improve on {res['tets']:,} tets ({device}): {res['median_s']} s")
        print(f"  worst min dihedral {b['min_dihedral_worst']:.2f} -> {a['min_dihedral_worst']:.2f} deg, "
              f"mean {b['min_dihedral_mean']:.2f} -> {a['min_dihedral_mean']:.2f} deg")
        print(f"  mean aspect {b['aspect_ratio_mean']:.3f} -> {a['aspect_ratio_mean']:.3f}, "
              f"min eta {b['eta_min']:.4f} -> {a['eta_min']:.4f}")
        print(f"  peak RSS {res['peak_rss_mb']} MiB")
    return 0 if info["after"]["inverted"] == 0 else 1
