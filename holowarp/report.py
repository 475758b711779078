"""The end of a reconstruction and its ``report.json``: one dict with every count, metric and
path of a run (:func:`finish_run` runs cleanup, export, previews and metrics, then
:func:`build_report` assembles the dict).

Keys (a contract other tools read): ``preset``, ``device``, ``dataset``, ``resolution``,
``ablations``, ``seconds_total``, ``stages``, ``tets_initial``, ``tets_final``,
``vertices_final``, ``components``, ``manifold``, ``genus``, ``boundary_shells``,
``overlapping_edges`` (:meth:`holowarp.tetmesh.TetMesh.overlapping_edges`: boundary edges
whose tets overlap in space, 0 for an embedded mesh), ``inverted_before_cleanup``,
``flipped``, ``dropped``, ``cleanup``, ``inverted_ratio``, ``min_dihedral_mean``,
``aspect_ratio_mean``, ``prunes``, ``raw_components_max``, ``geometry_blocks``, ``stage0``,
``psnr_test``, ``ssim_test``, ``test_views`` (the views those are measured on),
``held_out`` (``{"test_every", "views"}`` when they were held out of a dataset without its
own test split, else ``null``), ``mesh_mask_iou`` and ``mesh_surfel_normal_cos`` (the
mesh against the test views' masks and the surfels' normals, :mod:`holowarp.metrics.views`,
with ``mesh_see_through_covered``, the share of the masks' see-through pixels the mesh
closes, and ``mesh_checks_per_view``), ``peak_rss_mb``, ``outputs``, ``previews``, ``config``,
``improve`` (the element improvement's section, :func:`holowarp.stages.improve.improve`;
``null`` when ``config.improve.enabled`` is off), ``polish`` (the silhouette polish's section,
:func:`holowarp.stages.polish.polish_silhouettes` with ``pits_lifted``, ``overlap_put_back``
(the vertices :func:`holowarp.stages.polish.keep_unfolded` put back), ``refined`` (the
bisection at sharp bends, :func:`holowarp.stages.polish.refine_bends`'s info, ``null`` when
off or nothing bends that much) and ``after``, the
second fit's own section after §7b with ``angle_put_back``, the vertices
:func:`holowarp.stages.polish.keep_angles` put back, overlaps included, and ``surfel_prior``,
the weight of its prior against the surfels' normals (0 unless the data has no normal maps);
``null`` when off),
``metrics``
(method.md §9) when the dataset has a ground-truth mesh, and ``scene`` (method.md §11,
:func:`scene_objects`) when the run is scene level. The mesh counts and qualities are those
of the final mesh (after improvement).
"""

from __future__ import annotations

import resource
import sys
import time

import numpy as np

__all__ = ["build_report", "finish_run", "image_metrics", "peak_rss_mb", "scene_objects"]


def peak_rss_mb() -> float:
    """Peak resident set size of this process in MiB (Linux reports KiB, macOS bytes)."""
    r = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return r / (1024.0 * 1024.0) if sys.platform == "darwin" else r / 1024.0


def image_metrics(renders, gts) -> tuple[float, float, list[float]]:
    """Mean PSNR (dB), mean SSIM, and the per-view PSNRs of renders against ground truths
    (lists of (H, W, 3) arrays in [0, 1])."""
    import torch

    from holowarp.metrics.image import psnr, ssim

    ps, ss = [], []
    for r, g in zip(renders, gts):
        rt = torch.as_tensor(r)
        gt = torch.as_tensor(np.asarray(g, dtype=np.float32))
        ps.append(psnr(rt, gt))
        ss.append(float(ssim(rt, gt)))
    return float(np.mean(ps)), float(np.mean(ss)), ps


