"""Dataset layouts (stg_train.data.layouts, colmap, reference, rig, technicolor) on small examples written
here from the synthetic scene: COLMAP models through pycolmap, frames as PNGs or mp4 videos."""
import shutil

import cv2
import numpy as np
import pycolmap
import pytest

from stg_runtime.camera import Camera
from stg_train.data import DataError, Dataset, detect_layout, load_dataset, load_n3v
from stg_train.data.colmap import (cameras_from_reconstruction, read_reconstruction, reconstruction_from_cameras,
                                   reconstruction_points, write_reconstruction)
from stg_train.synthetic import SyntheticScene, write_n3v

CAMS, FRAMES, FPS, W, H = 4, 3, 30, 64, 48


@pytest.fixture(scope="module")
def scene():
    return SyntheticScene(seed=2, duration=FRAMES / FPS)


@pytest.fixture(scope="module")
def rig(scene):
    """(cameras, frames (C, F, H, W, 3) uint8 RGB): the renders every layout is written from."""
    cams = scene.cameras(CAMS, W, H)
    frames = np.stack([[np.rint(scene.render(c, k / FPS) * 255).astype(np.uint8) for k in range(FRAMES)]
                       for c in cams])
    return cams, frames


def _png(path, rgb):
    path.parent.mkdir(parents=True, exist_ok=True)
    assert cv2.imwrite(str(path), np.ascontiguousarray(rgb[..., ::-1]))


def _assert_same_cameras(got, want, rtol=0.0):
    assert [c.name for c in got] == [c.name for c in want]
    for a, b in zip(got, want):
        np.testing.assert_allclose([a.fx, a.fy, a.cx, a.cy], [b.fx, b.fy, b.cx, b.cy], rtol=rtol or 1e-12, atol=1e-6)
        np.testing.assert_allclose(a.world_to_camera, b.world_to_camera, atol=1e-6)
        assert (a.width, a.height) == (b.width, b.height)


def _assert_frames(data, frames):
    assert isinstance(data.frames, np.memmap)
    assert data.frames.shape == frames.shape
    for c in range(frames.shape[0]):
        for k in range(frames.shape[1]):
            np.testing.assert_array_equal(data.frame(c, k), frames[c, k])


def _expect(fragment, name, path, **kwargs):
    with pytest.raises(DataError) as e:
        load_dataset(path, **kwargs)
    message = str(e.value)
    assert name in message and fragment in message, message
    return message


# -- writers of each layout ------------------------------------------------------------------------
def write_reference(root, cams, frames):
    for i in range(frames.shape[1]):
        for c, cam in enumerate(cams):
            _png(root / f"colmap_{i}" / "images" / f"{cam.name}.png", frames[c, i])
        write_reconstruction(reconstruction_from_cameras(cams), root / f"colmap_{i}" / "sparse" / "0")
    return root


def write_rig(root, cams, frames, image_names=None, text=False, videos=False):
    for c, cam in enumerate(cams):
        if videos:
            (root / "videos").mkdir(parents=True, exist_ok=True)
            writer = cv2.VideoWriter(str(root / "videos" / f"{cam.name}.mp4"), cv2.VideoWriter_fourcc(*"mp4v"), 25,
                                     (W, H))
            for k in range(frames.shape[1]):
                writer.write(np.ascontiguousarray(frames[c, k, ..., ::-1]))
            writer.release()
        else:
            for k in range(frames.shape[1]):
                _png(root / "images" / cam.name / f"{k:05d}.png", frames[c, k])
    names = image_names or [f"{cam.name}/00000.png" for cam in cams]
    write_reconstruction(reconstruction_from_cameras(cams, names), root / "sparse" / "0", text=text)
    return root


def _quaternion(R):
    x, y, z, w = pycolmap.Rotation3d(R).quat
    return [w, x, y, z]


