"""The colour decoder through onnxruntime against a numpy MLP (formats/stg-v1.md section 2)."""
import numpy as np
import pytest

from stg_runtime import Camera
from stg_runtime.decoder import OnnxDecoder, lite_colour
from stg_runtime.onnx_mlp import mlp_to_onnx


def numpy_decoder(features, camera, weights, activation):
    h, w, c = features.shape
    rays = camera.ray_directions().reshape(-1, 3)
    x = np.concatenate([features.reshape(-1, c)[:, 3:], np.broadcast_to(camera.center, (h * w, 3)), rays], 1)
    for k, wk in enumerate(weights):
        x = x @ wk.T.astype(np.float64)
        if k < len(weights) - 1:
            x = np.maximum(x, 0)
    out = features.reshape(-1, c)[:, :3] + x
    if activation == "sigmoid":
        out = 1 / (1 + np.exp(-out))
    return np.clip(out, 0, 1).reshape(h, w, 3)


@pytest.fixture
def camera():
    return Camera.look_at([0.2, -0.1, -0.5], [0, 0, 3], [0, -1, 0], 55, 24, 16)


@pytest.mark.parametrize("activation", ["sigmoid", "clamp", "identity"])
@pytest.mark.parametrize("hidden", [6, 16])
def test_decoder_matches_numpy_mlp(camera, activation, hidden):
    rng = np.random.default_rng(hidden)
    weights = [rng.standard_normal((hidden, 12)).astype(np.float32), rng.standard_normal((3, hidden)).astype(np.float32)]
    feats = rng.standard_normal((16, 24, 9)).astype(np.float32)
    dec = OnnxDecoder(mlp_to_onnx(weights), activation)
    got = dec(feats, camera)
    want = numpy_decoder(feats.astype(np.float64), camera, weights, activation)
    assert got.shape == (16, 24, 3) and got.dtype == np.float32
    np.testing.assert_allclose(got, want, atol=2e-5)
    np.testing.assert_allclose(dec(feats, camera), got)  # cached view inputs give the same answer


def test_three_layer_decoder_with_other_channel_count(camera):
    rng = np.random.default_rng(1)
    weights = [rng.standard_normal((8, 10)).astype(np.float32), rng.standard_normal((8, 8)).astype(np.float32),
               rng.standard_normal((3, 8)).astype(np.float32)]
    feats = rng.standard_normal((16, 24, 7)).astype(np.float32)
    got = OnnxDecoder(mlp_to_onnx(weights), "sigmoid")(feats, camera)
    np.testing.assert_allclose(got, numpy_decoder(feats.astype(np.float64), camera, weights, "sigmoid"), atol=2e-5)


def test_torch_exported_decoder_runs(camera, tmp_path):
    torch = pytest.importorskip("torch")
    torch.manual_seed(0)
    mlp = torch.nn.Sequential(torch.nn.Linear(12, 6, bias=False), torch.nn.ReLU(), torch.nn.Linear(6, 3, bias=False))
    path = tmp_path / "mlp.onnx"
    torch.onnx.export(mlp, torch.zeros(5, 12), str(path), dynamo=False, input_names=["x"], output_names=["y"],
                      dynamic_axes={"x": {0: "P"}, "y": {0: "P"}})
    weights = [mlp[0].weight.detach().numpy(), mlp[2].weight.detach().numpy()]
    feats = np.random.default_rng(2).standard_normal((16, 24, 9)).astype(np.float32)
    got = OnnxDecoder(path.read_bytes(), "sigmoid")(feats, camera)
    np.testing.assert_allclose(got, numpy_decoder(feats.astype(np.float64), camera, weights, "sigmoid"), atol=2e-5)


def test_wrong_channel_count_is_refused(camera):
    dec = OnnxDecoder(mlp_to_onnx([np.ones((6, 12), np.float32), np.ones((3, 6), np.float32)]), "sigmoid")
    with pytest.raises(ValueError, match="feature channels"):
        dec(np.zeros((16, 24, 3), np.float32), camera)


def test_lite_colour_clamps():
    f = np.array([[[-0.5, 0.5, 1.5]]], np.float32)
    np.testing.assert_array_equal(lite_colour(f), [[[0, 0.5, 1]]])
