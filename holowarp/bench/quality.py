"""``python -m holowarp.bench quality [--objects ...] [--json]``: reconstruction quality against
the visual hull on the concavity suite (issue 12).

For every object: synthesise 120 views at 128² (method.md §2), build the visual hull
(carving, marching cubes, fTetWild) and reconstruct with the fast preset, then evaluate both
against the ground truth (method.md §9, plus ``f_score_005``, ``chamfer_l1_floor`` and
``concave_chamfer``) and print every metric of both, their ratios (holowarp / hull) and the
targets' pass/fail (issue 12's, and issue 13's angles: ``worst_dihedral_ge_10``,
``mean_dihedral_ge_40``). The objects are the procedural shapes of :mod:`holowarp.shapes` (bowl,
mug, dented box, star, plate) and the shared meshes spot, bob and fandisk.

Work goes to ``--work DIR`` (default ``runs/quality``); every step is skipped when its output
is already there, so an interrupted benchmark continues. ``--workers N`` runs N objects at a
time, each with one torch thread. Each reconstruction runs in a fresh interpreter, so its
mesh and its report's ``peak_rss_mb`` are those of ``python -m holowarp.reconstruct`` on the
same data and seed.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time
from pathlib import Path

__all__ = ["main", "build_parser", "OBJECTS", "run_object"]

SHARED = Path(__file__).resolve().parents[3] / "shared" / "data" / "meshes"
#: name -> (source, up axis, expected genus, has concave regions no silhouette sees)
OBJECTS = {
    "bowl": ("shape", "z", 0, True),
    "mug": ("shape", "z", 1, True),
    "dented_box": ("shape", "z", 0, True),
    "star": ("shape", "z", 0, True),
    "plate": ("shape", "z", 3, True),
    "spot": (SHARED / "spot" / "spot.obj", "y", 0, False),
    "bob": (SHARED / "bob" / "bob_tri.obj", "y", 1, False),
    "fandisk": (SHARED / "fandisk" / "fandisk.obj", "y", 0, False),
}
COMPARED = ("chamfer_l1", "chamfer_l2", "hausdorff", "precision", "recall", "f_score", "f_score_005",
            "precision_005", "recall_005", "normal_consistency", "volume_iou", "concave_chamfer", "edge_f1")
HIGHER_IS_BETTER = {"precision", "recall", "f_score", "f_score_005", "precision_005", "recall_005",
                    "normal_consistency", "volume_iou", "edge_f1"}


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="python -m holowarp.bench quality", description=__doc__.splitlines()[0])
    p.add_argument("--objects", nargs="+", default=list(OBJECTS), choices=list(OBJECTS), metavar="NAME",
                   help=f"objects to run (default all: {', '.join(OBJECTS)})")
    p.add_argument("--work", default="runs/quality", metavar="DIR", help="work folder (resumable)")
    p.add_argument("--res", type=int, default=128, help="image resolution (default 128)")
    p.add_argument("--views", type=int, default=120, help="views per object (default 120)")
    p.add_argument("--grid", type=int, default=128, help="visual-hull grid (default 128)")
    p.add_argument("--scale-iters", type=float, default=None, help="multiply the fast preset's iterations")
    p.add_argument("--tag", default="fast", help="name of the reconstruction folder (compare variants)")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="override a setting of the fast preset, e.g. topology.phi_init=depth_hull (repeatable)")
    p.add_argument("--workers", type=int, default=1, help="objects at a time (default 1)")
    p.add_argument("--device", default="cpu", help="cpu | cuda | cuda:N")
    p.add_argument("--json", action="store_true", help="print JSON only")
    return p


def _mesh_file(name: str, work: Path) -> tuple[Path, str]:
    from holowarp.shapes import write_shape

    src, up, _, _ = OBJECTS[name]
    if src == "shape":
        path = work / name / f"{name}.obj"
        if not path.is_file():
            write_shape(name, path)
        return path, up
    return Path(src), up


def apply_overrides(cfg, overrides):
    """``cfg`` with dotted ``section.field=value`` overrides applied (values parsed as JSON
    when they parse, else kept as strings; a value must fit the setting's type, so
    ``enabled=False`` is a bool and ``steps=ten`` an error)."""
    from dataclasses import fields, is_dataclass, replace

    for item in overrides:
        key, _, raw = item.partition("=")
        try:
            value = json.loads(raw)
        except json.JSONDecodeError:
            value = raw
        parts = key.split(".")
        if len(parts) > 2 or not all(parts) or not hasattr(cfg, parts[0]):
            raise ValueError(f"--set {item}: expected SECTION.SETTING=VALUE or SETTING=VALUE of the fast preset")
        if len(parts) == 1:
            cfg = replace(cfg, **{parts[0]: _typed(item, getattr(cfg, parts[0]), value)})
        else:
            sec = getattr(cfg, parts[0])
            if not is_dataclass(sec) or parts[1] not in {f.name for f in fields(sec)}:
                raise ValueError(f"--set {item}: {parts[0]} has no setting {parts[1]!r}")
            value = _typed(item, getattr(sec, parts[1]), value)
            cfg = replace(cfg, **{parts[0]: replace(sec, **{parts[1]: tuple(value) if isinstance(value, list) else value})})
    return cfg


def _typed(item: str, current, value):
    """``value`` checked against the type of the setting's ``current`` value: a bool setting
    takes true/false in any case (a string would be truthy), a number a number."""
    if isinstance(current, bool):
        if isinstance(value, str) and value.lower() in ("true", "false"):
            return value.lower() == "true"
        if not isinstance(value, bool):
            raise ValueError(f"--set {item}: expected true or false")
    elif isinstance(current, (int, float)) and (isinstance(value, (str, bool)) or value is None):
        raise ValueError(f"--set {item}: expected a number")
    return value


def run_object(name: str, work: str, *, res: int, views: int, grid: int, scale_iters, tag: str, device: str,
               overrides=()) -> dict:
    """Synthesise, hull, reconstruct and evaluate one object (each step skipped if done)."""
    import torch

    torch.set_num_threads(1)
    from dataclasses import replace

    from holowarp.baselines.hull import VisualHullSettings, run_visual_hull
    from holowarp.config import preset
    from holowarp.metrics import evaluate_mesh
    from holowarp.pipeline import reconstruct_alone
    from holowarp.synthesis import synthesize

    root = Path(work) / name
    data, vh, rec = root / f"data{res}", root / f"hull{res}", root / f"{tag}{res}"
    mesh, up = _mesh_file(name, Path(work))
    if not (data / "transforms_test.json").is_file():
        synthesize(mesh, data, views=views, res=res, up_axis=up, resume=True, progress=False, device=device)
    t0 = time.perf_counter()
    if not (vh / "report.json").is_file():
        run_visual_hull(data, vh, settings=VisualHullSettings(grid=grid), device=device, progress=False)
    t_vh = time.perf_counter() - t0
    if not (rec / "report.json").is_file():
        cfg = replace(preset("fast"), resolution=res)
        cfg = cfg.scaled(scale_iters) if scale_iters else cfg
        cfg = apply_overrides(cfg, overrides)
        reconstruct_alone(data, rec, config=cfg, device=device, resume=(rec / "checkpoints").is_dir(),
                          progress=False)
    rep = json.loads((rec / "report.json").read_text())
    out = {"object": name, "genus_expected": OBJECTS[name][2], "concave": OBJECTS[name][3], "seconds_hull": t_vh,
           "seconds_reconstruct": rep["seconds_total"]}
    for side, path in (("hull", vh / "tetmesh.vtu"), ("holowarp", rec / "tetmesh.vtu")):
        out[side] = evaluate_mesh(path, data / "gt.obj", device=device)
    return out


def _ratios(row: dict) -> dict:
    r = {}
    for k in COMPARED:
        a, b = row["holowarp"].get(k), row["hull"].get(k)
        if isinstance(a, (int, float)) and isinstance(b, (int, float)) and math.isfinite(a) and math.isfinite(b) and b:
            r[k] = a / b
    floor = row["holowarp"]["chamfer_l1_floor"]
    excess_h, excess_v = row["holowarp"]["chamfer_l1"] - floor, row["hull"]["chamfer_l1"] - floor
    if excess_v > 0:
        r["chamfer_l1_above_floor"] = excess_h / excess_v
    return r


def _targets(row: dict, ratios: dict) -> dict:
    """Issue 12's targets for one object, and issue 13's element-quality targets (worst
    minimum dihedral >= 10°, mean >= 40°), which any change upstream of §7b can undo: True/False
    each."""
    h, v = row["holowarp"], row["hull"]
    t = {
        "one_component": h["components"] == 1,
        "exact_genus": h["genus"] == row["genus_expected"],
        "no_sealed_void": h.get("boundary_shells") == 1,
        "manifold": bool(h["manifold"]),
        "no_inverted": h["inverted_ratio"] == 0,
        "iou_ge_hull": h["volume_iou"] >= v["volume_iou"],
        "f_score_005_ge_hull": h["f_score_005"] >= v["f_score_005"],
        "normal_consistency_ge_hull": h["normal_consistency"] >= v["normal_consistency"],
        "hausdorff_le_hull": h["hausdorff"] <= v["hausdorff"],
        "worst_dihedral_ge_10": h["min_dihedral_worst"] >= 10.0,
        "mean_dihedral_ge_40": h["min_dihedral_mean"] >= 40.0,
    }
    if row["concave"]:
        t["concave_chamfer_le_0.6_hull"] = ratios.get("concave_chamfer", math.inf) <= 0.6
        t["chamfer_le_0.8_hull"] = ratios.get("chamfer_l1", math.inf) <= 0.8
    elif row["object"] in ("spot", "bob"):
        t["chamfer_above_floor_le_0.8_hull"] = ratios.get("chamfer_l1_above_floor", math.inf) <= 0.8
    return t


def _input_error(args) -> str | None:
    """What makes the request unusable, checked before any work (a missing shared mesh used
    to surface as a traceback after the objects before it had run for an hour), or None."""
    from holowarp.config import preset

    for name in args.objects:
        src = OBJECTS[name][0]
        if src != "shape" and not Path(src).is_file():
            return (f"--objects {name}: {src}: no such file (the suite reads the shared test meshes from "
                    f"{SHARED}, beside the checkout)")
    try:
        cfg = apply_overrides(preset("fast"), tuple(args.set))
        # Stage 0's settings and the schedule are checked when a run starts, not when they
        # are set; checked here too, so a bad --set stops the suite before its first hull.
        cfg.stage0.validate()
        cfg.schedule.validate()
    except (TypeError, ValueError) as e:
        return str(e).splitlines()[0]
    return None


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    from holowarp.device import resolve_device
    from holowarp.fileio import check_output_dir

    problem = _input_error(args)
    if problem is not None:
        print(f"error: {problem}", file=sys.stderr)
        return 2

    device = resolve_device(args.device)
    work = check_output_dir(args.work, what="--work")
    kw = dict(res=args.res, views=args.views, grid=args.grid, scale_iters=args.scale_iters, tag=args.tag, device=device,
              overrides=tuple(args.set))
    t0 = time.perf_counter()
    if args.workers > 1:
        from concurrent.futures import ProcessPoolExecutor

        os.environ["OMP_NUM_THREADS"] = "1"
        from functools import partial

        with ProcessPoolExecutor(args.workers) as ex:
            rows = list(ex.map(partial(run_object, work=str(work), **kw), args.objects))
    else:
        rows = [run_object(n, str(work), **kw) for n in args.objects]
    for row in rows:
        row["ratios"] = _ratios(row)
        row["targets"] = _targets(row, row["ratios"])
    out = {"benchmark": "quality", "device": device, "resolution": args.res, "views": args.views, "tag": args.tag,
           "seconds": time.perf_counter() - t0, "objects": rows}
    if args.json:
        print(json.dumps(out, indent=2, default=str))
    else:
        for row in rows:
            fails = [k for k, ok in row["targets"].items() if not ok]
            print(f"{row['object']:>10}: " + ", ".join(f"{k} {v:.3f}" for k, v in row["ratios"].items())
                  + (f"  FAIL {fails}" if fails else "  all targets met"))
    return 0