def write_technicolor(root, cams, frames, first=151, scene="Birthday"):
    root.mkdir(parents=True, exist_ok=True)
    sx, sy = 2048 / W, 1088 / H  # the file's intrinsics refer to 2048x1088 images
    lines = ["f cu cv ar sk qw qx qy qz tx ty tz"]
    for cam in cams:
        f, fy = cam.fx * sx, cam.fy * sy
        row = [f, cam.cx * sx, cam.cy * sy, fy / f, 0.0, *_quaternion(cam.R), *cam.t]
        lines.append(" ".join(f"{v:.17g}" for v in row))
    (root / "cameras_parameters.txt").write_text("\n".join(lines) + "\n")
    for c in range(len(cams)):
        for k in range(frames.shape[1]):
            _png(root / f"{scene}_undist_{first + k:05d}_{c:02d}.png", frames[c, k])
    return root


# -- COLMAP models ---------------------------------------------------------------------------------
@pytest.mark.parametrize("text", [False, True])
def test_colmap_model_round_trip(rig, tmp_path, text):
    cams, _ = rig
    rec = reconstruction_from_cameras(cams)
    assert rec.num_reg_images() == CAMS and rec.num_cameras() == CAMS
    assert sorted(im.name for im in rec.images.values()) == [f"cam{i:02d}.png" for i in range(CAMS)]
    rec.add_point3D(np.array([0.5, 0.25, 4.0]), pycolmap.Track(), np.array([255, 51, 0], np.uint8))
    write_reconstruction(rec, tmp_path / "sparse" / "0", text=text)
    back = read_reconstruction(tmp_path / "sparse" / "0")
    _assert_same_cameras(cameras_from_reconstruction(back, "model"), cams)
    xyz, rgb = reconstruction_points(back)
    assert xyz.dtype == np.float64 and rgb.dtype == np.float32
    np.testing.assert_allclose(xyz, [[0.5, 0.25, 4.0]])
    np.testing.assert_allclose(rgb, [[1.0, 0.2, 0.0]], atol=1e-6)
    # a pixel centre projects through the COLMAP camera exactly as through ours
    ccam, image = back.cameras[2], back.images[2]
    point = cams[1].unproject(13.5, 29.5, 3.0)
    uv = ccam.img_from_cam(image.cam_from_world() * point)
    np.testing.assert_allclose(uv, [13.5, 29.5], atol=1e-9)


def test_colmap_models_must_be_undistorted_pinholes(tmp_path):
    rec = pycolmap.Reconstruction()
    models = [("SIMPLE_RADIAL", [50.0, 32, 24, 0.0]), ("OPENCV", [50.0, 51, 32, 24, 0, 0, 0, 0]),
              ("SIMPLE_PINHOLE", [50.0, 32, 24]), ("RADIAL", [50.0, 32, 24, 0.1, 0.0]),
              ("OPENCV_FISHEYE", [50.0, 51, 32, 24, 0, 0, 0, 0])]
    for i, (model, params) in enumerate(models):
        cam = pycolmap.Camera.create_from_model_name(i + 1, model, 50.0, W, H)
        cam.params = params
        rec.add_camera_with_trivial_rig(cam)
        rec.add_image_with_trivial_frame(pycolmap.Image(name=f"c{i}.png", camera_id=i + 1, image_id=i + 1),
                                         pycolmap.Rigid3d(np.eye(4)[:3]))
    good = pycolmap.Reconstruction(rec)
    for image_id in (4, 5):
        good.deregister_frame(image_id)
    with pytest.raises(DataError, match="not registered"):
        cameras_from_reconstruction(good, "somewhere/sparse/0")
    rec.write(str(tmp_path))
    with pytest.raises(DataError) as e:
        cameras_from_reconstruction(read_reconstruction(tmp_path), "somewhere/sparse/0")
    assert "somewhere/sparse/0" in str(e.value) and "RADIAL" in str(e.value) and "undistorted" in str(e.value)
    kept = read_reconstruction(tmp_path)
    for image_id in (4, 5):
        del kept.images[image_id]
    cams = cameras_from_reconstruction(kept, "x")
    assert [(c.fx, c.fy, c.cx, c.cy) for c in cams] == [(50, 50, 32, 24), (50, 51, 32, 24), (50, 50, 32, 24)]


