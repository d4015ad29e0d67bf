"""Static 3DGS PLYs (stg_train.convert.gaussians3d): import, render, export, round trips, errors.

The expected values come from float64 transcriptions of the 3DGS formulas (tests/sh3dgs.py).
"""
from __future__ import annotations

import json

import numpy as np
import pytest

from stg_runtime import Player
from stg_runtime.demo import demo_model
from stg_runtime.spec import evaluate_oracle, rasterize_oracle
from stg_train.convert.gaussians3d import export_ply, import_3dgs_ply, read_cameras_json
from stg_train.convert.ply import PLYError, read_ply, write_ply

from tests.sh3dgs import C0, REST, camera, colours_3dgs, inria_props, inria_sh


@pytest.mark.parametrize("degree", [1, 3])
def test_imported_3dgs_ply_renders_like_float64_3dgs(tmp_path, degree):
    props = inria_props(degree=degree, seed=degree)
    write_ply(tmp_path / "point_cloud.ply", props)
    player = Player(import_3dgs_ply(tmp_path / "point_cloud.ply", fps=24.0, num_frames=3))
    assert player.kind == "sh" and player.model.sh_degree == degree and player.num_frames == 3
    means = np.stack([props["x"], props["y"], props["z"]], 1)
    opacity = 1 / (1 + np.exp(-props["opacity"].astype(np.float64)))
    scales = np.exp(np.stack([props[f"scale_{i}"] for i in range(3)], 1).astype(np.float64))
    quats = np.stack([props[f"rot_{i}"] for i in range(4)], 1)
    renders = []
    for cam in (camera(), camera(eye=(-1.2, 0.6, 0.5), target=(0.2, 0, 4))):
        rgb = colours_3dgs(degree, inria_sh(props, degree), means, cam.center)
        feats, alpha, _ = rasterize_oracle(means, quats, scales, opacity, rgb, cam)
        want = np.clip(feats, 0, 1)
        for t in (0.0, 0.1):  # static: every time shows the same image
            got = player.render(cam, t)
            np.testing.assert_allclose(got, want, atol=1e-4)
        assert alpha.max() > 0.9 and want.std() > 0.05
        renders.append(want)
    # view dependence is real: without f_rest the image differs
    flat = dict(props, **{f"f_rest_{i}": np.zeros_like(props["x"]) for i in range(REST[degree])})
    write_ply(tmp_path / "flat.ply", flat)
    assert np.abs(Player(import_3dgs_ply(tmp_path / "flat.ply")).render(camera(), 0.0) - renders[0]).max() > 0.05


@pytest.mark.parametrize("degree", [0, 3])
def test_import_export_import_round_trip(tmp_path, degree):
    props = inria_props(n=40, degree=degree, seed=10 + degree)
    props["rot_0"][0] = props["rot_1"][0] = props["rot_2"][0] = props["rot_3"][0] = 0  # zero quaternion
    write_ply(tmp_path / "in.ply", props)
    model = import_3dgs_ply(tmp_path / "in.ply")
    assert export_ply(model, tmp_path / "out.ply", 0.0) == 40  # every Gaussian here has opacity >= 1/255
    out, count = read_ply(tmp_path / "out.ply")
    assert count == 40 and list(out) == list(props)  # the INRIA property order
    assert all(v.dtype == np.float32 for v in out.values())
    for name in props:
        if not name.startswith("rot_"):
            np.testing.assert_allclose(out[name], props[name], rtol=2e-6, atol=2e-6, err_msg=name)
    q = np.stack([props[f"rot_{i}"] for i in range(4)], 1).astype(np.float64)
    q[0] = [1, 0, 0, 0]
    np.testing.assert_allclose(np.stack([out[f"rot_{i}"] for i in range(4)], 1),
                               q / np.linalg.norm(q, axis=1, keepdims=True), atol=1e-6)
    again = import_3dgs_ply(tmp_path / "out.ply")
    for name, a in model.segments[0].arrays().items():
        np.testing.assert_allclose(again.segments[0].arrays()[name], a, rtol=1e-5, atol=1e-6, err_msg=name)


