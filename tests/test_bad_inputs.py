"""A corpus of broken inputs across every command (issue 15).

Each case runs a command's ``main`` and asserts three things:

1. a non-zero exit;
2. exactly one line on stderr, ``error: ...``, naming the file or argument at fault;
3. a previous good output in the target folder is byte-identical afterwards.

Cases are grouped by defect class (``CLASSES``); a test at the end counts them per class.
"""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[1]

CLASSES = ("silent wrong result", "output path", "raw traceback", "vague error", "simulation", "format")


@dataclass
class Case:
    """One broken request: ``cmd`` is a command module, ``argv`` uses ``{D}`` (a good dataset),
    ``{M}`` (a good tet mesh), ``{S}`` (a good surface), ``{T}`` (this case's folder) and
    ``{O}`` (the target output folder, which holds a previous good output)."""

    cls: str
    name: str
    cmd: str
    argv: list
    names: str  # what the one-line error must mention
    setup: object = None  # callable(T: Path) writing the case's bad files
    subprocess_prefix: list = field(default_factory=list)  # e.g. setpriv, for unwritable folders


def _write(path: Path, data) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    (path.write_bytes if isinstance(data, bytes) else path.write_text)(data)
    return path


# ------------------------------------------------------------------------------ fixtures


@pytest.fixture(scope="module")
def world(tmp_path_factory):
    """A good dataset (NeRF-synthetic, 12 views at 16x16), a good tet mesh and a good surface."""
    import trimesh

    from holowarp import write_tetmesh
    from holowarp.primitives import box_tetmesh
    from holowarp.synthesis import synthesize

    root = tmp_path_factory.mktemp("world")
    trimesh.creation.icosphere(subdivisions=2, radius=0.5).export(root / "ball.obj")
    synthesize(root / "ball.obj", root / "data", views=12, res=16, up_axis="z", supersample=1, progress=False)
    mesh = box_tetmesh((2, 2, 2))
    write_tetmesh(root / "box.vtu", mesh)
    return {"D": root / "data", "M": root / "box.vtu", "S": root / "ball.obj", "mesh": mesh}


def _nerf_copy(world, T: Path, edit) -> Path:
    """A copy of the good dataset with ``edit(transforms_train_dict)`` applied."""
    d = T / "bad_data"
    shutil.copytree(world["D"], d)
    doc = json.loads((d / "transforms_train.json").read_text())
    edit(doc)
    (d / "transforms_train.json").write_text(json.dumps(doc))
    return d


def _neus(T: Path, *, mask_names, image_names=None) -> Path:
    """A small NeuS/IDR folder (cameras on a circle looking at the origin)."""
    from PIL import Image

    from holowarp.camera import intrinsics_from_fov, look_at

    d = T / "neus"
    n = len(mask_names)
    image_names = image_names or [f"{i:06d}.png" for i in range(n)]
    (d / "image").mkdir(parents=True)
    (d / "mask").mkdir()
    K = intrinsics_from_fov(0.7, 16, 16)
    mats = {}
    for i, name in enumerate(image_names):
        a = 2 * np.pi * i / n
        V = look_at(np.array([2.5 * np.cos(a), 2.5 * np.sin(a), 0.5]))
        P = np.eye(4)
        P[:3, :4] = (K - np.array([[0, 0, 0.5], [0, 0, 0.5], [0, 0, 0]])) @ V[:3, :4]
        mats[f"world_mat_{i}"] = P
        Image.fromarray(np.full((16, 16, 3), 128, np.uint8)).save(d / "image" / name)
    for name in mask_names:
        m = np.zeros((16, 16), np.uint8)
        m[4:12, 4:12] = 255
        Image.fromarray(m).save(d / "mask" / name)
    np.savez(d / "cameras_sphere.npz", **mats)
    return d


def _npz_mesh(T: Path, vertices, tets, name="bad.npz") -> Path:
    np.savez(T / name, vertices=np.asarray(vertices, float), tets=np.asarray(tets))
    return T / name


