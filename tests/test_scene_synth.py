"""Scenes of several objects in one capture (``python -m holowarp.synth SCENE.toml``,
:mod:`holowarp.scene_synth`): the render, every ground truth closed and in the combined
frame, textures and colours kept exactly, bad scene files."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from holowarp.synth import main

SPOT = Path(__file__).resolve().parents[2] / "shared" / "data" / "meshes" / "spot" / "spot.obj"


def _closed(V, F) -> bool:
    """Every edge in exactly two faces, used once in each direction (closed, consistently wound)."""
    F = np.asarray(F)
    e = np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]])
    fwd = {tuple(x) for x in e.tolist()}
    return len(fwd) == len(e) and all((b, a) in fwd for a, b in fwd)


def _ball(path: Path) -> Path:
    import trimesh

    trimesh.creation.icosphere(subdivisions=2).export(path)
    return path


@pytest.fixture(scope="module")
def two_objects(tmp_path_factory):
    d = tmp_path_factory.mktemp("scene")
    _ball(d / "ball.obj")
    (d / "scene.toml").write_text(
        '[[objects]]\nmesh = "ball.obj"\nposition = [0.0, 0.0, 0.0]\nup_axis = "z"\n'
        '[[objects]]\nbox = [0.3, 0.6, 0.3]\nposition = [1.2, 0.0, 0.0]\nrotation = [0.0, 0.0, 30.0]\n'
        'color = [0.8, 0.2, 0.1]\n')
    rc = main([str(d / "scene.toml"), "--out", str(d / "out"), "--views", "12", "--res", "16", "--quiet"])
    return d, d / "out", rc


def test_two_object_scene_renders_as_one_dataset(two_objects, capsys):
    from holowarp.data.loaders import load_dataset

    d, out, rc = two_objects
    assert rc == 0
    ds = load_dataset(out)
    assert ds.num_views == 12 and ds.masks.shape[1:] == (16, 16) and ds.masks.max() > 0.5
    meta = json.loads((out / "transforms_train.json").read_text())["holowarp"]
    assert [o["name"] for o in meta["scene"]["objects"]] == ["ball", "box0"]
    assert meta["shading"] == "vertex_colors"  # the red box and the grey ball, each in its own colour


def test_every_scene_gt_is_closed_and_in_the_combined_frame(two_objects):
    from holowarp.surface_io import read_surface

    d, out, _ = two_objects
    V, F = read_surface(out / "gt.obj")
    assert _closed(V, F)
    lo, hi = V.min(axis=0), V.max(axis=0)
    np.testing.assert_allclose((lo + hi) / 2, 0.0, atol=1e-6)  # the scene's bbox: centred, largest side 1
    assert (hi - lo).max() == pytest.approx(1.0, abs=1e-6)
    meta = json.loads((out / "transforms_train.json").read_text())["holowarp"]
    s, t = meta["transform"]["scale"], np.asarray(meta["transform"]["translation"])
    parts = []
    for o, position in zip(meta["scene"]["objects"], ([0.0, 0.0, 0.0], [1.2, 0.0, 0.0])):
        Vo, Fo = read_surface(out / "objects" / o["name"] / "gt.obj")
        assert _closed(Vo, Fo)
        # The object's bbox centre sits where the scene file put it, mapped by the scene's normalisation.
        np.testing.assert_allclose((Vo.min(axis=0) + Vo.max(axis=0)) / 2, np.asarray(position) * s + t, atol=1e-6)
        parts.append(Vo)
    np.testing.assert_allclose(np.concatenate(parts), V, atol=1e-6)  # gt.obj = the objects, not welded across
    # Each object's recorded transform maps its source file onto its gt.obj.
    ball = meta["scene"]["objects"][0]
    src, _ = read_surface(d / "ball.obj")
    tr = ball["transform"]
    mapped = tr["scale"] * src @ np.asarray(tr["rotation"]).T + np.asarray(tr["translation"])
    np.testing.assert_allclose(np.sort(mapped, axis=0), np.sort(parts[0], axis=0), atol=1e-6)
    box_side = (parts[1].max(axis=0) - parts[1].min(axis=0))[2]
    assert box_side == pytest.approx(0.3 * s, rel=1e-6)  # a box keeps its size in metres (z is not rotated)


@pytest.mark.skipif(not SPOT.is_file(), reason="shared spot mesh not present")
def test_a_textured_object_renders_in_a_scene_as_it_renders_alone(tmp_path):
    """The atlas keeps every texel (and the wrapped seams) of spot's texture."""
    from PIL import Image

    (tmp_path / "scene.toml").write_text(f'[[objects]]\nmesh = "{SPOT}"\nposition = [5.0, -2.0, 1.0]\n')
    args = ["--views", "12", "--res", "32", "--quiet"]
    assert main([str(tmp_path / "scene.toml"), "--out", str(tmp_path / "scene"), *args]) == 0
    assert main([str(SPOT), "--out", str(tmp_path / "alone"), *args]) == 0
    for i in (0, 3, 7):
        split = "test" if i % 10 == 0 else "train"
        a = np.asarray(Image.open(tmp_path / "scene" / split / f"r_{i}.png"), np.float64)
        b = np.asarray(Image.open(tmp_path / "alone" / split / f"r_{i}.png"), np.float64)
        assert np.abs(a - b).max() <= 2.0  # 8-bit rounding of float32 round-off


