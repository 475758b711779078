"""``python -m holowarp.bench pipeline --json [--dataset D]``: where a reconstruction
iteration's time goes, phase by phase (issue 17).

It runs a short fast-preset reconstruction on the dataset (default: the README's main job,
bob synthesised at 128², cached in ``--work``): stage 0 for ``--stage0-iters`` iterations
(its own schedule of that length), the tetrahedral initialisation, ``--iters`` topology
steps, the first prune, ``--iters`` Gaussian steps, then one geometry block of ``--iters``
steps, each phase with the pipeline's own step functions. Per phase it prints:

- ``ms_per_iter``: the median wall time of an iteration, without instrumentation;
- ``kernel_share``, ``torch_share``, ``host_share``: where the time of ``--probe-iters``
  further, instrumented iterations went (:class:`holowarp.bench.probe.Probe`);
- ``syncs_per_iter``, ``uploads_per_iter``, ``launches_per_iter``: host reads of device
  values, host-to-device tensor creations, Warp launches;
- ``raster_ms``: the phase's rasteriser forward + backward alone on the same model, for
  each view a timed iteration drew, right after that iteration (the surfel rasteriser for
  stage 0, topology and Gaussian steps, the triangle rasteriser for geometry steps), the
  median over them; and
  ``overhead_factor``: the timed iterations' total time over the total of their views'
  rasteriser alone (target <= 1.5). Views differ in cost (bob's cover 2x more pixels in
  some than in others), so the rasteriser is timed on the iterations' own views, not one.

Also ``model`` sizes at each phase, ``peak_rss_mb``, and the torch/Warp thread counts.
Time it alone: other jobs on the same cores make every number meaningless.
"""

from __future__ import annotations

import argparse
import json
import statistics
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch

__all__ = ["main", "build_parser"]


def build_parser() -> argparse.ArgumentParser:
    from holowarp.cli import add_device

    p = argparse.ArgumentParser(prog="python -m holowarp.bench pipeline", description=__doc__.splitlines()[0])
    p.add_argument("--dataset", default=None, metavar="DIR",
                   help="dataset folder (default: bob synthesised at --res into --work/data)")
    p.add_argument("--work", default="runs/bench-pipeline", metavar="DIR", help="work folder (default runs/bench-pipeline)")
    p.add_argument("--res", type=int, default=128, help="working resolution (default 128)")
    p.add_argument("--stage0-iters", type=int, default=200, help="stage-0 iterations (default 200)")
    p.add_argument("--iters", type=int, default=30, help="timed iterations per main-loop phase (default 30)")
    p.add_argument("--probe-iters", type=int, default=8, help="instrumented iterations per phase (default 8)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--json", action="store_true", help="print JSON only")
    add_device(p)
    return p


def _sync(dev):
    if dev.type == "cuda":
        torch.cuda.synchronize(dev)


def _phase(name, step, n: int, n_probe: int, raster, dev, *, warmup: int = 2) -> dict:
    """Time ``step(i)`` for ``n`` iterations, each followed by ``raster(i)`` (the rasteriser
    alone on the view of step ``i``), then probe ``n_probe`` more steps.

    Step and rasteriser are timed in turns, so that both see the machine in the same state:
    timed one block after the other, a machine whose speed drifts by a quarter within a
    minute (this 2-core VM's does) moved the ratio as much as any change measured."""
    from holowarp.bench.probe import Probe

    for i in range(warmup):
        step(i)
    raster(0)
    times, r_times = [], []
    for i in range(warmup, warmup + n):
        _sync(dev)
        t0 = time.perf_counter()
        step(i)
        _sync(dev)
        t1 = time.perf_counter()
        raster(i)
        _sync(dev)
        times.append((t1 - t0) * 1e3)
        r_times.append((time.perf_counter() - t1) * 1e3)
    with Probe(str(dev)) as probe:
        for i in range(warmup + n, warmup + n + n_probe):
            with probe.region():
                step(i)
    ms, r_ms = statistics.median(times), statistics.median(r_times)
    return {"phase": name, "iters": n, "ms_per_iter": round(ms, 2), "raster_ms": round(r_ms, 2),
            "overhead_factor": round(sum(times) / sum(r_times), 2), **probe.summary()}


def _surfel_raster(render_inputs, W, H, background):
    """Forward + backward of the surfel rasteriser alone on detached copies of its inputs."""
    from holowarp.ops import rasterize_surfels

    def run():
        ins = [t.detach().requires_grad_(True) for t in render_inputs[:5]]
        out = rasterize_surfels(*ins, *render_inputs[5:], W, H, background)
        loss = sum(out[k].sum() for k in ("rgb", "alpha", "normal", "depth", "median_depth", "distortion"))
        loss.backward()
    return run


def _stage0(ds, cfg, args, dev, out: Path):
    from holowarp.stages.gaussian_init import _train_views, _Trainer

    sch = cfg.stage0.schedule(args.stage0_iters)
    tr = _Trainer(ds, cfg.stage0, sch, out, seed=args.seed, device=dev)
    tr.fresh()
    train = _train_views(ds)
    n_total = args.stage0_iters
    n_timed = args.iters
    # Train most of the schedule untimed, time the last iterations (the model at its size).
    for it in range(n_total - n_timed - args.probe_iters - 2):
        tr.step(it, train)
    start = n_total - n_timed - args.probe_iters - 2
    m = tr.model
    # The trainer draws its own views; note the camera each step renders with.
    cams, render, current = {}, m.render, [0]

    def noted(viewmat, K, *a, **kw):
        cams.setdefault(current[0], (viewmat, K))
        return render(viewmat, K, *a, **kw)

    def step(i):
        current[0] = i
        tr.step(start + i, train)

    m.render = noted
    try:
        rec = _phase("stage0", step, n_timed, args.probe_iters,
                     lambda i: _surfel_raster([m.means, m.quats, m.scales(), m.opacities(), m.colors(), *cams[i]],
                                              ds.width, ds.height, tr.bg)(), dev)
    finally:
        del m.render
    rec["surfels"] = m.num
    m.save_ply(out / "gaussians.ply")
    return rec


