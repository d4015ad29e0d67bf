"""stg_train.rig.gauge: the similarity of the whole world that pictures cannot reveal is found in small pose
corrections, and only it; pose refinement projects it out (PoseCorrections.center); pose errors
against a truth are reported with it removed (capture.pose_errors)."""
from __future__ import annotations

import numpy as np
import pytest

from stg_runtime.camera import Camera
from stg_train.rig.capture import in_model_frame, pose_errors
from stg_train.rig.gauge import corrections_between, gauge_part, gauge_projector
from stg_train.rotations import rotation_from_axis_angle, rotation_vector


def _rig(n=9, seed=0) -> np.ndarray:
    """(n, 4, 4) world_to_camera of cameras on an arc 3 units from the origin, looking at it."""
    rng = np.random.default_rng(seed)
    out = []
    for k in range(n):
        angle = np.radians(-30 + 60 * k / (n - 1))
        centre = np.array([3 * np.sin(angle), 0.3 * rng.normal(), -3 * np.cos(angle)])
        z = -centre / np.linalg.norm(centre)
        x = np.cross([0.0, 1.0, 0.0], z)
        x /= np.linalg.norm(x)
        r = np.stack([x, np.cross(z, x), z])
        w = np.eye(4)
        w[:3, :3], w[:3, 3] = r, -r @ centre
        out.append(w)
    return np.array(out)


def _moved_by_similarity(w2c: np.ndarray, turn, scale, shift) -> np.ndarray:
    """The cameras of a world mapped by X -> scale R(turn) X + shift (the same pictures of the mapped scene)."""
    rs = rotation_from_axis_angle(np.asarray(turn))
    out = []
    for w in w2c:
        r, centre = w[:3, :3], -w[:3, :3].T @ w[:3, 3]
        moved = np.eye(4)
        moved[:3, :3] = r @ rs.T
        moved[:3, 3] = -moved[:3, :3] @ (scale * rs @ centre + shift)
        out.append(moved)
    return np.array(out)


def test_rotation_vector_inverts_rodrigues():
    for v in ([0.0, 0.0, 0.0], [1e-9, 0, 0], [0.01, -0.02, 0.03], [0.5, 1.0, -0.7]):
        np.testing.assert_allclose(rotation_vector(rotation_from_axis_angle(np.array(v))), v, atol=1e-12)


def test_a_similarity_of_the_rig_is_all_gauge():
    rig = _rig()
    moved = _moved_by_similarity(rig, np.radians(0.3) * np.array([0.3, -0.5, 0.8]), 1.004, [0.01, -0.02, 0.005])
    w, t = corrections_between(moved, rig)
    gw, gt = gauge_part(rig, w, t)
    assert np.abs(w).max() > 1e-3 and np.abs(t).max() > 1e-2
    np.testing.assert_allclose(gw, w, atol=1e-5)  # second order in the similarity's size
    np.testing.assert_allclose(gt, t, atol=1e-5)


def test_what_is_left_has_no_gauge_and_one_camera_s_error_mostly_stays():
    rig = _rig()
    rng = np.random.default_rng(1)
    w, t = rng.normal(0, 3e-3, (9, 3)), rng.normal(0, 1e-2, (9, 3))
    gw, gt = gauge_part(rig, w, t)
    again = gauge_part(rig, w - gw, t - gt)
    assert np.abs(again[0]).max() < 1e-12 and np.abs(again[1]).max() < 1e-12
    # a correction of one camera alone is not a motion of the rig: most of it is kept
    single_w, single_t = np.zeros((9, 3)), np.zeros((9, 3))
    single_w[4], single_t[4] = [2e-3, 0, 0], [0, 0.01, 0]
    gw, gt = gauge_part(rig, single_w, single_t)
    assert np.linalg.norm(single_w[4] - gw[4]) > 0.8 * 2e-3 and np.linalg.norm(single_t[4] - gt[4]) > 0.8 * 0.01


def test_pose_errors_with_the_gauge_removed():
    rig = _rig()
    names = [f"c{i}" for i in range(len(rig))]
    record = {"cameras": [{"name": n, "true_world_to_camera": w.tolist()} for n, w in zip(names, rig)]}
    moved = _moved_by_similarity(rig, np.radians(0.2) * np.array([0.0, 1.0, 0.0]), 1.01, [0.02, 0.0, 0.0])

    def cams(w2c):
        return [Camera(50, 50, 32, 24, 64, 48, w, name=n) for n, w in zip(names, w2c)]

    errors = pose_errors(cams(moved), record)
    assert errors["rotation_deg"] == pytest.approx(0.2, abs=1e-6) and errors["translation"] > 0.02
    assert errors["aligned_rotation_deg"] < 1e-3 and errors["aligned_translation"] < 1e-4
    # a camera of its own off by 0.5 degrees stays visible: the rig's fit takes about a ninth of it as a
    # turn of all nine, leaving 8/9 of 0.5 on that camera and 1/9 on each other one (mean 2 x 0.5 x 8 / 81)
    wrong = moved.copy()
    wrong[3] = np.block([[rotation_from_axis_angle(np.radians(0.5) * np.array([1.0, 0, 0])), np.zeros((3, 1))],
                         [np.zeros((1, 3)), np.ones((1, 1))]]) @ wrong[3]
    aligned = pose_errors(cams(wrong), record)
    assert aligned["aligned_rotation_deg"] == pytest.approx(2 * 0.5 * 8 / 81, abs=0.01)


