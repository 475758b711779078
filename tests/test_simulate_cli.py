"""``python -m holowarp.simulate``: outputs (USD stage, report), reference Chamfer, renders
and clear errors for bad input. Small meshes and short scenes keep it to a few seconds."""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pytest

from holowarp.mesh_io import write_tetmesh
from holowarp.surface_io import write_surface
from holowarp.primitives import box_tetmesh
from holowarp.simulate import main

REPORT_KEYS = {"frames", "steps", "seconds", "steps_per_second", "max_inverted", "min_volume_ratio",
               "max_volume_ratio", "com", "nan", "components_end", "plan", "inverted", "volume_ratio",
               "contact_force", "max_penetration", "inverted_frames", "bodies"}


@pytest.fixture
def box_vtu(tmp_path) -> Path:
    p = tmp_path / "box.vtu"
    write_tetmesh(p, box_tetmesh((2, 2, 2), (1.0, 1.0, 1.0)))
    return p


def _short_scene(tmp_path, base: str, **sim) -> Path:
    """A copy of a built-in scene with [sim] values replaced (what a user would do)."""
    from holowarp.scenes import scene_path

    text = scene_path(base).read_text()
    for k, v in sim.items():
        text, n = re.subn(rf"(?m)^{k}\s*=\s*[^#\n]*", f"{k} = {v} ", text)
        assert n == 1, k
    p = tmp_path / f"{base}_short.toml"
    p.write_text(text)
    return p


def test_drop_writes_animated_usd_and_report(tmp_path, box_vtu, capsys):
    from pxr import Usd, UsdGeom

    out = tmp_path / "out"
    rc = main([str(box_vtu), "--scene", "drop", "--out", str(out), "--quiet"])
    assert rc == 0
    summary = json.loads(capsys.readouterr().out)
    report = json.loads((out / "report.json").read_text())
    assert REPORT_KEYS <= set(report)
    assert summary["frames"] == report["frames"] == 61 and report["steps"] == 60
    assert len(report["com"]) == 61 and report["nan"] is False
    assert report["components_end"] == 1 and report["max_inverted"] == 0
    assert report["steps_per_second"] == pytest.approx(report["steps"] / report["seconds"])
    assert 0.95 < report["min_volume_ratio"] <= 1.0 + 1e-6 <= report["max_volume_ratio"] + 1e-6
    assert report["com"][0][2] == pytest.approx(0.3, abs=1e-6)  # 0.2 m cube, 0.2 m above ground
    assert report["com"][-1][2] == pytest.approx(0.1, abs=0.003)
    # At 1/60 s a substep is far longer than a wave takes to cross an edge: "auto" is implicit Euler.
    assert report["plan"] == {"dt": 1 / 60, "substeps": 1, "iterations": 16, "softened_tets": 0, "solver": "vbd",
                              "integrator": "euler"}
    assert report["max_penetration"] < 1e-6 and report["inverted_frames"] == []

    stage = Usd.Stage.Open(str(out / "sim.usda"))
    assert UsdGeom.GetStageUpAxis(stage) == UsdGeom.Tokens.z
    assert UsdGeom.GetStageMetersPerUnit(stage) == 1.0
    assert stage.GetTimeCodesPerSecond() == 60.0
    assert (stage.GetStartTimeCode(), stage.GetEndTimeCode()) == (0.0, 60.0)
    tet = UsdGeom.TetMesh(stage.GetPrimAtPath("/World/Object/TetMesh"))
    surf = UsdGeom.Mesh(stage.GetPrimAtPath("/World/Object/Surface"))
    assert len(tet.GetPointsAttr().GetTimeSamples()) == 61
    assert len(surf.GetPointsAttr().GetTimeSamples()) == 61
    p60 = np.asarray(tet.GetPointsAttr().Get(60.0))
    assert p60[:, 2].min() >= -1e-6
    assert p60.mean(0)[2] == pytest.approx(0.1, abs=0.01)


def test_compress_animates_plates_in_usd(tmp_path, box_vtu):
    from pxr import Usd, UsdGeom

    scene = _short_scene(tmp_path, "compress", duration=1.0)
    out = tmp_path / "out"
    assert main([str(box_vtu), "--scene", str(scene), "--out", str(out), "--no-progress"]) == 0
    stage = Usd.Stage.Open(str(out / "sim.usda"))
    top = UsdGeom.Xformable(stage.GetPrimAtPath("/World/TopPlate"))
    op = top.GetOrderedXformOps()[0]
    assert len(op.GetAttr().GetTimeSamples()) == 61
    z0, z48 = op.Get(0.0)[2], op.Get(48.0)[2]  # 0.8 s: squeezed to half height
    assert z0 - z48 == pytest.approx(0.1, rel=1e-3)
    report = json.loads((out / "report.json").read_text())
    assert max(abs(f[2]) for f in report["contact_force"]["TopPlate"]) > 10.0


