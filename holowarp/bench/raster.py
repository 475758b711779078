"""Benchmark of the Warp surfel rasteriser: ``python -m holowarp.bench raster --json``.

Scenes: N surfels tangent to a sphere of radius 0.5 (the shape of a trained object: one
opaque layer in front, a hidden one behind), sized to cover it with some overlap, random
colours and opacities in [0.3, 0.95], seen by the synthetic protocol's camera (fov 39.3
degrees, distance 2.7). Cases: 10k surfels at 128^2 and 50k at 256^2 on the chosen device
(plus 200k at 512^2 on CUDA). Times are medians of ``--repeat`` runs after a warm-up;
"backward" is ``loss.backward()`` of a loss touching every output (rgb, alpha, normal,
depth, median depth, distortion). The dense float64 torch reference
(:mod:`holowarp.ops.surfels_ref`) is timed once at the smaller size for the speed-up.
Peak memory: ``peak_rss_mb_warp`` is the process's peak resident set after the Warp cases
(before the reference runs), ``peak_rss_mb`` after everything.
"""

from __future__ import annotations

import argparse
import json
import math
import statistics
import time

import numpy as np
import torch

from holowarp.bench import peak_rss_mb
from holowarp.camera import FOV_DEG, intrinsics_from_fov, look_at
from holowarp.device import resolve_device
from holowarp.gaussians import quats_facing

__all__ = ["sphere_scene", "time_case", "main"]

CPU_CASES = ((10_000, 128), (50_000, 256))
CUDA_EXTRA_CASES = ((200_000, 512),)


def sphere_scene(n: int, res: int, *, seed: int = 0, device="cpu"):
    """``n`` surfels tangent to a sphere of radius 0.5 and a camera at distance 2.7.

    Returns (means, quats, scales, opacities, colors, viewmat, K) as tensors.
    """
    rng = np.random.default_rng(seed)
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    quats = quats_facing(d)
    spacing = math.sqrt(4 * math.pi * 0.25 / n)
    scales = rng.uniform(0.5, 1.0, (n, 2)) * spacing
    opac = rng.uniform(0.3, 0.95, n)
    cols = rng.uniform(0, 1, (n, 3))
    V = look_at([2.7 * math.cos(0.3), 0.0, 2.7 * math.sin(0.3)])
    K = intrinsics_from_fov(math.radians(FOV_DEG), res, res)
    f32 = [torch.tensor(a, dtype=torch.float32, device=device) for a in (0.5 * d, quats, scales, opac, cols)]
    return (*f32, torch.tensor(V), torch.tensor(K))


def _loss(out):
    return (
        out["rgb"].sum() + out["alpha"].sum() + out["normal"].sum() + out["depth"].sum()
        + out["median_depth"].sum() + out["distortion"].sum()
    )  # fmt: skip


def _sync(device):
    if device.startswith("cuda"):
        torch.cuda.synchronize()


def time_case(fn, scene, res: int, *, repeat: int, device: str) -> dict:
    """Median forward and backward milliseconds of ``fn`` (rasterize_surfels or the reference)."""
    means, quats, scales, opac, cols, V, K = scene
    fwd, bwd = [], []
    out = None
    for r in range(repeat + 1):
        leaves = [t.detach().clone().requires_grad_(True) for t in (means, quats, scales, opac, cols)]
        _sync(device)
        t0 = time.perf_counter()
        out = fn(*leaves, V, K, res, res)
        _sync(device)
        t1 = time.perf_counter()
        _loss(out).backward()
        _sync(device)
        t2 = time.perf_counter()
        if r > 0 or repeat == 0:  # the first run warms up (kernel load, allocator)
            fwd.append((t1 - t0) * 1e3)
            bwd.append((t2 - t1) * 1e3)
    res_ = {
        "forward_ms": statistics.median(fwd),
        "backward_ms": statistics.median(bwd),
        "alpha_mean": float(out["alpha"].detach().mean()),
    }
    res_["total_ms"] = res_["forward_ms"] + res_["backward_ms"]
    return res_


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m holowarp.bench raster", description=__doc__.split("\n")[0])
    p.add_argument("--json", action="store_true", help="print JSON only")
    p.add_argument("--device", default="cpu")
    p.add_argument("--repeat", type=int, default=7, help="timed runs per case (after one warm-up)")
    p.add_argument("--no-reference", action="store_true", help="skip the dense reference (slow)")
    p.add_argument("--reference-chunk", type=int, default=256, help="pixels per reference chunk (memory bound)")
    args = p.parse_args(argv)
    device = resolve_device(args.device)
    from holowarp.ops import rasterize_surfels
    from holowarp.ops.surfels_ref import rasterize_surfels_ref

    cases = list(CPU_CASES) + (list(CUDA_EXTRA_CASES) if device.startswith("cuda") else [])
    results = []
    for n, res in cases:
        scene = sphere_scene(n, res, device=device)
        r = time_case(rasterize_surfels, scene, res, repeat=args.repeat, device=device)
        results.append({"surfels": n, "resolution": res, **r})
        if not args.json:
            print(f"warp  {n:>7d} surfels {res}^2: fwd {r['forward_ms']:.1f} ms, bwd {r['backward_ms']:.1f} ms")
    report = {"device": device, "cases": results, "peak_rss_mb_warp": peak_rss_mb()}
    if device.startswith("cuda"):
        report["peak_cuda_mb_warp"] = torch.cuda.max_memory_allocated() / 2**20
    if not args.no_reference:
        n, res = CPU_CASES[0]
        scene = sphere_scene(n, res, device=device)

        def ref(*a):
            return rasterize_surfels_ref(*a, pixel_chunk=args.reference_chunk)

        r = time_case(ref, scene, res, repeat=0, device=device)
        report["reference"] = {"surfels": n, "resolution": res, "dtype": "float64", **r}
        report["speedup_vs_reference"] = r["total_ms"] / results[0]["total_ms"]
        if not args.json:
            print(f"dense reference {n} surfels {res}^2: fwd {r['forward_ms']:.0f} ms, bwd {r['backward_ms']:.0f} ms "
                  f"-> speed-up {report['speedup_vs_reference']:.0f}x")  # fmt: skip
    if not device.startswith("cuda"):
        report["note"] = "CPU run (Warp runs kernel threads serially on CPU); no GPU figures (200k surfels at 512^2)."
    report["peak_rss_mb"] = peak_rss_mb()  # includes the reference's chunks
    print(json.dumps(report, indent=2))
    return 0
