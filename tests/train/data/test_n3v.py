"""The Neural 3D Video reader (stg_train.data) on folders written by stg_train.synthetic.write_n3v."""
import os
import shutil

import cv2
import numpy as np
import pytest

from stg_train.data import DataError, Dataset, load_n3v
from stg_train.synthetic import OBJECT_NAMES, SyntheticScene, write_n3v

CAMS, FRAMES, FPS, W, H = 4, 5, 30, 64, 48


@pytest.fixture(scope="module")
def scene():
    return SyntheticScene(seed=1, duration=FRAMES / FPS)


@pytest.fixture(scope="module")
def n3v(tmp_path_factory, scene):
    out = tmp_path_factory.mktemp("n3v") / "scene"
    cams = write_n3v(out, scene, num_cameras=CAMS, num_frames=FRAMES, fps=FPS, width=W, height=H)
    return out, cams


def _copy(n3v, tmp_path, png=False):
    """A private copy of the written folder (videos, poses and, when png, the frames)."""
    src, _ = n3v
    dst = tmp_path / "copy"
    ignore = shutil.ignore_patterns(".stg_cache", *(() if png else ("frames",)))
    shutil.copytree(src, dst, ignore=ignore)
    return dst


def _write_video(path, frames, size=(W, H)):
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"mp4v"), FPS, size)
    for k in range(frames):
        writer.write(np.full((size[1], size[0], 3), 40 * k % 255, np.uint8))
    writer.release()


def _psnr(a, b):
    mse = np.mean((a.astype(np.float64) - b.astype(np.float64)) ** 2)
    return 10 * np.log10(255.0**2 / mse)


def test_cameras_round_trip(n3v, tmp_path):
    path, cams = n3v
    data = load_n3v(path, cache_dir=tmp_path)
    assert isinstance(data, Dataset)
    assert [c.name for c in data.cameras] == [c.name for c in cams]
    for got, want in zip(data.cameras, cams):
        np.testing.assert_allclose(got.world_to_camera, want.world_to_camera, atol=1e-6)
        np.testing.assert_allclose([got.fx, got.fy, got.cx, got.cy], [want.fx, want.fy, want.cx, want.cy], atol=1e-6)
        assert (got.width, got.height) == (W, H)
    assert (data.num_cameras, data.num_frames, data.fps) == (CAMS, FRAMES, FPS)
    np.testing.assert_allclose(data.frame_times, np.arange(FRAMES) / FPS)
    assert data.test_cameras == [0] and data.cameras[0].name == "cam00"
    assert data.train_cameras == [1, 2, 3]
    assert data.bounds.shape == (CAMS, 2) and np.all(0 < data.bounds[:, 0]) and np.all(data.bounds[:, 0] < data.bounds[:, 1])


def test_views_with_other_cameras_and_corrected_pictures_share_the_frames(n3v, tmp_path):
    from dataclasses import replace

    data = load_n3v(n3v[0], cache_dir=tmp_path)
    moved = list(data.cameras)
    moved[0] = replace(moved[0], world_to_camera=np.eye(4))
    view = data.with_cameras(moved)
    assert view.cameras[0] is moved[0] and data.cameras[0] is not moved[0] and view.frames is data.frames
    with pytest.raises(ValueError, match="with_cameras: 3 cameras for a dataset of 4"):
        data.with_cameras(moved[:3])
    with pytest.raises(ValueError, match="at 64x48"):
        data.with_cameras([data.cameras[0].resized(16, 12)] + moved[1:])
    halves = data.corrected({1: np.full(3, 0.5, np.float32)})
    np.testing.assert_allclose(halves.image(1, 2), np.clip(data.image(1, 2) * 2, 0, 1))
    np.testing.assert_array_equal(halves.frame(1, 2), data.frame(1, 2))
    np.testing.assert_array_equal(halves.image(2, 2), data.image(2, 2))
    np.testing.assert_allclose(halves.frame_range(1, 2).image(1, 1), halves.image(1, 2))  # views keep it
    assert data.brightness is None


