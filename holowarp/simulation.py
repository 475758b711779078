"""The ``simulate`` application: load a mesh, run a scene, measure, write USD, report, render.

:func:`simulate` is what ``python -m holowarp.simulate`` calls; a Python user gets the same
result with one call::

    from holowarp.simulation import simulate
    report = simulate("bob.vtu", "drop", out_dir="out/bob_drop")

Frames are written at 60 per second (USD time code k = frame k = time k/60 s); the step
``dt`` of the scene must divide 1/60 s. The stepping itself is :func:`holowarp.sim.run_scene`.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

import numpy as np

from holowarp.errors import InputError
from holowarp.sim.analysis import center_of_mass, pieces_apart
from holowarp.sim.run import FPS, NonFiniteStateError, run_scene
from holowarp.sim.scene import load_scene, placement_transform
from holowarp.tetmesh import TetMesh

__all__ = ["SimulationError", "NonFiniteStateError", "FPS", "CHAMFER_TIMES", "MESH_FORMATS_HELP", "simulate",
           "load_sim_mesh", "render_frames"]


def _formats_help() -> str:
    from holowarp.mesh_io import TET_FORMATS
    from holowarp.surface_io import SURFACE_READ_FORMATS

    return (f"a tet mesh ({', '.join(TET_FORMATS)}) or a closed surface ({', '.join(SURFACE_READ_FORMATS)}; "
            "welded and tetrahedralised with fTetWild)")


#: The mesh files the application reads (for help texts).
MESH_FORMATS_HELP = _formats_help()

#: Times (s) at which ``sim_chamfer`` is measured (method.md §10).
CHAMFER_TIMES = (0.0, 0.25, 0.5, 0.75, 1.0)


class SimulationError(InputError):
    """The inputs of a simulation cannot be used; the message names the file or argument."""


#: Largest estimated work (steps x substeps x iterations x tets, summed over bodies) a
#: simulation starts without ``allow_long``: about ten minutes simulated at 60 steps per
#: second for a 5k-tet body at 16 iterations, hours of CPU time. A duration typed one unit
#: off (1e9 s) would otherwise run until killed.
MAX_WORK = 6.0e10


def check_work(scene, meshes, *, allow_long: bool = False) -> float:
    """The estimated work of simulating ``meshes`` in ``scene``; raises
    :class:`SimulationError` above :data:`MAX_WORK` unless ``allow_long``."""
    sim = scene.sim
    tets = sum(int(m.num_tets) for m in meshes)
    work = float(scene.num_steps) * sim.substeps * sim.iterations * tets
    if work > MAX_WORK and not allow_long:
        raise SimulationError(
            f"scene {scene.name!r}: duration {sim.duration:g} s is {scene.num_steps:.3g} steps x {sim.substeps} substeps "
            f"x {sim.iterations} iterations x {tets} tets = {work:.2g} tet-iterations, above the cap of {MAX_WORK:.2g} "
            "(hours of compute); shorten [sim] duration or pass --allow-long")
    return work


#: A surface given as a simulation mesh (a ground-truth reference) is decimated to this many
#: triangles before fTetWild when it has more. Its tets come out at fTetWild's default edge
#: length (5% of the diagonal), about the reconstructions' resolution; finer input triangles
#: only cost time (:func:`holowarp.tetmesh.tetrahedralize_surface`).
SURFACE_MAX_FACES = 10_000


def load_sim_mesh(src, *, what: str = "mesh") -> TetMesh:
    """A positively oriented tet mesh without unused vertices from ``src``.

    Args:
        src: a :class:`TetMesh`, a tet-mesh file (``.vtu``, ``.msh``, ``.npz``, ``.usd*``), or
            a closed surface (``.obj``, ``.ply``, ...), which is tetrahedralised with fTetWild
            (decimated first to ``SURFACE_MAX_FACES`` triangles when it has more).
        what: name used in error messages.
    """
    from holowarp.mesh_io import TET_FORMATS, MeshIOError, read_tetmesh

    if isinstance(src, TetMesh):
        mesh = src
    elif isinstance(src, (str, os.PathLike)):
        path = Path(src)
        if not path.is_file():
            raise SimulationError(f"{what} {path}: no such file")
        try:
            if path.suffix.lower() in TET_FORMATS:
                mesh = read_tetmesh(path)
            else:
                from holowarp.metrics import EvaluationError, load_surface
                from holowarp.tetmesh import tetrahedralize_surface

                try:
                    V, F, _ = load_surface(path)
                except EvaluationError as e:
                    raise SimulationError(f"{what} {e}") from None
                mesh = tetrahedralize_surface(V, F, max_faces=SURFACE_MAX_FACES)
        except MeshIOError as e:
            raise SimulationError(f"{what} {e}") from None
    else:
        raise SimulationError(f"{what}: expected a TetMesh or a file path, got {type(src).__name__}")
    if mesh.num_tets == 0:
        raise SimulationError(f"{what}: the mesh has no tetrahedra")
    mesh, _ = mesh.oriented()
    mesh, _ = mesh.remove_unused_vertices()
    return mesh


def _chamfer(mesh_a: TetMesh, xa, mesh_b: TetMesh, xb, to_eval, num_samples: int, seed: int) -> float:
    from holowarp.metrics.surface import chamfer_metrics, sample_surface

    rng = np.random.default_rng(seed)
    fa, fb = mesh_a.boundary_faces(), mesh_b.boundary_faces()
    pa, na, _ = sample_surface(to_eval(xa), fa, num_samples, rng=rng)
    pb, nb, _ = sample_surface(to_eval(xb), fb, num_samples, rng=rng)
    return chamfer_metrics(pa, na, pb, nb)["chamfer_l1"]


def _mesh_of_bodies(meshes, bodies) -> TetMesh:
    """One TetMesh holding the listed bodies' meshes (particle order of the model)."""
    V, T, off = [], [], 0
    for k in bodies:
        V.append(meshes[k].vertices)
        T.append(meshes[k].tets + off)
        off += meshes[k].num_vertices
    return TetMesh(np.concatenate(V), np.concatenate(T), validate=False)


