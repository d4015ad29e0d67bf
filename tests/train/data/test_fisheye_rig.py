"""Fisheye cameras in the data side: COLMAP's OPENCV_FISHEYE read and written (stg_train.data.colmap), the
rig layout with a fisheye model, SfM with fisheye cameras, and the visibility tests the initialisation
uses (stg_train.data.visibility, coverage, volume)."""
import cv2
import numpy as np
import pycolmap
import pytest

from stg_runtime.camera import Camera
from stg_train.data import DataError, Dataset, load_dataset
from stg_train.data.bounds import bounds_from_points, uniform_bounds
from stg_train.data.colmap import (cameras_from_reconstruction, read_reconstruction, reconstruction_from_cameras,
                                   write_reconstruction)
from stg_train.data.coverage import covered_pixels
from stg_train.data.sfm import sfm_points
from stg_train.data.visibility import MAX_SAMPLE_ANGLE_DEG, samplable_pixels, sees
from stg_train.data.volume import sample_view_volume
from stg_train.synthetic import SyntheticScene

W, H = 48, 36
K = (0.03, -0.01, 0.002, -0.0003)


def _fisheyes(count=3, hfov=150.0):
    return SyntheticScene().dome_cameras(count, W, H, hfov, "fisheye", K)


def test_opencv_fisheye_round_trip(tmp_path):
    cams = _fisheyes() + [SyntheticScene().dome_camera(5.0, 0.0, W, H, 90.0, "pinhole", name="pin")]
    rec = reconstruction_from_cameras(cams)
    assert [rec.cameras[i + 1].model_name for i in range(4)] == ["OPENCV_FISHEYE"] * 3 + ["PINHOLE"]
    write_reconstruction(rec, tmp_path / "m", text=True)
    back = cameras_from_reconstruction(read_reconstruction(tmp_path / "m"), "m")
    assert [c.name for c in back] == sorted(c.name for c in cams)
    for cam in back:
        want = next(c for c in cams if c.name == cam.name)
        assert (cam.model, cam.distortion) == (want.model, want.distortion)
        assert (cam.fx, cam.fy, cam.cx, cam.cy) == pytest.approx((want.fx, want.fy, want.cx, want.cy), abs=1e-9)
        np.testing.assert_allclose(cam.world_to_camera, want.world_to_camera, atol=1e-9)
    # COLMAP projects as Camera.project does: same numbers, same pixel-centre convention
    ccam = rec.cameras[1]
    points = np.array([[0.3, -0.2, 1.0], [-1.0, 0.4, 0.8], [0.05, 0.02, 2.0]])
    ours, _ = Camera(*ccam.params[:4], W, H, np.eye(4), "", "fisheye", tuple(ccam.params[4:])).project(points)
    np.testing.assert_allclose(ccam.img_from_cam(points), ours, atol=1e-9)


@pytest.mark.parametrize("model, params", [("FOV", [30.0, 31, 24, 18, 0.1]),
                                           ("RADIAL_FISHEYE", [30.0, 24, 18, 0.1, 0.0]),
                                           ("THIN_PRISM_FISHEYE", [30.0, 31, 24, 18] + [0.0] * 8)])
def test_unrepresentable_models_are_refused(model, params):
    rec = pycolmap.Reconstruction()
    cam = pycolmap.Camera.create_from_model_name(1, model, 30.0, W, H)
    cam.params = params
    rec.add_camera_with_trivial_rig(cam)
    rec.add_image_with_trivial_frame(pycolmap.Image(name="c.png", camera_id=1, image_id=1), pycolmap.Rigid3d(np.eye(4)[:3]))
    with pytest.raises(DataError) as e:
        cameras_from_reconstruction(rec, "rig/sparse/0")
    message = str(e.value)
    assert "rig/sparse/0" in message and model in message and "OPENCV_FISHEYE" in message, message