def build_report(*, config, device, data_dir, dataset, state, clean, cleanup_info, psnr, ssim, outputs, previews,
                 metrics=None, improve_info=None, polish_info=None) -> dict:
    """The report of a finished run (``seconds_total`` and ``peak_rss_mb`` are filled in by
    the caller once everything, writing included, is done)."""
    man = clean.manifold()
    q = clean.quality_summary()
    report = {
        "preset": config.preset,
        "device": str(device),
        "dataset": str(data_dir),
        "resolution": [dataset.height, dataset.width],
        "ablations": {
            "continuous_opacity": config.topology.continuous_opacity,
            "uniform_biharmonic": config.geometry.uniform_biharmonic,
            "single_stage_hc": not config.geometry.two_stage_hc,
        },
        "seconds_total": None,
        "stages": state.stages,
        "tets_initial": state.tets_initial,
        "tets_final": clean.num_tets,
        "vertices_final": clean.num_vertices,
        "components": clean.num_components(),
        "manifold": bool(man["manifold"]),
        "genus": clean.genus(),
        "boundary_shells": clean.boundary_shells(),
        "overlapping_edges": clean.overlapping_edges(),
        "inverted_before_cleanup": cleanup_info["inverted_before_cleanup"],
        "flipped": cleanup_info["flipped"],
        "dropped": cleanup_info["dropped"],
        "cleanup": cleanup_info,
        "inverted_ratio": q["inverted_ratio"],
        "min_dihedral_mean": q["min_dihedral_mean"],
        "aspect_ratio_mean": q["aspect_ratio_mean"],
        "prunes": state.prunes,
        # Coherence of the pruning decisions (the paper's ablation measure): the most
        # face-connected pieces any prune's plain rule would have left.
        "raw_components_max": max((p.get("raw_components", 1) for p in state.prunes), default=1),
        "geometry_blocks": state.geometry_blocks,
        "stage0": state.stage0,
        "psnr_test": psnr,
        "ssim_test": ssim,
        "test_views": [int(v) for v in dataset.test_idx],
        "held_out": dataset.meta.get("held_out"),
        "peak_rss_mb": None,
        "outputs": outputs,
        "previews": previews,
        "config": config.to_dict(),
        "improve": improve_info,
        "polish": polish_info,
    }
    if metrics is not None:
        report["metrics"] = metrics
    return report


def finish_run(model, dataset, data_dir, out_dir, config, device, state, history: dict, *, name: str) -> dict:
    """The end of a run (method.md §7): cleanup, the output files, test-view renders and
    previews, metrics against ``gt.obj`` when the dataset has one, and the report.

    Args:
        model: the :class:`holowarp.tetgs.TetGaussians` after the main loop (modified: it
            follows the cleanup).
        state: the run's :class:`holowarp.runstate.RunState` (its stage timings grow).
        history: the loss history by stage, for the loss-curve preview.
        name: the object's prim name in ``scene.usda``.
    """
    from pathlib import Path

    from holowarp.stages.cleanup import cleanup
    from holowarp.stages.export import write_outputs

    t0 = time.perf_counter()
    clean, kept, cinfo = cleanup(model.mesh(), config.cleanup)
    model.apply_cleanup(kept, clean)
    state.add_time("cleanup", time.perf_counter() - t0, 0)
    clean, polish_info, improve_info = _polish_and_improve(model, clean, dataset, config, device, state)
    clean = _touch_up(model, clean, dataset, config, device, state, polish_info, improved=improve_info is not None)

    t0 = time.perf_counter()
    out_dir = Path(out_dir)
    outputs = write_outputs(out_dir, model, clean, name=name, usd=not config.scene.enabled)
    scene = None
    if config.scene.enabled:
        scene = scene_objects(model, clean, data_dir, out_dir, config, device)
        outputs.update(scene_usda=scene.pop("scene_usda"), scene_toml=scene.pop("scene_toml"))
    _return_freed_memory()  # before the previews' off-screen renders, the run's peak
    views = _view_results(model, clean, dataset, out_dir / "previews", history, device)
    state.add_time("export", time.perf_counter() - t0, 0)

    metrics = None
    if dataset.gt_mesh is not None and Path(dataset.gt_mesh).is_file():
        from holowarp.metrics import evaluate_mesh
        from holowarp.metrics.evaluate import evaluation_surfaces
        from holowarp.previews import write_error_maps

        t0 = time.perf_counter()
        metrics = evaluate_mesh(clean, dataset.gt_mesh, dataset=dataset, device=str(device))
        _return_freed_memory()
        views["previews"]["error_maps"] = write_error_maps(out_dir / "previews",
                                                           *evaluation_surfaces(clean, dataset.gt_mesh),
                                                           device=str(device))["paths"]
        state.add_time("evaluate", time.perf_counter() - t0, 0)
    report = build_report(config=config, device=device, data_dir=data_dir, dataset=dataset, state=state, clean=clean,
                          cleanup_info=cinfo, psnr=views["psnr"], ssim=views["ssim"], outputs=outputs,
                          previews=views["previews"], metrics=metrics, improve_info=improve_info,
                          polish_info=polish_info)
    report.update(views["checks"])
    if scene is not None:
        report["scene"] = scene
    return report


