"""OBJ reading, the synth command's NeRF-synthetic output read back by the loaders, a NeuS
fixture written here, and the loaders' errors on broken folders."""

from __future__ import annotations

import json
import math
import shutil

import numpy as np
import pytest

from holowarp.camera import FOV_DEG, project_points
from holowarp.data import Dataset, DatasetError, load_dataset
from holowarp.data.loaders import decompose_projection, load_neus, write_nerf_synthetic
from holowarp.surface_io import SurfaceError, load_obj, weld
from holowarp.synthesis import SynthError, protocol_cameras, synthesize

VIEWS, RES = 12, 24
BOX = (0.6, 1.2, 0.3)  # Y-up model, tallest along y


def _write_textured_box(folder, rng):
    """A box with one quad (4 own vertices, split at every seam) per face, UVs and a texture."""
    from PIL import Image

    folder.mkdir(parents=True, exist_ok=True)
    hx, hy, hz = (s / 2 for s in BOX)
    corners = np.array([[x, y, z] for x in (-hx, hx) for y in (-hy, hy) for z in (-hz, hz)])
    quads = [[0, 1, 3, 2], [4, 6, 7, 5], [0, 4, 5, 1], [2, 3, 7, 6], [0, 2, 6, 4], [1, 5, 7, 3]]
    lines = ["mtllib box.mtl", "usemtl tex"]
    k = 0
    for q in quads:
        for c in q:
            lines.append("v %.6f %.6f %.6f" % tuple(corners[c]))
    for uv in ([0, 0], [1, 0], [1, 1], [0, 1]):
        lines.append("vt %g %g" % tuple(uv))
    for qi in range(6):
        a = 4 * qi + 1
        lines.append(f"f {a}/1 {a + 1}/2 {a + 2}/3 {a + 3}/4")  # quads: fan-triangulated
        k += 1
    (folder / "box.obj").write_text("\n".join(lines) + "\n")
    (folder / "box.mtl").write_text("newmtl tex\nKd 1 1 1\nmap_Kd box.png\n")
    Image.fromarray((rng.random((8, 8, 3)) * 255).astype(np.uint8)).save(folder / "box.png")
    return folder / "box.obj"


@pytest.fixture(scope="module")
def synth_box(tmp_path_factory):
    rng = np.random.default_rng(1234)
    root = tmp_path_factory.mktemp("synth")
    obj = _write_textured_box(root / "src", rng)
    out = root / "ds"
    summary = synthesize(obj, out, views=VIEWS, res=RES, supersample=2, progress=False)
    return obj, out, summary


def test_obj_reader_splits_seams_and_weld_merges_them(synth_box):
    obj, _, _ = synth_box
    m = load_obj(obj)
    assert m.positions.shape == (24, 3) and m.faces.shape == (12, 3)
    assert m.textured and m.texture.shape == (8, 8, 3) and m.face_uvs.shape == (12, 3)
    w = m.welded()
    assert w.positions.shape == (8, 3) and w.faces.shape == (12, 3)
    np.testing.assert_array_equal(w.face_uvs, m.face_uvs)  # texture mapping untouched
    # Every welded face keeps its geometry.
    np.testing.assert_allclose(w.positions[w.faces], m.positions[m.faces])


def test_weld_merges_within_tolerance_and_drops_collapsed_faces(rng):
    p = rng.random((5, 3))
    p = np.vstack([p, p[0] + 1e-9])  # vertex 5 duplicates vertex 0
    faces = np.array([[0, 1, 2], [5, 3, 4], [0, 5, 1]])
    v, f, old_to_new = weld(p, faces)
    assert len(v) == 5 and old_to_new[5] == old_to_new[0]
    assert len(f) == 2  # the face using both 0 and 5 collapsed


