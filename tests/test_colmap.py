"""COLMAP folders: a model written from a synthetic dataset's known cameras round-trips to
1e-6 px; COLMAP's pixel-centre convention (checked on its own SIFT); undistortion of radial
and OpenCV cameras against a NumPy distortion model; masks matched by stem; the visual-hull
normalisation; errors that name the file."""

from __future__ import annotations

import shutil

import numpy as np
import pytest

from holowarp.camera import camera_center, project_points
from holowarp.data import DatasetError, load_dataset
from holowarp.data.colmap import load_colmap, write_colmap
from holowarp.data.dataset import Dataset
from holowarp.data.loaders import detect_format

pycolmap = pytest.importorskip("pycolmap")

VIEWS, RES = 12, 32


@pytest.fixture(scope="module")
def synth(tmp_path_factory):
    """bob's synthetic views (NeRF-synthetic layout) and the loaded dataset."""
    from holowarp.synthesis import DEFAULT_OBJECT, synthesize

    out = tmp_path_factory.mktemp("colmap") / "bob"
    synthesize(DEFAULT_OBJECT, out, views=VIEWS, res=RES, supersample=2, progress=False)
    return out, load_dataset(out, load_normals=False, load_depths=False)


def _non_square_two_cameras(ds: Dataset) -> Dataset:
    """The views cropped to 32 x 28 pixels: even views lose 2 columns on each side, odd ones
    1 on the left and 3 on the right, so there are two cameras (two principal points)."""
    from dataclasses import replace

    K = ds.K.copy()
    images = np.empty((ds.num_views, RES, RES - 4, 3), np.float32)
    masks = np.empty((ds.num_views, RES, RES - 4), np.float32)
    for i in range(ds.num_views):
        left = 2 if i % 2 == 0 else 1
        images[i] = ds.images[i][:, left:left + RES - 4]
        masks[i] = ds.masks[i][:, left:left + RES - 4]
        K[i, 0, 2] -= left
    return replace(ds, images=images, masks=masks, K=K)


def _project_both(src: Dataset, back: Dataset, X: np.ndarray) -> float:
    """Largest pixel distance between world points projected by ``src``'s cameras and the
    same points, moved into ``back``'s normalised world, projected by ``back``'s."""
    Sinv = np.asarray(back.meta["normalization"]["world_from_input"])
    Xn = X @ Sinv[:3, :3].T + Sinv[:3, 3]
    err = 0.0
    for i in range(src.num_views):
        uv0, _ = project_points(X, src.viewmats[i], src.K[i])
        uv1, _ = project_points(Xn, back.viewmats[i], back.K[i])
        err = max(err, float(np.abs(uv0 - uv1).max()))
    return err


@pytest.mark.parametrize("text", [False, True])
def test_model_written_from_known_cameras_round_trips_to_1e6(synth, tmp_path, rng, text):
    src = _non_square_two_cameras(synth[1])
    write_colmap(src, tmp_path / "c", text=text)
    ext = ".txt" if text else ".bin"
    assert (tmp_path / "c" / "sparse" / "0" / f"cameras{ext}").is_file()
    assert detect_format(tmp_path / "c") == "colmap"
    back = load_dataset(tmp_path / "c")
    assert back.meta["format"] == "colmap" and len(back.meta["cameras"]) == 2
    assert back.images.shape == (VIEWS, RES, RES - 4, 3)
    np.testing.assert_allclose(back.K, src.K, atol=1e-9)  # a similarity leaves K alone
    np.testing.assert_allclose(back.masks, src.masks, atol=0.5 / 255 + 1e-7)  # 8-bit PNGs
    np.testing.assert_array_equal(back.test_idx, [0, 10])
    X = rng.normal(size=(200, 3)) * 0.4
    assert _project_both(src, back, X) < 1e-6
    S = np.asarray(back.meta["normalization"]["scale_mat"])
    for i in range(VIEWS):  # centres map through scale_mat; rotations turn by the up rotation
        c = camera_center(back.viewmats[i])
        np.testing.assert_allclose(S[:3, :3] @ c + S[:3, 3], camera_center(src.viewmats[i]), atol=1e-9)
        np.testing.assert_allclose(back.viewmats[i, :3, :3] @ back.viewmats[i, :3, :3].T, np.eye(3), atol=1e-12)