def _particles_of(model, bodies) -> np.ndarray:
    return np.concatenate([np.arange(model.bodies[k].particle_start, model.bodies[k].particle_end) for k in bodies])


def _warn_inverted(inverted, what: str) -> list[int]:
    """Frames with inverted tets; says so on stderr (the report lists them too)."""
    frames = [int(k) for k in np.flatnonzero(np.asarray(inverted) > 0)]
    if frames:
        worst = int(np.argmax(inverted))
        print(f"warning: {what}: inverted tets in {len(frames)} of {len(inverted)} frames (frames "
              f"{frames[0]}-{frames[-1]}; at most {int(inverted[worst])} at t = {worst / FPS:.3f} s; "
              f"{int(inverted[-1])} at the end)", file=sys.stderr)
    return frames


def simulate(mesh, scene, *, device: str = "cpu", reference=None, out_dir=None, render_dir=None,
             progress: bool = True, chamfer_samples: int | None = None, name: str = "Object",
             allow_long: bool = False) -> dict:
    """Simulate a tet mesh in a scene and report (method.md §10).

    Args:
        mesh: a :class:`TetMesh` or a mesh file (any tet format; a surface is tetrahedralised):
            the scene's body, or every ``[[bodies]]`` entry without a ``mesh`` of its own.
        scene: ``"drop"``, ``"compress"``, a ``.toml`` path, or a :class:`Scene`.
        device: ``"cpu"`` or ``"cuda[:N]"``.
        reference: optional ground-truth mesh (tet file, or a closed surface that is
            tetrahedralised with fTetWild) simulated in the same scene in place of ``mesh``,
            with the same placement; adds ``sim_chamfer``. The placement (and the
            evaluation frame) then come from the reference's rest bounding box.
        out_dir: if given, writes ``sim.usda`` and ``report.json`` there (atomically; a run
            that fails writes nothing, so earlier results stay).
        render_dir: if given, writes one PNG per frame there (pyvista, off screen).
        progress: show a progress bar (on stderr, and only when it is a terminal).
        chamfer_samples: surface samples per mesh for ``sim_chamfer`` (method.md §9: 100,000).
        name: prim name of the body in USD for a scene without ``[[bodies]]``.
        allow_long: run even when the estimated work exceeds :data:`MAX_WORK`.

    Returns:
        The report dict: ``frames``, ``steps``, ``seconds``, ``steps_per_second`` (of the
        stepping loop), ``max_inverted``, ``min_volume_ratio``, ``max_volume_ratio``, ``com``
        (per frame, m), ``nan`` (False: non-finite states raise), ``components_end`` (see
        :func:`holowarp.sim.analysis.pieces_apart`), ``max_penetration`` (m, deepest contact
        violation over all frames, see :meth:`SolverVBDNeoHookean.penetration`), and, with a
        reference, ``sim_chamfer`` ({time s: Chamfer-L1 in the evaluation frame}), plus
        context (scene, device, mesh size, bodies, the solver's step plan, per-frame volume
        ratio, inverted counts, penetration and contact forces, ``inverted_frames``).

    Raises:
        SimulationError: a mesh cannot be used. SceneError, ModelError: bad scene or model.
        NonFiniteStateError: the simulation produced non-finite positions (nothing written).
    """
    from holowarp.device import resolve_device
    from holowarp.progress import bar, bars_enabled

    device = resolve_device(device)
    if chamfer_samples is not None and int(chamfer_samples) < 100:
        raise SimulationError(f"chamfer_samples must be >= 100, got {chamfer_samples}")
    if out_dir is not None:
        from holowarp.fileio import check_output_dir

        out_dir = check_output_dir(out_dir, what="--out")  # before any work, not after it
    if render_dir is not None:
        from holowarp.fileio import check_output_dir

        render_dir = check_output_dir(render_dir, what="--render folder")
    scene = load_scene(scene)
    specs, meshes, ref, default, transforms = _load_bodies(mesh, scene, reference)
    check_work(scene, meshes, allow_long=allow_long)
    ref_meshes = [ref if sp.mesh is None else meshes[k] for k, sp in enumerate(specs)] if ref is not None else None
    pbar = bar(scene.num_steps * (2 if ref is not None else 1), desc=scene.name, unit="step", progress=progress)
    try:
        run = run_scene(scene, meshes, transform=transforms, device=device, progress=pbar)
        ref_run = None
        if ref is not None:
            ref_run = run_scene(scene, ref_meshes, transform=transforms, device=device, progress=pbar)
    finally:
        pbar.close()

    report, placed_mesh = _report(scene, device, specs, meshes, run)
    if ref_run is not None:
        _reference_report(report, run, ref_run, meshes, ref_meshes, default, chamfer_samples)
    if out_dir is not None:
        from holowarp.fileio import atomic_write_json

        out_dir = Path(out_dir)
        out_dir.mkdir(parents=True, exist_ok=True)
        names = [name] if not scene.bodies else [sp.name for sp in specs]
        _write_usd(out_dir / "sim.usda", scene, run, meshes, names, ref_run=ref_run, ref_meshes=ref_meshes)
        atomic_write_json(out_dir / "report.json", report)
    if render_dir is not None:
        render_frames(render_dir, placed_mesh, run["frames"], run["model"], run["surface_points"],
                      progress=bars_enabled(progress))
    return report