def test_the_scene_s_depth_keeps_shifts_from_passing_for_a_turn_of_the_rig():
    """Cameras shifted by 1 cm each, none turned: measured by the rig's radius (1.0 here) the shifts look
    like a turn of the whole rig, which removing the similarity then hands to every camera; measured in
    pictures of points 3 units away (the scene's depth) they do not."""
    rig = _rig()
    names = [f"c{i}" for i in range(len(rig))]
    record = {"cameras": [{"name": n, "true_world_to_camera": w.tolist()} for n, w in zip(names, rig)]}
    shifted = rig.copy()
    shifted[:, :3, 3] += np.random.default_rng(4).normal(0, 0.01, (len(rig), 3))
    cams = [Camera(50, 50, 32, 24, 64, 48, w, name=n) for n, w in zip(names, shifted)]
    by_radius, by_depth = pose_errors(cams, record), pose_errors(cams, record, depth=3.0)
    assert by_radius["rotation_deg"] < 1e-5
    assert by_radius["aligned_rotation_deg"] > 0.04 and by_depth["aligned_rotation_deg"] < 0.015


def test_a_camera_in_the_true_world_moves_into_the_model_s_frame():
    """A model trained on a rig that a similarity of the world moved sees an unseen camera where the same
    similarity moves it (to second order); each camera's own small error moves it only a little."""
    rig = _rig(10)
    moved = _moved_by_similarity(rig, np.radians(0.25) * np.array([0.2, 0.9, -0.4]), 1.006, [0.015, -0.01, 0.02])
    unseen = Camera(50, 50, 32, 24, 64, 48, rig[9], name="held-out")

    def off(placed):  # (degrees, distance) of a placed camera from the moved truth
        w, t = corrections_between(np.asarray(placed.world_to_camera)[None], moved[9][None])
        return np.degrees(np.linalg.norm(w)), np.linalg.norm(t)

    assert off(unseen)[0] > 0.2 and off(unseen)[1] > 0.015
    np.testing.assert_allclose(in_model_frame([unseen], rig[:9], rig[:9], 3.0)[0].world_to_camera, rig[9], atol=1e-12)
    degrees, distance = off(in_model_frame([unseen], moved[:9], rig[:9], 3.0)[0])
    assert degrees < 1e-3 and distance < 1e-4
    rng = np.random.default_rng(3)
    own = np.array([np.block([[rotation_from_axis_angle(rng.normal(0, 5e-4, 3)), rng.normal(0, 2e-3, (3, 1))],
                              [np.zeros((1, 3)), np.ones((1, 1))]]) @ w for w in moved[:9]])
    degrees, distance = off(in_model_frame([unseen], own, rig[:9], 3.0)[0])
    assert degrees < 0.25 * off(unseen)[0] and distance < 0.25 * off(unseen)[1]


def test_the_projector_is_gauge_part_as_one_matrix():
    rig = _rig()
    rng = np.random.default_rng(5)
    w, t = rng.normal(0, 1e-3, (9, 3)), rng.normal(0, 1e-2, (9, 3))
    gw, gt = gauge_part(rig, w, t)
    p = gauge_projector(rig)
    assert p.shape == (54, 54)
    np.testing.assert_allclose(p @ np.concatenate([w.ravel(), t.ravel()]), np.concatenate([gw.ravel(), gt.ravel()]),
                               rtol=0, atol=1e-15)
    np.testing.assert_allclose(p @ p, p, atol=1e-12)  # a projection: what it removes has no gauge left


def test_pose_refinement_projects_the_gauge_out():
    torch = pytest.importorskip("torch")
    from stg_train.rig.pose_refine import PoseCorrections

    rig = _rig()
    cams = [Camera(50, 50, 32, 24, 64, 48, w, name=f"c{i}") for i, w in enumerate(rig)]
    poses = PoseCorrections(range(len(rig)), cams, "cpu", scale=1.0)
    poses.load_state_dict({**poses.state_dict(), "scale": 2.0})  # the projector follows the unit
    moved = _moved_by_similarity(rig, np.radians(0.3) * np.array([0.6, 0.0, 0.8]), 0.995, [0.0, 0.01, -0.01])
    w, t = corrections_between(moved, rig)
    rng = np.random.default_rng(2)
    own_w, own_t = rng.normal(0, 1e-3, (9, 3)), rng.normal(0, 3e-3, (9, 3))
    gw, gt = gauge_part(rig, own_w, own_t)
    own_w, own_t = own_w - gw, own_t - gt
    with torch.no_grad():
        for c in range(9):
            poses.rotation[c].copy_(torch.as_tensor(w[c] + own_w[c]))
            poses.translation[c].copy_(torch.as_tensor((t[c] + own_t[c]) / 2.0))
    poses.center()
    kept_w = torch.stack([poses.rotation[c] for c in range(9)]).detach().double().numpy()
    kept_t = torch.stack([poses.translation[c] for c in range(9)]).detach().double().numpy() * 2.0
    np.testing.assert_allclose(kept_w, own_w, atol=2e-5)  # float32 corrections, the similarity to second order
    np.testing.assert_allclose(kept_t, own_t, atol=5e-5)
