"""The static description of a simulation (Newton's ``Model``) and the builder that makes it.

A :class:`Model` holds what never changes during a run: rest shape, tets, inverse rest
matrices, lumped masses, Lamé parameters, the particles' Gauss-Seidel colouring and tet
adjacency, the boundary triangles and face-connected components that contacts work on,
gravity, the ground plane and the kinematic plates with their schedules. It is built once by a
:class:`ModelBuilder` and then handed to a solver together with :class:`State` objects
(positions, velocities) and a :class:`Control` (plate poses over the current step).

All quantities are SI: metres, seconds, kilograms, pascals. Z is up.

Example:
    >>> b = ModelBuilder()
    >>> b.add_soft_mesh(mesh, pos=(0, 0, 0.5), density=1000.0, youngs_modulus=1e5,
    ...                 poissons_ratio=0.45)
    >>> b.add_ground_plane(friction=0.5)
    >>> model = b.finalize(device="cpu")
    >>> state0, state1, control = model.state(), model.state(), model.control()
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from holowarp.errors import InputError
from holowarp.tetmesh import TetMesh

__all__ = [
    "GRAVITY",
    "ModelError",
    "lame_parameters",
    "stable_neo_hookean_parameters",
    "euler_xyz_to_matrix",
    "Plate",
    "Body",
    "Model",
    "ModelBuilder",
    "color_vertices",
]

#: Standard gravity, m/s², along -Z (method.md §10: Z up, gravity 9.81).
GRAVITY = 9.81

#: Rest volumes at or below this fraction of (bounding-box diagonal)³ count as degenerate.
_DEGENERATE_VOLUME_FRACTION = 1.0e-12


class ModelError(InputError):
    """A simulation model cannot be built from the given input; the message says why."""


def lame_parameters(youngs_modulus: float, poissons_ratio: float) -> tuple[float, float]:
    """Lamé parameters (mu, lambda) in Pa from Young's modulus E [Pa] and Poisson ratio nu.

    ``mu = E / (2 (1 + nu))``, ``lambda = E nu / ((1 + nu)(1 - 2 nu))``.

    Raises:
        ModelError: E <= 0 or nu outside [0, 0.5).
    """
    E = float(youngs_modulus)
    nu = float(poissons_ratio)
    if not np.isfinite(E) or E <= 0:
        raise ModelError(f"youngs_modulus must be a positive number of Pa, got {youngs_modulus}")
    if not np.isfinite(nu) or not (0.0 <= nu < 0.5):
        raise ModelError(f"poissons_ratio must lie in [0, 0.5), got {poissons_ratio}")
    mu = E / (2.0 * (1.0 + nu))
    lam = E * nu / ((1.0 + nu) * (1.0 - 2.0 * nu))
    return mu, lam


def stable_neo_hookean_parameters(mu, lam):
    """Smith et al. 2018's (mu', lambda') from the Lamé parameters (Pa): ``mu' = 4/3 mu``,
    ``lambda' = lambda + 5/6 mu``; with ``alpha = 1 + 3 mu' / (4 lambda')`` their stable
    Neo-Hookean energy linearises to linear elasticity with exactly ``mu`` and ``lambda``
    (kernels/sim_vbd.py). Accepts scalars or arrays."""
    mu = np.asarray(mu, dtype=np.float64)
    lam = np.asarray(lam, dtype=np.float64)
    return mu * (4.0 / 3.0), lam + mu * (5.0 / 6.0)


def euler_xyz_to_matrix(degrees) -> np.ndarray:
    """Rotation matrix (3, 3) for extrinsic X, then Y, then Z rotations (degrees)."""
    ax, ay, az = np.deg2rad(np.asarray(degrees, dtype=np.float64).reshape(3))
    cx, sx, cy, sy, cz, sz = np.cos(ax), np.sin(ax), np.cos(ay), np.sin(ay), np.cos(az), np.sin(az)
    Rx = np.array([[1, 0, 0], [0, cx, -sx], [0, sx, cx]])
    Ry = np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]])
    Rz = np.array([[cz, -sz, 0], [sz, cz, 0], [0, 0, 1]])
    return Rz @ Ry @ Rx


@dataclass
class Plate:
    """A kinematic plate: the half-space on the ``normal`` side of its moving face.

    The contact is the whole plane through the face centre (an infinite one-sided
    half-space); ``size`` only sets the box drawn in USD and renders, which sits behind the
    face (on the ``-normal`` side).

    Attributes:
        name: prim name in the USD stage.
        normal: (3,) unit normal of the contact face, pointing toward the object.
        path: (K, 4) rows ``[t, x, y, z]``: face-centre position (m) at time t (s). Linear
            between rows, held constant before the first and after the last.
        size: (3,) display box extent in metres.
        friction: Coulomb friction coefficient against the bodies.
        restitution: normal restitution coefficient in [0, 1].
    """

    name: str
    normal: np.ndarray
    path: np.ndarray
    size: np.ndarray = field(default_factory=lambda: np.array([1.0, 1.0, 0.02]))
    friction: float = 0.5
    restitution: float = 0.0

    def position(self, t: float) -> np.ndarray:
        """Face-centre position (3,) in metres at time ``t`` (s)."""
        p = self.path
        return np.array([np.interp(t, p[:, 0], p[:, k]) for k in (1, 2, 3)])

    def box_center(self, t: float) -> np.ndarray:
        """Centre (3,) of the display box at time ``t``: behind the face along ``-normal``."""
        half = 0.5 * float(np.abs(self.size) @ np.abs(self.normal))
        return self.position(t) - self.normal * half


@dataclass(frozen=True)
class Body:
    """Index ranges of one soft body inside the model's particle and tet arrays."""

    name: str
    particle_start: int
    particle_end: int
    tet_start: int
    tet_end: int


class Model:
    """Static simulation data on one Warp device (built by :meth:`ModelBuilder.finalize`).

    Attributes (Warp arrays on ``device``; N particles, M tets, T surface triangles, S
    contact half-spaces):
        particle_q: initial positions [N] vec3, m.
        particle_qd: initial velocities [N] vec3, m/s.
        particle_mass: lumped masses [N], kg (density x tet volume / 4 per corner).
        particle_inv_mass: [N], 1/kg; 0 for fixed particles.
        particle_friction: [N] Coulomb coefficient of each particle's body.
        particle_stiffness: [N] rest elastic stiffness of each particle, N/m: the trace
            bound ``sum_t V_t (mu + lambda') |b_t|^2`` of its block Hessian (scales the
            contact penalty).
        particle_component: [N] int32 face-connected component of each particle (global
            over bodies: body by body, then the mesh's components).
        particle_color_order: [N] int32 particles sorted by colour (no two particles of a
            tet share a colour); ``particle_color_offsets`` (C + 1,) NumPy bounds.
        particle_adj_offsets, particle_adj: CSR of each particle's tets, packed ``4 t + k``
            (k its corner in the tet).
        tet_indices: [M, 4] int32, positively oriented, in input order (bodies concatenated).
        tet_dm_inv: [M] mat33, inverse rest edge matrix ``[b-a, c-a, d-a]^-1``.
        tet_volume: [M] rest volumes, m³.
        tet_mu, tet_lambda: [M] Lamé parameters, Pa.
        tet_component: [M] int32 component of each tet.
        tri_indices: [T, 3] int32 boundary triangles of every body, wound outward.
        tri_component: [T] int32 component of each triangle.
        surface_vertices: [Vs] int32 particles on the boundary.
        surface_normal, surface_friction, surface_restitution: [S] per contact half-space
            (the ground first when present, then the plates in the order added).
        gravity: (3,) NumPy, m/s².

    Host-side copies: ``rest_positions`` (N, 3) float64 (the positions the builder placed),
    ``tets`` (M, 4) int32, ``tris`` (T, 3) int32, ``masses`` (N,), ``fixed`` (N,) bool,
    ``tet_volume_host``, ``tet_mu_host``, ``tet_lambda_host``, ``tet_density_host`` (M,),
    ``components`` (N,) int64 particle components, ``component_count``, ``bodies`` (list of
    :class:`Body`), ``plates`` (list of :class:`Plate`), ``ground`` (dict or None).
    """

    def __init__(self):
        self.device = "cpu"
        self.particle_count = 0
        self.tet_count = 0
        self.component_count = 0
        self.bodies: list[Body] = []
        self.plates: list[Plate] = []
        self.ground: dict | None = None
        self.gravity = np.array([0.0, 0.0, -GRAVITY])

    @property
    def surface_count(self) -> int:
        """Number of contact half-spaces (ground + plates)."""
        return (1 if self.ground is not None else 0) + len(self.plates)

    @property
    def color_count(self) -> int:
        return len(self.particle_color_offsets) - 1

    @property
    def surface_names(self) -> list[str]:
        """Names of the contact half-spaces in model order: ``"Ground"``, then the plates."""
        return (["Ground"] if self.ground is not None else []) + [p.name for p in self.plates]

    def surface_points(self, t: float) -> np.ndarray:
        """(S, 3) contact-plane points at time ``t``: ground origin, then plate faces."""
        pts = []
        if self.ground is not None:
            pts.append(np.array([0.0, 0.0, float(self.ground["height"])]))
        pts += [p.position(t) for p in self.plates]
        return np.asarray(pts, dtype=np.float64).reshape(-1, 3)

    def surface_normals(self) -> np.ndarray:
        """(S, 3) unit normals of the contact half-spaces (model order)."""
        n = [[0.0, 0.0, 1.0]] if self.ground is not None else []
        n += [p.normal for p in self.plates]
        return np.asarray(n, dtype=np.float64).reshape(-1, 3)

    def state(self) -> "State":
        """A new :class:`State` holding the initial positions and velocities."""
        from holowarp.sim.state import State

        return State(self)

    def control(self) -> "Control":
        """A new :class:`Control` with the plates at their t = 0 poses."""
        from holowarp.sim.control import Control

        return Control(self)

    def rest_volume(self) -> float:
        """Total rest volume in m³."""
        return float(self.tet_volume_host.sum())

    def median_surface_edge(self) -> float:
        """Median length (m) of the boundary triangles' edges at rest."""
        X, F = self.rest_positions, self.tris
        if len(F) == 0:
            return float(np.ptp(X, axis=0).max())
        e = np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]])
        return float(np.median(np.linalg.norm(X[e[:, 0]] - X[e[:, 1]], axis=1)))


