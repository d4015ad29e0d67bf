"""Procedural Spacetime Gaussian models: a built-in demo scene and benchmark scenes: random ones
(`random_model`: small footprints of fixed pixel size, about one layer per pixel) and ones that load a
splatter like a trained model (`like_trained_model`: footprints that scale with the image, dozens of
faint layers per pixel).

World frame: OpenCV-like, y down; the demo rig sits near the origin looking down +z.
"""
from __future__ import annotations

import numpy as np

from .camera import Camera
from .model import Model, Segment
from .onnx_mlp import mlp_to_onnx


def _logit(p):
    p = np.clip(p, 1e-4, 1 - 1e-4)
    return np.log(p / (1 - p))


def _fit_cubic(path, tau_samples, t_center):
    """Least-squares cubic coefficients (N, 4, 3) in (tau - t_center) for positions path (S, N, 3)."""
    d = tau_samples[:, None] - t_center[None, :]  # (S, N)
    basis = d[..., None] ** np.arange(4)  # (S, N, 4)
    coeffs = np.empty((path.shape[1], 4, 3))
    for i in range(path.shape[1]):
        coeffs[i], *_ = np.linalg.lstsq(basis[:, i], path[:, i], rcond=None)
    return coeffs


def demo_rig(width: int = 320, height: int = 240, rows: int = 3, cols: int = 3) -> list[Camera]:
    """A forward-facing grid of cameras 0.3 units apart, all looking at (0, 0, 6)."""
    cams = []
    for r in range(rows):
        for c in range(cols):
            eye = np.array([(c - (cols - 1) / 2) * 0.3, (r - (rows - 1) / 2) * 0.3, 0.0])
            cams.append(Camera.look_at(eye, [0, 0, 6.0], [0, -1, 0], 50.0, width, height, name=f"cam{len(cams):02d}"))
    return cams


