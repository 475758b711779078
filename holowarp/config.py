"""Every number of the reconstruction, in one typed configuration per stage, with presets.

The paper's numbers (method.md §3–§8) appear here once, named, with their section. The two
presets differ only in numbers:

- ``paper``: the paper's exact schedule (10k stage-0 iterations, 30k main iterations with
  prunes at 15k/20k/25k and 5k-iteration mesh blocks at 20k and 25k) at 512×512.
- ``fast``: every iteration count multiplied by ONE factor (:data:`FAST_FACTOR`) and a lower
  resolution, keeping the order of events; sized to run on a laptop CPU in minutes.

``ReconConfig.scaled(factor)`` builds any other point on that line, which is how tests run a
few hundred iterations of the real pipeline.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field, replace

__all__ = [
    "FAST_FACTOR",
    "Schedule",
    "Stage0Config",
    "TetInitConfig",
    "TopologyConfig",
    "GeometryConfig",
    "ReconConfig",
    "preset",
    "PRESETS",
]

#: The single factor the ``fast`` preset applies to every iteration count of ``paper``.
FAST_FACTOR = 0.08


@dataclass(frozen=True)
class Schedule:
    """Order of events (method.md §8). Iterations count main-loop (Gaussian) steps; mesh
    blocks are inserted at their start iteration and do not advance the main counter.

    Attributes:
        stage0_iters: 2DGS iterations of stage 0 (§3; paper 10k).
        main_iters: main-loop iterations (paper 30k).
        topology_until: end of the topology-optimisation phase, where the first prune
            happens (paper 15k).
        prune_at: main iterations at which tets with alpha < threshold are pruned.
        mesh_blocks_at: main iterations at which a mesh-only block is inserted (after the
            prune of that iteration).
        mesh_block_iters: iterations of each mesh-only block (paper 5k).
    """

    stage0_iters: int = 10_000
    main_iters: int = 30_000
    topology_until: int = 15_000
    prune_at: tuple[int, ...] = (15_000, 20_000, 25_000)
    mesh_blocks_at: tuple[int, ...] = (20_000, 25_000)
    mesh_block_iters: int = 5_000

    def scaled(self, factor: float) -> "Schedule":
        """Every iteration count times ``factor`` (rounded, at least 1), same order."""
        s = lambda n: max(1, int(round(n * factor)))  # noqa: E731
        return Schedule(
            stage0_iters=s(self.stage0_iters),
            main_iters=s(self.main_iters),
            topology_until=s(self.topology_until),
            prune_at=tuple(s(p) for p in self.prune_at),
            mesh_blocks_at=tuple(s(p) for p in self.mesh_blocks_at),
            mesh_block_iters=s(self.mesh_block_iters),
        )

    def validate(self):
        if not (0 < self.topology_until <= self.main_iters):
            raise ValueError(f"schedule: topology_until {self.topology_until} outside (0, {self.main_iters}]")
        if self.prune_at and self.prune_at[0] != self.topology_until:
            raise ValueError("schedule: the first prune must end the topology phase")
        if list(self.prune_at) != sorted(self.prune_at) or list(self.mesh_blocks_at) != sorted(self.mesh_blocks_at):
            raise ValueError("schedule: prune and mesh-block iterations must be increasing")
        if any(b not in self.prune_at for b in self.mesh_blocks_at):
            raise ValueError("schedule: every mesh block starts right after a prune")
        if any(p > self.main_iters for p in self.prune_at):
            raise ValueError("schedule: a prune lies beyond main_iters")


@dataclass(frozen=True)
class Stage0Config:
    """Stage 0, 2DGS (method.md §3). Iterations come from :class:`Schedule`.

    Attributes:
        dssim_weight: lambda_DSSIM of the photometric loss (0.2).
    """

    dssim_weight: float = 0.2


@dataclass(frozen=True)
class TetInitConfig:
    """Tetrahedral initialisation (method.md §4).

    Attributes:
        hull_scale: hull inflation about its centroid so it strictly covers the object (1.1).
        epsilon: fTetWild envelope relative to the bbox (1e-3).
        edge_length_fac: fTetWild ideal edge length / bbox diagonal (the resolution knob).
        min_opacity: stage-0 surfels below this opacity are dropped before the hull.
        min_points: fewer surviving centres than this is a degenerate hull.
    """

    hull_scale: float = 1.1
    epsilon: float = 1e-3
    edge_length_fac: float = 0.03
    min_opacity: float = 0.05
    min_points: int = 16


@dataclass(frozen=True)
class TopologyConfig:
    """Topology optimisation and the Gaussian phases of the main loop (method.md §5).

    Attributes:
        s: fixed scale of the opacity map alpha = sigmoid(-s * phi_bar * kappa) (1).
        kappa_init, kappa_lr: learnable sharpness, its init (10) and Adam lr (0.01).
        kappa_clamp: range of s * kappa ([1, 50]).
        lam_eik, lam_smooth: weights of L_eik and L_smooth (3, 3).
        w_rgb, w_mask, w_normal, w_prior: L_render weights (10, 3, 0.05, 0.25).
        dssim_weight: L_rgb = (1 - w) L1 + w (1 - SSIM), w = 0.2.
        prune_alpha: tets with alpha below this are pruned (0.1).
        scale_factor: post-prune surfel scale = factor * mean centroid-to-vertex distance (0.65).
        scale_lr, opacity_lr: Adam lrs after the first prune (0.005 on log-scale, 0.05 on logit).
        phi_lr, color_lr, rotation_lr: Adam lrs of the field and Gaussian attributes
            (method.md is silent: 3DGS-style values).
        normal_rank_fraction: the ranked normal loss averages the largest this fraction of
            per-pixel errors ("large-error-focused", §5).
        phi_init: "visual_hull" (signed graph distance to the mask-consistent region, an
            SDF-like start) or "inside" (every vertex at -phi_inside, all tets opaque).
        continuous_opacity: False runs the ablation "w/o continuous opacity": one free
            opacity per tet instead of the vertex field phi.
    """

    s: float = 1.0
    kappa_init: float = 10.0
    kappa_lr: float = 0.01
    kappa_clamp: tuple[float, float] = (1.0, 50.0)
    lam_eik: float = 3.0
    lam_smooth: float = 3.0
    w_rgb: float = 10.0
    w_mask: float = 3.0
    w_normal: float = 0.05
    w_prior: float = 0.25
    dssim_weight: float = 0.2
    prune_alpha: float = 0.1
    scale_factor: float = 0.65
    scale_lr: float = 0.005
    opacity_lr: float = 0.05
    phi_lr: float = 0.01
    color_lr: float = 0.01
    rotation_lr: float = 0.005
    normal_rank_fraction: float = 0.5
    phi_init: str = "visual_hull"
    phi_inside: float = 0.3
    continuous_opacity: bool = True


@dataclass(frozen=True)
class GeometryConfig:
    """Geometry optimisation blocks (method.md §6).

    Attributes:
        w_mask, w_norm: weights of L_mask (20) and L_norm (0.25).
        c_w: inner coefficient of L_w (2e-4, "normalised by the number of tet spheres", which
            is 1 here), multiplied by lam(t) = (1 - t/T)^2.
        c_hc: inner coefficient of L_HC, also multiplied by lam(t). The paper gives 2e-4
            for its own (unstated) normalisation of the image terms; with ours (per-pixel
            means, L_HC in squared mean-edge units) 2e-4 under-smooths badly (bob at 128²:
            Chamfer-L1 0.0059 and normal consistency 0.79, against 0.0031 and 0.97 with
            2e-3), so we use 2e-3.
        c_barrier: coefficient of the orientation penalty max(-det F, 0)^p (2e-4).
        barrier_p: exponent p rising linearly from the first to the second value over the
            mesh iterations (2 -> 4).
        surface_weight: bi-harmonic weight gamma of tets touching surface vertices (5e-4).
        uniform_biharmonic: ablation, w = 1 everywhere.
        two_stage_hc: False is the ablation "single-stage HC" (lam_cond = 1 throughout).
        lr_start, lr_end: uniform-Adam lr, cosine-annealed (2e-4 -> 1e-4), in metres per
            step for the vertex with the largest normalised gradient. Scaling the schedule
            by a factor divides both by it, so the total displacement a block can make is
            the paper's whatever the iteration count.
        max_step: cap on any vertex's displacement per step, in units of the mean edge length.
        min_volume_fraction: a step may not shrink a tet below this fraction of its volume
            at the block's start (the orientation guarantee, with a margin against slivers).
    """

    w_mask: float = 20.0
    w_norm: float = 0.25
    c_hc: float = 2e-3
    c_w: float = 2e-4
    c_barrier: float = 2e-4
    barrier_p: tuple[float, float] = (2.0, 4.0)
    surface_weight: float = 5e-4
    uniform_biharmonic: bool = False
    two_stage_hc: bool = True
    lr_start: float = 2e-4
    lr_end: float = 1e-4
    max_step: float = 0.05
    min_volume_fraction: float = 0.05


@dataclass(frozen=True)
class ReconConfig:
    """The whole reconstruction.

    Attributes:
        preset: name of the preset this came from.
        resolution: longer image side used for every stage, pixels.
        schedule: order of events.
        checkpoint_every: main-loop iterations between checkpoints.
        seed: seeds every random choice (view order, initialisation), so runs and resumed
            runs are reproducible.
    """

    preset: str = "paper"
    resolution: int = 512
    schedule: Schedule = field(default_factory=Schedule)
    stage0: Stage0Config = field(default_factory=Stage0Config)
    tet_init: TetInitConfig = field(default_factory=TetInitConfig)
    topology: TopologyConfig = field(default_factory=TopologyConfig)
    geometry: GeometryConfig = field(default_factory=GeometryConfig)
    checkpoint_every: int = 250
    seed: int = 0

    def scaled(self, factor: float) -> "ReconConfig":
        """Same config with every iteration count multiplied by ``factor`` (and the mesh
        learning rates divided by it, see :class:`GeometryConfig`)."""
        g = self.geometry
        return replace(
            self,
            schedule=self.schedule.scaled(factor),
            geometry=replace(g, lr_start=g.lr_start / factor, lr_end=g.lr_end / factor),
        )

    def with_ablations(
        self, *, continuous_opacity: bool = True, uniform_biharmonic: bool = False, single_stage_hc: bool = False
    ) -> "ReconConfig":
        """Apply the paper's ablations (method.md §5, §6)."""
        return replace(
            self,
            topology=replace(self.topology, continuous_opacity=continuous_opacity),
            geometry=replace(
                self.geometry, uniform_biharmonic=uniform_biharmonic, two_stage_hc=not single_stage_hc
            ),
        )

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)


def _paper() -> ReconConfig:
    return ReconConfig(preset="paper", resolution=512)


def _fast() -> ReconConfig:
    base = _paper().scaled(FAST_FACTOR)
    return replace(base, preset="fast", resolution=128, checkpoint_every=50)


PRESETS = {"paper": _paper, "fast": _fast}


def preset(name: str) -> ReconConfig:
    """The named preset (``"fast"`` or ``"paper"``)."""
    try:
        return PRESETS[name]()
    except KeyError:
        raise ValueError(f"--preset {name!r}: expected one of {', '.join(PRESETS)}") from None
