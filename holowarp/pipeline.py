"""The HoloTetSphere reconstruction pipeline (method.md §3–§8), resumable at any point.

:func:`reconstruct` runs, in order:

1. stage 0 (§3): 2DGS surfels from the images (:func:`holowarp.gs2d.train_gs2d`);
2. tetrahedral initialisation (§4): scaled convex hull of their centres, fTetWild, one surfel
   per tet;
3. the main loop (§5, §6, §8): topology optimisation of the vertex field, prunes, Gaussian
   phases and mesh-only geometry blocks, in the schedule's order;
4. cleanup (§7), outputs, previews, metrics and ``report.json``.

State is checkpointed atomically to ``DIR/checkpoints/state.pt`` (every
``checkpoint_every`` iterations and at every stage boundary); ``resume=True`` continues from
it. Every random choice is a function of (seed, iteration), so a resumed run draws the same
views and ends with the same result as an uninterrupted one (fTetWild itself is not
deterministic, which is why its output is checkpointed before anything uses it).
"""

from __future__ import annotations

import json
import logging
import resource
import sys
import time
from dataclasses import asdict
from pathlib import Path

import numpy as np
import torch

from holowarp.config import ReconConfig
from holowarp.fileio import atomic_path, atomic_write_json

__all__ = ["ReconstructionError", "reconstruct", "preflight", "default_dataset"]

log = logging.getLogger("holowarp.reconstruct")

#: Minimum number of views a reconstruction accepts.
MIN_VIEWS = 8
STATE_FILE = "checkpoints/state.pt"


class ReconstructionError(RuntimeError):
    """The reconstruction cannot start or continue; the message says why."""


def _peak_rss_mb() -> float:
    r = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return r / (1024.0 * 1024.0) if sys.platform == "darwin" else r / 1024.0


def default_dataset(out_dir: Path, *, resolution: int, device: str, progress: bool) -> Path:
    """Synthesise the built-in default object (bob, genus 1, CC0) into ``out_dir/data``:
    120 Fibonacci views at ``resolution`` (method.md §2)."""
    from holowarp.data.synth import synthesize

    asset = Path(__file__).resolve().parent / "assets" / "bob" / "bob_tri.obj"
    data = Path(out_dir) / "data"
    done = (data / "transforms_train.json").is_file() and (data / "transforms_test.json").is_file()
    if not done:
        synthesize(asset, data, res=resolution, device=device, up_axis="y", resume=True, progress=progress)
    return data


def preflight(dataset, *, min_views: int = MIN_VIEWS) -> None:
    """Checks that fail fast, before any work: view count, empty or full-frame masks, and a
    visual hull that spans a volume.

    Raises:
        ReconstructionError: naming the problem (and the view).
    """
    n = dataset.num_views
    ntrain = len(dataset.train_idx)
    if n < min_views or ntrain < min_views:
        raise ReconstructionError(
            f"dataset {dataset.name}: {n} views ({ntrain} for training); at least {min_views} training views are needed"
        )
    cover = dataset.masks.reshape(n, -1).mean(axis=1)
    empty = np.flatnonzero(dataset.masks.reshape(n, -1).max(axis=1) < 0.5)
    if len(empty):
        raise ReconstructionError(f"dataset {dataset.name}: the masks of views {empty[:10].tolist()} are empty")
    full = np.flatnonzero(cover > 0.98)
    if len(full):
        raise ReconstructionError(
            f"dataset {dataset.name}: the masks of views {full[:10].tolist()} cover the whole frame; "
            "the object must be seen against background"
        )
    _check_visual_hull(dataset)


def _check_visual_hull(dataset, grid: int = 24) -> None:
    """Carve a coarse grid around the cameras' look-at region; fail if the carved set
    cannot span a 3D hull (e.g. too few or inconsistent views)."""
    from holowarp.camera import axes_focus, camera_center
    from holowarp.stages.tet_init import HullError, scaled_hull
    from holowarp.stages.topology import sample_masks

    views = dataset.train_idx
    centres = np.stack([camera_center(dataset.viewmats[v]) for v in views])
    # The region every camera looks at: around the point nearest to all optical axes,
    # within the smallest camera distance.
    focus = axes_focus(dataset.viewmats[views])
    r = float(np.min(np.linalg.norm(centres - focus, axis=1)))
    g = np.linspace(-r, r, grid)
    pts = np.stack(np.meshgrid(g, g, g, indexing="ij"), axis=-1).reshape(-1, 3) + focus
    inside = sample_masks(pts, dataset, views).min(axis=1) > 0.5
    try:
        scaled_hull(pts[inside])
    except HullError as e:
        raise ReconstructionError(
            f"dataset {dataset.name}: the masks' visual hull degenerates ({e}); "
            "the views do not agree on a 3D object (too few views, wrong poses or masks?)"
        ) from None