def demo_model(kind: str = "full", fps: float = 30.0, num_frames: int = 60, seed: int = 0) -> Model:
    """A small dynamic scene: a patterned back wall, an orbiting ring of coloured blobs (cubic motion
    fitted to a circle), a propeller (polynomial rotation) and a ball that fades in and out
    (temporal opacity). The full model adds a view-dependent tint through its decoder."""
    rng = np.random.default_rng(seed)
    parts = []

    # Back wall: a 64 x 48 grid of flat Gaussians with a colourful pattern, static.
    gx, gy = np.meshgrid(np.linspace(-4, 4, 64), np.linspace(-3, 3, 48))
    n = gx.size
    pos = np.stack([gx.ravel(), gy.ravel(), np.full(n, 8.0)], 1)
    rgb = 0.5 + 0.5 * np.stack([np.sin(1.5 * gx), np.sin(1.3 * gy + 1), np.cos(gx + gy)], -1).reshape(-1, 3)
    rgb = 0.25 + 0.5 * rgb
    parts.append(dict(pos=pos, vel=None, rgb=rgb, scale=np.tile([0.09, 0.09, 0.01], (n, 1)),
                      opacity=np.full(n, 0.95), t_center=np.full(n, 0.5), t_scale=np.zeros(n)))

    # Orbiting ring of blobs around (0, 0, 5): circular motion fitted by a cubic around t_center.
    n = 400
    phase = rng.uniform(0, 2 * np.pi, n)
    radius = 1.2 + 0.1 * rng.standard_normal(n)
    tau = np.linspace(0, 1, 33)
    ang = phase[None, :] + 2 * np.pi * 0.5 * tau[:, None]  # half a turn over the segment
    path = np.stack([radius * np.cos(ang), 0.3 * np.sin(2 * ang), 5.0 + radius * np.sin(ang)], -1)
    t_c = np.full(n, 0.5)
    hue = (phase / (2 * np.pi))[:, None]
    rgb = 0.5 + 0.45 * np.cos(2 * np.pi * (hue + np.array([0, 1 / 3, 2 / 3])))
    parts.append(dict(pos=None, coeffs=_fit_cubic(path, tau, t_c), rgb=rgb,
                      scale=np.full((n, 3), 0.06), opacity=np.full(n, 0.9), t_center=t_c, t_scale=np.zeros(n)))

    # Propeller: three long Gaussians sharing a centre at (0, 0.9, 4), turning about the z axis through
    # their linear quaternions q(d) = c0 + c1 d (c1 is the tangent of a turn about z; spec: normalised).
    half = np.radians([0.0, 60.0, 120.0]) / 2
    c0 = np.stack([np.cos(half), 0 * half, 0 * half, np.sin(half)], 1)
    c1 = 3.0 * np.stack([-np.sin(half), 0 * half, 0 * half, np.cos(half)], 1)
    parts.append(dict(pos=np.tile([0.0, 0.9, 4.0], (3, 1)), rgb=np.tile([0.95, 0.85, 0.2], (3, 1)),
                      scale=np.tile([0.35, 0.025, 0.025], (3, 1)), opacity=np.full(3, 0.95),
                      t_center=np.full(3, 0.5), t_scale=np.zeros(3), rot=np.stack([c0, c1], 1)))

    # A ball that fades in and out around the middle of the clip.
    n = 300
    d = rng.standard_normal((n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    parts.append(dict(pos=np.array([0.0, -0.6, 4.5]) + 0.45 * d, rgb=np.tile([0.9, 0.2, 0.25], (n, 1)) + 0.05 * rng.standard_normal((n, 3)),
                      scale=np.full((n, 3), 0.07), opacity=np.full(n, 0.95), t_center=np.full(n, 0.5), t_scale=np.full(n, 40.0)))

    arrays = {k: [] for k in ("opacity", "t_center", "t_scale", "position", "rotation", "scale", "features")}
    for p in parts:
        n = p["rgb"].shape[0]
        coeffs = p.get("coeffs")
        if coeffs is None:
            coeffs = np.zeros((n, 4, 3))
            coeffs[:, 0] = p["pos"]
        rot = p.get("rot")
        if rot is None:
            rot = np.zeros((n, 2, 4))
            rot[:, 0, 0] = 1.0
        base = np.clip(p["rgb"], 0, 1)
        if kind == "full":
            feats = np.concatenate([_logit(base), 0.5 * rng.standard_normal((n, 3)), 0.5 * rng.standard_normal((n, 3))], 1)
        else:
            feats = base
        for k, v in (("opacity", p["opacity"]), ("t_center", p["t_center"]), ("t_scale", p["t_scale"]),
                     ("position", coeffs), ("rotation", rot), ("scale", p["scale"]), ("features", feats)):
            arrays[k].append(v)
    arrays = {k: np.concatenate(v) for k, v in arrays.items()}
    decoder = None
    if kind == "full":
        w1 = 0.6 * rng.standard_normal((6, 12))
        w2 = 0.4 * rng.standard_normal((3, 6))
        decoder = mlp_to_onnx([w1.astype(np.float32), w2.astype(np.float32)])
    seg = Segment(0, num_frames, decoder=decoder, activation="sigmoid", **arrays)
    return Model(kind, fps, [seg], cameras=demo_rig(), bounds=((-4.0, -3.0, 0.5), (4.0, 3.0, 8.1)),
                 provenance={"tool": "stg_runtime.demo", "settings": {"seed": seed}})


def _random_motion(rng: np.random.Generator, centres: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Random polynomial motion and rotation for Gaussians at `centres` (N, 3): position coefficients
    (N, 4, 3) (the centre, then 0.05 x normal ones) and rotation coefficients (N, 2, 4) (a normal
    quaternion, then 0.2 x a normal velocity), drawn from `rng` in that order."""
    n = len(centres)
    position = np.zeros((n, 4, 3))
    position[:, 0] = centres
    position[:, 1:] = 0.05 * rng.standard_normal((n, 3, 3))
    rotation = np.zeros((n, 2, 4))
    rotation[:, 0] = rng.standard_normal((n, 4))
    rotation[:, 1] = 0.2 * rng.standard_normal((n, 4))
    return position, rotation


def random_segment(num_gaussians: int, kind: str = "lite", seed: int = 0, num_frames: int = 50,
                   width: int = 640, height: int = 360, radius_px=(0.5, 10.0)) -> Segment:
    """A plausible random scene for benchmarks, seen by `bench_camera(width, height)` (at the origin,
    looking down +z, 60 degree horizontal field of view): Gaussians uniform in the volume of the frustum
    between depths 2 and 10, each with a projected 3-sigma radius log-uniform in `radius_px` pixels times
    a per-axis anisotropy in [0.5, 2], opacity uniform in [0.1, 0.9], random rotations, features uniform
    in [0, 1]. Over the clip they move a little (cubic motion, rotation velocity) and their temporal
    opacity varies mildly (t_scale <= 4), so almost all are visible at any time."""
    rng = np.random.default_rng(seed)
    n = num_gaussians
    fx = bench_camera(width, height).fx
    z = np.cbrt(rng.uniform(2.0 ** 3, 10.0 ** 3, n))  # uniform in volume: density ~ z^2
    x = rng.uniform(-1, 1, n) * z * (width / 2) / fx
    y = rng.uniform(-1, 1, n) * z * (height / 2) / fx
    sigma_px = np.exp(rng.uniform(np.log(radius_px[0]), np.log(radius_px[1]), n)) / 3.0
    scale = (sigma_px * z / fx)[:, None] * np.exp(rng.uniform(np.log(0.5), np.log(2.0), (n, 3)))
    position, rotation = _random_motion(rng, np.stack([x, y, z], 1))
    channels = 9 if kind == "full" else 3
    features = rng.uniform(0, 1, (n, channels))
    decoder = None
    if kind == "full":
        decoder = mlp_to_onnx([rng.standard_normal((6, 12)).astype(np.float32) * 0.3,
                               rng.standard_normal((3, 6)).astype(np.float32) * 0.3])
    return Segment(0, num_frames, opacity=rng.uniform(0.1, 0.9, n), t_center=rng.uniform(0, 1, n),
                   t_scale=rng.uniform(0, 4, n), position=position, rotation=rotation, scale=scale,
                   features=features, decoder=decoder, activation="sigmoid")


def bench_camera(width: int = 640, height: int = 360) -> Camera:
    """The benchmark camera: at the origin looking down +z, 60 degree horizontal field of view."""
    f = 0.5 * width / np.tan(np.radians(30.0))
    return Camera(f, f, width / 2, height / 2, width, height, np.eye(4), name="bench")


def random_model(num_gaussians: int, kind: str = "lite", seed: int = 0, width: int = 640, height: int = 360,
                 fps: float = 30.0, radius_px=(0.5, 10.0)) -> Model:
    """random_segment wrapped in a Model whose one camera is bench_camera(width, height)."""
    seg = random_segment(num_gaussians, kind, seed, width=width, height=height, radius_px=radius_px)
    return Model(kind, fps, [seg], cameras=[bench_camera(width, height)])


#: What like_trained_model copies from a trained model (the demo's, `stg-train --demo`: 32k Gaussians,
#: 1500 steps; its statistics are in docs/performance.md): Gaussians composited per pixel (their
#: summed footprints cover the image about this many times; few pixels stop, the Gaussians being
#: faint), the spread of the footprints' areas (log-normal: sigma of log area; the trained model's
#: tail is thinner than a log-normal's, so this is a compromise between its median and its mean), the
#: opacity's logit-normal distribution (mean, sigma) and the temporal scale's log-normal one
#: (median, sigma).
TRAINED_LAYERS = 50.0
TRAINED_AREA_SIGMA = 1.5
TRAINED_OPACITY_LOGIT = (-1.8, 1.95)
TRAINED_T_SCALE = (0.5, 2.8)
#: The fraction of the Gaussians gathered around _OBJECTS objects (the rest are uniform over the
#: image), which makes some pixels deeper than others, as in a trained model (99th percentile of the
#: layers about 1.6 times their mean).
TRAINED_CLUSTERED = 0.15
_OBJECTS = 8
#: Calibrated with render_load so that the layers per pixel come out at `layers`: the pixels a
#: Gaussian reaches (alpha >= 1/255 within 3 sigma, in the image) over pi sigma_px^2, averaged over the
#: scene's distributions, with the Gaussians that reach no pixel at the time counted in.
_AREA_PER_SIGMA2 = 6.9


def like_trained_segment(num_gaussians: int, width: int = 640, height: int = 360, kind: str = "lite",
                         seed: int = 0, num_frames: int = 50, layers: float = TRAINED_LAYERS) -> Segment:
    """A scene for benchmarks that loads a splatter like a trained model, seen by
    `bench_camera(width, height)`: centres uniform over the image (10 % beyond each edge) at depths
    uniform in [2, 10]; footprint areas log-normal (TRAINED_AREA_SIGMA), scaled so that the footprints
    of all Gaussians cover the image `layers` times: a fixed fraction of the image whatever its
    resolution (footprints grow with it) and smaller as the count grows (as a model trained with more
    Gaussians has smaller ones); opacities and temporal scales distributed as a trained model's
    (TRAINED_OPACITY_LOGIT, TRAINED_T_SCALE), temporal centres uniform; per-axis anisotropy in [0.5, 2],
    random rotations, a little motion. Features uniform in [0, 1] (3 lite, 9 full with a random
    decoder)."""
    rng = np.random.default_rng(seed)
    n = num_gaussians
    fx = bench_camera(width, height).fx
    z = rng.uniform(2.0, 10.0, n)
    u = rng.uniform(-0.05, 1.05, n)
    v = rng.uniform(-0.05, 1.05, n)
    objects = rng.uniform(size=n) < TRAINED_CLUSTERED  # the rest gathered around a few objects
    centres = rng.uniform(0.1, 0.9, (_OBJECTS, 2))[rng.integers(0, _OBJECTS, objects.sum())]
    u[objects], v[objects] = (centres + 0.08 * rng.standard_normal(centres.shape)).T
    u, v = u * width, v * height
    x = (u - width / 2) * z / fx
    y = (v - height / 2) * z / fx
    # Log-normal areas pi sigma_px^2 whose mean times n covers the image layers / _AREA_PER_SIGMA2 times.
    mean_sigma2 = layers * width * height / (n * np.pi * _AREA_PER_SIGMA2)
    log_area = rng.normal(0.0, TRAINED_AREA_SIGMA, n)
    sigma_px = np.sqrt(mean_sigma2 * np.exp(log_area - TRAINED_AREA_SIGMA ** 2 / 2))
    scale = (sigma_px * z / fx)[:, None] * np.exp(rng.uniform(np.log(0.5), np.log(2.0), (n, 3)))
    position, rotation = _random_motion(rng, np.stack([x, y, z], 1))
    mu, sd = TRAINED_OPACITY_LOGIT
    opacity = 1.0 / (1.0 + np.exp(-rng.normal(mu, sd, n)))
    t_scale = TRAINED_T_SCALE[0] * np.exp(rng.normal(0.0, TRAINED_T_SCALE[1], n))
    channels = 9 if kind == "full" else 3
    decoder = None
    if kind == "full":
        decoder = mlp_to_onnx([rng.standard_normal((6, 12)).astype(np.float32) * 0.3,
                               rng.standard_normal((3, 6)).astype(np.float32) * 0.3])
    return Segment(0, num_frames, opacity=opacity, t_center=rng.uniform(0, 1, n), t_scale=t_scale,
                   position=position, rotation=rotation, scale=scale, features=rng.uniform(0, 1, (n, channels)),
                   decoder=decoder, activation="sigmoid")


def like_trained_model(num_gaussians: int, width: int = 640, height: int = 360, kind: str = "lite",
                       seed: int = 0, fps: float = 30.0, layers: float = TRAINED_LAYERS) -> Model:
    """like_trained_segment wrapped in a Model whose one camera is bench_camera(width, height)."""
    seg = like_trained_segment(num_gaussians, width, height, kind, seed, layers=layers)
    return Model(kind, fps, [seg], cameras=[bench_camera(width, height)])
