"""Benchmark: holowarp's VBD solver against Newton SolverVBD at equal accuracy (issue 14).

``python -m holowarp.bench sim [--json] [--device cpu|cuda] [--sizes 5000,50000] [--bodies 2,8]
[--duration 0.5] [--reference 512x4] [--steps 5] [--substeps ...] [--iterations ...]
[--newton-settings SxI] [--no-newton]``

On a 2-core CPU the full search takes hours, mostly Newton's at 50k tets. The runs behind
issue 14's figures were ``--sizes 5000,50000 --bodies "" --newton-settings 128x1`` (35 min)
and ``--sizes "" --bodies 2`` (or 8) ``--reference 256x4 --substeps 32,64,128,256
--iterations 2,4,8 --newton-settings 256x2 --steps 3`` (4 and 8 min): 128x1 and 256x2 are
Newton's most accurate settings on those scenes, from full searches.

Scenes (0.2 m objects, E = 200 kPa, nu = 0.45, rho = 1000 kg/m^3, friction 0.5, dt = 1/60 s):

- ``drop-N``: the ``drop`` scene with a cube of about N tets (mirrored five-tet cells, which
  favour no diagonal), dropped 0.2 m;
- ``bodies-K``: K cubes of 0.1 m (about 600 tets each) in a 2 x K/2 ... grid: half resting on
  the ground, half dropped 0.1 m onto them (contact between bodies; Newton's particle
  self-contact does that for it).

For each scene:

1. a converged reference trajectory: holowarp at ``--reference`` substeps x iterations
   (512 x 4 by default: one sweep per substep is not enough for a reference, as candidates
   with one sweep share its sweep-order bias; the iterate is a displacement, so float32
   keeps its digits at any substep count). Its integrator is the solver's ``"auto"``: BDF2
   at such substeps, which is converged there (on ``drop-5000``, 256 x 4 is within 0.03 %
   of the fall height of 512 x 4, and 512 x 4 within 0.6 % of the Richardson extrapolation
   2 E(1024) - E(512) of implicit Euler, whose own 512-substep run is still 3 % off);
2. for each engine, the candidate settings ``SUBSTEPS x ITERATIONS`` (for holowarp, none as
   fine as the reference in both: that would be the reference itself) in order of cost
   (substeps x iterations, then fewer substeps), until one keeps the centre of mass within
   ``COM_TOLERANCE`` (1 %) of the fall height of the reference at every frame and ends
   with a surface within ``CHAMFER_TOLERANCE`` (0.005, Chamfer-L1 in the unit-cube
   frame of the rest scene, same barycentric samples on both) of the reference's. A
   candidate of a search stops at its first frame outside ``ABORT_BAND`` times the COM
   band (a single given setting, ``--newton-settings``, runs to the end); a substep count
   whose free fall already leaves the band is not tried with more iterations (iterations
   do not change free flight);
3. the cheapest passing setting of each engine is timed in a fresh process (one untimed
   warm-up step that compiles kernels, then ``--steps`` steps): steps per second, median
   step time, set-up time and the process's peak resident memory.

``speedup`` = holowarp's steps/s over Newton's, each at its own cheapest accurate setting.
When Newton reaches the tolerances at no setting (its velocities are float32 position
differences, which lose the digits of small substeps: its free fall drifts from about 100
substeps on), ``speedup_at_newton_best_accuracy`` compares with holowarp's cheapest setting
at least as accurate as Newton's best.
On a CUDA device the default sizes add 500k tets. The JSON also states the machine's load
average while it ran and, on the CPU, ``cpu_threads``: the threads holowarp's sweeps of a
contact-free mesh of at least 2,048 particles use (``$HOLOWARP_THREADS``, default the cores
available; :func:`holowarp.sim.solver.sweep_phases`). Newton's CPU launches run on one.
"""

from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import os
import statistics
import sys
import time
from dataclasses import dataclass

__all__ = ["main", "cube_cells_for", "scenario", "candidate_grid", "COM_TOLERANCE", "CHAMFER_TOLERANCE", "SUBSTEPS", "ITERATIONS"]

