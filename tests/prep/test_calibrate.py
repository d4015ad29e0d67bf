"""Calibration: the synthetic 12-camera rig, its poses thrown away, is calibrated back (every camera
registered; after one similarity to the truth, rotations within 0.1 degrees and positions within 0.5 %
of the rig's size), and the written model is what stg_train.data.load_dataset reads; a camera that does
not register is an error naming it with its match counts, OUT untouched."""
import re
from dataclasses import replace
import shutil

import cv2
import numpy as np
import pytest

from stg_train.cli.prep import main
from stg_train.data import load_dataset
from stg_train.prep import prepare
from stg_train.rig.gauge import aligned_pose_errors

from .distort import distort, distortion_map
from .raw import raw_folder


def _centres(cameras) -> np.ndarray:
    return np.stack([-c.world_to_camera[:3, :3].T @ c.world_to_camera[:3, 3] for c in cameras])


@pytest.mark.parametrize("scene", ["calibration_scene", "calibration_scene_seed1"])
def test_the_rig_is_calibrated_back(scene, request, tmp_path):
    n3v, truth = request.getfixturevalue(scene)
    raw = raw_folder(n3v, tmp_path / "videos")
    report = prepare(raw, tmp_path / "out", offsets=[0] * 12, min_frames=1)
    cal = report["calibration"]
    assert (cal["registered"], cal["cameras"], cal["camera_model"], cal["fallback"]) == (12, 12, "pinhole", None)
    assert 0 < cal["mean_reprojection_error_px"] < 0.5
    # identical cameras: the shared intrinsics explain the features as well, and are kept
    fits = cal["intrinsics_fits"]
    assert cal["intrinsics"] == "shared" and set(fits) == {"shared", "per camera"}
    assert fits["shared"]["mean_reprojection_error_px"] == cal["mean_reprojection_error_px"]
    assert fits["shared"]["observations"] == sum(c["observations"] for c in report["cameras"])
    assert all(c["observations"] > 100 for c in report["cameras"])

    dataset = load_dataset(tmp_path / "out")
    assert [c.name for c in dataset.cameras] == [c.name for c in truth]
    rotation_deg, position = aligned_pose_errors(np.stack([c.world_to_camera for c in dataset.cameras]),
                                                 np.stack([c.world_to_camera for c in truth]))
    centres = _centres(truth)
    size = max(np.linalg.norm(a - b) for a in centres for b in centres)  # the rig's largest distance
    assert rotation_deg.max() < 0.1, rotation_deg
    assert 100 * position.max() / size < 0.5, 100 * position / size
    for got, want in zip(dataset.cameras, truth):  # the intrinsics: the focal length within 1 %
        assert abs(got.fx / want.fx - 1) < 0.01 and got.fx == got.fy
        assert (got.cx, got.cy, got.width, got.height) == (want.cx, want.cy, want.width, want.height)


