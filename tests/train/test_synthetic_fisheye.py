"""The synthetic scene through fisheye cameras: the dome rig (SyntheticScene.dome_cameras), fisheye
rendering, and `stg-synth --fisheye` / `--pinhole-dome` writing the Immersive layout."""
import json

import cv2
import numpy as np
import pytest

from stg_runtime.camera import Camera
from stg_train.cli.synth import main as synth_main
from stg_train.data import detect_layout, load_dataset
from stg_train.synthetic import DOME_CENTRE, OBJECT_NAMES, SyntheticScene, write_n3v

W, H = 40, 30


@pytest.mark.parametrize("model, distortion", [("fisheye", (0, 0, 0, 0)), ("fisheye", (0.03, -0.01, 0.002, 0)),
                                               ("pinhole", ())])
def test_dome_rig(model, distortion):
    scene = SyntheticScene()
    cams = scene.dome_cameras(9, W, H, 120.0, model, distortion or (0, 0, 0, 0))
    assert [c.name for c in cams] == [f"camera_{k:04d}" for k in range(1, 10)]
    assert all(c.model == model for c in cams)
    np.testing.assert_allclose(cams[0].center, 0, atol=1e-12)
    np.testing.assert_allclose(cams[0].R[2], [0, 0, 1], atol=1e-12)
    for cam in cams:
        outwards = cam.center - DOME_CENTRE
        np.testing.assert_allclose(cam.R[2], outwards / np.linalg.norm(outwards), atol=1e-12)
        assert cam.R[1] @ [0, 1, 0] > 0.8  # image down is roughly world down
        # the middles of the left and right image edges are 60 degrees off the axis
        rays = cam.camera_rays(np.array([0.0, W]), np.array([H / 2, H / 2]))
        np.testing.assert_allclose(np.degrees(np.arccos(rays[:, 2])), 60.0, atol=1e-9)
        for name in OBJECT_NAMES:  # every camera sees every object
            uv, z = cam.project(scene.object_center(name, 0.5))
            assert z > 0 and 0 <= uv[0] < W and 0 <= uv[1] < H, (cam.name, name)


def test_fisheye_render_agrees_with_the_camera_model():
    """Surfaces seen through the fisheye's pixels, placed in 3D with Camera.unproject at the rendered
    depth, are seen as the same objects through a pinhole of the same pose (Camera.project)."""
    scene = SyntheticScene(blur=0.0)
    fish = scene.dome_camera(20.0, 40.0, 64, 48, 150.0, "fisheye", (0.02, -0.005, 0, 0))
    pin = scene.dome_camera(20.0, 40.0, 64, 48, 100.0, "pinhole")
    _, depth = scene.render(fish, 0.4, return_depth=True)
    ids = scene.object_ids(fish, 0.4)
    v, u = np.mgrid[0:48, 0:64]
    points = fish.unproject(u + 0.5, v + 0.5, depth)
    uv, z = pin.project(points)
    inside = (z > 0) & (uv[..., 0] >= 0) & (uv[..., 0] < 64) & (uv[..., 1] >= 0) & (uv[..., 1] < 48)
    assert inside.mean() > 0.4
    pin_ids = scene.object_ids(pin, 0.4)[np.floor(uv[..., 1][inside]).astype(int), np.floor(uv[..., 0][inside]).astype(int)]
    assert (pin_ids == ids[inside]).mean() > 0.97
    assert len(np.unique(ids[inside])) >= 4  # room and objects, not one flat wall
    # and the fisheye sees beyond the pinhole's field: pixels whose rays lie over 50 degrees off the axis
    assert (np.degrees(np.arccos(fish.ray_directions() @ fish.R[2])) > 60).mean() > 0.2