TARGET_SPEEDUP = 2.0
#: Largest centre-of-mass distance to the reference, as a fraction of the fall height.
COM_TOLERANCE = 0.01
#: Largest final-surface Chamfer-L1 to the reference (unit-cube frame of the rest scene).
CHAMFER_TOLERANCE = 0.005
#: Candidate substeps and iterations per substep. Implicit Euler converges in the step
#: length at first order (a 1 % match of the converged drop needs over a thousand
#: substeps); holowarp's BDF2 (the solver's "auto" once a substep resolves a wave crossing
#: one edge) at second order.
SUBSTEPS = (1, 4, 16, 32, 64, 128, 256, 384, 512)
ITERATIONS = (1, 2, 4, 8, 16)
#: A candidate run stops when its COM leaves this many times the tolerance band.
ABORT_BAND = 5.0
#: Tets per cell of the benchmark meshes (``box_tetmesh(split=5)``).
TETS_PER_CELL = 5
#: Surface samples per Chamfer.
CHAMFER_SAMPLES = 50_000


def cube_cells_for(num_tets: int) -> tuple[int, int, int]:
    """Cells (n, n, m) of a five-tets-per-cell cube mesh with about ``num_tets`` tets."""
    n = max(1, round((num_tets / TETS_PER_CELL) ** (1.0 / 3.0)))
    m = max(1, round(num_tets / (TETS_PER_CELL * n * n)))
    return (n, n, m)


@dataclass
class Scenario:
    """A benchmark scene: the scene, one mesh and placement per body, the fall height (m)."""

    name: str
    scene: object
    meshes: list
    transforms: list
    fall: float

    @property
    def tets(self) -> int:
        return sum(m.num_tets for m in self.meshes)

    @property
    def vertices(self) -> int:
        return sum(m.num_vertices for m in self.meshes)


