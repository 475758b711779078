"""The suite file of a dataset run (issue 18; method.md §9 dataset-level rates, §11
"dataset-level evaluation"): the objects and the settings they share.

A suite file (TOML) lists the objects and the settings they share::

    preset = "fast"                 # or "paper"
    [overrides]                     # optional: the reconstruct flags, by their long names
    res = 128
    scale_iters = 1.0
    [resources]                     # optional: what one object asks of the executor
    num_cpus = 1                    # CPUs (and torch threads) per object
    num_gpus = 0                    # > 0: the object runs on CUDA
    [synth]                         # optional: views = 120, res = the reconstruction's, supersample = 2, up_axis = "y"
    [hull]                          # optional: grid = 128, edge_length_fac = 0.03, max_surface_faces = 12000
    [evaluate]                      # optional: samples = 100000, volume_points = 100000 (method.md §9)
    [simulate]                      # optional: chamfer_samples = 100000
    [[objects]]
    name = "bob"                    # optional: default the mesh file stem or the dataset folder name
    mesh = "path/to/bob.obj"        # synthesised with holowarp.synth; or: dataset = "path/to/dataset"
    up_axis = "y"                   # optional, with mesh: the mesh's up axis (default [synth] up_axis)
    genus = 1                       # optional: checked in the summary
    gt = "path/to/gt.obj"           # optional with dataset (default: the dataset's gt.obj); implied with mesh
    resources = { num_cpus = 2 }    # optional: this object's own request

Override keys are the long flags of ``python -m holowarp.reconstruct`` with ``_`` for ``-``:
``res``, ``scale_iters``, ``edge_length``, ``seed``, ``no_continuous_opacity``,
``uniform_biharmonic``, ``single_stage_hc``. Relative paths are relative to the suite file.

Each object works in ``OUT/NAME/``: ``data/`` (synth, when it has a mesh), ``hull/`` (the
visual-hull baseline, with ``hull/metrics.json`` and ``hull/sim/``), ``recon/``
(reconstruct), ``metrics.json`` (evaluate), ``reference/gt.vtu`` (the ground truth
tetrahedralised once for both simulations), ``sim/`` (simulate drop with the ground truth as
reference) and ``status.json``. Every step skips itself when its output is there, and
reconstruct resumes from its checkpoint, so a killed run continues where each object was.
A failing step records ``{"step", "error"}`` in ``status.json``; the other side's steps
(holowarp or the visual hull) and the other objects go on.

Executors: ``"local"`` runs the objects one after the other in this process;
``"ray"`` submits one Ray task per object, with the object's CPU/GPU request, to a local
Ray runtime sized to this machine's cores or to an existing cluster (``ray_address``).
:func:`summarise` then reads every object's files into ``summary.json`` and ``summary.md``.
"""

from __future__ import annotations

import math
import os
import re
from dataclasses import dataclass, field, replace
from pathlib import Path

from holowarp.errors import InputError, one_line
from holowarp.fileio import check_input_file

__all__ = ["SuiteError", "ObjectSpec", "Suite", "load_suite", "recon_config",
           "OVERRIDE_KEYS", "EXECUTORS"]

EXECUTORS = ("local", "ray")
#: The reconstruct flags a suite may override, with their value types.
OVERRIDE_KEYS = {"res": int, "scale_iters": float, "edge_length": float, "seed": int, "no_continuous_opacity": bool,
                 "uniform_biharmonic": bool, "single_stage_hc": bool}
_TOP_KEYS = ("preset", "overrides", "resources", "synth", "hull", "evaluate", "simulate", "objects")
_OBJECT_KEYS = ("name", "mesh", "dataset", "gt", "genus", "up_axis", "resources")
#: Shared step settings: section -> {key: (type, default, lowest allowed)}; res None = the reconstruction's.
_SECTIONS = {
    "resources": {"num_cpus": (float, 1.0, 0.0), "num_gpus": (float, 0.0, 0.0)},
    "synth": {"views": (int, 120, 1), "res": (int, None, 8), "supersample": (int, 2, 1), "up_axis": (str, "y", None)},
    "hull": {"grid": (int, 128, 8), "edge_length_fac": (float, 0.03, 0.0), "max_surface_faces": (int, 12_000, 100)},
    "evaluate": {"samples": (int, 100_000, 1), "volume_points": (int, 100_000, 1)},
    "simulate": {"chamfer_samples": (int, 100_000, 1)},
}
_NAME = re.compile(r"^[A-Za-z0-9_][A-Za-z0-9_.-]*$")
#: The files of the run's own folder, which no object folder may take.
_RESERVED = ("suite.json", "summary.json", "summary.md")


class SuiteError(InputError):
    """A suite file (or a run's arguments) cannot be used; the message names the file and key."""


