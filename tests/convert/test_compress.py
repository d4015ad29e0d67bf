"""stg_train.convert.compress: quantization bounds, exact pruning, Morton order, presets' sizes."""
import numpy as np
import pytest

from stg_runtime import Camera, Model, Player, Segment
from stg_runtime import format as stg_format
from stg_runtime.demo import random_model
from stg_runtime.model import ATTRIBUTES
from stg_train.convert.compress import (attribute_bytes, channel_groups, compress, file_attribute_bytes, importance,
                                        model_views, morton_order, mse, parse_encodings, peak_opacity,
                                        prune_least_important, psnr_of_mse, render_views, report, seen_mask, snapped)


def small_model(kind="full", n=2500, seed=0) -> Model:
    return random_model(n, kind, seed=seed, width=96, height=72, radius_px=(0.5, 4.0))


def test_snapped_values_stay_within_their_bound():
    rng = np.random.default_rng(0)
    values = rng.normal(0, 3, (500, 4, 3)).astype(np.float32)
    seg = Segment(0, 10, opacity=np.ones(500), t_center=np.zeros(500), t_scale=np.zeros(500), position=values,
                  rotation=np.tile([1.0, 0, 0, 0], (500, 1, 1)), scale=np.ones((500, 3)), features=np.zeros((500, 3)))
    groups = channel_groups("position", seg, "lite")
    assert groups == [slice(0, 3), slice(3, 6), slice(6, 9), slice(9, 12)]
    for bits in ([16, 12, 8, 5], [8, 6, 4, 7]):
        cbits = 16 if max(bits) > 8 else 8
        out = snapped(values, bits, groups)
        x = values.reshape(500, 12).astype(np.float64)
        scale = (x.max(0) - x.min(0)) / (2 ** cbits - 1)
        step = np.concatenate([np.full(3, 2.0 ** (cbits - b)) for b in bits])
        bound = step / 2 * scale * (1 + 1e-6) + 2.0 ** -23 * np.abs(x).max(0)
        assert np.all(np.abs(out.reshape(500, 12) - x) <= bound)
        # Written and read back, the snapped values survive (only float32 rounding moves them).
        stored, params = stg_format.quantize(out, "u8" if cbits == 8 else "u16")
        back = stg_format.dequantize(stored, "u8" if cbits == 8 else "u16", params)
        assert np.all(np.abs(back - out) <= 2.0 ** -22 * np.abs(x).max(0).reshape(4, 3))
        # The unused low bits are zero, which is what makes zlib store them cheaply.
        q = stored.reshape(500, 12).astype(np.int64)
        low = q % step.astype(np.int64)
        assert np.all((low == 0) | (q == 2 ** cbits - 1))


def test_compressed_file_round_trip_within_bounds(tmp_path):
    model = small_model("lite", seed=1)
    out, settings = compress(model, "balanced", prune_opacity=None, prune_unseen=False, order=None)
    path = tmp_path / "c.stg"
    stg_format.save(out, path, **settings.save_kwargs())
    back = stg_format.load(path)
    for name in ATTRIBUTES:
        a, b = getattr(out.segments[0], name), getattr(back.segments[0], name)
        enc = settings.encodings[name]
        assert np.all(np.abs(a - b).reshape(len(a), -1) <= np.asarray(stg_format.error_bound(a, enc)) + 1e-7), name
        # and the snapped values are within the chosen precision of the original
        orig = getattr(model.segments[0], name).reshape(len(a), -1).astype(np.float64)
        if enc in ("u8", "u16"):
            bits = settings.bits[name]
            cbits = 8 if enc == "u8" else 16
            groups = channel_groups(name, model.segments[0], model.kind)
            step = np.ones(orig.shape[1])
            for g, b_ in zip(groups, bits):
                step[g] = 2.0 ** (cbits - b_)
            scale = (orig.max(0) - orig.min(0)) / (2 ** cbits - 1)
            assert np.all(np.abs(b.reshape(len(a), -1) - orig) <= step * scale * 0.5001 + 3e-7 * (1 + np.abs(orig))), name