def test_cli_writes_the_immersive_layout(tmp_path, capsys):
    out = tmp_path / "dome"
    assert synth_main([str(out), "--fisheye", "120", "--cameras", "3", "--frames", "2", "--size", "32x24",
                       "--fps", "10", "--quiet"]) == 0
    assert detect_layout(out) == "immersive"
    data = load_dataset(out)
    want = SyntheticScene().dome_cameras(3, 32, 24, 120.0)
    assert [c.name for c in data.cameras] == [c.name for c in want]
    for got, cam in zip(data.cameras, want):
        assert got.model == "fisheye" and got.distortion == (0, 0, 0, 0)
        assert (got.fx, got.fy, got.cx, got.cy) == pytest.approx((cam.fx, cam.fy, cam.cx, cam.cy), abs=1e-9)
        np.testing.assert_allclose(got.world_to_camera, cam.world_to_camera, atol=1e-9)
    assert [data.cameras[i].name for i in data.test_cameras] == ["camera_0001"] and data.fps == 10
    scene = SyntheticScene(seed=0, duration=2 / 10)
    for c in (0, 2):
        truth = np.rint(scene.render(want[c], 1 / 10) * 255).astype(np.uint8)
        np.testing.assert_array_equal(data.frame(c, 1), truth)
    meta = json.loads((out / "scene.json").read_text())
    assert meta["held_out"] == "camera_0001" and meta["model"] == "fisheye" and len(meta["depth_bounds"]) == 3

    # the pinhole dome into the same folder: same poses, pinhole lenses of the same horizontal field
    assert synth_main([str(out), "--pinhole-dome", "120", "--cameras", "2", "--frames", "2", "--size", "32x24",
                       "--quiet"]) == 0
    pinholes = load_dataset(out)
    assert [c.model for c in pinholes.cameras] == ["pinhole", "pinhole"] and not (out / "camera_0003").exists()
    same_count = SyntheticScene().dome_cameras(2, 32, 24, 120.0)  # the rig's poses depend on its size only
    np.testing.assert_allclose(pinholes.cameras[1].world_to_camera, same_count[1].world_to_camera, atol=1e-9)
    assert pinholes.cameras[0].fx == pytest.approx(16 / np.tan(np.radians(60)))
    # an N3V run over it leaves no Immersive file behind (and the other way round)
    write_n3v(out, scene, num_cameras=2, num_frames=1, width=32, height=24, png=False)
    assert detect_layout(out) == "n3v" and not (out / "models.json").exists()
    assert synth_main([str(out), "--fisheye", "200", "--cameras", "2", "--frames", "1", "--size", "32x24",
                       "--quiet", "--no-png"]) == 0
    assert detect_layout(out) == "immersive" and not (out / "poses_bounds.npy").exists()
    assert not list(out.glob("cam0*.mp4")) and load_dataset(out).num_frames == 1


@pytest.mark.parametrize("args", [["--fisheye", "0"], ["--fisheye", "360"], ["--pinhole-dome", "180"],
                                  ["--fisheye", "120", "--pinhole-dome", "90"], ["--fisheye", "120", "--focal", "50"],
                                  ["--fisheye", "wide"]])
def test_cli_bad_fields_of_view(tmp_path, capsys, args):
    with pytest.raises(SystemExit) as e:
        synth_main([str(tmp_path / "x"), *args, "--quiet"])
    assert e.value.code == 2
    assert "error" in capsys.readouterr().err and not (tmp_path / "x").exists()


def test_novel_views_of_any_camera():
    from stg_train.synthetic import novel_view_dataset

    scene = SyntheticScene()
    cams = scene.dome_novel_cameras(W, H)
    rig = scene.dome_cameras(12, W, H)
    spacing = min(np.linalg.norm(a.center - b.center) for i, a in enumerate(rig) for b in rig[i + 1:])
    for cam in cams:  # between the rig's cameras, not on one
        assert cam.model == "pinhole" and 0.02 < min(np.linalg.norm(cam.center - r.center) for r in rig) < spacing
    ds = novel_view_dataset(scene, 1, 30.0, cameras=cams)
    assert ds.cameras == cams and ds.test_cameras == [0, 1]
    np.testing.assert_array_equal(ds.frame(0, 0), np.rint(scene.render(cams[0], 0.0) * 255).astype(np.uint8))
    assert isinstance(ds.cameras[0], Camera) and cv2 is not None


def test_stg_eval_renders_the_datasets_fisheye_camera(tmp_path, monkeypatch, capsys):
    """stg-eval renders the held-out camera with the dataset's camera model (here a fisheye)."""
    from stg_runtime.demo import demo_model
    from stg_runtime.format import save
    from stg_runtime.player import Player
    from stg_train.cli.eval import main as eval_main

    data = tmp_path / "dome"
    assert synth_main([str(data), "--fisheye", "150", "--cameras", "3", "--frames", "2", "--size", "32x24",
                       "--quiet", "--no-png"]) == 0
    save(demo_model("lite", fps=30.0, num_frames=2), tmp_path / "m.stg")
    seen = []
    render = Player.render
    monkeypatch.setattr(Player, "render", lambda self, camera, *a, **k: seen.append(camera) or render(self, camera, *a, **k))
    assert eval_main([str(tmp_path / "m.stg"), str(data), "--no-lpips", "--quiet", "--any-cameras"]) == 0  # a demo model: not trained on this dome
    held_out = load_dataset(data).cameras[0]
    assert seen and all(c == held_out for c in seen) and held_out.model == "fisheye"
    assert '"psnr"' in capsys.readouterr().out
