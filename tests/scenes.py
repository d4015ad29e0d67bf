"""Random test scenes shared by the splatter tests (CPU, GPU, torch), with their float64 oracle renders."""
from __future__ import annotations

import numpy as np

from stg_runtime.camera import Camera
from stg_runtime.spec import rasterize_oracle


def _random_rotation(rng):
    q = rng.normal(size=4)
    w, x, y, z = q / np.linalg.norm(q)
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                     [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                     [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


def random_scene(rng, m, width, height, channels, opacity=(0.0, 1.0), size=(0.2, 6.0)):
    """m Gaussians seen by a randomly posed camera with an off-centre principal point: most in front,
    some behind the camera, some at the near plane, some mostly outside the image; opacities uniform
    in `opacity`, standard deviations log-uniform in `size` pixels (at their depth), per axis.
    float32 arrays."""
    fx = rng.uniform(0.8, 1.2) * width
    fy = fx * rng.uniform(0.9, 1.1)
    cx = width * rng.uniform(0.35, 0.65)
    cy = height * rng.uniform(0.35, 0.65)
    R = _random_rotation(rng)
    eye = rng.normal(size=3)
    w2c = np.eye(4)
    w2c[:3, :3] = R
    w2c[:3, 3] = -R @ eye
    camera = Camera(fx, fy, cx, cy, width, height, w2c)
    z = rng.uniform(0.5, 6.0, m)
    kind = rng.uniform(size=m)
    z[kind < 0.1] = rng.uniform(-3.0, -0.01, (kind < 0.1).sum())  # behind the camera
    near = (kind >= 0.1) & (kind < 0.15)
    z[near] = rng.uniform(0.0, 0.03, near.sum())  # around the near plane (0.01)
    u = rng.uniform(-0.3, 1.3, m) * width  # some centres outside the image
    v = rng.uniform(-0.3, 1.3, m) * height
    p_cam = np.stack([(u - cx) / fx * np.abs(z), (v - cy) / fy * np.abs(z), z], axis=1)
    means = (p_cam - w2c[:3, 3]) @ R  # R^T (p - t)
    pixel_size = np.abs(z) / fx  # world size of a pixel at that depth
    scales = pixel_size[:, None] * np.exp(rng.uniform(np.log(size[0]), np.log(size[1]), (m, 3)))
    quats = rng.normal(size=(m, 4)) * rng.uniform(0.5, 2.0, (m, 1))  # not unit length
    opacities = rng.uniform(*opacity, m)
    features = rng.uniform(-1.0, 1.0, (m, channels))
    f32 = lambda a: np.ascontiguousarray(a, dtype=np.float32)  # noqa: E731
    return (f32(means), f32(quats), f32(scales), f32(opacities), f32(features)), camera


def clean_scenes(seed, count, m, width, height, channels, **kwargs):
    """`count` random scenes (random_scene(..., **kwargs)) whose oracle render takes no decision
    within float32 rounding of its threshold (see rasterize_oracle's margins), with the
    oracle's images. The few scenes that do (a few percent) are discarded."""
    rng = np.random.default_rng(seed)
    scenes = []
    for _ in range(20 * count):
        arrays, camera = random_scene(rng, m, width, height, channels, **kwargs)
        margins = {}
        ref = rasterize_oracle(*arrays, camera, margins=margins)
        if (margins["footprint"] > 1e-6 and margins["power"] > 1e-5 and margins["alpha"] > 1e-5
                and margins["stop"] > 1e-4):
            scenes.append((arrays, camera, ref))
            if len(scenes) == count:
                return scenes
    raise AssertionError("could not draw clean random scenes")
