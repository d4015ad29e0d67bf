"""Initial motion from optical flow (stg_train.data.flow): the projection Jacobian, the least-squares
triangulation of displacements, and velocities of points on the synthetic scene's moving sphere."""
import numpy as np
import pytest

from stg_runtime.camera import Camera
from stg_train.data.dataset import Dataset
from stg_train.data.flow import initial_velocity, projection_jacobian, triangulate_displacement
from stg_train.synthetic import OBJECT_NAMES, SyntheticScene, novel_view_dataset

W, H = 96, 72


def _rig(n=6, width=W, height=H):
    return SyntheticScene(seed=0).cameras(n, width, height)


def test_projection_jacobian_is_the_pinhole_derivative():
    cam = _rig()[3]
    rng = np.random.default_rng(0)
    xyz = np.array([0.0, 0.3, 4.0]) + rng.uniform(-1, 1, (20, 3))
    p = xyz @ cam.R.T + cam.t
    x, y, z = p.T
    d_cam = np.zeros((20, 2, 3))
    d_cam[:, 0, 0] = cam.fx / z
    d_cam[:, 0, 2] = -cam.fx * x / z ** 2
    d_cam[:, 1, 1] = cam.fy / z
    d_cam[:, 1, 2] = -cam.fy * y / z ** 2
    np.testing.assert_allclose(projection_jacobian(cam, xyz), d_cam @ cam.R, rtol=1e-6, atol=1e-8)


def test_projection_jacobian_of_a_fisheye_matches_finite_differences_of_project():
    pinhole = Camera.look_at([0, 0, 0], [0, 0, 1], [0, -1, 0], 120.0, W, H)
    cam = Camera(pinhole.fx, pinhole.fy, pinhole.cx, pinhole.cy, W, H, pinhole.world_to_camera, model="fisheye",
                 distortion=(0.05, -0.01, 0.002, 0.0))
    xyz = np.array([[0.5, 0.2, 1.0], [-1.5, 0.4, 1.0], [0.0, 0.0, 2.0]])
    jac = projection_jacobian(cam, xyz)
    for k in range(3):
        step = np.zeros(3)
        step[k] = 1e-6
        numeric = (cam.project(xyz + step)[0] - cam.project(xyz - step)[0]) / 2e-6
        np.testing.assert_allclose(jac[:, :, k], numeric, rtol=1e-4, atol=1e-4)


def test_triangulation_recovers_a_displacement_from_exact_pixel_motion():
    cams = _rig()
    rng = np.random.default_rng(1)
    xyz = np.array([0.0, 0.3, 4.0]) + rng.uniform(-0.8, 0.8, (30, 3))
    true = rng.normal(0, 0.01, (30, 3))  # world units per frame
    jac = np.stack([projection_jacobian(c, xyz) for c in cams])
    flows = np.stack([c.project(xyz + true)[0] - c.project(xyz)[0] for c in cams])
    used = np.ones((len(cams), 30), bool)
    used[1:, 0] = False  # point 0: one camera only -> left at rest
    used[2:, 1] = False  # point 1: two cameras -> enough
    d = triangulate_displacement(jac, flows, used)
    np.testing.assert_array_equal(d[0], 0.0)
    np.testing.assert_allclose(d[1:], true[1:], atol=2e-4)  # linearisation error only


def _scene_dataset(scene, cams, num_frames, supersample=2, bounds=None):
    """A Dataset of `scene` seen by `cams` at frames k / 30 s, k < num_frames, all of them training
    cameras (novel_view_dataset's frames); bounds: (near, far) of every camera, or None."""
    rendered = novel_view_dataset(scene, num_frames, 30.0, cameras=cams, supersample=supersample)
    near_far = None if bounds is None else np.tile(bounds, (len(cams), 1))
    return Dataset(cams, rendered.frames, 30.0, test_cameras=[], bounds=near_far, bounds_source="user")


def _surface_points(scene, cam, t, name):
    """World points (P, 3) where camera `cam`'s pixel centres see object `name` at time t, and their
    colours in that camera's image."""
    ids = scene.object_ids(cam, t)
    rgb, depth = scene.render(cam, t, return_depth=True, supersample=1)
    v, u = np.nonzero(ids == OBJECT_NAMES.index(name) if name != "room" else ids == -1)
    xyz = cam.unproject(u + 0.5, v + 0.5, depth[v, u])
    return xyz, rgb[v, u]


def test_velocities_on_the_moving_sphere_and_rest_on_the_room():
    scene = SyntheticScene(seed=0, duration=1.0, blur=0.0)
    cams = _rig(8)
    ds = _scene_dataset(scene, cams, 3)
    t = 1 / 30.0  # frame 1 of the clip: normalised time 1/3 of this 3-frame dataset
    moving, moving_rgb = _surface_points(scene, cams[0], t, "moving_sphere")
    room, room_rgb = _surface_points(scene, cams[0], t, "room")
    room, room_rgb = room[::7], room_rgb[::7]
    xyz = np.concatenate([moving, room])
    rgb = np.concatenate([moving_rgb, room_rgb]).astype(np.float32)
    v = initial_velocity(ds, xyz, rgb, np.full(len(xyz), 1 / 3, np.float32))
    # the sphere translates: every point of it moves like its centre; velocity per unit of normalised
    # time of this 3-frame dataset = displacement per frame x 3
    true = (scene.moving_sphere_center(2 / 30.0) - scene.moving_sphere_center(t)) * 3
    on = np.linalg.norm(v[:len(moving)], axis=1) > 0
    assert on.mean() > 0.8
    err = np.linalg.norm(v[:len(moving)][on] - true, axis=1) / np.linalg.norm(true)
    assert np.median(err) < 0.25
    at_rest = np.linalg.norm(v[len(moving):], axis=1) == 0
    assert at_rest.mean() > 0.9


def test_trainer_starts_the_gaussians_with_the_flow_velocities_or_at_rest():
    from stg_train.trainer import Trainer, TrainConfig
    scene = SyntheticScene(seed=0, duration=1.0)
    cams = _rig(5, 64, 48)
    ds = _scene_dataset(scene, cams, 3, supersample=1, bounds=(0.5, 9.0))
    config = TrainConfig(iterations=10, num_points=600, init="volume", depth_candidates=8)
    moving = Trainer(ds, config)
    initial = moving.initial
    expected = initial_velocity(ds, initial.xyz, initial.rgb, initial.t_center)
    motion = moving.params.raw["motion"].detach().numpy()
    np.testing.assert_allclose(motion[:, 0:3], expected, rtol=1e-6)
    np.testing.assert_array_equal(motion[:, 3:], 0.0)
    assert (np.linalg.norm(expected, axis=1) > 0).sum() >= 3  # the moving sphere and the spinning box
    at_rest = Trainer(ds, TrainConfig(iterations=10, num_points=600, init="volume", depth_candidates=8,
                                      motion_init="zero"))
    np.testing.assert_array_equal(at_rest.params.raw["motion"].detach().numpy(), 0.0)
    with pytest.raises(ValueError, match="motion_init"):
        Trainer(ds, TrainConfig(iterations=10, num_points=600, motion_init="optical"))
