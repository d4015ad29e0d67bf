"""Depth bounds for every layout (stg_train.data.bounds), SfM coverage (stg_train.data.coverage), the
combined initialisation (stg_train.data.points) and --near/--far (stg_train.cli)."""
import cv2
import numpy as np
import pycolmap
import pytest

import stg_train  # noqa: F401  (sets the OpenMP policy before torch is imported)
from stg_runtime.camera import Camera
from stg_train.data import Dataset, load_dataset
from stg_train.data import points as points_module
from stg_train.data.bounds import MARGIN, bounds_from_points, describe, uniform_bounds, visible_depths
from stg_train.data.colmap import reconstruction_from_cameras, write_reconstruction
from stg_train.data.coverage import coverage_masks, covered_pixels
from stg_train.data.points import default_method, initial_points
from stg_train.synthetic import SyntheticScene

W, H, CAMS, FRAMES = 64, 48, 6, 3


def rig_cameras():
    return SyntheticScene().cameras(CAMS, W, H)


def points_in_view(camera, count, near, far, rng, columns=(0, W)):
    """`count` points on the rays of random pixels of `camera` (in the given column range), at depths
    uniform in [near, far]."""
    u = rng.uniform(*columns, count)
    v = rng.uniform(0, H, count)
    return camera.unproject(u, v, rng.uniform(near, far, count))


def fake_dataset(bounds=None, seed=0):
    cams = rig_cameras()
    frames = np.random.default_rng(seed).integers(0, 256, (CAMS, FRAMES, H, W, 3), dtype=np.uint8)
    return Dataset(cams, frames, 30.0, test_cameras=[0], bounds=bounds)


# -- bounds -----------------------------------------------------------------------------------------
def test_bounds_from_known_points():
    cams = rig_cameras()
    rng = np.random.default_rng(0)
    xyz = points_in_view(cams[0], 4000, 3.0, 7.0, rng)
    bounds = bounds_from_points(cams, xyz)
    assert bounds.shape == (CAMS, 2)
    near, far = bounds[0]  # cam00's depths are uniform in [3, 7]: percentiles 1 and 99 are 3.04 and 6.96
    assert near == pytest.approx(3.04 / MARGIN, rel=0.02) and far == pytest.approx(6.96 * MARGIN, rel=0.02)
    for ci, cam in enumerate(cams):  # every camera's bounds enclose what it sees, with the margin
        z = visible_depths(cam, xyz)
        assert bounds[ci, 0] < np.percentile(z, 1) and bounds[ci, 1] > np.percentile(z, 99)
    outlier = np.concatenate([xyz, cams[0].unproject(np.array([32.0]), np.array([24.0]), np.array([500.0]))])
    assert bounds_from_points(cams, outlier)[0, 1] < 10  # one stray point does not move the far bound


def test_cameras_without_points_get_the_median_bounds():
    cams = rig_cameras()
    away = Camera(cams[1].fx, cams[1].fy, cams[1].cx, cams[1].cy, W, H, np.diag([1.0, 1.0, -1.0, 1.0]) @
                  cams[1].world_to_camera, "away")  # looks backwards: sees none of the points
    xyz = points_in_view(cams[0], 2000, 3.0, 7.0, np.random.default_rng(1))
    bounds = bounds_from_points(cams[:3] + [away], xyz)
    np.testing.assert_allclose(bounds[3], np.median(bounds[:3], axis=0))
    assert bounds_from_points([away], xyz) is None
    assert bounds_from_points(cams, xyz[:5]) is None  # too few points for any camera


def test_uniform_bounds_and_description():
    np.testing.assert_array_equal(uniform_bounds(2, 0.5, 9.0), [[0.5, 9.0], [0.5, 9.0]])
    for near, far in ((0.0, 1.0), (2.0, 1.0), (1.0, np.inf), (-1.0, 3.0)):
        with pytest.raises(ValueError, match="0 < near < far"):
            uniform_bounds(2, near, far)
    assert describe(uniform_bounds(3, 0.5, 9.0), "user") == "depth bounds from --near/--far: near 0.5, far 9"