def test_colmap_projection_is_holowarps(synth, tmp_path, rng):
    """pycolmap's own projection of the written model equals holowarp's of the dataset:
    same axes (OpenCV), same K, same pixel-centre convention."""
    src = _non_square_two_cameras(synth[1])
    write_colmap(src, tmp_path / "c")
    rec = pycolmap.Reconstruction(tmp_path / "c" / "sparse" / "0")
    X = rng.normal(size=(50, 3)) * 0.4
    for im in rec.images.values():
        i = int(im.name[:4])
        uv, _ = project_points(X, src.viewmats[i], src.K[i])
        M = im.cam_from_world().matrix()
        uv_colmap = rec.cameras[im.camera_id].img_from_cam(X @ M[:, :3].T + M[:, 3])
        np.testing.assert_allclose(uv_colmap, uv, atol=1e-9)


def test_colmap_sift_puts_pixel_centres_at_half_integers(rng):
    """A Gaussian blob centred at holowarp image point (x, y) (pixel (i, j) spans [i, i + 1])
    is found by COLMAP's SIFT at (x, y), not (x - 0.5, y - 0.5): COLMAP's image coordinates
    are holowarp's, so K needs no half-pixel shift."""
    o = pycolmap.FeatureExtractionOptions()
    o.num_threads = 1
    sift = pycolmap.FeatureExtractor.create(o, pycolmap.Device.cpu)
    H = W = 64
    yy, xx = np.mgrid[0:H, 0:W] + 0.5  # pixel centres, holowarp's convention
    for _ in range(3):
        x0, y0 = rng.uniform(24, 40, 2)
        img = np.exp(-((xx - x0) ** 2 + (yy - y0) ** 2) / (2 * 2.5**2)).astype(np.float32)
        kp = pycolmap.keypoints_to_matrix(sift.extract_from_float32_array(img)[0])
        d = np.hypot(kp[:, 0] - x0, kp[:, 1] - y0)
        assert d.min() < 0.1, (kp[:, :2], x0, y0)


def test_models_without_points3d_or_rigs_load(synth, tmp_path):
    write_colmap(_non_square_two_cameras(synth[1]), tmp_path / "c")
    full = load_dataset(tmp_path / "c")
    for name in ("points3D", "rigs", "frames"):  # COLMAP < 3.12 has no rigs/frames
        (tmp_path / "c" / "sparse" / "0" / f"{name}.bin").unlink()
    shutil.move(tmp_path / "c" / "sparse" / "0", tmp_path / "c" / "model")
    (tmp_path / "c" / "sparse").rmdir()
    shutil.move(tmp_path / "c" / "model", tmp_path / "c" / "sparse")  # sparse/ itself holds the model
    back = load_dataset(tmp_path / "c")
    np.testing.assert_allclose(back.viewmats, full.viewmats, atol=1e-12)


# ---------------------------------------------------------------- distortion

def _distort(x, y, model, params):
    """Forward distortion of normalised camera coordinates, written from COLMAP's camera
    model definitions (NumPy, independent of pycolmap)."""
    r2 = x * x + y * y
    if model == "SIMPLE_RADIAL":
        k = params[3]
        return x * (1 + k * r2), y * (1 + k * r2)
    k1, k2, p1, p2 = params[4:8]
    radial = 1 + k1 * r2 + k2 * r2 * r2
    return (x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x),
            y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y)


def _pattern(x, y):
    """A smooth RGB pattern in normalised coordinates, and a disk mask."""
    rgb = np.stack([0.5 + 0.4 * np.sin(3 * x + 1), 0.5 + 0.4 * np.cos(2 * y - 0.5), 0.5 + 0.3 * np.sin(2 * (x + y))], -1)
    return rgb, (x * x + y * y < 0.2).astype(np.float64)


