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
from pathlib import Path

import numpy as np

from holowarp.sim.analysis import pieces_apart
from holowarp.sim.run import FPS, run_scene
from holowarp.sim.scene import load_scene, placement_transform
from holowarp.tetmesh import TetMesh

__all__ = ["SimulationError", "FPS", "CHAMFER_TIMES", "simulate", "load_sim_mesh", "render_frames"]

#: Times (s) at which ``sim_chamfer`` is measured (method.md §10).
CHAMFER_TIMES = (0.0, 0.25, 0.5, 0.75, 1.0)


class SimulationError(ValueError):
    """The inputs of a simulation cannot be used; the message names the file or argument."""


def load_sim_mesh(src, *, what: str = "mesh") -> TetMesh:
    """A positively oriented tet mesh without unused vertices from ``src``.

    Args:
        src: a :class:`TetMesh`, a tet-mesh file (``.vtu``, ``.msh``, ``.npz``, ``.usd*``), or
            a closed surface (``.obj``, ``.ply``, ...), which is tetrahedralised with fTetWild.
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
                mesh = tetrahedralize_surface(V, F)
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


def simulate(mesh, scene, *, device: str = "cpu", reference=None, out_dir=None, render_dir=None,
             progress: bool = True, chamfer_samples: int | None = None, name: str = "Object") -> dict:
    """Simulate a tet mesh in a scene and report (method.md §10).

    Args:
        mesh: a :class:`TetMesh` or a mesh file (any tet format; a surface is tetrahedralised).
        scene: ``"drop"``, ``"compress"``, a ``.toml`` path, or a :class:`Scene`.
        device: ``"cpu"`` or ``"cuda[:N]"``.
        reference: optional ground-truth mesh (tet file, or a closed surface that is
            tetrahedralised with fTetWild) simulated in the same scene and the same placement;
            adds ``sim_chamfer``. The placement (and the evaluation frame) then come from the
            reference's rest bounding box.
        out_dir: if given, writes ``sim.usda`` and ``report.json`` there (atomically).
        render_dir: if given, writes one PNG per frame there (pyvista, off screen).
        progress: show a progress bar.
        chamfer_samples: surface samples per mesh for ``sim_chamfer`` (method.md §9: 100,000).
        name: prim name of the body in USD.

    Returns:
        The report dict: ``frames``, ``steps``, ``seconds``, ``steps_per_second``,
        ``max_inverted``, ``min_volume_ratio``, ``max_volume_ratio``, ``com`` (per frame, m),
        ``nan``, ``components_end`` (see :func:`holowarp.sim.analysis.pieces_apart`), and,
        with a reference, ``sim_chamfer`` ({time s: Chamfer-L1 in the evaluation frame}),
        plus context (scene, device, mesh size, the solver's step plan, per-frame volume
        ratio, inverted counts and contact forces).
    """
    from tqdm.auto import tqdm

    from holowarp.device import resolve_device
    from holowarp.metrics.surface import SurfaceMetricSettings

    device = resolve_device(device)
    scene = load_scene(scene)
    mesh = load_sim_mesh(mesh, what="mesh")
    ref = load_sim_mesh(reference, what="reference") if reference is not None else None
    transform = placement_transform((ref if ref is not None else mesh).vertices, scene.placement)

    n_runs = 2 if ref is not None else 1
    bar = tqdm(total=scene.num_steps * n_runs, desc=f"{scene.name}", unit="step", disable=not progress)
    try:
        run = run_scene(scene, mesh, transform=transform, device=device, progress=bar)
        ref_run = None
        if ref is not None:
            ref_run = run_scene(scene, ref, transform=transform, device=device, progress=bar)
    finally:
        bar.close()

    model = run["model"]
    rest_placed = model.rest_positions
    placed_mesh = mesh.with_vertices(rest_placed)
    V0 = model.rest_volume()
    frames = run["frames"]
    vol_ratio = run["volume"] / V0
    comps, comp_info = pieces_apart(placed_mesh, frames[-1]) if not run["nan"] else (None, {})
    report = {
        "frames": int(len(frames)),
        "steps": int(run["steps"]),
        "seconds": float(run["seconds"]),
        "steps_per_second": float(run["steps"] / run["seconds"]) if run["seconds"] > 0 else None,
        "max_inverted": int(run["inverted"].max()),
        "min_volume_ratio": float(np.nanmin(vol_ratio)),
        "max_volume_ratio": float(np.nanmax(vol_ratio)),
        "com": run["com"].tolist(),
        "nan": bool(run["nan"]),
        "components_end": comps,
        "scene": scene.name,
        "scene_file": scene.source,
        "device": device,
        "vertices": mesh.num_vertices,
        "tets": mesh.num_tets,
        "components_start": int(mesh.components()[1]),
        "components_info": comp_info,
        "dt": scene.sim.dt,
        "plan": run["plan"].as_dict(),
        "inverted_end": int(run["inverted"][-1]),
        "inverted": run["inverted"].tolist(),
        "volume_ratio": vol_ratio.tolist(),
        "contact_force": {
            sname: run["surface_force"][:, k].tolist()
            for k, sname in enumerate((["Ground"] if model.ground is not None else []) + [p.name for p in model.plates])
        },
    }

    if ref_run is not None:
        from holowarp.metrics import unit_cube_transform

        n = chamfer_samples or SurfaceMetricSettings().num_samples
        s, t = unit_cube_transform(ref_run["model"].rest_positions)
        to_eval = lambda x: np.asarray(x, np.float64) * s + t  # noqa: E731
        sc = {}
        for tc in CHAMFER_TIMES:
            k = int(round(tc * FPS))
            if k < len(frames) and k < len(ref_run["frames"]):
                sc[f"{tc:g}"] = _chamfer(mesh, frames[k], ref, ref_run["frames"][k], to_eval, n, seed=k)
        report["sim_chamfer"] = sc
        report["reference"] = {"vertices": ref.num_vertices, "tets": ref.num_tets, "nan": bool(ref_run["nan"]),
                               "max_inverted": int(ref_run["inverted"].max())}

    if out_dir is not None:
        out_dir = Path(out_dir)
        out_dir.mkdir(parents=True, exist_ok=True)
        _write_usd(out_dir / "sim.usda", scene, run, placed_mesh, name,
                   ref_run=ref_run, ref_mesh=ref)
        from holowarp.fileio import atomic_write_json

        atomic_write_json(out_dir / "report.json", report)
    if render_dir is not None:
        render_frames(render_dir, placed_mesh, frames, run["model"], run["surface_points"], progress=progress)
    return report


def _write_usd(path, scene, run, placed_mesh, name, *, ref_run=None, ref_mesh=None):
    from holowarp.usd import PhysicsMaterial, UsdSceneWriter

    m = scene.material
    mat = PhysicsMaterial(m.youngs_modulus, m.poissons_ratio, m.density, m.friction, m.friction)
    w = UsdSceneWriter(path, fps=FPS)
    w.add_tetmesh(name, placed_mesh, material=mat)
    for k, x in enumerate(run["frames"]):
        if np.all(np.isfinite(x)):
            w.set_points(name, x, k)
    if ref_run is not None:
        rname = "Reference"
        w.add_tetmesh(rname, ref_mesh.with_vertices(ref_run["model"].rest_positions), material=mat,
                      color=(0.35, 0.55, 0.8))
        for k, x in enumerate(ref_run["frames"]):
            if np.all(np.isfinite(x)):
                w.set_points(rname, x, k)
    model = run["model"]
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