def _mixed(world, T):
    m = world["mesh"]
    t = m.tets.copy()
    t[:3, [2, 3]] = t[:3, [3, 2]]
    return _npz_mesh(T, m.vertices, t, "mixed.npz")


def _zero_volume(world, T):
    m = world["mesh"]
    v = m.vertices.copy()
    v[m.tets[0]] = v[m.tets[0][0]] + np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0]]) * 0.1  # a flat tet
    return _npz_mesh(T, v, m.tets, "flat.npz")


def _nan_vertex(world, T):
    m = world["mesh"]
    v = m.vertices.copy()
    v[3] = np.nan
    return _npz_mesh(T, v, m.tets, "nan.npz")


def _nan_obj(T):
    return _write(T / "nan.obj", "v 0 0 0\nv 1 0 0\nv 0 1 0\nv nan 0 1\nf 1 2 3\nf 1 2 4\nf 2 3 4\nf 1 3 4\n")


def _garbage_ckpt(T, O, name):
    _write(O / name, b"\x00\x01 not a checkpoint at all")


CASES = [
    # ------------------------------------------------------------------ silent wrong results
    Case("silent wrong result", "mixed orientation", "convert", ["{T}/mixed.npz", "{O}/out.vtu"], "mixed orientation",
         setup=lambda w, T, O: _mixed(w, T)),
    Case("silent wrong result", "zero-volume tet", "convert", ["{T}/flat.npz", "{O}/out.vtu"], "zero volume",
         setup=lambda w, T, O: _zero_volume(w, T)),
    Case("silent wrong result", "no tets", "convert", ["{T}/empty.npz", "{O}/out.vtu"], "empty.npz",
         setup=lambda w, T, O: _npz_mesh(T, np.zeros((4, 3)), np.zeros((0, 4), int), "empty.npz")),
    Case("silent wrong result", "youngs modulus 0", "convert", ["{M}", "{O}/out.usda", "--youngs-modulus", "0"],
         "youngs_modulus"),
    Case("silent wrong result", "density 0", "convert", ["{M}", "{O}/out.usda", "--density", "0"], "density"),
    Case("silent wrong result", "poisson 0.5", "convert", ["{M}", "{O}/out.usda", "--poissons-ratio", "0.5"],
         "poissons_ratio"),
    Case("silent wrong result", "poisson negative", "convert", ["{M}", "{O}/out.usda", "--poissons-ratio", "-0.1"],
         "poissons_ratio"),
    Case("silent wrong result", "neus masks numbered apart", "gs2d", ["{T}/neus", "--out", "{O}", "--iters", "1"],
         "mask", setup=lambda w, T, O: _neus(T, mask_names=[f"{i}.png" for i in range(1, 13)])),
    Case("silent wrong result", "neus one mask missing", "baselines.visual_hull", ["{T}/neus", "--out", "{O}"],
         "000011.png", setup=lambda w, T, O: _neus(T, mask_names=[f"{i:03d}.png" for i in range(11)],
                                                   image_names=[f"{i:06d}.png" for i in range(12)])),
    Case("silent wrong result", "neus duplicate frame numbers", "reconstruct", ["{T}/neus", "--out", "{O}"],
         "same frame number", setup=lambda w, T, O: _neus(T, mask_names=[f"{i:03d}.png" for i in range(12)]
                                                           + ["0000.png"], image_names=[f"{i:06d}.png" for i in range(13)])),
    Case("silent wrong result", "synth one view", "synth", ["{S}", "--out", "{O}", "--views", "1", "--overwrite"],
         "--views 1"),
    Case("silent wrong result", "synth test-every 1", "synth", ["{S}", "--out", "{O}", "--views", "6", "--test-every",
                                                              "1", "--overwrite"], "--test-every"),
    Case("silent wrong result", "reconstruct too few views", "reconstruct", ["{T}/few", "--out", "{O}"], "training views",
         setup=lambda w, T, O: _few_views(w, T)),
    # ------------------------------------------------------------------ output paths
    Case("output path", "reconstruct --out is a file", "reconstruct", ["{D}", "--out", "{O}/report.json"], "is a file"),
    Case("output path", "reconstruct parent is a file", "reconstruct", ["{D}", "--out", "{O}/report.json/sub"],
         "is a file"),
    Case("output path", "gs2d --out is a file", "gs2d", ["{D}", "--out", "{O}/report.json"], "is a file"),
    Case("output path", "synth --out is a file", "synth", ["{S}", "--out", "{O}/report.json"], "is a file"),
    Case("output path", "synth parent is a file", "synth", ["{S}", "--out", "{O}/report.json/x"], "is a file"),
    Case("output path", "visual hull --out is a file", "baselines.visual_hull", ["{D}", "--out", "{O}/report.json"],
         "is a file"),
    Case("output path", "evaluate --json is a folder", "evaluate", ["{M}", "--gt", "{S}", "--json", "{O}"],
         "--json"),
    Case("output path", "evaluate --details parent is a file", "evaluate",
         ["{M}", "--gt", "{S}", "--details", "{O}/report.json/d.json"], "--details"),
    Case("output path", "convert OUT is a folder", "convert", ["{M}", "{O}"], "is a folder"),
    Case("output path", "convert OUT parent is a file", "convert", ["{M}", "{O}/report.json/x.vtu"], "is a file"),
    Case("output path", "reconstruct unwritable --out", "reconstruct", ["{D}", "--out", "{T}/ro/run"], "cannot write",
         setup=lambda w, T, O: _readonly(T / "ro"), subprocess_prefix=["setpriv", "--bounding-set=-dac_override"]),
    Case("output path", "synth unwritable --out", "synth", ["{S}", "--out", "{T}/ro/data"], "cannot write",
         setup=lambda w, T, O: _readonly(T / "ro"), subprocess_prefix=["setpriv", "--bounding-set=-dac_override"]),
    Case("output path", "evaluate unwritable --json", "evaluate", ["{M}", "--gt", "{S}", "--json", "{T}/ro/m.json"],
         "cannot write", setup=lambda w, T, O: _readonly(T / "ro"),
         subprocess_prefix=["setpriv", "--bounding-set=-dac_override"]),
    Case("output path", "convert unwritable OUT", "convert", ["{M}", "{T}/ro/x.vtu"], "cannot write",
         setup=lambda w, T, O: _readonly(T / "ro"), subprocess_prefix=["setpriv", "--bounding-set=-dac_override"]),
    Case("output path", "existing run without --resume", "reconstruct", ["{D}", "--out", "{T}/run"], "--resume",
         setup=lambda w, T, O: _fake_run(T / "run")),
    Case("output path", "existing dataset without --overwrite", "synth", ["{S}", "--out", "{D}"], "--overwrite"),
    # ------------------------------------------------------------------ raw tracebacks
    Case("raw traceback", "camera_angle_x zero", "gs2d", ["{T}/bad_data", "--out", "{O}"], "camera_angle_x",
         setup=lambda w, T, O: _nerf_copy(w, T, lambda d: d.update(camera_angle_x=0))),
    Case("raw traceback", "camera_angle_x string", "reconstruct", ["{T}/bad_data", "--out", "{O}"], "camera_angle_x",
         setup=lambda w, T, O: _nerf_copy(w, T, lambda d: d.update(camera_angle_x="wide"))),
    Case("raw traceback", "camera_angle_x NaN", "baselines.visual_hull", ["{T}/bad_data", "--out", "{O}"],
         "camera_angle_x", setup=lambda w, T, O: _nerf_copy(w, T, lambda d: d.update(camera_angle_x=float("nan")))),
    Case("raw traceback", "camera_angle_x above pi", "gs2d", ["{T}/bad_data", "--out", "{O}"], "camera_angle_x",
         setup=lambda w, T, O: _nerf_copy(w, T, lambda d: d.update(camera_angle_x=4.0))),
    Case("raw traceback", "transform_matrix of strings", "reconstruct", ["{T}/bad_data", "--out", "{O}"],
         "transform_matrix", setup=lambda w, T, O: _nerf_copy(
             w, T, lambda d: d["frames"][1].update(transform_matrix=[["a"] * 4] * 4))),
    Case("raw traceback", "transform_matrix 2x2", "gs2d", ["{T}/bad_data", "--out", "{O}"], "transform_matrix",
         setup=lambda w, T, O: _nerf_copy(w, T, lambda d: d["frames"][0].update(transform_matrix=[[1, 0], [0, 1]]))),
    Case("raw traceback", "frames not a list", "reconstruct", ["{T}/bad_data", "--out", "{O}"], "frames",
         setup=lambda w, T, O: _nerf_copy(w, T, lambda d: d.update(frames={"a": 1}))),
    Case("raw traceback", "file_path a number", "gs2d", ["{T}/bad_data", "--out", "{O}"], "file_path",
         setup=lambda w, T, O: _nerf_copy(w, T, lambda d: d["frames"][2].update(file_path=7))),
    Case("raw traceback", "transforms not JSON", "reconstruct", ["{T}/bad_data", "--out", "{O}"], "transforms_train.json",
         setup=lambda w, T, O: _broken_json(w, T)),
    Case("raw traceback", "corrupt PNG", "gs2d", ["{T}/bad_data", "--out", "{O}"], "r_1.png",
         setup=lambda w, T, O: _corrupt_png(w, T)),
    Case("raw traceback", "evaluate --volume-points -5", "evaluate", ["{M}", "--gt", "{S}", "--volume-points", "-5"],
         "--volume-points"),
    Case("raw traceback", "evaluate --samples 0", "evaluate", ["{M}", "--gt", "{S}", "--samples", "0"], "--samples"),
    Case("raw traceback", "garbage gs2d checkpoint", "gs2d", ["{D}", "--out", "{O}", "--resume", "--iters", "3"],
         "checkpoint.pt", setup=lambda w, T, O: _garbage_ckpt(T, O, "checkpoint.pt")),
    Case("raw traceback", "garbage run checkpoint", "reconstruct", ["{D}", "--out", "{O}", "--resume"], "state.pt",
         setup=lambda w, T, O: _garbage_ckpt(T, O, "checkpoints/state.pt")),
    Case("raw traceback", "garbage USD", "convert", ["{T}/bad.usda", "{O}/out.vtu"], "bad.usda",
         setup=lambda w, T, O: _write(T / "bad.usda", "#usda 1.0\n(\n  this is { not usd\n")),
    Case("raw traceback", "garbage vtu", "convert", ["{T}/bad.vtu", "{O}/out.vtu"], "bad.vtu",
         setup=lambda w, T, O: _write(T / "bad.vtu", "<VTKFile><garbage")),
    Case("raw traceback", "npz without tets", "convert", ["{T}/notets.npz", "{O}/out.vtu"], "notets.npz",
         setup=lambda w, T, O: np.savez(T / "notets.npz", vertices=np.zeros((4, 3)))),
    Case("raw traceback", "reconstruct --res 8", "reconstruct", ["{D}", "--out", "{O}", "--res", "8"], "--res"),
    Case("raw traceback", "reconstruct --scale-iters 0", "reconstruct", ["{D}", "--out", "{O}", "--scale-iters", "0"],
         "--scale-iters"),
    Case("raw traceback", "reconstruct --edge-length 1", "reconstruct", ["{D}", "--out", "{O}", "--edge-length", "1"],
         "--edge-length"),
    Case("raw traceback", "reconstruct --refine-factor 0", "reconstruct",
         ["{D}", "--out", "{O}", "--refine", "band", "--refine-factor", "0"], "--refine-factor"),
    Case("raw traceback", "reconstruct --refine off --refine-factor", "reconstruct",
         ["{D}", "--out", "{O}", "--refine", "off", "--refine-factor", "0.5"], "--refine-factor"),
    Case("raw traceback", "reconstruct --device tpu", "reconstruct", ["{D}", "--out", "{O}", "--device", "tpu"],
         "--device"),
    Case("raw traceback", "gs2d --threads 0", "gs2d", ["{D}", "--out", "{O}", "--threads", "0"], "--threads"),
    Case("raw traceback", "reconstruct --seed -1", "reconstruct", ["{D}", "--out", "{O}", "--seed", "-1"], "--seed"),
    Case("raw traceback", "gs2d --seed -1", "gs2d", ["{D}", "--out", "{O}", "--seed", "-1"], "--seed"),
    Case("raw traceback", "evaluate --seed 2**63", "evaluate", ["{M}", "--gt", "{S}", "--seed", str(2**63)], "--seed"),
    Case("raw traceback", "gs2d --res 4", "gs2d", ["{D}", "--out", "{O}", "--res", "4"], "--res"),
    Case("raw traceback", "synth --res 4", "synth", ["{S}", "--out", "{T}/x", "--res", "4"], "--res"),
    Case("raw traceback", "synth --supersample 0", "synth", ["{S}", "--out", "{T}/x", "--supersample", "0"],
         "--supersample"),
    Case("raw traceback", "visual hull --grid 4", "baselines.visual_hull", ["{D}", "--out", "{O}", "--grid", "4"],
         "grid"),
    Case("raw traceback", "convert --device cuda:x", "convert", ["{M}", "{O}/out.vtu", "--device", "cuda:x"], "--device"),
    # ------------------------------------------------------------------ vague errors
    Case("vague error", "NaN vertex in a tet mesh", "convert", ["{T}/nan.npz", "{O}/out.vtu"], "nan.npz",
         setup=lambda w, T, O: _nan_vertex(w, T)),
    Case("vague error", "NaN vertex in a ground truth", "evaluate", ["{M}", "--gt", "{T}/nan.obj"], "nan.obj:4",
         setup=lambda w, T, O: _nan_obj(T)),
    Case("vague error", "NaN vertex in a mesh to synthesise", "synth", ["{T}/nan.obj", "--out", "{T}/x"], "nan.obj:4",
         setup=lambda w, T, O: _nan_obj(T)),
    Case("vague error", "flat ground truth", "evaluate", ["{M}", "--gt", "{T}/flat.obj"], "flat.obj",
         setup=lambda w, T, O: _write(T / "flat.obj", "v 0 0 0\nv 0 0 0\nv 0 0 0\nf 1 2 3\n")),
    Case("vague error", "missing prediction", "evaluate", ["{T}/none.vtu", "--gt", "{S}"], "none.vtu"),
    Case("vague error", "missing dataset", "reconstruct", ["{T}/nowhere", "--out", "{O}"], "nowhere"),
    Case("vague error", "dataset is a file", "gs2d", ["{S}", "--out", "{O}"], "ball.obj"),
    # ------------------------------------------------------------------ formats
    Case("format", "ground truth of unknown format", "evaluate", ["{M}", "--gt", "{T}/gt.xyz"], "gt.xyz",
         setup=lambda w, T, O: _write(T / "gt.xyz", "0 0 0\n")),
    Case("format", "empty STL", "synth", ["{T}/e.stl", "--out", "{T}/x"], "e.stl",
         setup=lambda w, T, O: _write(T / "e.stl", "")),
    Case("format", "point-cloud PLY", "evaluate", ["{M}", "--gt", "{T}/pts.ply"], "pts.ply",
         setup=lambda w, T, O: _write(T / "pts.ply", "ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\n"
                                      "property float y\nproperty float z\nend_header\n0 0 0\n1 1 1\n")),
    Case("format", "OBJ without faces", "synth", ["{T}/p.obj", "--out", "{T}/x"], "p.obj",
         setup=lambda w, T, O: _write(T / "p.obj", "v 0 0 0\nv 1 0 0\n")),
    Case("format", "surface given as a tet mesh", "convert", ["{S}", "{O}/out.vtu"], "holds a surface"),
    # ------------------------------------------------------------------ simulations that blow up or never end
    Case("simulation", "stiffness the solver cannot honour", "simulate", ["{M}", "--scene", "{T}/s.toml", "--out", "{O}"],
         "youngs_modulus", setup=lambda w, T, O: _scene(T, O, "[material]\nyoungs_modulus = 1e15\n")),
    Case("simulation", "duration of 1e9 s", "simulate", ["{M}", "--scene", "{T}/s.toml", "--out", "{O}"], "--allow-long",
         setup=lambda w, T, O: _scene(T, O, "[sim]\nduration = 1e9\n")),
    Case("simulation", "huge gravity", "simulate", ["{M}", "--scene", "{T}/s.toml", "--out", "{O}"], "gravity",
         setup=lambda w, T, O: _scene(T, O, "[sim]\ngravity = [0.0, 0.0, -3e38]\n")),
    Case("simulation", "huge initial velocity", "simulate", ["{M}", "--scene", "{T}/s.toml", "--out", "{O}"], "velocity",
         setup=lambda w, T, O: _scene(T, O, "[placement]\nvelocity = [1e30, 0.0, 0.0]\n")),
    Case("simulation", "huge size", "simulate", ["{M}", "--scene", "{T}/s.toml", "--out", "{O}"], "size",
         setup=lambda w, T, O: _scene(T, O, "[placement]\nsize = 1e30\n")),
    Case("simulation", "infinite damping", "simulate", ["{M}", "--scene", "{T}/s.toml", "--out", "{O}"], "damping",
         setup=lambda w, T, O: _scene(T, O, "[sim]\ndamping = inf\n")),
    Case("simulation", "too many substeps", "simulate", ["{M}", "--scene", "{T}/s.toml", "--out", "{O}"], "substeps",
         setup=lambda w, T, O: _scene(T, O, "[sim]\nsubsteps = 100000\n")),
    Case("raw traceback", "binary TOML scene", "simulate", ["{M}", "--scene", "{T}/s.toml", "--out", "{O}"], "not UTF-8",
         setup=lambda w, T, O: _scene(T, O, b"\xff\xfe[sim]\x00")),
    Case("raw traceback", "TOML syntax error", "simulate", ["{M}", "--scene", "{T}/s.toml", "--out", "{O}"], "s.toml",
         setup=lambda w, T, O: _scene(T, O, "[sim\nduration = \n")),
    Case("output path", "simulate --out is a file", "simulate", ["{M}", "--scene", "drop", "--out", "{O}/report.json"],
         "is a file"),
    Case("vague error", "simulate a missing mesh", "simulate", ["{T}/none.vtu", "--scene", "drop", "--out", "{O}"],
         "none.vtu"),
    Case("vague error", "unknown scene", "simulate", ["{M}", "--scene", "dorp", "--out", "{O}"], "dorp"),
    # ------------------------------------------------------------------ improve
    Case("raw traceback", "improve --max-surface-move -1", "improve", ["{M}", "{O}/out.vtu", "--max-surface-move", "-1"],
         "--max-surface-move"),
    Case("output path", "improve OUT parent is a file", "improve", ["{M}", "{O}/report.json/x.vtu"], "is a file"),
    Case("raw traceback", "bench quality --set unknown setting", "bench.quality",
         ["--work", "{O}/q", "--objects", "bowl", "--set", "geometry.no_such=1"], "--set geometry.no_such=1"),
    Case("raw traceback", "bench quality --set unknown section", "bench.quality",
         ["--work", "{O}/q", "--objects", "bowl", "--set", "nowhere.x=1"], "--set nowhere.x=1"),
    Case("raw traceback", "bench quality --set bad value", "bench.quality",
         ["--work", "{O}/q", "--objects", "bowl", "--set", "geometry.hc_floor=-1"], "hc_floor"),
    Case("vague error", "bench quality --set a stage-0 value out of range", "bench.quality",
         ["--work", "{O}/q", "--objects", "bowl", "--set", "stage0.coarse_fraction=2"], "coarse_fraction"),
    Case("vague error", "bench quality --set a schedule out of order", "bench.quality",
         ["--work", "{O}/q", "--objects", "bowl", "--set", "schedule.topology_until=0"], "topology_until"),
    Case("silent wrong result", "bench quality --set a bool to a word", "bench.quality",
         ["--work", "{O}/q", "--objects", "bowl", "--set", "polish.enabled=no"], "expected true or false"),
    Case("silent wrong result", "improve a mixed-orientation mesh", "improve", ["{T}/mixed.npz", "{O}/out.vtu"],
         "mixed orientation", setup=lambda w, T, O: _mixed(w, T)),
]