class _Bars:
    """One tqdm bar per stage, created on first use, with ETA and the current losses."""

    def __init__(self, enabled: bool):
        self.enabled = enabled
        self.bars: dict = {}

    def get(self, name: str, total: int, initial: int = 0):
        if not self.enabled:
            return None
        if name not in self.bars:
            from tqdm import tqdm

            self.bars[name] = tqdm(total=total, initial=initial, desc=name, unit="it", dynamic_ncols=True, leave=True)
        return self.bars[name]

    def close(self, name: str | None = None):
        for k in [name] if name else list(self.bars):
            b = self.bars.pop(k, None)
            if b is not None:
                b.close()


def _save_state(out_dir: Path, payload: dict) -> None:
    path = Path(out_dir) / STATE_FILE
    with atomic_path(path) as tmp:
        torch.save(payload, tmp)


def _load_state(out_dir: Path) -> dict | None:
    path = Path(out_dir) / STATE_FILE
    if not path.is_file():
        return None
    try:
        return torch.load(path, map_location="cpu", weights_only=False)
    except Exception as e:  # a truncated file cannot happen (atomic writes), a foreign one can
        raise ReconstructionError(f"{path}: unreadable checkpoint ({type(e).__name__}: {e})") from None


def _same_run(cfg: dict, saved: dict) -> list[str]:
    """Settings that differ between a checkpoint and the current request."""
    diff = []

    def walk(a, b, prefix=""):
        if isinstance(a, dict) and isinstance(b, dict):
            for k in set(a) | set(b):
                walk(a.get(k), b.get(k), f"{prefix}{k}.")
        elif a != b and not (isinstance(a, (list, tuple)) and list(a) == list(b or [])):
            diff.append(prefix.rstrip("."))

    walk(cfg, saved)
    return sorted(diff)


def reconstruct(
    dataset_path=None,
    out_dir="runs/holowarp",
    *,
    config: ReconConfig,
    device: str = "cpu",
    resume: bool = False,
    progress: bool = True,
) -> dict:
    """Reconstruct one connected, manifold, inversion-free tet mesh from multi-view images.

    Args:
        dataset_path: a NeRF-synthetic or NeuS/IDR folder; ``None`` synthesises the
            built-in bob into ``out_dir/data``.
        out_dir: output folder (see :mod:`holowarp.stages.export` for its contents).
        config: the :class:`holowarp.config.ReconConfig` (``holowarp.config.preset(...)``).
        device: ``"cpu"`` or ``"cuda[:N]"``.
        resume: continue from ``out_dir/checkpoints/state.pt``.
        progress: show progress bars.

    Returns:
        the report dict also written to ``out_dir/report.json``.

    Raises:
        ReconstructionError / DeviceError / DatasetError: before any work, with the reason.
    """
    from holowarp.data import DatasetError, load_dataset
    from holowarp.device import DeviceError, resolve_device

    t_start = time.perf_counter()
    try:
        device = resolve_device(device)
    except DeviceError as e:
        raise ReconstructionError(str(e)) from None
    config.schedule.validate()
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    saved = _load_state(out_dir)
    if saved is not None and not resume:
        raise ReconstructionError(
            f"{out_dir} already holds a reconstruction (checkpoints/state.pt); pass --resume to continue it "
            "or choose another --out"
        )
    cfg_dict = config.to_dict()
    if saved is not None:
        diff = _same_run(cfg_dict, saved["config"])
        if diff:
            raise ReconstructionError(
                f"{out_dir}: --resume with different settings than the checkpoint ({', '.join(diff[:8])})"
            )
        if saved.get("dataset_path") != (str(dataset_path) if dataset_path else None):
            raise ReconstructionError(f"{out_dir}: --resume with a different dataset than the checkpoint")

    # ---------------------------------------------------------------- data + preflight
    try:
        if dataset_path is None:
            data_dir = default_dataset(out_dir, resolution=config.resolution, device=device, progress=progress)
        else:
            data_dir = Path(dataset_path)
            if not data_dir.exists():
                raise ReconstructionError(f"dataset {data_dir}: no such folder")
        dataset = load_dataset(data_dir, res=config.resolution)
    except DatasetError as e:
        raise ReconstructionError(f"cannot read the dataset: {e}") from None
    preflight(dataset)

    _say(
        f"reconstructing {dataset.name}: {len(dataset.train_idx)} training / {len(dataset.test_idx)} test views at "
        f"{dataset.width}x{dataset.height}, preset {config.preset}, device {device}"
        + (", resuming" if saved is not None else ""),
        progress,
    )
    run = _Run(dataset, data_dir, dataset_path, out_dir, config, device, progress, saved)
    try:
        report = run.execute()
    finally:
        run.bars.close()
    report["seconds_total"] = float(run.state["seconds_before"] + time.perf_counter() - t_start)
    report["peak_rss_mb"] = round(_peak_rss_mb(), 1)
    atomic_write_json(out_dir / "report.json", report)
    return report


