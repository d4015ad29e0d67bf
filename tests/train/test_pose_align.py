"""Photometric pose alignment (stg_train.rig.pose_align) against the ray-traced synthetic scene: a camera
posed slightly off is brought back onto the pose its pictures were taken from, measured in the pictures
(how far the scene's surface moves between the true and the aligned camera)."""
import numpy as np
import pytest

from stg_train.rig.capture import corrected, pose_error
from stg_train.rig.pose_align import align_pose
from stg_train.synthetic import SyntheticScene


@pytest.fixture(scope="module")
def scene():
    return SyntheticScene(seed=0)


def _render(scene):
    return lambda camera, frame: scene.render(camera, frame / 10.0)


def _pictures(scene, camera, frames):
    return [(f, scene.render(camera, f / 10.0)) for f in frames]


def _misplacement(scene, truth, camera) -> float:
    """Median distance (pixels) between where the truth and `camera` see the surface of each pixel."""
    _, depth = scene.render(truth, 0.0, return_depth=True)
    v, u = np.mgrid[0:truth.height, 0:truth.width] + 0.5
    points = np.stack([(u - truth.cx) / truth.fx * depth, (v - truth.cy) / truth.fy * depth, depth,
                       np.ones_like(depth)], -1).reshape(-1, 4)
    world = points @ np.linalg.inv(np.asarray(truth.world_to_camera)).T
    seen = world @ np.asarray(camera.world_to_camera).T
    du = seen[:, 0] / seen[:, 2] * camera.fx + camera.cx - u.reshape(-1)
    dv = seen[:, 1] / seen[:, 2] * camera.fy + camera.cy - v.reshape(-1)
    return float(np.median(np.hypot(du, dv)))


def test_recovers_a_small_pose_error(scene):
    truth = SyntheticScene.rig_camera(0.2, 0.1, width=64, height=48)
    stated = corrected(truth, np.radians([0.3, -0.2, 0.1]), np.array([0.02, -0.01, 0.015]))
    result = align_pose(_render(scene), stated, _pictures(scene, truth, [0, 5]), depth=4.0, colour=False)
    assert _misplacement(scene, truth, stated) > 0.4
    assert _misplacement(scene, truth, result.camera) < 0.1
    assert result.mse_after < 0.2 * result.mse_before
    assert result.rotation_deg > 0.05 and result.shift > 0.001
    # a frame it was not aligned on agrees as well
    later = scene.render(truth, 0.8)
    error = lambda camera: np.mean((scene.render(camera, 0.8) - later) ** 2)
    assert error(result.camera) < 0.2 * error(stated)


def test_the_pictures_colour_does_not_move_the_pose(scene):
    truth = SyntheticScene.rig_camera(-0.3, 0.0, width=64, height=48)
    stated = corrected(truth, np.radians([-0.25, 0.2, 0.0]), np.zeros(3))
    pictures = [(f, np.clip(p * [1.15, 1.0, 0.85] + 0.02, 0, 1)) for f, p in _pictures(scene, truth, [0, 5])]
    with_colour = align_pose(_render(scene), stated, pictures, depth=4.0, colour=True)
    plain = align_pose(_render(scene), stated, pictures, depth=4.0, colour=False)
    assert _misplacement(scene, truth, with_colour.camera) < 0.25 * _misplacement(scene, truth, stated)
    assert _misplacement(scene, truth, with_colour.camera) < _misplacement(scene, truth, plain.camera)


def test_an_exact_pose_stays_and_bad_input_is_refused(scene):
    camera = SyntheticScene.rig_camera(0.0, 0.0, width=48, height=36)
    pictures = _pictures(scene, camera, [3])
    result = align_pose(_render(scene), camera, pictures, depth=4.0, iterations=2)
    assert _misplacement(scene, camera, result.camera) < 0.02
    assert pose_error(result.camera, camera.world_to_camera)[0] < 0.05
    assert result.mse_after <= result.mse_before
    with pytest.raises(ValueError, match="no picture"):
        align_pose(_render(scene), camera, [], depth=4.0)
    with pytest.raises(ValueError, match="depth"):
        align_pose(_render(scene), camera, pictures, depth=0.0)
