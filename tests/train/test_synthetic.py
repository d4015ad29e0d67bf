"""The analytic ray tracer of stg_train.synthetic and the stg-synth command line."""
import json

import cv2
import numpy as np
import pytest

from stg_train.data import load_n3v
from stg_train.cli.synth import main as synth_main
from stg_train.synthetic import LIGHT, OBJECT_NAMES, TARGET, SyntheticScene, llff_pose

W, H = 64, 48


def _project(cam, X):
    x = cam.R @ X + cam.t
    return np.array([cam.fx * x[0] / x[2] + cam.cx, cam.fy * x[1] / x[2] + cam.cy]), x[2]


def _unproject(cam, u, v, depth):
    """World point seen through pixel (column u, row v) at camera-space depth."""
    x = np.array([(u + 0.5 - cam.cx) / cam.fx, (v + 0.5 - cam.cy) / cam.fy, 1.0]) * depth
    return cam.R.T @ (x - cam.t)


def test_render_shapes_ranges_and_determinism():
    cam = SyntheticScene(0).cameras(4, W, H)[1]
    rgb, depth = SyntheticScene(seed=3).render(cam, 0.1, return_depth=True)
    assert rgb.shape == (H, W, 3) and rgb.dtype == np.float32
    assert depth.shape == (H, W) and depth.dtype == np.float32
    assert rgb.min() >= 0 and rgb.max() <= 1 and rgb.std() > 0.05
    assert np.all(np.isfinite(depth)) and depth.min() > 0
    again = SyntheticScene(seed=3).render(cam, 0.1)
    np.testing.assert_array_equal(rgb, again)
    other_seed = SyntheticScene(seed=4).render(cam, 0.1)
    assert np.abs(other_seed - rgb).mean() > 0.01


def test_rig_is_forward_facing_and_cam00_in_the_middle():
    scene = SyntheticScene()
    cams = scene.cameras(12, W, H)
    assert [c.name for c in cams] == [f"cam{i:02d}" for i in range(12)]
    centres = np.stack([c.center for c in cams])
    np.testing.assert_allclose(centres[0], 0, atol=1e-12)
    np.testing.assert_allclose(centres.mean(axis=0)[:2], 0, atol=0.2)  # cam00 is central
    nearest = [np.sort(np.linalg.norm(centres - c, axis=1))[1] for c in centres]
    assert 0.25 <= min(nearest) and max(nearest) <= 1.0
    lo, hi = scene.bounds()
    np.testing.assert_allclose(cams[0].R[0], [1, 0, 0], atol=1e-12)  # image right is world +x
    for cam in cams:
        np.testing.assert_allclose(cam.R @ cam.R.T, np.eye(3), atol=1e-12)
        assert np.linalg.det(cam.R) == pytest.approx(1.0)
        assert _project(cam, np.array([0.0, lo[1] + 0.1, 6.0]))[0][1] < H / 2  # ceiling in the upper half
        assert _project(cam, np.array([0.0, hi[1], 4.0]))[0][1] > H / 2  # floor in the lower half
        assert np.all(cam.center > lo) and np.all(cam.center < hi)
        uv, z = _project(cam, TARGET)  # every camera looks at the target
        assert z > 0
        np.testing.assert_allclose(uv, [W / 2, H / 2], atol=1e-9)
        assert cam.fx == cam.fy == pytest.approx(0.9 * W)


