"""USD export: a stage that physics engines and plain viewers both open.

Layout of every stage holowarp writes (Z up, metres, ``/World`` as default prim)::

    /World                         Xform (default prim)
      /World/<Name>                Xform, OmniPhysicsDeformableBodyAPI (volume deformable root)
        /World/<Name>/TetMesh      UsdGeom.TetMesh: points, tetVertexIndices,
                                   surfaceFaceVertexIndices; OmniPhysicsVolumeDeformableSimAPI
                                   + PhysicsCollisionAPI; rest shape attributes
        /World/<Name>/Surface      UsdGeom.Mesh of the boundary triangles, so viewers without
                                   TetMesh support (most of them) still show the object
      /World/Materials/<Name>Physics  UsdShade.Material with OmniPhysicsDeformableMaterialAPI,
                                   bound to the body with purpose "physics"

Physics material attributes follow the Omni Physics deformable schema of Isaac Sim 5
(``omniphysics:youngsModulus`` [Pa], ``omniphysics:poissonsRatio``, ``omniphysics:density``
[kg/m³], ``omniphysics:staticFriction``, ``omniphysics:dynamicFriction``); ``physics:density``
of the standard ``UsdPhysics.MaterialAPI`` is written too for engines that read only that.

Animation goes through the same writer (:class:`UsdSceneWriter`): ``set_points`` authors
time samples on both the TetMesh and the surface mesh, so a simulation opens as an animated
clip at ``fps`` frames per second. Files are written atomically.
"""

from __future__ import annotations

import os
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from holowarp.fileio import atomic_path
from holowarp.tetmesh import TetMesh

__all__ = ["PhysicsMaterial", "UsdSceneWriter", "write_usd", "read_usd_tetmesh"]


@dataclass(frozen=True)
class PhysicsMaterial:
    """Elastic material of a deformable body (SI units).

    Attributes:
        youngs_modulus: Young's modulus E in Pa.
        poissons_ratio: Poisson ratio nu, in [0, 0.5).
        density: mass density in kg/m³.
        static_friction: Coulomb static friction coefficient.
        dynamic_friction: Coulomb dynamic friction coefficient.
    """

    youngs_modulus: float = 1.0e5
    poissons_ratio: float = 0.45
    density: float = 1000.0
    static_friction: float = 0.5
    dynamic_friction: float = 0.5

    def __post_init__(self):
        if not (self.youngs_modulus > 0):
            raise ValueError(f"youngs_modulus must be > 0 Pa, got {self.youngs_modulus}")
        if not (0.0 <= self.poissons_ratio < 0.5):
            raise ValueError(f"poissons_ratio must lie in [0, 0.5), got {self.poissons_ratio}")
        if not (self.density > 0):
            raise ValueError(f"density must be > 0 kg/m^3, got {self.density}")


def _prim_name(name: str) -> str:
    """A valid USD prim identifier from an arbitrary name."""
    s = re.sub(r"[^A-Za-z0-9_]", "_", str(name)) or "Object"
    return s if not s[0].isdigit() else "_" + s