def test_synth_writes_nerf_synthetic_layout(synth_box):
    _, out, summary = synth_box
    tr = json.loads((out / "transforms_train.json").read_text())
    te = json.loads((out / "transforms_test.json").read_text())
    assert math.isclose(tr["camera_angle_x"], math.radians(FOV_DEG))
    assert [f["view_index"] for f in te["frames"]] == [0, 10]
    assert [f["view_index"] for f in tr["frames"]] == [i for i in range(VIEWS) if i % 10]
    for doc, split in ((tr, "train"), (te, "test")):
        for fr in doc["frames"]:
            assert fr["file_path"] == f"./{split}/r_{fr['view_index']}"
            for suffix in (".png", "_normal.png", "_depth.png", "_geom.npz"):
                assert (out / split / f"r_{fr['view_index']}{suffix}").is_file()
            assert np.asarray(fr["transform_matrix"]).shape == (4, 4)
    assert tr["holowarp"]["transform"]["scale"] > 0 and summary["train"] == 10 and summary["test"] == 2
    # gt.obj: welded, Z up (the model's tall y axis is now z), bbox centred with largest side 1.
    g = load_obj(out / "gt.obj")
    assert len(g.positions) == 8
    lo, hi = g.positions.min(0), g.positions.max(0)
    np.testing.assert_allclose(lo + hi, 0, atol=1e-7)
    np.testing.assert_allclose(hi - lo, np.array([BOX[0], BOX[2], BOX[1]]) / BOX[1], atol=1e-7)


def test_loader_round_trips_synth_output(synth_box):
    from PIL import Image

    from holowarp.render_gt import GTRenderer

    obj, out, _ = synth_box
    ds = load_dataset(out)
    assert ds.num_views == VIEWS and ds.images.shape == (VIEWS, RES, RES, 3)
    np.testing.assert_array_equal(ds.test_idx, [0, 10])
    np.testing.assert_array_equal(ds.train_idx, [i for i in range(VIEWS) if i % 10])
    assert ds.gt_mesh == out / "gt.obj"
    meta = ds.meta["holowarp"]
    V_expect, K_expect = protocol_cameras(VIEWS, meta["camera_distance"], RES)
    np.testing.assert_allclose(ds.viewmats, V_expect, atol=1e-9)
    np.testing.assert_allclose(ds.K, np.broadcast_to(K_expect, (VIEWS, 3, 3)), atol=1e-9)
    rgba = np.asarray(Image.open(out / "train" / "r_3.png"), dtype=np.float32) / 255
    np.testing.assert_array_equal(ds.masks[3], rgba[..., 3])
    # Exact normals/depth equal a fresh render of gt.obj with the same cameras.
    g = load_obj(out / "gt.obj")
    r = GTRenderer(g.positions, g.faces, supersample=2).render(ds.viewmats[3], ds.K[3], RES, RES)
    np.testing.assert_allclose(ds.normals[3], r["normal"], atol=1e-6)
    np.testing.assert_allclose(ds.depths[3], r["depth"], atol=1e-6)
    assert np.abs(ds.masks[3] - r["mask"]).max() <= 0.5 / 255 + 1e-7
    # Fully covered pixels back-project (through K and viewmat) onto the box surface.
    half = (g.positions.max(0) - g.positions.min(0)) / 2
    for i in (0, 5):
        # Fully covered pixels whose rays all hit one face (axis-aligned mean normal).
        yy, xx = np.nonzero((ds.masks[i] == 1.0) & (np.abs(ds.normals[i]).max(-1) > 1 - 1e-6))
        z = ds.depths[i][yy, xx]
        pc = np.stack([(xx + 0.5 - ds.K[i, 0, 2]) / ds.K[i, 0, 0] * z, (yy + 0.5 - ds.K[i, 1, 2]) / ds.K[i, 1, 1] * z, z], 1)
        R, t = ds.viewmats[i, :3, :3], ds.viewmats[i, :3, 3]
        pw = (pc - t) @ R
        # Signed distance to the box surface (depth is the mean of 2x2 sub-pixel rays, which
        # is not exactly the centre ray's depth under perspective).
        sd = (np.abs(pw) - half).max(axis=1)
        assert len(pw) > 20 and np.abs(sd).max() < 2e-3


