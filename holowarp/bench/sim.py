"""Benchmark: holowarp's XPBD solver against Newton ``SolverVBD`` (issue 7, item 6).

``python -m holowarp.bench sim [--json] [--device cpu|cuda] [--sizes 5000,50000] [--steps 24]``

For each size, a cube tet mesh of about that many tets (mirrored five-tet cells, which
favour no diagonal; 0.2 m, the ``drop`` scene: E = 200 kPa, nu = 0.45, dt = 1/60 s) is dropped for ``--steps`` steps by both
engines with the SAME dt, substeps and iterations: the substeps of holowarp's step plan
for that mesh (the scene's substeps raised to the stability limit) and ``--iterations``
per substep (default 3: at 1 iteration per substep the engines disagree by up to 8 % of the
drop height at the impact, Newton's contact penetrating and holowarp's rebound too high;
from 3 on they agree to about 1.5 %). Reported per engine: steps per second
over the timed loop (the first step, which compiles and warms up, is excluded), the median
step time, set-up time and the peak resident memory of a fresh process that ran only that
engine at that size. ``speedup`` = holowarp steps/s over Newton's. ``com_difference`` is the
largest centre-of-mass difference between the engines over the run, as a fraction of the
drop height (``com_z_difference``: vertical only): both ran the same physics to that
accuracy (the impact happens at step 12, the rebound peaks near step 20).

On CUDA the default sizes add 500k tets. Each measurement runs in its own process so that
peak memory is per engine and size.
"""

from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import statistics
import sys
import time

__all__ = ["main", "cube_cells_for", "run_one"]

TARGET_SPEEDUP = 2.0


#: Tets per cell of the benchmark meshes (``box_tetmesh(split=5)``).
TETS_PER_CELL = 5


def cube_cells_for(num_tets: int) -> tuple[int, int, int]:
    """Cells (n, n, m) of a five-tets-per-cell cube mesh with about ``num_tets`` tets."""
    n = max(1, round((num_tets / TETS_PER_CELL) ** (1.0 / 3.0)))
    m = max(1, round(num_tets / (TETS_PER_CELL * n * n)))
    return (n, n, m)


def run_one(engine: str, num_tets: int, steps: int, device: str, plan: dict | None = None,
            iterations: int = 3) -> dict:
    """Time one engine at one size in this process; returns timings, plan and COM track.

    ``plan`` (substeps, iterations) is required for Newton; holowarp makes its own from its
    stability plan's substeps and ``iterations``."""
    import numpy as np

    from holowarp.bench import peak_rss_mb
    from holowarp.device import init_warp
    from holowarp.primitives import box_tetmesh
    from holowarp.sim import SolverXPBDNeoHookean, load_scene
    from holowarp.sim.analysis import center_of_mass
    from holowarp.sim.scene import build_model, placement_transform

    wp = init_warp()
    sc = load_scene("drop")
    mesh = box_tetmesh(cube_cells_for(num_tets), (1.0, 1.0, 1.0), split=TETS_PER_CELL)
    tr = placement_transform(mesh.vertices, sc.placement)
    dt = sc.sim.dt
    t0 = time.perf_counter()
    com, step_s = [], []
    if engine == "holowarp":
        model, _, _ = build_model(sc, mesh, transform=tr, device=device)
        stable = SolverXPBDNeoHookean(model, iterations=sc.sim.iterations, substeps=sc.sim.substeps).plan(dt)
        solver = SolverXPBDNeoHookean(model, iterations=iterations, substeps=stable.substeps, damping=sc.sim.damping)
        p = solver.plan(dt)
        plan = {"substeps": p.substeps, "iterations": p.iterations, "softened_tets": p.softened_tets}
        s0, s1, c = model.state(), model.state(), model.control()
        masses = model.masses
        setup = time.perf_counter() - t0

        def step(k):
            nonlocal s0, s1
            c.set_time(k * dt, (k + 1) * dt)
            solver.step(s0, s1, c, None, dt)
            s0, s1 = s1, s0
            wp.synchronize_device(model.device)

        def positions():
            return s0.positions()
    else:
        from holowarp.sim.newton_ref import newton_vbd_model

        newton, model = newton_vbd_model(sc, mesh, tr, device=device)
        solver = newton.solvers.SolverVBD(model, iterations=plan["iterations"], particle_enable_self_contact=False,
                                          particle_enable_tile_solve=False)
        n0, n1, ctrl = model.state(), model.state(), model.control()
        pipeline = newton.CollisionPipeline(model)
        contacts = pipeline.contacts()
        masses = model.particle_mass.numpy().astype(np.float64)
        h = dt / plan["substeps"]
        setup = time.perf_counter() - t0

        def step(k):
            nonlocal n0, n1
            for _ in range(plan["substeps"]):
                n0.clear_forces()
                pipeline.collide(n0, contacts)
                solver.step(n0, n1, ctrl, contacts, h)
                n0, n1 = n1, n0
            wp.synchronize_device(model.device)

        def positions():
            return n0.particle_q.numpy().astype(np.float64)

    com.append(center_of_mass(positions(), masses).tolist())
    tw = time.perf_counter()
    step(0)  # compiles kernels on first use; not timed
    warmup = time.perf_counter() - tw
    com.append(center_of_mass(positions(), masses).tolist())
    loop = 0.0
    for k in range(1, steps):
        ts = time.perf_counter()
        step(k)
        d = time.perf_counter() - ts
        loop += d
        step_s.append(d)
        com.append(center_of_mass(positions(), masses).tolist())  # outside the timing
    return {
        "engine": engine,
        "tets": mesh.num_tets,
        "vertices": mesh.num_vertices,
        "plan": plan,
        "timed_steps": steps - 1,
        "steps_per_second": (steps - 1) / loop if loop > 0 else None,
        "median_step_ms": 1e3 * statistics.median(step_s) if step_s else None,
        "setup_s": setup,
        "first_step_s": warmup,
        "peak_rss_mb": peak_rss_mb(),
        "com": com,
        "drop_height": sc.placement.height,
    }