def scenario(kind: str, n: int, duration: float) -> Scenario:
    """``kind`` ``"drop"`` (n tets) or ``"bodies"`` (n bodies)."""
    import dataclasses

    from holowarp.primitives import box_tetmesh
    from holowarp.sim import BodySpec, load_scene
    from holowarp.sim.scene import Placement, placement_transform

    sc = load_scene("drop")
    sc = dataclasses.replace(sc, sim=dataclasses.replace(sc.sim, substeps=1, iterations=1, duration=duration))
    if kind == "drop":
        mesh = box_tetmesh(cube_cells_for(n), (1.0, 1.0, 1.0), split=TETS_PER_CELL)
        return Scenario(f"drop-{mesh.num_tets}", sc, [mesh], [placement_transform(mesh.vertices, sc.placement)],
                        sc.placement.height)
    cube = box_tetmesh(cube_cells_for(600), (1.0, 1.0, 1.0), split=TETS_PER_CELL)
    bodies = []
    cols = max(1, n // 2)
    for k in range(n):
        col, layer = k % cols, k // cols
        pl = Placement(size=0.1, center_xy=(0.13 * (col - (cols - 1) / 2), 0.0), height=0.2 * layer,
                       rotation=(0.0, 0.0, 20.0 * layer))
        bodies.append(BodySpec(f"Cube{k}", None, pl, sc.material))
    sc = dataclasses.replace(sc, name=f"bodies-{n}", bodies=tuple(bodies))
    return Scenario(sc.name, sc, [cube] * n, [placement_transform(cube.vertices, b.placement) for b in bodies],
                    0.1 if n > 1 else 0.0)


# ---------------------------------------------------------------------------- running
def _run_holowarp(sc: Scenario, S: int, I: int, *, device: str, abort=None, steps=None):
    """Frames' centres of mass (F, 3) and the last frame (N, 3); stops when ``abort``."""
    import dataclasses

    import numpy as np

    from holowarp.sim.analysis import center_of_mass
    from holowarp.sim.scene import build_model, solver_options
    from holowarp.sim.solver import SolverVBDNeoHookean

    scene = dataclasses.replace(sc.scene, sim=dataclasses.replace(sc.scene.sim, substeps=S, iterations=I))
    model, _, _ = build_model(scene, sc.meshes, transform=sc.transforms, device=device)
    solver = SolverVBDNeoHookean(model, **solver_options(scene))
    s0, s1, c = model.state(), model.state(), model.control()
    dt = scene.sim.dt
    com = [center_of_mass(s0.positions(), model.masses)]
    x = s0.positions()
    for k in range(scene.num_steps if steps is None else steps):
        c.set_time(k * dt, (k + 1) * dt)
        solver.step(s0, s1, c, None, dt)
        s0, s1 = s1, s0
        x = s0.positions()
        com.append(center_of_mass(x, model.masses))
        if abort is not None and abort(len(com) - 1, x):
            break
    return np.stack(com), x, model, solver.plan(dt).integrator


def _run_newton(sc: Scenario, S: int, I: int, *, device: str, abort=None, steps=None):
    from holowarp.sim.newton_ref import simulate_newton_vbd
    from holowarp.sim.scene import build_model
    from holowarp.sim.solver import SolverVBDNeoHookean

    model, _, _ = build_model(sc.scene, sc.meshes, transform=sc.transforms, device="cpu")
    probe = SolverVBDNeoHookean(model)
    out = simulate_newton_vbd(sc.scene, sc.meshes, sc.transforms, substeps=S, iterations=I, device=device,
                              steps=steps, abort=abort, contact_radius=probe.contact_radius,
                              contact_margin=probe.contact_margin)
    return out["com"], out["frames"][-1].astype("float64"), None, "euler"  # SolverVBD: implicit Euler


_RUNNERS = {"holowarp": _run_holowarp, "newton": _run_newton}


class _Judge:
    """Accuracy of a run against the reference (see the module docstring)."""

    def __init__(self, sc: Scenario, ref_com, ref_final, rest):
        import numpy as np

        from holowarp.frame import unit_cube_transform
        from holowarp.tetmesh import TetMesh

        self.sc, self.ref_com, self.ref_final = sc, ref_com, ref_final
        V, T, off = [], [], 0
        for m in sc.meshes:
            V.append(m.vertices)
            T.append(m.tets + off)
            off += m.num_vertices
        self.faces = TetMesh(np.concatenate(V), np.concatenate(T), validate=False).boundary_faces()
        self.s, self.t = unit_cube_transform(rest)
        height = sc.fall if sc.fall > 0 else 0.1
        self.band = COM_TOLERANCE * height
        self.height = height
        z = ref_com[:, 2]
        self.free_frames = int(np.argmax(np.diff(z, 2) > 0)) + 1 if len(z) > 2 else 0  # until the first upturn

    def com_error(self, com) -> float:
        import numpy as np

        n = min(len(com), len(self.ref_com))
        return float(np.abs(com[:n] - self.ref_com[:n]).max() / self.height)

    def chamfer(self, final) -> float:
        import numpy as np

        from holowarp.metrics.surface import chamfer_metrics, sample_surface

        pa, na, _ = sample_surface(final * self.s + self.t, self.faces, CHAMFER_SAMPLES, rng=np.random.default_rng(0))
        pb, nb, _ = sample_surface(self.ref_final * self.s + self.t, self.faces, CHAMFER_SAMPLES,
                                   rng=np.random.default_rng(0))
        return float(chamfer_metrics(pa, na, pb, nb)["chamfer_l1"])


def _search(engine: str, sc: Scenario, judge: _Judge, device: str, grid) -> dict:
    """The cheapest of the candidate pairs ``grid`` [(S, I), ...] within the tolerances
    (module docstring), and every candidate
    tried with its errors (runs stop once their COM leaves ``ABORT_BAND`` times the band)."""
    tried, dead = [], set()
    # A single candidate (--newton-settings) runs to the end: there is nothing to prune, and
    # its full-run accuracy is what the other engine is compared at.
    prune = len(grid) > 1
    for S, I in sorted(grid, key=lambda p: (p[0] * p[1], p[0])):
        if S in dead:
            continue
        com, final, _, integrator = _RUNNERS[engine](sc, S, I, device=device,
                                                      abort=_make_abort(judge) if prune else None)
        err = judge.com_error(com)
        full = len(com) == len(judge.ref_com)
        rec = {"substeps": S, "iterations": I, "integrator": integrator, "com_error": err,
               "chamfer": judge.chamfer(final) if full else None, "frames_run": int(len(com) - 1)}
        tried.append(rec)
        if not full and len(com) - 1 <= judge.free_frames:
            dead.add(S)  # left the band in free flight: more iterations cannot help
        if _passes(rec, COM_TOLERANCE, CHAMFER_TOLERANCE):
            return {"reached": True, **rec, "tried": tried}
    full = [r for r in tried if r["chamfer"] is not None]
    best = min(full, key=lambda r: max(r["com_error"] / COM_TOLERANCE, r["chamfer"] / CHAMFER_TOLERANCE)) if full \
        else min(tried, key=lambda r: r["com_error"])
    return {"reached": False, "best": best, "tried": tried}


def candidate_grid(grid, reference=None):
    """The candidate pairs [(S, I), ...] of ``grid`` = (substeps, iterations). With a
    ``reference`` (S, I) (holowarp's own engine), without the settings at least as fine as
    the reference's in both: the reference's own setting reproduces it exactly and would
    pass at zero error."""
    pairs = [(S, I) for S in grid[0] for I in grid[1]]
    if reference is None:
        return pairs
    Sr, Ir = reference
    return [(S, I) for S, I in pairs if not (S >= Sr and I >= Ir)]


def _passes(rec: dict, com_tol: float, cd_tol: float) -> bool:
    return rec["chamfer"] is not None and rec["com_error"] <= com_tol and rec["chamfer"] <= cd_tol


def _cheapest_within(tried: list, com_tol: float, cd_tol: float):
    ok = [r for r in tried if _passes(r, com_tol, cd_tol)]
    return min(ok, key=lambda r: (r["substeps"] * r["iterations"], r["substeps"])) if ok else None


def _make_abort(judge: _Judge):
    """An ``abort(frame, positions)`` that stops a run whose centre of mass left
    ``ABORT_BAND`` times the tolerance band (it can no longer pass, nor be the best)."""
    import numpy as np

    state = {"com": [judge.ref_com[0]]}
    masses = {}

    def abort(frame, x):
        if "m" not in masses:
            masses["m"] = _masses_for(judge.sc, len(x))
        m = masses["m"]
        state["com"].append((x * m[:, None]).sum(0) / m.sum())
        return judge.com_error(np.asarray(state["com"])) > ABORT_BAND * COM_TOLERANCE

    return abort


def _masses_for(sc: Scenario, n: int):
    from holowarp.sim.scene import build_model

    model, _, _ = build_model(sc.scene, sc.meshes, transform=sc.transforms, device="cpu")
    assert model.particle_count == n
    return model.masses


# ---------------------------------------------------------------------------- timing
def _time_one(engine: str, kind: str, n: int, duration: float, S: int, I: int, steps: int, device: str) -> dict:
    """Steps per second of one engine at one setting, in this (fresh) process."""
    from holowarp.bench import peak_rss_mb
    from holowarp.device import init_warp

    wp = init_warp()
    sc = scenario(kind, n, duration)
    t0 = time.perf_counter()
    step, sync = _stepper(engine, sc, S, I, device)
    setup = time.perf_counter() - t0
    tw = time.perf_counter()
    step(0)
    sync()
    first = time.perf_counter() - tw
    times = []
    for k in range(1, steps + 1):
        ts = time.perf_counter()
        step(k)
        sync()
        times.append(time.perf_counter() - ts)
    del wp
    return {"steps_per_second": len(times) / sum(times), "median_step_ms": 1e3 * statistics.median(times),
            "setup_s": setup, "first_step_s": first, "timed_steps": len(times), "peak_rss_mb": peak_rss_mb()}


def _stepper(engine: str, sc: Scenario, S: int, I: int, device: str):
    """(step(k), synchronise) for one engine; step k advances one 1/60 s step."""
    import dataclasses

    import warp as wp

    from holowarp.sim.scene import build_model, solver_options
    from holowarp.sim.solver import SolverVBDNeoHookean

    scene = dataclasses.replace(sc.scene, sim=dataclasses.replace(sc.scene.sim, substeps=S, iterations=I))
    dt = scene.sim.dt
    if engine == "holowarp":
        model, _, _ = build_model(scene, sc.meshes, transform=sc.transforms, device=device)
        solver = SolverVBDNeoHookean(model, **solver_options(scene))
        st = [model.state(), model.state()]
        c = model.control()

        def step(k):
            c.set_time(k * dt, (k + 1) * dt)
            solver.step(st[0], st[1], c, None, dt)
            st.reverse()

        return step, lambda: wp.synchronize_device(model.device)
    from holowarp.sim.newton_ref import newton_vbd_model, newton_vbd_solver

    probe = SolverVBDNeoHookean(build_model(scene, sc.meshes, transform=sc.transforms, device="cpu")[0])
    newton, model = newton_vbd_model(scene, sc.meshes, sc.transforms, device=device)
    solver = newton_vbd_solver(newton, model, iterations=I, bodies=len(sc.meshes), contact_radius=probe.contact_radius,
                               contact_margin=probe.contact_margin)
    st = [model.state(), model.state()]
    ctrl = model.control()
    pipeline = newton.CollisionPipeline(model)
    contacts = pipeline.contacts()

    def step(k):
        for _ in range(S):
            st[0].clear_forces()
            pipeline.collide(st[0], contacts)
            solver.step(st[0], st[1], ctrl, contacts, dt / S)
            st.reverse()

    return step, lambda: wp.synchronize_device(model.device)


def _child(conn, fn, *args):
    try:
        conn.send(("ok", fn(*args)))
    except BaseException as e:  # report, don't hang the parent
        conn.send(("error", f"{type(e).__name__}: {e}"))
    finally:
        conn.close()


def _in_process(fn, *args):
    ctx = mp.get_context("spawn")
    a, b = ctx.Pipe(duplex=False)
    p = ctx.Process(target=_child, args=(b, fn, *args))
    p.start()
    b.close()
    status, payload = a.recv()
    p.join()
    if status != "ok":
        raise RuntimeError(payload)
    return payload


# ---------------------------------------------------------------------------- one scene
def _scene_result(kind: str, n: int, args, device: str, use_newton: bool) -> dict:
    """Reference, search and timing of one scene (in a fresh process per engine)."""
    grid = (tuple(args.substeps), tuple(args.iterations))
    newton_grid = grid if args.newton_settings is None else ((args.newton_settings[0],), (args.newton_settings[1],))
    return _in_process(_scene_child, kind, n, args.duration, args.reference, args.steps, device, use_newton,
                       (grid, newton_grid))


def _scene_child(kind: str, n: int, duration: float, reference: str, steps: int, device: str, use_newton: bool,
                 grids):
    from holowarp.device import init_warp

    init_warp()
    sc = scenario(kind, n, duration)
    Sr, Ir = (int(v) for v in reference.lower().split("x"))
    t0 = time.perf_counter()
    ref_com, ref_final, model, ref_integrator = _run_holowarp(sc, Sr, Ir, device=device)
    judge = _Judge(sc, ref_com, ref_final, model.rest_positions)
    row = {"scene": sc.name, "tets": sc.tets, "vertices": sc.vertices, "bodies": len(sc.meshes),
           "fall_height_m": judge.height, "reference": {"engine": "holowarp", "substeps": Sr, "iterations": Ir,
                                                         "integrator": ref_integrator,
                                                         "seconds": time.perf_counter() - t0}}
    for engine in ("holowarp",) + (("newton",) if use_newton else ()):
        grid = candidate_grid(grids[0], (Sr, Ir)) if engine == "holowarp" else candidate_grid(grids[1])
        found = _search(engine, sc, judge, device, grid)
        setting = found if found["reached"] else found["best"]
        timing = _in_process(_time_one, engine, kind, n, duration, setting["substeps"], setting["iterations"], steps,
                             device)
        row["holowarp" if engine == "holowarp" else "newton_vbd"] = {**found, **timing}
    row["speedup"] = None
    if use_newton:
        ours, theirs = row["holowarp"], row["newton_vbd"]
        if ours["reached"] and theirs["reached"]:
            row["speedup"] = ours["steps_per_second"] / theirs["steps_per_second"]
        elif not theirs["reached"] and theirs["best"]["chamfer"] is not None:
            # Newton cannot reach the tolerances: compare at the accuracy it does reach.
            b = theirs["best"]
            match = _cheapest_within(ours["tried"], b["com_error"], b["chamfer"])
            if match is not None:
                t = _in_process(_time_one, "holowarp", kind, n, duration, match["substeps"], match["iterations"],
                                steps, device)
                row["holowarp_at_newton_best_accuracy"] = {**match, **t}
                row["speedup_at_newton_best_accuracy"] = t["steps_per_second"] / theirs["steps_per_second"]
    return row


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m holowarp.bench sim", description=__doc__.splitlines()[0])
    ap.add_argument("--json", action="store_true", help="print only the JSON result")
    ap.add_argument("--device", default="cpu", help="cpu, cuda or cuda:N")
    ap.add_argument("--sizes", default=None, help="drop scenes, comma-separated tet counts (default 5000,50000; "
                                                  "+500000 on CUDA); empty for none")
    ap.add_argument("--bodies", default="2,8", help="contact scenes, comma-separated body counts (default 2,8)")
    ap.add_argument("--duration", type=float, default=0.5, help="simulated seconds per run (default 0.5)")
    ap.add_argument("--reference", default="512x4", help="reference SUBSTEPSxITERATIONS (default 512x4)")
    ap.add_argument("--steps", type=int, default=5, help="timed steps per setting (default 5)")
    ap.add_argument("--substeps", default=",".join(map(str, SUBSTEPS)), help="candidate substeps (comma-separated)")
    ap.add_argument("--iterations", default=",".join(map(str, ITERATIONS)), help="candidate iterations")
    ap.add_argument("--newton-settings", default=None, metavar="SxI",
                    help="run Newton only at this setting instead of searching (large meshes, where its search "
                         "takes hours on a CPU: at 50k tets none of its settings leaves the abort band, so it walks "
                         "the whole grid). Its most accurate settings, from full searches on this bench's scenes: "
                         "128x1 for the drops, 256x2 for the contact scenes")
    ap.add_argument("--no-newton", action="store_true", help="skip the Newton SolverVBD reference")
    args = ap.parse_args(argv)

    from holowarp.device import DeviceError, cpu_threads, resolve_device

    try:
        device = resolve_device(args.device)
        sizes = _ints(args.sizes, [5000, 50000] + ([500000] if device.startswith("cuda") else []), "--sizes")
        bodies = _ints(args.bodies, [], "--bodies")
        args.substeps = _ints(args.substeps, list(SUBSTEPS), "--substeps")
        args.iterations = _ints(args.iterations, list(ITERATIONS), "--iterations")
        if args.newton_settings is not None:
            args.newton_settings = tuple(_ints(args.newton_settings.lower().replace("x", ","), [], "--newton-settings"))
            if len(args.newton_settings) != 2:
                raise ValueError("--newton-settings must be SUBSTEPSxITERATIONS")
        if args.steps < 1 or not args.duration > 0 or "x" not in args.reference.lower():
            raise ValueError("--steps must be >= 1, --duration > 0 and --reference SUBSTEPSxITERATIONS")
    except (DeviceError, ValueError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    from holowarp.sim.newton_ref import newton_available

    use_newton = not args.no_newton and newton_available()
    load = [os.getloadavg()]
    results = []
    for kind, n in [("drop", s) for s in sizes] + [("bodies", b) for b in bodies]:
        row = _scene_result(kind, n, args, device, use_newton)
        results.append(row)
        if not args.json:
            print(json.dumps(row), file=sys.stderr)
        load.append(os.getloadavg())
    out = {"benchmark": "sim", "device": device, "dt": 1.0 / 60.0, "duration": args.duration,
           "criteria": {"com_tolerance_of_fall_height": COM_TOLERANCE, "chamfer_tolerance": CHAMFER_TOLERANCE,
                        "substeps": args.substeps, "iterations": args.iterations, "abort_band": ABORT_BAND,
                        "newton_settings": args.newton_settings},
           "target_speedup": TARGET_SPEEDUP,
           "newton": "SolverVBD (add_soft_mesh), each engine at its own cheapest accurate setting" if use_newton
           else "not run (newton not installed or --no-newton)",
           "load_average": {"start": load[0], "end": load[-1]},
           "cpu_threads": cpu_threads() if not device.startswith("cuda") else None, "results": results}
    if not device.startswith("cuda"):
        out["cuda_500k"] = "not measured: run with --device cuda on a machine with a GPU"
    print(json.dumps(out, indent=None if args.json else 2))
    return 0


def _ints(text, default, what):
    if text is None:
        return default
    try:
        return [int(s) for s in text.split(",") if s.strip()]
    except ValueError:
        raise ValueError(f"{what} must be comma-separated integers, got {text!r}") from None


if __name__ == "__main__":
    sys.exit(main())
