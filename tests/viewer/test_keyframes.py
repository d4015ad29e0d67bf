"""Camera paths from keyframes, as stg-render --path reads them (stg_runtime.viewer.keyframes)."""
from pathlib import Path

import numpy as np
import pytest

from stg_runtime import Camera, Player
from stg_runtime.camera import camera_path_json, load_camera_path
from stg_runtime.cli import main as render_main
from stg_runtime.viewer.keyframes import interpolate_path

VECTORS = Path(__file__).resolve().parents[2] / "formats" / "vectors"


def test_path_passes_through_the_keyframes_and_interpolates():
    a = Camera.look_at([0, 0, 0], [0, 0, 5], [0, -1, 0], fov_deg=40, width=64, height=48)
    b = Camera.look_at([2, 0, 0], [2, 1, 5], [0, -1, 0], fov_deg=60, width=64, height=48)
    path = interpolate_path([a, b], frames_between=3)
    assert len(path) == 5
    np.testing.assert_allclose(path[0].world_to_camera, a.world_to_camera, atol=1e-12)
    np.testing.assert_allclose(path[-1].world_to_camera, b.world_to_camera, atol=1e-12)
    assert path[0].fy == pytest.approx(a.fy) and path[-1].fy == pytest.approx(b.fy)
    np.testing.assert_allclose(path[2].center, [1, 0, 0], atol=1e-12)  # half-way
    fovs = [2 * np.degrees(np.arctan(24 / c.fy)) for c in path]
    assert fovs == sorted(fovs) and fovs[2] == pytest.approx(50)
    (only,) = interpolate_path([a], 10)
    np.testing.assert_allclose(only.world_to_camera, a.world_to_camera, atol=1e-12)


def test_stg_render_accepts_a_saved_path(tmp_path):
    player = Player(VECTORS / "full.stg", device="cpu")
    cam = player.cameras[0]
    moved = Camera.from_colmap(cam.K, np.c_[cam.R, cam.t + [0.2, 0.0, 0.0]], cam.width, cam.height)
    keys = [cam, moved]
    path_file = tmp_path / "path.json"
    path_file.write_text(camera_path_json(interpolate_path(keys, 2)))
    assert len(load_camera_path(path_file)) == 4
    assert render_main([str(VECTORS / "full.stg"), "--out", str(tmp_path / "frames"), "--path", str(path_file),
                        "--quiet"]) == 0
    frames = sorted((tmp_path / "frames").glob("*.png"))
    assert len(frames) == 4
