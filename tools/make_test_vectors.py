#!/usr/bin/env python
"""Regenerate the test vectors in formats/vectors/: tiny .stg files and their expected renders.

The expected renders come from the float64 oracles (stg_runtime.spec: evaluate_oracle,
sh_colours_oracle, rasterize_oracle) and a numpy decoder, not from the Player, so a player is checked
against an independent transcription of formats/stg-v1.md. Usage: python tools/make_test_vectors.py
"""
from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np

from stg_runtime import Camera, Model, Segment
from stg_runtime import format as stg_format
from stg_runtime.onnx_mlp import mlp_to_onnx
from stg_runtime.spec import evaluate_oracle, rasterize_oracle, sh_colours_oracle

OUT = Path(__file__).resolve().parent.parent / "formats" / "vectors"
FPS = 10.0


def _camera() -> Camera:
    return Camera.look_at([0.2, -0.1, 0.0], [0, 0, 4], [0, -1, 0], 55.0, 48, 32, name="cam00")


def _fisheye_camera() -> Camera:
    """A distorted fisheye about 190 degrees across, inside the scene (Gaussians up to 90 degrees off its
    axis and beyond)."""
    pose = Camera.look_at([0.1, 0.1, 2.2], [0, 0, 4], [0, -1, 0], 55.0, 48, 32).world_to_camera
    return Camera(14.5, 15.0, 24.3, 15.8, 48, 32, pose, "fish00", "fisheye", (0.03, -0.01, 0.002, -0.0004))


def _segment(rng, start, frames, kind, weights=None) -> Segment:
    n = 40
    position = np.zeros((n, 4, 3))
    position[:, 0] = np.stack([rng.uniform(-1.5, 1.5, n), rng.uniform(-1, 1, n), rng.uniform(3, 5, n)], 1)
    position[:, 1:] = 0.3 * rng.standard_normal((n, 3, 3))
    rotation = np.concatenate([rng.standard_normal((n, 1, 4)), 0.5 * rng.standard_normal((n, 1, 4))], 1)
    channels = {"full": 9, "lite": 3, "sh": 27}[kind]
    features = rng.uniform(0, 1, (n, channels)) if kind == "lite" else rng.standard_normal((n, channels))
    if kind == "sh":  # degree 2: a colourful DC term, smaller higher bands
        features[:, 3:] *= 0.3
    return Segment(start, frames, opacity=rng.uniform(0.2, 1.0, n), t_center=rng.uniform(0, 1, n),
                   t_scale=rng.uniform(0, 6, n), position=position, rotation=rotation,
                   scale=rng.uniform(0.05, 0.4, (n, 3)), features=features,
                   decoder=None if weights is None else mlp_to_onnx(weights), activation="sigmoid")


def _numpy_decoder(features, camera, weights, activation):
    h, w, c = features.shape
    x = np.concatenate([features.reshape(-1, c)[:, 3:], np.broadcast_to(camera.center, (h * w, 3)),
                        camera.ray_directions().reshape(-1, 3)], 1)
    for k, wk in enumerate(weights):
        x = x @ wk.astype(np.float64).T
        x = np.maximum(x, 0) if k < len(weights) - 1 else x
    rgb = features.reshape(-1, c)[:, :3] + x
    rgb = 1 / (1 + np.exp(-rgb)) if activation == "sigmoid" else rgb
    return np.clip(rgb, 0, 1).reshape(h, w, 3)


def _segment_render(model: Model, seg: Segment, camera: Camera, t: float, weights) -> np.ndarray:
    """(H, W, 3) float64 render of segment `seg` of `model` at t seconds (at its own tau, inside or
    outside [0, 1]); weights: the decoder's, or {start_frame: weights} per segment."""
    tau = (t - seg.start_frame / model.fps) / (seg.num_frames / model.fps)
    g = evaluate_oracle(seg, tau)
    colours = g["features"]
    if model.kind == "sh":  # per-Gaussian colour for this view, before splatting
        colours = sh_colours_oracle(colours, g["means"], camera.center)
    feats, _, _ = rasterize_oracle(g["means"], g["quats"], g["scales"], g["opacities"], colours, camera)
    if model.kind in ("lite", "sh"):
        return np.clip(feats[..., :3], 0, 1)
    return _numpy_decoder(feats, camera, weights[seg.start_frame] if isinstance(weights, dict) else weights,
                          seg.activation)


def expected_render(model: Model, camera: Camera, t: float, weights) -> np.ndarray:
    """(H, W, 3) float64 render of `model` at t seconds by the reference path (formats/stg-v1.md,
    section 2: the segment holding frame floor(t fps), or inside a crossfade of b frames into segment B
    starting at frame s, (1 - w) A + w B with w = (t fps - (s - 1/2 - b/2)) / b)."""
    frame = int(np.floor(t * model.fps + 1e-9))
    index = next((i for i, s in enumerate(model.segments) if frame < s.start_frame + s.num_frames),
                 len(model.segments) - 1)
    for later in (index, index + 1):
        if 0 < later < len(model.segments) and model.segments[later].crossfade_frames:
            a, b = model.segments[later - 1], model.segments[later]
            w = (t * model.fps - (b.start_frame - 0.5 - 0.5 * b.crossfade_frames)) / b.crossfade_frames
            if 0 < w < 1:
                return ((1 - w) * _segment_render(model, a, camera, t, weights)
                        + w * _segment_render(model, b, camera, t, weights))
    return _segment_render(model, model.segments[index], camera, t, weights)


