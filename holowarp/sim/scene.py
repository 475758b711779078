"""Simulation scenarios as data: TOML files under ``scenes/`` (method.md §10).

A scene fixes everything but the mesh: time stepping, material, where the object is put,
the ground and the kinematic plates. ``load_scene("drop")`` reads a built-in scene,
``load_scene("my.toml")`` any file. Every value is checked; a bad value raises
:class:`SceneError` naming the file and the key (``drop.toml: [material] poissons_ratio:
must lie in [0, 0.5), got 0.5``). Unknown keys are errors too, so a typo never passes
silently.

Layout (all SI; see ``scenes/drop.toml`` for a commented example)::

    name = "drop"
    [sim]        dt, substeps, iterations, duration, gravity, damping, integrator
    [material]   youngs_modulus, poissons_ratio, density, friction, restitution
    [placement]  size, rotation, center_xy, height, velocity
    [ground]     enabled
    [contact]    radius, margin, stiffness, self_collision, friction_epsilon
    [[plates]]   name, normal, size, frame ("object" | "world"), path = [[t, x, y, z], ...]
    [[bodies]]   name, mesh, [bodies.placement] (as [placement]),
                 [bodies.material] youngs_modulus, poissons_ratio, density, friction

Without ``[[bodies]]`` the scene has one body: the mesh given to the simulation, placed by
``[placement]`` with ``[material]`` (every scene file written before bodies existed stays
valid). Each ``[[bodies]]`` entry adds a body: ``mesh`` is a mesh file (relative paths are
relative to the scene file; omitted: the mesh given to the simulation), its placement and
material start from ``[placement]`` and ``[material]`` and override what they list. The
ground and plates use ``[material]`` friction and restitution; two bodies in contact use
the mean of their frictions. ``[contact]`` tunes the contacts between bodies and between
the disjoint pieces of one mesh (:class:`holowarp.sim.SolverVBDNeoHookean`).

Plate paths in the ``"object"`` frame are fractions of the placed bodies' rest bounding
box (``[0, 0, 0]`` its minimum corner, ``[1, 1, 1]`` its maximum corner), and so are their
sizes; in the ``"world"`` frame they are metres.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from holowarp.errors import InputError
from holowarp.sim.model import GRAVITY, ModelBuilder, euler_xyz_to_matrix
from holowarp.sim.solver import CONTACT_STIFFNESS, FRICTION_EPSILON, INTEGRATORS, PAPER_DT, PAPER_ITERATIONS

__all__ = [
    "SceneError",
    "SimSettings",
    "MaterialSettings",
    "Placement",
    "PlateSpec",
    "ContactSettings",
    "BodySpec",
    "Scene",
    "parse_scene",
    "load_scene",
    "placement_transform",
    "build_model",
    "solver_options",
]


class SceneError(InputError):
    """A scene file is missing, unreadable or holds a bad value; the message says where."""


@dataclass(frozen=True)
class SimSettings:
    """Time stepping (method.md §10: dt = 1/60 s, 16 iterations)."""

    dt: float = PAPER_DT  # s
    substeps: int = 1
    iterations: int = PAPER_ITERATIONS  # per substep
    duration: float = 1.0  # s
    gravity: tuple = (0.0, 0.0, -GRAVITY)  # m/s²
    damping: float = 0.0  # 1/s
    integrator: str = "auto"  # "auto", "euler" or "bdf2" (holowarp.sim.solver.INTEGRATORS)


@dataclass(frozen=True)
class MaterialSettings:
    """Stable Neo-Hookean material and contact coefficients."""

    youngs_modulus: float = 1.0e5  # Pa
    poissons_ratio: float = 0.45
    density: float = 1000.0  # kg/m³
    friction: float = 0.5  # Coulomb (static = kinetic)
    restitution: float = 0.0


@dataclass(frozen=True)
class Placement:
    """Where the object goes: rotate about its bbox centre, scale, then put it down."""

    size: float = 0.0  # m, largest bbox side after scaling; 0 keeps the mesh's scale
    rotation: tuple = (0.0, 0.0, 0.0)  # degrees, extrinsic X, Y, Z
    center_xy: tuple = (0.0, 0.0)  # m
    height: float = 0.0  # m, lowest point above z = 0
    velocity: tuple = (0.0, 0.0, 0.0)  # m/s


@dataclass(frozen=True)
class PlateSpec:
    """A kinematic plate as written in the scene (see the module docstring)."""

    name: str
    normal: tuple
    path: tuple  # ((t, x, y, z), ...)
    size: tuple = (1.5, 1.5, 0.05)
    frame: str = "object"


@dataclass(frozen=True)
class ContactSettings:
    """Contacts between bodies and between the disjoint pieces of one mesh (``None``: the
    solver's default, derived from the mesh)."""

    radius: float | None = None  # m, contact distance
    margin: float | None = None  # m, extra detection distance
    stiffness: float = CONTACT_STIFFNESS  # multiple of the rest elastic stiffness
    self_collision: bool = False  # collide a connected piece with itself (paper: off)
    friction_epsilon: float = FRICTION_EPSILON  # m/s, friction smoothing speed


@dataclass(frozen=True)
class BodySpec:
    """One body of a scene: its mesh file (``None``: the mesh given to the simulation),
    placement and material."""

    name: str
    mesh: str | None = None
    placement: Placement = field(default_factory=Placement)
    material: MaterialSettings = field(default_factory=MaterialSettings)


@dataclass(frozen=True)
class Scene:
    """A parsed, validated scene (``bodies`` empty: one body, the given mesh, placed by
    ``placement`` with ``material``)."""

    name: str
    source: str
    sim: SimSettings = field(default_factory=SimSettings)
    material: MaterialSettings = field(default_factory=MaterialSettings)
    placement: Placement = field(default_factory=Placement)
    ground: bool = True
    plates: tuple = ()
    bodies: tuple = ()
    contact: ContactSettings = field(default_factory=ContactSettings)

    def body_specs(self) -> tuple:
        """The bodies to build: ``bodies``, or the one implicit body of a scene without them."""
        if self.bodies:
            return tuple(self.bodies)
        return (BodySpec("Object", None, self.placement, self.material),)

    @property
    def num_steps(self) -> int:
        """Steps to simulate: ``round(duration / dt)``."""
        return int(round(self.sim.duration / self.sim.dt))

    def as_dict(self) -> dict:
        """Plain-data view (for reports)."""
        import dataclasses

        return dataclasses.asdict(self)


# ---------------------------------------------------------------------------- parsing
_TOP_KEYS = {"name", "description", "sim", "material", "placement", "ground", "plates", "bodies", "contact"}
_MATERIAL_KEYS = {"youngs_modulus", "poissons_ratio", "density", "friction", "restitution"}
_BODY_MATERIAL_KEYS = _MATERIAL_KEYS - {"restitution"}
_PLACEMENT_KEYS = {"size", "rotation", "center_xy", "height", "velocity"}


def _num(src, sec, key, v, *, lo=None, hi=None, lo_open=False, integer=False):
    where = f"{src}: [{sec}] {key}"
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        raise SceneError(f"{where}: expected a number, got {v!r}")
    if integer and (not float(v).is_integer()):
        raise SceneError(f"{where}: expected an integer, got {v!r}")
    v = int(v) if integer else float(v)
    if not math.isfinite(v):
        raise SceneError(f"{where}: must be finite, got {v!r}")
    if lo is not None and (v <= lo if lo_open else v < lo):
        raise SceneError(f"{where}: must be {'>' if lo_open else '>='} {lo}, got {v!r}")
    if hi is not None and v > hi:
        raise SceneError(f"{where}: must be <= {hi}, got {v!r}")
    return v


#: Largest magnitude accepted for a length (m), speed (m/s) or acceleration (m/s^2) of a
#: scene: far beyond any scene this solver is for, and far below where float32 positions
#: and masses overflow (a size of 1e30 m would otherwise run and report NaN volumes).
MAX_MAGNITUDE = 1.0e4


def _vec(src, sec, key, v, n, *, bound=None):
    where = f"{src}: [{sec}] {key}"
    if not isinstance(v, (list, tuple)) or len(v) != n:
        raise SceneError(f"{where}: expected a list of {n} numbers, got {v!r}")
    out = tuple(_num(src, sec, key, x) for x in v)
    if bound is not None and max((abs(x) for x in out), default=0.0) > bound:
        raise SceneError(f"{where}: components must lie within +-{bound:g}, got {list(out)}")
    return out


def _table(src, data, sec, allowed, where=None):
    t = data.get(sec, {})
    name = sec if where is None else f"{where}.{sec}"
    if not isinstance(t, dict):
        raise SceneError(f"{src}: [{name}] must be a table, got {type(t).__name__}")
    unknown = sorted(set(t) - set(allowed))
    if unknown:
        raise SceneError(f"{src}: [{name}] unknown key(s) {', '.join(unknown)}; allowed: {', '.join(sorted(allowed))}")
    return t


def parse_scene(data: dict, *, source: str = "<scene>") -> Scene:
    """Validate a scene given as a dict (the parsed TOML)."""
    src = source
    unknown = sorted(set(data) - _TOP_KEYS)
    if unknown:
        raise SceneError(f"{src}: unknown top-level key(s) {', '.join(unknown)}; allowed: {', '.join(sorted(_TOP_KEYS))}")
    name = data.get("name", Path(src).stem)
    if not isinstance(name, str) or not name:
        raise SceneError(f"{src}: name must be a non-empty string, got {name!r}")

    d = SimSettings()
    t = _table(src, data, "sim", {"dt", "substeps", "iterations", "duration", "gravity", "damping", "integrator"})
    integ = t.get("integrator", d.integrator)
    if integ not in INTEGRATORS:
        raise SceneError(f"{src}: [sim] integrator: expected one of {', '.join(repr(i) for i in INTEGRATORS)}, "
                         f"got {integ!r}")
    sim = SimSettings(
        dt=_num(src, "sim", "dt", t.get("dt", d.dt), lo=0.0, lo_open=True, hi=1.0),
        substeps=_num(src, "sim", "substeps", t.get("substeps", d.substeps), lo=1, hi=1024, integer=True),
        iterations=_num(src, "sim", "iterations", t.get("iterations", d.iterations), lo=1, hi=10000, integer=True),
        duration=_num(src, "sim", "duration", t.get("duration", d.duration), lo=0.0, lo_open=True),
        gravity=_vec(src, "sim", "gravity", t.get("gravity", d.gravity), 3, bound=MAX_MAGNITUDE),
        damping=_num(src, "sim", "damping", t.get("damping", d.damping), lo=0.0),
        integrator=integ,
    )
    if sim.duration < sim.dt:
        raise SceneError(f"{src}: [sim] duration ({sim.duration} s) is shorter than one step dt ({sim.dt} s)")
    ratio = 1.0 / (60.0 * sim.dt)
    if abs(ratio - round(ratio)) > 1e-6 * max(ratio, 1.0) or round(ratio) < 1:
        raise SceneError(
            f"{src}: [sim] dt: must be 1/60 s divided by a whole number (output is 60 frames per "
            f"second), got {sim.dt}"
        )

    mat = _material(src, "material", _table(src, data, "material", _MATERIAL_KEYS), MaterialSettings())
    pl = _placement(src, "placement", _table(src, data, "placement", _PLACEMENT_KEYS), Placement())

    t = _table(src, data, "ground", {"enabled"})
    ground = t.get("enabled", True)
    if not isinstance(ground, bool):
        raise SceneError(f"{src}: [ground] enabled: expected true or false, got {ground!r}")

    plates_raw = data.get("plates", [])
    if not isinstance(plates_raw, list):
        raise SceneError(f"{src}: plates must be an array of tables ([[plates]]), got {type(plates_raw).__name__}")
    plates = []
    names = set()
    for k, p in enumerate(plates_raw):
        sec = f"plates.{k}"
        if not isinstance(p, dict):
            raise SceneError(f"{src}: [[plates]] entry {k} must be a table")
        unknown = sorted(set(p) - {"name", "normal", "size", "frame", "path"})
        if unknown:
            raise SceneError(f"{src}: [{sec}] unknown key(s) {', '.join(unknown)}")
        pname = p.get("name", f"Plate{k}")
        if not isinstance(pname, str) or not pname or pname in names:
            raise SceneError(f"{src}: [{sec}] name must be a unique non-empty string, got {pname!r}")
        names.add(pname)
        normal = _vec(src, sec, "normal", p.get("normal"), 3)
        if np.linalg.norm(normal) < 1e-9:
            raise SceneError(f"{src}: [{sec}] normal: must be non-zero")
        size = _vec(src, sec, "size", p.get("size", PlateSpec.size), 3)
        if min(size) <= 0:
            raise SceneError(f"{src}: [{sec}] size: all three extents must be > 0, got {list(size)}")
        frame = p.get("frame", "object")
        if frame not in ("object", "world"):
            raise SceneError(f"{src}: [{sec}] frame: must be \"object\" or \"world\", got {frame!r}")
        path = p.get("path")
        if not isinstance(path, list) or not path:
            raise SceneError(f"{src}: [{sec}] path: expected a non-empty list of [t, x, y, z] rows")
        rows = tuple(_vec(src, sec, f"path[{i}]", r, 4) for i, r in enumerate(path))
        ts = [r[0] for r in rows]
        if any(b <= a for a, b in zip(ts, ts[1:])):
            raise SceneError(f"{src}: [{sec}] path: times must strictly increase, got {ts}")
        plates.append(PlateSpec(pname, normal, rows, size, frame))
    contact = _contact(src, _table(src, data, "contact",
                                   {"radius", "margin", "stiffness", "self_collision", "friction_epsilon"}))
    bodies = _bodies(src, data.get("bodies", []), mat, pl)
    return Scene(name=name, source=src, sim=sim, material=mat, placement=pl, ground=ground, plates=tuple(plates),
                 bodies=bodies, contact=contact)


def _material(src, sec, t, d: MaterialSettings) -> MaterialSettings:
    mat = MaterialSettings(
        youngs_modulus=_num(src, sec, "youngs_modulus", t.get("youngs_modulus", d.youngs_modulus), lo=0.0,
                            lo_open=True),
        poissons_ratio=_num(src, sec, "poissons_ratio", t.get("poissons_ratio", d.poissons_ratio), lo=0.0),
        density=_num(src, sec, "density", t.get("density", d.density), lo=0.0, lo_open=True),
        friction=_num(src, sec, "friction", t.get("friction", d.friction), lo=0.0),
        restitution=_num(src, sec, "restitution", t.get("restitution", d.restitution), lo=0.0, hi=1.0),
    )
    if not mat.poissons_ratio < 0.5:
        raise SceneError(f"{src}: [{sec}] poissons_ratio: must lie in [0, 0.5), got {mat.poissons_ratio}")
    return mat


def _placement(src, sec, t, d: Placement) -> Placement:
    return Placement(
        size=_num(src, sec, "size", t.get("size", d.size), lo=0.0, hi=MAX_MAGNITUDE),
        rotation=_vec(src, sec, "rotation", t.get("rotation", d.rotation), 3),
        center_xy=_vec(src, sec, "center_xy", t.get("center_xy", d.center_xy), 2, bound=MAX_MAGNITUDE),
        height=_num(src, sec, "height", t.get("height", d.height), lo=0.0, hi=MAX_MAGNITUDE),
        velocity=_vec(src, sec, "velocity", t.get("velocity", d.velocity), 3, bound=MAX_MAGNITUDE),
    )


def _contact(src, t) -> ContactSettings:
    d = ContactSettings()
    opt = {}
    for key in ("radius", "margin"):
        if key in t:  # an explicit 0 is a value, not "use the default"
            opt[key] = _num(src, "contact", key, t[key], lo=0.0)
    sc = t.get("self_collision", d.self_collision)
    if not isinstance(sc, bool):
        raise SceneError(f"{src}: [contact] self_collision: expected true or false, got {sc!r}")
    return ContactSettings(
        stiffness=_num(src, "contact", "stiffness", t.get("stiffness", d.stiffness), lo=0.0, lo_open=True),
        self_collision=sc,
        friction_epsilon=_num(src, "contact", "friction_epsilon", t.get("friction_epsilon", d.friction_epsilon),
                              lo=0.0, lo_open=True),
        **opt,
    )


def _bodies(src, raw, mat: MaterialSettings, pl: Placement) -> tuple:
    if not isinstance(raw, list):
        raise SceneError(f"{src}: bodies must be an array of tables ([[bodies]]), got {type(raw).__name__}")
    out, names = [], set()
    base = Path(src).parent
    for k, b in enumerate(raw):
        sec = f"bodies.{k}"
        if not isinstance(b, dict):
            raise SceneError(f"{src}: [[bodies]] entry {k} must be a table")
        unknown = sorted(set(b) - {"name", "mesh", "placement", "material"})
        if unknown:
            raise SceneError(f"{src}: [{sec}] unknown key(s) {', '.join(unknown)}; allowed: material, mesh, name, "
                             "placement")
        bname = b.get("name", f"Body{k}")
        if not isinstance(bname, str) or not bname.isidentifier() or bname in names:
            raise SceneError(f"{src}: [{sec}] name must be a unique identifier (letters, digits, _), got {bname!r}")
        names.add(bname)
        mesh = b.get("mesh")
        if mesh is not None:
            if not isinstance(mesh, str) or not mesh:
                raise SceneError(f"{src}: [{sec}] mesh: expected a file path, got {mesh!r}")
            mp = Path(mesh)
            mesh = str(mp if mp.is_absolute() else base / mp)
        bp = _placement(src, f"{sec}.placement", _table(src, b, "placement", _PLACEMENT_KEYS, where=sec), pl)
        bm = _material(src, f"{sec}.material", _table(src, b, "material", _BODY_MATERIAL_KEYS, where=sec), mat)
        out.append(BodySpec(bname, mesh, bp, bm))
    return tuple(out)


def load_scene(name_or_path: "str | os.PathLike | Scene") -> Scene:
    """Load a built-in scene (``"drop"``, ``"compress"``) or a ``.toml`` file.

    Raises:
        SceneError: unknown name, missing file, TOML syntax error or a bad value.
    """
    if isinstance(name_or_path, Scene):
        return name_or_path
    from holowarp.scenes import scene_path

    try:
        path = scene_path(str(name_or_path))
    except FileNotFoundError as e:
        raise SceneError(str(e)) from None
    try:
        import tomllib
    except ModuleNotFoundError:  # Python < 3.11
        import tomli as tomllib
    try:
        with open(path, "rb") as f:
            data = tomllib.load(f)
    except tomllib.TOMLDecodeError as e:
        raise SceneError(f"{path}: not valid TOML ({e})") from None
    except UnicodeDecodeError as e:  # binary files, other encodings: TOML is UTF-8
        raise SceneError(f"{path}: not UTF-8 text, so not a TOML scene (byte {e.start}: {e.reason})") from None
    except OSError as e:
        raise SceneError(f"{path}: cannot read ({e.strerror})") from None
    return parse_scene(data, source=str(path))


# ---------------------------------------------------------------------------- building
def placement_transform(vertices, placement: Placement) -> tuple[np.ndarray, float, np.ndarray]:
    """``(rot (3, 3), scale, pos (3,))`` with ``world = rot @ (scale * v) + pos`` that applies
    ``placement`` to a mesh with these ``vertices`` (N, 3): rotate about the bbox centre,
    scale so the largest bbox side is ``placement.size`` (if > 0), centre in x, y at
    ``center_xy`` and lift the lowest point to ``height``."""
    v = np.asarray(vertices, dtype=np.float64)
    R = euler_xyz_to_matrix(placement.rotation)
    c = 0.5 * (v.min(0) + v.max(0))
    vr = (v - c) @ R.T
    ext = float(np.ptp(vr, axis=0).max())
    if not ext > 0:
        raise SceneError("placement: the mesh has a zero-size bounding box")
    s = placement.size / ext if placement.size > 0 else 1.0
    vs = vr * s
    lo, hi = vs.min(0), vs.max(0)
    t = np.array([
        placement.center_xy[0] - 0.5 * (lo[0] + hi[0]),
        placement.center_xy[1] - 0.5 * (lo[1] + hi[1]),
        placement.height - lo[2],
    ])
    pos = t - s * (R @ c)
    return R, s, pos


def build_model(scene: Scene, meshes, *, transform=None, device: str = "cpu", names=None):
    """Build the :class:`holowarp.sim.Model` of ``scene``.

    Args:
        scene: the scene.
        meshes: one :class:`TetMesh` per body of ``scene.body_specs()`` (a list), or one
            TetMesh used for every body. For a scene without ``[[bodies]]`` a list of k
            meshes makes k bodies that share ``[placement]`` and ``[material]``.
        transform: placement ``(rot, scale, pos)`` with ``world = rot @ (scale v) + pos``:
            one for every body, or a list with one per body (``None`` entries: from the
            body's placement). Default: for a scene without ``[[bodies]]`` one transform from
            all the meshes' vertices together (:func:`placement_transform`); with bodies,
            each body's from its own mesh. Pass the reference's to share a frame.
        device: Warp device.
        names: body names (default: the scene's).

    Returns:
        (model, transforms (one per body), bbox (2, 3) of the placed bodies that defines
        plate "object" frames).
    """
    from holowarp.tetmesh import TetMesh

    specs = list(scene.body_specs())
    if isinstance(meshes, TetMesh):
        meshes = [meshes] * len(specs)
    meshes = list(meshes)
    if not scene.bodies and len(meshes) > 1:
        specs = [BodySpec(f"Body{k}", None, scene.placement, scene.material) for k in range(len(meshes))]
        if transform is None:
            transform = placement_transform(np.concatenate([m.vertices for m in meshes]), scene.placement)
    if len(meshes) != len(specs):
        raise SceneError(f"{scene.source}: the scene has {len(specs)} bodies but {len(meshes)} meshes were given")
    if transform is None or (isinstance(transform, tuple) and len(transform) == 3 and np.ndim(transform[1]) == 0):
        transforms = [transform] * len(specs)
    else:
        transforms = list(transform)
        if len(transforms) != len(specs):
            raise SceneError(f"{scene.source}: {len(transforms)} transforms for {len(specs)} bodies")
    transforms = [placement_transform(m.vertices, sp.placement) if tr is None else tr
                  for m, sp, tr in zip(meshes, specs, transforms)]
    b = ModelBuilder(gravity=scene.sim.gravity)
    placed = []
    for k, (mesh, sp, (R, s, pos)) in enumerate(zip(meshes, specs, transforms)):
        mat = sp.material
        b.add_soft_mesh(
            mesh, pos=pos, rot=R, scale=s, vel=sp.placement.velocity, density=mat.density,
            youngs_modulus=mat.youngs_modulus, poissons_ratio=mat.poissons_ratio, friction=mat.friction,
            name=(names[k] if names else sp.name),
        )
        placed.append((mesh.vertices * s) @ R.T + pos)
    allp = np.concatenate(placed)
    bbox = np.stack([allp.min(0), allp.max(0)])
    _add_contacts(b, scene, bbox)
    return b.finalize(device=device), transforms, bbox


def solver_options(scene: Scene) -> dict:
    """Keyword arguments of :class:`holowarp.sim.SolverVBDNeoHookean` that ``scene`` sets."""
    sim, c = scene.sim, scene.contact
    return dict(iterations=sim.iterations, substeps=sim.substeps, damping=sim.damping, integrator=sim.integrator,
                contact_radius=c.radius,
                contact_margin=c.margin, contact_stiffness=c.stiffness, self_collision=c.self_collision,
                friction_epsilon=c.friction_epsilon)


def _add_contacts(b: ModelBuilder, scene: Scene, bbox):
    mat = scene.material
    if scene.ground:
        b.add_ground_plane(friction=mat.friction, restitution=mat.restitution)
    lo, hi = bbox
    ext = hi - lo
    for p in scene.plates:
        path = np.asarray(p.path, dtype=np.float64)
        size = np.asarray(p.size, dtype=np.float64)
        if p.frame == "object":
            path = np.concatenate([path[:, :1], lo + path[:, 1:] * ext], axis=1)
            size = size * np.where(ext > 0, ext, 1.0)
        b.add_plate(p.name, normal=p.normal, path=path, size=size, friction=mat.friction,
                    restitution=mat.restitution)