def test_png_frames_equal_the_renders_and_mp4_frames_are_close(n3v, scene, tmp_path):
    path, cams = n3v
    png = load_n3v(path, prefer_png=True, cache_dir=tmp_path / "png")
    mp4 = load_n3v(path, cache_dir=tmp_path / "mp4")
    assert isinstance(png.frames, np.memmap) and isinstance(mp4.frames, np.memmap)
    for ci in range(CAMS):
        for k in range(FRAMES):
            frame = png.frame(ci, k)
            assert frame.shape == (H, W, 3) and frame.dtype == np.uint8
            want = np.rint(scene.render(cams[ci], k / FPS) * 255).astype(np.uint8)
            np.testing.assert_array_equal(frame, want)
            assert _psnr(mp4.frame(ci, k), frame) > 30
    assert png.image(1, 2).dtype == np.float32 and png.image(1, 2).max() <= 1


def test_projection_lands_where_the_ray_tracer_sees_the_point(n3v, scene, tmp_path):
    path, cams = n3v
    data = load_n3v(path, cache_dir=tmp_path)
    mover = OBJECT_NAMES.index("moving_sphere")
    for ci, cam in enumerate(data.cameras):
        for k in (0, FRAMES - 1):
            t = data.frame_times[k]
            # the moving sphere's centre projects into the sphere's pixels
            x = cam.R @ scene.moving_sphere_center(t) + cam.t
            u, v = cam.fx * x[0] / x[2] + cam.cx, cam.fy * x[1] / x[2] + cam.cy
            assert scene.object_ids(cams[ci], t)[int(v), int(u)] == mover
        # a surface point seen through pixel (col 13, row 29) by the ray tracer projects back onto that pixel centre
        _, depth = scene.render(cams[ci], 0.0, return_depth=True)
        gen = cams[ci]
        p = np.array([(13.5 - gen.cx) / gen.fx, (29.5 - gen.cy) / gen.fy, 1.0]) * depth[29, 13]
        X = gen.R.T @ (p - gen.t)
        x = cam.R @ X + cam.t
        np.testing.assert_allclose([cam.fx * x[0] / x[2] + cam.cx, cam.fy * x[1] / x[2] + cam.cy], [13.5, 29.5], atol=1e-4)
        assert x[2] == pytest.approx(depth[29, 13], rel=1e-6)