def test_loader_resizes_and_writer_round_trips(synth_box, tmp_path):
    _, out, _ = synth_box
    ds = load_dataset(out, res=RES // 2)
    assert ds.images.shape == (VIEWS, RES // 2, RES // 2, 3)
    np.testing.assert_allclose(ds.K[:, 0, 0], load_dataset(out).K[:, 0, 0] / 2)
    full = load_dataset(out)
    write_nerf_synthetic(full, tmp_path / "copy")
    back = load_dataset(tmp_path / "copy")
    np.testing.assert_allclose(back.viewmats, full.viewmats, atol=1e-9)
    np.testing.assert_allclose(back.K, full.K, atol=1e-9)
    np.testing.assert_allclose(back.images, full.images, atol=0.5 / 255 + 1e-6)
    np.testing.assert_array_equal(back.test_idx, full.test_idx)
    assert back.gt_mesh is not None


def test_folder_without_test_split_holds_out_every_tenth_training_view(synth_box, tmp_path):
    _, out, _ = synth_box
    dst = tmp_path / "ds"
    shutil.copytree(out, dst)
    (dst / "transforms_test.json").unlink()  # as the real lego capture
    ds = load_dataset(dst, res=RES // 2, test_every=4)
    train_views = [i for i in range(VIEWS) if i % 10]  # the synth split's training views, in order
    assert ds.num_views == len(train_views) and ds.images.shape[1:3] == (RES // 2, RES // 2)
    np.testing.assert_array_equal(ds.test_idx, [0, 4, 8])
    assert ds.meta["held_out"] == {"test_every": 4, "views": [0, 4, 8]}
    np.testing.assert_array_equal(ds.train_idx, [j for j in range(len(train_views)) if j % 4])


def test_nerf_loader_converts_opengl_axes_to_opencv(tmp_path, rng):
    from PIL import Image

    img = np.zeros((10, 20, 4), np.uint8)
    img[3:7, 5:15] = 255
    (tmp_path / "train").mkdir()
    Image.fromarray(img).save(tmp_path / "train" / "a.png")
    c2w = np.eye(4)
    c2w[:3, 3] = [0.0, 0.0, 3.0]  # OpenGL camera at +3z looking down -z, y up
    doc = {"camera_angle_x": 0.8, "frames": [{"file_path": "./train/a", "transform_matrix": c2w.tolist()}]}
    (tmp_path / "transforms_train.json").write_text(json.dumps(doc))
    ds = load_dataset(tmp_path)
    assert ds.images.shape == (1, 10, 20, 3)
    assert math.isclose(ds.K[0, 0, 0], 10 / math.tan(0.4)) and ds.K[0, 0, 2] == 10 and ds.K[0, 1, 2] == 5
    uv, z = project_points(np.array([[0.0, 0.0, 0.0], [0.5, 0.0, 0.0], [0.0, 0.5, 0.0]]), ds.viewmats[0], ds.K[0])
    assert np.allclose(z, 3.0)  # in front of the camera
    assert uv[1, 0] > uv[0, 0]  # world +x to the image right
    assert uv[2, 1] < uv[0, 1]  # world +y up in the image (OpenCV y points down)


def _write_neus(root, rng, n=12, h=16, w=20):
    from PIL import Image

    (root / "image").mkdir(parents=True)
    (root / "mask").mkdir()
    cams = {}
    truth = []
    for i in range(n):
        K = np.array([[rng.uniform(20, 30), rng.uniform(-0.5, 0.5), rng.uniform(8, 12)], [0, rng.uniform(20, 30), rng.uniform(6, 10)], [0, 0, 1]])
        q = rng.normal(size=4)
        q /= np.linalg.norm(q)
        a, b, c, d = q
        R = np.array([
            [a * a + b * b - c * c - d * d, 2 * (b * c - a * d), 2 * (b * d + a * c)],
            [2 * (b * c + a * d), a * a - b * b + c * c - d * d, 2 * (c * d - a * b)],
            [2 * (b * d - a * c), 2 * (c * d + a * b), a * a - b * b - c * c + d * d],
        ])
        centre = rng.normal(size=3) * 3
        P = np.eye(4)
        P[:3, :4] = K @ np.hstack([R, (-R @ centre)[:, None]])
        P *= rng.choice([-1, 1]) * rng.uniform(0.5, 2)  # projections are defined up to scale
        S = np.diag([2.0, 2.0, 2.0, 1.0])
        S[:3, 3] = rng.normal(size=3)
        cams[f"world_mat_{i}"] = P
        cams[f"scale_mat_{i}"] = S
        truth.append((P, S))
        Image.fromarray((rng.random((h, w, 3)) * 255).astype(np.uint8)).save(root / "image" / f"{i:03d}.png")
        m = np.zeros((h, w, 3), np.uint8)
        m[4:10, 5:12] = 255
        Image.fromarray(m).save(root / "mask" / f"{i:03d}.png")
    np.savez(root / "cameras_sphere.npz", **cams)
    return truth


def test_neus_fixture_loads_with_matching_projections(tmp_path, rng):
    truth = _write_neus(tmp_path / "neus", rng)
    ds = load_dataset(tmp_path / "neus")
    assert ds.meta["format"] == "neus" and ds.num_views == 12
    np.testing.assert_array_equal(ds.test_idx, [0, 10])
    assert ds.masks.max() == 1.0 and ds.masks[:, 5, 6].min() == 1.0 and ds.masks[:, 0, 0].max() == 0.0
    X = rng.normal(size=(50, 3)) * 0.5  # points in the normalised (scale_mat) frame
    for i, (P, S) in enumerate(truth):
        Ph = (P @ S)[:3] @ np.hstack([X, np.ones((50, 1))]).T
        uv_neus = (Ph[:2] / Ph[2]).T  # NeuS: pixel centres at integers
        uv, z = project_points(X, ds.viewmats[i], ds.K[i])
        np.testing.assert_allclose(uv, uv_neus + 0.5, atol=1e-7)
        np.testing.assert_allclose(ds.viewmats[i, :3, :3] @ ds.viewmats[i, :3, :3].T, np.eye(3), atol=1e-10)
        assert np.linalg.det(ds.viewmats[i, :3, :3]) > 0 and (np.diag(ds.K[i]) > 0).all()


def test_neus_views_are_resized_as_decoded_keeping_skew_and_aspect(tmp_path, rng):
    truth = _write_neus(tmp_path / "neus", rng, n=11, h=30, w=44)
    full = load_neus(tmp_path / "neus")
    small = load_neus(tmp_path / "neus", res=20, workers=3)
    assert small.images.shape == (11, 14, 20, 3)  # 44 x 30 -> 20 x 13.6, rounded
    ref = full.resized(20)  # the area filter applied to the full-resolution stack
    np.testing.assert_allclose(small.images, ref.images, atol=2e-6)
    np.testing.assert_allclose(small.masks, ref.masks, atol=2e-6)
    np.testing.assert_allclose(small.K, ref.K, atol=1e-12)
    np.testing.assert_array_equal(load_neus(tmp_path / "neus", res=20, workers=1).images, small.images)
    X = rng.normal(size=(40, 3)) * 0.5
    for i, (P, S) in enumerate(truth):  # the skewed projection, scaled to the small images
        Ph = (P @ S)[:3] @ np.hstack([X, np.ones((40, 1))]).T
        uv_neus = (Ph[:2] / Ph[2]).T + 0.5  # NeuS pixel centres at integers
        uv, _ = project_points(X, small.viewmats[i], small.K[i])
        np.testing.assert_allclose(uv, uv_neus * [20 / 44, 14 / 30], atol=1e-7)
    assert abs(small.K[0, 0, 1]) > 0  # the skew survives the resize
    with pytest.raises(DatasetError, match="--res must be >= 1"):
        load_neus(tmp_path / "neus", res=0)


def test_decompose_projection_recovers_camera(rng):
    K = np.array([[500.0, 1.0, 320.0], [0.0, 480.0, 240.0], [0.0, 0.0, 1.0]])
    R, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    R *= np.sign(np.linalg.det(R))
    c = rng.normal(size=3)
    P = -2.5 * K @ np.hstack([R, (-R @ c)[:, None]])
    K2, R2, c2 = decompose_projection(P)
    np.testing.assert_allclose(K2, K, atol=1e-8)
    np.testing.assert_allclose(R2, R, atol=1e-10)
    np.testing.assert_allclose(c2, c, atol=1e-10)


# ---------------------------------------------------------------- errors on broken folders


@pytest.fixture
def broken_copy(synth_box, tmp_path):
    _, out, _ = synth_box
    dst = tmp_path / "ds"
    shutil.copytree(out, dst)
    return dst


def test_missing_image_is_named(broken_copy):
    (broken_copy / "train" / "r_3.png").unlink()
    with pytest.raises(DatasetError, match="r_3"):
        load_dataset(broken_copy)


def test_mismatched_image_size_is_named(broken_copy):
    from PIL import Image

    Image.fromarray(np.zeros((RES + 2, RES, 4), np.uint8)).save(broken_copy / "train" / "r_4.png")
    with pytest.raises(DatasetError, match="r_4.png.*differs"):
        load_dataset(broken_copy)


def test_absent_and_empty_masks_are_rejected(broken_copy):
    from PIL import Image

    p = broken_copy / "train" / "r_5.png"
    rgb = np.asarray(Image.open(p))[..., :3]
    Image.fromarray(rgb).save(p)
    with pytest.raises(DatasetError, match="r_5.png.*no alpha"):
        load_dataset(broken_copy)
    Image.fromarray(np.zeros((RES, RES, 4), np.uint8)).save(p)
    with pytest.raises(DatasetError, match="r_5.png.*empty"):
        load_dataset(broken_copy)


def test_non_invertible_pose_is_rejected(broken_copy):
    jp = broken_copy / "transforms_train.json"
    doc = json.loads(jp.read_text())
    doc["frames"][2]["transform_matrix"] = np.zeros((4, 4)).tolist()
    jp.write_text(json.dumps(doc))
    with pytest.raises(DatasetError, match="frame 2.*not invertible"):
        load_dataset(broken_copy)


def test_neus_without_masks_or_with_singular_camera_is_rejected(tmp_path, rng):
    _write_neus(tmp_path / "a", rng, n=3)
    shutil.rmtree(tmp_path / "a" / "mask")
    with pytest.raises(DatasetError, match="mask"):
        load_neus(tmp_path / "a")
    _write_neus(tmp_path / "b", rng, n=3)
    cams = dict(np.load(tmp_path / "b" / "cameras_sphere.npz"))
    cams["world_mat_1"] = np.zeros((4, 4))
    np.savez(tmp_path / "b" / "cameras_sphere.npz", **cams)
    with pytest.raises(DatasetError, match="world_mat_1.*not an invertible"):
        load_neus(tmp_path / "b")


def test_unknown_layout_and_existing_output_give_clear_errors(synth_box, tmp_path):
    obj, out, _ = synth_box
    with pytest.raises(DatasetError, match="unknown dataset layout"):
        load_dataset(tmp_path)
    with pytest.raises(SynthError, match="--resume"):
        synthesize(obj, out, views=VIEWS, res=RES, progress=False)
    with pytest.raises(SurfaceError, match="missing.obj: no such file"):
        synthesize(tmp_path / "missing.obj", tmp_path / "x", views=2, res=16, progress=False)


def test_synth_resume_keeps_existing_views(synth_box, tmp_path):
    obj, out, _ = synth_box
    dst = tmp_path / "ds"
    shutil.copytree(out, dst)
    (dst / "train" / "r_7.png").unlink()
    s = synthesize(obj, dst, views=VIEWS, res=RES, resume=True, progress=False)
    assert s["rendered"] == 1 and (dst / "train" / "r_7.png").is_file()
    assert isinstance(load_dataset(dst), Dataset)
    with pytest.raises(SynthError, match="resolution: 24 -> 32"):
        synthesize(obj, dst, views=VIEWS, res=32, resume=True, progress=False)


@pytest.mark.parametrize("name,euler", [("spot", 2), ("bob", 0)])
def test_shared_textured_objs_weld_into_closed_surfaces(name, euler):
    from conftest import shared_mesh

    m = load_obj(shared_mesh(name))
    assert m.textured
    w = m.welded()
    f = w.faces.astype(np.int64)
    e = np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1)
    _, counts = np.unique(e, axis=0, return_counts=True)
    assert (counts == 2).all()  # closed, edge-manifold once the seams are welded
    assert len(np.unique(f)) - len(counts) + len(f) == euler  # spot genus 0, bob genus 1