@pytest.mark.parametrize("model", ["SIMPLE_RADIAL", "OPENCV"])
def test_radial_and_opencv_photos_are_undistorted_on_load(tmp_path, model):
    from PIL import Image

    W, H = 60, 44
    f, cx, cy = 50.0, 30.7, 21.9
    params = [f, cx, cy, -0.12] if model == "SIMPLE_RADIAL" else [f, 51.0, cx, cy, -0.15, 0.03, 0.004, -0.003]
    fx, fy = params[0], params[0] if model == "SIMPLE_RADIAL" else params[1]
    rec = pycolmap.Reconstruction()
    rec.add_camera_with_trivial_rig(pycolmap.Camera(model=model, width=W, height=H, params=params, camera_id=1))
    (tmp_path / "images").mkdir()
    (tmp_path / "masks").mkdir()
    ud, vd = np.meshgrid(np.arange(W) + 0.5, np.arange(H) + 0.5)  # the photo is distorted:
    rgb, mask = _pattern((ud - cx) / fx, (vd - cy) / fy)  # the pattern lives at distorted points
    for i in range(3):
        R = pycolmap.Rotation3d(np.array([0.1 * i, -0.05, 0.02])).matrix()
        rec.add_image_with_trivial_frame(pycolmap.Image(name=f"{i}.png", camera_id=1, image_id=i + 1),
                                         pycolmap.Rigid3d(np.c_[R, [0.1 * i, 0.0, 3.0]]))
        Image.fromarray(np.uint8(np.rint(rgb * 255))).save(tmp_path / "images" / f"{i}.png")
        Image.fromarray(np.uint8(np.rint(mask * 255))).save(tmp_path / "masks" / f"{i}.png")
    (tmp_path / "sparse" / "0").mkdir(parents=True)
    rec.write(tmp_path / "sparse" / "0")
    ds = load_colmap(tmp_path, normalize=False)
    np.testing.assert_allclose(ds.K[0], [[fx, 0, cx], [0, fy, cy], [0, 0, 1]])
    assert ds.meta["cameras"][1]["undistorted"]
    u, v = np.meshgrid(np.arange(W) + 0.5, np.arange(H) + 0.5)
    xd, yd = _distort((u - cx) / fx, (v - cy) / fy, model, params)
    want_rgb, want_mask = _pattern(xd, yd)
    # Pixels whose distorted source lies inside the photo, away from the mask's edge.
    xs, ys = xd * fx + cx, yd * fy + cy
    inside = (xs > 1) & (xs < W - 1) & (ys > 1) & (ys < H - 1)
    assert inside.mean() > 0.8
    np.testing.assert_allclose(ds.images[0][inside], want_rgb[inside], atol=6e-3)  # bilinear + 8 bit
    firm = inside & (np.abs(xd**2 + yd**2 - 0.2) > 0.03)
    np.testing.assert_allclose(ds.masks[0][firm], want_mask[firm], atol=1e-6)
    # Sensitivity: the photo read as a pinhole image misses by several times the tolerance.
    assert np.abs(rgb[inside] - want_rgb[inside]).max() > 0.02


def test_fisheye_cameras_are_refused_with_the_model_named(synth, tmp_path):
    write_colmap(synth[1], tmp_path / "c")
    rec = pycolmap.Reconstruction(tmp_path / "c" / "sparse" / "0")
    cam = rec.cameras[1]
    rec.cameras[1] = pycolmap.Camera(model="OPENCV_FISHEYE", width=cam.width, height=cam.height,
                                     params=[cam.focal_length_x, cam.focal_length_y, cam.principal_point_x,
                                             cam.principal_point_y, 0.01, 0.0, 0.0, 0.0], camera_id=1)
    rec.write(tmp_path / "c" / "sparse" / "0")
    with pytest.raises(DatasetError, match="camera 1 is OPENCV_FISHEYE.*undistorts SIMPLE_RADIAL"):
        load_dataset(tmp_path / "c")


# ---------------------------------------------------------------- masks, normalisation, errors