def _load_bodies(mesh, scene, reference):
    """(body specs, one mesh per body, reference mesh or None, indices of the bodies that
    use ``mesh``, placement transforms shared by both runs)."""
    specs = scene.body_specs()
    default = [k for k, sp in enumerate(specs) if sp.mesh is None]
    main_mesh = load_sim_mesh(mesh, what="mesh") if default else None
    meshes = [main_mesh if sp.mesh is None else load_sim_mesh(sp.mesh, what=f"{scene.source}: body {sp.name!r} mesh")
              for sp in specs]
    ref = load_sim_mesh(reference, what="reference") if reference is not None else None
    if ref is not None and not default:
        raise SimulationError(f"reference: every body of {scene.source} has its own mesh; the reference replaces "
                              "the bodies without one, and there are none")
    frame_mesh = ref if ref is not None else main_mesh
    transforms = [placement_transform((frame_mesh if sp.mesh is None else meshes[k]).vertices, sp.placement)
                  for k, sp in enumerate(specs)]
    return specs, meshes, ref, default, transforms


def _report(scene, device, specs, meshes, run) -> tuple[dict, TetMesh]:
    """The report of one run (see :func:`simulate`) and the placed mesh of all bodies."""
    model = run["model"]
    whole = _mesh_of_bodies(meshes, range(len(specs)))
    placed_mesh = whole.with_vertices(model.rest_positions)
    frames = run["frames"]
    vol_ratio = run["volume"] / model.rest_volume()
    comps, comp_info = pieces_apart(placed_mesh, frames[-1])
    bodies = []
    for k, (sp, b) in enumerate(zip(specs, model.bodies)):
        bm = placed_mesh.submesh(np.arange(b.tet_start, b.tet_end))
        xb = frames[-1][b.particle_start:b.particle_end]
        bodies.append({
            "name": b.name, "mesh": sp.mesh, "vertices": meshes[k].num_vertices, "tets": meshes[k].num_tets,
            "components_start": int(meshes[k].components()[1]), "components_end": pieces_apart(bm, xb)[0],
            "com_end": center_of_mass(xb, model.masses[b.particle_start:b.particle_end]).tolist(),
        })
    report = {
        "frames": int(len(frames)), "steps": int(run["steps"]), "seconds": float(run["seconds"]),
        "steps_per_second": float(run["steps"] / run["seconds"]) if run["seconds"] > 0 else None,
        "max_inverted": int(run["inverted"].max()),
        "min_volume_ratio": float(np.nanmin(vol_ratio)), "max_volume_ratio": float(np.nanmax(vol_ratio)),
        "com": run["com"].tolist(), "nan": bool(run["nan"]), "components_end": comps,
        "max_penetration": float(run["penetration"].max()),
        "scene": scene.name, "scene_file": scene.source, "device": device,
        "vertices": int(whole.num_vertices), "tets": int(whole.num_tets),
        "components_start": int(whole.components()[1]), "components_info": comp_info, "bodies": bodies,
        "dt": scene.sim.dt, "plan": run["plan"].as_dict(),
        "inverted_end": int(run["inverted"][-1]),
        "inverted_frames": _warn_inverted(run["inverted"], f"scene {scene.name!r}"),
        "inverted": run["inverted"].tolist(), "volume_ratio": vol_ratio.tolist(),
        "penetration": run["penetration"].tolist(),
        "contact_force": {sname: run["surface_force"][:, k].tolist() for k, sname in enumerate(model.surface_names)},
    }
    return report, placed_mesh


