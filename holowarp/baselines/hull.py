"""Visual-hull baseline: silhouette carving -> marching cubes -> fTetWild.

The first thing anyone compares a multi-view reconstruction against, and the bar holowarp
must clear. Steps:

1. Region: the point nearest (least squares) to every camera's optical axis is the object
   centre; a cube around it whose half-size is the nearest camera distance holds anything
   all cameras can see in front of them.
2. Coarse carve (``coarse_grid`` nodes along the cube's side, :func:`holowarp.carve.hull_grid`)
   -> tight bounding box of the hull, padded.
3. Fine carve at ``grid`` nodes along the longest side of that box (cubic cells): the
   field ``min over training views of the mask at the node's projection``. The box is then
   shrunk to the carved nodes (+2 cells) and carved again, so ``grid`` spans the hull
   itself; if the hull touches the box, the box grows and the carve is repeated.
4. Marching cubes (VTK flying edges through pyvista) at ``threshold`` = 0.5, largest
   connected surface piece, decimated to ``max_surface_faces`` triangles.
5. fTetWild (``holowarp.tetmesh.tetrahedralize_surface``, epsilon 1e-3), orient, keep the
   largest face-connected component, drop unused vertices.

Only training views carve (test views stay held out). :func:`run_visual_hull` (and the
command ``python -m holowarp.baselines.visual_hull DATASET --out DIR [--grid 128]``) writes
``DIR/tetmesh.vtu``, ``DIR/surface.obj`` (the tet mesh's boundary), ``DIR/hull_surface.obj``
(the marching-cubes surface) and ``DIR/report.json``.
"""

from __future__ import annotations

import os
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from holowarp.carve import hull_grid, look_region
from holowarp.errors import InputError

__all__ = [
    "VisualHullSettings",
    "VisualHullError",
    "hull_surface",
    "visual_hull",
    "run_visual_hull",
]


class VisualHullError(InputError):
    """The visual hull could not be built; the message says which step and why."""


@dataclass(frozen=True)
class VisualHullSettings:
    """Knobs of the visual-hull baseline.

    Attributes:
        grid: nodes along the longest side of the hull's bounding box.
        threshold: iso level of the carved field (mask > 0.5 in every view).
        coarse_grid: nodes per side of the first, region-finding carve.
        max_surface_faces: the marching-cubes surface is decimated (VTK quadric decimation)
            to about this many triangles before fTetWild, which is 2-3x faster on it; the
            fTetWild envelope, not the input tessellation, bounds the surface error.
        edge_length_fac: fTetWild ideal edge length / bbox diagonal (interior tet size; the
            surface is held to the envelope whatever this is).
        epsilon: fTetWild envelope, relative to the bbox (method.md §4: 1e-3).
        outside_is_empty: a node projecting outside an image is empty space (true for the
            synthetic protocol, where every view sees the whole object).
    """

    grid: int = 128
    threshold: float = 0.5
    coarse_grid: int = 64
    max_surface_faces: int = 12_000
    edge_length_fac: float = 0.03
    epsilon: float = 1e-3
    outside_is_empty: bool = True


def _marching_cubes(field: np.ndarray, origin, spacing: float, level: float):
    """Triangle surface (V, F) of the ``level`` set of ``field`` (nodes at origin + ijk*spacing)."""
    import pyvista as pv

    padded = np.zeros(tuple(s + 2 for s in field.shape), np.float32)
    padded[1:-1, 1:-1, 1:-1] = field  # a zero border closes the surface
    img = pv.ImageData(dimensions=padded.shape, spacing=(spacing,) * 3, origin=tuple(np.asarray(origin) - spacing))
    img.point_data["occ"] = padded.ravel(order="F")
    surf = img.contour([level], scalars="occ", method="flying_edges")
    if surf.n_cells == 0:
        return np.zeros((0, 3)), np.zeros((0, 3), np.int32)
    surf = surf.triangulate().clean()
    surf = surf.connectivity("largest")
    surf = surf.clean()
    faces = surf.faces.reshape(-1, 4)[:, 1:].astype(np.int32)
    # VTK's contour winds triangles with normals towards increasing scalar (inwards here).
    verts = np.asarray(surf.points, dtype=np.float64)
    vol = np.einsum("ij,ij->i", verts[faces[:, 0]], np.cross(verts[faces[:, 1]], verts[faces[:, 2]])).sum() / 6.0
    if vol < 0:
        faces = faces[:, [0, 2, 1]]
    return verts, faces