class ModelBuilder:
    """Accumulates soft bodies, a ground plane and plates, then builds a :class:`Model`.

    Args:
        gravity: (3,) gravity vector in m/s² (default ``(0, 0, -9.81)``, Z up).
    """

    def __init__(self, *, gravity=(0.0, 0.0, -GRAVITY)):
        g = np.asarray(gravity, dtype=np.float64).reshape(-1)
        if g.shape != (3,) or not np.all(np.isfinite(g)):
            raise ModelError(f"gravity must be 3 finite numbers in m/s^2, got {gravity!r}")
        self.gravity = g
        self._positions: list[np.ndarray] = []
        self._velocities: list[np.ndarray] = []
        self._fixed: list[np.ndarray] = []
        self._tets: list[np.ndarray] = []
        self._density: list[np.ndarray] = []
        self._mu: list[np.ndarray] = []
        self._lambda: list[np.ndarray] = []
        self._tet_comp: list[np.ndarray] = []
        self._tris: list[np.ndarray] = []
        self._tri_comp: list[np.ndarray] = []
        self._friction: list[np.ndarray] = []
        self._ncomp = 0
        self._bodies: list[Body] = []
        self._plates: list[Plate] = []
        self._ground: dict | None = None
        self._n = 0
        self._m = 0

    # ------------------------------------------------------------------ bodies
    def add_soft_mesh(
        self,
        mesh: TetMesh,
        *,
        pos=(0.0, 0.0, 0.0),
        rot=None,
        scale: float = 1.0,
        vel=(0.0, 0.0, 0.0),
        density: float = 1000.0,
        youngs_modulus: float = 1.0e5,
        poissons_ratio: float = 0.45,
        friction: float = 0.5,
        fixed=None,
        name: str | None = None,
    ) -> Body:
        """Add a tetrahedral soft body with a stable Neo-Hookean material.

        World position of vertex ``v``: ``rot @ (scale * v) + pos``.

        Args:
            mesh: the tet mesh (rest shape = the transformed vertices). Inverted tets are
                re-oriented; every vertex must belong to a tet.
            pos: (3,) translation in metres.
            rot: (3, 3) rotation matrix (default identity).
            scale: uniform scale factor.
            vel: (3,) initial velocity in m/s.
            density: kg/m³.
            youngs_modulus: E in Pa.
            poissons_ratio: nu in [0, 0.5).
            friction: Coulomb coefficient of this body against other bodies (a pair uses
                the mean of both bodies' coefficients).
            fixed: optional bool mask (N,) or index array of vertices held in place
                (infinite mass).
            name: body name (defaults to ``Body<k>``).

        Returns:
            The :class:`Body` with this mesh's index ranges.

        Raises:
            ModelError: bad material, unused vertices or degenerate (zero-volume) tets.
        """
        mu, lam = lame_parameters(youngs_modulus, poissons_ratio)
        if not np.isfinite(density) or density <= 0:
            raise ModelError(f"density must be a positive number of kg/m^3, got {density}")
        _check_coeffs("add_soft_mesh", friction, 0.0)
        x, mesh_w = _placed_mesh(mesh, pos, rot, scale)
        fix = _fixed_mask(fixed, mesh.num_vertices)
        v0 = np.broadcast_to(np.asarray(vel, dtype=np.float64).reshape(-1), (mesh.num_vertices, 3)).copy()
        v0[fix] = 0.0

        body = Body(
            name or f"Body{len(self._bodies)}",
            self._n,
            self._n + mesh.num_vertices,
            self._m,
            self._m + mesh.num_tets,
        )
        self._positions.append(x)
        self._velocities.append(v0)
        self._fixed.append(fix)
        self._tets.append(mesh_w.tets.astype(np.int64) + self._n)
        labels, ncomp = mesh_w.components()
        self._tet_comp.append(labels.astype(np.int64) + self._ncomp)
        self._tris.append(mesh_w.boundary_faces().astype(np.int64) + self._n)
        self._tri_comp.append(labels[mesh_w.boundary_face_tets()].astype(np.int64) + self._ncomp)
        self._ncomp += int(ncomp)
        self._friction.append(np.full(mesh.num_vertices, float(friction)))
        M = mesh.num_tets
        self._density.append(np.full(M, float(density)))
        self._mu.append(np.full(M, mu))
        self._lambda.append(np.full(M, lam))
        self._bodies.append(body)
        self._n += mesh.num_vertices
        self._m += M
        return body

    # ------------------------------------------------------------------ contacts
    def add_ground_plane(self, *, height: float = 0.0, friction: float = 0.5, restitution: float = 0.0) -> None:
        """The ground: the half-space ``z >= height`` (m), with Coulomb ``friction`` and
        normal ``restitution``."""
        _check_coeffs("ground", friction, restitution)
        self._ground = {"height": float(height), "friction": float(friction), "restitution": float(restitution)}

    def add_plate(
        self,
        name: str,
        *,
        normal,
        path,
        size=(1.0, 1.0, 0.02),
        friction: float = 0.5,
        restitution: float = 0.0,
    ) -> Plate:
        """Add a kinematic plate (see :class:`Plate`).

        Args:
            name: prim name.
            normal: (3,) contact normal pointing toward the object (normalised here).
            path: (K, 4) rows ``[t s, x m, y m, z m]`` of the face centre, times increasing.
            size: (3,) display box extent, m.
            friction: Coulomb coefficient.
            restitution: in [0, 1].
        """
        n = np.asarray(normal, dtype=np.float64).reshape(-1)
        if n.shape != (3,) or not np.all(np.isfinite(n)) or np.linalg.norm(n) < 1e-9:
            raise ModelError(f"plate {name!r}: normal must be a non-zero 3-vector, got {normal!r}")
        p = np.asarray(path, dtype=np.float64)
        if p.ndim != 2 or p.shape[1] != 4 or len(p) < 1 or not np.all(np.isfinite(p)):
            raise ModelError(f"plate {name!r}: path must be rows of [t, x, y, z], got shape {p.shape}")
        if np.any(np.diff(p[:, 0]) <= 0):
            raise ModelError(f"plate {name!r}: path times must strictly increase, got {p[:, 0].tolist()}")
        sz = np.asarray(size, dtype=np.float64).reshape(-1)
        if sz.shape != (3,) or np.any(sz <= 0):
            raise ModelError(f"plate {name!r}: size must be 3 positive lengths in m, got {size!r}")
        _check_coeffs(f"plate {name!r}", friction, restitution)
        plate = Plate(str(name), n / np.linalg.norm(n), p, sz, float(friction), float(restitution))
        self._plates.append(plate)
        return plate

    # ------------------------------------------------------------------ build
    def finalize(self, *, device: str = "cpu") -> Model:
        """Build the :class:`Model` on ``device`` (``"cpu"``, ``"cuda"``, ``"cuda:N"``)."""
        from holowarp.device import init_warp, resolve_device

        wp = init_warp()
        device = resolve_device(device)
        if not self._bodies:
            raise ModelError("finalize: the model has no soft body; call add_soft_mesh first")
        X = np.concatenate(self._positions)
        V = np.concatenate(self._velocities)
        fix = np.concatenate(self._fixed)
        T = np.concatenate(self._tets).astype(np.int32)
        N, M = len(X), len(T)
        a, b, c, d = (X[T[:, k]] for k in range(4))
        Dm = np.stack([b - a, c - a, d - a], axis=2)  # [M, 3, 3] columns are edges
        vol = np.linalg.det(Dm) / 6.0
        Dm_inv = np.linalg.inv(Dm)
        rho = np.concatenate(self._density)
        mass = np.zeros(N)
        np.add.at(mass, T.reshape(-1), np.repeat(rho * vol / 4.0, 4))
        inv_mass = np.where(fix, 0.0, 1.0 / mass)
        mu_t = np.concatenate(self._mu)
        lam_t = np.concatenate(self._lambda)
        mu_p, lam_p = stable_neo_hookean_parameters(mu_t, lam_t)

        # Rest shape-function gradients b (rows of Dm^-1; corner 0: minus their sum) give
        # each particle's rest stiffness bound sum V (mu + lambda') |b|^2 (the trace bound of
        # its block Hessian at rest, where mu' I_C / (I_C + 1) = mu).
        grads = np.concatenate([-Dm_inv.sum(axis=1, keepdims=True), Dm_inv], axis=1)  # [M, 4, 3]
        stiff = np.zeros(N)
        np.add.at(stiff, T.reshape(-1), ((vol * (mu_t + lam_p))[:, None] * (grads**2).sum(axis=2)).reshape(-1))

        order, offsets = color_vertices(T, N)
        # Each particle's tets (CSR), packed 4 t + corner, grouped by particle.
        flat_v = T.reshape(-1).astype(np.int64)
        packed = np.arange(4 * M, dtype=np.int64)  # = 4 t + k for tets[t, k]
        o = np.argsort(flat_v, kind="stable")
        adj = packed[o].astype(np.int32)
        adj_off = np.concatenate([[0], np.cumsum(np.bincount(flat_v, minlength=N))]).astype(np.int32)

        tet_comp = np.concatenate(self._tet_comp)
        tris = np.concatenate(self._tris).astype(np.int32)
        tri_comp = np.concatenate(self._tri_comp)
        comp = np.zeros(N, np.int64)
        comp[T.reshape(-1)] = np.repeat(tet_comp, 4)  # a particle shared by pieces takes one
        surf_v = np.unique(tris).astype(np.int32)

        m = Model()
        m.device = device
        m.particle_count = N
        m.tet_count = M
        m.component_count = int(self._ncomp)
        m.bodies = list(self._bodies)
        m.plates = list(self._plates)
        m.ground = None if self._ground is None else dict(self._ground)
        m.gravity = self.gravity.copy()
        m.rest_positions = X
        m.tets = T
        m.tris = tris
        m.masses = mass
        m.fixed = fix
        m.components = comp
        m.tet_volume_host = vol
        m.tet_mu_host = mu_t
        m.tet_lambda_host = lam_t
        m.tet_density_host = rho
        m.particle_color_offsets = offsets
        m.particle_stiffness_host = stiff

        _upload(m, wp, device, V=V, inv_mass=inv_mass, friction=np.concatenate(self._friction), adj=adj,
                adj_off=adj_off, order=order, Dm_inv=Dm_inv, mu_p=mu_p, lam_p=lam_p, tet_comp=tet_comp,
                tri_comp=tri_comp, surf_v=surf_v)
        return m


