"""Tetrahedral energies of the geometry stage (method.md §5, §6): the domain API.

:class:`TetEnergies` owns the mesh topology (tets, face adjacency, boundary) and the rest
shape captured on demand (``Dm^-1`` per tet), and evaluates, as differentiable torch
scalars computed by Warp kernels:

- :meth:`TetEnergies.biharmonic`: weighted bi-harmonic energy ``sum_e w_e ||(L F)_e||^2``;
- :meth:`TetEnergies.inversion_penalty`: ``sum_e max(-det F_e, 0)^p``;
- :meth:`TetEnergies.hc_laplacian`: the two-stage HC-Laplacian energy on boundary vertices;
- :meth:`TetEnergies.biharmonic_and_inversion`: the first two from one pass over the tets
  (what a geometry step uses: F and det F computed once).

The eikonal and smoothness losses of the per-vertex field ``phi`` (method.md §5) are plain
functions, :func:`eikonal_loss` and :func:`smoothness_loss`, and :func:`phi_edge_losses`
computes both in one pass over the edges (what a topology step uses).

Example:
    >>> energies = TetEnergies(mesh, weights="surface")   # rest = mesh.vertices
    >>> x = torch.tensor(mesh.vertices, dtype=torch.float32, requires_grad=True)
    >>> loss = energies.biharmonic(x) + energies.hc_laplacian(x, lam_cond=0.0)
    >>> loss.backward()
"""

from __future__ import annotations

import numpy as np
import torch

from holowarp.ops._warp import FRESH
from holowarp.ops.tet_energy import (
    HCTopology,
    biharmonic_energy,
    deformation_gradients,
    eikonal_loss,
    hc_laplacian_energy,
    hc_topology,
    inversion_penalty,
    phi_edge_losses,
    prepare_hc_laplacian,
    prepare_tet_energies,
    smoothness_loss,
    tet_energies,
)
from holowarp.tetmesh import TetMesh

__all__ = [
    "SURFACE_WEIGHT",
    "HC_ALPHA",
    "HC_BETA",
    "TetEnergies",
    "biharmonic_weights",
    "eikonal_loss",
    "smoothness_loss",
    "phi_edge_losses",
]

#: gamma of the weighted bi-harmonic energy: weight of tets touching a surface vertex
#: (interior tets weigh 1), method.md §6.
SURFACE_WEIGHT = 5.0e-4
#: Vollmer et al.'s HC parameters: alpha mixes the original positions into the correction
#: (0 = none), beta weighs a vertex's own correction against its neighbours' mean.
HC_ALPHA = 0.0
HC_BETA = 0.5
#: Rest tets with |det Dm| below this fraction of the mean |det Dm| have no usable Dm^-1:
#: they are left out of the energies (weight 0, cut from the adjacency on both sides, so
#: rigid motions still cost nothing).
DEGENERATE_REL_VOLUME = 1.0e-12


def biharmonic_weights(tets, surface_vertices, gamma: float = SURFACE_WEIGHT, *, device=None) -> torch.Tensor:
    """Per-tet weights of the weighted bi-harmonic energy (method.md §6).

    Args:
        tets: (M, 4) vertex indices.
        surface_vertices: (S,) ids of the vertices on the current boundary faces.
        gamma: weight of tets with at least one surface vertex (< 1); others weigh 1.

    Returns:
        (M,) float64 tensor.
    """
    t = _np(tets)
    s = _np(surface_vertices)
    if t.ndim != 2 or t.shape[1] != 4:
        raise ValueError(f"biharmonic_weights: tets must have shape (M, 4), got {t.shape}")
    if not 0.0 < gamma <= 1.0:
        raise ValueError(f"biharmonic_weights: gamma must be in (0, 1], got {gamma}")
    n = int(max(t.max(initial=-1), s.max(initial=-1))) + 1
    on_surface = np.zeros(n, dtype=bool)
    on_surface[s.astype(np.int64)] = True
    touch = on_surface[t].any(axis=1)
    w = np.where(touch, float(gamma), 1.0)
    return torch.as_tensor(w, dtype=torch.float64, device=device)