def test_reference_adds_sim_chamfer_at_five_times(tmp_path, box_vtu):
    """The reference (the same cube, tessellated differently) is simulated in the same
    scene; the Chamfer between the two simulated surfaces is reported at 0, 0.25, 0.5, 0.75
    and 1 s in the reference's evaluation frame."""
    ref = tmp_path / "ref.vtu"
    write_tetmesh(ref, box_tetmesh((3, 3, 3), (1.0, 1.0, 1.0), split=5))
    out = tmp_path / "out"
    rc = main([str(box_vtu), "--scene", "drop", "--out", str(out), "--reference", str(ref),
               "--chamfer-samples", "20000", "--no-progress"])
    assert rc == 0
    report = json.loads((out / "report.json").read_text())
    sc = report["sim_chamfer"]
    assert list(sc) == ["0", "0.25", "0.5", "0.75", "1"]
    assert all(0.0 <= v < 0.1 for v in sc.values())
    assert sc["0"] < 0.012  # same cube at rest: sampling noise only
    assert max(sc.values()) > sc["0"]  # the two tessellations deform differently
    from pxr import Usd

    stage = Usd.Stage.Open(str(out / "sim.usda"))
    assert stage.GetPrimAtPath("/World/Reference/TetMesh").IsValid()


def test_surface_reference_is_tetrahedralised(tmp_path):
    """A closed surface given as reference is tetrahedralised (fTetWild) into a positively
    oriented tet mesh with the same bounding box."""
    from holowarp.simulation import load_sim_mesh

    ref = tmp_path / "cube.obj"
    write_surface(ref, box_tetmesh((1, 1, 1), (1.0, 1.0, 1.0)))
    m = load_sim_mesh(ref)
    assert m.num_tets > 0 and (m.signed_volumes() > 0).all()
    np.testing.assert_allclose(m.vertices.min(0), 0.0, atol=1e-3)
    np.testing.assert_allclose(m.vertices.max(0), 1.0, atol=1e-3)
    assert m.volume() == pytest.approx(1.0, rel=1e-3)


def test_render_writes_png_frames(tmp_path, box_vtu):
    from PIL import Image

    scene = _short_scene(tmp_path, "drop", duration=0.1)
    out = tmp_path / "out"
    assert main([str(box_vtu), "--scene", str(scene), "--out", str(out), "--render", "--no-progress"]) == 0
    pngs = sorted((out / "frames").glob("frame_*.png"))
    assert len(pngs) == 7
    img = np.asarray(Image.open(pngs[0]).convert("RGB"), dtype=np.float32)
    last = np.asarray(Image.open(pngs[-1]).convert("RGB"), dtype=np.float32)
    assert img.std() > 5.0  # not a blank image
    assert np.abs(img - last).mean() > 1.0  # the falling cube moved between the frames


@pytest.mark.parametrize(
    "edit, message",
    [
        ("poissons_ratio = 0.5", r"\[material\] poissons_ratio: must lie in \[0, 0.5\)"),
        ("frcition = 0.3", r"\[material\] unknown key\(s\) frcition"),
        ("dt = 0.01", r"\[sim\] dt: must be 1/60 s divided by a whole number"),
        ('integrator = "rk4"', r"\[sim\] integrator: expected one of 'auto', 'euler', 'bdf2', got 'rk4'"),
    ],
)
def test_bad_scene_value_is_reported_with_file_and_key(tmp_path, box_vtu, capsys, edit, message):
    from holowarp.scenes import scene_path

    text = scene_path("drop").read_text()
    key = edit.split("=")[0].strip()
    if key == "frcition":
        text = text.replace("[material]\n", "[material]\nfrcition = 0.3\n")
    else:
        text = re.sub(rf"(?m)^{key}\s*=\s*[^#\n]*", edit + " ", text)
    bad = tmp_path / "bad.toml"
    bad.write_text(text)
    rc = main([str(box_vtu), "--scene", str(bad), "--out", str(tmp_path / "o"), "--no-progress"])
    err = capsys.readouterr().err
    assert rc == 2
    assert str(bad) in err and re.search(message, err), err
    assert not (tmp_path / "o" / "report.json").exists()