def _scene(T: Path, O: Path, text) -> Path:
    """A scene file ``T/s.toml`` and a previous good simulation in the target folder."""
    _write(O / "sim.usda", "#usda 1.0\n(\n    doc = \"a previous good simulation\"\n)\n")
    return _write(T / "s.toml", text)


def _few_views(world, T):
    d = T / "few"
    shutil.copytree(world["D"], d)
    doc = json.loads((d / "transforms_train.json").read_text())
    doc["frames"] = doc["frames"][:4]
    (d / "transforms_train.json").write_text(json.dumps(doc))
    return d


def _readonly(path: Path):
    path.mkdir(parents=True, exist_ok=True)
    path.chmod(0o555)


def _fake_run(out: Path):
    from holowarp.config import preset
    from holowarp.runstate import Checkpoint, RunState

    Checkpoint(preset("fast").to_dict(), None, RunState()).save(out)


def _broken_json(world, T):
    d = T / "bad_data"
    shutil.copytree(world["D"], d)
    (d / "transforms_train.json").write_text('{"frames": [')


def _corrupt_png(world, T):
    d = T / "bad_data"
    shutil.copytree(world["D"], d)
    (d / "train" / "r_1.png").write_bytes(b"\x89PNG\r\n\x1a\n garbage")


def _fill(arg: str, world, T: Path, O: Path) -> str:
    return arg.format(D=world["D"], M=world["M"], S=world["S"], T=T, O=O)


