"""Spherical-harmonics colour ("sh" models): the runtime's SH colour, rendering, the .stg round trip.

The expected values come from float64 transcriptions of the 3DGS formulas (tests/sh3dgs.py), not from
stg_runtime.sh, so the runtime is checked against an independent evaluation.
"""
from __future__ import annotations

import hashlib
import json
import struct

import numpy as np
import pytest

from stg_runtime import FormatError, Model, Player, Segment
from stg_runtime import format as stg_format
from stg_runtime.demo import demo_model
from stg_runtime.onnx_mlp import mlp_to_onnx
from stg_runtime.sh import sh_colours
from stg_runtime.spec import evaluate_oracle, rasterize_oracle, sh_colours_oracle
from stg_train.convert.gaussians3d import import_3dgs_ply
from stg_train.convert.ply import write_ply

from tests.sh3dgs import camera, colours_3dgs, inria_props


@pytest.mark.parametrize("degree", [0, 1, 2, 3])
def test_runtime_sh_matches_3dgs_formulas(degree):
    rng = np.random.default_rng(degree)
    n, k = 500, (degree + 1) ** 2
    sh = rng.normal(0, 1, (n, 3, k))
    means = rng.normal(0, 2, (n, 3)).astype(np.float32)
    center = np.array([0.3, -0.5, 1.0])
    want = colours_3dgs(degree, sh, means, center)
    coeffs = sh.transpose(0, 2, 1).reshape(n, 3 * k).astype(np.float32)  # coefficient-major
    got = sh_colours(coeffs, means, center)
    assert got.dtype == np.float32 and got.shape == (n, 3)
    np.testing.assert_allclose(got, want, atol=2e-5)
    np.testing.assert_allclose(sh_colours_oracle(coeffs, means, center), want, atol=1e-5)
    assert (want == 0).any() and (want > 0.6).any()  # the max(., 0) clamp and bright colours both occur
    with pytest.raises(ValueError, match="not an SH layout"):
        sh_colours(np.zeros((n, 6), np.float32), means, center)


def test_sh_model_with_motion_uses_the_mean_at_t():
    rng = np.random.default_rng(5)
    n = 50
    position = np.zeros((n, 4, 3))
    position[:, 0] = np.stack([rng.uniform(-1.5, 1.5, n), rng.uniform(-1, 1, n), rng.uniform(3, 5, n)], 1)
    position[:, 1:] = 0.5 * rng.standard_normal((n, 3, 3))
    seg = Segment(0, 10, opacity=rng.uniform(0.3, 1, n), t_center=rng.uniform(0, 1, n),
                  t_scale=rng.uniform(0, 4, n), position=position, rotation=rng.standard_normal((n, 2, 4)),
                  scale=rng.uniform(0.1, 0.3, (n, 3)), features=rng.normal(0, 1, (n, 27)))
    player = Player(Model("sh", 10.0, [seg]))
    cam = camera()
    for t in (0.0, 0.37, 1.0):
        g = evaluate_oracle(seg, t)
        sh = seg.features.astype(np.float64).reshape(n, 9, 3).transpose(0, 2, 1)
        rgb = colours_3dgs(2, sh, g["means"], cam.center)
        feats, _, _ = rasterize_oracle(g["means"], g["quats"], g["scales"], g["opacities"], rgb, cam)
        np.testing.assert_allclose(player.render(cam, t), np.clip(feats, 0, 1), atol=1e-4)


def test_sh_model_survives_the_stg_round_trip(tmp_path):
    write_ply(tmp_path / "s.ply", inria_props(n=30, degree=2, seed=3))
    model = import_3dgs_ply(tmp_path / "s.ply", fps=25.0, num_frames=50, cameras=[camera()])
    stg_format.save(model, tmp_path / "s.stg")
    data = (tmp_path / "s.stg").read_bytes()
    assert struct.unpack_from("<HH", data, 8) == (1, 1)  # kind "sh" is new in version 1.1
    back = stg_format.load(tmp_path / "s.stg")
    assert back.kind == "sh" and back.fps == 25.0 and back.num_frames == 50 and back.cameras == model.cameras
    for name, a in model.segments[0].arrays().items():
        np.testing.assert_array_equal(back.segments[0].arrays()[name], a, err_msg=name)
    assert back.segments[0].decoder is None and back.segments[0].features.shape == (30, 27)
    np.testing.assert_array_equal(Player(back).render(camera(), 1.0), Player(model).render(camera(), 1.0))
    stg_format.save(demo_model("lite", num_frames=2), tmp_path / "lite.stg")  # lite and full files stay 1.0
    assert struct.unpack_from("<HH", (tmp_path / "lite.stg").read_bytes(), 8) == (1, 0)
    q = stg_format.load(tmp_path / "s.stg")
    stg_format.save(q, tmp_path / "q.stg", encodings={"features": "u16", "position": "f16"})
    assert stg_format.load(tmp_path / "q.stg").segments[0].features.shape == (30, 27)


def reseal(data, edit):
    length = struct.unpack_from("<Q", data, 12)[0]
    header = json.loads(data[20:20 + length])
    edit(header)
    text = json.dumps(header).encode()
    body = data[:12] + struct.pack("<Q", len(text)) + text + data[20 + length:-32]
    return body + hashlib.sha256(body).digest()


def test_reader_refuses_bad_sh_files(tmp_path):
    stg_format.save(demo_model("full", num_frames=2), tmp_path / "full.stg")
    full = (tmp_path / "full.stg").read_bytes()
    for edit, match in [(lambda h: h.update(kind="sh"), r"shape \[\d+, 9\] is not \(count, C\)"),
                        (lambda h: h.update(kind="hologram"), "unknown model kind 'hologram'")]:
        (tmp_path / "bad.stg").write_bytes(reseal(full, edit))
        with pytest.raises(FormatError, match=match) as info:
            stg_format.load(tmp_path / "bad.stg")
        assert str(info.value).startswith(str(tmp_path / "bad.stg"))
    seg = demo_model("full", num_frames=2).segments[0]
    decoder = mlp_to_onnx([np.ones((6, 15), np.float32), np.ones((3, 6), np.float32)])  # fits 12 features
    with pytest.raises(ValueError, match="has no decoder"):
        Model("sh", 30.0, [Segment(0, 2, decoder=decoder, **{**seg.arrays(), "features": np.zeros((seg.count, 12))})])
    with pytest.raises(ValueError, match="must map 15 -> 3"):  # a decoder that does not fit the features
        Segment(0, 2, decoder=seg.decoder, **{**seg.arrays(), "features": np.zeros((seg.count, 12))})
    with pytest.raises(ValueError, match="3 or 12 or 27 or 48"):
        Model("sh", 30.0, [Segment(0, 2, **{**seg.arrays(), "features": seg.features})])