def test_peak_opacity_and_pruning_are_exact():
    # Gaussians: visible; faint (0.003); alive only outside [0, 1]; peak 0.0099 at tau = 0 (t_center -0.1).
    opacity = [0.6, 0.003, 0.5, 0.01]
    t_center = [0.5, 0.5, 2.0, -0.1]
    t_scale = [2.0, 0.0, 10.0, 0.1]
    n = 4
    position = np.zeros((n, 4, 3))
    position[:, 0] = [[0, 0, 4], [0.2, 0, 4], [-0.2, 0, 4], [0, 0.2, 4]]
    seg = Segment(0, 10, opacity=opacity, t_center=t_center, t_scale=t_scale, position=position,
                  rotation=np.tile([1.0, 0, 0, 0, 0, 0, 0, 0], (n, 1)).reshape(n, 2, 4),
                  scale=np.full((n, 3), 0.1), features=np.full((n, 3), 0.5))
    taus = np.linspace(0, 1, 100001)
    brute = np.max(seg.opacity[:, None] * np.exp(-seg.t_scale[:, None] * (taus[None] - seg.t_center[:, None]) ** 2), 1)
    assert np.allclose(peak_opacity(seg), brute, rtol=1e-6)
    cam = Camera.look_at([0, 0, 0], [0, 0, 4], [0, -1, 0], 50, 48, 36)
    model = Model("lite", 10.0, [seg], cameras=[cam])
    out, s = compress(model, "lossless", prune_opacity=1 / 255, order=None)
    assert s.removed_opacity == 2 and np.allclose(out.segments[0].opacity, [0.6, 0.01])
    out2, s2 = compress(model, "lossless", prune_opacity=0.01, order=None)
    assert s2.removed_opacity == 3 and np.allclose(out2.segments[0].opacity, [0.6])
    # Below 1/255 the runtime never draws a Gaussian: renders are unchanged at every time.
    for t in (0.0, 0.35, 1.0):
        assert np.array_equal(Player(model).render(cam, t), Player(out).render(cam, t))


def test_unseen_pruning_removes_exactly_the_unseen():
    cam = Camera.look_at([0, 0, 0], [0, 0, 5], [0, -1, 0], 50, 64, 48, name="cam00")
    # 0 in view; 1 behind the camera; 2 far to the side; 3 moves into view at the last frame only;
    # 4 in view but alive (opacity >= 1/255) only long after the segment; 5 off-screen, its footprint reaching in.
    n = 6
    position = np.zeros((n, 4, 3))
    position[:, 0] = [[0, 0, 5], [0, 0, -3], [40, 0, 5], [-20, 0, 5], [0.5, 0, 5], [3.6, 0, 5]]
    position[3, 1] = [20 / 0.9, 0, 0]  # x(tau) = -20 + 22.2 tau: reaches 0 at tau = 0.9 = frame 9 of 10
    t_center = np.array([0.5, 0.5, 0.5, 0.0, 3.0, 0.5])
    t_scale = np.array([0, 0, 0, 0, 5.0, 0])
    opacity = np.full(n, 0.8)
    scale = np.full((n, 3), 0.05)
    scale[5] = [1.0, 1.0, 1.0]   # centre outside the image, 3-sigma footprint reaching into it
    seg = Segment(0, 10, opacity=opacity, t_center=t_center, t_scale=t_scale, position=position,
                  rotation=np.tile([1.0, 0, 0, 0, 0, 0, 0, 0], (n, 1)).reshape(n, 2, 4), scale=scale,
                  features=np.tile([0.9, 0.5, 0.1], (n, 1)))
    uv, _ = cam.project(position[5, 0])
    assert uv[0] > 64  # its centre projects outside the image
    assert seen_mask(seg, [cam]).tolist() == [True, False, False, True, False, True]
    model = Model("lite", 10.0, [seg], cameras=[cam])
    out, s = compress(model, "lossless", prune_opacity=None, prune_unseen=True, order=None)
    assert s.removed_unseen == 3 and out.segments[0].count == 3
    for j in range(10):
        assert np.array_equal(Player(model).render_frame(cam, j), Player(out).render_frame(cam, j))


