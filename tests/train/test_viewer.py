"""stg-train --viewer: a short training run serves frames of the model as it trains, and its final
model is the same as without the viewer."""
from __future__ import annotations

import time
import urllib.request

import numpy as np
import pytest

pytest.importorskip("torch")
pytest.importorskip("viser")

from stg_runtime import Player  # noqa: E402
from stg_runtime import format as stg_format  # noqa: E402
from stg_runtime.video import to_uint8  # noqa: E402
from stg_runtime.viewer.camera import viser_pose  # noqa: E402
from stg_train.cli.train import main as train_main  # noqa: E402
from stg_train.data import load_n3v  # noqa: E402
from stg_train.pipeline import train  # noqa: E402
from stg_train.trainer import TrainConfig  # noqa: E402
from stg_train.viewer import TrainingViewer  # noqa: E402
from tests.viewer.test_frames import FakeClient  # noqa: E402

SCENE = dict(num_cameras=4, num_frames=4, fps=4.0, width=48, height=32)
TRAIN = dict(iterations=24, num_points=300, schedule={"refine_start": 8, "refine_every": 8, "reset_every": 0})


@pytest.fixture(scope="module", autouse=True)
def one_torch_thread():
    """Training is bit-reproducible with one torch thread only (docs/performance.md), and the test
    compares two runs bit for bit."""
    import torch
    old = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(old)


@pytest.fixture(scope="module")
def dataset(synthetic_n3v):
    return load_n3v(synthetic_n3v("viewer_scene", **SCENE), prefer_png=True)


def test_training_viewer_serves_frames_and_changes_nothing(dataset, tmp_path):
    viewer = TrainingViewer(port=0, every=0.0, quiet=True)  # a snapshot after every step
    client = FakeClient(viser_pose(dataset.cameras[0]), SCENE["width"], SCENE["height"])
    pages = []

    def callback(trainer):
        viewer(trainer)
        if not pages:
            viewer.viewer.connect(client)  # as viser does for a browser
            with urllib.request.urlopen(viewer.viewer.url, timeout=30) as page:
                pages.append(page.status)
        time.sleep(0.05)  # let the stream render some of the snapshots

    try:
        train(dataset, tmp_path / "with", TrainConfig(**TRAIN), quiet=True, check=False, callback=callback)
        assert viewer.snapshots == TRAIN["iterations"]
        stream = next(iter(viewer.viewer.streams.values()))
        end = time.monotonic() + 60
        while stream._last_key is None or stream._last_key[3] != viewer.viewer.version:
            assert time.monotonic() < end, "the last snapshot was never rendered"
            time.sleep(0.1)
        status = viewer.viewer._status.content
        t = viewer.viewer.playback.time
    finally:
        viewer.close()
    assert pages == [200]
    assert len(client.sent) >= 2 and stream.stats.sent >= 2  # frames of several snapshots
    assert f"step {TRAIN['iterations']} of {TRAIN['iterations']}" in status and "Gaussians" in status
    # the last frame shows the final parameters: the exported model's picture
    final = Player(tmp_path / "with" / "model.stg", device="cpu")
    np.testing.assert_array_equal(client.sent[-1][0], to_uint8(final.render(dataset.cameras[0], t)))

    train(dataset, tmp_path / "without", TrainConfig(**TRAIN), quiet=True, check=False)
    a, b = (stg_format.load(tmp_path / name / "model.stg") for name in ("with", "without"))
    for sa, sb in zip(a.segments, b.segments, strict=True):
        for name, array in sa.arrays().items():
            np.testing.assert_array_equal(array, sb.arrays()[name], err_msg=name)
        assert sa.decoder == sb.decoder


def test_cli_viewer_port_in_use(dataset, tmp_path, capsys):
    import socket
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen()
        port = s.getsockname()[1]
        code = train_main([str(dataset.path), "--out", str(tmp_path / "run"), "--iterations", "2", "--quiet",
                           "--viewer", str(port)])
    assert code == 2
    assert f"port {port}" in capsys.readouterr().err
    assert not (tmp_path / "run").exists()
