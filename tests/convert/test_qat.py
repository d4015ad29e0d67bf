"""stg_train.convert.qat: fake quantisation is what the file decodes, gradients pass straight through,
the file-space Gaussians are the runtime's, and quantisation-aware fine-tuning beats quantising after."""
import numpy as np
import torch

from stg_runtime import Model
from stg_runtime import format as stg_format
from stg_runtime.spec import evaluate_oracle
from stg_train.convert.compress import _encoding, _with_segments, quantized
from stg_train.convert.finetune import finetune, finetune_file, finetune_quantised, params_of
from stg_train.convert.qat import (fake_quantised, file_tensors, gaussians_of_file, lowered, quantised_tensors,
                                   snapped_segment)

from .test_finetune import scene, train_psnr  # noqa: F401  (the module's fixture)

#: Every kind of part the web writer makes: acB at 1 to 12 bits (with or without differences), a
#: constant (u8), f16, f32.
BITS = {"opacity": [5], "t_center": [10], "t_scale": [12], "position": [12, 7, 3, 1], "rotation": [4, "f16"],
        "scale": [6], "features": [6, 0, "f32"]}


def test_forward_is_exactly_what_the_written_file_decodes(scene):
    model = stg_format.load(scene[2])
    seg = model.segments[0]
    params = params_of(seg, model.kind)
    with torch.no_grad():
        forward = quantised_tensors(params.raw, BITS, seg, model.kind)
    written = _with_segments(model, [snapped_segment(params.raw, BITS, seg, model.kind, seg.decoder)])
    encodings = {name: _encoding(written, name, ("compact", BITS[name]), 9) for name in BITS}
    assert encodings["t_scale"].removesuffix("-delta") == "ac12" and encodings["features"].startswith("ac6")
    assert encodings["position"].replace("-delta", "") == "ac12:3+ac7:3+ac3:3+ac1:3"
    assert "+u8:3+f32:3" in encodings["features"] and encodings["rotation"].endswith("+f16:4")
    back = stg_format.loads(stg_format.dumps(written, encodings=encodings, codec="zlib", level=9), "<qat>")
    for name in BITS:
        decoded = getattr(back.segments[0], name)
        assert decoded.dtype == np.float32 and np.array_equal(forward[name].numpy(), decoded), name
    exact = file_tensors(params.raw)
    assert not np.array_equal(forward["position"].numpy(), exact["position"].detach().numpy())
    # the same grid as the web preset's search (compress.quantized) up to the writer's last ulp
    searched = quantized(seg, {name: ("compact", b) for name, b in BITS.items()}, model.kind)
    for name in BITS:
        np.testing.assert_allclose(forward[name].numpy(), getattr(searched, name), rtol=0, atol=1e-5)


def test_gradient_passes_straight_through():
    values = torch.tensor(np.random.default_rng(0).normal(size=(50, 6)), dtype=torch.float32, requires_grad=True)
    groups = [slice(0, 3), slice(3, 6)]
    out = fake_quantised(values, [3, 0], groups)
    assert not torch.equal(out, values)
    assert torch.allclose(out[:, 3:], values[:, 3:].mean(0).expand(50, 3), atol=1e-6)  # 0 bits: the mean
    weights = torch.arange(300, dtype=torch.float32).reshape(50, 6)
    (out * weights).sum().backward()
    assert torch.equal(values.grad, weights)


def test_file_gaussians_are_the_runtimes_and_the_trainers(scene):
    model = stg_format.load(scene[2])
    seg = model.segments[0]
    params = params_of(seg, model.kind)
    with torch.no_grad():
        ours = gaussians_of_file(file_tensors(params.raw), 0.4)
        trainer = params.at(0.4)
    oracle = evaluate_oracle(seg, 0.4)
    for got, want, key in zip(ours, trainer, ("means", "quats", "scales", "opacities", "features")):
        np.testing.assert_allclose(got.numpy(), oracle[key], rtol=1e-4, atol=1e-5)
        np.testing.assert_allclose(got.numpy(), want.numpy(), rtol=1e-4, atol=1e-5)


def test_lowered_keeps_floats_and_constants():
    assert lowered([12, 7, 1, 0, "f16"]) == [10, 6, 1, 0, "f16"]
    assert lowered([8, 5], 2) == [6, 3]


def test_quantisation_aware_finetuning_beats_quantising_afterwards(scene):
    _, ds, path = scene
    model = stg_format.load(path)
    bits = {"position": [5, 3, 2, 1], "rotation": [3, 1], "scale": [3], "features": [3, 2, 1], "opacity": [3]}
    tuned = finetune(model, ds, 60, lr_scale=0.5)  # the same steps and rates both ways
    after = Model(model.kind, model.fps, [quantized(tuned.segments[0], {k: ("compact", b) for k, b in bits.items()},
                                                    model.kind)], model.cameras, model.bounds)
    aware = finetune_quantised(model, ds, 60, bits, lr_scale=0.5)
    assert aware.segments[0].count == model.segments[0].count
    assert train_psnr(aware, ds) > train_psnr(after, ds) + 0.3  # measured 24.82 against 24.12 dB


def test_finetune_file_with_quantised_steps(scene, tmp_path):
    _, ds, path = scene
    rep, info = finetune_file(path, tmp_path / "q.stg", ds, 5, "web", 0.3, quantised_steps=5)
    assert info.quantised_steps == 5 and np.isfinite(info.psnr_quantised)
    stored = stg_format.load(tmp_path / "q.stg")
    assert stored.provenance["compress"]["finetune"]["quantised_steps"] == 5
    assert rep.file_after == (tmp_path / "q.stg").stat().st_size < rep.file_before