def _upload(m: Model, wp, device, *, V, inv_mass, friction, adj, adj_off, order, Dm_inv, mu_p, lam_p, tet_comp,
            tri_comp, surf_v) -> None:
    """Put the model's arrays on ``device`` (float32; see :class:`Model`)."""
    f32 = np.float32
    i32 = np.int32
    m.particle_q = wp.array(m.rest_positions.astype(f32), dtype=wp.vec3, device=device)
    m.particle_qd = wp.array(V.astype(f32), dtype=wp.vec3, device=device)
    m.particle_mass = wp.array(m.masses.astype(f32), dtype=float, device=device)
    m.particle_inv_mass = wp.array(inv_mass.astype(f32), dtype=float, device=device)
    m.particle_friction = wp.array(friction.astype(f32), dtype=float, device=device)
    m.particle_stiffness = wp.array(m.particle_stiffness_host.astype(f32), dtype=float, device=device)
    m.particle_component = wp.array(m.components.astype(i32), dtype=wp.int32, device=device)
    m.particle_color_order = wp.array(order.astype(i32), dtype=wp.int32, device=device)
    m.particle_adj_offsets = wp.array(adj_off, dtype=wp.int32, device=device)
    m.particle_adj = wp.array(adj, dtype=wp.int32, device=device)
    m.tet_indices = wp.array(m.tets, dtype=wp.int32, device=device)
    m.tet_dm_inv = wp.array(Dm_inv.astype(f32), dtype=wp.mat33, device=device)
    m.tet_volume = wp.array(m.tet_volume_host.astype(f32), dtype=float, device=device)
    m.tet_mu = wp.array(m.tet_mu_host.astype(f32), dtype=float, device=device)
    m.tet_lambda = wp.array(m.tet_lambda_host.astype(f32), dtype=float, device=device)
    m.tet_mu_v = wp.array((m.tet_volume_host * mu_p).astype(f32), dtype=float, device=device)
    m.tet_lam_v = wp.array((m.tet_volume_host * lam_p).astype(f32), dtype=float, device=device)
    m.tet_alpha = wp.array((1.0 + 0.75 * mu_p / lam_p).astype(f32), dtype=float, device=device)
    m.tet_component = wp.array(tet_comp.astype(i32), dtype=wp.int32, device=device)
    m.tri_indices = wp.array(m.tris.reshape(-1, 3), dtype=wp.int32, device=device)
    m.tri_component = wp.array(tri_comp.astype(i32), dtype=wp.int32, device=device)
    m.surface_vertices = wp.array(surf_v, dtype=wp.int32, device=device)

    fric, restitution = [], []
    if m.ground is not None:
        fric.append(m.ground["friction"])
        restitution.append(m.ground["restitution"])
    for p in m.plates:
        fric.append(p.friction)
        restitution.append(p.restitution)
    # Arrays keep at least one row so kernels always get a valid array; ``surface_count``
    # says how many are real.
    normals = m.surface_normals().astype(f32) if fric else np.zeros((1, 3), f32)
    m.surface_normal = wp.array(normals, dtype=wp.vec3, device=device)
    m.surface_friction = wp.array(np.asarray(fric or [0.0], f32), dtype=float, device=device)
    m.surface_restitution = wp.array(np.asarray(restitution or [0.0], f32), dtype=float, device=device)


