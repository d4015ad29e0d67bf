"""stg_train.rig.capture: a realistic capture of the synthetic scene (exposure, white balance, vignetting,
noise, pose error) and its record in scene.json."""
from __future__ import annotations

import json

import numpy as np
import pytest

from stg_runtime.camera import Camera
from stg_train.rig.capture import CameraEffects, CaptureModel
from stg_train.data import load_n3v
from stg_train.synthetic import SyntheticScene, write_n3v


def _camera():
    return Camera(40, 40, 16, 12, 32, 24, np.eye(4))


def _effects(**kw):
    base = dict(gain=1.0, white_balance=np.ones(3), vignetting=0.0, noise=0.0, rotation=np.zeros(3),
                translation=np.zeros(3), seed=0)
    return CameraEffects(**{**base, **kw})


def test_gain_white_balance_and_vignetting_follow_the_model():
    image = np.full((24, 32, 3), 0.5)
    out = _effects(gain=1.2, white_balance=np.array([1.0, 0.9, 1.1])).apply(image, _camera())
    np.testing.assert_allclose(out[0, 0], [0.6, 0.54, 0.66])
    vignetted = _effects(vignetting=0.3).apply(image, _camera())
    # the corner pixels' centres lie just inside the corners; the centre pixels next to the principal point
    assert vignetted[12, 16, 0] == pytest.approx(0.5, abs=1e-3)
    assert vignetted[0, 0, 0] == pytest.approx(0.5 * (1 - 0.3 * (15.5 ** 2 + 11.5 ** 2) / (16 ** 2 + 12 ** 2)))


def test_noise_has_the_stated_spread_and_changes_every_frame():
    effects = _effects(noise=0.02)
    image = np.full((200, 200, 3), 0.5)
    a, b = effects.apply(image, Camera(100, 100, 100, 100, 200, 200, np.eye(4))), effects.apply(image, Camera(
        100, 100, 100, 100, 200, 200, np.eye(4)))
    assert np.std(a - 0.5) == pytest.approx(0.02, rel=0.05)
    assert not np.array_equal(a, b)


def test_the_pose_error_has_the_stated_size():
    cam = _camera()
    model = CaptureModel(rotation_deg=0.5, translation=0.02, seed=3)
    for effects in model.draw(5):
        wrong = effects.perturb(cam)
        r = wrong.world_to_camera[:3, :3] @ cam.world_to_camera[:3, :3].T
        assert np.degrees(np.arccos(np.clip((np.trace(r) - 1) / 2, -1, 1))) == pytest.approx(0.5, abs=1e-6)
        assert np.linalg.norm(wrong.center - cam.center) == pytest.approx(0.02, abs=1e-9)


def test_the_mean_exposure_and_white_balance_of_the_cameras_trained_on_are_one():
    effects = CaptureModel(gain=0.4, white_balance=0.1, seed=4).draw(7)
    gains = np.array([e.gain for e in effects])
    balances = np.array([e.white_balance for e in effects])
    assert gains.mean() == pytest.approx(1.0) and np.std(np.log2(gains)) > 0.1  # spread kept, mean divided out
    np.testing.assert_allclose(balances.mean(0), 1.0)
    # a held-out camera's pictures are not trained on: the mean is over the others (the same draw)
    trained = CaptureModel(gain=0.4, white_balance=0.1, seed=4).draw(7, held_out=[0])
    kept = np.array([e.gain for e in trained])
    assert kept[1:].mean() == pytest.approx(1.0) and abs(kept[0] - 1.0) > 0.05
    np.testing.assert_allclose(kept / gains, kept[0] / gains[0])
    np.testing.assert_allclose(np.mean([e.white_balance for e in trained[1:]], axis=0), 1.0)
    # with a reference camera, that camera is the truth and nothing is divided
    referenced = CaptureModel(gain=0.4, white_balance=0.1, seed=4, reference_camera=2).draw(7)
    first_draw = 2.0 ** np.random.default_rng(4).normal(0, 0.4)
    assert referenced[2].gain == 1.0 and referenced[0].gain == pytest.approx(first_draw)


def test_a_realistic_n3v_capture_records_its_truth(tmp_path):
    model = CaptureModel(seed=1, reference_camera=0)
    cams = write_n3v(tmp_path, SyntheticScene(seed=0, duration=1.0), num_cameras=3, num_frames=1, fps=1,
                     width=48, height=36, capture=model)
    ds = load_n3v(tmp_path, prefer_png=True)
    meta = json.loads((tmp_path / "scene.json").read_text())["capture"]
    assert meta["seed"] == 1 and len(meta["cameras"]) == 3
    # the reference camera is exact; the others' stated poses are off from the true ones
    np.testing.assert_allclose(ds.cameras[0].world_to_camera, cams[0].world_to_camera, atol=1e-9)
    for ci in (1, 2):
        np.testing.assert_allclose(meta["cameras"][ci]["true_world_to_camera"], cams[ci].world_to_camera)
        assert np.linalg.norm(ds.cameras[ci].center - cams[ci].center) == pytest.approx(model.translation, rel=1e-3)
    # the pictures went through each camera's gain: the frames differ from the ideal render
    clean = SyntheticScene(seed=0, duration=1.0).render(cams[1], 0.0)
    assert np.abs(ds.image(1, 0) - clean).mean() > 0.005