def _run(case: Case, argv: list[str]) -> tuple[int, str]:
    if case.subprocess_prefix:
        if shutil.which(case.subprocess_prefix[0]) is None:
            pytest.skip(f"{case.subprocess_prefix[0]} is not available")
        p = subprocess.run(case.subprocess_prefix + [sys.executable, "-m", f"holowarp.{case.cmd}", *argv],
                           capture_output=True, text=True, timeout=600)
        return p.returncode, p.stderr
    import importlib

    mod = importlib.import_module(f"holowarp.{case.cmd}")
    from contextlib import redirect_stderr, redirect_stdout
    from io import StringIO

    err, out = StringIO(), StringIO()
    with redirect_stderr(err), redirect_stdout(out):
        rc = mod.main(argv)
    return rc, err.getvalue()


@pytest.mark.parametrize("case", CASES, ids=[f"{c.cls}: {c.name}" for c in CASES])
def test_bad_input_fails_with_one_line_naming_the_culprit_and_keeps_the_old_output(case, world, tmp_path):
    T, O = tmp_path / "case", tmp_path / "target"
    T.mkdir()
    O.mkdir()
    good = O / "report.json"
    good.write_text(json.dumps({"previous": "good output"}))
    if case.setup is not None:
        case.setup(world, T, O)
    snapshot = {p: p.read_bytes() for p in O.rglob("*") if p.is_file()}
    argv = [_fill(a, world, T, O) for a in case.argv]
    rc, err = _run(case, argv)
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert rc != 0, f"exit 0 for {argv}"
    assert len(lines) == 1 and lines[0].startswith("error: "), err
    assert case.names in lines[0], lines[0]
    assert "Traceback" not in err
    for p, data in snapshot.items():
        assert p.read_bytes() == data, f"{p} changed"