def test_downscale_halves_sizes_and_intrinsics(n3v, tmp_path):
    path, _ = n3v
    full = load_n3v(path, prefer_png=True, cache_dir=tmp_path)
    half = load_n3v(path, prefer_png=True, downscale=2, cache_dir=tmp_path)
    assert (half.width, half.height) == (W // 2, H // 2)
    for a, b in zip(full.cameras, half.cameras):
        np.testing.assert_allclose([b.fx, b.fy, b.cx, b.cy], np.array([a.fx, a.fy, a.cx, a.cy]) / 2)
        assert (b.width, b.height) == (W // 2, H // 2)
        np.testing.assert_array_equal(a.world_to_camera, b.world_to_camera)
    want = cv2.resize(full.frame(2, 3), (W // 2, H // 2), interpolation=cv2.INTER_AREA)
    np.testing.assert_array_equal(half.frame(2, 3), want)


def test_cache_is_reused_and_rebuilt_when_data_change(n3v, tmp_path):
    path = _copy(n3v, tmp_path)
    first = load_n3v(path)
    cache = path / ".stg_cache" / "n3v_video_x1_f5" / "frames_uint8.npy"
    assert cache.is_file()
    stamp = cache.stat().st_mtime_ns
    again = load_n3v(path)
    assert cache.stat().st_mtime_ns == stamp
    np.testing.assert_array_equal(again.frame(3, 4), first.frame(3, 4))
    _write_video(path / "cam03.mp4", FRAMES)  # new content, same layout
    changed = load_n3v(path)
    assert not np.array_equal(changed.frame(3, 4), first.frame(3, 4))
    short = load_n3v(path, num_frames=2)
    assert short.num_frames == 2
    with pytest.raises(IndexError):
        short.frame(0, 2)


# -- bad data ------------------------------------------------------------------------------------
def _expect(path, fragment, name, **kwargs):
    with pytest.raises(DataError) as e:
        load_n3v(path, **kwargs)
    assert name in str(e.value), str(e.value)
    assert fragment in str(e.value), str(e.value)
    return str(e.value)


def test_missing_directory_and_no_videos(tmp_path):
    _expect(tmp_path / "nowhere", "no such directory", "nowhere")
    (tmp_path / "empty").mkdir()
    _expect(tmp_path / "empty", "no camXX.mp4", "empty")


def test_bad_poses_bounds(n3v, tmp_path):
    path = _copy(n3v, tmp_path)
    good = np.load(path / "poses_bounds.npy")
    (path / "poses_bounds.npy").unlink()
    _expect(path, "missing", "poses_bounds.npy")
    (path / "poses_bounds.npy").write_bytes(b"this is not a numpy file")
    _expect(path, "cannot be read", "poses_bounds.npy")
    np.save(path / "poses_bounds.npy", good[:, :15])
    _expect(path, "(num_cameras, 17)", "poses_bounds.npy")
    np.save(path / "poses_bounds.npy", good[:3])
    _expect(path, "has 3 cameras but there are 4", "poses_bounds.npy")
    bad = good.copy()
    bad[1, 0] = np.nan
    np.save(path / "poses_bounds.npy", bad)
    _expect(path, "non-finite", "poses_bounds.npy")
    for near, far in ((-1.0, 5.0), (5.0, 2.0), (0.0, 1.0)):
        bad = good.copy()
        bad[2, 15:17] = near, far
        np.save(path / "poses_bounds.npy", bad)
        _expect(path, "row 2 has near/far depth bounds", "poses_bounds.npy")
    (path / "poses_bounds.npy").write_text("1 2 3\n")
    _expect(path, "not a numpy .npy file", "poses_bounds.npy")


def test_bad_videos(n3v, tmp_path):
    path = _copy(n3v, tmp_path)
    (path / "cam02.mp4").write_bytes(b"garbage" * 100)
    _expect(path, "cannot be opened", "cam02.mp4", cache_dir=tmp_path / "c")
    _write_video(path / "cam02.mp4", 0)  # no frames at all
    _expect(path, "cam02.mp4", "cam02.mp4", cache_dir=tmp_path / "c")
    _write_video(path / "cam02.mp4", 3)
    message = _expect(path, "different frame counts", "cam02.mp4: 3 frames", cache_dir=tmp_path / "c")
    assert "cam00.mp4: 5 frames" in message
    _expect(path, "fewer than the 4 asked for", "cam02.mp4", num_frames=4, cache_dir=tmp_path / "c")
    _write_video(path / "cam02.mp4", FRAMES, size=(32, 24))
    _expect(path, "different frame sizes", "cam02.mp4: 32x24", cache_dir=tmp_path / "c")


def test_bad_png_layout(n3v, tmp_path):
    path = _copy(n3v, tmp_path, png=True)
    shutil.rmtree(path / "frames" / "cam01")
    _expect(path, "missing", "cam01", prefer_png=True, cache_dir=tmp_path / "c")
    (path / "frames" / "cam01").mkdir()
    _expect(path, "no PNG frames", "cam01", prefer_png=True, cache_dir=tmp_path / "c")
    shutil.copytree(path / "frames" / "cam00", path / "frames" / "cam01", dirs_exist_ok=True)
    (path / "frames" / "cam01" / "000004.png").unlink()
    _expect(path, "different frame counts", "cam01: 4 frames", prefer_png=True, cache_dir=tmp_path / "c")
    (path / "frames" / "cam01" / "000004.png").write_bytes(b"not a png")
    _expect(path, "cannot be read as an image", "000004.png", prefer_png=True, cache_dir=tmp_path / "c")
    frame = path / "frames" / "cam01" / "000004.png"
    if os.geteuid() != 0:  # (root reads any file)
        frame.chmod(0)
        _expect(path, "cannot be read (Permission denied)", "000004.png", prefer_png=True, cache_dir=tmp_path / "c")
    frame.unlink()
    frame.mkdir()  # a frame that cannot be opened at all: the reason is in the message
    _expect(path, "cannot be read (Is a directory)", "000004.png", prefer_png=True, cache_dir=tmp_path / "c")
    frame.rmdir()
    frame.write_bytes(b"not a png")
    # without prefer_png the videos are read and the broken PNGs do not matter
    assert load_n3v(path, cache_dir=tmp_path / "c").num_frames == FRAMES
