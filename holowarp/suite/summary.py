"""The paper's tables over a suite (method.md §9 dataset-level rates, §11), holowarp and the
visual hull side by side, read from every object's files.

Per object and side (``holowarp``: ``recon/``, ``metrics.json``, ``sim/``; ``visual_hull``:
``hull/``, ``hull/metrics.json``, ``hull/sim/``): the evaluation metrics, PSNR/SSIM on the
test views (holowarp's report; the visual hull has no appearance, so none), and Sim-CD = the
mean of ``sim_chamfer`` over its times (method.md §10; per time as well).

Rates are over ALL objects of the suite, so a failure counts against a method: an object
whose side produced no tet mesh (its synth, hull or reconstruct step failed, or it has not
run yet) is a failure; the others are single- or multi-component, and the three rates add up
to 1. ``manifold_rate`` and ``genus_rate`` (objects whose genus matches the suite's
``genus``, over the objects that give one) are over all objects too. Means are over the
objects that have the value (``n`` says how many).
"""

from __future__ import annotations

import json
import math
from pathlib import Path

from holowarp.fileio import atomic_write_json, atomic_write_text

__all__ = ["SIDES", "MEAN_KEYS", "object_record", "summarise", "write_summary", "format_markdown"]

SIDES = {"holowarp": ("recon", "metrics.json", "sim"), "visual_hull": ("hull", "hull/metrics.json", "hull/sim")}
#: Per-object values averaged over the suite, in table order: (key, label, format).
MEAN_KEYS = (
    ("components", "components (mean)", "{:.2f}"),
    ("chamfer_l1", "Chamfer-L1", "{:.4f}"), ("chamfer_l2", "Chamfer-L2", "{:.5f}"),
    ("recall", "recall (tau 0.01)", "{:.3f}"), ("hausdorff", "Hausdorff", "{:.4f}"),
    ("volume_iou", "volume IoU", "{:.3f}"),
    ("min_dihedral_mean", "min dihedral mean (deg)", "{:.1f}"),
    ("min_dihedral_worst", "min dihedral worst (deg)", "{:.1f}"),
    ("aspect_ratio_mean", "aspect ratio mean", "{:.2f}"), ("inverted_ratio", "inverted ratio", "{:.4f}"),
    ("psnr", "PSNR test (dB)", "{:.2f}"), ("ssim", "SSIM test", "{:.4f}"), ("psnr_mask", "mask PSNR (dB)", "{:.2f}"),
    ("sim_cd", "Sim-CD", "{:.4f}"),
)
_METRIC_KEYS = ("components", "manifold", "genus", "tets", "chamfer_l1", "chamfer_l2", "recall", "hausdorff",
                "volume_iou", "f_score", "min_dihedral_mean", "min_dihedral_worst", "aspect_ratio_mean",
                "inverted_ratio", "psnr_mask")


def _read(path: Path):
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError):
        return None


def _num(v):
    """A finite float, or None (JSON writes NaN as the string "nan")."""
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        return None
    return float(v) if math.isfinite(v) else None


def _side(folder: Path, side: str, genus_expected) -> dict:
    mesh_dir, metrics_file, sim_dir = SIDES[side]
    has_mesh = (folder / mesh_dir / "tetmesh.vtu").is_file() and (folder / mesh_dir / "report.json").is_file()
    m = _read(folder / metrics_file) or {}
    rep = _read(folder / mesh_dir / "report.json") or {}
    sim = _read(folder / sim_dir / "report.json") or {}
    rec = {"mesh": has_mesh, **{k: m.get(k) for k in _METRIC_KEYS}}
    if has_mesh and rec["components"] is None:  # not evaluated (yet): topology from the step's own report
        src = rep if side == "holowarp" else rep.get("summary", {})
        rec.update(components=src.get("components"), manifold=src.get("manifold"), genus=src.get("genus"))
    rec["psnr"] = _num(rep.get("psnr_test")) if side == "holowarp" else None
    rec["ssim"] = _num(rep.get("ssim_test")) if side == "holowarp" else None
    sc = {t: _num(v) for t, v in (sim.get("sim_chamfer") or {}).items()}
    vals = [v for v in sc.values() if v is not None]
    rec["sim_chamfer"] = sc
    rec["sim_cd"] = sum(vals) / len(vals) if vals and len(vals) == len(sc) else None
    rec["genus_ok"] = None if genus_expected is None or rec["genus"] is None else rec["genus"] == genus_expected
    return rec


def object_record(folder: Path, spec) -> dict:
    """Everything the tables say about one object, from its files."""
    from holowarp.suite.work import read_status

    st = read_status(folder) or {"status": "pending", "errors": []}
    return {"name": spec.name, "status": st.get("status", "pending"), "errors": st.get("errors", []),
            "genus_expected": spec.genus, "device": spec.device, "seconds": st.get("seconds", {}),
            **{side: _side(folder, side, spec.genus) for side in SIDES}}


def _mean(values):
    vals = [v for v in (_num(x) for x in values) if v is not None]
    return {"mean": sum(vals) / len(vals) if vals else None, "n": len(vals)}


