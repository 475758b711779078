"""Tet-mesh I/O with clear errors and atomic writes.

Tet meshes: ``.vtu`` (VTK XML unstructured grid), ``.msh`` (Gmsh 4.1 written; 2.2 and 4.x
read), ``.npz`` (``vertices`` (N,3) float64, ``tets`` (M,4) int32), and ``.usd``/``.usda``/
``.usdc`` (the first ``UsdGeom.TetMesh``). Triangle surfaces (a tet mesh's boundary
included) are :mod:`holowarp.surface_io`'s.

VTK and Gmsh order a linear tetrahedron's nodes like holowarp (positive volume for
``det[b-a, c-a, d-a] > 0``), so no reordering happens on either side.

Every failure while reading raises :class:`MeshIOError` whose message starts with the file's
path and says why (missing file, unknown extension, unreadable content, wrong cell types,
non-finite coordinates, out-of-range or repeated indices). Every write goes to a temporary
file in the destination folder that is renamed over the destination only on success.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from holowarp.errors import InputError, pxr_reason
from holowarp.fileio import atomic_path, check_input_file
from holowarp.fileio import quiet_stdio as _quiet
from holowarp.surface_io import SURFACE_READ_FORMATS
from holowarp.tetmesh import TetMesh, TetMeshError

__all__ = ["MeshIOError", "TET_FORMATS", "ZERO_VOLUME_REL", "load_tetmesh", "read_tetmesh", "write_tetmesh"]

TET_FORMATS = (".vtu", ".msh", ".npz", ".usd", ".usda", ".usdc")

# meshio cell types that are volume elements but not linear tets: refuse them by name.
_OTHER_VOLUME_CELLS = {
    "tetra10", "hexahedron", "hexahedron20", "hexahedron27", "wedge", "wedge15",
    "wedge18", "pyramid", "pyramid13", "pyramid14", "polyhedron",
}


class MeshIOError(InputError):
    """A mesh file cannot be read or written; the message names the file and the reason."""


def _check_input(path) -> Path:
    return check_input_file(path, error=MeshIOError, what="mesh file")


def _build(path: Path, vertices, tets) -> TetMesh:
    try:
        v = np.asarray(vertices, dtype=np.float64)
        if v.ndim == 2 and v.shape[1] == 2:
            raise MeshIOError(f"{path}: points are 2D; a tet mesh needs 3D coordinates")
        return TetMesh(v, tets)
    except TetMeshError as e:
        raise MeshIOError(f"{path}: {e}") from None


def read_tetmesh(path: str | os.PathLike) -> TetMesh:
    """Read a tet mesh from ``.vtu``, ``.msh``, ``.npz`` or ``.usd[a|c]``.

    Lower-dimensional cells (boundary triangles, lines, points that Gmsh files often carry)
    are ignored; any volume cell that is not a linear tet is an error. Orientation is kept
    as stored: call :meth:`TetMesh.oriented` to fix inverted tets.

    Raises:
        MeshIOError: missing or empty file, unknown extension, unreadable content, no or
            wrong cell types, non-finite coordinates, out-of-range or repeated indices.
    """
    path = _check_input(path)
    ext = path.suffix.lower()
    if ext in SURFACE_READ_FORMATS:
        raise MeshIOError(
            f"{path}: {ext} holds a surface, not a tet mesh; tet meshes are {', '.join(TET_FORMATS)}"
        )
    if ext not in TET_FORMATS:
        raise MeshIOError(f"{path}: unknown tet-mesh extension {ext!r}; use one of {', '.join(TET_FORMATS)}")

    if ext == ".npz":
        try:
            with np.load(path, allow_pickle=False) as z:
                missing = [k for k in ("vertices", "tets") if k not in z.files]
                if missing:
                    raise MeshIOError(
                        f"{path}: missing array(s) {missing}; a holowarp .npz holds 'vertices' (N,3) and 'tets' (M,4)"
                    )
                v, t = z["vertices"], z["tets"]
        except MeshIOError:
            raise
        except Exception as e:  # zipfile/pickle/format errors
            raise MeshIOError(f"{path}: not a readable .npz archive ({type(e).__name__}: {e})") from None
        if t.ndim != 2 or t.shape[1] != 4:
            raise MeshIOError(f"{path}: 'tets' must have shape (M, 4), got {t.shape}")
        if not np.issubdtype(t.dtype, np.integer):
            raise MeshIOError(f"{path}: 'tets' must be integers, got {t.dtype}")
        return _build(path, v, t)

    if ext in (".usd", ".usda", ".usdc"):
        from holowarp.usd import read_usd_tetmesh

        try:
            with _quiet():
                return read_usd_tetmesh(path)
        except TetMeshError as e:
            raise MeshIOError(f"{path}: {e}") from None
        except ValueError as e:
            msg = str(e)
            raise MeshIOError(msg if msg.startswith(str(path)) else f"{path}: {msg}") from None
        except Exception as e:  # pxr raises Tf.ErrorException on parse errors
            raise MeshIOError(f"{path}: not a readable USD stage ({pxr_reason(e)})") from None

    import meshio

    try:
        with _quiet():
            m = meshio.read(path, file_format="gmsh" if ext == ".msh" else "vtu")
    except IndexError as e:
        # meshio's Gmsh reader maps node tags through a table: a tag beyond it lands here.
        raise MeshIOError(f"{path}: element indices out of range, they reference missing nodes ({e})") from None
    except SystemExit:  # meshio prints its reason and calls sys.exit() on some malformed files
        raise MeshIOError(f"{path}: cannot parse as {ext} (malformed or truncated file)") from None
    except Exception as e:
        raise MeshIOError(f"{path}: cannot parse as {ext} ({type(e).__name__}: {e})") from None
    kinds = [c.type for c in m.cells]
    other = sorted({k for k in kinds if k in _OTHER_VOLUME_CELLS})
    if other:
        raise MeshIOError(
            f"{path}: holds {', '.join(other)} cells; holowarp reads linear tetrahedra ('tetra') only"
        )
    blocks = [c.data for c in m.cells if c.type == "tetra"]
    if not blocks:
        raise MeshIOError(
            f"{path}: no tetrahedra found (cell types: {', '.join(sorted(set(kinds))) or 'none'})"
        )
    return _build(path, m.points, np.concatenate(blocks, axis=0))


def write_tetmesh(path: str | os.PathLike, mesh: TetMesh, **usd_kwargs) -> Path:
    """Write ``mesh`` by extension (``.vtu``, ``.msh``, ``.npz``, ``.usd[a|c]``), atomically.

    ``usd_kwargs`` go to :func:`holowarp.usd.write_usd` (``material``, ``name``).
    """
    path = Path(path)
    ext = path.suffix.lower()
    if ext not in TET_FORMATS:
        raise MeshIOError(f"{path}: unknown tet-mesh extension {ext!r}; use one of {', '.join(TET_FORMATS)}")
    if ext in (".usd", ".usda", ".usdc"):
        from holowarp.usd import write_usd

        return write_usd(path, mesh, **usd_kwargs)
    if ext == ".npz":
        with atomic_path(path) as tmp:
            with open(tmp, "wb") as f:
                np.savez_compressed(
                    f, vertices=mesh.vertices.astype(np.float64), tets=mesh.tets.astype(np.int32)
                )
        return path

    import meshio

    m = meshio.Mesh(mesh.vertices.astype(np.float64), [("tetra", mesh.tets.astype(np.int32))])
    with atomic_path(path) as tmp:
        with _quiet():
            if ext == ".msh":
                meshio.write(tmp, m, file_format="gmsh", binary=False)
            else:
                meshio.write(tmp, m, file_format="vtu", binary=True, compression="zlib")
    return path


#: Tets whose |volume| is below this fraction of the bounding-box diagonal cubed are
#: degenerate (zero volume up to round-off).
ZERO_VOLUME_REL = 1e-12


def load_tetmesh(path: str | os.PathLike, *, fix_orientation: bool = False, allow_mixed: bool = False):
    """Read a tet mesh for use, with its orientation checked (method.md §7b).

    - no tets, or a tet of zero volume: :class:`MeshIOError` naming the first such tet;
    - every tet negative (the winding of raw TetGen/fTetWild output): re-oriented, and
      ``info["reoriented"]`` says how many were flipped;
    - some tets negative: an error unless ``fix_orientation`` (they are flipped and counted in
      ``info["flipped"]``) or ``allow_mixed`` (kept as they are, e.g. to measure them).

    Returns:
        (mesh, info) with ``info = {"tets", "reoriented", "flipped", "inverted"}``.
    """
    mesh = read_tetmesh(path)
    if mesh.num_tets == 0:
        raise MeshIOError(f"{path}: the mesh has no tetrahedra")
    vol = mesh.signed_volumes()
    diag = float(np.linalg.norm(np.ptp(mesh.vertices[np.unique(mesh.tets)], axis=0)))
    flat = np.abs(vol) <= ZERO_VOLUME_REL * max(diag, 1e-300) ** 3
    if flat.any():
        i = int(np.argmax(flat))
        raise MeshIOError(f"{path}: {int(flat.sum())} tets have zero volume (first: tet {i} = {mesh.tets[i].tolist()}); "
                          "degenerate elements cannot be simulated or oriented")
    neg = vol < 0
    info = {"tets": mesh.num_tets, "reoriented": 0, "flipped": 0, "inverted": int(neg.sum())}
    if neg.all():
        mesh, n = mesh.oriented()
        info.update(reoriented=n, inverted=0)
    elif neg.any() and fix_orientation:
        mesh, n = mesh.oriented()
        info.update(flipped=n, inverted=0)
    elif neg.any() and not allow_mixed:
        raise MeshIOError(f"{path}: mixed orientation, {int(neg.sum())} of {mesh.num_tets} tets have negative volume "
                          f"(first: tet {int(np.argmax(neg))}); pass --orient to flip them")
    return mesh, info