def hull_surface(dataset, *, settings: VisualHullSettings | None = None, device: str = "cpu", bar=None):
    """Carve and extract the visual-hull surface.

    Returns:
        ``(vertices (V, 3) float64, faces (F, 3) int32, info dict)``.

    Raises:
        VisualHullError: no training view, or the masks leave nothing.
    """
    st = settings or VisualHullSettings()
    views = dataset.train_idx if len(dataset.train_idx) else np.arange(dataset.num_views)
    if len(views) == 0:
        raise VisualHullError("the dataset has no views to carve with")
    if st.grid < 8 or st.coarse_grid < 8:
        raise VisualHullError(f"grid must be >= 8 nodes, got grid={st.grid}, coarse_grid={st.coarse_grid}")
    centre, half = look_region(dataset.viewmats[views])
    if not np.isfinite(half) or half <= 0:
        raise VisualHullError("cameras coincide with the estimated object centre; cannot place the carving grid")
    n = st.coarse_grid
    sp = 2.0 * half / (n - 1)
    origin = centre - half
    coarse = hull_grid(dataset, views, origin, sp, (n, n, n), outside_is_empty=st.outside_is_empty, device=device)
    occ = np.argwhere(coarse > 0.0)
    if len(occ) == 0:
        raise VisualHullError(
            f"every node of the region (centre {centre.round(3).tolist()}, half-size {half:.3g}) was carved away: "
            "masks and cameras disagree (wrong poses, wrong axes convention, or empty masks)"
        )
    lo = origin + (occ.min(0) - 1) * sp
    hi = origin + (occ.max(0) + 1) * sp
    if bar is not None:
        bar.update(1)
    info = {"centre": centre.tolist(), "region_half_size": half, "carving_views": int(len(views))}
    for attempt in range(6):
        ext = hi - lo
        spacing = float(ext.max()) / (st.grid - 1)
        shape = tuple(int(x) for x in np.ceil(ext / spacing - 1e-9).astype(int) + 1)
        field = hull_grid(dataset, views, lo, spacing, shape, outside_is_empty=st.outside_is_empty, device=device)
        inside = field > st.threshold
        if not inside.any():
            raise VisualHullError("no grid node projects inside every training mask (mask > 0.5): the hull is empty")
        idx = np.argwhere(inside)
        imin, imax = idx.min(0), idx.max(0)
        touches = bool((imin == 0).any() or (imax == np.array(shape) - 1).any())
        if touches:  # the hull may continue outside the box: grow it
            lo, hi = lo - 0.25 * ext, hi + 0.25 * ext
            continue
        # Shrink to the hull plus two cells so the grid resolution is spent on the object.
        new_lo = lo + (imin - 2) * spacing
        new_hi = lo + (imax + 2) * spacing
        if np.all(np.abs(new_lo - lo) <= 2.5 * spacing) and np.all(np.abs(new_hi - (lo + (np.array(shape) - 1) * spacing)) <= 2.5 * spacing):
            break
        lo, hi = new_lo, new_hi
    if bar is not None:
        bar.update(1)
    verts, faces = _marching_cubes(field, lo, spacing, st.threshold)
    if len(faces) < 4:
        raise VisualHullError("marching cubes produced no closed surface")
    mc_faces = len(faces)
    if len(faces) > st.max_surface_faces:
        from holowarp.tetmesh import decimate_surface

        verts, faces = decimate_surface(verts, faces, st.max_surface_faces)
    info.update(
        grid_shape=list(shape),
        spacing=spacing,
        bbox_min=lo.tolist(),
        bbox_max=(lo + spacing * (np.array(shape) - 1)).tolist(),
        occupied_nodes=int(inside.sum()),
        marching_cubes_faces=int(mc_faces),
        surface_vertices=int(len(verts)),
        surface_faces=int(len(faces)),
    )
    if bar is not None:
        bar.update(1)
    return verts, faces, info