def _compact(full: Model) -> tuple[Model, dict]:
    """(1.4) The full model with its motion, rotations, last two scale channels and last six features
    drawn from small tables (so that codebooks hold them), and encodings that use every encoding of 1.4:
    differences of u8 and u16, vq with codebooks of every plain encoding, parts of plain and vq arrays."""
    rng = np.random.default_rng(2028)
    seg = full.segments[0]
    n = seg.count
    pick = lambda table: table[rng.integers(len(table), size=n)]  # noqa: E731
    position = seg.position.copy()
    position[:, 1:] = pick(0.3 * rng.standard_normal((6, 3, 3)))
    scale = seg.scale.copy()
    scale[:, 1:] = pick(rng.uniform(0.05, 0.4, (5, 2)))
    features = seg.features.copy()
    features[:, 3:] = pick(rng.standard_normal((7, 6)))
    compact = replace(seg, position=position, rotation=pick(np.concatenate(
        [rng.standard_normal((8, 1, 4)), 0.5 * rng.standard_normal((8, 1, 4))], 1)), scale=scale, features=features)
    encodings = {"opacity": "u8-delta", "t_center": "u16-delta", "t_scale": "f16",
                 "position": "u16-delta:3+vq/f16:9", "rotation": "vq/u16", "scale": "u8:1+vq/f32:2",
                 "features": "u8:3+vq/u8-delta:6"}
    return Model("full", FPS, [compact], cameras=full.cameras, bounds=full.bounds, provenance=full.provenance), encodings


#: (1.5) arithmetic-coded fixed point at several bit depths, with and without differences, as a whole
#: array, as parts beside a 1.0 encoding and as a codebook.
AC_ENCODINGS = {"opacity": "ac8", "t_center": "ac12-delta", "t_scale": "ac16", "position": "ac14:3+ac10-delta:9",
                "rotation": "vq/ac12", "scale": "ac11-delta", "features": "ac8:3+ac3-delta:3+u8:3"}


def main() -> None:
    rng = np.random.default_rng(2024)
    cam = _camera()
    weights = [0.5 * rng.standard_normal((6, 12)).astype(np.float32), 0.5 * rng.standard_normal((3, 6)).astype(np.float32)]
    lite = Model("lite", FPS, [_segment(rng, 0, 5, "lite"), _segment(rng, 5, 5, "lite")], cameras=[cam],
                 bounds=((-2, -2, 2), (2, 2, 6)), provenance={"tool": "tools/make_test_vectors.py"})
    full = Model("full", FPS, [_segment(rng, 0, 10, "full", weights)], cameras=[cam],
                 bounds=((-2, -2, 2), (2, 2, 6)), provenance={"tool": "tools/make_test_vectors.py"})
    quantized = {"position": "f16", "rotation": "u16", "scale": "u16", "features": "u8", "opacity": "u8",
                 "t_center": "u16", "t_scale": "f16"}
    sh = Model("sh", FPS, [_segment(np.random.default_rng(2026), 0, 10, "sh")], cameras=[cam],
               bounds=((-2, -2, 2), (2, 2, 6)), provenance={"tool": "tools/make_test_vectors.py"})
    fisheye = Model("full", FPS, full.segments, cameras=[_fisheye_camera()], bounds=full.bounds,
                    provenance=full.provenance)
    # (1.3) two full segments with their own decoders, each fitted 2 frames beyond the seam at frame 5,
    # crossfaded over 4 frames (3, 4, 5, 6 blended at B weights 1/8, 3/8, 5/8, 7/8)
    fade_rng = np.random.default_rng(2027)
    fade_weights = {start: [0.5 * fade_rng.standard_normal((6, 12)).astype(np.float32),
                            0.5 * fade_rng.standard_normal((3, 6)).astype(np.float32)] for start in (0, 5)}
    first, second = (_segment(fade_rng, start, 5, "full", fade_weights[start]) for start in (0, 5))
    crossfade = Model("full", FPS, [replace(first, context_frames=(0, 2)),
                                    replace(second, context_frames=(2, 0), crossfade_frames=4)],
                      cameras=[cam], bounds=full.bounds, provenance=full.provenance)
    compact, compact_encodings = _compact(full)
    vectors = [("lite", lite, {}, weights), ("full", full, {}, weights), ("full_quantized", full, quantized, weights),
               ("sh", sh, {}, weights), ("full_fisheye", fisheye, {}, weights),
               ("full_crossfade", crossfade, {}, fade_weights), ("full_compact", compact, compact_encodings, weights),
               ("full_ac", full, AC_ENCODINGS, weights)]
    index = {}
    for name, model, encodings, model_weights in vectors:
        times = [0.0, 0.3, 0.45, 0.62, 0.95] if name == "full_crossfade" else [0.0, 0.25, 0.62, 0.95]
        path = OUT / f"{name}.stg"
        stg_format.save(model, path, encodings=encodings)
        stored = stg_format.load(path)  # render what the file holds (quantized values included)
        camera = stored.cameras[0]
        renders = np.stack([expected_render(stored, camera, t, model_weights) for t in times]).astype(np.float32)
        np.savez_compressed(OUT / f"{name}.expected.npz", times=np.array(times), camera=np.array(0), rgb=renders)
        index[name] = {"file": path.name, "encodings": encodings or "f32", "segments": len(model.segments),
                       "expected": f"{name}.expected.npz"}
        print(f"{path.name}: {path.stat().st_size} bytes, {len(times)} expected renders")
    (OUT / "index.json").write_text(json.dumps(index, indent=1) + "\n")


if __name__ == "__main__":
    main()