def _reference_report(report, run, ref_run, meshes, ref_meshes, default, chamfer_samples) -> None:
    """Add ``sim_chamfer`` (between the bodies that use the simulated mesh and the same bodies
    made of the reference, in the reference's evaluation frame) and ``reference``."""
    from holowarp.frame import unit_cube_transform
    from holowarp.metrics.surface import SurfaceMetricSettings

    n = SurfaceMetricSettings().num_samples if chamfer_samples is None else int(chamfer_samples)
    model, rmodel = run["model"], ref_run["model"]
    ours_d, ref_d = _mesh_of_bodies(meshes, default), _mesh_of_bodies(ref_meshes, default)
    pa_idx, pb_idx = _particles_of(model, default), _particles_of(rmodel, default)
    s, t = unit_cube_transform(rmodel.rest_positions[pb_idx])
    to_eval = lambda x: np.asarray(x, np.float64) * s + t  # noqa: E731
    frames, rframes = run["frames"], ref_run["frames"]
    sc = {}
    for tc in CHAMFER_TIMES:
        k = int(round(tc * FPS))
        if k < len(frames) and k < len(rframes):
            sc[f"{tc:g}"] = _chamfer(ours_d, frames[k][pa_idx], ref_d, rframes[k][pb_idx], to_eval, n, seed=k)
    report["sim_chamfer"] = sc
    ref = ref_meshes[default[0]]
    report["reference"] = {"vertices": ref.num_vertices, "tets": ref.num_tets, "nan": bool(ref_run["nan"]),
                           "max_inverted": int(ref_run["inverted"].max()),
                           "inverted_frames": _warn_inverted(ref_run["inverted"], "reference"),
                           "max_penetration": float(ref_run["penetration"].max())}


