"""The HoloTetSphere reconstruction pipeline (method.md §3–§8), resumable at any point.

:func:`reconstruct` runs stage 0 (§3), the tetrahedral initialisation (§4), the main loop's
events (§5, §6, §8: :meth:`holowarp.config.Schedule.events`), then cleanup, outputs,
previews, metrics and ``report.json`` (:func:`holowarp.report.finish_run`). The typed state
(:class:`holowarp.runstate.RunState`) is checkpointed atomically at every stage boundary and
every ``checkpoint_every`` iterations; ``resume=True`` continues from it. Every random choice
is a function of (seed, iteration), so a resumed run ends with the same result as an
uninterrupted one, and fTetWild's is seeded by the run's seed where :mod:`holowarp.repeatable`
can do so (its output is checkpointed before use, so a resume never depends on that).
"""

from __future__ import annotations

import json
import queue
import time
from pathlib import Path

import numpy as np
import torch

from holowarp.config import GaussianStep, MeshBlock, Prune, ReconConfig
from holowarp.device import resolve_device
from holowarp.fileio import atomic_write_json, check_output_dir
from holowarp.preflight import ReconstructionError, prepare_dataset
from holowarp.progress import Bars, LossBuffer, say
from holowarp.report import finish_run, peak_rss_mb
from holowarp.runstate import Checkpoint, HistoryLog, Phase, RunState, check_resume
from holowarp.stages.gaussian_init import train_gs2d
from holowarp.stages.geometry import GeometryState, run_geometry_block
from holowarp.stages.topology import (EmptyEvidence, GaussianOptimizers, ViewTensors, after_first_prune,
                                      gaussian_step, init_model_from_surfels, prune, prune_message,
                                      refine_near_surface)
from holowarp.tetgs import TetGaussians

__all__ = ["ReconstructionError", "reconstruct", "reconstruct_alone"]


def reconstruct(dataset_path=None, out_dir="runs/holowarp", *, config: ReconConfig, device: str = "cpu",
                resume: bool = False, progress: bool = True) -> dict:
    """Reconstruct one connected, manifold, inversion-free tet mesh from multi-view images.

    Args:
        dataset_path: a NeRF-synthetic, NeuS/IDR or COLMAP folder; ``None`` synthesises the built-in
            bob into ``out_dir/data``.
        out_dir: output folder (see :mod:`holowarp.stages.export` for its contents).
        config: the :class:`holowarp.config.ReconConfig` (``holowarp.config.preset(...)``).
        device: ``"cpu"`` or ``"cuda[:N]"``.
        resume: continue from ``out_dir/checkpoints/state.pt``.
        progress: show progress bars and status lines (:mod:`holowarp.progress`).

    Returns the report dict also written to ``out_dir/report.json``. Raises
    :class:`holowarp.errors.InputError` subclasses before any work, with the reason.
    """
    t_start = time.perf_counter()
    device = resolve_device(device)
    config.schedule.validate()
    t = config.topology
    if t.refine_rings > 0 and t.refine_at_prune >= len(config.schedule.prune_at):
        raise ValueError(f"topology.refine_at_prune {t.refine_at_prune}: the schedule has only "
                         f"{len(config.schedule.prune_at)} prune(s)")
    out_dir = check_output_dir(out_dir)
    ckpt = Checkpoint.load(out_dir)
    check_resume(out_dir, ckpt, config.to_dict(), dataset_path, resume=resume)
    dataset, data_dir = prepare_dataset(dataset_path, out_dir, config, device=device, progress=progress,
                                        resuming=ckpt is not None)
    run_config, pieces = _run_config(config, dataset, device, progress)
    run = _Run(dataset, data_dir, dataset_path, out_dir, run_config, device, progress, ckpt, checkpoint_config=config,
               pieces=pieces)
    try:
        report = run.execute()
    finally:
        run.bars.close()
        run.history.close()
    report["seconds_total"] = float(run.seconds_before + time.perf_counter() - t_start)
    report["peak_rss_mb"] = round(peak_rss_mb(), 1)
    atomic_write_json(out_dir / "report.json", report)
    return report