def color_vertices(tets: np.ndarray, num_vertices: int) -> tuple[np.ndarray, np.ndarray]:
    """Colour particles so that no two particles of one tet share a colour.

    Uses Warp's graph colouring (maximum cardinality search) on the tets' edge graph.

    Args:
        tets: (M, 4) vertex indices.
        num_vertices: N.

    Returns:
        (order (N,) int32 particles sorted by colour, offsets (C + 1,) int64 colour bounds).
    """
    from holowarp.device import init_warp
    from holowarp.tetmesh import TetMesh

    wp = init_warp()
    edges = TetMesh(np.zeros((num_vertices, 3)), tets, validate=False).edges().astype(np.int32)
    colors = wp.zeros(num_vertices, dtype=wp.int32, device="cpu")
    if len(edges):
        wp.utils.graph_coloring_assign(wp.array(edges, dtype=wp.int32, device="cpu"), colors)
    col = colors.numpy()
    order = np.argsort(col, kind="stable").astype(np.int32)
    offsets = np.concatenate([[0], np.cumsum(np.bincount(col))]).astype(np.int64)
    return order, offsets


def _placed_mesh(mesh, pos, rot, scale) -> tuple[np.ndarray, TetMesh]:
    """World positions (N, 3) ``rot @ (scale v) + pos`` and the positively oriented mesh on
    them; raises :class:`ModelError` for input no simulation can use."""
    if not isinstance(mesh, TetMesh):
        raise ModelError(f"add_soft_mesh: expected a holowarp TetMesh, got {type(mesh).__name__}")
    if mesh.num_tets == 0:
        raise ModelError("add_soft_mesh: the mesh has no tets")
    if not np.isfinite(scale) or scale <= 0:
        raise ModelError(f"scale must be positive, got {scale}")
    used = np.zeros(mesh.num_vertices, dtype=bool)
    used[mesh.tets.reshape(-1)] = True
    if not used.all():
        raise ModelError(
            f"add_soft_mesh: {int((~used).sum())} of {mesh.num_vertices} vertices belong to no "
            "tet and would have no mass; call mesh.remove_unused_vertices() first"
        )
    R = np.eye(3) if rot is None else np.asarray(rot, dtype=np.float64)
    if R.shape != (3, 3) or not np.allclose(R @ R.T, np.eye(3), atol=1e-6) or np.linalg.det(R) <= 0:
        raise ModelError("add_soft_mesh: rot must be a 3x3 rotation matrix")
    x = (mesh.vertices * float(scale)) @ R.T + np.asarray(pos, dtype=np.float64).reshape(3)
    if not np.all(np.isfinite(x)):
        raise ModelError("add_soft_mesh: the placed vertices are not all finite")
    mesh_w, _ = TetMesh(x, mesh.tets, validate=False).oriented()
    vol = mesh_w.signed_volumes()
    diag = float(np.linalg.norm(x.max(0) - x.min(0)))
    tiny = _DEGENERATE_VOLUME_FRACTION * diag**3
    bad = np.abs(vol) <= tiny
    if bad.any():
        raise ModelError(
            f"add_soft_mesh: {int(bad.sum())} of {mesh.num_tets} tets are degenerate (rest volume "
            f"<= {tiny:.3g} m^3, first: tet {int(np.argmax(bad))}); clean the mesh first "
            "(drop degenerate tets)"
        )
    return x, mesh_w


def _fixed_mask(fixed, n: int) -> np.ndarray:
    """(n,) bool from a bool mask or an index array (None: nothing fixed)."""
    fix = np.zeros(n, dtype=bool)
    if fixed is not None:
        f = np.asarray(fixed)
        if f.dtype == bool:
            if f.shape != (n,):
                raise ModelError(f"fixed mask must have shape ({n},), got {f.shape}")
            fix = f.copy()
        else:
            fix[f.astype(np.int64)] = True
    return fix


def _check_coeffs(what: str, friction, restitution) -> None:
    if not np.isfinite(friction) or friction < 0:
        raise ModelError(f"{what}: friction must be >= 0, got {friction}")
    if not np.isfinite(restitution) or not (0.0 <= restitution <= 1.0):
        raise ModelError(f"{what}: restitution must lie in [0, 1], got {restitution}")