@dataclass(frozen=True)
class ObjectSpec:
    """One object of a suite, checked; paths absolute."""

    name: str
    mesh: str | None = None  # surface to synthesise
    dataset: str | None = None  # existing dataset folder
    gt: str | None = None  # ground-truth surface (None: none known)
    genus: int | None = None  # expected genus
    up_axis: str = "y"  # of the mesh
    num_cpus: float = 1.0
    num_gpus: float = 0.0

    @property
    def device(self) -> str:
        """``"cuda"`` when the object asks for a GPU, else ``"cpu"``."""
        return "cuda" if self.num_gpus > 0 else "cpu"


@dataclass(frozen=True)
class Suite:
    """A checked suite file: the shared settings and the objects."""

    source: str
    preset: str = "fast"
    overrides: dict = field(default_factory=dict)
    steps: dict = field(default_factory=dict)  # section -> {key: value}, every key of _SECTIONS filled in
    objects: tuple = ()

    def settings(self) -> dict:
        """What every object's work depends on (compared on resume)."""
        return {"preset": self.preset, "overrides": dict(self.overrides),
                **{k: dict(v) for k, v in self.steps.items() if k != "resources"}}


def _value(src, where: str, v, kind, lo=None):
    """``v`` checked as ``kind`` (bool is not a number; an int is a float), >= ``lo``."""
    ok = isinstance(v, kind) and not (kind is not bool and isinstance(v, bool))
    if kind is float:
        ok = isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)
    names = {int: "an integer", float: "a number", bool: "true or false", str: "a string"}
    if not ok:
        raise SuiteError(f"{src}: {where} = {v!r}: expected {names[kind]}")
    if lo is not None and v < lo:
        raise SuiteError(f"{src}: {where} = {v!r}: must be >= {lo:g}")
    return float(v) if kind is float else v


def _table(src, where: str, t, allowed) -> dict:
    if not isinstance(t, dict):
        raise SuiteError(f"{src}: {where}: expected a table, got {type(t).__name__}")
    unknown = sorted(set(t) - set(allowed))
    if unknown:
        raise SuiteError(f"{src}: {where}.{unknown[0]}: unknown key (known: {', '.join(allowed)})")
    return t


def _section(src, name: str, t) -> dict:
    spec = _SECTIONS[name]
    t = _table(src, f"[{name}]", t, spec)
    out = {k: (_value(src, f"{name}.{k}", t[k], kind, lo) if k in t else default)
           for k, (kind, default, lo) in spec.items()}
    if name == "synth" and out["up_axis"] not in ("y", "z"):
        raise SuiteError(f"{src}: synth.up_axis = {out['up_axis']!r}: expected 'y' or 'z'")
    if name == "hull" and not 0 < out["edge_length_fac"] < 1:
        raise SuiteError(f"{src}: hull.edge_length_fac = {out['edge_length_fac']:g}: must lie in (0, 1)")
    if name == "resources" and not out["num_cpus"] > 0:
        raise SuiteError(f"{src}: resources.num_cpus = {out['num_cpus']:g}: must be > 0")
    return out


def recon_config(preset_name: str, overrides: dict, *, source: str = "suite"):
    """The :class:`holowarp.config.ReconConfig` of ``preset_name`` with ``overrides`` (the
    reconstruct command's long flags, ``_`` for ``-``), checked as the command checks them;
    errors name ``source`` and the key."""
    from holowarp.config import preset

    for k, v in overrides.items():
        if k not in OVERRIDE_KEYS:
            raise SuiteError(f"{source}: overrides.{k}: unknown key (known: {', '.join(OVERRIDE_KEYS)})")
        _value(source, f"overrides.{k}", v, OVERRIDE_KEYS[k])
    ov = overrides
    cfg = preset(preset_name).with_ablations(continuous_opacity=not ov.get("no_continuous_opacity", False),
                                             uniform_biharmonic=ov.get("uniform_biharmonic", False),
                                             single_stage_hc=ov.get("single_stage_hc", False))
    if "res" in ov:
        if ov["res"] < 16:
            raise SuiteError(f"{source}: overrides.res = {ov['res']}: at least 16 pixels")
        cfg = replace(cfg, resolution=ov["res"])
    if "scale_iters" in ov:
        if not ov["scale_iters"] > 0:
            raise SuiteError(f"{source}: overrides.scale_iters = {ov['scale_iters']}: must be > 0")
        cfg = cfg.scaled(float(ov["scale_iters"]))
    if "edge_length" in ov:
        if not 0 < ov["edge_length"] < 1:
            raise SuiteError(f"{source}: overrides.edge_length = {ov['edge_length']}: must lie in (0, 1)")
        cfg = replace(cfg, tet_init=replace(cfg.tet_init, edge_length_fac=float(ov["edge_length"])))
    if "seed" in ov:
        cfg = replace(cfg, seed=ov["seed"])
    return cfg