def reconstruct_alone(dataset_path, out_dir, *, config: ReconConfig, device: str = "cpu", resume: bool = False,
                      progress: bool = True) -> dict:
    """:func:`reconstruct` in a fresh interpreter, as ``python -m holowarp.reconstruct`` runs it,
    for callers that run several objects in one process (``bench quality``, the dataset runs).

    fTetWild's meshes depend on what the process meshed before (the visual hull, an earlier
    object), so a reconstruction that shares its process gets another mesh than the same data
    and seed on their own, and its report's ``peak_rss_mb`` includes the others' memory. The
    child uses the caller's torch thread count. Returns the report; the child's exception is
    raised again here (a ``RuntimeError`` naming it when it cannot be passed back).
    """
    import multiprocessing

    ctx = multiprocessing.get_context("spawn")
    errors = ctx.Queue()
    child = ctx.Process(target=_reconstruct_child, args=(str(dataset_path), str(out_dir), config, device, resume,
                                                         progress, torch.get_num_threads(), errors))
    child.start()
    # Read the child's error while it runs: it waits for its message to leave the pipe before
    # it exits, so joining first would hang on a message larger than the pipe's buffer.
    data = None
    while data is None and (child.is_alive() or not errors.empty()):
        try:
            data = errors.get(timeout=1.0)
        except queue.Empty:
            pass
    child.join()
    if child.exitcode != 0:
        import pickle

        try:
            err = pickle.loads(data)
        except Exception:  # noqa: BLE001 -- killed before it could say why
            err = RuntimeError(f"reconstructing {dataset_path} into {out_dir}: the process ended with status "
                               f"{child.exitcode}")
        raise err
    return json.loads((Path(out_dir) / "report.json").read_text())


def _reconstruct_child(dataset_path, out_dir, config, device, resume, progress, threads, errors) -> None:
    torch.set_num_threads(threads)
    try:
        reconstruct(dataset_path, out_dir, config=config, device=device, resume=resume, progress=progress)
    except BaseException as e:  # passed back whole, so the caller sees holowarp's own error types
        import pickle

        try:
            data = pickle.dumps(e)
            pickle.loads(data)
        except Exception:  # noqa: BLE001 -- cannot make the trip: its type and message
            data = pickle.dumps(RuntimeError(f"{type(e).__name__}: {e}"))
        errors.put(data)
        errors.close()
        errors.join_thread()
        raise SystemExit(1) from None


def _run_config(config: ReconConfig, dataset, device: str, progress: bool) -> tuple[ReconConfig, list | None]:
    """The config a run uses, and a scene's objects as the masks see them.

    One object: ``(config, None)``. A scene: its length-valued settings at the scene's
    object size (:meth:`ReconConfig.at_object_size`, measured from the masks' hull pieces
    unless ``scene.object_size`` gives it), and those pieces
    (:func:`holowarp.stages.objects.hull_pieces`, which size the initial tets per object).
    Derived again on resume (the same masks give the same pieces); checkpoints keep ``config``."""
    if not config.scene.enabled:
        return config, None
    from holowarp.stages.objects import hull_pieces, largest_side

    pieces = hull_pieces(dataset, device=device)
    size = config.scene.object_size
    if size is None:
        size = largest_side(pieces)
    say(f"scene level: the largest object is {size:.3f} frame units wide; length-valued settings scaled to it",
        progress)
    return config.at_object_size(size), pieces