def test_rig_bounds_from_the_colmap_points_or_the_user(tmp_path):
    cams = rig_cameras()
    frames = np.random.default_rng(0).integers(0, 256, (CAMS, 1, H, W, 3), dtype=np.uint8)
    root = tmp_path / "rig"
    for c, cam in enumerate(cams):
        (root / "images" / cam.name).mkdir(parents=True)
        assert cv2.imwrite(str(root / "images" / cam.name / "0000.png"), frames[c, 0])
    rec = reconstruction_from_cameras(cams)
    write_reconstruction(rec, root / "sparse" / "0")
    plain = load_dataset(root, cache_dir=tmp_path / "cache", show_progress=False)
    assert plain.bounds is None and default_method(plain) == "volume"

    xyz = points_in_view(cams[0], 500, 2.0, 6.0, np.random.default_rng(2))
    for p in xyz:
        rec.add_point3D(p, pycolmap.Track(), np.array([200, 100, 50], np.uint8))
    write_reconstruction(rec, root / "sparse" / "0")
    data = load_dataset(root, cache_dir=tmp_path / "cache", show_progress=False)
    assert data.bounds_source == "colmap"
    np.testing.assert_allclose(data.bounds, bounds_from_points(data.cameras, xyz))

    user = load_dataset(root, cache_dir=tmp_path / "cache", depth_range=(0.5, 20.0), show_progress=False)
    assert user.bounds_source == "user"
    np.testing.assert_array_equal(user.bounds, np.tile([0.5, 20.0], (CAMS, 1)))
    with pytest.raises(ValueError, match="0 < near < far"):
        load_dataset(root, cache_dir=tmp_path / "cache", depth_range=(3.0, 2.0))


# -- coverage ---------------------------------------------------------------------------------------
def test_covered_pixels_of_a_constructed_case():
    cam = rig_cameras()[0]
    centres = np.array([[10.5, 20.5], [40.5, 5.5]])
    xyz = cam.unproject(centres[:, 0], centres[:, 1], np.array([4.0, 5.0]))
    exact = covered_pixels(cam, xyz, radius=0)
    assert exact.sum() == 2 and exact[20, 10] and exact[5, 40]
    disc = covered_pixels(cam, xyz, radius=3)
    rows, cols = np.mgrid[0:H, 0:W]
    want = ((cols - 10) ** 2 + (rows - 20) ** 2 <= 9) | ((cols - 40) ** 2 + (rows - 5) ** 2 <= 9)
    np.testing.assert_array_equal(disc, want)
    behind = cam.unproject(np.array([10.5]), np.array([20.5]), np.array([-4.0]))
    assert not covered_pixels(cam, behind, radius=3).any()


def _left_half_sfm(dataset, count=3000, seed=5):
    """SfM points filling the left half of cam01's view, at depths 4-6 (what SIFT finds on a textured
    wall beside a smooth one)."""
    rng = np.random.default_rng(seed)
    xyz = points_in_view(dataset.cameras[1], count, 4.0, 6.0, rng, columns=(0, W / 2))
    return xyz.astype(np.float32), np.full((count, 3), 0.5, np.float32), np.zeros(count, np.float32)


def test_combined_fills_the_holes_of_the_sfm_points(monkeypatch):
    ds = fake_dataset()
    sfm = _left_half_sfm(ds)
    monkeypatch.setattr(points_module, "sfm_points", lambda *a, **k: sfm)
    init = initial_points(ds, "combined", 8000, np.random.default_rng(0))
    assert init.method == "combined" and init.bounds_source == "sfm"
    train = [ds.cameras[i] for i in ds.train_cameras]
    covered = coverage_masks(train, sfm[0])
    np.testing.assert_allclose(init.coverage, covered.reshape(len(train), -1).mean(1))
    assert 0.3 < init.coverage.mean() < 0.7  # about the left half
    assert init.sfm_points == 3000 and init.volume_points == 5000 == len(init.xyz) - 3000
    np.testing.assert_array_equal(init.xyz[:3000], sfm[0].astype(np.float64))
    hole = init.xyz[3000:]
    in_a_hole = np.zeros(len(hole), bool)  # each sample comes from an uncovered pixel of some training camera
    for cam, mask in zip(train, covered):
        uv, z = cam.project(hole)
        u, v = np.floor(uv[:, 0]).astype(int), np.floor(uv[:, 1]).astype(int)
        ok = (z > 0) & (u >= 0) & (u < W) & (v >= 0) & (v < H)
        in_a_hole[ok] |= ~mask[v[ok], u[ok]]
    assert in_a_hole.all()
    assert np.all(init.bounds[:, 0] > 2.5) and np.all(init.bounds[:, 1] < 9.0)
    text = init.describe()
    assert "3000 SfM +" in text and "view-volume samples in the holes" in text and "depth bounds from the SfM" in text
    assert init.summary()["method"] == "combined"