def test_the_corpus_covers_every_class_with_enough_cases():
    counts = {c: sum(case.cls == c for case in CASES) for c in CLASSES}
    assert len(CASES) >= 60, len(CASES)
    assert all(counts[c] > 0 for c in CLASSES), counts
    assert sum(counts.values()) == len(CASES)


# ------------------------------------------------------------------ what must NOT be an error


def test_a_uniformly_negative_mesh_is_reoriented_and_the_summary_says_so(world, tmp_path, capsys):
    from holowarp import read_tetmesh
    from holowarp.convert import main
    from holowarp.tetmesh import TetMesh

    m = world["mesh"]
    neg = tmp_path / "tetgen_winding.npz"
    np.savez(neg, vertices=m.vertices, tets=m.tets[:, [0, 1, 3, 2]])  # every tet negative
    assert np.all(TetMesh(m.vertices, m.tets[:, [0, 1, 3, 2]]).signed_volumes() < 0)
    assert main([str(neg), str(tmp_path / "out.usda")]) == 0
    out = capsys.readouterr().out
    assert f"re-oriented all {m.num_tets} tets" in out
    from pxr import Usd, UsdGeom

    stage = Usd.Stage.Open(str(tmp_path / "out.usda"))
    (prim,) = [p for p in stage.Traverse() if p.IsA(UsdGeom.TetMesh)]
    assert len(UsdGeom.TetMesh.FindInvertedElements(UsdGeom.TetMesh(prim), Usd.TimeCode.Default())) == 0
    assert np.all(read_tetmesh(tmp_path / "out.usda").signed_volumes() > 0)