class UsdSceneWriter:
    """Builds a Z-up, metre-scale stage with tet meshes, boxes and animation, then saves it
    atomically.

    Args:
        path: destination (``.usd``, ``.usda`` or ``.usdc``).
        fps: time codes per second; frame k of an animation sits at time code k.

    Example:
        >>> w = UsdSceneWriter("sim.usda", fps=60)
        >>> w.add_tetmesh("Bob", mesh, material=PhysicsMaterial())
        >>> for k, x in enumerate(frames):
        ...     w.set_points("Bob", x, k)
        >>> w.save()
    """

    def __init__(self, path: str | os.PathLike, *, fps: float = 60.0):
        from pxr import Sdf, Usd, UsdGeom

        self.path = Path(path)
        if self.path.suffix.lower() not in (".usd", ".usda", ".usdc"):
            raise ValueError(f"{self.path}: USD output must end in .usd, .usda or .usdc")
        self.fps = float(fps)
        # Build in memory; save() exports to a temporary file and renames it.
        self.stage = Usd.Stage.CreateInMemory()
        UsdGeom.SetStageUpAxis(self.stage, UsdGeom.Tokens.z)
        UsdGeom.SetStageMetersPerUnit(self.stage, 1.0)
        self.stage.SetTimeCodesPerSecond(self.fps)
        self.stage.SetFramesPerSecond(self.fps)
        world = UsdGeom.Xform.Define(self.stage, "/World")
        self.stage.SetDefaultPrim(world.GetPrim())
        self._bodies: dict[str, dict] = {}
        self._xforms: dict[str, object] = {}
        self._tmin: float | None = None
        self._tmax: float | None = None
        self._Sdf = Sdf

    # ----------------------------------------------------------------- time bookkeeping
    def _touch(self, t):
        if t is None:
            return
        t = float(t)
        self._tmin = t if self._tmin is None else min(self._tmin, t)
        self._tmax = t if self._tmax is None else max(self._tmax, t)

    # ----------------------------------------------------------------- content
    def add_tetmesh(
        self,
        name: str,
        mesh: TetMesh,
        *,
        material: PhysicsMaterial | None = None,
        color=(0.8, 0.55, 0.35),
    ) -> str:
        """Add a volume-deformable body made of ``mesh``; returns its root prim path.

        The surface faces authored are ``mesh.boundary_faces()`` (outward). The initial
        points are authored as default values and as the rest shape.
        """
        from pxr import Gf, Sdf, UsdGeom, UsdPhysics, UsdShade, Vt

        pname = _prim_name(name)
        if pname in self._bodies:
            raise ValueError(f"a body named {pname!r} was already added")
        root_path = f"/World/{pname}"
        root = UsdGeom.Xform.Define(self.stage, root_path)
        rp = root.GetPrim()
        rp.AddAppliedSchema("OmniPhysicsDeformableBodyAPI")
        rp.CreateAttribute("omniphysics:deformableBodyEnabled", Sdf.ValueTypeNames.Bool).Set(True)
        # mass 0: derived from the bound material's density by the engine.
        rp.CreateAttribute("omniphysics:mass", Sdf.ValueTypeNames.Float).Set(0.0)

        bf = mesh.boundary_faces()
        pts = Vt.Vec3fArray.FromNumpy(np.asarray(mesh.vertices, dtype=np.float32))
        tets = Vt.Vec4iArray.FromNumpy(np.asarray(mesh.tets, dtype=np.int32))
        surf = Vt.Vec3iArray.FromNumpy(np.asarray(bf, dtype=np.int32))

        tm = UsdGeom.TetMesh.Define(self.stage, f"{root_path}/TetMesh")
        tm.CreatePointsAttr(pts)
        tm.CreateTetVertexIndicesAttr(tets)
        tm.CreateSurfaceFaceVertexIndicesAttr(surf)
        tm.CreateOrientationAttr(UsdGeom.Tokens.rightHanded)
        tm.CreateDisplayColorAttr(Vt.Vec3fArray([Gf.Vec3f(*color)]))
        tp = tm.GetPrim()
        tp.AddAppliedSchema("OmniPhysicsVolumeDeformableSimAPI")
        tp.CreateAttribute("omniphysics:restShapePoints", Sdf.ValueTypeNames.Point3fArray).Set(pts)
        tp.CreateAttribute("omniphysics:restTetVtxIndices", Sdf.ValueTypeNames.Int4Array).Set(tets)
        UsdPhysics.CollisionAPI.Apply(tp)

        sm = UsdGeom.Mesh.Define(self.stage, f"{root_path}/Surface")
        sm.CreatePointsAttr(pts)
        sm.CreateFaceVertexCountsAttr(Vt.IntArray.FromNumpy(np.full(len(bf), 3, np.int32)))
        sm.CreateFaceVertexIndicesAttr(Vt.IntArray.FromNumpy(np.asarray(bf, np.int32).reshape(-1)))
        sm.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
        sm.CreateOrientationAttr(UsdGeom.Tokens.rightHanded)
        sm.CreateDisplayColorAttr(Vt.Vec3fArray([Gf.Vec3f(*color)]))

        lo, hi = mesh.vertices.min(axis=0), mesh.vertices.max(axis=0)
        extent = Vt.Vec3fArray([Gf.Vec3f(*map(float, lo)), Gf.Vec3f(*map(float, hi))])
        tm.CreateExtentAttr(extent)
        sm.CreateExtentAttr(extent)

        if material is not None:
            mat_path = f"/World/Materials/{pname}Physics"
            UsdGeom.Scope.Define(self.stage, "/World/Materials")
            mat = UsdShade.Material.Define(self.stage, mat_path)
            mp = mat.GetPrim()
            mp.AddAppliedSchema("OmniPhysicsDeformableMaterialAPI")
            f = Sdf.ValueTypeNames.Float
            mp.CreateAttribute("omniphysics:youngsModulus", f).Set(float(material.youngs_modulus))
            mp.CreateAttribute("omniphysics:poissonsRatio", f).Set(float(material.poissons_ratio))
            mp.CreateAttribute("omniphysics:density", f).Set(float(material.density))
            mp.CreateAttribute("omniphysics:staticFriction", f).Set(float(material.static_friction))
            mp.CreateAttribute("omniphysics:dynamicFriction", f).Set(float(material.dynamic_friction))
            pm = UsdPhysics.MaterialAPI.Apply(mp)
            pm.CreateDensityAttr(float(material.density))
            pm.CreateStaticFrictionAttr(float(material.static_friction))
            pm.CreateDynamicFrictionAttr(float(material.dynamic_friction))
            for prim in (rp, tp):
                UsdShade.MaterialBindingAPI.Apply(prim).Bind(
                    mat, UsdShade.Tokens.weakerThanDescendants, "physics"
                )

        self._bodies[pname] = {"tet": tm, "surf": sm, "n": mesh.num_vertices}
        return root_path

    def set_points(self, name: str, vertices, time: float) -> None:
        """Author positions (N, 3) of body ``name`` at time code ``time`` (frame index)."""
        from pxr import Gf, Vt

        body = self._bodies.get(_prim_name(name))
        if body is None:
            raise KeyError(f"no body named {name!r}; add it with add_tetmesh first")
        v = np.asarray(vertices, dtype=np.float32)
        if v.shape != (body["n"], 3):
            raise ValueError(f"set_points({name!r}): expected ({body['n']}, 3), got {v.shape}")
        if not np.all(np.isfinite(v)):
            raise ValueError(f"set_points({name!r}): non-finite positions at time {time}")
        arr = Vt.Vec3fArray.FromNumpy(v)
        t = float(time)
        body["tet"].GetPointsAttr().Set(arr, t)
        body["surf"].GetPointsAttr().Set(arr, t)
        lo, hi = v.min(axis=0), v.max(axis=0)
        ext = Vt.Vec3fArray([Gf.Vec3f(*map(float, lo)), Gf.Vec3f(*map(float, hi))])
        body["tet"].GetExtentAttr().Set(ext, t)
        body["surf"].GetExtentAttr().Set(ext, t)
        self._touch(t)

    def add_box(
        self,
        name: str,
        size,
        translation=(0.0, 0.0, 0.0),
        *,
        color=(0.6, 0.6, 0.65),
        collider: bool = True,
    ) -> str:
        """Add an axis-aligned box (a ``UsdGeom.Cube`` scaled to ``size`` (3,) metres) whose
        centre sits at ``translation``; returns its prim path. Animate with
        :meth:`set_translation`."""
        from pxr import Gf, UsdGeom, UsdPhysics, Vt

        pname = _prim_name(name)
        path = f"/World/{pname}"
        xf = UsdGeom.Xform.Define(self.stage, path)
        cube = UsdGeom.Cube.Define(self.stage, f"{path}/Geom")
        cube.CreateSizeAttr(1.0)
        cube.CreateDisplayColorAttr(Vt.Vec3fArray([Gf.Vec3f(*color)]))
        cube.AddScaleOp().Set(Gf.Vec3f(*map(float, size)))
        if collider:
            UsdPhysics.CollisionAPI.Apply(cube.GetPrim())
        op = xf.AddTranslateOp()
        op.Set(Gf.Vec3d(*map(float, translation)))
        self._xforms[pname] = op
        return path

    def set_translation(self, name: str, translation, time: float) -> None:
        """Author the translation (3,) of a box added with :meth:`add_box` at ``time``."""
        from pxr import Gf

        op = self._xforms.get(_prim_name(name))
        if op is None:
            raise KeyError(f"no box named {name!r}; add it with add_box first")
        op.Set(Gf.Vec3d(*map(float, translation)), float(time))
        self._touch(time)

    def add_ground(self, *, size: float = 10.0) -> str:
        """A thin grey ground slab whose top face is the plane z = 0."""
        return self.add_box("Ground", (size, size, 0.01), (0.0, 0.0, -0.005), color=(0.45, 0.45, 0.45))

    def save(self) -> Path:
        """Set start/end time codes from what was animated and write the file atomically."""
        if self._tmin is not None:
            self.stage.SetStartTimeCode(self._tmin)
            self.stage.SetEndTimeCode(self._tmax)
        with atomic_path(self.path) as tmp:
            if not self.stage.GetRootLayer().Export(str(tmp)):
                raise OSError(f"{self.path}: USD export failed")
        return self.path


