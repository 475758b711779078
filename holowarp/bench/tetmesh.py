"""``python -m holowarp.bench tetmesh [--tets 1000000] [--json]``: the TetMesh core at scale.

Times every TetMesh query on a fresh mesh (caches cleared between repeats) of about
``--tets`` tetrahedra: a structured box with jittered interior vertices, so that nothing is
axis-aligned. The issue's bar: 1M tets in seconds, not minutes.
"""

from __future__ import annotations

import argparse
import json
import math

import numpy as np

from holowarp.bench import median_ms, peak_rss_mb
from holowarp.primitives import box_tetmesh
from holowarp.tetmesh import TetMesh

__all__ = ["main"]


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m holowarp.bench tetmesh")
    p.add_argument("--tets", type=int, default=1_000_000, help="approximate number of tets")
    p.add_argument("--repeat", type=int, default=3)
    p.add_argument("--json", action="store_true", help="print JSON only")
    args = p.parse_args(argv)

    n = max(1, round((args.tets / 6) ** (1 / 3)))
    base = box_tetmesh((n, n, n), (1.0, 1.0, 1.0))
    rng = np.random.default_rng(0)
    V = base.vertices + rng.uniform(-0.1, 0.1, base.vertices.shape) / n
    fresh = lambda: TetMesh(V, base.tets)  # noqa: E731  (a new mesh = empty caches)

    ops = {
        "construct_validate": lambda: fresh(),
        "signed_volumes": lambda: fresh().signed_volumes(),
        "oriented": lambda: fresh().oriented(),
        "boundary_faces": lambda: fresh().boundary_faces(),
        "surface_vertices": lambda: fresh().surface_vertices(),
        "edges": lambda: fresh().edges(),
        "face_adjacency": lambda: fresh().face_adjacency(),
        "adjacency_laplacian": lambda: fresh().adjacency_laplacian(),
        "components": lambda: fresh().components(),
        "keep_largest_component": lambda: fresh().keep_largest_component(),
        "remove_unused_vertices": lambda: fresh().remove_unused_vertices(),
        "manifold": lambda: fresh().manifold(),
        "genus": lambda: fresh().genus(),
        "quality_summary": lambda: fresh().quality_summary(),
        "summary_all": lambda: fresh().summary(),
    }
    times = {k: median_ms(f, repeat=args.repeat, warmup=0) for k, f in ops.items()}
    out = {
        "benchmark": "tetmesh",
        "tets": base.num_tets,
        "vertices": base.num_vertices,
        "median_ms": {k: round(v, 1) for k, v in times.items()},
        "total_s_all_queries": round(times["summary_all"] / 1e3, 2),
        "peak_rss_mb": round(peak_rss_mb(), 1),
    }
    if args.json:
        print(json.dumps(out, indent=2))
    else:
        print(f"TetMesh core on {out['tets']:,} tets / {out['vertices']:,} vertices")
        for k, v in times.items():
            print(f"  {k:26s} {v:10.1f} ms")
        print(f"  peak RSS {out['peak_rss_mb']} MiB")
    return 0 if all(math.isfinite(t) for t in times.values()) else 1
