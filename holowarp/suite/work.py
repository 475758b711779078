"""One object of a suite, step by step, in its own folder (see :mod:`holowarp.suite`).

Steps and the output that marks each done (a step whose output is there is skipped):

=================  ================================  ======================================
step               done when                         side
=================  ================================  ======================================
``data``           ``data/transforms_test.json``     both (synth, only for a mesh)
``hull``           ``hull/report.json``              visual hull
``reconstruct``    ``recon/report.json``             holowarp (resumes its own checkpoint)
``evaluate``       ``metrics.json``                  holowarp
``hull_evaluate``  ``hull/metrics.json``             visual hull
``reference``      ``reference/gt.vtu``              both simulations (the GT tetrahedralised once)
``simulate``       ``sim/report.json``               holowarp (drop, GT as reference)
``hull_simulate``  ``hull/sim/report.json``          visual hull
=================  ================================  ======================================

A failing step is recorded and skips the later steps of its side only; ``data`` and
``reference`` belong to both. ``status.json`` is rewritten atomically as the object goes
(``status`` running / done / failed, the current ``step``, ``errors`` as
``[{"step", "error"}]``, seconds per step), so a worker that dies leaves the step it was in.
"""

from __future__ import annotations

import json
import os
import time
import traceback
from pathlib import Path

from holowarp.errors import InputError, RunError, one_line
from holowarp.fileio import atomic_write_json

__all__ = ["STEPS", "run_object", "read_status", "object_folder"]

#: step -> (done marker relative to the object's folder, sides it serves).
STEPS = {
    "data": ("data/transforms_test.json", ("holowarp", "visual_hull")),
    "hull": ("hull/report.json", ("visual_hull",)),
    "reconstruct": ("recon/report.json", ("holowarp",)),
    "evaluate": ("metrics.json", ("holowarp",)),
    "hull_evaluate": ("hull/metrics.json", ("visual_hull",)),
    "reference": ("reference/gt.vtu", ("holowarp", "visual_hull")),
    "simulate": ("sim/report.json", ("holowarp",)),
    "hull_simulate": ("hull/sim/report.json", ("visual_hull",)),
}


def object_folder(out_root, name: str) -> Path:
    return Path(out_root) / name


def read_status(folder: Path) -> dict | None:
    """The object's ``status.json``, or None when it has none (or an unreadable one)."""
    try:
        return json.loads((Path(folder) / "status.json").read_text())
    except (OSError, ValueError):
        return None


class _Object:
    """The state of one object's run: its folder, the lazily loaded dataset, the status."""

    def __init__(self, spec, settings: dict, folder: Path, progress: bool):
        self.spec, self.settings, self.folder, self.progress = spec, settings, folder, progress
        self.data_dir = Path(spec.dataset) if spec.dataset else folder / "data"
        self.gt = spec.gt if spec.gt else (str(self.data_dir / "gt.obj") if spec.mesh else None)
        self._dataset = None
        self.status = {"name": spec.name, "status": "running", "step": None, "error": None, "errors": [],
                       "seconds": {}, "device": spec.device, "started": time.time()}
        self.failed: set = set()

    @property
    def cfg(self):
        from holowarp.suite.spec import recon_config

        return recon_config(self.settings["preset"], self.settings["overrides"])

    def dataset(self):
        """The dataset at the reconstruction's resolution (what holowarp sees), loaded once."""
        if self._dataset is None:
            from holowarp.data.loaders import load_dataset

            self._dataset = load_dataset(self.data_dir, res=self.cfg.resolution)
        return self._dataset

    def save(self) -> None:
        atomic_write_json(self.folder / "status.json", self.status)

    def step(self, name: str, fn) -> None:
        """Run step ``name`` unless done, not needed, or after a failure of every side it serves."""
        marker, sides = STEPS[name]
        if all(s in self.failed for s in sides) or (self.folder / marker).is_file():
            return
        self.status["step"] = name
        self.save()
        t0 = time.perf_counter()
        try:
            fn()
        except Exception as e:  # noqa: BLE001 -- a failed object is recorded; the others go on
            # holowarp's own errors say what and where; anything else also needs its type.
            msg = one_line(e if isinstance(e, (InputError, RunError)) else f"{type(e).__name__}: {e}")
            self.status["errors"].append({"step": name, "error": msg,
                                          "traceback": traceback.format_exc(limit=6).splitlines()[-6:]})
            self.failed.update(sides)
        self.status["seconds"][name] = time.perf_counter() - t0