def test_combined_keeps_room_for_the_holes_and_falls_back(monkeypatch):
    ds = fake_dataset()
    sfm = _left_half_sfm(ds)
    monkeypatch.setattr(points_module, "sfm_points", lambda *a, **k: sfm)
    init = initial_points(ds, "combined", 1000, np.random.default_rng(0))  # room for the holes' samples
    assert init.sfm_points + init.volume_points == 1000 and init.volume_points > 300
    assert init.sfm_points == round(1000 * coverage_masks([ds.cameras[i] for i in ds.train_cameras],
                                                          sfm[0]).mean())
    few = tuple(a[:50] for a in sfm)
    monkeypatch.setattr(points_module, "sfm_points", lambda *a, **k: few)
    with pytest.raises(points_module.DataError, match="no near/far depth bounds.*--near and --far"):
        initial_points(ds, "combined", 500, np.random.default_rng(0))
    with pytest.raises(points_module.DataError, match="needs near/far depth bounds.*--near and --far"):
        initial_points(ds, "volume", 500, np.random.default_rng(0))
    user = ds.with_bounds(uniform_bounds(CAMS, 1.0, 9.0), "user")
    with pytest.warns(UserWarning, match="found only 50 points"):
        init = initial_points(user, "combined", 500, np.random.default_rng(0))
    assert init.method == "volume" and init.volume_points == 500 and init.bounds_source == "user"


def test_trainer_records_the_sfm_bounds_and_resume_restores_them(monkeypatch, tmp_path):
    from stg_train.trainer import Trainer, TrainConfig

    ds = fake_dataset()
    sfm = _left_half_sfm(ds)
    monkeypatch.setattr(points_module, "sfm_points", lambda *a, **k: sfm)
    trainer = Trainer(ds, TrainConfig(iterations=1, num_points=800, model="lite", depth_candidates=0), tmp_path)
    assert trainer.config.init == "volume" and ds.bounds is None  # the caller's dataset is left as it was
    assert trainer.dataset.bounds_source == "sfm" and trainer.initial.volume_points == 800
    np.testing.assert_array_equal(trainer.dataset.bounds, trainer.initial.bounds)
    trainer.train(progress=False)
    resumed = Trainer.resume(ds, tmp_path / "checkpoint.pt")
    np.testing.assert_array_equal(resumed.dataset.bounds, trainer.dataset.bounds)
    assert resumed.dataset.bounds_source == "sfm" and resumed.initial is None


# -- the command line -------------------------------------------------------------------------------
@pytest.mark.parametrize("argv, message", [
    (["--near", "2"], "--near needs --far"),
    (["--far", "9"], "--far needs --near"),
    (["--near", "5", "--far", "2"], "--far 2 must be larger than --near 5"),
    (["--near", "0", "--far", "2"], "must be positive"),
    (["--near", "-1", "--far", "2"], "must be positive"),
    (["--near", "x", "--far", "2"], "argument --near: must be a number"),
])
def test_cli_rejects_bad_near_far(tmp_path, capsys, argv, message):
    from stg_train.cli import train as train_cli

    with pytest.raises(SystemExit) as e:
        train_cli.main([str(tmp_path), "--out", str(tmp_path / "out"), *argv])
    assert e.value.code == 2
    err = capsys.readouterr().err
    assert message in err and "Traceback" not in err
    assert not (tmp_path / "out").exists()


def test_cli_near_far_reach_load_dataset():
    from stg_train.cli import train as train_cli
    from stg_train.cli.common import dataset_options

    args = train_cli.build_parser().parse_args(["data", "--out", "o", "--near", "0.5", "--far", "12"])
    assert dataset_options(args)["depth_range"] == (0.5, 12.0) and args.init == "auto"
    args = train_cli.build_parser().parse_args(["data", "--out", "o", "--init", "combined"])
    assert "depth_range" not in dataset_options(args) and args.init == "combined"