def _tet_raster(model, ds, view):
    vm = torch.as_tensor(ds.viewmats[view], dtype=torch.float32, device=model.device)
    K = torch.as_tensor(ds.K[view], dtype=torch.float32, device=model.device)
    ins = [model.means(), model.quats, model.scales(), model.opacities(), model.colors(), vm, K]
    return _surfel_raster(ins, ds.width, ds.height, None)


def _main_loop(ds, cfg, args, dev, out: Path) -> list[dict]:
    from holowarp.stages.topology import (
        GaussianOptimizers,
        ViewTensors,
        after_first_prune,
        gaussian_step,
        init_model_from_surfels,
        prune,
    )

    t0 = time.perf_counter()
    model = init_model_from_surfels(out / "stage0" / "gaussians.ply", ds, cfg.tet_init, cfg.topology, seed=args.seed,
                                    device=dev, progress=False)
    recs = [{"phase": "tet_init", "seconds": round(time.perf_counter() - t0, 2), "tets": model.num_tets}]
    tensors = ViewTensors(ds, dev)
    train = ds.train_idx
    views = lambda i: int(train[np.random.default_rng([args.seed, 0, i]).integers(len(train))])  # noqa: E731

    def gaussian_phase(name, topo):
        opts = GaussianOptimizers(model, cfg.topology, learn_scales=not topo)
        edges = torch.tensor(np.array(model.mesh().edges()), dtype=torch.int32, device=dev)
        step = lambda i: gaussian_step(model, ds, views(i), cfg.topology, opts, topology_phase=topo,  # noqa: E731
                                       edges=edges, tensors=tensors)
        rec = _phase(name, step, args.iters, args.probe_iters, lambda i: _tet_raster(model, ds, views(i))(), dev)
        rec["tets"] = model.num_tets  # one surfel per tet
        return rec

    recs.append(gaussian_phase("topology", True))
    t0 = time.perf_counter()
    info = prune(model, cfg.topology)
    after_first_prune(model)
    recs.append({"phase": "prune", "seconds": round(time.perf_counter() - t0, 2), "tets": info.get("tets_after")})
    recs.append(gaussian_phase("gaussian", False))
    recs.append(_geometry(model, ds, cfg, args, dev))
    return recs


def _geometry(model, ds, cfg, args, dev) -> dict:
    from holowarp.ops import rasterize_mesh
    from holowarp.stages.geometry import GeometryBlock

    n = args.iters + args.probe_iters + 2
    blk = GeometryBlock(model, ds, ds.train_idx, cfg.geometry, block_iters=n, total_mesh_iters=n)
    # A block renders the frozen surfels' normals once per view it draws; over a whole run
    # that is a per-view cost, not a per-step one, so the cache is filled before timing.
    t0 = time.perf_counter()
    for v in ds.train_idx:
        blk.surfel_normals(int(v))
    cache_ms = (time.perf_counter() - t0) * 1e3 / len(ds.train_idx)

    def raster(k):
        view = blk.view_of(k, args.seed)
        x = blk.x.detach().clone().requires_grad_(True)
        out = rasterize_mesh(x, blk.faces, ds.viewmats[view], ds.K[view], ds.width, ds.height)
        (out["alpha"].sum() + out["normal"].sum()).backward()

    rec = _phase("geometry", lambda k: blk.step(k, k, args.seed), args.iters, args.probe_iters, raster, dev)
    blk.finish()
    rec.update(tets=model.num_tets, boundary_faces=int(blk.faces.shape[0]), surfel_normals_ms_per_view=round(cache_ms, 2))
    return rec


def main(argv=None) -> int:
    from holowarp.cli import run

    return run(_body, build_parser().parse_args(argv))


def _body(args) -> int:
    from holowarp.bench import peak_rss_mb
    from holowarp.cli import fail
    from holowarp.config import preset
    from holowarp.device import cpu_threads, resolve_device
    from holowarp.preflight import prepare_dataset

    for name in ("stage0_iters", "iters", "probe_iters", "res"):
        if getattr(args, name) < 1:
            fail(f"--{name.replace('_', '-')} must be >= 1, got {getattr(args, name)}")
    if args.stage0_iters < args.iters + args.probe_iters + 3:
        fail(f"--stage0-iters must be at least --iters + --probe-iters + 3 = {args.iters + args.probe_iters + 3}")
    dev_name = resolve_device(args.device)
    dev = torch.device(dev_name)
    cfg = replace(preset("fast"), resolution=args.res)
    work = Path(args.work)
    (work / "stage0").mkdir(parents=True, exist_ok=True)
    ds, data_dir = prepare_dataset(args.dataset, work, cfg, device=dev_name, progress=not args.json)

    phases = [_stage0(ds, cfg, args, dev, work / "stage0")] + _main_loop(ds, cfg, args, dev, work)
    doc = {"benchmark": "pipeline", "dataset": str(data_dir), "resolution": [ds.width, ds.height],
           "device": dev_name, "torch_threads": torch.get_num_threads(), "warp_cpu_threads": cpu_threads(),
           "phases": phases, "peak_rss_mb": round(peak_rss_mb(), 1)}
    print(json.dumps(doc, indent=None if args.json else 2))
    return 0
