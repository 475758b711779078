"""The hybrid representation of HoloTetSphere: one tet mesh, one surfel bound to each tet.

Each tet ``e`` carries one 2D-Gaussian surfel at its centroid, i.e. with fixed barycentric
coordinates beta = (1/4, 1/4, 1/4, 1/4) (method.md §4): moving the tet's vertices moves the
surfel. Colour and rotation are learnable per surfel. Opacity comes either from

- the continuous field (method.md §5): a learnable scalar ``phi`` per VERTEX (SDF-like,
  negative inside), ``alpha_e = sigmoid(-s * kappa * mean(phi[tet_e]))`` with a learnable
  sharpness ``kappa`` whose product with ``s`` is clamped to ``kappa_clamp``; or
- a free per-tet opacity logit: after the first prune (method.md §5, initialised from the
  field), and throughout in the ablation "w/o continuous opacity".

Surfel scales are fixed at ``scale_factor`` times the mean centroid-to-vertex distance of the
host tet until the first prune, after which they become learnable (log-scale).

All learnable tensors are plain ``torch.nn.Parameter`` attributes so the pipeline builds its
Adam groups explicitly, and everything is serialisable with :meth:`state_dict`.
"""

from __future__ import annotations

import numpy as np
import torch

from holowarp.config import TopologyConfig
from holowarp.tetmesh import TetMesh

__all__ = ["TetGaussians", "tet_mean_radius"]


def tet_mean_radius(vertices: torch.Tensor, tets: torch.Tensor) -> torch.Tensor:
    """Mean distance (M,) from each tet's centroid to its four vertices."""
    P = vertices[tets]  # [M, 4, 3]
    c = P.mean(dim=1, keepdim=True)
    return (P - c).norm(dim=-1).mean(dim=1)


def _logit(p: torch.Tensor) -> torch.Tensor:
    p = p.clamp(1e-6, 1 - 1e-6)
    return torch.log(p) - torch.log1p(-p)