class _Run:
    """One reconstruction: its typed state, model and optimisers; a handler per phase and event."""

    def __init__(self, dataset, data_dir, dataset_path, out_dir, config, device, progress, ckpt, *,
                 checkpoint_config=None, pieces=None):
        self.ds, self.data_dir, self.dataset_path, self.out = dataset, Path(data_dir), dataset_path, Path(out_dir)
        self.cfg, self.device, self.progress = config, torch.device(device), progress
        # What --resume compares against: the caller's config, before _run_config derives from it.
        self.checkpoint_cfg = config if checkpoint_config is None else checkpoint_config
        # A scene's objects as bounding boxes (hull_pieces): the initial tets are sized per object.
        self.pieces = pieces
        self.state = ckpt.state if ckpt is not None else RunState()
        self.seconds_before, self._t0 = self.state.elapsed, time.perf_counter()
        self.ckpt, self.model, self.opts, self.evidence = ckpt, None, None, None
        if ckpt is not None and ckpt.model is not None:
            self.model = TetGaussians.from_state_dict(ckpt.model, device=self.device)
        self.bars = Bars(progress)
        self.history = HistoryLog(self.out, keep_lines=self.state.history_lines)
        self.losses = LossBuffer(self.history.append)  # main-loop terms, read every LOG_EVERY steps

    def save(self):
        st = self.state
        st.elapsed = self.seconds_before + (time.perf_counter() - self._t0)
        self.losses.flush()
        st.history_lines = self.history.flush()
        Checkpoint(self.checkpoint_cfg.to_dict(), str(self.dataset_path) if self.dataset_path else None, st,
                   None if self.model is None else self.model.state_dict(),
                   None if self.opts is None else self.opts.state_dict()).save(self.out)

    def execute(self) -> dict:
        steps = ((Phase.STAGE0, self.stage0, Phase.TET_INIT), (Phase.TET_INIT, self.tet_init, Phase.MAIN),
                 (Phase.MAIN, self.main_loop, Phase.CLEANUP))
        for phase, run, following in steps:
            if self.state.phase is phase:
                run()
                self.state.phase = following
                self.save()
        return self.finish()

    def stage0(self):
        iters = self.cfg.schedule.stage0_iters
        with self.state.timed("stage0", iters):
            res = train_gs2d(self.ds, self.cfg.stage0, self.out / "stage0", iters=iters, seed=self.cfg.seed,
                             device=str(self.device), resume=True, progress=self.progress)
        self.state.stage0 = {k: res[k] for k in ("psnr_test", "gaussians", "iters")}

    def tet_init(self):
        with self.state.timed("tet_init"):
            # The depth carve's maps are made once: the field's start and the prunes' evidence share them.
            maps = self._evidence().maps() if self.cfg.topology.phi_init == "depth_hull" else None
            self.model = init_model_from_surfels(self.out / "stage0" / "gaussians.ply", self.ds, self.cfg.tet_init,
                                                 self.cfg.topology, seed=self.cfg.seed, device=self.device,
                                                 progress=self.progress, pieces=self.pieces, depth_maps=maps)
        self.state.tets_initial, self.state.vertices_initial = self.model.num_tets, self.model.num_vertices

    def _rebuild_optimizers(self, saved: dict | None = None, *, learn_scales: bool):
        self.opts = GaussianOptimizers(self.model, self.cfg.topology, learn_scales=learn_scales)
        if saved is not None:
            self.opts.load_state_dict(saved)
        self.edges = torch.tensor(np.array(self.model.mesh().edges()), dtype=torch.int32, device=self.device)

    def main_loop(self):
        self._rebuild_optimizers(self.ckpt.optimizers if self.ckpt is not None else None,
                                 learn_scales=self.state.first_prune_done)
        self.tensors = ViewTensors(self.ds, self.device, pieces=self.pieces)
        self.coarse = None
        for ev in self.cfg.schedule.events(self.state.main_iter):
            if isinstance(ev, GaussianStep):
                self.on_step(ev)
            elif ev.key not in self.state.done:
                self.losses.flush()
                self.bars.close("topology", "gaussian")
                self.on_prune(ev) if isinstance(ev, Prune) else self.on_mesh_block(ev)
                self.state.done.append(ev.key)
                self.save()
        self.losses.flush()
        self.bars.close("topology", "gaussian")

    def _evidence(self) -> EmptyEvidence:
        if self.evidence is None:
            self.evidence = EmptyEvidence(self.out / "stage0" / "gaussians.ply", self.ds, self.cfg.topology,
                                          device=self.device)
        return self.evidence

    def _depth_maps(self) -> dict | None:
        """The depth carve's maps by view, ``{view: (stage-0 depth, alpha, corrected)}``, for the
        mesh blocks' depth pull; None without normal-corrected maps or with the pull off."""
        if not self.cfg.geometry.depth_pull > 0:
            return None
        ev = self._evidence()
        maps = ev.maps()
        if maps is None or maps[2] is None:
            return None
        return {int(v): (maps[0][j], maps[1][j], maps[2][j]) for j, v in enumerate(ev.views)}

    def on_prune(self, ev: Prune):
        evidence = self._evidence() if self.cfg.topology.uses_evidence else None
        t0 = time.perf_counter()
        mesh = self.model.mesh()
        outside, in_front = evidence.parts(mesh) if evidence else (None, None)
        # The depth evidence prunes on its own only where normal maps made it good (TopologyConfig.prune_in_front).
        forced, t = None, self.cfg.topology
        if t.prune_in_front and self.ds.normals is not None and evidence is not None:
            lid = None if t.prune_in_front_lid_tol is None else (t.prune_in_front_lid_gap, t.prune_in_front_lid_tol)
            forced = in_front if (t.prune_in_front_tol == t.depth_carve_tol and lid is None) else evidence.in_front(
                mesh, tol=t.prune_in_front_tol, lid=lid)
        info = prune(self.model, self.cfg.topology, evidence=None if outside is None else outside | in_front,
                     outside=outside, genus_bound=(lambda: evidence.hull_genus(mesh)) if evidence else None,
                     in_front=forced)
        info["seconds"] = time.perf_counter() - t0  # the evidence and the guards, before any refinement
        if self.cfg.schedule.prune_at.index(ev.iteration) == self.cfg.topology.refine_at_prune:
            refined = refine_near_surface(self.model, self.cfg.topology, self.ds)
            if refined is not None:
                info["refined"] = refined
                say(f"refined the {refined['band']} tets near the surface to a longest edge of "
                    f"{refined['target']:.4f}: {refined['tets_before']} -> {refined['tets_after']} tets", self.progress)
        if ev.first:
            after_first_prune(self.model)
        info["iteration"] = ev.iteration
        self.state.prunes.append(info)
        say(prune_message(info, self.cfg.topology.prune_alpha), self.progress)
        self._rebuild_optimizers(learn_scales=True)

    def on_mesh_block(self, ev: MeshBlock):
        st, sch = self.state, self.cfg.schedule
        gstate = GeometryState(mesh_iter=st.mesh_iter)

        def block_ckpt(resume):
            st.block, st.mesh_iter = resume, gstate.mesh_iter
            self.save()

        with st.timed("geometry", sch.mesh_block_iters - (st.block.step if st.block else 0)):
            summary = run_geometry_block(
                self.model, self.ds, self.ds.train_idx, self.cfg.geometry, block_iters=sch.mesh_block_iters,
                depth_maps=self._depth_maps(),
                total_mesh_iters=sch.total_mesh_iters, state=gstate, at=ev.iteration, seed=self.cfg.seed,
                resume=st.block, progress=self.bars.get("geometry", sch.total_mesh_iters, st.mesh_iter),
                checkpoint=block_ckpt, checkpoint_every=self.cfg.checkpoint_every,
                log=lambda r: self.history.append("geometry", r))
        st.geometry_blocks.append({"at": ev.iteration, **{k: v for k, v in summary.items() if k != "final"}})
        st.block, st.mesh_iter = None, gstate.mesh_iter
        if st.mesh_iter >= sch.total_mesh_iters:
            self.bars.close("geometry")

    def on_step(self, ev: GaussianStep):
        sch, train, topo = self.cfg.schedule, self.ds.train_idx, ev.phase == "topology"
        view = int(train[np.random.default_rng([self.cfg.seed, 0, ev.iteration]).integers(len(train))])
        ds, tensors = self._views_at(ev.iteration) if topo else (self.ds, self.tensors)
        with self.state.timed(ev.phase, 1):
            terms = gaussian_step(self.model, ds, view, self.cfg.topology, self.opts, topology_phase=topo,
                                  edges=self.edges, tensors=tensors)
        last = (self.losses.add(ev.phase, {"iter": ev.iteration}, terms) or [(None, None)])[-1][1]
        total, start = (sch.topology_until, 0) if topo else (sch.main_iters - sch.topology_until, sch.topology_until)
        self.bars.advance(ev.phase, total, ev.iteration - start, **({} if last is None else dict(
            loss=f"{last['loss']:.4f}", rgb=f"{last['rgb']:.4f}", mask=f"{last['mask']:.4f}", tets=self.model.num_tets)))
        self.state.main_iter = ev.iteration + 1
        if self.state.main_iter % self.cfg.checkpoint_every == 0:
            self.save()

    def _views_at(self, iteration: int):
        """The dataset and view tensors topology step ``iteration`` renders at: the coarse copy
        in the first ``coarse_fraction`` of the phase (:class:`TopologyConfig`), else the full."""
        t = self.cfg.topology
        if iteration >= round(t.coarse_fraction * self.cfg.schedule.topology_until):
            self.coarse = None
            return self.ds, self.tensors
        if self.coarse is None:
            ds = self.ds.scaled(t.coarse_scale)
            self.coarse = (ds, ViewTensors(ds, self.device, pieces=self.pieces))
        return self.coarse

    def finish(self) -> dict:
        """No checkpoint here: --resume of a finished run redoes cleanup and export alike."""
        # The main loop's view tensors, optimiser moments and evidence maps are not needed any
        # more; dropped here, their memory is reused by the finish's renders instead of
        # adding to the run's peak (the finish is where a run's RSS peaks, issue 17).
        self.tensors = self.coarse = self.opts = self.evidence = self.edges = None
        name = "Bob" if self.dataset_path is None else (self.data_dir.name or "Object")
        return finish_run(self.model, self.ds, self.data_dir, self.out, self.cfg, self.device, self.state,
                          self.history.read(), name=name)