def test_rig_layout_with_fisheye_cameras(tmp_path):
    scene = SyntheticScene(seed=1, duration=0.1)
    cams = _fisheyes()
    root = tmp_path / "rig"
    for cam in cams:
        for k in range(2):
            path = root / "images" / cam.name / f"{k:05d}.png"
            path.parent.mkdir(parents=True, exist_ok=True)
            rgb = np.rint(scene.render(cam, k / 30) * 255).astype(np.uint8)
            assert cv2.imwrite(str(path), np.ascontiguousarray(rgb[..., ::-1]))
    write_reconstruction(reconstruction_from_cameras(cams, [f"{c.name}/00000.png" for c in cams]), root / "sparse" / "0")
    data = load_dataset(root)
    assert [c.name for c in data.cameras] == [c.name for c in cams] and data.test_cameras == [0]
    for got, want in zip(data.cameras, cams):
        assert got.model == "fisheye" and got.distortion == pytest.approx(want.distortion)
        np.testing.assert_allclose(got.world_to_camera, want.world_to_camera, atol=1e-9)
    half = load_dataset(root, downscale=2)
    assert half.cameras[1].model == "fisheye" and half.cameras[1].fx == pytest.approx(cams[1].fx / 2)
    assert half.cameras[1].distortion == data.cameras[1].distortion


def test_sfm_with_fisheye_cameras(tmp_path):
    """SfM on a fisheye dome (guided verification with the known poses): enough points, lying where the
    cameras see the scene."""
    scene = SyntheticScene(seed=0)
    cams = SyntheticScene().dome_cameras(6, 160, 120, 120.0)
    frames = np.stack([[np.rint(scene.render(c, 0.0) * 255).astype(np.uint8)] for c in cams])
    data = Dataset(cams, frames, 30.0, test_cameras=[0])
    xyz, rgb, _ = sfm_points(data, cache_dir=tmp_path, threads=1)
    assert len(xyz) >= 100
    xyz = xyz.astype(np.float64)
    seen = np.stack([sees(c, xyz)[2] for c in cams[1:]])
    assert seen.sum(axis=0).min() >= 2  # every point triangulated from at least two of the training views
    bounds = bounds_from_points(cams, xyz)
    assert np.all(bounds[:, 0] > 0.3) and np.all(bounds[:, 1] < 20)  # inside the room (depths 0.6-8)


def test_visibility_and_sampling_beyond_90_degrees():
    wide = Camera.look_at([0, 0, 0], [0, 0, 1], [0, -1, 0], 220.0 * H / W, W, H, "wide", "fisheye")
    assert wide.max_angle == pytest.approx(np.pi)
    behind = np.array([[2.0, 0.0, -0.5], [0.0, 0.0, -1.0], [0.1, 0.1, 1.0]])  # 104, 180 and 8 degrees off axis
    _, z, visible = sees(wide, behind)
    assert visible.tolist() == [True, False, True] and z[0] < 0
    assert covered_pixels(wide, behind[:1], 0).sum() == 1  # a point behind the camera plane, seen by the lens
    pinhole = Camera.look_at([0, 0, 0], [0, 0, 1], [0, -1, 0], 90.0, W, H, "pin")
    assert sees(pinhole, behind)[2].tolist() == [False, False, True]
    mask = samplable_pixels(wide)
    angles = np.degrees(np.arccos(np.clip(wide.ray_directions() @ wide.R[2], -1, 1)))
    np.testing.assert_array_equal(mask, angles <= MAX_SAMPLE_ANGLE_DEG + 1e-9)
    assert 0.2 < mask.mean() < 0.9 and samplable_pixels(pinhole).all()

    # the view-volume sampler on a rig of such lenses: every point finite, at a ray within the limit
    cams = [Camera.look_at([x, 0, 0], [x, 0, 1], [0, -1, 0], 220.0 * H / W, W, H, f"c{i}", "fisheye")
            for i, x in enumerate((-0.2, 0.0, 0.2, 0.4))]
    frames = np.random.default_rng(0).integers(0, 256, (4, 2, H, W, 3), dtype=np.uint8)
    data = Dataset(cams, frames, 30.0, test_cameras=[0], bounds=uniform_bounds(4, 1.0, 3.0))
    xyz, rgb, t = sample_view_volume(data, 500, np.random.default_rng(1), depth_candidates=4)
    assert np.all(np.isfinite(xyz)) and xyz.shape == (500, 3)
    seen = np.stack([sees(c, xyz)[2] for c in cams[1:]]).sum(axis=0)
    assert (seen >= 2).mean() > 0.95
    for cam in cams[1:]:
        _, z, _ = sees(cam, xyz)
        assert np.all(z[np.isfinite(z)] < 3.0 / np.cos(np.radians(MAX_SAMPLE_ANGLE_DEG)) + 1)