class TetEnergies:
    """Energies of one tet mesh topology against a captured rest shape.

    Args:
        mesh_or_tets: a :class:`~holowarp.tetmesh.TetMesh` (its vertices are the default
            rest shape) or a (M, 4) integer array/tensor of tets.
        rest_vertices: (N, 3) rest positions. If omitted (and no TetMesh was given), the
            first energy call captures the positions it is given.
        weights: per-tet bi-harmonic weights: ``None`` (uniform 1, the ablation),
            ``"surface"`` (:func:`biharmonic_weights` with the mesh's boundary vertices and
            :data:`SURFACE_WEIGHT`) or an (M,) array/tensor.
        device: torch device for the cached tensors (default: that of ``rest_vertices`` if it
            is a tensor, else CPU). Energies move them to each call's device as needed.

    Topology (tets, face adjacency, boundary faces) is fixed per instance; after a topology
    change build a new one. ``capture_rest`` may be called any time (method.md §6 captures
    the rest mesh at the start of each geometry block).
    """

    def __init__(self, mesh_or_tets, rest_vertices=None, *, weights=None, device=None):
        if isinstance(mesh_or_tets, TetMesh):
            mesh = mesh_or_tets
            if rest_vertices is None:
                rest_vertices = mesh.vertices
        else:
            t = _np(mesh_or_tets)
            if t.ndim != 2 or t.shape[1] != 4 or not np.issubdtype(t.dtype, np.integer):
                raise ValueError(f"TetEnergies: tets must be a (M, 4) integer array, got {t.shape} {t.dtype}")
            n = int(t.max(initial=-1)) + 1
            if rest_vertices is not None:
                n = max(n, int(rest_vertices.shape[0]))
            verts = np.zeros((n, 3)) if rest_vertices is None else _np64(rest_vertices)
            mesh = TetMesh(verts, t, validate=True)
        # a placeholder (all-zero) geometry is replaced at the first capture_rest, so that the
        # boundary winding, which follows each tet's orientation, comes from real positions
        self._placeholder = rest_vertices is None
        if device is None:
            device = rest_vertices.device if isinstance(rest_vertices, torch.Tensor) else "cpu"
        self.device = torch.device(device)
        self._mesh = mesh
        self.num_vertices = mesh.num_vertices
        self.num_tets = mesh.num_tets
        self.tets = torch.as_tensor(np.array(mesh.tets, dtype=np.int32), device=self.device)  # [M, 4]
        self._adjacency_full = np.array(mesh.face_adjacency(), dtype=np.int32)
        self.adjacency = torch.as_tensor(self._adjacency_full, device=self.device)  # [M, 4]
        self._user_weights = None
        self._weights_mode = weights
        self.active = torch.ones(self.num_tets, dtype=torch.bool, device=self.device)
        self.num_degenerate_rest = 0
        self.rest_vertices = None
        self.dm_inv = None  # [M, 3, 3] float64
        self._cast: dict = {}
        self._hc_cache: tuple | None = None
        self.set_weights(weights)
        if rest_vertices is not None:
            self.capture_rest(rest_vertices)

    # ------------------------------------------------------------------ set-up
    @property
    def mesh(self) -> TetMesh:
        """The topology (with the vertices it was built with)."""
        return self._mesh

    def set_weights(self, weights=None) -> None:
        """Set the bi-harmonic weights: ``None`` (uniform), ``"surface"`` or (M,) values."""
        if weights is None:
            w = torch.ones(self.num_tets, dtype=torch.float64)
        elif isinstance(weights, str):
            if weights != "surface":
                raise ValueError(f"TetEnergies: weights must be None, 'surface' or an (M,) array, got {weights!r}")
            w = biharmonic_weights(self._mesh.tets, self._mesh.surface_vertices())
        else:
            w = torch.as_tensor(np.array(_np(weights), dtype=np.float64))
            if w.shape != (self.num_tets,):
                raise ValueError(f"TetEnergies: weights must have shape ({self.num_tets},), got {tuple(w.shape)}")
            if not torch.isfinite(w).all() or (w < 0).any():
                raise ValueError("TetEnergies: weights must be finite and non-negative")
        self._user_weights = w.to(self.device)
        self._refresh()

    def capture_rest(self, vertices) -> None:
        """Capture the rest shape: ``Dm^-1`` of every tet from ``vertices`` (N, 3).

        Tets that are degenerate at rest (see :data:`DEGENERATE_REL_VOLUME`) are excluded
        from every energy; their count is in ``num_degenerate_rest``.
        """
        v = _np64(vertices)
        if v.shape != (self.num_vertices, 3):
            raise ValueError(f"TetEnergies.capture_rest: vertices must have shape ({self.num_vertices}, 3), got {v.shape}")
        if not np.isfinite(v).all():
            raise ValueError("TetEnergies.capture_rest: vertices have non-finite coordinates")
        t = self._mesh.tets.astype(np.int64)
        c0 = v[t[:, 1]] - v[t[:, 0]]  # columns of Dm, [M, 3] each
        c1 = v[t[:, 2]] - v[t[:, 0]]
        c2 = v[t[:, 3]] - v[t[:, 0]]
        # closed-form inverse: row k of Dm^-1 is the cross product of the other two columns
        # over det (batched LAPACK inv is ~20x slower for 3x3 blocks)
        cof = np.stack([np.cross(c1, c2), np.cross(c2, c0), np.cross(c0, c1)], axis=1)  # [M, 3, 3]
        det = np.einsum("ij,ij->i", c0, cof[:, 0])
        scale = np.abs(det).mean() if len(det) else 0.0
        ok = np.abs(det) > DEGENERATE_REL_VOLUME * max(scale, np.finfo(np.float64).tiny)
        dm_inv = np.zeros_like(cof)
        dm_inv[ok] = cof[ok] / det[ok, None, None]
        if self._placeholder:
            self._mesh = TetMesh(v.copy(), self._mesh.tets, validate=False)  # TetMesh freezes its array
            self._placeholder = False
            self._hc_cache = None
        self.rest_vertices = torch.as_tensor(v, device=self.device)
        self.dm_inv = torch.as_tensor(dm_inv, device=self.device)
        self.active = torch.as_tensor(ok, device=self.device)
        self.num_degenerate_rest = int((~ok).sum())
        self._refresh()

    def _refresh(self) -> None:
        ok = self.active.cpu().numpy()
        adj = self._adjacency_full.copy()
        if not ok.all():
            adj[~ok] = -1
            nb_bad = np.zeros_like(adj, dtype=bool)
            valid = adj >= 0
            nb_bad[valid] = ~ok[adj[valid]]
            adj[nb_bad] = -1
        self.adjacency = torch.as_tensor(adj, device=self.device)
        self.weights = self._user_weights * self.active.to(torch.float64)  # [M]
        self._cast = {}

    def _rest_for(self, x: torch.Tensor):
        if not isinstance(x, torch.Tensor) or x.ndim != 2 or x.shape != (self.num_vertices, 3):
            raise ValueError(f"TetEnergies: x must be a ({self.num_vertices}, 3) float tensor, got {getattr(x, 'shape', type(x))}")
        if self.dm_inv is None:
            self.capture_rest(x.detach())
        key = (x.dtype, x.device)
        c = self._cast.get(key)
        if c is None:
            c = (
                self.tets.to(x.device),
                self.dm_inv.to(device=x.device, dtype=x.dtype).contiguous(),
                self.adjacency.to(x.device),
                self.weights.to(device=x.device, dtype=x.dtype).contiguous(),
            )
            self._cast[key] = c
        return c

    # ------------------------------------------------------------------ energies
    def deformation_gradients(self, x: torch.Tensor) -> torch.Tensor:
        """``F = Ds Dm^-1`` per tet (M, 3, 3), differentiable in ``x`` (N, 3)."""
        tets, dm_inv, _, _ = self._rest_for(x)
        return deformation_gradients(x, tets, dm_inv)

    def biharmonic(self, x: torch.Tensor) -> torch.Tensor:
        """Weighted bi-harmonic energy ``sum_e w_e ||(L F)_e||_F^2`` (a SUM over tets).

        ``L`` is the tet face-adjacency graph Laplacian (``L_ee`` = number of face
        neighbours, ``L_ee'`` = -1 for face neighbours); translations and rotations of the
        rest shape give zero energy and zero gradient.
        """
        tets, dm_inv, adj, w = self._rest_for(x)
        return biharmonic_energy(x, tets, dm_inv, adj, w)

    def inversion_penalty(self, x: torch.Tensor, p: float = 2.0) -> torch.Tensor:
        """``sum_e max(-det F_e, 0)^p`` (a SUM over tets); method.md §6 raises p from 2 to 4.

        ``det F < 0`` means the tet has flipped relative to its rest orientation.
        """
        tets, dm_inv, _, _ = self._rest_for(x)
        return inversion_penalty(x, tets, dm_inv, p)

    def biharmonic_and_inversion(self, x: torch.Tensor, p: float = 2.0, *, cache=FRESH) -> tuple[torch.Tensor, torch.Tensor]:
        """``(self.biharmonic(x), self.inversion_penalty(x, p))`` from one fused pass: the
        deformation gradients and their determinants are computed once. ``cache``: see
        :func:`holowarp.ops.tet_energy.tet_energies`."""
        tets, dm_inv, adj, w = self._rest_for(x)
        return tet_energies(x, tets, dm_inv, adj, w, p, cache=cache)

    def prepare_biharmonic_and_inversion(self, x: torch.Tensor, p: float = 2.0, *, cache, need: bool = True) -> None:
        """Run :meth:`biharmonic_and_inversion`'s kernels now into ``cache`` (a
        :class:`holowarp.ops._warp.StepCache`), so that its next call on the same ``x``, ``p``
        and cache only takes their results (:func:`holowarp.ops.tet_energy.prepare_tet_energies`:
        the geometry step runs this on a second thread while the rasteriser runs). Call
        :meth:`biharmonic_and_inversion` once on this thread first: the rest shape is
        captured there."""
        tets, dm_inv, adj, w = self._rest_for(x)
        prepare_tet_energies(x, tets, dm_inv, adj, w, p, cache=cache, need=need)

    def hc_topology(self, boundary_faces=None) -> HCTopology:
        """Surface connectivity for :meth:`hc_laplacian` (cached by the faces' contents)."""
        bf = self._mesh.boundary_faces() if boundary_faces is None else boundary_faces
        bf = _np(bf)
        if self._hc_cache is not None and np.array_equal(self._hc_cache[0], bf):
            return self._hc_cache[1]
        if bf.size and (bf.min() < 0 or bf.max() >= self.num_vertices):
            raise ValueError(f"TetEnergies.hc_laplacian: boundary_faces index vertices outside [0, {self.num_vertices})")
        topo = hc_topology(bf, device=self.device)
        self._hc_cache = (bf.copy(), topo)
        return topo

    def hc_laplacian(
        self,
        x: torch.Tensor,
        boundary_faces=None,
        lam_cond: float = 1.0,
        *,
        alpha: float = HC_ALPHA,
        beta: float = HC_BETA,
        cache=FRESH,
    ) -> torch.Tensor:
        """Two-stage HC-Laplacian energy on the boundary vertices S (method.md §6).

        ``L_HC = sum_S ||d_t||^2 + lam_cond (d_n)_-^2 + (d_n)_+^2`` with ``d_i`` = HC target
        minus ``x_i`` split along the outward area-weighted vertex normal: ``(d_n)_+`` is
        the outward part (vertex inside its target: a concavity, always pulled out),
        ``(d_n)_-`` the inward part (a bump, pulled in only when ``lam_cond > 0``). Stage 1
        uses ``lam_cond = 0``, stage 2 ``lam_cond = 1``. Targets (Vollmer et al. 1999, with
        ``alpha``, ``beta``; original positions = the captured rest shape) and normals are
        computed from ``x`` and held constant (stop-gradient), so the gradient pulls each
        vertex towards its target. See :func:`holowarp.ops.tet_energy.hc_energy` (computed by
        :func:`holowarp.ops.tet_energy.hc_laplacian_energy`, targets and energy in one pass).

        Args:
            x: (N, 3) vertex positions.
            boundary_faces: (B, 3) outward-wound boundary faces (global ids); default: the
                boundary of this instance's tets.
            lam_cond: weight of the inward normal part (0 in stage 1, 1 in stage 2).
            cache: see :func:`holowarp.ops.tet_energy.hc_laplacian_energy`.
        """
        topo, x_orig = self._hc_args(x, boundary_faces, alpha)
        return hc_laplacian_energy(x, topo, lam_cond, x_orig=x_orig, alpha=alpha, beta=beta, cache=cache)

    def prepare_hc_laplacian(self, x: torch.Tensor, boundary_faces=None, lam_cond: float = 1.0, *,
                             alpha: float = HC_ALPHA, beta: float = HC_BETA, cache, need: bool = True) -> None:
        """Run :meth:`hc_laplacian`'s kernels now into ``cache``, for its next call with the
        same arguments to take (:func:`holowarp.ops.tet_energy.prepare_hc_laplacian`; see
        :meth:`prepare_biharmonic_and_inversion`)."""
        topo, x_orig = self._hc_args(x, boundary_faces, alpha)
        prepare_hc_laplacian(x, topo, lam_cond, x_orig=x_orig, alpha=alpha, beta=beta, cache=cache, need=need)

    def _hc_args(self, x: torch.Tensor, boundary_faces, alpha: float):
        """The surface connectivity on ``x``'s device and the original positions (None
        with ``alpha`` 0) of :meth:`hc_laplacian`."""
        if not isinstance(x, torch.Tensor) or x.shape != (self.num_vertices, 3):
            raise ValueError(f"TetEnergies: x must be a ({self.num_vertices}, 3) float tensor, got {getattr(x, 'shape', type(x))}")
        topo = self.hc_topology(boundary_faces)
        if topo.surf_ids.device != x.device:
            fields = ("surf_ids", "nbr_offsets", "nbr_ids", "faces_global", "faces_local")
            topo = HCTopology(*(getattr(topo, f).to(x.device) for f in fields))
        x_orig = None
        if alpha != 0.0:
            if self.rest_vertices is None:
                self.capture_rest(x.detach())
            x_orig = self._rest_as(x)
        return topo, x_orig

    def _rest_as(self, x: torch.Tensor) -> torch.Tensor:
        """The captured rest positions in ``x``'s dtype and device, cast once per pair."""
        key = ("rest", x.dtype, x.device)
        r = self._cast.get(key)
        if r is None or r[0] is not self.rest_vertices:
            r = self._cast[key] = (self.rest_vertices, self.rest_vertices.to(device=x.device, dtype=x.dtype).contiguous())
        return r[1]


def _np(a) -> np.ndarray:
    return a.detach().cpu().numpy() if isinstance(a, torch.Tensor) else np.asarray(a)


def _np64(v) -> np.ndarray:
    if isinstance(v, torch.Tensor):
        v = v.detach().cpu().numpy()
    return np.array(v, dtype=np.float64)  # a writable copy (TetMesh arrays are read-only)