def test_a_camera_that_does_not_register_is_named(sync_scene, tmp_path, capsys):
    n3v, _ = sync_scene
    raw = raw_folder(n3v, tmp_path / "videos", kind="png")
    rng = np.random.default_rng(1)
    (raw / "cam09").mkdir()
    for k in range(40):  # a camera that sees something else altogether
        cv2.imwrite(str(raw / "cam09" / f"{k}.png"), (rng.random((120, 160, 3)) * 255).astype(np.uint8))
    assert main([str(raw), str(tmp_path / "out"), "--quiet", "--offsets", "0,0,0,0,0"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1
    assert re.match(r"stg-prep: error: cam09: not registered by the calibration: cam09 \((no verified matches|\d+ "
                    r"verified matches)", err[0]), err[0]
    assert not (tmp_path / "out").exists()
    assert [p.name for p in tmp_path.iterdir()] == ["videos"]


def test_the_camera_model_must_be_known(sync_scene, tmp_path):
    with pytest.raises(ValueError, match="camera_model"):
        prepare(sync_scene[0], tmp_path / "out", camera_model="orthographic")


def test_a_fisheye_dome_registers_every_camera(fisheye_scene, tmp_path, capsys):
    folder, truth = fisheye_scene
    raw = tmp_path / "videos"
    raw.mkdir()
    for cam in truth:  # the frame folders, without models.json
        shutil.copytree(folder / cam.name, raw / cam.name)
    assert main([str(raw), str(tmp_path / "out"), "--camera-model", "fisheye", "--min-frames", "2"]) == 0
    assert re.search(r"calibration: fisheye \((shared|per camera) intrinsics\), 12 of 12 cameras registered",
                     capsys.readouterr().err)
    dataset = load_dataset(tmp_path / "out")
    assert [c.name for c in dataset.cameras] == [c.name for c in truth]
    assert all(c.model == "fisheye" and len(c.distortion) == 4 for c in dataset.cameras)
    rotation_deg, position = aligned_pose_errors(np.stack([c.world_to_camera for c in dataset.cameras]),
                                                 np.stack([c.world_to_camera for c in truth]))
    centres = _centres(truth)
    size = max(np.linalg.norm(a - b) for a in centres for b in centres)
    assert rotation_deg.max() < 0.5 and 100 * position.max() / size < 3, (rotation_deg, 100 * position / size)


def _psnr(a: np.ndarray, b: np.ndarray) -> float:
    return float(10 * np.log10(255.0 ** 2 / np.mean((a.astype(np.float64) - b.astype(np.float64)) ** 2)))


def test_distorted_lenses_are_undistorted_into_the_frames(calibration_scene, tmp_path):
    n3v, truth = calibration_scene
    coefficients = (-0.12, 0.03, 0.0005, -0.0005)  # barrel: about 25 px at the corners of 800x600
    raw = tmp_path / "videos"
    maps = distortion_map(truth[0], coefficients)  # the rig's cameras share their intrinsics
    for cam in truth:
        (raw / cam.name).mkdir(parents=True)
        ideal = cv2.imread(str(n3v / "frames" / cam.name / "000000.png"))
        cv2.imwrite(str(raw / cam.name / "0.png"), distort(ideal, maps))
    report = prepare(raw, tmp_path / "out", camera_model="opencv", offsets=[0] * 12, min_frames=1)
    assert (report["calibration"]["registered"], report["calibration"]["camera_model"]) == (12, "opencv")
    inner = (slice(60, -60), slice(80, -80))  # away from the borders, which undistortion stretches
    for cam in truth:
        ideal = cv2.imread(str(n3v / "frames" / cam.name / "000000.png"))[inner]
        recorded = cv2.imread(str(raw / cam.name / "0.png"))[inner]
        written = cv2.imread(str(tmp_path / "out" / "images" / cam.name / "00000.png"))[inner]
        assert _psnr(written, ideal) > _psnr(recorded, ideal) + 8, cam.name
    dataset = load_dataset(tmp_path / "out")  # written as undistorted pinholes
    assert all(c.model == "pinhole" and c.distortion == () for c in dataset.cameras)
    k1 = [c["distortion"][0] for c in report["cameras"]]
    assert all(-0.15 < k < -0.08 for k in k1), k1


def test_an_implausible_focal_length_is_found():
    """A degenerate fit (seen once under load: fx = -649811 px on a 160 px wide rig) is named, so that
    stg-prep refits on one thread or stops with a PrepError, never a Camera's ValueError traceback."""
    from types import SimpleNamespace

    from stg_train.prep.calibrate import implausible_focal

    def model(*focals):
        cams = {i + 1: SimpleNamespace(params=[f, 80.0, 60.0]) for i, f in enumerate(focals)}
        ims = {i + 1: SimpleNamespace(name=f"cam{i:02d}.png", camera_id=i + 1, has_pose=True) for i in range(len(focals))}
        return SimpleNamespace(cameras=cams, images=ims)

    assert implausible_focal(model(150.0, 160.0, 170.0), 160) is None
    assert implausible_focal(model(150.0, -649811.7, 170.0), 160) == ("cam01", -649811.7)
    assert implausible_focal(model(150.0, 160.0, 9000.0), 160) == ("cam02", 9000.0)
    assert implausible_focal(model(150.0, 5.0), 160) == ("cam01", 5.0)


def test_cameras_with_different_lenses_keep_their_own_intrinsics(tmp_path):
    """A rig whose cameras zoom differently (focal lengths 8 % apart): one shared focal length explains
    fewer of their features (the mapper drops those off by more than 1 px), so each camera keeps its
    own, fitted within 1 %."""
    from stg_train.prep.calibrate import calibrate
    from stg_train.synthetic import SyntheticScene, _to_uint8

    scene = SyntheticScene(seed=0, duration=1 / 30)
    zoom = [0.92, 1.0, 1.08] * 4
    truth = [replace(c, fx=c.fx * z, fy=c.fy * z) for c, z in zip(scene.cameras(12, 640, 480), zoom)]
    pictures = {c.name: _to_uint8(scene.render(c, 0.0)) for c in truth}
    cal = calibrate(pictures, tmp_path / "work")
    assert cal.intrinsics == "per camera"
    (_, shared_count), (_, count) = cal.intrinsics_fits["shared"], cal.intrinsics_fits["per camera"]
    assert shared_count < 0.97 * count, cal.intrinsics_fits
    for got, want in zip(cal.cameras, truth):
        assert abs(got.fx / want.fx - 1) < 0.01, (got.name, got.fx, want.fx)


def test_shared_intrinsics_must_explain_the_features_as_well():
    from stg_train.prep.calibrate import Calibration, shared_is_as_good

    def fit(error, observations):
        return Calibration([], np.zeros((0, 3)), np.zeros((0, 3)), "pinhole", error,
                           {"cam00": (observations // 2, error), "cam01": (observations - observations // 2, error)})

    per_camera = fit(0.30, 10000)
    assert shared_is_as_good(fit(0.30, 10000), per_camera)
    assert shared_is_as_good(fit(0.315, 9700), per_camera)
    assert not shared_is_as_good(fit(0.316, 10000), per_camera)  # a worse fit
    assert not shared_is_as_good(fit(0.25, 9690), per_camera)  # features lost to the mapper's 1 px bound