def _write_usd(path, scene, run, meshes, names, *, ref_run=None, ref_meshes=None):
    from holowarp.usd import PhysicsMaterial, UsdSceneWriter

    model = run["model"]
    w = UsdSceneWriter(path, fps=FPS)
    specs = scene.body_specs()

    def add_bodies(run_, meshes_, names_, **kw):
        m_ = run_["model"]
        for sp, b, mesh_, nm in zip(specs, m_.bodies, meshes_, names_):
            mat = sp.material
            pm = PhysicsMaterial(mat.youngs_modulus, mat.poissons_ratio, mat.density, mat.friction, mat.friction)
            w.add_tetmesh(nm, mesh_.with_vertices(m_.rest_positions[b.particle_start:b.particle_end]), material=pm,
                          **kw)
            for f, x in enumerate(run_["frames"]):
                xb = x[b.particle_start:b.particle_end]
                if np.all(np.isfinite(xb)):
                    w.set_points(nm, xb, f)

    add_bodies(run, meshes, names)
    if ref_run is not None:
        ref_names = ["Reference"] if len(names) == 1 else [f"Reference{n}" for n in names]
        add_bodies(ref_run, ref_meshes, ref_names, color=(0.35, 0.55, 0.8))
    if model.ground is not None:
        w.add_ground()
    for p in model.plates:
        w.add_box(p.name, p.size, p.box_center(0.0))
        for k in range(len(run["frames"])):
            w.set_translation(p.name, p.box_center(k / FPS), k)
    w.save()


def render_frames(render_dir, placed_mesh: TetMesh, frames, model, surface_points=None, *,
                  window_size=(640, 480), progress: bool = True) -> list[Path]:
    """Render every frame off screen with pyvista to ``render_dir/frame_0000.png`` ...

    Args:
        render_dir: output folder.
        placed_mesh: the simulated mesh at rest (connectivity).
        frames: (F, N, 3) positions.
        model: the model (ground and plates).
        surface_points: (F, S, 3) contact-surface points per frame (plates follow them).

    Returns:
        The written paths.
    """
    import pyvista as pv
    from tqdm.auto import tqdm

    from holowarp.fileio import atomic_path
    from holowarp.viz import offscreen_plotter

    render_dir = Path(render_dir)
    render_dir.mkdir(parents=True, exist_ok=True)
    bf = placed_mesh.boundary_faces().astype(np.int64)
    faces = np.concatenate([np.full((len(bf), 1), 3, np.int64), bf], axis=1).reshape(-1)
    surf = pv.PolyData(np.asarray(frames[0], np.float64), faces)
    pl = offscreen_plotter(window_size)
    pl.set_background("white")
    body = pl.add_mesh(surf, color=(0.85, 0.55, 0.35), smooth_shading=False, show_edges=False)
    surf = body.mapper.dataset  # add_mesh may copy the mesh: update the one drawn
    allx = np.asarray(frames, np.float64).reshape(-1, 3)
    finite = allx[np.all(np.isfinite(allx), axis=1)]
    lo, hi = finite.min(0), finite.max(0)
    ext = float(np.max(hi - lo))
    if model.ground is not None:
        c = 0.5 * (lo + hi)
        ground = pv.Plane(center=(c[0], c[1], 0.0), direction=(0, 0, 1), i_size=3 * ext, j_size=3 * ext)
        pl.add_mesh(ground, color=(0.7, 0.7, 0.7))
    plate_actors = []
    for p in model.plates:
        ctr = p.box_center(0.0)
        box = pv.Box(bounds=(ctr[0] - p.size[0] / 2, ctr[0] + p.size[0] / 2, ctr[1] - p.size[1] / 2,
                             ctr[1] + p.size[1] / 2, ctr[2] - p.size[2] / 2, ctr[2] + p.size[2] / 2))
        plate_actors.append((p, pl.add_mesh(box, color=(0.5, 0.55, 0.65), opacity=0.6), ctr))
    centre = 0.5 * (lo + hi)
    pl.camera.focal_point = tuple(centre)
    pl.camera.position = tuple(centre + np.array([1.8, -2.6, 0.7]) * max(ext, 1e-3))
    pl.camera.up = (0.0, 0.0, 1.0)
    paths = []
    for k in tqdm(range(len(frames)), desc="render", unit="frame", disable=not progress):
        x = np.asarray(frames[k], np.float64)
        if not np.all(np.isfinite(x)):
            break
        surf.points = x
        surf.Modified()
        for p, actor, c0 in plate_actors:
            actor.position = tuple(p.box_center(k / FPS) - c0)
        pl.render()
        out = render_dir / f"frame_{k:04d}.png"
        with atomic_path(out) as tmp:
            pl.screenshot(str(tmp))
        paths.append(out)
    pl.close()
    return paths