def test_vertex_colours_beside_a_texture_interpolate_exactly():
    """In an atlas, vertex colours become 2 x 2 texel blocks whose bilinear lookup is the
    barycentric interpolation the renderer does for vertex colours."""
    from holowarp.camera import look_at
    from holowarp.render_gt import GTRenderer
    from holowarp.scene_synth import merge_objects
    from holowarp.surface_io import SurfaceMesh

    import trimesh

    ico = trimesh.creation.icosphere(subdivisions=2)
    rng = np.random.default_rng(0)
    coloured = SurfaceMesh(positions=np.asarray(ico.vertices), faces=np.asarray(ico.faces, np.int32),
                           vertex_colors=rng.random((len(ico.vertices), 3)).astype(np.float32))
    tex = rng.random((8, 8, 3)).astype(np.float32)
    textured = SurfaceMesh(positions=np.asarray(ico.vertices) + 10.0, faces=np.asarray(ico.faces, np.int32),
                           uvs=rng.random((len(ico.vertices), 2)), face_uvs=np.asarray(ico.faces, np.int32),
                           texture=tex)
    merged = merge_objects([coloured, textured], [(0.7, 0.7, 0.7)] * 2)
    assert merged.textured
    K = np.array([[40.0, 0.0, 16.0], [0.0, 40.0, 16.0], [0.0, 0.0, 1.0]])
    view = look_at(np.array([0.0, -4.0, 1.0]), (0.0, 0.0, 0.0), (0.0, 0.0, 1.0))
    a = GTRenderer(merged.positions, merged.faces, uvs=merged.uvs, face_uvs=merged.face_uvs,
                   texture=merged.texture).render(view, K, 32, 32)
    b = GTRenderer(coloured.positions, coloured.faces, vertex_colors=coloured.vertex_colors).render(view, K, 32, 32)
    assert a["mask"].sum() > 100
    np.testing.assert_allclose(a["rgba"], b["rgba"], atol=2e-5)


def test_object_names_default_to_the_mesh_stem_then_box_numbers(tmp_path):
    from holowarp.scene_synth import load_scene_file

    _ball(tmp_path / "ball.obj")
    (tmp_path / "s.toml").write_text(
        '[[objects]]\nbox = [1, 1, 1]\nposition = [0, 0, 0]\n[[objects]]\nmesh = "ball.obj"\nposition = [2, 0, 0]\n'
        '[[objects]]\nbox = [1, 1, 1]\nposition = [4, 0, 0]\nname = "lid"\n'
        '[[objects]]\nbox = [1, 2, 1]\nposition = [6, 0, 0]\n')
    assert [o.name for o in load_scene_file(tmp_path / "s.toml")] == ["box0", "ball", "lid", "box1"]


def test_resume_with_another_scene_is_refused(two_objects, capsys):
    d, out, _ = two_objects
    moved = d / "moved.toml"
    moved.write_text((d / "scene.toml").read_text().replace("[1.2, 0.0, 0.0]", "[1.5, 0.0, 0.0]"))
    assert main([str(moved), "--out", str(out), "--views", "12", "--res", "16", "--resume", "--quiet"]) == 2
    assert "differs" in capsys.readouterr().err


BAD_SCENES = [
    ("[[objects]\n", "not valid TOML"),
    ("camera = 1\n[[objects]]\nbox = [1, 1, 1]\nposition = [0, 0, 0]\n", "unknown key 'camera'"),
    ("# no objects\n", "objects: expected one or more"),
    ("[[objects]]\nbox = [1, 1, 1]\n", "objects[0].position: missing"),
    ("[[objects]]\nposition = [0, 0, 0]\n", "objects[0]: give exactly one of mesh"),
    ("[[objects]]\nmesh = 'ball.obj'\nbox = [1, 1, 1]\nposition = [0, 0, 0]\n", "objects[0]: give exactly one"),
    ("[[objects]]\nmesh = 'nowhere.obj'\nposition = [0, 0, 0]\n", "nowhere.obj: no such file"),
    ("[[objects]]\nbox = [1, 0, 1]\nposition = [0, 0, 0]\n", "objects[0].box = [1, 0, 1]"),
    ("[[objects]]\nbox = [1, 1, 1]\nposition = [0, 0]\n", "objects[0].position = [0, 0]"),
    ("[[objects]]\nbox = [1, 1, 1]\nposition = [0, 0, 0]\nscale = 0\n", "objects[0].scale = 0"),
    ("[[objects]]\nbox = [1, 1, 1]\nposition = [0, 0, 0]\nrotation = [0, 'x', 0]\n", "objects[0].rotation"),
    ("[[objects]]\nbox = [1, 1, 1]\nposition = [0, 0, 0]\ncolor = [2, 0, 0]\n", "objects[0].color"),
    ("[[objects]]\nbox = [1, 1, 1]\nposition = [0, 0, 0]\nsize = 2\n", "objects[0]: unknown key 'size'"),
    ("[[objects]]\nmesh = 'ball.obj'\nposition = [0, 0, 0]\nup_axis = 'x'\n", "objects[0].up_axis = 'x'"),
    ("[[objects]]\nmesh = 'ball.obj'\nposition = [0, 0, 0]\n[[objects]]\nmesh = 'ball.obj'\nposition = [2, 0, 0]\n",
     "objects[1].name: 'ball' is already"),
]


@pytest.mark.parametrize("text, expected", BAD_SCENES, ids=[e for _, e in BAD_SCENES])
def test_bad_scene_files_fail_with_one_line_naming_the_file_and_key(tmp_path, capsys, text, expected):
    _ball(tmp_path / "ball.obj")
    scene = tmp_path / "scene.toml"
    scene.write_text(text)
    assert main([str(scene), "--out", str(tmp_path / "out"), "--views", "12", "--res", "16"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: ") and err.count("\n") == 1, err
    assert str(scene) in err and expected in err, err
    assert not (tmp_path / "out").exists()