def test_masks_match_images_by_stem(synth, tmp_path):
    write_colmap(synth[1], tmp_path / "c")
    m = tmp_path / "c" / "masks"
    (m / "0001.png").rename(m / "0001.png.png")  # COLMAP's own mask naming: <image name>.png
    (m / "0002.png").rename(m / "0002.jpg")
    ds = load_dataset(tmp_path / "c")
    assert ds.meta["mask_files"][1:3] == ["0001.png.png", "0002.jpg"]
    (m / "0003.png").unlink()
    with pytest.raises(DatasetError, match=r"masks: no mask for 0003\.png \(1 of 12 images"):
        load_dataset(tmp_path / "c")
    shutil.copyfile(m / "0004.png", m / "0003.png")
    shutil.copyfile(m / "0004.png", m / "0004.jpg")
    with pytest.raises(DatasetError, match="both masks of image stem '0004'"):
        load_dataset(tmp_path / "c")


def test_normalisation_maps_the_hull_into_the_unit_sphere_with_cameras_up_along_z(synth, tmp_path, rng):
    from dataclasses import replace

    from holowarp.surface_io import load_obj

    out, ds = synth
    # Move the world by a random similarity first: COLMAP worlds have any scale and up.
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    q *= np.sign(np.linalg.det(q))
    s, t = rng.uniform(0.2, 5.0), rng.normal(size=3) * 3
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = s * q, t  # x_colmap = T x_dataset
    V = ds.viewmats @ np.linalg.inv(T)  # its rotation block is R q^T / s
    V[:, :3, :] *= s  # rigid again: scaling camera coordinates moves no pixel
    write_colmap(replace(ds, viewmats=V), tmp_path / "c")
    back = load_dataset(tmp_path / "c")
    norm = back.meta["normalization"]
    up = -back.viewmats[:, 1, :3].mean(0)
    np.testing.assert_allclose(up / np.linalg.norm(up), [0, 0, 1], atol=1e-9)
    W = np.asarray(norm["world_from_input"]) @ T
    gt = load_obj(out / "gt.obj").positions
    r = np.linalg.norm(gt @ W[:3, :3].T + W[:3, 3], axis=1)
    assert r.max() <= 1.0 and r.max() > 0.8  # the object fills the unit sphere, as NeuS's
    assert _project_both(replace(ds, viewmats=V), back, rng.normal(size=(50, 3))) < 1e-6


def test_bad_colmap_folders_name_the_file(synth, tmp_path):
    from PIL import Image

    write_colmap(synth[1], tmp_path / "c")
    c = tmp_path / "c"
    (c / "images" / "0005.png").unlink()
    with pytest.raises(DatasetError, match=r"0005\.png.*not found"):
        load_dataset(c)
    Image.fromarray(np.zeros((RES, RES + 3, 3), np.uint8)).save(c / "images" / "0005.png")
    with pytest.raises(DatasetError, match=r"0005\.png: size 35x32 differs from its COLMAP camera 1 \(32x32\)"):
        load_dataset(c)
    shutil.copyfile(c / "images" / "0004.png", c / "images" / "0005.png")
    Image.fromarray(np.zeros((RES, RES), np.uint8)).save(c / "masks" / "0006.png")
    with pytest.raises(DatasetError, match=r"0006\.png: mask is empty"):
        load_dataset(c)
    (c / "sparse" / "0" / "cameras.bin").write_bytes(b"\x07" * 20)
    with pytest.raises(DatasetError, match=r"sparse/0: pycolmap cannot read the model"):
        load_dataset(c)
    shutil.rmtree(c / "images")
    write_colmap(synth[1], tmp_path / "d")
    shutil.rmtree(tmp_path / "d" / "images")
    with pytest.raises(DatasetError, match=r"d/images: image folder not found"):
        load_dataset(tmp_path / "d")


def test_skewed_datasets_are_refused_by_the_writer(synth, tmp_path):
    from dataclasses import replace

    K = synth[1].K.copy()
    K[:, 0, 1] = 0.3
    with pytest.raises(DatasetError, match="no skew"):
        write_colmap(replace(synth[1], K=K), tmp_path / "c")