def write_usd(
    path: str | os.PathLike,
    mesh: TetMesh,
    *,
    material: PhysicsMaterial | None = None,
    name: str = "Object",
    points_over_time=None,
    fps: float = 60.0,
) -> Path:
    """Write ``mesh`` as a simulation-ready USD stage (see the module docstring).

    Args:
        path: ``.usd``, ``.usda`` or ``.usdc`` destination.
        mesh: the tet mesh (positively oriented).
        material: physics material; a default (E = 100 kPa, nu = 0.45, 1000 kg/m³) if None.
        name: body prim name.
        points_over_time: optional (T, N, 3) positions authored at time codes 0..T-1.
        fps: time codes per second.
    """
    w = UsdSceneWriter(path, fps=fps)
    w.add_tetmesh(name, mesh, material=material or PhysicsMaterial())
    if points_over_time is not None:
        for k, x in enumerate(np.asarray(points_over_time)):
            w.set_points(name, x, k)
    return w.save()


def read_usd_tetmesh(path: str | os.PathLike, *, time=None) -> TetMesh:
    """Read the first ``UsdGeom.TetMesh`` of a stage (at ``time``, default: its default value,
    else the earliest sample).

    Raises:
        ValueError: the stage cannot be opened or holds no TetMesh prim.
    """
    from pxr import Usd, UsdGeom

    stage = Usd.Stage.Open(str(path))
    if stage is None:
        raise ValueError(f"{path}: not a readable USD stage")
    for prim in stage.Traverse():
        if prim.IsA(UsdGeom.TetMesh):
            tm = UsdGeom.TetMesh(prim)
            tc = Usd.TimeCode.Default() if time is None else Usd.TimeCode(float(time))
            pts = tm.GetPointsAttr().Get(tc)
            if pts is None:
                samples = tm.GetPointsAttr().GetTimeSamples()
                if samples:
                    pts = tm.GetPointsAttr().Get(samples[0])
            idx = tm.GetTetVertexIndicesAttr().Get()
            if pts is None or idx is None:
                raise ValueError(f"{path}: TetMesh {prim.GetPath()} has no points or tetVertexIndices")
            return TetMesh(np.asarray(pts, dtype=np.float64), np.asarray(idx, dtype=np.int64))
    raise ValueError(f"{path}: the stage holds no UsdGeom.TetMesh prim")
