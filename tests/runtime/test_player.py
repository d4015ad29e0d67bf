"""Player: renders of the shipped test vectors, time handling, videos, errors, the stg-render CLI."""
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from stg_runtime import Camera, Player
from stg_runtime import format as stg_format
from stg_runtime.cli import main as render_main
from stg_runtime.demo import demo_model
from stg_runtime.format import FormatError
from stg_runtime.camera import save_camera_path

VECTORS = Path(__file__).resolve().parents[2] / "formats" / "vectors"
INDEX = json.loads((VECTORS / "index.json").read_text())


@pytest.mark.parametrize("name", sorted(INDEX))
def test_player_renders_test_vectors(name):
    player = Player(VECTORS / INDEX[name]["file"], device="cpu")
    expected = np.load(VECTORS / INDEX[name]["expected"], allow_pickle=False)
    camera = player.cameras[int(expected["camera"])]
    assert len(player.model.segments) == INDEX[name]["segments"]
    for t, want in zip(expected["times"], expected["rgb"]):
        got = player.render(camera, float(t))
        assert got.shape == want.shape and got.dtype == np.float32
        np.testing.assert_allclose(got, want, atol=1e-4, err_msg=f"{name} at t={t}")
        assert want.std() > 0.05  # the vector shows something


@pytest.mark.parametrize("kind", ["lite", "full"])
def test_player_renders_fisheye_views_of_a_pinhole_model(kind):
    """A model trained with pinholes, seen through a 180-degree fisheye at the rig's first camera: the
    float64 oracle's image of the Gaussians at that time, decoded with the fisheye's pixel rays."""
    from stg_runtime.decoder import OnnxDecoder, activate
    from stg_runtime.spec import evaluate_oracle, rasterize_oracle
    player = Player(demo_model(kind, num_frames=4), device="cpu")
    pin = player.cameras[0].resized(48, 36)
    fish = Camera(pin.fy * 0.5, pin.fy * 0.5, 24, 18, 48, 36, pin.world_to_camera, "fish", "fisheye",
                  (0.02, -0.01, 0.0, 0.0))
    segment, tau = player.model.segment_at(0.05)
    g = evaluate_oracle(segment, tau)
    features, alpha, _ = rasterize_oracle(g["means"], g["quats"], g["scales"], g["opacities"], g["features"], fish)
    features = features.astype(np.float32)
    want = (np.clip(features[..., :3], 0, 1) if kind == "lite"
            else OnnxDecoder(segment.decoder, segment.activation)(features, fish))
    got = player.render(fish, 0.05)
    np.testing.assert_allclose(got, want, atol=2e-4)
    assert alpha.mean() > 0.1 and not np.allclose(got, player.render(pin, 0.05), atol=0.05)


def test_time_api():
    model = demo_model("lite", fps=25, num_frames=50)
    player = Player(model)
    assert player.fps == 25 and player.num_frames == 50 and player.duration == pytest.approx(2.0)
    cam = player.cameras[4].resized(40, 30)
    np.testing.assert_array_equal(player.render_frame(cam, 37), player.render(cam, 37 / 25))
    assert not np.array_equal(player.render(cam, 0.0), player.render(cam, 1.0))  # it moves
    player.render(cam, player.duration)  # the end is inclusive
    for bad in (-0.1, 2.01):
        with pytest.raises(ValueError, match="outside"):
            player.render(cam, bad)


def test_segments_play_end_to_end():
    lite = Player(VECTORS / "lite.stg")
    cam = lite.cameras[0]
    seg0, seg1 = lite.model.segments
    assert lite.model.segment_at(0.49)[0] is seg0 and lite.model.segment_at(0.5)[0] is seg1
    assert lite.model.segment_at(0.5)[1] == pytest.approx(0.0)
    assert lite.num_frames == 10 and lite.duration == pytest.approx(1.0)
    assert not np.array_equal(lite.render(cam, 0.45), lite.render(cam, 0.55))


