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


def _random_pose(rng):
    """A random (4, 4) world-to-camera transform: random rotation, camera centre ~ N(0, 1)."""
    R = _random_rotation(rng)
    eye = rng.normal(size=3)
    w2c = np.eye(4)
    w2c[:3, :3] = R
    w2c[:3, 3] = -R @ eye
    return w2c


def random_scene(rng, m, width, height, channels, opacity=(0.0, 1.0), size=(0.2, 6.0), fisheye=None):
    """m Gaussians seen by a randomly posed camera with an off-centre principal point: most in front,
    some behind the camera, some at the near plane, some mostly outside the image; opacities uniform
    in `opacity`, standard deviations log-uniform in `size` pixels (at their depth), per axis.
    fisheye=HFOV (degrees) makes the camera a fisheye of about that horizontal field of view with random
    small k1..k4, and spreads the Gaussians over every direction up to 100 degrees off its axis (see
    random_fisheye_points). float32 arrays."""
    if fisheye is not None:
        camera = _random_fisheye(rng, width, height, fisheye, _random_pose(rng))
        p_cam, pixel_size = random_fisheye_points(rng, m, camera)
        return _gaussians(rng, camera, p_cam, pixel_size, channels, opacity, size), camera
    fx = rng.uniform(0.8, 1.2) * width
    fy = fx * rng.uniform(0.9, 1.1)
    cx = width * rng.uniform(0.35, 0.65)
    cy = height * rng.uniform(0.35, 0.65)
    camera = Camera(fx, fy, cx, cy, width, height, _random_pose(rng))
    z = rng.uniform(0.5, 6.0, m)
    kind = rng.uniform(size=m)
    z[kind < 0.1] = rng.uniform(-3.0, -0.01, (kind < 0.1).sum())  # behind the camera
    near = (kind >= 0.1) & (kind < 0.15)
    z[near] = rng.uniform(0.0, 0.03, near.sum())  # around the near plane (0.01)
    u = rng.uniform(-0.3, 1.3, m) * width  # some centres outside the image
    v = rng.uniform(-0.3, 1.3, m) * height
    p_cam = np.stack([(u - cx) / fx * np.abs(z), (v - cy) / fy * np.abs(z), z], axis=1)
    pixel_size = np.abs(z) / fx  # world size of a pixel at that depth
    return _gaussians(rng, camera, p_cam, pixel_size, channels, opacity, size), camera


def _random_fisheye(rng, width, height, hfov, w2c):
    """A fisheye camera of about `hfov` degrees across its width, off-centre, with small k1..k4."""
    fx = 0.5 * width / np.radians(0.5 * hfov) * rng.uniform(0.95, 1.05)
    fy = fx * rng.uniform(0.95, 1.05)
    k = rng.uniform(-1, 1, 4) * [0.05, 0.01, 0.002, 0.0005]
    return Camera(fx, fy, width * rng.uniform(0.4, 0.6), height * rng.uniform(0.4, 0.6), width, height, w2c,
                  model="fisheye", distortion=k)


def random_fisheye_points(rng, m, camera):
    """(m, 3) camera-space points in every direction up to 100 degrees off the axis (a tenth of them
    between 85 and 95 degrees, straddling the image plane's edge z = 0), at distances 0.5 to 6, and the
    world size of a pixel at each (distance / fx)."""
    theta = np.radians(rng.uniform(0, 100, m))
    edge = rng.uniform(size=m) < 0.1
    theta[edge] = np.radians(rng.uniform(85, 95, edge.sum()))
    phi = rng.uniform(0, 2 * np.pi, m)
    dist = rng.uniform(0.5, 6.0, m)
    p_cam = dist[:, None] * np.stack([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), np.cos(theta)], 1)
    return p_cam, dist / camera.fx


def _gaussians(rng, camera, p_cam, pixel_size, channels, opacity, size):
    """float32 (means, quats, scales, opacities, features) for Gaussians at camera-space p_cam (m, 3)
    with standard deviations log-uniform in `size` x pixel_size (m,) world units."""
    m = len(p_cam)
    means = (p_cam - camera.t) @ camera.R  # R^T (p - t)
    scales = pixel_size[:, None] * np.exp(rng.uniform(np.log(size[0]), np.log(size[1]), (m, 3)))
    quats = rng.normal(size=(m, 4)) * rng.uniform(0.5, 2.0, (m, 1))  # not unit length
    opacities = rng.uniform(*opacity, m)
    features = rng.uniform(-1.0, 1.0, (m, channels))
    f32 = lambda a: np.ascontiguousarray(a, dtype=np.float32)  # noqa: E731
    return f32(means), f32(quats), f32(scales), f32(opacities), f32(features)


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
