"""The Google Immersive layout (stg_train.data.immersive): models.json read into fisheye Cameras (checked
against cv2.fisheye), frames from folders or videos, the held-out centre camera, and every kind of bad
models.json stopping with a message naming the file and the camera."""
import json
import math
import shutil

import cv2
import numpy as np
import pytest

from stg_runtime.camera import Camera
from stg_train.data import DataError, detect_layout, load_dataset
from stg_train.data.immersive import camera_from_entry, centre_camera, entry_from_camera, natural_order

W, H, FRAMES = 24, 18, 3

#: Three cameras of an outward-facing rig; the centre camera (camera_0001) is not first in the file.
ENTRIES = [
    {"name": "camera_0002", "width": W, "height": H, "focal_length": 11.0, "pixel_aspect_ratio": 1.03,
     "principal_point": [12.3, 8.8], "radial_distortion": [0.05, -0.01], "orientation": [0.1, -0.25, 0.05],
     "position": [-0.2, 0.05, 0.1], "projection_type": "fisheye", "skew": 0.0, "tangential_distortion": [0, 0]},
    {"name": "camera_0001", "width": W, "height": H, "focal_length": 10.5, "principal_point": [11.9, 9.2],
     "radial_distortion": [0.02, 0.003, -0.001, 0.0002], "orientation": [0.0, 0.0, 0.0], "position": [0, 0, 0]},
    {"name": "camera_0003", "width": W, "height": H, "focal_length": 11.0, "pixel_aspect_ratio": 1.0,
     "principal_point": [12.0, 9.0], "radial_distortion": [0.0, 0.0], "orientation": [-0.1, 0.3, 0.0],
     "position": [0.2, -0.05, 0.1]},
]


def _frames(seed=0):
    return np.random.default_rng(seed).integers(0, 256, (len(ENTRIES), FRAMES, H, W, 3), dtype=np.uint8)


def _write(root, entries=ENTRIES, frames=None, videos=False, folders=True):
    """An Immersive folder: models.json and, per camera, a frames folder <name>/0.png ... (and/or a video)."""
    frames = _frames() if frames is None else frames
    root.mkdir(parents=True, exist_ok=True)
    (root / "models.json").write_text(json.dumps(entries) if not isinstance(entries, str) else entries)
    for entry, rgb in zip(ENTRIES, frames):
        if folders:
            (root / entry["name"]).mkdir(exist_ok=True)
            for k, image in enumerate(rgb):
                assert cv2.imwrite(str(root / entry["name"] / f"{k}.png"), np.ascontiguousarray(image[..., ::-1]))
        if videos:
            writer = cv2.VideoWriter(str(root / f"{entry['name']}.mp4"), cv2.VideoWriter_fourcc(*"mp4v"), 30.0, (W, H))
            for image in rgb:
                writer.write(np.ascontiguousarray(image[..., ::-1]))
            writer.release()
    return root


@pytest.fixture(scope="module")
def immersive(tmp_path_factory):
    return _write(tmp_path_factory.mktemp("immersive") / "scene")