def test_morton_order_is_a_permutation_that_keeps_renders():
    model = small_model("full", seed=2)
    seg = model.segments[0]
    perm = morton_order(seg.position[:, 0])
    assert np.array_equal(np.sort(perm), np.arange(seg.count))
    pts = seg.position[perm, 0]
    # neighbours along the curve are close: much closer than in the original (random) order
    assert np.linalg.norm(np.diff(pts, axis=0), axis=1).mean() < 0.3 * np.linalg.norm(np.diff(seg.position[:, 0], axis=0), axis=1).mean()
    out, _ = compress(model, "lossless", order="morton")
    assert np.array_equal(out.segments[0].opacity, seg.opacity[perm])
    views = model_views(model)
    for a, b in zip(render_views(model, views), render_views(out, views)):
        assert np.abs(a - b).max() <= 1e-6


#: Largest file size (fraction of the float32 file) and lowest PSNR against the uncompressed render per
#: preset, measured on small_model(kind, 3000 Gaussians) with seeds 3 and 4 (balanced: full 0.212-0.214
#: at 51.8-52.5 dB, lite 0.290-0.291 at 52.7-52.8 dB; small: full 0.171-0.176 at 45.1-45.4 dB, lite
#: 0.251 at 45.9-46.1 dB), with margin. The search's budgets (model PSNR assumed 33 dB, 70% of the
#: preset's loss) are 50.9 dB for balanced and 43.8 dB for small. Random positions and features leave
#: zlib nothing to find, so this model is the hard case: on a trained model (bench/compress.py)
#: balanced is below 1/5 and small below 1/8 of the float32 file.
#: web (format 1.4; a 38 dB model assumed, budget 51.1 dB): full 0.163-0.172 at 51.1 dB, lite
#: 0.236-0.237 at 51.3 dB (seeds 3 and 4): smaller than small at the fidelity of balanced.
LIMITS = {"full": {"lossless": (1.01, np.inf), "balanced": (0.24, 50.5), "small": (0.195, 43.5), "web": (0.18, 50.5)},
          "lite": {"lossless": (1.01, np.inf), "balanced": (0.31, 50.5), "small": (0.27, 43.5), "web": (0.245, 50.5)}}


@pytest.mark.parametrize("kind", ["full", "lite"])
def test_presets_meet_their_size_ratios(kind):
    model = small_model(kind, n=3000, seed=3)
    f32 = len(stg_format.dumps(model))
    sizes = {}
    for preset, (max_ratio, min_fidelity) in LIMITS[kind].items():
        out, settings = compress(model, preset)
        rep = report(model, out, settings)
        sizes[preset] = rep.file_after
        assert rep.file_after <= max_ratio * f32, (preset, rep.file_after / f32)
        assert rep.fidelity_db >= min_fidelity, (preset, rep.fidelity_db)
    assert sizes["web"] < sizes["small"] < sizes["balanced"] < 0.5 * sizes["lossless"]


def test_the_least_important_go_first():
    """importance: peak opacity x footprint area x the share of the segment's time a Gaussian is drawn."""
    seg = small_model("lite", n=6, seed=1).segments[0]
    seg.opacity[:] = [0.9, 0.9, 0.02, 0.9, 0.9, 0.9]
    seg.scale[:] = 0.1
    seg.scale[1] = 0.01  # a tenth of the size: a hundredth of the area
    seg.t_scale[:] = 0.0
    seg.t_scale[4], seg.t_center[4] = 1e4, 0.5  # drawn for about 5 % of the segment
    rank = np.argsort(importance(seg))
    assert rank[:3].tolist() == [1, 2, 4] and importance(seg)[0] == pytest.approx(0.9 * 0.01)
    assert importance(seg)[4] == pytest.approx(0.9 * 0.01 * 2 * np.sqrt(np.log(0.9 * 255) / 1e4))
    kept = prune_least_important(seg, 0.5)
    np.testing.assert_array_equal(kept.opacity, seg.opacity[[0, 3, 5]])


