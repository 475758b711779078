"""Mesh I/O: round trips through every format, clear errors, atomic writes, convert CLI."""

from __future__ import annotations

import os

import meshio
import numpy as np
import pytest
import trimesh

from holowarp import MeshIOError, TetMesh, read_tetmesh, write_surface, write_tetmesh
from holowarp.surface_io import SurfaceError
from holowarp.convert import main as convert_main
from holowarp.primitives import box_tetmesh

TET_EXTS = [".vtu", ".msh", ".npz", ".usda", ".usd"]


@pytest.fixture
def mesh(rng):
    m = box_tetmesh((3, 2, 2), (0.3, 0.2, 0.2))
    return m.with_vertices(m.vertices + rng.uniform(-0.005, 0.005, m.vertices.shape))


@pytest.mark.parametrize("ext", TET_EXTS)
def test_tet_formats_round_trip_exactly(tmp_path, mesh, ext):
    path = tmp_path / f"m{ext}"
    write_tetmesh(path, mesh)
    back = read_tetmesh(path)
    np.testing.assert_array_equal(back.tets, mesh.tets)
    # USD stores float32 points; every other format is lossless float64.
    tol = 1e-7 if ext.startswith(".usd") else 0.0
    np.testing.assert_allclose(back.vertices, mesh.vertices, atol=tol, rtol=0)
    assert np.all(back.signed_volumes() > 0)


@pytest.mark.parametrize("src,dst", [(a, b) for a in TET_EXTS for b in TET_EXTS if a != b][::3])
def test_convert_cli_between_tet_formats(tmp_path, mesh, src, dst, capsys):
    write_tetmesh(tmp_path / f"in{src}", mesh)
    rc = convert_main([str(tmp_path / f"in{src}"), str(tmp_path / f"out{dst}")])
    assert rc == 0
    assert "component(s)" in capsys.readouterr().out
    back = read_tetmesh(tmp_path / f"out{dst}")
    np.testing.assert_array_equal(back.tets, mesh.tets)
    np.testing.assert_allclose(back.vertices, mesh.vertices, atol=1e-7)


def test_convert_cli_says_where_tets_overlap(tmp_path, capsys):
    from oracles import edge_fan

    fan, _ = edge_fan([(a, a + 50) for a in range(0, 400, 50)], spiral=0.05)  # 400 degrees round one edge
    assert convert_main([str(_write(tmp_path, fan)), str(tmp_path / "out.vtu")]) == 0
    assert "overlapping edges=1" in capsys.readouterr().out
    assert fan.summary()["overlapping_edges"] == 1
    box, _ = edge_fan([(a, a + 50) for a in range(0, 350, 50)], spiral=0.05)
    assert convert_main([str(_write(tmp_path, box, "b.npz")), str(tmp_path / "b.vtu")]) == 0
    assert "overlapping" not in capsys.readouterr().out


@pytest.mark.parametrize("ext", [".obj", ".ply"])
def test_boundary_surface_export_is_closed_outward_and_matches_volume(tmp_path, mesh, ext):
    path = tmp_path / f"s{ext}"
    assert convert_main([str(_write(tmp_path, mesh)), str(path)]) == 0
    tm = trimesh.load(path, process=False)
    assert len(tm.faces) == len(mesh.boundary_faces())
    assert tm.is_watertight
    assert tm.volume == pytest.approx(mesh.volume(), rel=1e-5)  # positive => outward


def _write(tmp_path, mesh, name="src.npz"):
    p = tmp_path / name
    write_tetmesh(p, mesh)
    return p


def test_missing_file_error_names_the_file(tmp_path):
    p = tmp_path / "nope.vtu"
    with pytest.raises(MeshIOError, match=rf"{p}: no such file"):
        read_tetmesh(p)


def test_unknown_extension_and_surface_input_are_refused(tmp_path, mesh):
    p = tmp_path / "m.xyz"
    p.write_text("0 0 0\n")
    with pytest.raises(MeshIOError, match="unknown tet-mesh extension"):
        read_tetmesh(p)
    st = tmp_path / "m.stl"
    st.write_text("solid x\nendsolid x\n")
    with pytest.raises(MeshIOError, match="holds a surface, not a tet mesh"):
        read_tetmesh(st)
    s = tmp_path / "m.obj"
    write_surface(s, mesh)
    with pytest.raises(MeshIOError, match="holds a surface, not a tet mesh"):
        read_tetmesh(s)


def test_wrong_cell_types_are_named(tmp_path):
    pts = np.random.default_rng(1).random((8, 3))
    p = tmp_path / "hex.vtu"
    meshio.write(p, meshio.Mesh(pts, [("hexahedron", np.arange(8)[None])]))
    with pytest.raises(MeshIOError, match="hexahedron cells"):
        read_tetmesh(p)
    p2 = tmp_path / "tri.vtu"
    meshio.write(p2, meshio.Mesh(pts, [("triangle", np.array([[0, 1, 2]]))]))
    with pytest.raises(MeshIOError, match=r"no tetrahedra found \(cell types: triangle\)"):
        read_tetmesh(p2)