def test_mixed_orientation_is_fixed_only_when_asked(world, tmp_path, capsys):
    from holowarp.convert import main

    bad = _mixed(world, tmp_path)
    assert main([str(bad), str(tmp_path / "fixed.vtu"), "--orient"]) == 0
    assert "flipped=3" in capsys.readouterr().out


@pytest.mark.parametrize("ext", [".off", ".stl", ".ply", ".glb"])
def test_every_surface_format_trimesh_reads_is_a_ground_truth_and_a_mesh_to_synthesise(world, tmp_path, ext, capsys):
    import trimesh

    from holowarp.evaluate import main as evaluate_main
    from holowarp.synth import main as synth_main

    src = tmp_path / f"ball{ext}"
    trimesh.creation.icosphere(subdivisions=2, radius=0.5).export(src)
    assert synth_main([str(src), "--out", str(tmp_path / "ds"), "--views", "12", "--res", "16", "--quiet"]) == 0
    assert (tmp_path / "ds" / "gt.obj").is_file()
    rc = evaluate_main([str(world["M"]), "--gt", str(src), "--samples", "2000", "--volume-points", "2000",
                        "--json", str(tmp_path / "m.json")])
    assert rc == 0 and json.loads((tmp_path / "m.json").read_text())["chamfer_l1"] > 0
    capsys.readouterr()


def test_bench_quality_refuses_a_missing_suite_mesh_before_any_work(tmp_path, monkeypatch, capsys):
    from holowarp.bench import quality

    missing = tmp_path / "nowhere" / "spot.obj"
    monkeypatch.setitem(quality.OBJECTS, "spot", (missing, "y", 0, False))
    rc = quality.main(["--work", str(tmp_path / "q"), "--objects", "bowl", "spot"])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1 and err[0].startswith("error: --objects spot: ") and str(missing) in err[0]
    assert not (tmp_path / "q").exists()  # refused before the bowl's hour of work, and before --work was made