def _child(conn, *args):
    try:
        conn.send(("ok", run_one(*args)))
    except BaseException as e:  # report, don't hang the parent
        conn.send(("error", f"{type(e).__name__}: {e}"))
    finally:
        conn.close()


def _in_process(*args) -> dict:
    ctx = mp.get_context("spawn")
    a, b = ctx.Pipe(duplex=False)
    p = ctx.Process(target=_child, args=(b, *args))
    p.start()
    b.close()
    status, payload = a.recv()
    p.join()
    if status != "ok":
        raise RuntimeError(payload)
    return payload


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m holowarp.bench sim", description=__doc__.splitlines()[0])
    ap.add_argument("--json", action="store_true", help="print only the JSON result")
    ap.add_argument("--device", default="cpu", help="cpu, cuda or cuda:N")
    ap.add_argument("--sizes", default=None, help="comma-separated tet counts (default 5000,50000; +500000 on CUDA)")
    ap.add_argument("--steps", type=int, default=24, help="steps per run, the first untimed (default 24 = 0.4 s)")
    ap.add_argument("--iterations", type=int, default=3, help="iterations per substep for both engines (default 3)")
    ap.add_argument("--no-newton", action="store_true", help="skip the Newton SolverVBD reference")
    args = ap.parse_args(argv)

    from holowarp.device import DeviceError, resolve_device

    try:
        device = resolve_device(args.device)
    except DeviceError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    if args.iterations < 1:
        print("error: --iterations must be >= 1", file=sys.stderr)
        return 2
    if args.steps < 2:
        print("error: --steps must be >= 2", file=sys.stderr)
        return 2
    if args.sizes:
        try:
            sizes = [int(s) for s in args.sizes.split(",") if s.strip()]
        except ValueError:
            print(f"error: --sizes must be comma-separated integers, got {args.sizes!r}", file=sys.stderr)
            return 2
    else:
        sizes = [5000, 50000] + ([500000] if device.startswith("cuda") else [])

    from holowarp.sim.newton_ref import newton_available

    use_newton = not args.no_newton and newton_available()
    results = []
    for n in sizes:
        ours = _in_process("holowarp", n, args.steps, device, None, args.iterations)
        row = {"tets": ours["tets"], "vertices": ours["vertices"], "substeps": ours["plan"]["substeps"],
               "iterations": ours["plan"]["iterations"], "softened_tets": ours["plan"]["softened_tets"],
               "holowarp": {k: ours[k] for k in ("steps_per_second", "median_step_ms", "setup_s", "first_step_s",
                                                 "peak_rss_mb")}}
        if use_newton:
            ref = _in_process("newton", n, args.steps, device, ours["plan"], args.iterations)
            row["newton_vbd"] = {k: ref[k] for k in ("steps_per_second", "median_step_ms", "setup_s",
                                                     "first_step_s", "peak_rss_mb")}
            row["speedup"] = ours["steps_per_second"] / ref["steps_per_second"]
            import numpy as np

            diff = np.abs(np.asarray(ours["com"]) - np.asarray(ref["com"]))
            row["com_difference"] = float(diff.max() / ours["drop_height"])
            row["com_z_difference"] = float(diff[:, 2].max() / ours["drop_height"])
        results.append(row)
        if not args.json:
            print(json.dumps(row), file=sys.stderr)

    out = {
        "benchmark": "sim",
        "device": device,
        "scene": "drop",
        "dt": 1.0 / 60.0,
        "steps": args.steps,
        "target_speedup": TARGET_SPEEDUP,
        "newton": "SolverVBD, same dt, substeps and iterations" if use_newton else "not run (newton not installed or --no-newton)",
        "results": results,
    }
    if not device.startswith("cuda"):
        out["cuda_500k"] = "not measured: run with --device cuda on a machine with a GPU"
    print(json.dumps(out, indent=None if args.json else 2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