def test_colmap_missing_and_broken_models(tmp_path):
    with pytest.raises(DataError, match="nowhere.*missing"):
        read_reconstruction(tmp_path / "nowhere")
    (tmp_path / "m").mkdir()
    (tmp_path / "m" / "cameras.bin").write_bytes(b"\x00")
    with pytest.raises(DataError, match="not a COLMAP model"):
        read_reconstruction(tmp_path / "m")
    for name in ("images.bin", "points3D.bin"):
        (tmp_path / "m" / name).write_bytes(b"garbage!" * 3)
    with pytest.raises(DataError, match="cannot read the COLMAP model") as e:
        read_reconstruction(tmp_path / "m")
    assert str(tmp_path / "m") in str(e.value)


# -- the reference layout --------------------------------------------------------------------------
@pytest.fixture(scope="module")
def reference(rig, tmp_path_factory):
    cams, frames = rig
    return write_reference(tmp_path_factory.mktemp("reference") / "scene", cams, frames)


def test_reference_layout(reference, rig, tmp_path):
    cams, frames = rig
    assert detect_layout(reference) == "reference"
    data = load_dataset(reference, cache_dir=tmp_path)
    assert isinstance(data, Dataset)
    _assert_same_cameras(data.cameras, cams)
    _assert_frames(data, frames)
    assert data.fps == 30 and data.test_cameras == [0] and data.cameras[0].name == "cam00"
    again = load_dataset(reference, layout="reference", fps=25, num_frames=2, test_camera="cam02", cache_dir=tmp_path)
    assert (again.fps, again.num_frames, again.test_cameras) == (25, 2, [2])
    half = load_dataset(reference, downscale=2, cache_dir=tmp_path)
    assert (half.width, half.height) == (W // 2, H // 2)
    np.testing.assert_allclose(half.cameras[1].K[:2], cams[1].K[:2] / 2)
    want = cv2.resize(frames[1, 2], (W // 2, H // 2), interpolation=cv2.INTER_AREA)
    np.testing.assert_array_equal(half.frame(1, 2), want)


def test_reference_layout_errors(reference, rig, tmp_path):
    cams, frames = rig
    root = tmp_path / "ref"
    shutil.copytree(reference, root, ignore=shutil.ignore_patterns(".stg_cache"))
    cache = dict(cache_dir=tmp_path / "cache")
    png = root / "colmap_1" / "images" / "cam02.png"
    png.unlink()
    _expect("missing", "colmap_1/images/cam02.png", root, **cache)
    _png(png, frames[2, 1][:40])
    _expect("expected 64x48", "colmap_1/images/cam02.png", root, **cache)
    _png(png, frames[2, 1])
    _png(root / "colmap_1" / "images" / "cam07.png", frames[2, 1])
    _expect("not in the COLMAP model", "colmap_1/images/cam07.png", root, **cache)
    (root / "colmap_1" / "images" / "cam07.png").unlink()
    moved = list(cams)
    w2c = cams[3].world_to_camera.copy()
    w2c[0, 3] += 0.01
    moved[3] = Camera(cams[3].fx, cams[3].fy, cams[3].cx, cams[3].cy, W, H, w2c, cams[3].name)
    write_reconstruction(reconstruction_from_cameras(moved), root / "colmap_2" / "sparse" / "0")
    _expect("camera cam03 differs", "colmap_2/sparse/0", root, **cache)
    write_reconstruction(reconstruction_from_cameras(cams), root / "colmap_2" / "sparse" / "0")
    (root / "colmap_0" / "sparse" / "0" / "images.bin").write_bytes(b"broken")
    _expect("cannot read the COLMAP model", "colmap_0/sparse/0", root, layout="reference", **cache)
    shutil.rmtree(root / "colmap_0")
    _expect("missing", "colmap_0", root, layout="reference", **cache)


# -- the rig layout --------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def rig_images(rig, tmp_path_factory):
    cams, frames = rig
    return write_rig(tmp_path_factory.mktemp("rig") / "capture", cams, frames)


def test_rig_layout_from_images(rig_images, rig, tmp_path):
    cams, frames = rig
    assert detect_layout(rig_images) == "rig"
    data = load_dataset(rig_images, cache_dir=tmp_path)
    _assert_same_cameras(data.cameras, cams)
    _assert_frames(data, frames)
    assert data.fps == 30 and data.test_cameras == [0]  # the first camera in name order
    other = load_dataset(rig_images, test_camera="cam03", fps=24, cache_dir=tmp_path)
    assert other.test_cameras == [3] and other.train_cameras == [0, 1, 2] and other.fps == 24
    with pytest.raises(DataError, match="no camera named 'cam09'"):
        load_dataset(rig_images, test_camera="cam09", cache_dir=tmp_path)


def test_rig_layout_camera_named_images_text_model_and_videos(rig, tmp_path):
    cams, frames = rig
    root = write_rig(tmp_path / "a", cams, frames, image_names=[f"{c.name}.jpg" for c in cams], text=True)
    assert (root / "sparse" / "0" / "images.txt").is_file()
    _assert_same_cameras(load_dataset(root).cameras, cams)
    videos = write_rig(tmp_path / "v", cams, frames, videos=True)
    assert detect_layout(videos) == "rig"
    data = load_dataset(videos)
    assert data.fps == 25 and data.num_frames == FRAMES
    _assert_same_cameras(data.cameras, cams)
    for c in range(CAMS):
        for k in range(FRAMES):
            mse = np.mean((data.frame(c, k).astype(float) - frames[c, k]) ** 2)
            assert 10 * np.log10(255**2 / mse) > 28
    # with both images/ and videos/, images win unless from_video
    shutil.copytree(tmp_path / "a" / "images", videos / "images")
    assert load_dataset(videos).fps == 30 and load_dataset(videos, from_video=True).fps == 25


def test_rig_layout_errors(rig_images, rig, tmp_path):
    cams, frames = rig
    root = tmp_path / "rig"
    shutil.copytree(rig_images, root, ignore=shutil.ignore_patterns(".stg_cache"))
    model = root / "sparse" / "0"
    (root / "images" / "cam01" / "00002.png").unlink()
    message = _expect("different frame counts", "cam01: 2 frames", root)
    assert "cam00: 3 frames" in message
    assert load_dataset(root, num_frames=2).num_frames == 2
    _png(root / "images" / "cam01" / "00002.png", frames[1, 2])
    shutil.copytree(root / "images" / "cam01", root / "images" / "cam09")
    _expect("has no image in the COLMAP model", "images/cam09", root)
    shutil.rmtree(root / "images" / "cam09")
    shutil.rmtree(root / "images" / "cam03")
    _expect("missing", "images/cam03", root)
    (root / "images" / "cam03").mkdir()
    _expect("no frames", "images/cam03", root)
    shutil.rmtree(root / "images" / "cam03")
    write_reconstruction(reconstruction_from_cameras(cams[:3] + cams[:1], [f"cam0{i}/00000.png" for i in range(3)]
                                                     + ["cam00/00001.png"]), model)
    _expect("several images of camera cam00", str(model), root)
    write_reconstruction(reconstruction_from_cameras([c.resized(32, 24) for c in cams[:3]],
                                                     [f"cam0{i}/00000.png" for i in range(3)]), model)
    _expect("calibrated for 32x24", "images/cam00", root)
    shutil.rmtree(model)
    _expect("missing", "sparse/0", root, layout="rig")
    write_reconstruction(reconstruction_from_cameras(cams[:3]), root / "sparse")  # model files directly in sparse/
    assert [c.name for c in load_dataset(root).cameras] == ["cam00", "cam01", "cam02"]
    for d in (root / "images").iterdir():
        shutil.rmtree(d)
    _png(root / "images" / "00000.png", frames[0, 0])
    _expect("put each camera's frames in images/<camera>/", "00000.png lies directly in images/", root)


# -- Technicolor -----------------------------------------------------------------------------------
def test_technicolor_layout(scene, rig, tmp_path):
    cams11 = scene.cameras(11, W, H)
    frames = np.stack([[np.rint(scene.render(c, k / FPS) * 255).astype(np.uint8) for k in range(2)] for c in cams11])
    root = write_technicolor(tmp_path / "Birthday", cams11, frames)
    assert detect_layout(root) == "technicolor"
    data = load_dataset(root)
    _assert_same_cameras(data.cameras, cams11, rtol=1e-12)
    _assert_frames(data, frames)
    assert data.cameras[10].name == "cam10" and data.test_cameras == [10] and data.fps == 30


def test_technicolor_layout_errors(rig, tmp_path):
    cams, frames = rig
    root = write_technicolor(tmp_path / "Train", cams, frames, scene="Train", first=0)
    data = load_dataset(root)
    assert data.test_cameras == [0] and data.num_frames == FRAMES  # no cam10: the first camera
    params = root / "cameras_parameters.txt"
    good = params.read_text()
    (root / "Train_undist_00001_02.png").unlink()
    _expect("missing", "Train_undist_00001_02.png", root)
    _png(root / "Train_undist_00001_02.png", frames[2, 1])
    _png(root / "Train_undist_00000_04.png", frames[2, 1])
    _expect("has no line in", "Train_undist_00000_04.png", root)
    (root / "Train_undist_00000_04.png").unlink()
    lines = good.splitlines()
    params.write_text("\n".join(lines + [lines[-1]]) + "\n")
    _expect("has no images Train_undist_*_04.png", "cameras_parameters.txt", root)
    params.write_text("\n".join(lines[:2] + [lines[2] + " 0 0"] + lines[3:]) + "\n")
    _expect("distorted", "cameras_parameters.txt: line 3", root)
    params.write_text("\n".join(lines[:2] + [lines[2] + " 1"] + lines[3:]) + "\n")
    _expect("has 13 numbers", "cameras_parameters.txt: line 3", root)
    params.unlink()
    _expect("missing", "cameras_parameters.txt", root, layout="technicolor")


# -- detection, N3V through load_dataset, the command lines ----------------------------------------
def test_detection_and_n3v_dispatch(scene, tmp_path):
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(DataError) as e:
        detect_layout(empty)
    for word in ("empty", "poses_bounds.npy", "cameras_parameters.txt", "colmap_0", "sparse/0"):
        assert word in str(e.value)
    with pytest.raises(DataError, match="no such directory"):
        load_dataset(tmp_path / "nowhere")
    with pytest.raises(ValueError, match="unknown layout"):
        load_dataset(empty, layout="llff")
    n3v = tmp_path / "n3v"
    cams = write_n3v(n3v, scene, num_cameras=3, num_frames=2, fps=FPS, width=W, height=H)
    write_reference(n3v, cams, np.zeros((3, 2, H, W, 3), np.uint8))  # preprocessed beside the raw data
    assert detect_layout(n3v) == "n3v"
    data, direct = load_dataset(n3v), load_n3v(n3v, prefer_png=True)
    assert data.test_cameras == direct.test_cameras == [0]
    np.testing.assert_array_equal(data.frame(2, 1), direct.frame(2, 1))
    assert load_dataset(n3v, test_camera="cam02").test_cameras == [2]
    assert load_dataset(n3v, layout="reference").frame(1, 1).max() == 0


def test_cli_layout_options(rig_images, tmp_path, capsys):
    from stg_train.cli import eval as eval_cli
    from stg_train.cli import train as train_cli

    args = train_cli.build_parser().parse_args([str(rig_images), "--out", "x", "--layout", "rig", "--fps", "24",
                                                "--test-camera", "cam01"])
    assert (args.layout, args.fps, args.test_camera) == ("rig", 24.0, "cam01")
    assert eval_cli.build_parser().parse_args(["m.stg", "d", "--layout", "reference"]).layout == "reference"
    data = load_dataset(rig_images, layout="auto", fps=24, test_camera="cam01", show_progress=False)
    assert data.fps == 24 and data.test_cameras == [1]
    assert train_cli.main([str(rig_images), "--out", str(tmp_path / "out"), "--layout", "technicolor"]) == 2
    err = capsys.readouterr().err
    assert str(rig_images) in err and "_undist_" in err and "Traceback" not in err
    assert not (tmp_path / "out").exists()