def _aggregate(records, side: str) -> dict:
    rows = [r[side] for r in records]
    n = len(rows)
    comps = [r["components"] for r in rows if r["mesh"]]
    expected = [rec for rec in records if rec["genus_expected"] is not None]
    out = {
        "objects": n,
        "with_mesh": sum(r["mesh"] for r in rows),
        "single_component_rate": sum(1 for c in comps if c == 1) / n,
        "multi_component_rate": sum(1 for c in comps if c is not None and c > 1) / n,
        "failure_rate": sum(1 for r in rows if not r["mesh"]) / n,
        "manifold_rate": sum(1 for r in rows if r["mesh"] and r["manifold"] is True) / n,
        "genus_rate": (sum(1 for rec in expected if rec[side]["genus_ok"]) / len(expected)) if expected else None,
        "mean": {k: _mean(r[k] for r in rows) for k, _, _ in MEAN_KEYS},
    }
    times = sorted({t for r in rows for t in r["sim_chamfer"]}, key=float)
    out["sim_chamfer"] = {t: _mean(r["sim_chamfer"].get(t) for r in rows) for t in times}
    return out


def summarise(out_root, suite) -> dict:
    """The suite's summary (module docstring) from the files under ``out_root``."""
    from holowarp.suite.work import object_folder

    records = [object_record(object_folder(out_root, o.name), o) for o in suite.objects]
    return {"suite": suite.source, "preset": suite.preset, "overrides": suite.overrides,
            "objects": len(records), "done": sum(r["status"] == "done" for r in records),
            "failed": sum(r["status"] == "failed" for r in records),
            **{side: _aggregate(records, side) for side in SIDES}, "per_object": records}


def _fmt(v, fmt: str = "{:.4f}") -> str:
    if v is None:
        return "-"
    if isinstance(v, bool):
        return "yes" if v else "no"
    return fmt.format(v)


def _rate(v) -> str:
    return "-" if v is None else f"{100.0 * v:.1f}%"


def _dataset_table(s: dict) -> list[str]:
    h, v = s["holowarp"], s["visual_hull"]
    lines = ["| | holowarp | visual hull |", "| --- | --- | --- |"]
    for key, label in (("single_component_rate", "single-component rate"), ("multi_component_rate",
                       "multi-component rate"), ("failure_rate", "failure rate"), ("manifold_rate", "manifold rate"),
                       ("genus_rate", "genus as expected")):
        lines.append(f"| {label} | {_rate(h[key])} | {_rate(v[key])} |")
    for key, label, fmt in MEAN_KEYS:
        a, b = h["mean"][key], v["mean"][key]
        lines.append(f"| {label} | {_fmt(a['mean'], fmt)} (n={a['n']}) | {_fmt(b['mean'], fmt)} (n={b['n']}) |")
    for t in sorted(set(h["sim_chamfer"]) | set(v["sim_chamfer"]), key=float):
        a, b = h["sim_chamfer"].get(t, {"mean": None}), v["sim_chamfer"].get(t, {"mean": None})
        lines.append(f"| Sim-CD at {t} s | {_fmt(a['mean'])} | {_fmt(b['mean'])} |")
    return lines


def _object_table(s: dict) -> list[str]:
    lines = ["| object | status | components | manifold | genus (expected) | Chamfer-L1 | volume IoU | "
             "min dihedral | PSNR | Sim-CD | hull Chamfer-L1 | hull volume IoU | hull Sim-CD |",
             "| --- " * 13 + "|"]
    for r in s["per_object"]:
        h, v = r["holowarp"], r["visual_hull"]
        genus = f"{_fmt(h['genus'], '{}')} ({_fmt(r['genus_expected'], '{}')})"
        lines.append(f"| {r['name']} | {r['status']} | {_fmt(h['components'], '{}')} | {_fmt(h['manifold'])} | "
                     f"{genus} | {_fmt(h['chamfer_l1'])} | {_fmt(h['volume_iou'], '{:.3f}')} | "
                     f"{_fmt(h['min_dihedral_mean'], '{:.1f}')} | {_fmt(h['psnr'], '{:.2f}')} | {_fmt(h['sim_cd'])} | "
                     f"{_fmt(v['chamfer_l1'])} | {_fmt(v['volume_iou'], '{:.3f}')} | {_fmt(v['sim_cd'])} |")
    return lines


def format_markdown(s: dict) -> str:
    """``summary.md``: the dataset table (holowarp and the visual hull side by side), the
    per-object table, and every recorded error."""
    lines = [f"# Suite {Path(s['suite']).name}", "",
             f"{s['objects']} objects ({s['done']} done, {s['failed']} failed), preset `{s['preset']}`"
             + (f", overrides `{json.dumps(s['overrides'])}`" if s["overrides"] else "") + ".", "",
             "Rates are over all objects (an object without a tet mesh is a failure); means over the objects "
             "that have the value (n). Distances in the evaluation frame (GT bbox largest side 1).", "",
             "## Dataset", "", *_dataset_table(s), "", "## Per object", "", *_object_table(s)]
    errors = [(r["name"], e) for r in s["per_object"] for e in r["errors"]]
    if errors:
        lines += ["", "## Errors", ""] + [f"- {name}, step `{e['step']}`: {e['error']}" for name, e in errors]
    return "\n".join(lines) + "\n"


def write_summary(out_root, suite) -> dict:
    """Write ``summary.json`` and ``summary.md`` into ``out_root``; returns the summary."""
    s = summarise(out_root, suite)
    atomic_write_json(Path(out_root) / "summary.json", s)
    atomic_write_text(Path(out_root) / "summary.md", format_markdown(s))
    return s
