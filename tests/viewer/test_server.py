"""The viewer application (stg_runtime.viewer.server) without a browser: the initial view, the
screenshot and camera-path downloads, keyframes, model swaps."""
import io
import json
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("viser")

from stg_runtime import Player  # noqa: E402
from stg_runtime.camera import load_camera_path  # noqa: E402
from stg_runtime.viewer.camera import camera_from_viser, viser_pose  # noqa: E402
from stg_runtime.viewer.frames import render_image  # noqa: E402
from stg_runtime.viewer.server import Viewer  # noqa: E402
from tests.viewer.test_frames import FakeClient  # noqa: E402

VECTORS = Path(__file__).resolve().parents[2] / "formats" / "vectors"


class DownloadingClient(FakeClient):
    def __init__(self, *args):
        super().__init__(*args)
        self.files = {}

    def send_file_download(self, name, content, save_immediately=False):
        self.files[name] = content

    def add_notification(self, title, body, **_):
        self.files["notification"] = title


@pytest.fixture
def viewer():
    v = Viewer(VECTORS / "full.stg", port=0, device="cpu")
    yield v
    v.close()


def test_initial_view_is_training_camera_0(viewer):
    cam0 = viewer.player.cameras[0]
    initial = viewer.server.initial_camera
    np.testing.assert_allclose(initial.position, cam0.center, atol=1e-9)
    assert initial.fov == pytest.approx(2 * np.arctan(0.5 * cam0.height / cam0.fy))
    forward = (np.asarray(initial.look_at) - cam0.center) / np.linalg.norm(np.asarray(initial.look_at) - cam0.center)
    np.testing.assert_allclose(forward, cam0.R[2], atol=1e-9)
    assert viewer.playback.time == viewer.player.frame_times()[0]


def test_screenshot_and_camera_paths(viewer, tmp_path):
    import imageio.v3 as iio
    cam0 = viewer.player.cameras[0]
    pose = viser_pose(cam0)
    client = DownloadingClient(pose, 64, 40)
    viewer.playback.seek(0.5)
    png = viewer.screenshot(client)
    camera = camera_from_viser(pose.wxyz, pose.position, pose.fov, 64, 40)
    np.testing.assert_array_equal(iio.imread(io.BytesIO(png)), render_image(viewer.player, camera, 0.5))
    assert client.files[f"stg-view-{viewer.playback.frame:05d}.png"] == png

    (saved,) = load_camera_path_text(viewer.camera_path(client, keyframes=False), tmp_path)
    np.testing.assert_allclose(saved.world_to_camera, camera.world_to_camera, atol=1e-12)
    assert json.loads(client.files["camera.json"]) == json.loads(viewer.camera_path(client, keyframes=False))

    assert viewer.camera_path(client, keyframes=True) is None and client.files["notification"]
    viewer.add_keyframe(client)
    client.camera.position = client.camera.position + np.array([0.3, 0.0, 0.0])
    viewer.add_keyframe(client)
    viewer._between.value = 4
    path = load_camera_path_text(viewer.camera_path(client, keyframes=True), tmp_path)
    assert len(path) == 6 and viewer._keyframe_count.content == "keyframes: 2"
    np.testing.assert_allclose(path[-1].center - path[0].center, [0.3, 0.0, 0.0], atol=1e-9)


def load_camera_path_text(text, folder: Path):
    (folder / "path.json").write_text(text)
    return load_camera_path(folder / "path.json")


def test_set_model_keeps_the_time_and_bumps_the_version(viewer):
    viewer.playback.seek(0.3)
    viewer.set_model(Player(VECTORS / "full_quantized.stg", device="cpu").model)
    assert viewer.version == 1 and viewer.playback.time == pytest.approx(0.3)
    assert viewer.player.model.segments[0].position.dtype == np.float32
