"""USD export checked by reopening the stage with pxr."""

from __future__ import annotations

import numpy as np
import pytest
from pxr import Usd, UsdGeom, UsdShade

from holowarp.primitives import box_tetmesh
from holowarp.usd import PhysicsMaterial, UsdSceneWriter, write_usd


def _api_schemas(prim):
    """Authored apiSchemas, including codeless ones this pxr build has no definition for
    (GetAppliedSchemas() filters those out)."""
    return list(prim.GetMetadata("apiSchemas").GetAddedOrExplicitItems())


def _canonical(faces):
    """Rotate each triangle so its smallest index comes first (keeps winding), sort rows."""
    f = np.asarray(faces).reshape(-1, 3)
    k = np.argmin(f, axis=1)
    rolled = np.stack([np.roll(row, -s) for row, s in zip(f, k)])
    return rolled[np.lexsort(rolled.T[::-1])]


@pytest.fixture
def torus(rng):
    mask = np.ones((3, 3, 2), dtype=bool)
    mask[1, 1, :] = False
    m = box_tetmesh((3, 3, 2), (0.3, 0.3, 0.1), split=5, cell_mask=mask)
    return m.with_vertices(m.vertices + rng.uniform(-0.003, 0.003, m.vertices.shape))


def test_stage_is_z_up_metres_with_default_prim_and_our_boundary(tmp_path, torus):
    path = tmp_path / "scene.usda"
    mat = PhysicsMaterial(youngs_modulus=2.5e5, poissons_ratio=0.4, density=1100.0)
    write_usd(path, torus, material=mat, name="Torus")
    stage = Usd.Stage.Open(str(path))
    assert UsdGeom.GetStageUpAxis(stage) == UsdGeom.Tokens.z
    assert UsdGeom.GetStageMetersPerUnit(stage) == 1.0
    assert stage.GetDefaultPrim().GetPath() == "/World"

    tm = UsdGeom.TetMesh(stage.GetPrimAtPath("/World/Torus/TetMesh"))
    assert tm
    t = Usd.TimeCode.Default()
    computed = np.asarray(UsdGeom.TetMesh.ComputeSurfaceFaces(tm, t))
    np.testing.assert_array_equal(_canonical(computed), _canonical(torus.boundary_faces()))
    np.testing.assert_array_equal(
        _canonical(np.asarray(tm.GetSurfaceFaceVertexIndicesAttr().Get())), _canonical(torus.boundary_faces())
    )
    assert len(UsdGeom.TetMesh.FindInvertedElements(tm, t)) == 0

    surf = UsdGeom.Mesh(stage.GetPrimAtPath("/World/Torus/Surface"))
    assert np.all(np.asarray(surf.GetFaceVertexCountsAttr().Get()) == 3)
    assert len(surf.GetFaceVertexIndicesAttr().Get()) == 3 * len(torus.boundary_faces())


def test_physics_material_uses_omni_physics_deformable_names_and_is_bound(tmp_path, torus):
    path = tmp_path / "scene.usd"
    mat = PhysicsMaterial(youngs_modulus=3.0e6, poissons_ratio=0.45, density=950.0, static_friction=0.7)
    write_usd(path, torus, material=mat, name="Body")
    stage = Usd.Stage.Open(str(path))
    body = stage.GetPrimAtPath("/World/Body")
    assert "OmniPhysicsDeformableBodyAPI" in _api_schemas(body)
    assert "OmniPhysicsVolumeDeformableSimAPI" in _api_schemas(stage.GetPrimAtPath("/World/Body/TetMesh"))
    bound, _ = UsdShade.MaterialBindingAPI(body).ComputeBoundMaterial("physics")
    assert bound
    mp = bound.GetPrim()
    assert "OmniPhysicsDeformableMaterialAPI" in _api_schemas(mp)
    assert mp.GetAttribute("omniphysics:youngsModulus").Get() == pytest.approx(3.0e6)
    assert mp.GetAttribute("omniphysics:poissonsRatio").Get() == pytest.approx(0.45)
    assert mp.GetAttribute("omniphysics:density").Get() == pytest.approx(950.0)
    assert mp.GetAttribute("omniphysics:staticFriction").Get() == pytest.approx(0.7)
    assert mp.GetAttribute("physics:density").Get() == pytest.approx(950.0)


def test_time_sampled_points_animate_tet_and_surface(tmp_path, torus, rng):
    frames = [torus.vertices + np.array([0.0, 0.0, -0.01 * k]) for k in range(5)]
    w = UsdSceneWriter(tmp_path / "anim.usda", fps=60)
    w.add_tetmesh("Obj", torus, material=PhysicsMaterial())
    w.add_box("Plate", (1.0, 1.0, 0.02), (0.0, 0.0, 0.5))
    for k, x in enumerate(frames):
        w.set_points("Obj", x, k)
        w.set_translation("Plate", (0.0, 0.0, 0.5 - 0.02 * k), k)
    w.save()
    stage = Usd.Stage.Open(str(tmp_path / "anim.usda"))
    assert stage.GetStartTimeCode() == 0 and stage.GetEndTimeCode() == 4
    assert stage.GetTimeCodesPerSecond() == 60
    tm = UsdGeom.TetMesh(stage.GetPrimAtPath("/World/Obj/TetMesh"))
    sm = UsdGeom.Mesh(stage.GetPrimAtPath("/World/Obj/Surface"))
    for k in (0, 3):
        np.testing.assert_allclose(np.asarray(tm.GetPointsAttr().Get(k)), frames[k], atol=1e-6)
        np.testing.assert_allclose(np.asarray(sm.GetPointsAttr().Get(k)), frames[k], atol=1e-6)
    plate = UsdGeom.Xformable(stage.GetPrimAtPath("/World/Plate"))
    m = plate.ComputeLocalToWorldTransform(Usd.TimeCode(3))
    assert m.ExtractTranslation()[2] == pytest.approx(0.44)


def test_invalid_material_and_bad_points_are_refused(tmp_path, torus):
    with pytest.raises(ValueError, match="poissons_ratio"):
        PhysicsMaterial(poissons_ratio=0.5)
    with pytest.raises(ValueError, match="youngs_modulus"):
        PhysicsMaterial(youngs_modulus=-1)
    w = UsdSceneWriter(tmp_path / "x.usda")
    w.add_tetmesh("A", torus)
    with pytest.raises(ValueError, match="expected"):
        w.set_points("A", torus.vertices[:-1], 0)
    with pytest.raises(ValueError, match="non-finite"):
        w.set_points("A", np.full_like(torus.vertices, np.nan), 0)
    with pytest.raises(ValueError, match=r"\.usd"):
        UsdSceneWriter(tmp_path / "x.obj")