def test_missing_mesh_and_unknown_scene_are_clear_errors(tmp_path, box_vtu, capsys):
    rc = main([str(tmp_path / "nope.vtu"), "--scene", "drop", "--out", str(tmp_path / "o")])
    assert rc == 2 and "nope.vtu" in capsys.readouterr().err
    rc = main([str(box_vtu), "--scene", "bounce", "--out", str(tmp_path / "o")])
    err = capsys.readouterr().err
    assert rc == 2 and "bounce" in err and "drop" in err


def test_simulate_api_equals_cli(tmp_path, box_vtu):
    """One call does what the command does."""
    from holowarp.simulation import simulate

    rep = simulate(box_vtu, "drop", progress=False)
    out = tmp_path / "out"
    main([str(box_vtu), "--scene", "drop", "--out", str(out), "--no-progress"])
    cli = json.loads((out / "report.json").read_text())
    assert rep["com"] == cli["com"] and rep["components_end"] == cli["components_end"]


def test_help_names_the_mesh_formats_and_quiet(capsys):
    with pytest.raises(SystemExit):
        main(["--help"])
    text = capsys.readouterr().out
    assert ".vtu" in text and ".obj" in text and "fTetWild" in text and "--quiet" in text
    assert "--no-progress" not in text  # the old spelling still works, hidden


def test_progress_bar_stays_off_when_stderr_is_not_a_terminal(tmp_path, box_vtu, capsys):
    scene = _short_scene(tmp_path, "drop", duration=0.1)
    assert main([str(box_vtu), "--scene", str(scene), "--out", str(tmp_path / "o")]) == 0
    err = capsys.readouterr().err  # pytest's capture is not a terminal
    assert "step/s" not in err and "%|" not in err


def _write_scene(path: Path, text: str) -> Path:
    path.write_text(text)
    return path


def test_scene_with_bodies_simulates_each_with_its_mesh(tmp_path, box_vtu):
    """A [[bodies]] scene: a body from a mesh file next to the scene (relative path) dropped
    onto the command-line mesh; both rest, stacked, and the report lists them."""
    sub = tmp_path / "scenes"
    sub.mkdir()
    write_tetmesh(sub / "small.vtu", box_tetmesh((2, 2, 2), (0.5, 0.5, 0.5)))
    scene = _write_scene(sub / "two.toml", """
name = "two"
[sim]
duration = 1.0
[placement]
size = 0.1
[[bodies]]
name = "Base"
[[bodies]]
name = "Top"
mesh = "small.vtu"
[bodies.placement]
size = 0.05
height = 0.12
[bodies.material]
youngs_modulus = 1.0e6
""")
    out = tmp_path / "out"
    assert main([str(box_vtu), "--scene", str(scene), "--out", str(out), "--quiet"]) == 0
    report = json.loads((out / "report.json").read_text())
    assert [b["name"] for b in report["bodies"]] == ["Base", "Top"]
    assert report["bodies"][1]["mesh"] == str(sub / "small.vtu") and report["bodies"][1]["tets"] == 48
    assert report["bodies"][1]["com_end"][2] == pytest.approx(0.1 + 0.025, abs=0.003)  # on the base
    assert report["max_penetration"] < 0.001  # 1 % of the base
    from pxr import Usd

    stage = Usd.Stage.Open(str(out / "sim.usda"))
    assert stage.GetPrimAtPath("/World/Base/TetMesh").IsValid() and stage.GetPrimAtPath("/World/Top/TetMesh").IsValid()


@pytest.mark.parametrize(
    "text, message",
    [
        ('[[bodies]]\nname = "A"\nmesh = "nope.vtu"\n', r"body 'A' mesh .*nope\.vtu: no such file"),
        ('[[bodies]]\nname = "A"\ncolour = 1\n', r"\[bodies\.0\] unknown key\(s\) colour"),
        ('[[bodies]]\nname = "A"\n[bodies.material]\nrestitution = 0.5\n', r"\[bodies\.0\.material\] unknown key"),
        ('[contact]\nstiffness = 0\n', r"\[contact\] stiffness: must be > 0"),
        ('[contact]\nradius = -1\n', r"\[contact\] radius: must be >= 0"),
    ],
)
def test_bad_bodies_and_contact_values_are_one_line_errors(tmp_path, box_vtu, capsys, text, message):
    bad = _write_scene(tmp_path / "bad.toml", text)
    rc = main([str(box_vtu), "--scene", str(bad), "--out", str(tmp_path / "o"), "--quiet"])
    err = capsys.readouterr().err
    assert rc == 2 and re.search(message, err), err
    assert len(err.strip().splitlines()) == 1
    assert not (tmp_path / "o" / "report.json").exists()