def scene_objects(model, mesh, data_dir, out_dir, config, device) -> dict:
    """Scene level (method.md §11, :mod:`holowarp.stages.objects`): split the final ``mesh``
    into objects, name them from ``data_dir/objects/NAME/gt.obj``, write their outputs, and
    return the report's ``scene`` section: ``objects`` (per object ``name``, ``tets``,
    ``vertices``, ``components``, ``genus``, ``manifold``, ``inverted`` (tets with signed
    volume <= 0), ``centre`` (bbox centre, dataset world), ``source_component``, ``gt``,
    ``tetmesh`` and ``metrics`` against its own ground truth when there is one), the
    assignment's counts (:func:`holowarp.stages.objects.assign_objects`), ``min_component``,
    ``scene_usda`` and ``scene_toml``."""
    import torch

    from holowarp.stages.objects import assign_objects, dataset_objects, name_objects, write_scene
    from holowarp.surface_io import read_surface

    sc = config.scene
    gts = dataset_objects(data_dir)
    expected = sc.objects if sc.objects is not None else (len(gts) or None)
    with torch.no_grad():
        pos, col = model.means().cpu().numpy(), model.colors().cpu().numpy()
    objects, info = assign_objects(mesh, pos, col, expected, sc, seed=config.seed)
    centres = [0.5 * (v.min(0) + v.max(0)) for v in (mesh.vertices[np.unique(mesh.tets[o])] for o in objects)]
    gt_centres = {}
    for n, p in gts.items():
        V, _ = read_surface(p)
        gt_centres[n] = 0.5 * (V.min(0) + V.max(0))
    names = name_objects(centres, gt_centres)
    paths = write_scene(out_dir, mesh, objects, names, col, config=sc)
    rows = []
    for ids, n, c, src in zip(objects, names, centres, info["source_component"]):
        m = mesh.submesh(ids)
        row = {"name": n, "tets": m.num_tets, "vertices": m.num_vertices, "components": m.num_components(),
               "genus": m.genus(), "manifold": bool(m.manifold()["manifold"]),
               "inverted": int(np.count_nonzero(m.signed_volumes() <= 0)), "centre": [float(x) for x in c],
               "source_component": src, "gt": str(gts[n]) if n in gts else None,
               "tetmesh": paths["objects"][n]}
        if n in gts and sc.evaluate_objects:
            from holowarp.metrics import evaluate_mesh

            row["metrics"] = evaluate_mesh(m, gts[n], device=str(device))
        rows.append(row)
    missing = sorted(set(gts) - set(names))
    return {"objects": rows, "min_component": sc.min_component, "missing": missing,
            **{k: v for k, v in info.items() if k != "source_component"},
            "scene_usda": paths["scene_usda"], "scene_toml": paths["scene_toml"]}


def _view_results(model, mesh, dataset, prev, history, device) -> dict:
    """The test views: the surfels' PSNR/SSIM, the mesh's image checks (issue 16:
    ``mesh_mask_iou``, ``mesh_surfel_normal_cos`` and their per-view values), and the
    previews (test views, silhouettes on three photos, turntable, cutaway, losses)."""
    import torch

    from holowarp.metrics.views import mesh_image_checks, mesh_renders
    from holowarp.previews import (preview_cutaway, preview_losses, preview_silhouettes, preview_test_views,
                                   preview_turntable)
    from holowarp.stages.export import render_surfel_views

    test = dataset.test_idx if len(dataset.test_idx) else dataset.train_idx[:4]
    surfels = render_surfel_views(model, dataset, test, background=torch.zeros(3, device=device))
    renders = [r["rgb"] for r in surfels]
    gts = list(dataset.composite((0.0, 0.0, 0.0))[test])
    psnr, ssim, per_view = image_metrics(renders, gts)
    meshes = mesh_renders(mesh, dataset, test, device=str(device))
    checks = mesh_image_checks(meshes, dataset.masks[test], surfels)
    pick = np.linspace(0, len(test) - 1, min(3, len(test))).round().astype(int)
    previews = {
        "test_views": preview_test_views(prev, renders, gts, test, psnrs=per_view),
        "silhouettes": preview_silhouettes(prev / "silhouettes.png", [dataset.images[test[i]] for i in pick],
                                           [meshes[i]["alpha"] for i in pick], dataset.masks[test[pick]], test[pick]),
        "turntable": preview_turntable(prev / "turntable.png", mesh, device=str(device)),
        "cutaway": preview_cutaway(prev / "cutaway_components.png", mesh, device=str(device)),
        "losses": preview_losses(prev / "losses.png", history),
    }
    return {"psnr": psnr, "ssim": ssim, "previews": previews,
            "checks": {"mesh_mask_iou": checks["mesh_mask_iou"], "mesh_surfel_normal_cos": checks["mesh_surfel_normal_cos"],
                       "mesh_see_through_covered": checks["mesh_see_through_covered"],
                       "mesh_checks_per_view": checks["per_view"]}}