def test_msh_with_boundary_triangles_reads_its_tets(tmp_path, mesh):
    p = tmp_path / "with_tris.msh"
    m = meshio.Mesh(mesh.vertices, [("triangle", mesh.boundary_faces()), ("tetra", mesh.tets)])
    meshio.write(p, m, file_format="gmsh22", binary=False)
    back = read_tetmesh(p)
    np.testing.assert_array_equal(back.tets, mesh.tets)


def test_non_finite_coordinates_are_reported(tmp_path, mesh):
    V = mesh.vertices.copy()
    V[3, 1] = np.inf
    p = tmp_path / "bad.npz"
    np.savez(p, vertices=V, tets=mesh.tets)
    with pytest.raises(MeshIOError, match=r"bad\.npz: 1 vertices have non-finite coordinates"):
        read_tetmesh(p)
    p2 = tmp_path / "bad.vtu"
    meshio.write(p2, meshio.Mesh(V, [("tetra", mesh.tets)]))
    with pytest.raises(MeshIOError, match="non-finite"):
        read_tetmesh(p2)


@pytest.mark.parametrize(
    "mutate,match",
    [
        (lambda t, n: t.__setitem__((0, 2), n + 5), "indices must lie|indices out of range"),
        (lambda t, n: t.__setitem__((1, 3), t[1, 0]), "repeat a vertex"),
    ],
)
@pytest.mark.parametrize("ext", [".npz", ".vtu", ".msh"])
def test_bad_indices_are_reported(tmp_path, mesh, mutate, match, ext):
    t = mesh.tets.astype(np.int64).copy()
    mutate(t, mesh.num_vertices)
    p = tmp_path / f"bad{ext}"
    if ext == ".npz":
        np.savez(p, vertices=mesh.vertices, tets=t)
    else:
        meshio.write(p, meshio.Mesh(mesh.vertices, [("tetra", t)]), file_format="gmsh" if ext == ".msh" else None)
    with pytest.raises(MeshIOError, match=match) as err:
        read_tetmesh(p)
    assert str(p) in str(err.value)


def test_corrupt_and_empty_files_are_reported(tmp_path):
    for name, content in [("c.vtu", b"<VTKFile garbage"), ("c.msh", b"$MeshFormat\nnonsense"), ("c.npz", b"PK")]:
        p = tmp_path / name
        p.write_bytes(content)
        with pytest.raises(MeshIOError, match=str(p)):
            read_tetmesh(p)
    e = tmp_path / "empty.vtu"
    e.write_bytes(b"")
    with pytest.raises(MeshIOError, match="file is empty"):
        read_tetmesh(e)
    z = tmp_path / "keys.npz"
    np.savez(z, points=np.zeros((4, 3)))
    with pytest.raises(MeshIOError, match="missing array"):
        read_tetmesh(z)


@pytest.mark.parametrize("ext", [".vtu", ".msh", ".npz", ".obj"])
def test_failed_write_leaves_previous_file_intact(tmp_path, mesh, ext, monkeypatch):
    path = tmp_path / f"keep{ext}"
    (write_surface if ext == ".obj" else write_tetmesh)(path, mesh)
    before = path.read_bytes()

    def boom(*a, **k):
        # Write some bytes first, as a real crash mid-write would.
        target = a[0] if a else None
        if target is not None and not hasattr(target, "write"):
            with open(target, "wb") as f:
                f.write(b"partial")
        raise RuntimeError("disk full")

    monkeypatch.setattr(meshio, "write", boom)
    monkeypatch.setattr(np, "savez_compressed", lambda f, **k: (f.write(b"partial"), boom())[1])
    monkeypatch.setattr(np, "savetxt", lambda f, *a, **k: (f.write("partial"), boom())[1])
    with pytest.raises(RuntimeError, match="disk full"):
        (write_surface if ext == ".obj" else write_tetmesh)(path, mesh)
    assert path.read_bytes() == before
    assert [p.name for p in tmp_path.iterdir()] == [path.name]  # no temporary left behind


def test_convert_cli_reports_errors_without_traceback(tmp_path, capsys):
    rc = convert_main([str(tmp_path / "missing.msh"), str(tmp_path / "out.vtu")])
    err = capsys.readouterr().err
    assert rc == 2 and "no such file" in err and "Traceback" not in err and err.count("\n") == 1
    assert not (tmp_path / "out.vtu").exists()


def test_convert_orient_flag_fixes_inverted_tets(tmp_path, mesh, capsys):
    t = mesh.tets.copy()
    t[:5, [2, 3]] = t[:5, [3, 2]]
    p = tmp_path / "inv.npz"
    write_tetmesh(p, TetMesh(mesh.vertices, t))
    assert convert_main([str(p), str(tmp_path / "fixed.vtu"), "--orient"]) == 0
    assert "flipped=5" in capsys.readouterr().out
    assert np.all(read_tetmesh(tmp_path / "fixed.vtu").signed_volumes() > 0)
    assert os.path.getsize(tmp_path / "fixed.vtu") > 0