def test_models_json_cameras(immersive):
    assert detect_layout(immersive) == "immersive"
    data = load_dataset(immersive)
    assert [c.name for c in data.cameras] == [e["name"] for e in ENTRIES]
    for cam, e in zip(data.cameras, ENTRIES):
        f, aspect = e["focal_length"], e.get("pixel_aspect_ratio", 1.0)
        assert (cam.model, cam.width, cam.height) == ("fisheye", W, H)
        assert (cam.fx, cam.fy, cam.cx, cam.cy) == pytest.approx((f, f * aspect, *e["principal_point"]), abs=1e-12)
        assert cam.distortion == pytest.approx(tuple(e["radial_distortion"]) + (0.0,) * (4 - len(e["radial_distortion"])))
        np.testing.assert_allclose(cam.R, cv2.Rodrigues(np.array(e["orientation"], float))[0], atol=1e-12)
        np.testing.assert_allclose(cam.center, e["position"], atol=1e-12)
        # a known point, projected by cv2.fisheye with the same numbers (principal point as given)
        point = cam.center + 2.0 * (cam.R[2] + 0.4 * cam.R[0] - 0.3 * cam.R[1])
        K = np.array([[f, 0, e["principal_point"][0]], [0, f * aspect, e["principal_point"][1]], [0, 0, 1]])
        D = np.array(cam.distortion, float).reshape(4, 1)
        rvec = np.array(e["orientation"], float).reshape(3, 1)
        tvec = (-cam.R @ np.array(e["position"], float)).reshape(3, 1)
        want, _ = cv2.fisheye.projectPoints(point.reshape(1, 1, 3), rvec, tvec, K, D)
        got, z = cam.project(point)
        np.testing.assert_allclose(got, want.reshape(2), atol=1e-9)
        assert z > 0
    # the frames, in natural order, and entry_from_camera reading back
    np.testing.assert_array_equal(data.frames, _frames())
    for cam in data.cameras:
        back = camera_from_entry(json.loads(json.dumps(entry_from_camera(cam))), "x")
        assert back.to_dict()["intrinsics"] == pytest.approx(cam.to_dict()["intrinsics"], abs=1e-12)
        np.testing.assert_allclose(back.world_to_camera, cam.world_to_camera, atol=1e-12)


def test_centre_camera_held_out(immersive, tmp_path):
    data = load_dataset(immersive)
    assert [data.cameras[i].name for i in data.test_cameras] == ["camera_0001"]
    assert load_dataset(immersive, test_camera="camera_0003").test_cameras == [2]
    # without a camera_0001: the camera whose optical axis is closest to the rig's mean axis
    renamed = [dict(e, name=n) for e, n in zip(ENTRIES, ("left", "middle", "right"))]
    root = tmp_path / "renamed"
    root.mkdir()
    (root / "models.json").write_text(json.dumps(renamed))
    for e, n in zip(ENTRIES, ("left", "middle", "right")):
        shutil.copytree(immersive / e["name"], root / n)
    data = load_dataset(root)
    assert [data.cameras[i].name for i in data.test_cameras] == ["middle"]
    assert centre_camera(data.cameras) == "middle"


def test_videos_natural_order_downscale(tmp_path):
    frames = _frames(1)
    root = _write(tmp_path / "v", frames=frames, videos=True, folders=False)
    data = load_dataset(root)
    assert data.frames.shape == frames.shape and data.fps == 30
    assert np.abs(data.frames.astype(int) - frames).mean() < 60  # lossy mp4 of noise, but the same frames
    half = load_dataset(root, downscale=2)
    assert half.cameras[0].model == "fisheye" and half.cameras[0].distortion == data.cameras[0].distortion
    assert half.cameras[0].fx == pytest.approx(data.cameras[0].fx / 2)
    names = [f"{k}.png" for k in (10, 2, 0, 1)] + ["a.png"]
    assert [p.name for p in natural_order(tmp_path / n for n in names)] == ["0.png", "1.png", "2.png", "10.png", "a.png"]


def _entries(**change):
    """ENTRIES with camera_0003's fields changed (None: removed)."""
    third = {k: v for k, v in dict(ENTRIES[2], **change).items() if v is not None}
    return ENTRIES[:2] + [third]


BAD_MODELS = [
    ("{not json", "not a JSON file", None),
    (json.dumps({"cameras": ENTRIES}), "non-empty JSON list", None),
    ("[]", "non-empty JSON list", None),
    (json.dumps(ENTRIES[:2] + [[1, 2]]), "must be a JSON object", "camera 2"),
    (_entries(focal_length=None), "missing field focal_length", "camera_0003"),
    (_entries(projection_type="equirectangular"), "projection_type 'equirectangular' is not supported", "camera_0003"),
    (_entries(radial_distortion=[0.1, 0, 0, 0, 0.2]), "unsupported distortion model", "camera_0003"),
    (_entries(tangential_distortion=[0.01, 0]), "tangential_distortion", "camera_0003"),
    (_entries(skew=0.5), "skew 0.5 is not supported", "camera_0003"),
    (_entries(projection_type="perspective"), None, None),  # zero distortion: a pinhole, fine
    (_entries(projection_type="perspective", radial_distortion=[0.1]), "perspective camera", "camera_0003"),
    (_entries(position=[0, math.nan, 0]), "non-finite", "camera_0003"),
    (_entries(focal_length=math.inf), "finite number", "camera_0003"),
    (_entries(focal_length=-3.0), "must be positive", "camera_0003"),
    (_entries(width=W + 0.5), "whole number", "camera_0003"),
    (_entries(orientation=[0, 1]), "orientation must be a list of 3 numbers", "camera_0003"),
    (_entries(principal_point="middle"), "principal_point", "camera_0003"),
    (_entries(name="camera_0002"), "a second camera named camera_0002", "camera 2"),
    (_entries(name="../camera_0003"), "plain file name", "camera 2"),
]