def test_moving_sphere_moves_and_differences_concentrate_on_it():
    scene = SyntheticScene(duration=5 / 30)
    cam = scene.cameras(1, W, H)[0]
    t_end = 4 / 30
    a, b = scene.render(cam, 0.0), scene.render(cam, t_end)
    ids_a, ids_b = scene.object_ids(cam, 0.0), scene.object_ids(cam, t_end)
    mover, spinner = OBJECT_NAMES.index("moving_sphere"), OBJECT_NAMES.index("rotating_box")
    moving = (ids_a == mover) | (ids_b == mover)
    assert (ids_a == mover).sum() > 20 and not np.array_equal(ids_a == mover, ids_b == mover)
    # the sphere's centre projects onto sphere pixels at both times
    for t, ids in ((0.0, ids_a), (t_end, ids_b)):
        (u, v), _ = _project(cam, scene.moving_sphere_center(t))
        assert ids[int(v), int(u)] == mover
    diff = np.abs(a - b).max(axis=-1)
    near = cv2.dilate((moving | (ids_a == spinner) | (ids_b == spinner)).astype(np.uint8), np.ones((5, 5), np.uint8)) > 0
    assert diff[moving].mean() > 0.1
    assert diff[moving].mean() > 20 * diff[~near].mean()
    assert np.median(diff[~near]) == 0  # the static room does not change


def test_fader_appears_and_vanishes():
    scene = SyntheticScene(duration=1.0)
    cam = scene.cameras(1, W, H)[0]
    fader = OBJECT_NAMES.index("fader")
    assert scene.fader_alpha(0.0) == 0 and scene.fader_alpha(0.5) == 1 and scene.fader_alpha(0.99) == 0
    assert 0 < scene.fader_alpha(0.3) < 1
    assert not (scene.object_ids(cam, 0.0) == fader).any()
    assert (scene.object_ids(cam, 0.5) == fader).sum() > 10
    assert not (scene.object_ids(cam, 0.9) == fader).any()
    differs = np.abs(scene.render(cam, 0.5) - scene.render(cam, 0.0)).max(axis=-1) > 0.1
    assert differs[scene.object_ids(cam, 0.5) == fader].mean() > 0.8


def test_highlight_depends_on_the_viewpoint():
    """The brightest point of the shiny sphere is the Blinn-Phong highlight: it sits where the normal
    bisects the light and view directions, so it moves on the sphere when the camera moves."""
    scene = SyntheticScene(blur=0)
    cams = scene.cameras(12, 160, 120)
    centre, radius = scene.shiny_sphere
    shiny = OBJECT_NAMES.index("shiny_sphere")
    found = []
    for cam in (cams[9], cams[10]):  # 1.6 units apart, on either side of cam00
        rgb, depth = scene.render(cam, 0.0, return_depth=True)
        lum = rgb.sum(axis=-1)
        lum[scene.object_ids(cam, 0.0) != shiny] = -1
        v, u = np.unravel_index(np.argmax(lum), lum.shape)
        X = _unproject(cam, u, v, depth[v, u])
        assert np.linalg.norm(X - centre) == pytest.approx(radius, abs=1e-4)  # depth is on the surface
        half = (LIGHT - centre) / np.linalg.norm(LIGHT - centre) + (cam.center - centre) / np.linalg.norm(cam.center - centre)
        np.testing.assert_allclose(X, centre + radius * half / np.linalg.norm(half), atol=0.04)
        found.append(X)
        flat = SyntheticScene(blur=0, specular=0).render(cam, 0.0)
        assert rgb[v, u].mean() > flat[v, u].mean() + 0.3  # the highlight is the specular term
    assert np.linalg.norm(found[0] - found[1]) > 0.05


def test_depth_is_camera_z_of_the_visible_surface():
    scene = SyntheticScene(blur=0)
    cam = scene.cameras(3, W, H)[2]
    rgb, depth = scene.render(cam, 0.2, return_depth=True)
    (u, v), z = _project(cam, scene.moving_sphere_center(0.2))
    u, v = int(u), int(v)
    X = _unproject(cam, u, v, depth[v, u])
    assert np.linalg.norm(X - scene.moving_sphere_center(0.2)) == pytest.approx(scene.moving_sphere_radius, abs=1e-4)
    assert depth[v, u] < z
    lo, hi = scene.bounds()
    assert depth.max() < np.linalg.norm(hi - lo)
    ss = scene.render(cam, 0.2, return_depth=True, supersample=2)
    np.testing.assert_array_equal(ss[1], depth)
    assert np.abs(ss[0] - rgb).mean() < 0.05