def visual_hull(dataset, *, grid: int = 128, settings: VisualHullSettings | None = None, device: str = "cpu", progress: bool = False, return_info: bool = False):
    """The visual hull of ``dataset``'s training masks as one tet mesh.

    Args:
        dataset: :class:`holowarp.data.Dataset` (or a dataset folder path).
        grid: nodes along the longest side of the hull's bounding box (``settings.grid``
            wins when ``settings`` is given).
        device: Warp device of the carving kernel.
        progress: tqdm bar over the steps.
        return_info: also return a dict of counts and settings.

    Returns:
        :class:`holowarp.TetMesh` (positively oriented, one face-connected component, in
        the dataset's world frame), or ``(mesh, info)``.
    """
    from holowarp.progress import bar as progress_bar
    from holowarp.tetmesh import TetMeshError, tetrahedralize_surface

    if isinstance(dataset, (str, os.PathLike)):
        from holowarp.data.loaders import load_dataset

        dataset = load_dataset(dataset)
    st = settings or VisualHullSettings(grid=grid)
    t0 = time.perf_counter()
    bar = progress_bar(5, desc="visual hull", unit="step", progress=progress)
    try:
        bar.set_postfix_str("carving")
        V, F, info = hull_surface(dataset, settings=st, device=device, bar=bar)
        t1 = time.perf_counter()
        bar.set_postfix_str(f"fTetWild on {len(F)} triangles")
        try:
            mesh = tetrahedralize_surface(V, F, edge_length_fac=st.edge_length_fac, epsilon=st.epsilon)
        except TetMeshError as e:
            raise VisualHullError(f"fTetWild failed on the hull surface: {e}") from e
        bar.update(1)
        t2 = time.perf_counter()
        mesh, n_flipped = mesh.oriented()
        mesh, comp = mesh.keep_largest_component()
        mesh, _ = mesh.remove_unused_vertices()
        bar.update(1)
    finally:
        bar.close()
    info.update(
        settings=asdict(st),
        flipped=int(n_flipped),
        components_before=int(comp.get("components", 1)),
        removed_tets=int(comp.get("removed_tets", 0)),
        vertices=int(mesh.num_vertices),
        tets=int(mesh.num_tets),
        seconds={"carve_and_surface": t1 - t0, "ftetwild": t2 - t1, "total": time.perf_counter() - t0},
        hull_surface=(V, F),
    )
    return (mesh, info) if return_info else mesh


def run_visual_hull(dataset, out_dir: str | os.PathLike, *, grid: int = 128, settings: VisualHullSettings | None = None, device: str = "cpu", progress: bool = True) -> dict:
    """Build the visual hull and write ``tetmesh.vtu``, ``surface.obj``, ``hull_surface.obj``
    and ``report.json`` into ``out_dir``. Returns the report."""
    from holowarp.fileio import atomic_write_json
    from holowarp.mesh_io import write_tetmesh
    from holowarp.surface_io import write_surface

    from holowarp.fileio import check_output_dir

    out = check_output_dir(out_dir)
    src = str(dataset) if isinstance(dataset, (str, os.PathLike)) else str(getattr(dataset, "root", ""))
    mesh, info = visual_hull(dataset, grid=grid, settings=settings, device=device, progress=progress, return_info=True)
    out.mkdir(parents=True, exist_ok=True)
    V, F = info.pop("hull_surface")
    write_tetmesh(out / "tetmesh.vtu", mesh)
    write_surface(out / "surface.obj", mesh)
    write_surface(out / "hull_surface.obj", (V, F))
    report = {"method": "visual_hull", "dataset": src, **info, "summary": mesh.summary()}
    atomic_write_json(out / "report.json", report)
    return report