class _Run:
    """One reconstruction's mutable state and its stages (kept out of the public API)."""

    def __init__(self, dataset, data_dir, dataset_path, out_dir, config, device, progress, saved):
        self.dataset = dataset
        self.data_dir = Path(data_dir)
        self.dataset_path = dataset_path
        self.out = Path(out_dir)
        self.cfg = config
        self.device = torch.device(device)
        self.bars = _Bars(progress)
        self.progress = progress
        self.model = None
        self.saved = saved
        self._t0 = time.perf_counter()
        if saved is None:
            self.state = {
                "phase": "stage0",
                "main_iter": 0,
                "done": [],
                "stages": {},
                "history": {"topology": [], "gaussian": [], "geometry": []},
                "counts": {"prunes": []},
                "geometry": {"mesh_iter": 0},
                "block": None,
                "seconds_before": 0.0,
            }
        else:
            self.state = saved["state"]
            self.state["seconds_before"] = float(saved["state"].get("elapsed", 0.0))
            log.info("resuming %s at phase %s, main iteration %d", out_dir, self.state["phase"], self.state["main_iter"])

    # ------------------------------------------------------------------ bookkeeping
    def _stage_add(self, name: str, seconds: float, iterations: int = 0):
        s = self.state["stages"].setdefault(name, {"seconds": 0.0, "iterations": 0})
        s["seconds"] += float(seconds)
        s["iterations"] += int(iterations)

    def _checkpoint(self, extra: dict | None = None):
        self.state["elapsed"] = self.state["seconds_before"] + (time.perf_counter() - self._t0)
        payload = {
            "config": self.cfg.to_dict(),
            "dataset_path": str(self.dataset_path) if self.dataset_path else None,
            "state": self.state,
            "model": None if self.model is None else self.model.state_dict(),
        }
        if extra:
            payload.update(extra)
        _save_state(self.out, payload)

    # ------------------------------------------------------------------ stages
    def execute(self) -> dict:
        if self.state["phase"] == "stage0":
            self._stage0()
        if self.state["phase"] == "tet_init":
            self._tet_init()
        if self.state["phase"] == "main":
            self._main_loop()
        if self.state["phase"] == "cleanup":
            return self._finish()
        raise ReconstructionError(f"checkpoint in unknown phase {self.state['phase']!r}")

    def _stage0(self):
        from holowarp.gs2d import GS2DConfig, train_gs2d

        t0 = time.perf_counter()
        sch = self.cfg.schedule
        gcfg = GS2DConfig.for_iterations(sch.stage0_iters, dssim_weight=self.cfg.stage0.dssim_weight, seed=self.cfg.seed)
        res = train_gs2d(
            self.dataset, gcfg, self.out / "stage0", device=str(self.device), resume=True, progress=self.progress
        )
        self._stage_add("stage0", time.perf_counter() - t0, sch.stage0_iters)
        self.state["stage0"] = {k: res[k] for k in ("psnr_test", "gaussians", "iters") if k in res}
        self.state["phase"] = "tet_init"
        self._checkpoint()

    def _tet_init(self):
        from holowarp.gaussians import load_gaussians_ply
        from holowarp.stages.tet_init import HullError, initial_tetmesh
        from holowarp.stages.topology import init_colors, init_phi
        from holowarp.tetgs import TetGaussians

        t0 = time.perf_counter()
        _say(
            f"tetrahedralising the 1.1x convex hull of the stage-0 surfels with fTetWild "
            f"(edge length {self.cfg.tet_init.edge_length_fac} x bbox diagonal)",
            self.progress,
        )
        g = load_gaussians_ply(self.out / "stage0" / "gaussians.ply")
        try:
            mesh = initial_tetmesh(g["means"], g["opacities"], self.cfg.tet_init)
        except HullError as e:
            raise ReconstructionError(f"tetrahedral initialisation failed: {e}") from None
        tcfg = self.cfg.topology
        train = self.dataset.train_idx
        phi = init_phi(mesh, self.dataset, train, tcfg)
        colors = init_colors(mesh, self.dataset, train)
        self.model = TetGaussians(
            mesh,
            colors=colors,
            phi=phi,
            continuous_opacity=tcfg.continuous_opacity,
            kappa=tcfg.kappa_init,
            s=tcfg.s,
            kappa_clamp=tcfg.kappa_clamp,
            scale_factor=tcfg.scale_factor,
            device=self.device,
            seed=self.cfg.seed,
        )
        if not tcfg.continuous_opacity:
            # Ablation: independent per-tet opacities, started from the same field so the
            # comparison isolates the parameterisation (no shared vertices, no eik/smooth).
            self.model.free_opacity = False
            self.model.freeze_opacity_from_field()
        _say(f"initial tet mesh: {mesh.num_tets} tets, {mesh.num_vertices} vertices", self.progress)
        self.state["counts"]["tets_initial"] = mesh.num_tets
        self.state["counts"]["vertices_initial"] = mesh.num_vertices
        self._stage_add("tet_init", time.perf_counter() - t0, 0)
        self.state["phase"] = "main"
        self._checkpoint()

    def _load_model(self):
        from holowarp.tetgs import TetGaussians

        if self.model is None:
            self.model = TetGaussians.from_state_dict(self.saved["model"], device=self.device)

    def _tensors(self):
        ds = self.dataset
        dev = self.device
        bg = torch.zeros(3, device=dev)
        images = torch.as_tensor(ds.composite((0.0, 0.0, 0.0)), device=dev)
        masks = torch.as_tensor(ds.masks, device=dev)
        normals = torch.as_tensor(ds.normals, device=dev) if ds.normals is not None else None
        return bg, images, masks, normals

    def _main_loop(self):
        from holowarp.stages.geometry import GeometryState, run_geometry_block
        from holowarp.stages.topology import GaussianOptimizers, gaussian_step, prune

        self._load_model()
        sch, tcfg = self.cfg.schedule, self.cfg.topology
        bg, images, masks, normals = self._tensors()
        train = self.dataset.train_idx
        st = self.state
        first_prune_done = any(d.startswith("prune@") for d in st["done"])
        opts = GaussianOptimizers(self.model, tcfg, learn_scales=first_prune_done)
        if self.saved is not None and self.saved.get("optimizers") is not None:
            opts.load_state_dict(self.saved["optimizers"])
        edges = self._edges()
        gstate = GeometryState(mesh_iter=st["geometry"]["mesh_iter"], history=st["history"]["geometry"])
        total_mesh = len(sch.mesh_blocks_at) * sch.mesh_block_iters

        def ckpt(extra=None):
            st["geometry"]["mesh_iter"] = gstate.mesh_iter
            payload = {"optimizers": opts.state_dict()}
            if extra:
                payload.update(extra)
            self._checkpoint(payload)

        i = st["main_iter"]
        while i <= sch.main_iters:
            # ---- events scheduled at this iteration, in order: prune, then mesh block
            if i in sch.prune_at and f"prune@{i}" not in st["done"]:
                self._close_phase_bars()
                info = prune(self.model, tcfg)
                first = not first_prune_done
                if first:
                    self.model.reset_scales()
                    self.model.freeze_opacity_from_field()
                    first_prune_done = True
                info["iteration"] = i
                st["counts"]["prunes"].append(info)
                self._report_prune(info)
                opts = GaussianOptimizers(self.model, tcfg, learn_scales=True)
                edges = self._edges()
                st["done"].append(f"prune@{i}")
                ckpt()
            if i in sch.mesh_blocks_at and f"mesh@{i}" not in st["done"]:
                self._close_phase_bars()
                blk = st["block"] if (st["block"] and st["block"]["at"] == i) else None
                rest = blk["rest"] if blk else self.model.vertices.detach().cpu().numpy().astype(np.float64)
                start = blk["step"] if blk else 0
                bar = self.bars.get("geometry", total_mesh, gstate.mesh_iter)
                t0 = time.perf_counter()

                def block_ckpt(step, opt_state, _i=i, _rest=rest):
                    st["block"] = {"at": _i, "step": step, "rest": _rest, "opt": opt_state}
                    ckpt()

                summary = run_geometry_block(
                    self.model,
                    self.dataset,
                    train,
                    self.cfg.geometry,
                    block_iters=sch.mesh_block_iters,
                    total_mesh_iters=total_mesh,
                    state=gstate,
                    seed=self.cfg.seed,
                    start=start,
                    rest_vertices=rest,
                    optimizer_state=blk["opt"] if blk else None,
                    progress=bar,
                    checkpoint=block_ckpt,
                    checkpoint_every=self.cfg.checkpoint_every,
                )
                self._stage_add("geometry", time.perf_counter() - t0, summary["steps"])
                st.setdefault("geometry_blocks", []).append({"at": i, **{k: v for k, v in summary.items() if k != "final"}})
                st["block"] = None
                st["done"].append(f"mesh@{i}")
                if gstate.mesh_iter >= total_mesh:
                    self.bars.close("geometry")
                ckpt()
            if i >= sch.main_iters:
                break
            # ---- one Gaussian step
            phase = "topology" if i < sch.topology_until else "gaussian"
            total = sch.topology_until if phase == "topology" else sch.main_iters - sch.topology_until
            done_in_phase = i if phase == "topology" else i - sch.topology_until
            bar = self.bars.get(phase, total, done_in_phase)
            t0 = time.perf_counter()
            view = int(train[np.random.default_rng([self.cfg.seed, 0, i]).integers(len(train))])
            terms = gaussian_step(
                self.model,
                self.dataset,
                view,
                tcfg,
                opts,
                topology_phase=phase == "topology",
                edges=edges,
                images=images,
                masks=masks,
                normals=normals,
                background=bg,
            )
            self._stage_add(phase, time.perf_counter() - t0, 1)
            st["history"][phase].append({"iter": i, **terms})
            if bar is not None:
                bar.update(1)
                bar.set_postfix(loss=f"{terms['loss']:.4f}", rgb=f"{terms['rgb']:.4f}", mask=f"{terms['mask']:.4f}",
                                tets=self.model.num_tets, refresh=False)
            i += 1
            st["main_iter"] = i
            if i % self.cfg.checkpoint_every == 0:
                ckpt()
        self._close_phase_bars()
        st["phase"] = "cleanup"
        ckpt()

    def _close_phase_bars(self):
        self.bars.close("topology")
        self.bars.close("gaussian")

    def _edges(self):
        return torch.tensor(np.array(self.model.mesh().edges()), dtype=torch.int32, device=self.device)

    def _report_prune(self, info: dict):
        msg = (
            f"prune at iteration {info['iteration']}: {info['pruned']} tets below alpha "
            f"{self.cfg.topology.prune_alpha} removed, {info['tets_after']} remain"
        )
        if info.get("emptied"):
            msg = (
                f"prune at iteration {info['iteration']}: every tet is below alpha {self.cfg.topology.prune_alpha}; "
                "pruning would empty the mesh, so nothing was pruned"
            )
        elif info.get("removed_components"):
            msg += (
                f"; pruning split the mesh, kept the largest component and removed "
                f"{info['removed_components']} other component(s) ({info['tets_removed_by_component']} tets)"
            )
        _say(msg, self.progress)

    # ------------------------------------------------------------------ the end
    def _finish(self) -> dict:
        from holowarp.stages.cleanup import cleanup
        from holowarp.stages.export import (
            preview_cutaway,
            preview_losses,
            preview_test_views,
            render_test_views,
            write_outputs,
        )

        self._load_model()
        st = self.state
        t0 = time.perf_counter()
        mesh_before = self.model.mesh()
        clean, kept, cinfo = cleanup(mesh_before)
        # Surfels follow their tets; flipped tets keep their centroid, so nothing moves.
        self.model.keep(kept)
        # model.keep and cleanup both drop unused vertices in increasing id order, so the
        # numbering agrees; taking cleanup's tets also carries its flips over.
        if clean.num_vertices != self.model.num_vertices:
            raise AssertionError("cleanup and the surfel model disagree on the vertex set")
        self.model.tets = torch.tensor(np.array(clean.tets), dtype=torch.int64, device=self.device)
        self._stage_add("cleanup", time.perf_counter() - t0, 0)

        t0 = time.perf_counter()
        outputs = write_outputs(self.out, self.model, clean, name=self._object_name())
        ds = self.dataset
        test = ds.test_idx if len(ds.test_idx) else ds.train_idx[:4]
        bg = torch.zeros(3, device=self.device)
        renders = render_test_views(self.model, ds, test, background=bg)
        gts = list(ds.composite((0.0, 0.0, 0.0))[test])
        psnr, ssim = _image_metrics(renders, gts)
        prev = self.out / "previews"
        previews = {
            "test_views": preview_test_views(prev, renders, gts, test),
            "cutaway": preview_cutaway(prev / "cutaway_components.png", clean),
            "losses": preview_losses(prev / "losses.png", st["history"]),
        }
        self._stage_add("export", time.perf_counter() - t0, 0)

        metrics = None
        if ds.gt_mesh is not None and Path(ds.gt_mesh).is_file():
            from holowarp.metrics import evaluate_mesh

            t0 = time.perf_counter()
            metrics = evaluate_mesh(clean, ds.gt_mesh, dataset=ds, device=str(self.device))
            self._stage_add("evaluate", time.perf_counter() - t0, 0)

        man = clean.manifold()
        q = clean.quality_summary()
        report = {
            "preset": self.cfg.preset,
            "device": str(self.device),
            "dataset": str(self.data_dir),
            "resolution": [ds.height, ds.width],
            "ablations": {
                "continuous_opacity": self.cfg.topology.continuous_opacity,
                "uniform_biharmonic": self.cfg.geometry.uniform_biharmonic,
                "single_stage_hc": not self.cfg.geometry.two_stage_hc,
            },
            "seconds_total": None,
            "stages": st["stages"],
            "tets_initial": st["counts"].get("tets_initial"),
            "tets_final": clean.num_tets,
            "vertices_final": clean.num_vertices,
            "components": clean.num_components(),
            "manifold": bool(man["manifold"]),
            "genus": clean.genus(),
            "inverted_before_cleanup": cinfo["inverted_before_cleanup"],
            "flipped": cinfo["flipped"],
            "dropped": cinfo["dropped"],
            "cleanup": cinfo,
            "inverted_ratio": q["inverted_ratio"],
            "min_dihedral_mean": q["min_dihedral_mean"],
            "aspect_ratio_mean": q["aspect_ratio_mean"],
            "prunes": st["counts"]["prunes"],
            # Coherence of the pruning decisions (the paper's ablation measure): the most
            # face-connected pieces any prune's plain rule would have left.
            "raw_components_max": max((p.get("raw_components", 1) for p in st["counts"]["prunes"]), default=1),
            "geometry_blocks": st.get("geometry_blocks", []),
            "stage0": st.get("stage0"),
            "psnr_test": psnr,
            "ssim_test": ssim,
            "peak_rss_mb": None,
            "outputs": outputs,
            "previews": previews,
            "config": self.cfg.to_dict(),
        }
        if metrics is not None:
            report["metrics"] = metrics
        # No checkpoint here: the saved state stays the pre-cleanup one, so re-running a
        # finished (or interrupted-while-exporting) run with --resume redoes cleanup and
        # export from the same input and writes the same files.
        return report

    def _object_name(self) -> str:
        return "Bob" if self.dataset_path is None else (Path(self.data_dir).name or "Object")


def _say(msg: str, progress: bool):
    if progress:
        from tqdm import tqdm

        tqdm.write(msg)
    log.info(msg)


def _image_metrics(renders, gts) -> tuple[float, float]:
    """Mean PSNR (dB) and SSIM over test views."""
    from holowarp.losses import psnr, ssim

    ps, ss = [], []
    for r, g in zip(renders, gts):
        rt = torch.as_tensor(r)
        gt = torch.as_tensor(np.asarray(g, dtype=np.float32))
        ps.append(float(psnr(rt, gt)))
        ss.append(float(ssim(rt, gt)))
    return float(np.mean(ps)), float(np.mean(ss))