def test_non_finite_state_fails_with_the_step_and_keeps_the_previous_report(tmp_path, box_vtu, capsys):
    out = tmp_path / "out"
    scene = _short_scene(tmp_path, "drop", duration=0.1)
    assert main([str(box_vtu), "--scene", str(scene), "--out", str(out), "--quiet"]) == 0
    before = (out / "report.json").read_text()
    # (an absurd gravity, size or speed is refused when the scene is read; a stiffness far
    # beyond float32's range gets through and blows up in the first step)
    bad = _write_scene(tmp_path / "blowup.toml", re.sub(r"(?m)^youngs_modulus\s*=\s*[^#\n]*", "youngs_modulus = 1e15 ",
                                                       scene.read_text()))
    capsys.readouterr()
    rc = main([str(box_vtu), "--scene", str(bad), "--out", str(out), "--quiet"])
    err = capsys.readouterr().err
    assert rc == 1 and re.search(r"non-finite positions after step \d+", err), err
    assert (out / "report.json").read_text() == before


def test_inverted_frames_are_reported_on_stderr_and_in_the_report(tmp_path, box_vtu, capsys):
    """A very soft, fully compressible cube crushed to a fifth of its height folds tets;
    every frame with inverted tets is listed and a warning names them."""
    from holowarp.scenes import scene_path

    text = scene_path("compress").read_text()
    text = text.replace("[0.8, 0.5, 0.5, 0.5], [1.1, 0.5, 0.5, 0.5]", "[0.8, 0.5, 0.5, 0.2], [1.1, 0.5, 0.5, 0.2]")
    text = re.sub(r"(?m)^youngs_modulus\s*=\s*[^#\n]*", "youngs_modulus = 1.0e4 ", text)
    text = re.sub(r"(?m)^poissons_ratio\s*=\s*[^#\n]*", "poissons_ratio = 0.0 ", text)
    text = re.sub(r"(?m)^duration\s*=\s*[^#\n]*", "duration = 1.2 ", text)
    scene = _write_scene(tmp_path / "crush.toml", text)
    out = tmp_path / "out"
    assert main([str(box_vtu), "--scene", str(scene), "--out", str(out), "--quiet"]) == 0
    report = json.loads((out / "report.json").read_text())
    err = capsys.readouterr().err
    frames = [k for k, n in enumerate(report["inverted"]) if n > 0]
    assert frames and report["inverted_frames"] == frames and report["max_inverted"] > 0
    assert "warning" in err and "inverted tets" in err and f"frames {frames[0]}-{frames[-1]}" in err


def test_surface_reference_with_seam_split_vertices_gives_sim_chamfer(tmp_path, box_vtu):
    """--reference accepts a closed surface whose vertices are split along UV seams (as
    textured OBJs are): it is welded, tetrahedralised with fTetWild and simulated; the
    report has sim_chamfer at the five times."""
    cube = box_tetmesh((1, 1, 1), (1.0, 1.0, 1.0))
    V, F = cube.surface_mesh()
    # split: the second half of the faces use their own copies of the vertices
    F = F.copy()
    half = len(F) // 2
    V2 = np.concatenate([V, V])
    F[half:] += len(V)
    ref = tmp_path / "gt.obj"
    with open(ref, "w") as f:
        np.savetxt(f, V2, fmt="v %.9g %.9g %.9g")
        np.savetxt(f, F + 1, fmt="f %d %d %d")
    out = tmp_path / "out"
    scene = _short_scene(tmp_path, "drop", duration=0.5)
    rc = main([str(box_vtu), "--scene", str(scene), "--out", str(out), "--reference", str(ref),
               "--chamfer-samples", "5000", "--quiet"])
    assert rc == 0
    report = json.loads((out / "report.json").read_text())
    assert list(report["sim_chamfer"]) == ["0", "0.25", "0.5"]
    assert report["sim_chamfer"]["0"] < 0.02 and report["reference"]["tets"] > 0
