"""Static 3D Gaussian Splatting PLYs (the INRIA layout) in and out of our models (numpy only).

The INRIA layout, one vertex per Gaussian, all float32: x y z, nx ny nz (unused, 0), f_dc_0..2,
f_rest_0..(3 (K-1) - 1) with K = (d+1)^2 SH coefficients per channel (0, 9, 24 or 45 properties for
degree 0..3, stored channel-major: every R coefficient, then G, then B), opacity (logit), scale_0..2
(log), rot_0..3 (quaternion wxyz, not necessarily unit). Our "sh" models hold the same coefficients
coefficient-major (formats/stg-v1.md, section 2).
"""
from __future__ import annotations

import json
import os
import warnings
from pathlib import Path

import numpy as np

from stg_runtime import Camera, Model, Segment
from stg_runtime.spec import MIN_ALPHA
from stg_runtime.spec import SH_C0 as C0
from stg_runtime.timeeval import evaluate

from .ply import PLYError, float32_values, read_ply, require, write_ply

BASE = ["x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity", "scale_0", "scale_1", "scale_2",
        "rot_0", "rot_1", "rot_2", "rot_3"]
#: number of f_rest_* properties -> SH degree
REST_DEGREES = {3 * (k - 1): d for d, k in ((d, (d + 1) ** 2) for d in range(4))}
OPACITY_EPS = 1e-6    # opacities are clipped to [eps, 1 - eps] before the logit
MIN_SCALE = 1e-20     # scales are clipped below before the log


def sh_from_inria(f_dc: np.ndarray, f_rest: np.ndarray) -> np.ndarray:
    """f_dc (N, 3), f_rest (N, 3 (K-1)) channel-major -> features (N, 3 K) coefficient-major."""
    n, k = f_dc.shape[0], f_rest.shape[1] // 3 + 1
    coeffs = np.empty((n, k, 3), np.float64)
    coeffs[:, 0] = f_dc
    coeffs[:, 1:] = f_rest.reshape(n, 3, k - 1).transpose(0, 2, 1)
    return coeffs.reshape(n, 3 * k)