def _object(src: Path, i: int, t, steps: dict) -> ObjectSpec:
    where = f"objects[{i}]"
    t = _table(src, where, t, _OBJECT_KEYS)
    if ("mesh" in t) == ("dataset" in t):
        raise SuiteError(f"{src}: {where}: give exactly one of mesh = \"path\" or dataset = \"path\"")
    if "mesh" in t and "gt" in t:
        raise SuiteError(f"{src}: {where}.gt: implied by mesh (the synthesised data/gt.obj); give gt with dataset only")
    if "dataset" in t and "up_axis" in t:
        raise SuiteError(f"{src}: {where}.up_axis: only for a mesh to synthesise")
    paths = {}
    for key in ("mesh", "dataset", "gt"):
        if key in t:
            p = src.parent / _value(src, f"{where}.{key}", t[key], str)
            if key == "dataset":
                if not p.is_dir():
                    raise SuiteError(f"{src}: {where}.dataset: {p}: no such folder")
            else:
                try:
                    check_input_file(p, error=SuiteError, what="surface file")
                except SuiteError as e:
                    raise SuiteError(f"{src}: {where}.{key}: {e}") from None
            paths[key] = os.path.abspath(p)
    if "dataset" in paths and "gt" not in paths and (Path(paths["dataset"]) / "gt.obj").is_file():
        paths["gt"] = str(Path(paths["dataset"]) / "gt.obj")
    default = Path(paths["mesh"]).stem if "mesh" in paths else Path(paths["dataset"]).name
    name = _value(src, f"{where}.name", t.get("name", default), str)
    if not _NAME.match(name) or name in _RESERVED:
        raise SuiteError(f"{src}: {where}.name = {name!r}: expected letters, digits, '_', '.', '-' (it names a folder), "
                         f"other than {', '.join(_RESERVED)}")
    up = _value(src, f"{where}.up_axis", t.get("up_axis", steps["synth"]["up_axis"]), str)
    if up not in ("y", "z"):
        raise SuiteError(f"{src}: {where}.up_axis = {up!r}: expected 'y' or 'z'")
    genus = _value(src, f"{where}.genus", t["genus"], int, 0) if "genus" in t else None
    res = dict(steps["resources"])
    if "resources" in t:
        own = _table(src, f"{where}.resources", t["resources"], _SECTIONS["resources"])
        res.update({k: _value(src, f"{where}.resources.{k}", v, float, 0.0) for k, v in own.items()})
        if not res["num_cpus"] > 0:
            raise SuiteError(f"{src}: {where}.resources.num_cpus = {res['num_cpus']:g}: must be > 0")
    return ObjectSpec(name=name, mesh=paths.get("mesh"), dataset=paths.get("dataset"), gt=paths.get("gt"),
                      genus=genus, up_axis=up if "mesh" in paths else "y", **res)


def load_suite(path: str | os.PathLike) -> Suite:
    """The checked suite of a suite file (module docstring); every error is one line naming
    the file and the key, raised before any work (:class:`SuiteError`)."""
    try:
        import tomllib
    except ModuleNotFoundError:  # Python 3.10
        import tomli as tomllib

    src = check_input_file(path, error=SuiteError, what="suite file")
    try:
        data = tomllib.loads(src.read_text(encoding="utf-8"))
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as e:
        raise SuiteError(f"{src}: not valid TOML ({one_line(e)})") from None
    _table(src, "suite", data, _TOP_KEYS)
    preset_name = data.get("preset", "fast")
    if preset_name not in ("fast", "paper"):
        raise SuiteError(f"{src}: preset = {preset_name!r}: expected 'fast' or 'paper'")
    overrides = _table(src, "[overrides]", data.get("overrides", {}), OVERRIDE_KEYS)
    recon_config(preset_name, overrides, source=str(src))  # every override checked now
    steps = {name: _section(src, name, data.get(name, {})) for name in _SECTIONS}
    raw = data.get("objects")
    if not isinstance(raw, list) or not raw:
        raise SuiteError(f"{src}: objects: expected one or more [[objects]] tables")
    objects, seen = [], {}
    for i, t in enumerate(raw):
        o = _object(src, i, t, steps)
        if o.name in seen:
            raise SuiteError(f"{src}: objects[{i}].name: {o.name!r} is already the name of objects[{seen[o.name]}]")
        seen[o.name] = i
        objects.append(o)
    return Suite(source=str(src.resolve()), preset=preset_name, overrides=dict(overrides), steps=steps,
                 objects=tuple(objects))
