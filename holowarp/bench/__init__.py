"""Benchmarks: ``python -m holowarp.bench NAME [--json] [--device cpu|cuda]``.

Each benchmark is a module ``holowarp.bench.NAME`` with a ``main(argv)`` that prints JSON
with median times, the ratio to the reference the issue names, and peak memory. Speed lives
here, never in timed tests.

- ``tetmesh``: the TetMesh core at 1M tets.
- ``raster``: the surfel rasteriser against the dense torch reference.
- ``mesh``: the triangle rasteriser and tet energies.
- ``sim``: the simulator against Newton ``SolverVBD``.
- ``eval``: metrics on a 100k-point pair and ground-truth rendering of 120 views.
- ``quality``: reconstruction quality against the visual hull on the concavity suite.
- ``improve``: the element-improvement stage on a 200k-tet mesh with planted slivers.
- ``load``: loading a 49-view 1600x1200 NeuS/IDR capture at 128 px (target: under 10 s).
- ``pipeline``: per phase of a short fast run, ms per iteration, kernel/torch/host shares,
  syncs and the overhead factor over the rasteriser alone.
"""

from __future__ import annotations

import resource
import statistics
import sys
import time

__all__ = ["BENCHMARKS", "median_ms", "peak_rss_mb"]

BENCHMARKS = ("tetmesh", "raster", "mesh", "sim", "eval", "improve", "quality", "load", "pipeline")


def median_ms(fn, *, repeat: int = 5, warmup: int = 1) -> float:
    """Median wall time of ``fn()`` in milliseconds over ``repeat`` runs after ``warmup``."""
    for _ in range(warmup):
        fn()
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        times.append((time.perf_counter() - t0) * 1e3)
    return statistics.median(times)


def peak_rss_mb() -> float:
    """Peak resident set size of this process in MiB (Linux reports KiB, macOS bytes)."""
    r = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return r / (1024.0 * 1024.0) if sys.platform == "darwin" else r / 1024.0
