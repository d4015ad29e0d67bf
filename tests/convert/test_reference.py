"""Importing the reference implementation's models: renders match a float64 evaluation of the
reference's own formulas; malformed inputs give errors naming the file."""
import numpy as np
import pytest
import torch

from stg_runtime import Camera, Player
from stg_runtime.spec import MIN_ALPHA, rasterize_oracle
from stg_train.convert.ply import PLYError, write_ply
from stg_train.convert.reference import ReferenceModelError, import_reference, load_decoder

FPS = 30.0
CAMERA = Camera.look_at([0.3, -0.2, 0.0], [0, 0, 5.0], [0, -1, 0], 55.0, 64, 48, name="cam")


def reference_properties(n: int, kind: str, seed: int) -> dict:
    """Random but sensible raw parameters of a reference model, in its PLY's property order."""
    rng = np.random.default_rng(seed)
    p = {"x": rng.uniform(-1.2, 1.2, n), "y": rng.uniform(-0.9, 0.9, n), "z": rng.uniform(4.0, 6.5, n),
         "trbf_center": rng.uniform(0.0, 0.98, n), "trbf_scale": rng.uniform(-2.0, 0.5, n),
         "nx": np.zeros(n), "ny": np.zeros(n), "nz": np.zeros(n)}
    p.update({f"motion_{i}": rng.normal(0, [0.6, 0.4, 0.3][i // 3], n) for i in range(9)})
    p.update({f"f_dc_{i}": rng.normal(0, 1.0, n) for i in range(6 if kind == "full" else 3)})
    if kind == "lite":
        p.update({f"f_dc_{i}": rng.uniform(0, 1, n) for i in range(3)})
    p["opacity"] = rng.normal(0.5, 1.5, n)
    p.update({f"scale_{i}": np.log(rng.uniform(0.04, 0.2, n)) for i in range(3)})
    p.update({f"rot_{i}": rng.normal(0, 1, n) for i in range(4)})
    p.update({f"omega_{i}": rng.normal(0, 0.8, n) for i in range(4)})
    if kind == "full":
        p.update({f"f_t_{i}": rng.normal(0, 1.0, n) for i in range(3)})
    return {k: v.astype(np.float32) for k, v in p.items()}


def reference_render(p: dict, weights, t: float, kind: str) -> np.ndarray:
    """The reference's formulas in float64 at its time t (= j / duration), then the spec's splatter."""
    f = {k: v.astype(np.float64) for k, v in p.items()}
    col = lambda name, c: np.stack([f[f"{name}_{i}"] for i in range(c)], 1)  # noqa: E731
    dt = (t - f["trbf_center"])[:, None]
    opacity = 1 / (1 + np.exp(-f["opacity"])) * np.exp(-(dt[:, 0] / np.exp(f["trbf_scale"])) ** 2)
    m = col("motion", 9)
    xyz = np.stack([f["x"], f["y"], f["z"]], 1) + m[:, 0:3] * dt + m[:, 3:6] * dt ** 2 + m[:, 6:9] * dt ** 3
    q = col("rot", 4) + dt * col("omega", 4)
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    feats = col("f_dc", 6 if kind == "full" else 3)
    if kind == "full":
        feats = np.concatenate([feats, dt * col("f_t", 3)], 1)
    keep = opacity >= MIN_ALPHA
    F, _, _ = rasterize_oracle(xyz[keep], q[keep], np.exp(col("scale", 3))[keep], opacity[keep], feats[keep], CAMERA)
    if kind == "lite":
        return np.clip(F[..., :3], 0, 1)
    rays = CAMERA.ray_directions()
    x = np.concatenate([F[..., 3:], np.broadcast_to(CAMERA.center, rays.shape), rays], -1)
    w1, w2 = (w.astype(np.float64) for w in weights)
    y = np.maximum(x @ w1.T, 0) @ w2.T
    return 1 / (1 + np.exp(-(F[..., :3] + y)))


def save_decoder(path, seed: int):
    g = torch.Generator().manual_seed(seed)
    state = {"mlp1.weight": 0.5 * torch.randn(6, 12, 1, 1, generator=g),
             "mlp2.weight": 0.5 * torch.randn(3, 6, 1, 1, generator=g)}
    torch.save(state, path)
    return [state["mlp1.weight"].numpy()[:, :, 0, 0], state["mlp2.weight"].numpy()[:, :, 0, 0]]


def test_full_two_segments_render_like_the_reference(tmp_path):
    # Two segments: 50 frames (reference time = ours) and a short 30-frame one (time rescaled).
    props = [reference_properties(120, "full", seed) for seed in (1, 2)]
    plys, pts, weights = [], [], []
    for i, p in enumerate(props):
        plys.append(tmp_path / f"point_cloud_{i}.ply")
        pts.append(tmp_path / f"decoder_{i}.pth")
        write_ply(plys[-1], p)
        weights.append(save_decoder(pts[-1], i))
    model = import_reference(plys, pts, fps=FPS, start_frame=10, segment_frames=[50, 30])
    assert model.kind == "full" and [(s.start_frame, s.num_frames) for s in model.segments] == [(10, 50), (60, 30)]
    player = Player(model, device="cpu")
    worst = 0.0
    for seg, (start, frames) in enumerate([(10, 50), (60, 30)]):
        for j in (0, 7, frames - 1):
            ours = player.render(CAMERA, (start + j) / FPS)
            ref = reference_render(props[seg], weights[seg], j / 50.0, "full")
            worst = max(worst, float(np.abs(ours - ref).max()))
    assert worst < 1e-4, worst  # float32 rendering against float64


@pytest.mark.parametrize("frames, duration", [(50, 50), (20, 50), (20, 20), (60, 50), (60, 60)])
def test_segments_trained_with_any_duration(tmp_path, frames, duration):
    """The official code maps frame j of a segment to t = j / duration (50 by default; a short last segment
    may be trained with its own length): the import matches its renders at every kind of frame."""
    p = reference_properties(120, "full", frames + duration)
    p["trbf_center"] = np.random.default_rng(3).uniform(0, (frames - 1) / duration, 120).astype(np.float32)
    write_ply(tmp_path / "seg.ply", p)
    weights = save_decoder(tmp_path / "seg.pth", 4)
    model = import_reference([tmp_path / "seg.ply"], [tmp_path / "seg.pth"], fps=FPS, segment_frames=frames,
                             duration=duration)
    assert model.provenance["settings"]["duration"] == [float(duration)]
    player = Player(model, device="cpu")
    for j in (0, frames // 3, frames - 1):
        diff = np.abs(player.render(CAMERA, j / FPS) - reference_render(p, weights, j / duration, "full"))
        assert diff.max() < 1e-4, (j, diff.max())
    if frames != duration:  # reading the segment with the wrong duration renders something else
        wrong = Player(import_reference([tmp_path / "seg.ply"], [tmp_path / "seg.pth"], fps=FPS,
                                        segment_frames=frames, duration=frames), device="cpu")
        j = frames - 1
        assert np.abs(wrong.render(CAMERA, j / FPS) - reference_render(p, weights, j / duration, "full")).max() > 0.05


def test_durations_per_ply_and_bad_values(tmp_path):
    for i in range(2):
        write_ply(tmp_path / f"{i}.ply", reference_properties(20, "lite", i))
    plys = [tmp_path / "0.ply", tmp_path / "1.ply"]
    model = import_reference(plys, fps=FPS, segment_frames=[50, 20], duration=[50, 20])
    assert [s.num_frames for s in model.segments] == [50, 20]
    assert model.provenance["settings"]["duration"] == [50.0, 20.0]
    with pytest.raises(ValueError, match="duration: need one positive number, or one per PLY"):
        import_reference(plys, segment_frames=[50, 20], duration=[50, 20, 10])
    with pytest.raises(ValueError, match="duration"):
        import_reference(plys, duration=0)


def test_lite_segment_of_30_frames(tmp_path):
    p = reference_properties(150, "lite", 5)
    write_ply(tmp_path / "lite.ply", p)
    model = import_reference([tmp_path / "lite.ply"], fps=25.0, segment_frames=30)
    assert model.kind == "lite" and model.segments[0].decoder is None
    player = Player(model, device="cpu")
    for j in (0, 13, 29):
        diff = np.abs(player.render(CAMERA, j / 25.0) - reference_render(p, None, j / 50.0, "lite"))
        assert diff.max() < 1e-4, (j, diff.max())


def test_missing_property_names_file_and_property(tmp_path):
    p = reference_properties(10, "full", 0)
    del p["omega_2"]
    write_ply(tmp_path / "bad.ply", p)
    torch.save({"mlp1.weight": torch.zeros(6, 12, 1, 1), "mlp2.weight": torch.zeros(3, 6, 1, 1)}, tmp_path / "d.pth")
    with pytest.raises(PLYError, match=r"bad\.ply.*omega_2"):
        import_reference([tmp_path / "bad.ply"], [tmp_path / "d.pth"])


def test_truncated_and_miscounted_plys(tmp_path):
    write_ply(tmp_path / "ok.ply", reference_properties(10, "lite", 0))
    data = (tmp_path / "ok.ply").read_bytes()
    (tmp_path / "cut.ply").write_bytes(data[:-7])
    with pytest.raises(PLYError, match=r"cut\.ply: truncated"):
        import_reference([tmp_path / "cut.ply"])
    (tmp_path / "count.ply").write_bytes(data.replace(b"element vertex 10", b"element vertex 12"))
    with pytest.raises(PLYError, match=r"count\.ply: truncated"):
        import_reference([tmp_path / "count.ply"])
    (tmp_path / "junk.ply").write_bytes(b"not a ply at all")
    with pytest.raises(PLYError, match=r"junk\.ply"):
        import_reference([tmp_path / "junk.ply"])


def test_bad_decoders_name_the_file(tmp_path):
    ply = tmp_path / "full.ply"
    write_ply(ply, reference_properties(10, "full", 0))
    cases = {
        "missing.pth": {"mlp1.weight": torch.zeros(6, 12, 1, 1)},
        "shape.pth": {"mlp1.weight": torch.zeros(6, 9, 1, 1), "mlp2.weight": torch.zeros(3, 6, 1, 1)},
        "extra.pth": {"mlp1.weight": torch.zeros(6, 12, 1, 1), "mlp2.weight": torch.zeros(3, 6, 1, 1),
                      "mlp1.bias": torch.zeros(6)},
    }
    messages = {"missing.pth": "missing tensor 'mlp2.weight'", "shape.pth": r"mlp1.weight has shape \[6, 9, 1, 1\]",
                "extra.pth": "unexpected keys mlp1.bias"}
    for name, state in cases.items():
        torch.save(state, tmp_path / name)
        with pytest.raises(ReferenceModelError, match=f"{name}: {messages[name]}"):
            import_reference([ply], [tmp_path / name])
    (tmp_path / "garbage.pth").write_bytes(b"\x80\x02garbage")
    with pytest.raises(ReferenceModelError, match=r"garbage\.pth: not a readable torch state dict"):
        load_decoder(tmp_path / "garbage.pth")
    torch.save({"mlp1.weight": np.zeros((6, 12, 1, 1))}, tmp_path / "pickled.pth")  # needs unpickling numpy
    with pytest.raises(ReferenceModelError, match=r"pickled\.pth: not a readable torch state dict"):
        load_decoder(tmp_path / "pickled.pth")
    with pytest.raises(ValueError, match="needs its decoder"):
        import_reference([ply])