def _synth(o: _Object) -> None:
    from holowarp.synthesis import synthesize

    st = o.settings["synth"]
    res = st["res"] if st["res"] is not None else o.cfg.resolution
    synthesize(o.spec.mesh, o.data_dir, views=st["views"], res=res, up_axis=o.spec.up_axis,
               supersample=st["supersample"], device=o.spec.device, resume=True, progress=o.progress)


def _hull(o: _Object) -> None:
    from holowarp.baselines.hull import VisualHullSettings, run_visual_hull

    run_visual_hull(o.dataset(), o.folder / "hull", settings=VisualHullSettings(**o.settings["hull"]),
                    device=o.spec.device, progress=o.progress)


def _reconstruct(o: _Object) -> None:
    from holowarp.pipeline import reconstruct_alone

    # resume=True continues recon/checkpoints/state.pt when a killed run left one (same settings).
    # Its own process: the hull's fTetWild call before it would change its mesh.
    reconstruct_alone(str(o.data_dir), o.folder / "recon", config=o.cfg, device=o.spec.device, resume=True,
                      progress=o.progress)


def _reference(o: _Object) -> None:
    from holowarp.mesh_io import write_tetmesh
    from holowarp.simulation import load_sim_mesh

    write_tetmesh(o.folder / "reference" / "gt.vtu", load_sim_mesh(o.gt, what="gt"))


def _tet_only_metrics(path: Path) -> dict:
    """Topology and tet quality of a mesh without a ground truth (the tet keys of
    :func:`holowarp.metrics.evaluate_mesh`)."""
    from holowarp.mesh_io import read_tetmesh

    m = read_tetmesh(path)
    q, oriented = m.quality_summary(), m.oriented()[0]
    return {"components": int(m.num_components()), "manifold": bool(oriented.manifold()["manifold"]),
            "genus": int(oriented.genus()), "tets": int(m.num_tets), "inverted_ratio": float(q["inverted_ratio"]),
            "min_dihedral_mean": float(q["min_dihedral_mean"]), "min_dihedral_worst": float(q["min_dihedral_worst"]),
            "aspect_ratio_mean": float(q["aspect_ratio_mean"])}


def _evaluate(o: _Object, mesh: Path, out: Path) -> None:
    from holowarp.metrics import evaluate_mesh

    if o.gt is None:
        metrics = _tet_only_metrics(mesh)
    else:
        st = o.settings["evaluate"]
        metrics = evaluate_mesh(mesh, o.gt, dataset=o.dataset(), num_samples=st["samples"],
                                volume_points=st["volume_points"], device=o.spec.device)
    atomic_write_json(out, metrics)


def _simulate(o: _Object, mesh: Path, out: Path) -> None:
    from holowarp.simulation import simulate

    ref = o.folder / "reference" / "gt.vtu" if o.gt is not None else None
    simulate(mesh, "drop", reference=ref, out_dir=out, device=o.spec.device, progress=o.progress,
             chamfer_samples=o.settings["simulate"]["chamfer_samples"])


def run_object(spec, settings: dict, out_root: str, *, progress: bool = False) -> dict:
    """Every step of one object (module docstring) in ``out_root/NAME``; returns its status.

    Sets torch to ``max(1, int(spec.num_cpus))`` threads: a Ray task (and the local
    executor) is given that many cores, and torch would otherwise spread over all of them.
    Never raises for a failing step: the error is in the returned status.
    """
    import torch

    torch.set_num_threads(max(1, int(spec.num_cpus)))
    folder = object_folder(out_root, spec.name)
    folder.mkdir(parents=True, exist_ok=True)
    o = _Object(spec, settings, folder, progress)
    recon, hull = folder / "recon" / "tetmesh.vtu", folder / "hull" / "tetmesh.vtu"
    if spec.mesh:
        o.step("data", lambda: _synth(o))
    o.step("hull", lambda: _hull(o))
    o.step("reconstruct", lambda: _reconstruct(o))
    o.step("evaluate", lambda: _evaluate(o, recon, folder / "metrics.json"))
    o.step("hull_evaluate", lambda: _evaluate(o, hull, folder / "hull" / "metrics.json"))
    if o.gt is not None:
        o.step("reference", lambda: _reference(o))
    o.step("simulate", lambda: _simulate(o, recon, folder / "sim"))
    o.step("hull_simulate", lambda: _simulate(o, hull, folder / "hull" / "sim"))
    errors = o.status["errors"]
    o.status.update(status="failed" if errors else "done", step=errors[0]["step"] if errors else None,
                    error=errors[0]["error"] if errors else None, finished=time.time(), pid=os.getpid())
    o.save()
    return o.status