class TetGaussians:
    """Tet mesh + bound surfels.

    Args:
        mesh: the (positively oriented) tet mesh.
        colors: (M, 3) initial colours in [0, 1] (grey if None).
        phi: (V,) initial vertex field (``-config.phi_inside`` everywhere if None).
        config: the :class:`holowarp.config.TopologyConfig` giving kappa's initial value and
            clamp, s, the surfel scale factor and the free opacities' initial value.
        free_opacity: start with free per-tet opacities instead of the vertex field.
        device: torch device.
        seed: seeds the random initial surfel orientations.

    Attributes (torch tensors on ``device``):
        vertices [V, 3] float32 (a Parameter; only mesh blocks give it to an optimiser),
        tets [M, 4] int64, phi [V] (Parameter), kappa [] (Parameter), opacity_logit [M]
        (Parameter, used when ``free_opacity``), color_logit [M, 3], quats [M, 4] wxyz,
        log_scales [M, 2].
    """

    def __init__(self, mesh: TetMesh, *, colors=None, phi=None, config: TopologyConfig = TopologyConfig(),
                 free_opacity: bool = False, device="cpu", seed: int = 0):
        dev = torch.device(device)
        P = torch.nn.Parameter
        M, V = mesh.num_tets, mesh.num_vertices
        self.device = dev
        self.s = float(config.s)
        self.kappa_clamp = (float(config.kappa_clamp[0]), float(config.kappa_clamp[1]))
        self.scale_factor = float(config.scale_factor)
        self.vertices = P(torch.tensor(np.array(mesh.vertices), dtype=torch.float32, device=dev))
        self.tets = torch.tensor(np.array(mesh.tets), dtype=torch.int64, device=dev)
        if phi is None:
            phi = np.full(V, -config.phi_inside)
        self.phi = P(torch.as_tensor(np.asarray(phi), dtype=torch.float32, device=dev).clone())
        self.kappa = P(torch.tensor(float(config.kappa_init), dtype=torch.float32, device=dev))
        self.free_opacity = bool(free_opacity)
        self.opacity_logit = P(torch.full((M,), float(_logit(torch.tensor(config.initial_opacity))), device=dev))
        if colors is None:
            colors = np.full((M, 3), 0.5)
        self.color_logit = P(_logit(torch.as_tensor(np.asarray(colors), dtype=torch.float32, device=dev)).clone())
        # Random initial orientations: no direction is privileged inside a hull.
        g = torch.Generator().manual_seed(int(seed))
        q = torch.randn((M, 4), generator=g)
        self.quats = P((q / q.norm(dim=1, keepdim=True)).to(dev))
        with torch.no_grad():
            r = tet_mean_radius(self.vertices, self.tets) * self.scale_factor
        self.log_scales = P(torch.log(r.clamp_min(1e-8))[:, None].repeat(1, 2).contiguous())

    # ------------------------------------------------------------------ views of the state
    @property
    def num_tets(self) -> int:
        return int(self.tets.shape[0])

    @property
    def num_vertices(self) -> int:
        return int(self.vertices.shape[0])

    def mesh(self) -> TetMesh:
        """The current tet mesh (float64 copy of the vertices)."""
        return TetMesh(self.vertices.detach().cpu().double().numpy(), self.tets.cpu().numpy(), validate=False)

    def means(self, vertices: torch.Tensor | None = None) -> torch.Tensor:
        """Surfel centres [M, 3]: the tet centroids (beta = 1/4 each), differentiable in x.

        ``vertices`` (V, 3) overrides the model's positions (e.g. a block's rest shape)."""
        from holowarp.ops.tet_energy import tet_mean

        v = self.vertices if vertices is None else vertices
        return tet_mean(v, self._tets_i32())

    def _tets_i32(self) -> torch.Tensor:
        """``tets`` as int32 for the Warp ops, converted once per topology (cached against the
        tensor object and its in-place version)."""
        cached = getattr(self, "_tets32", None)
        if cached is None or cached[0] is not self.tets or cached[1] != self.tets._version:
            cached = self._tets32 = (self.tets, self.tets._version, self.tets.to(torch.int32).contiguous())
        return cached[2]

    def sharpness(self) -> torch.Tensor:
        """s * kappa clamped to ``kappa_clamp`` (method.md §5)."""
        return (self.s * self.kappa).clamp(*self.kappa_clamp)

    def field_opacities(self) -> torch.Tensor:
        """Opacities [M] from the vertex field: sigmoid(-s kappa mean(phi[tet]))."""
        from holowarp.ops.tet_energy import tet_mean

        phi_bar = tet_mean(self.phi, self._tets_i32())
        return torch.sigmoid(-self.sharpness() * phi_bar)

    def opacities(self) -> torch.Tensor:
        """Current per-surfel opacities [M] in (0, 1)."""
        if self.free_opacity:
            return torch.sigmoid(self.opacity_logit)
        return self.field_opacities()

    def colors(self) -> torch.Tensor:
        return torch.sigmoid(self.color_logit)

    def scales(self) -> torch.Tensor:
        return torch.exp(self.log_scales)

    def render(self, viewmat, K, width: int, height: int, *, background=None, vertices=None) -> dict:
        """Render the bound surfels with :func:`holowarp.ops.rasterize_surfels`
        (``vertices`` optionally overrides the positions the surfels are bound to)."""
        from holowarp.ops import rasterize_surfels

        return rasterize_surfels(
            self.means(vertices),
            self.quats,
            self.scales(),
            self.opacities(),
            self.colors(),
            # The rasteriser reads the camera on the host: keep it there (float64).
            torch.as_tensor(viewmat, dtype=torch.float64),
            torch.as_tensor(K, dtype=torch.float64),
            int(width),
            int(height),
            background=background,
        )

    # ------------------------------------------------------------------ topology changes
    def reset_scales(self) -> None:
        """Scale = scale_factor * mean centroid-to-vertex distance of the host tet (§5)."""
        with torch.no_grad():
            r = tet_mean_radius(self.vertices, self.tets) * self.scale_factor
            self.log_scales.data = torch.log(r.clamp_min(1e-8))[:, None].repeat(1, 2).contiguous()

    def freeze_opacity_from_field(self) -> None:
        """Switch to free per-tet opacities initialised from the current field (§5)."""
        if not self.free_opacity:
            with torch.no_grad():
                self.opacity_logit.data = _logit(self.field_opacities()).contiguous()
            self.free_opacity = True

    def keep(self, keep_tets) -> np.ndarray:
        """Keep only the tets in ``keep_tets`` (bool (M,) or indices); drop unused vertices.

        Surviving surfels keep their colour, rotation, scale and opacity; surviving vertices
        keep their position and phi. Returns old-to-new vertex ids (V_old,), -1 = removed.
        """
        keep_tets = torch.as_tensor(np.asarray(keep_tets), device=self.device)
        if keep_tets.dtype == torch.bool:
            keep_tets = torch.nonzero(keep_tets).squeeze(1)
        tets = self.tets[keep_tets]
        used = torch.zeros(self.num_vertices, dtype=torch.bool, device=self.device)
        used[tets.reshape(-1)] = True
        old_to_new = torch.full((self.num_vertices,), -1, dtype=torch.int64, device=self.device)
        old_to_new[used] = torch.arange(int(used.sum()), device=self.device)
        P = torch.nn.Parameter
        with torch.no_grad():
            self.tets = old_to_new[tets]
            self.vertices = P(self.vertices.data[used].clone())
            self.phi = P(self.phi.data[used].clone())
            self.opacity_logit = P(self.opacity_logit.data[keep_tets].clone())
            self.color_logit = P(self.color_logit.data[keep_tets].clone())
            self.quats = P(self.quats.data[keep_tets].clone())
            self.log_scales = P(self.log_scales.data[keep_tets].clone())
        return old_to_new.cpu().numpy()

    def apply_cleanup(self, kept, mesh: TetMesh) -> None:
        """Follow a cleanup (method.md §7) that kept input tets ``kept`` (K,) and produced
        ``mesh`` (its tets in that order, possibly with two vertices swapped, unused vertices
        removed in increasing id order, knife ridges blunted). Surfels follow their tets; a
        swap keeps a tet's centroid, and the vertices take ``mesh``'s positions.

        Raises:
            ValueError: ``mesh`` is not a cleanup of this model's mesh (other vertex set).
        """
        self.keep(kept)
        if mesh.num_vertices != self.num_vertices or mesh.num_tets != self.num_tets:
            raise ValueError(
                f"cleanup result ({mesh.num_tets} tets, {mesh.num_vertices} vertices) does not match the surfel "
                f"model after keeping its tets ({self.num_tets} tets, {self.num_vertices} vertices)"
            )
        self.tets = torch.tensor(np.array(mesh.tets), dtype=torch.int64, device=self.device)
        with torch.no_grad():
            x = torch.tensor(np.array(mesh.vertices), dtype=self.vertices.dtype, device=self.device)
            self.vertices = torch.nn.Parameter(x)

    def apply_improve(self, mesh: TetMesh, parent) -> None:
        """Follow the element improvement (method.md §7b) that turned this model's mesh into
        ``mesh`` and gave each output tet an input ``parent`` (K,) it derives from.

        Each surfel takes its parent's colour, rotation and opacity; its scales are the
        parent's times the ratio of the two tets' mean radii, so a split tet's surfel shrinks
        with it (flips and smoothing change sizes a little). Vertices are ``mesh``'s; phi (not
        used once opacities are free) is the mean over a vertex's tets of their parent's mean phi.
        """
        tets = torch.tensor(np.array(mesh.tets), dtype=torch.int64, device=self.device)
        parent = self._parents(parent, tets, "apply_improve")
        x = torch.tensor(np.array(mesh.vertices), dtype=torch.float32, device=self.device)
        with torch.no_grad():
            phi_t = self.phi.data[self.tets].mean(dim=1)[parent]
            acc = torch.zeros(x.shape[0], device=self.device).index_add_(0, tets.reshape(-1), phi_t.repeat_interleave(4))
            cnt = torch.zeros(x.shape[0], device=self.device).index_add_(0, tets.reshape(-1), torch.ones(tets.numel(), device=self.device))
            self._follow_parents(x, tets, parent, acc / cnt.clamp_min(1.0))

    def apply_refine(self, vertices, tets, parent, ends) -> None:
        """Follow a refinement by bisection (:func:`holowarp.refine.bisect_longest_edges`):
        ``vertices`` (N', 3) keep this model's N first, the new ones being midpoints of
        ``ends`` (N' - N, 2) in creation order; ``tets`` (K, 4) with input ``parent`` (K,).

        phi is interpolated linearly at the midpoints, so the piecewise-linear field (and its
        zero level set) is unchanged; each child surfel takes its parent's colour, rotation
        and opacity, with scales shrunk by the ratio of the tets' mean radii (as
        :meth:`apply_improve` does). Adam moments are not carried: the optimisers are rebuilt
        after every topology change (:class:`holowarp.stages.topology.GaussianOptimizers`).
        """
        x = torch.as_tensor(np.asarray(vertices), dtype=torch.float32, device=self.device)
        ends = np.asarray(ends, dtype=np.int64).reshape(-1, 2)
        N = self.num_vertices
        if x.shape != (N + len(ends), 3) or (len(ends) and ends.max() >= N + len(ends)):
            raise ValueError(f"apply_refine: {x.shape[0]} vertices for {N} old + {len(ends)} midpoints")
        tets = torch.as_tensor(np.asarray(tets, dtype=np.int64), device=self.device)
        parent = self._parents(parent, tets, "apply_refine")
        phi = np.concatenate([self.phi.detach().cpu().double().numpy(), np.zeros(len(ends))])
        # A midpoint may sit on an edge to an earlier midpoint: sweep until every value is
        # final (as many sweeps as the deepest chain, a few per refinement round).
        for _ in range(len(ends) + 1):
            mid = 0.5 * (phi[ends[:, 0]] + phi[ends[:, 1]])
            if np.array_equal(mid, phi[N:]):
                break
            phi[N:] = mid
        self._follow_parents(x, tets, parent, torch.as_tensor(phi, dtype=torch.float32, device=self.device))

    def _parents(self, parent, tets: torch.Tensor, caller: str) -> torch.Tensor:
        """``parent`` as (K,) int64 ids of this model's tets, one per row of ``tets`` (K, 4)."""
        parent = torch.as_tensor(np.asarray(parent, dtype=np.int64), device=self.device)
        if parent.shape != (tets.shape[0],) or (tets.shape[0] and (parent.min() < 0 or parent.max() >= self.num_tets)):
            raise ValueError(f"{caller}: parent must be ({tets.shape[0]},) ids of the model's {self.num_tets} tets")
        return parent

    def _follow_parents(self, x: torch.Tensor, tets: torch.Tensor, parent: torch.Tensor, phi: torch.Tensor) -> None:
        """Take the mesh (x (N', 3), tets (K, 4)) and field phi (N',); each surfel its parent's
        (K,) colour, rotation and opacity, its scales times the ratio of the tets' mean radii."""
        P = torch.nn.Parameter
        with torch.no_grad():
            ratio = tet_mean_radius(x, tets) / tet_mean_radius(self.vertices.data, self.tets)[parent].clamp_min(1e-12)
            self.phi = P(phi)
            self.vertices = P(x)
            self.tets = tets
            self.opacity_logit = P(self.opacity_logit.data[parent].clone())
            self.color_logit = P(self.color_logit.data[parent].clone())
            self.quats = P(self.quats.data[parent].clone())
            self.log_scales = P((self.log_scales.data[parent] + torch.log(ratio.clamp_min(1e-6))[:, None]).contiguous())

    # ------------------------------------------------------------------ (de)serialisation
    _TENSORS = ("vertices", "tets", "phi", "kappa", "opacity_logit", "color_logit", "quats", "log_scales")

    def state_dict(self) -> dict:
        d = {k: getattr(self, k).detach().cpu().clone() for k in self._TENSORS}
        d.update(free_opacity=self.free_opacity, s=self.s, kappa_clamp=self.kappa_clamp, scale_factor=self.scale_factor)
        return d

    @classmethod
    def from_state_dict(cls, d: dict, *, device="cpu") -> "TetGaussians":
        obj = cls.__new__(cls)
        obj.device = torch.device(device)
        obj.load_state_dict(d)
        return obj

    def load_state_dict(self, d: dict) -> None:
        """Become the model :meth:`state_dict` saved, in place, on this model's device (new
        parameters: optimisers built on the old ones no longer apply)."""
        self.s = float(d["s"])
        self.kappa_clamp = tuple(d["kappa_clamp"])
        self.scale_factor = float(d["scale_factor"])
        self.free_opacity = bool(d["free_opacity"])
        for k in self._TENSORS:
            t = d[k].to(self.device)
            setattr(self, k, t if k == "tets" else torch.nn.Parameter(t.clone()))