def test_web_preset_writes_what_it_measured(tmp_path):
    """A web file is format 1.5 with per-group arithmetic-coded parts; it decodes to the values compress
    returned (up to float32 rounding of a re-quantization), and its report names every part."""
    import struct

    model = small_model("full", n=1500, seed=4)
    out, settings = compress(model, "web")
    assert ":" in settings.encodings["position"] and settings.encodings["position"].startswith("ac")
    path = tmp_path / "web.stg"
    stg_format.save(out, path, **settings.save_kwargs())
    assert struct.unpack_from("<HH", path.read_bytes(), 8) == (1, 5)
    assert all(e.partition(":")[0].startswith("ac") for e in settings.encodings["position"].split("+"))
    back = stg_format.load(path)
    for a, b in zip(out.segments, back.segments):
        for name, values in a.arrays().items():
            np.testing.assert_allclose(getattr(b, name), values, rtol=0, atol=2.0 ** -20 * max(np.abs(values).max(), 1))
    text = report(model, out, settings).format()
    assert "position      parts" in text and "(ac12-delta:3+" in text and "bits 16" not in text
    assert sum(file_attribute_bytes(path).values()) == sum(attribute_bytes(out, settings.encodings, 9).values())


def test_encoding_overrides_and_errors():
    assert parse_encodings("position=u16, features=u8") == {"position": "u16", "features": "u8"}
    for bad in ("position", "colour=u8", "position=u12"):
        with pytest.raises(ValueError, match="bad encoding"):
            parse_encodings(bad)
    model = small_model("lite", n=400)
    out, s = compress(model, "balanced", encodings={"position": "f16", "features": "u8"})
    assert s.encodings["position"] == "f16" and s.encodings["features"] == "u8" and "position" not in s.bits
    with pytest.raises(ValueError, match="unknown preset"):
        compress(model, "tiny")


def test_psnr_helpers():
    a = np.zeros((4, 4, 3))
    assert psnr_of_mse(mse([a], [a])) == np.inf
    assert psnr_of_mse(mse([a + 0.1], [a])) == pytest.approx(20.0)


def test_compression_keeps_context_and_crossfades():
    """Format 1.3 keys survive pruning, reordering and quantization (every preset step)."""
    from dataclasses import replace

    a, b = small_model("full", n=800, seed=2), small_model("full", n=800, seed=3)
    model = Model("full", a.fps, [replace(a.segments[0], context_frames=(0, 2)),
                                  replace(b.segments[0].retimed(50, 50), context_frames=(2, 0), crossfade_frames=2)],
                  cameras=a.cameras)
    out, _ = compress(model, "small", order="morton")
    assert [(s.context_frames, s.crossfade_frames) for s in out.segments] == [((0, 2), 0), ((2, 0), 2)]


def test_merging_web_files_keeps_their_encodings(tmp_path):
    from stg_train.convert.merge import attribute_encodings, merge_files

    a, b = small_model("lite", n=600, seed=5), small_model("lite", n=600, seed=6)
    b = Model("lite", b.fps, [b.segments[0].retimed(a.num_frames, b.num_frames)], cameras=b.cameras)
    encodings = {"position": "u16-delta:3+u8:9", "features": "vq/u8", "opacity": "u8-delta"}
    for name, model in (("a", a), ("b", b)):
        stg_format.save(model, tmp_path / f"{name}.stg", encodings=encodings)
    merge_files([tmp_path / "a.stg", tmp_path / "b.stg"], tmp_path / "ab.stg")
    found = attribute_encodings(tmp_path / "ab.stg")
    assert {name: found[name] for name in encodings} == {name: {e} for name, e in encodings.items()}
