"""Structured tetrahedral meshes of boxes (and boxes with cells removed).

Used by tests, benchmarks and simulation scenes as exact, cheap meshes whose volume,
boundary and topology are known in closed form.
"""

from __future__ import annotations

import numpy as np

from holowarp.tetmesh import TetMesh

__all__ = ["box_tetmesh", "KUHN_TETS", "FIVE_TETS"]

# Hex corner k sits at (k & 1, (k >> 1) & 1, (k >> 2) & 1).
#: Kuhn (Freudenthal) split of a cube into 6 positive tets around the 0-7 diagonal. The
#: split is translation invariant, so neighbouring cells share conforming faces.
KUHN_TETS = np.array(
    [[0, 1, 3, 7], [0, 3, 2, 7], [0, 2, 6, 7], [0, 6, 4, 7], [0, 4, 5, 7], [0, 5, 1, 7]],
    dtype=np.int64,
)
#: Split of a cube into 5 tets: four corner tets and one central regular-ish tet. It is
#: conforming across cells only when alternate cells are mirrored, which box_tetmesh does.
FIVE_TETS = np.array(
    [[0, 1, 2, 4], [1, 3, 2, 7], [1, 4, 5, 7], [2, 4, 7, 6], [1, 2, 4, 7]], dtype=np.int64
)
_FIVE_TETS_MIRRORED = np.array(
    [[0, 1, 3, 5], [0, 3, 2, 6], [0, 5, 4, 6], [3, 5, 6, 7], [0, 3, 6, 5]], dtype=np.int64
)


def box_tetmesh(
    cells=(1, 1, 1),
    size=(1.0, 1.0, 1.0),
    origin=(0.0, 0.0, 0.0),
    *,
    split: int = 6,
    cell_mask=None,
) -> TetMesh:
    """Tet mesh of an axis-aligned box made of ``nx × ny × nz`` hexahedral cells.

    Args:
        cells: (nx, ny, nz) number of cells per axis.
        size: (sx, sy, sz) box extent in metres.
        origin: position of the box's minimum corner.
        split: 6 (Kuhn split) or 5 (five tets per cell, alternating mirror for conformity).
        cell_mask: optional (nx, ny, nz) bool array; cells that are False are left out
            (e.g. remove the centre column of a 3×3×1 box to get a solid torus).

    Returns:
        A positively oriented, conforming :class:`TetMesh` with unused vertices removed.
    """
    nx, ny, nz = (int(c) for c in cells)
    if min(nx, ny, nz) < 1:
        raise ValueError(f"box_tetmesh: cells must be >= 1, got {cells}")
    if split not in (5, 6):
        raise ValueError(f"box_tetmesh: split must be 5 or 6, got {split}")
    sx, sy, sz = (float(s) for s in size)
    gx, gy, gz = np.meshgrid(
        np.linspace(0, sx, nx + 1), np.linspace(0, sy, ny + 1), np.linspace(0, sz, nz + 1), indexing="ij"
    )
    V = np.stack([gx, gy, gz], axis=-1).reshape(-1, 3) + np.asarray(origin, dtype=np.float64)

    def vid(i, j, k):
        return (i * (ny + 1) + j) * (nz + 1) + k

    ci, cj, ck = np.meshgrid(np.arange(nx), np.arange(ny), np.arange(nz), indexing="ij")
    if cell_mask is not None:
        mask = np.asarray(cell_mask, dtype=bool)
        if mask.shape != (nx, ny, nz):
            raise ValueError(f"box_tetmesh: cell_mask must have shape {(nx, ny, nz)}, got {mask.shape}")
    else:
        mask = np.ones((nx, ny, nz), dtype=bool)
    ci, cj, ck = ci[mask], cj[mask], ck[mask]
    corners = np.stack(
        [vid(ci + (c & 1), cj + ((c >> 1) & 1), ck + ((c >> 2) & 1)) for c in range(8)], axis=1
    )  # [C, 8]
    if split == 6:
        T = corners[:, KUHN_TETS].reshape(-1, 4)
    else:
        parity = ((ci + cj + ck) % 2).astype(bool)
        T = np.where(parity[:, None, None], corners[:, _FIVE_TETS_MIRRORED], corners[:, FIVE_TETS])
        T = T.reshape(-1, 4)
    mesh, _ = TetMesh(V, T).oriented()
    mesh, _ = mesh.remove_unused_vertices()
    return mesh