def test_llff_pose_axes():
    cam = SyntheticScene().cameras(2, W, H)[1]
    m = llff_pose(cam)
    np.testing.assert_allclose(m[:, 0], cam.R[1])   # down = camera y
    np.testing.assert_allclose(m[:, 1], cam.R[0])   # right = camera x
    np.testing.assert_allclose(m[:, 2], -cam.R[2])  # backwards = -camera z
    np.testing.assert_allclose(m[:, 3], cam.center)
    np.testing.assert_allclose(m[:, 4], [H, W, cam.fx])


def test_cli_writes_the_layout(tmp_path, capsys):
    out = tmp_path / "scene"
    assert synth_main([str(out), "--cameras", "2", "--frames", "3", "--size", "32x24", "--fps", "15", "--seed", "2"]) == 0
    assert sorted(p.name for p in out.glob("cam*.mp4")) == ["cam00.mp4", "cam01.mp4"]
    assert len(list((out / "frames" / "cam01").glob("*.png"))) == 3
    poses = np.load(out / "poses_bounds.npy")
    assert poses.shape == (2, 17) and np.all(poses[:, 15] < poses[:, 16])
    meta = json.loads((out / "scene.json").read_text())
    assert (meta["seed"], meta["fps"], meta["width"], meta["height"], meta["num_frames"]) == (2, 15.0, 32, 24, 3)
    assert "6/6" in capsys.readouterr().err
    # writing again into the same folder leaves no file of the larger earlier run behind
    assert synth_main([str(out), "--cameras", "1", "--frames", "2", "--size", "32x24", "--quiet"]) == 0
    assert [p.name for p in out.glob("cam*.mp4")] == ["cam00.mp4"]
    assert sorted(p.name for p in (out / "frames").rglob("*.png")) == ["000000.png", "000001.png"]
    data = load_n3v(out, prefer_png=True, cache_dir=tmp_path / "cache")
    assert (data.num_cameras, data.num_frames, data.fps) == (1, 2, 30.0)
    out2 = tmp_path / "nopng"
    assert synth_main([str(out2), "--cameras", "1", "--frames", "1", "--size", "16x16", "--no-png", "--quiet"]) == 0
    assert not (out2 / "frames").exists() and (out2 / "cam00.mp4").exists()


def test_cli_help_and_bad_size(capsys):
    with pytest.raises(SystemExit) as e:
        synth_main(["--help"])
    assert e.value.code == 0
    text = capsys.readouterr().out
    for option in ("--cameras", "--frames", "--fps", "--size", "--seed", "--no-png"):
        assert option in text
    with pytest.raises(SystemExit) as e:
        synth_main(["out", "--size", "big"])
    assert e.value.code == 2


def test_novel_views_are_rig_cameras_between_the_cameras():
    from stg_train.synthetic import NOVEL_VIEWS, novel_view_dataset

    scene = SyntheticScene(seed=0, duration=2 / 30)
    rig = scene.cameras(12, 32, 24)
    cam01 = next(c for c in rig if np.allclose(c.center[:2], [0.4, 0.0]) or np.allclose(c.center[:2], [-0.4, 0.0]))
    ds = novel_view_dataset(scene, 2, 30.0, 32, 24, positions=(tuple(cam01.center[:2]),) + NOVEL_VIEWS)
    assert ds.num_cameras == 3 and ds.test_cameras == [0, 1, 2] and ds.num_frames == 2
    assert [c.name for c in ds.cameras] == ["novel0", "novel1", "novel2"]
    np.testing.assert_allclose(ds.cameras[0].world_to_camera, cam01.world_to_camera, atol=1e-12)
    expected = np.rint(scene.render(cam01, 1 / 30) * 255).astype(np.uint8)
    np.testing.assert_array_equal(ds.frame(0, 1), expected)
    xs = [c.center[0] for c in rig]
    for cam in ds.cameras[1:]:  # inside the rig, and not one of its cameras
        assert min(xs) < cam.center[0] < max(xs)
        assert min(np.linalg.norm(cam.center - c.center) for c in rig) > 0.1