def _return_freed_memory() -> None:
    """Hand memory that Python and torch have freed back to the OS (glibc keeps freed heap
    pages mapped, and the main loop's temporaries left hundreds of MB of them), so VTK's
    renders at the end do not stack on top of it. A no-op where libc has no malloc_trim."""
    import ctypes
    import gc

    gc.collect()
    try:
        ctypes.CDLL("libc.so.6").malloc_trim(0)
    except (OSError, AttributeError):
        pass


def _polish(model, clean, dataset, config, device, state):
    """The silhouette polish (:mod:`holowarp.stages.polish`) of the cleaned mesh: pits
    lifted, then the boundary fitted to the masks, the surfels following their tets; returns
    (mesh, report section or None when disabled)."""
    if not config.polish.enabled:
        return clean, None
    from holowarp.stages.polish import keep_unfolded, lift_pits, polish_silhouettes, refine_bends
    from holowarp.tetmesh import TetMesh

    t0 = time.perf_counter()
    refined = refine_bends(clean, config.polish)
    if refined is not None:
        V, T, parent, ends, refine_info = refined
        model.apply_refine(V, T, parent, ends)
        clean = TetMesh(V, T)
    V, pits = lift_pits(clean, config.polish)
    lifted = clean.with_vertices(V)
    V, info = polish_silhouettes(lifted, dataset, config.polish, seed=config.seed, device=str(device))
    V, info["overlap_put_back"] = keep_unfolded(lifted, V)
    info["pits_lifted"] = pits
    info["refined"] = None if refined is None else refine_info
    state.add_time("polish", time.perf_counter() - t0, 0)
    return _move_vertices(model, clean, V), info


def _polish_and_improve(model, clean, dataset, config, device, state):
    """The polish, then §7b, which mends the tets the polish flattens or skews; returns
    (mesh, polish section, improve section).

    The polish's bisection at sharp bends (``PolishConfig.refine_bend``) is kept only when §7b
    still reaches ``PolishConfig.refine_keep_deg`` on the refined mesh: on a coarse mesh
    (a 40-pixel run, where a tenth of the tets sit at such bends) the bisection multiplies
    the slivers §7b has to mend, and §7b's worst angle fell from 17.0° to 3.8°. Then both run
    again without it, from the model as cleanup left it, and the better of the two meshes (by
    §7b's worst angle; ``refined.min_dihedral_worst`` with the bisection, ``refined.without``
    without it) is kept; ``refined.kept`` says which."""
    from dataclasses import replace

    from holowarp.progress import say

    p = config.polish
    snapshot = model.state_dict() if p.enabled and p.refine_bend is not None and config.improve.enabled else None
    cleaned = clean
    clean, polish_info = _polish(model, cleaned, dataset, config, device, state)
    clean, improve_info = _improve(model, clean, dataset, config, device, state)
    refined = polish_info.get("refined") if polish_info is not None else None
    if snapshot is None or refined is None:  # no bisection, or no §7b to judge it by
        if refined is not None:
            refined["kept"] = True
        return clean, polish_info, _refit(model, dataset, config, device, state, improve_info)
    worst = improve_info["after"]["min_dihedral_worst"]
    refined.update(kept=bool(worst >= p.refine_keep_deg), min_dihedral_worst=worst)
    if refined["kept"]:
        return clean, polish_info, _refit(model, dataset, config, device, state, improve_info)
    say(f"the bisection at sharp bends left §7b at {worst:.1f}° (under {p.refine_keep_deg:g}°): "
        "polishing and improving again without it", progress=False)
    first = (clean, polish_info, improve_info, model.state_dict())
    model.load_state_dict(snapshot)
    plain = replace(config, polish=replace(p, refine_bend=None))
    clean, polish_info = _polish(model, cleaned, dataset, plain, device, state)
    clean, improve_info = _improve(model, clean, dataset, plain, device, state)
    refined["without"] = improve_info["after"]["min_dihedral_worst"]
    if refined["without"] < worst:  # the refined mesh was the better of two misses
        refined["kept"] = True
        model.load_state_dict(first[3])
        clean, polish_info, improve_info = first[:3]
    else:
        polish_info["refined"] = refined
    return clean, polish_info, _refit(model, dataset, config, device, state, improve_info)