@pytest.mark.parametrize("kind", ["lite", "full"])
def test_export_ply_of_a_dynamic_model_at_t(tmp_path, kind):
    model = demo_model(kind, fps=10, num_frames=20)
    seg = model.segments[0]
    t = 0.2  # the demo's fading ball is invisible then
    want = evaluate_oracle(seg, t / model.duration)
    keep = want["opacities"] >= 1 / 255
    if kind == "full":
        with pytest.warns(UserWarning, match="decoder"):
            written = export_ply(model, tmp_path / "snap.ply", t)
    else:
        written = export_ply(model, tmp_path / "snap.ply", t)
    got, count = read_ply(tmp_path / "snap.ply")
    assert written == count == keep.sum() and 0 < count < seg.count  # some Gaussians are invisible at t
    np.testing.assert_allclose(np.stack([got["x"], got["y"], got["z"]], 1), want["means"][keep], atol=2e-5)
    np.testing.assert_allclose(1 / (1 + np.exp(-got["opacity"].astype(np.float64))), want["opacities"][keep],
                               atol=1e-6)
    np.testing.assert_allclose(np.exp(np.stack([got[f"scale_{i}"] for i in range(3)], 1)), want["scales"][keep],
                               rtol=1e-5)
    quats = np.stack([got[f"rot_{i}"] for i in range(4)], 1)
    np.testing.assert_allclose(np.abs(np.sum(quats * want["quats"][keep], 1)), 1.0, atol=1e-5)
    base = seg.features[keep, :3].astype(np.float64)
    rgb = base if kind == "lite" else 1 / (1 + np.exp(-base))  # the demo's decoder activation is sigmoid
    dc = np.stack([got[f"f_dc_{i}"] for i in range(3)], 1)
    np.testing.assert_allclose(C0 * dc + 0.5, rgb, atol=1e-5)
    assert not any(name.startswith("f_rest") for name in got)
    with pytest.raises(ValueError, match="outside"):
        export_ply(model, tmp_path / "late.ply", 2.5)
    assert not (tmp_path / "late.ply").exists()


def test_import_errors_name_the_file(tmp_path):
    props = inria_props(n=5, degree=1)
    for change, match in [(lambda p: p.pop("scale_1"), "missing vertex properties: scale_1"),
                          (lambda p: p.pop("f_rest_8"), "8 f_rest_"),
                          (lambda p: p.update(f_rest_9=p["x"]), "10 f_rest_"),
                          (lambda p: p["opacity"].__setitem__(2, np.nan), "'opacity' has values that are not finite.*1 of")]:
        broken = {k: v.copy() for k, v in props.items()}
        change(broken)
        write_ply(tmp_path / "bad.ply", broken)
        with pytest.raises(PLYError, match=match) as info:
            import_3dgs_ply(tmp_path / "bad.ply")
        assert str(info.value).startswith(str(tmp_path / "bad.ply"))
    write_ply(tmp_path / "ok.ply", props)
    data = (tmp_path / "ok.ply").read_bytes()
    (tmp_path / "cut.ply").write_bytes(data[:-7])
    with pytest.raises(PLYError, match="cut.ply: truncated"):
        import_3dgs_ply(tmp_path / "cut.ply")


def test_cameras_json_of_a_3dgs_output_folder(tmp_path):
    cam = camera()
    c2w = np.linalg.inv(cam.world_to_camera)
    entry = {"id": 0, "img_name": "00001", "width": 64, "height": 48, "position": c2w[:3, 3].tolist(),
             "rotation": c2w[:3, :3].tolist(), "fx": cam.fx, "fy": cam.fy}
    (tmp_path / "cameras.json").write_text(json.dumps([entry]))
    ply = tmp_path / "point_cloud" / "iteration_30000" / "point_cloud.ply"
    ply.parent.mkdir(parents=True)
    write_ply(ply, inria_props(n=10, degree=0))
    (got,) = import_3dgs_ply(ply).cameras  # found two folders up, as 3DGS writes it
    assert got.name == "00001" and (got.cx, got.cy) == (32.0, 24.0)
    np.testing.assert_allclose(got.world_to_camera, cam.world_to_camera, atol=1e-12)
    assert import_3dgs_ply(ply, cameras=[]).cameras == []
    (tmp_path / "cameras.json").write_text("[{\"id\": 0}]")
    with pytest.raises(ValueError, match="cameras.json: not a readable 3DGS cameras.json"):
        read_cameras_json(tmp_path / "cameras.json")