@pytest.mark.parametrize("text, fragment, camera", BAD_MODELS)
def test_bad_models_json(immersive, tmp_path, text, fragment, camera):
    root = tmp_path / "bad"
    shutil.copytree(immersive, root, ignore=shutil.ignore_patterns(".stg_cache"))
    (root / "models.json").write_text(text if isinstance(text, str) else json.dumps(text))
    if fragment is None:
        assert load_dataset(root).cameras[2].model == "pinhole"
        return
    with pytest.raises(DataError) as e:
        load_dataset(root)
    message = str(e.value)
    assert str(root / "models.json") in message and fragment in message, message
    if camera:
        assert camera in message, message
    assert not (root / ".stg_cache").exists()  # nothing decoded, nothing written


def test_frames_and_cameras_must_match(immersive, tmp_path):
    def copy(name):
        root = tmp_path / name
        shutil.copytree(immersive, root, ignore=shutil.ignore_patterns(".stg_cache"))
        return root

    root = copy("no_frames")
    shutil.rmtree(root / "camera_0003")
    with pytest.raises(DataError, match=r"camera_0003: missing: camera camera_0003 of .*models.json has no frames"):
        load_dataset(root)
    root = copy("extra_folder")
    shutil.copytree(root / "camera_0003", root / "camera_0009")
    with pytest.raises(DataError, match=r"camera_0009: frames of a camera camera_0009 that .*models.json does not"):
        load_dataset(root)
    root = _write(tmp_path / "no_video", videos=True, folders=False)
    (root / "camera_0002.mp4").unlink()
    with pytest.raises(DataError, match=r"camera_0002.mp4: missing: camera camera_0002 of .*models.json has no video"):
        load_dataset(root)
    root = _write(tmp_path / "extra_video", videos=True, folders=False)
    shutil.copy(root / "camera_0002.mp4", root / "camera_0007.mp4")
    with pytest.raises(DataError, match=r"camera_0007.mp4: there is no camera camera_0007 in .*models.json"):
        load_dataset(root)
    root = copy("no_models")
    (root / "models.json").unlink()
    with pytest.raises(DataError, match="models.json: missing"):
        load_dataset(root, layout="immersive")


def test_cli_exit_code(immersive, tmp_path, capsys):
    from stg_train.cli import train as train_cli

    root = tmp_path / "bad"
    shutil.copytree(immersive, root, ignore=shutil.ignore_patterns(".stg_cache"))
    (root / "models.json").write_text(json.dumps(_entries(radial_distortion=[1, 2, 3, 4, 5, 6])))
    assert train_cli.main([str(root), "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err
    assert str(root / "models.json") in err and "camera_0003" in err and "Traceback" not in err
    assert not (tmp_path / "out").exists() and not (root / ".stg_cache").exists()


def test_detection_beside_preprocessed_folders(immersive, tmp_path):
    root = tmp_path / "both"
    shutil.copytree(immersive, root, ignore=shutil.ignore_patterns(".stg_cache"))
    (root / "colmap_0").mkdir()  # the reference code's preprocessing output beside the raw data
    assert detect_layout(root) == "immersive"
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(DataError, match="models.json"):
        detect_layout(empty)


def test_camera_from_entry_is_a_camera():
    cam = camera_from_entry(ENTRIES[1], "x")
    assert isinstance(cam, Camera) and cam.name == "camera_0001" and cam.max_angle == pytest.approx(math.pi)
