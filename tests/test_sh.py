"""Spherical-harmonics colour ("sh" models) and static 3DGS PLYs: import, render, export, .stg round trip.

The expected values come from float64 transcriptions of the 3DGS formulas written out here, not from
stg_runtime.sh, so the runtime is checked against an independent evaluation.
"""
import hashlib
import json
import struct

import numpy as np
import pytest

from stg_runtime import Camera, FormatError, Model, Player, Segment
from stg_runtime import format as stg_format
from stg_runtime.demo import demo_model
from stg_runtime.sh import sh_colours, sh_colours_reference
from stg_runtime.splat_reference import rasterize_reference
from stg_runtime.timeeval import evaluate_reference
from stg_train.convert.gaussians3d import export_ply, import_3dgs_ply, read_cameras_json
from stg_train.convert.ply import PLYError, read_ply, write_ply

C0 = 0.28209479177387814
C1 = 0.4886025119029199
C2 = [1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792, 0.5462742152960396]
C3 = [-0.5900435899266435, 2.890611442640554, -0.4570457994644658, 0.3731763325901154, -0.4570457994644658,
      1.445305721320277, -0.5900435899266435]
REST = {0: 0, 1: 9, 2: 24, 3: 45}


def eval_sh_3dgs(degree, sh, dirs):
    """3DGS's eval_sh in float64: sh (N, 3, K) per channel, dirs (N, 3) unit -> (N, 3)."""
    sh = np.asarray(sh, np.float64)
    x, y, z = (v[:, None] for v in np.asarray(dirs, np.float64).T)  # (N, 1) each, broadcast over channels
    r = C0 * sh[..., 0]
    if degree > 0:
        r = r - C1 * y * sh[..., 1] + C1 * z * sh[..., 2] - C1 * x * sh[..., 3]
    if degree > 1:
        xx, yy, zz, xy, yz, xz = x * x, y * y, z * z, x * y, y * z, x * z
        r = (r + C2[0] * xy * sh[..., 4] + C2[1] * yz * sh[..., 5] + C2[2] * (2 * zz - xx - yy) * sh[..., 6]
             + C2[3] * xz * sh[..., 7] + C2[4] * (xx - yy) * sh[..., 8])
    if degree > 2:
        r = (r + C3[0] * y * (3 * xx - yy) * sh[..., 9] + C3[1] * xy * z * sh[..., 10]
             + C3[2] * y * (4 * zz - xx - yy) * sh[..., 11] + C3[3] * z * (2 * zz - 3 * xx - 3 * yy) * sh[..., 12]
             + C3[4] * x * (4 * zz - xx - yy) * sh[..., 13] + C3[5] * z * (xx - yy) * sh[..., 14]
             + C3[6] * x * (xx - 3 * yy) * sh[..., 15])
    return r


def colours_3dgs(degree, sh, means, center):
    d = np.asarray(means, np.float64) - center
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return np.maximum(eval_sh_3dgs(degree, sh, d) + 0.5, 0.0)


def camera(eye=(0.3, -0.2, 0.0), target=(0, 0, 4)):
    return Camera.look_at(list(eye), list(target), [0, -1, 0], 60.0, 64, 48, name="view")


def inria_props(n=60, degree=3, seed=0):
    rng = np.random.default_rng(seed)
    props = {"x": rng.uniform(-1.5, 1.5, n), "y": rng.uniform(-1, 1, n), "z": rng.uniform(3, 5, n),
             "nx": np.zeros(n), "ny": np.zeros(n), "nz": np.zeros(n)}
    props.update({f"f_dc_{i}": rng.normal(0, 1, n) for i in range(3)})
    props.update({f"f_rest_{i}": rng.normal(0, 0.4, n) for i in range(REST[degree])})
    props["opacity"] = rng.normal(0.5, 1.5, n)
    props.update({f"scale_{i}": rng.uniform(-3.2, -1.8, n) for i in range(3)})
    props.update({f"rot_{i}": rng.normal(0, 1, n) for i in range(4)})
    return {k: v.astype(np.float32) for k, v in props.items()}


def inria_sh(props, degree):
    """(N, 3, K) per-channel coefficients read from the INRIA properties (f_rest channel-major)."""
    k = (degree + 1) ** 2
    dc = np.stack([props[f"f_dc_{c}"] for c in range(3)], 1)[:, :, None]
    rest = np.stack([props[f"f_rest_{i}"] for i in range(REST[degree])], 1).reshape(-1, 3, k - 1)
    return np.concatenate([dc, rest], axis=2).astype(np.float64)


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
    np.testing.assert_allclose(sh_colours_reference(coeffs, means, center), want, atol=1e-5)
    assert (want == 0).any() and (want > 0.6).any()  # the max(., 0) clamp and bright colours both occur
    with pytest.raises(ValueError, match="not an SH layout"):
        sh_colours(np.zeros((n, 6), np.float32), means, center)


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
        feats, alpha, _ = rasterize_reference(means, quats, scales, opacity, rgb, cam)
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
        g = evaluate_reference(seg, t)
        sh = seg.features.astype(np.float64).reshape(n, 9, 3).transpose(0, 2, 1)
        rgb = colours_3dgs(2, sh, g["means"], cam.center)
        feats, _, _ = rasterize_reference(g["means"], g["quats"], g["scales"], g["opacities"], rgb, cam)
        np.testing.assert_allclose(player.render(cam, t), np.clip(feats, 0, 1), atol=1e-4)


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
    want = evaluate_reference(seg, t / model.duration)
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
    with pytest.raises(ValueError, match="has no decoder"):
        Model("sh", 30.0, [Segment(0, 2, decoder=seg.decoder, **{**seg.arrays(), "features": np.zeros((seg.count, 12))})])
    with pytest.raises(ValueError, match="3 or 12 or 27 or 48"):
        Model("sh", 30.0, [Segment(0, 2, **{**seg.arrays(), "features": seg.features})])


def test_import_errors_name_the_file(tmp_path):
    props = inria_props(n=5, degree=1)
    for change, match in [(lambda p: p.pop("scale_1"), "missing vertex properties: scale_1"),
                          (lambda p: p.pop("f_rest_8"), "8 f_rest_"),
                          (lambda p: p.update(f_rest_9=p["x"]), "10 f_rest_"),
                          (lambda p: p["opacity"].__setitem__(2, np.nan), "'opacity' has 1 non-finite")]:
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