def _touch_up(model, clean, dataset, config, device, state, polish_info, *, improved: bool):
    """A short second fit of the polish after §7b (``PolishConfig.after_steps``, under the
    tighter ``after_volume_fraction``), which wins back what the improvement's boundary
    operations undid; on data without normal maps its prior is the refitted surfels'
    normals (``after_w_surfels``). Its section goes to ``polish_info["after"]``."""
    p = config.polish
    if polish_info is None or not improved or p.after_steps == 0:
        return clean
    from dataclasses import replace

    from holowarp.stages.polish import SurfelNormals, keep_angles, keep_unfolded, polish_silhouettes

    t0 = time.perf_counter()
    second = replace(p, steps=p.after_steps, min_volume_fraction=p.after_volume_fraction,
                     interior_follow=p.after_interior_follow)
    normals = None
    if dataset.normals is None and p.after_w_surfels > 0:  # the refitted surfels stand in for normal maps
        normals, second = SurfelNormals(model, dataset, device), replace(second, w_prior=p.after_w_surfels)
    V, info = polish_silhouettes(clean, dataset, second, seed=config.seed + 1, device=str(device), normals=normals)
    info["surfel_prior"] = float(second.w_prior) if normals is not None else 0.0
    if p.after_angle_floor is not None:
        V, info["angle_put_back"] = keep_angles(clean, V, p.after_angle_floor)
    else:
        V, info["angle_put_back"] = keep_unfolded(clean, V)
    polish_info["after"] = info
    state.add_time("polish", time.perf_counter() - t0, 0)
    return _move_vertices(model, clean, V)


def _move_vertices(model, mesh, V):
    """``mesh`` with vertices ``V`` (V, 3), the model's vertices (and so its surfels) following."""
    import torch

    with torch.no_grad():
        model.vertices.data.copy_(torch.as_tensor(V, dtype=model.vertices.dtype, device=model.vertices.device))
    return mesh.with_vertices(V)


def _improve(model, clean, dataset, config, device, state):
    """The element improvement (method.md §7b) of the cleaned mesh, the surfels following
    their parent tets (not yet refitted: :func:`_refit`); returns (mesh, report section or
    None when disabled)."""
    if not config.improve.enabled:
        return clean, None
    from holowarp.stages.improve import improve

    t0 = time.perf_counter()
    mesh, parent, info = improve(clean, config.improve, device=str(device))
    model.apply_improve(mesh, parent)
    state.add_time("improve", time.perf_counter() - t0, 0)
    return mesh, info


def _refit(model, dataset, config, device, state, info):
    """Refit the surfels that §7b moved to the images (``ImproveConfig.refit_steps``; on
    data without normal maps ``refit_steps_without_maps`` at ``refit_w_normal``), once, on
    the mesh :func:`_polish_and_improve` keeps: the refit moves no vertex, so it cannot
    change which of two meshes is kept, and refitting both cost the README's main job 14 s
    of its 250. Its section goes to ``info["refit"]``; returns ``info``."""
    if info is None:
        return None
    from holowarp.stages.topology import refit_appearance

    t0 = time.perf_counter()
    topo, steps = config.improve.refit_settings(config.topology, normal_maps=dataset.normals is not None)
    info["refit"] = refit_appearance(model, dataset, topo, steps, seed=config.seed, device=device)
    info["refit"]["w_normal"] = topo.w_normal
    state.add_time("improve", time.perf_counter() - t0, 0)
    return info