def test_render_video_png_and_mp4(tmp_path):
    player = Player(demo_model("full", num_frames=6))
    cam = player.cameras[0].resized(32, 24)
    n = player.render_video(tmp_path / "frames", cam, progress=False)
    files = sorted((tmp_path / "frames").glob("frame_*.png"))
    assert n == 6 and len(files) == 6
    cv2 = pytest.importorskip("cv2")
    png = cv2.imread(str(files[2]))[..., ::-1]
    want = (np.clip(player.render_frame(cam, 2), 0, 1) * 255 + 0.5).astype(np.uint8)
    np.testing.assert_array_equal(png, want)
    assert player.render_video(tmp_path / "v.mp4", [cam] * 3, times=[0, 0.05, 0.1], progress=False) == 3
    cap = cv2.VideoCapture(str(tmp_path / "v.mp4"))
    frames = 0
    while cap.read()[0]:
        frames += 1
    assert frames == 3
    assert not list(tmp_path.glob(".*partial*"))


def test_render_video_camera_count_mismatch(tmp_path):
    player = Player(demo_model("lite", num_frames=4))
    cam = player.cameras[0].resized(16, 12)
    with pytest.raises(ValueError, match="one per frame"):
        player.render_video(tmp_path / "x", [cam, cam], progress=False)


def test_bad_file_raises_format_error(tmp_path):
    bad = tmp_path / "bad.stg"
    bad.write_bytes(b"definitely not a model")
    with pytest.raises(FormatError, match="bad.stg"):
        Player(bad)


def test_cuda_device_without_gpu_is_refused_clearly():
    from stg_runtime.cuda import device
    if device.usable():
        pytest.skip("numba sees a GPU (or its simulator) here: see tests/runtime/cuda/test_kernels.py")
    with pytest.raises(RuntimeError, match="numba sees no CUDA GPU.*device='cpu'"):
        Player(demo_model("lite", num_frames=2), device="cuda")
    with pytest.raises(ValueError, match="device must be one of"):
        Player(demo_model("lite", num_frames=2), device="gpu")


def test_cli_renders_demo_and_model(tmp_path, capsys):
    assert render_main(["--demo", "--out", str(tmp_path / "demo"), "--size", "32x24", "--end", "0.1", "--quiet"]) == 0
    assert len(list((tmp_path / "demo").glob("*.png"))) == 4  # t = 0, 1/30, 2/30, 3/30
    model = demo_model("lite", num_frames=3)
    stg_format.save(model, tmp_path / "m.stg")
    assert render_main([str(tmp_path / "m.stg"), "--out", str(tmp_path / "orbit"), "--orbit", "--size", "24x18", "--quiet"]) == 0
    assert len(list((tmp_path / "orbit").glob("*.png"))) == 3
    path = [Camera.look_at([x, 0, 0], [0, 0, 6], [0, -1, 0], 50, 20, 16) for x in (0, 0.1)]
    save_camera_path(tmp_path / "path.json", path)
    assert render_main([str(tmp_path / "m.stg"), "--out", str(tmp_path / "p"), "--path", str(tmp_path / "path.json"), "--quiet"]) == 0
    assert len(list((tmp_path / "p").glob("*.png"))) == 2


def test_cli_errors_name_the_problem(tmp_path, capsys):
    (tmp_path / "broken.stg").write_bytes(b"\x89STG\r\n\x1a\n" + b"\0" * 10)
    assert render_main([str(tmp_path / "broken.stg"), "--out", str(tmp_path / "o")]) == 2
    assert "broken.stg" in capsys.readouterr().err
    stg_format.save(demo_model("lite", num_frames=2), tmp_path / "m.stg")
    assert render_main([str(tmp_path / "m.stg"), "--out", str(tmp_path / "o"), "--camera", "99"]) == 2
    assert "has 9 cameras" in capsys.readouterr().err


def test_cli_help_runs():
    out = subprocess.run([sys.executable, "-m", "stg_runtime.cli", "--help"], capture_output=True, text=True)
    assert out.returncode == 0 and "--orbit" in out.stdout and "examples" in out.stdout