def sh_to_inria(features: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """features (N, 3 K) coefficient-major -> (f_dc (N, 3), f_rest (N, 3 (K-1)) channel-major)."""
    n, k = features.shape[0], features.shape[1] // 3
    coeffs = features.reshape(n, k, 3)
    return coeffs[:, 0], coeffs[:, 1:].transpose(0, 2, 1).reshape(n, 3 * (k - 1))


def import_3dgs_ply(path, fps: float = 30.0, num_frames: int = 1, cameras=None) -> Model:
    """A static 3DGS PLY (INRIA layout) -> a one-segment "sh" model without motion.

    Activations as in 3DGS: opacity = sigmoid(opacity), scale = exp(scale_i), rotation = normalised
    rot_0..3 (wxyz; a zero quaternion becomes the identity). Position and rotation degree 0, t_scale 0
    (constant opacity). The model covers `num_frames` frames at `fps` (every frame shows the same scene).
    cameras: a list of Camera, the path of a 3DGS `cameras.json`, or None to use the `cameras.json` of the
    3DGS output folder when there is one (beside the PLY, or two folders up as in
    `point_cloud/iteration_N/point_cloud.ply`). Raises PLYError naming the file for a malformed PLY.
    """
    name = os.fsdecode(path)
    props, count = read_ply(path)
    require(props, BASE, path)
    rest = sorted((p for p in props if p.startswith("f_rest_")), key=lambda p: (len(p), p))
    if len(rest) not in REST_DEGREES or rest != [f"f_rest_{i}" for i in range(len(rest))]:
        raise PLYError(f"{name}: {len(rest)} f_rest_* properties; expected f_rest_0.. with 0, 9, 24 or 45 "
                       "of them (SH degree 0, 1, 2 or 3)")
    values = float32_values(props, BASE + rest, path)

    def stack(names):
        return np.stack([values[p] for p in names], axis=1) if names else np.zeros((count, 0))

    with np.errstate(over="ignore"):
        opacity = 1.0 / (1.0 + np.exp(-values["opacity"]))
        scale = np.exp(stack(["scale_0", "scale_1", "scale_2"]))
    with np.errstate(over="ignore"):
        finite = np.all(np.isfinite(scale.astype(np.float32)))
    if not finite:
        raise PLYError(f"{name}: scale_* values too large (exp overflows float32)")
    quat = stack(["rot_0", "rot_1", "rot_2", "rot_3"])
    norm = np.linalg.norm(quat, axis=1, keepdims=True)
    quat = np.where(norm > 0, quat / np.where(norm > 0, norm, 1.0), [1.0, 0.0, 0.0, 0.0])
    features = sh_from_inria(stack(["f_dc_0", "f_dc_1", "f_dc_2"]), stack(rest))
    position = stack(["x", "y", "z"])
    segment = Segment(0, num_frames, opacity=opacity, t_center=np.zeros(count), t_scale=np.zeros(count),
                      position=position[:, None, :], rotation=quat[:, None, :], scale=scale, features=features)
    if cameras is None:
        found = find_cameras_json(path)
        cameras = read_cameras_json(found) if found else []
    elif isinstance(cameras, (str, os.PathLike)):
        cameras = read_cameras_json(cameras)
    bounds = (tuple(position.min(0).tolist()), tuple(position.max(0).tolist())) if count else None
    provenance = {"tool": "stg-convert import-3dgs", "source": Path(name).name,
                  "sh_degree": REST_DEGREES[len(rest)]}
    return Model("sh", fps, [segment], cameras=list(cameras), bounds=bounds, provenance=provenance)


def find_cameras_json(ply_path) -> Path | None:
    """The `cameras.json` of a 3DGS output folder holding `ply_path`, or None."""
    here = Path(ply_path).resolve().parent
    for folder in (here, here.parent.parent):
        if (folder / "cameras.json").is_file():
            return folder / "cameras.json"
    return None


def read_cameras_json(path) -> list[Camera]:
    """Cameras of a 3DGS `cameras.json`: a list of {img_name, width, height, position (camera centre),
    rotation (3x3 camera-to-world), fx, fy}; principal point at the image centre (3DGS's assumption)."""
    try:
        entries = json.loads(Path(path).read_text())
        cameras = []
        for e in entries:
            c2w = np.eye(4)
            c2w[:3, :3] = np.asarray(e["rotation"], dtype=np.float64).reshape(3, 3)
            c2w[:3, 3] = np.asarray(e["position"], dtype=np.float64).reshape(3)
            w, h = int(e["width"]), int(e["height"])
            cameras.append(Camera(e["fx"], e["fy"], w / 2, h / 2, w, h, np.linalg.inv(c2w),
                                  name=str(e.get("img_name", e.get("id", len(cameras))))))
        return cameras
    except (OSError, ValueError, KeyError, TypeError, np.linalg.LinAlgError) as e:
        raise ValueError(f"{os.fsdecode(path)}: not a readable 3DGS cameras.json ({type(e).__name__}: {e})") from None


def _logit(p: np.ndarray) -> np.ndarray:
    p = np.clip(p.astype(np.float64), OPACITY_EPS, 1.0 - OPACITY_EPS)
    return np.log(p) - np.log1p(-p)


def snapshot_colours(model: Model, segment: Segment, features: np.ndarray) -> np.ndarray:
    """Time-evaluated features (M, C) -> (M, 3 K) SH coefficients (coefficient-major) for a 3DGS viewer.

    sh: as they are. lite: rgb -> DC (rgb - 0.5) / C0 (3DGS clamps a Gaussian's colour at 0, so negative
    features become 0). full: the base rgb through the decoder's activation -> DC; the decoder's view- and
    time-dependent part cannot be expressed and is dropped (a warning says so).
    """
    if model.kind == "sh":
        return features
    rgb = features[:, :3].astype(np.float64)
    if model.kind == "full":
        warnings.warn("export-ply: a full model's colour decoder (view- and time-dependent colour) has no "
                      "3DGS equivalent; the snapshot keeps only each Gaussian's base colour", UserWarning,
                      stacklevel=3)
        if segment.activation == "sigmoid":
            rgb = 1.0 / (1.0 + np.exp(-rgb))
        elif segment.activation == "clamp":
            rgb = np.clip(rgb, 0.0, 1.0)
    return (rgb - 0.5) / C0


def export_ply(model: Model, path, t: float, min_opacity: float = MIN_ALPHA) -> int:
    """Write a static snapshot of `model` at time `t` (seconds) as a 3DGS PLY (INRIA layout); returns the
    number of Gaussians written.

    Positions, rotations and opacities are evaluated at t (stg_runtime.timeeval); Gaussians whose
    opacity at t is below `min_opacity` (default the renderers' 1/255 floor, below which they draw
    nothing) are left out. Stored raw values: logit(opacity), log(scale), unit quaternion wxyz. Colours:
    see snapshot_colours. The file is written atomically.
    """
    end = model.start_frame / model.fps + model.duration
    if not (model.start_frame / model.fps - 1e-9 <= t <= end + 1e-9):
        raise ValueError(f"t = {t} s is outside the model's time span [{model.start_frame / model.fps}, {end}] s")
    segment, tau = model.segment_at(t)
    g = evaluate(segment, tau, min_opacity=min_opacity)
    f_dc, f_rest = sh_to_inria(snapshot_colours(model, segment, g.features))
    m = g.index.shape[0]
    props = {"x": g.means[:, 0], "y": g.means[:, 1], "z": g.means[:, 2],
             "nx": np.zeros(m), "ny": np.zeros(m), "nz": np.zeros(m)}
    props.update({f"f_dc_{i}": f_dc[:, i] for i in range(3)})
    props.update({f"f_rest_{i}": f_rest[:, i] for i in range(f_rest.shape[1])})
    props["opacity"] = _logit(g.opacities)
    log_scale = np.log(np.maximum(g.scales.astype(np.float64), MIN_SCALE))
    props.update({f"scale_{i}": log_scale[:, i] for i in range(3)})
    props.update({f"rot_{i}": g.quats[:, i] for i in range(4)})
    write_ply(path, {k: np.asarray(v, dtype=np.float32) for k, v in props.items()})
    return m
