"""Cameras in the OpenCV convention (x right, y down, z forward), world-to-camera poses, and camera
paths (an orbit around a rig; camera-path JSON files, a list of camera objects).

Two camera models (formats/stg-v1.md, section 1): `pinhole` and `fisheye` (OpenCV's fisheye model,
Kannala-Brandt with k1..k4). Pixel (column u, row v) has its centre at (u + 0.5, v + 0.5).
"""
from __future__ import annotations

import json
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Sequence

import numpy as np

from .atomic import write_atomic


MODELS = ("pinhole", "fisheye")


def fisheye_distort(theta, k) -> np.ndarray:
    """theta_d = theta (1 + k1 theta^2 + k2 theta^4 + k3 theta^6 + k4 theta^8): the fisheye model's
    distorted angle (radians; the image radius is f * theta_d) for angles `theta` (radians) off the axis."""
    t2 = np.square(theta)
    return theta * (1 + t2 * (k[0] + t2 * (k[1] + t2 * (k[2] + t2 * k[3]))))


def fisheye_max_angle(k) -> float:
    """The largest angle off the axis (radians, at most pi) up to which theta_d(theta) is increasing:
    the first zero of d theta_d / d theta = 1 + 3 k1 theta^2 + 5 k2 theta^4 + 7 k3 theta^6 + 9 k4 theta^8,
    or pi. A fisheye camera sees (and splatters draw) only what lies within it (spec section 3)."""
    roots = np.roots([9 * k[3], 0, 7 * k[2], 0, 5 * k[1], 0, 3 * k[0], 0, 1.0])
    real = roots[(np.abs(roots.imag) < 1e-12) & (roots.real > 0)].real
    return float(min(real.min(initial=np.pi), np.pi))


def fisheye_undistort(theta_d, k, max_angle: float, iterations: int = 10) -> np.ndarray:
    """The angles theta (radians, in [0, max_angle]) with fisheye_distort(theta, k) = theta_d: Newton's
    method from theta = theta_d, `iterations` steps, each clamped to [0, max_angle] (beyond the image
    circle, theta_d > fisheye_distort(max_angle), the answer is max_angle)."""
    theta_d = np.asarray(theta_d, dtype=np.float64)
    theta = np.clip(theta_d, 0.0, max_angle)
    for _ in range(iterations):
        t2 = theta * theta
        slope = 1 + t2 * (3 * k[0] + t2 * (5 * k[1] + t2 * (7 * k[2] + t2 * 9 * k[3])))
        step = (fisheye_distort(theta, k) - theta_d) / np.where(slope > 0, slope, 1.0)
        theta = np.clip(theta - np.where(slope > 0, step, 0.0), 0.0, max_angle)
    return theta


@dataclass(frozen=True, eq=False)
class Camera:
    """A camera: pinhole (the default) or fisheye.

    fx, fy, cx, cy: intrinsics in pixels; width, height: image size in pixels;
    world_to_camera: (4, 4) float64 rigid transform, x_cam = R @ x_world + t;
    model: "pinhole" or "fisheye"; distortion: () for pinhole, (k1, k2, k3, k4) for fisheye (OpenCV's
    cv2.fisheye coefficients; the default is the equidistant fisheye, all zero).
    """

    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int
    world_to_camera: np.ndarray = field(repr=False)
    name: str = ""
    model: str = "pinhole"
    distortion: tuple = ()

    def __post_init__(self):
        w2c = np.array(self.world_to_camera, dtype=np.float64).reshape(4, 4)
        w2c.setflags(write=False)
        object.__setattr__(self, "world_to_camera", w2c)
        object.__setattr__(self, "width", int(self.width))
        object.__setattr__(self, "height", int(self.height))
        for name in ("fx", "fy", "cx", "cy"):
            object.__setattr__(self, name, float(getattr(self, name)))
        if self.width <= 0 or self.height <= 0:
            raise ValueError(f"camera {self.name!r}: image size must be positive, got {self.width}x{self.height}")
        if not (self.fx > 0 and self.fy > 0):
            raise ValueError(f"camera {self.name!r}: focal lengths must be positive, got fx={self.fx}, fy={self.fy}")
        if not np.all(np.isfinite(w2c)):
            raise ValueError(f"camera {self.name!r}: world_to_camera has non-finite entries")
        if self.model not in MODELS:
            raise ValueError(f"camera {self.name!r}: unknown camera model {self.model!r} (known: {', '.join(MODELS)})")
        k = tuple(float(v) for v in self.distortion)
        if self.model == "fisheye" and not k:
            k = (0.0, 0.0, 0.0, 0.0)
        expected = 4 if self.model == "fisheye" else 0
        if len(k) != expected or not np.all(np.isfinite(k)):
            raise ValueError(f"camera {self.name!r}: a {self.model} camera takes {expected} finite distortion "
                             f"coefficients, got {list(self.distortion)}")
        object.__setattr__(self, "distortion", k)

    def __eq__(self, other) -> bool:
        return isinstance(other, Camera) and self.to_dict() == other.to_dict()

    __hash__ = None

    # -- constructors -------------------------------------------------------------------------
    @classmethod
    def from_colmap(cls, K, world_to_camera, width: int, height: int, name: str = "") -> "Camera":
        """From a 3x3 intrinsic matrix K in this project's (and COLMAP's, and gsplat's) convention, the
        centre of pixel (column u, row v) at (u + 0.5, v + 0.5), and a 4x4 (or 3x4) world-to-camera
        matrix (OpenCV axes). K's numbers are kept as they are."""
        K = np.asarray(K, dtype=np.float64)
        w2c = np.eye(4)
        w2c[: np.shape(world_to_camera)[0]] = np.asarray(world_to_camera, dtype=np.float64)
        return cls(K[0, 0], K[1, 1], K[0, 2], K[1, 2], width, height, w2c, name)

    @classmethod
    def from_opencv(cls, K, world_to_camera, width: int, height: int, name: str = "") -> "Camera":
        """From an OpenCV calibration (calibrateCamera, solvePnP): a 3x3 intrinsic matrix K whose pixel
        centres are at integers, converted to this project's convention (cx + 0.5, cy + 0.5), and a 4x4
        (or 3x4) world-to-camera matrix (x right, y down, z forward)."""
        camera = cls.from_colmap(K, world_to_camera, width, height, name)
        return cls(camera.fx, camera.fy, camera.cx + 0.5, camera.cy + 0.5, width, height,
                   camera.world_to_camera, name)

    @classmethod
    def look_at(cls, eye, target, up, fov_deg: float, width: int, height: int, name: str = "",
                model: str = "pinhole") -> "Camera":
        """A camera at `eye` looking at `target`; `up` is the world direction that appears up in the
        image; `fov_deg` is the vertical field of view in degrees; principal point at the image centre.
        model "fisheye" gives an equidistant fisheye (k = 0: image radius = f x angle), so fov_deg may
        reach 360 (the image's top and bottom edges at fov_deg / 2 off the axis)."""
        eye, target, up = (np.asarray(v, dtype=np.float64) for v in (eye, target, up))
        forward = target - eye
        if np.linalg.norm(forward) == 0:
            raise ValueError("look_at: eye and target coincide")
        z = forward / np.linalg.norm(forward)
        x = np.cross(z, up)  # right = forward x up (image y points down)
        if np.linalg.norm(x) < 1e-12:
            raise ValueError("look_at: up is parallel to the viewing direction")
        x /= np.linalg.norm(x)
        y = np.cross(z, x)
        R = np.stack([x, y, z])
        w2c = np.eye(4)
        w2c[:3, :3] = R
        w2c[:3, 3] = -R @ eye
        half = np.radians(fov_deg) / 2
        f = 0.5 * height / (half if model == "fisheye" else np.tan(half))
        return cls(f, f, width / 2, height / 2, width, height, w2c, name, model)

    # -- derived quantities ---------------------------------------------------------------------
    @property
    def R(self) -> np.ndarray:
        """(3, 3) world-to-camera rotation."""
        return self.world_to_camera[:3, :3]

    @property
    def t(self) -> np.ndarray:
        """(3,) world-to-camera translation."""
        return self.world_to_camera[:3, 3]

    @property
    def center(self) -> np.ndarray:
        """(3,) camera centre in world coordinates."""
        return -self.R.T @ self.t

    @property
    def K(self) -> np.ndarray:
        """(3, 3) intrinsic matrix."""
        return np.array([[self.fx, 0, self.cx], [0, self.fy, self.cy], [0, 0, 1.0]])

    def resized(self, width: int, height: int) -> "Camera":
        """The same camera with the image scaled to width x height (intrinsics scaled to match)."""
        sx, sy = width / self.width, height / self.height
        return Camera(self.fx * sx, self.fy * sy, self.cx * sx, self.cy * sy, width, height,
                      self.world_to_camera, self.name, self.model, self.distortion)

    @property
    def max_angle(self) -> float:
        """The largest angle off the optical axis (radians) the camera sees: for a fisheye, where its
        distortion stops increasing (fisheye_max_angle; pi when it never does); for a pinhole, pi / 2."""
        return fisheye_max_angle(self.distortion) if self.model == "fisheye" else np.pi / 2

    @property
    def vertical_fov(self) -> float:
        """The vertical field of view (radians) of the camera with its principal point centred: twice
        the angle off the axis of the middle of the top edge (for a fisheye, it may exceed pi)."""
        half = 0.5 * self.height / self.fy
        if self.model == "fisheye":
            return 2.0 * float(fisheye_undistort(half, self.distortion, self.max_angle))
        return 2.0 * float(np.arctan(half))

    def project(self, points) -> tuple[np.ndarray, np.ndarray]:
        """World points (..., 3) -> (pixel coordinates (..., 2) as (u, v), camera-space depth (...,)).

        Continuous coordinates: the pixel of column c, row r covers [c, c+1) x [r, r+1). Points at or
        behind the camera plane (depth <= 0) get meaningless coordinates: check the depth."""
        p = np.asarray(points, dtype=np.float64) @ self.R.T + self.t
        x, y, z = p[..., 0], p[..., 1], p[..., 2]
        if self.model == "fisheye":
            r = np.hypot(x, y)
            theta_d = fisheye_distort(np.arctan2(r, z), self.distortion)
            scale = np.where(r > 0, theta_d / np.where(r > 0, r, 1.0), 1.0 / np.where(z > 0, z, 1.0))
        else:
            scale = 1.0 / np.where(z > 0, z, 1.0)
        return np.stack([self.fx * x * scale + self.cx, self.fy * y * scale + self.cy], -1), z

    def camera_rays(self, u, v) -> np.ndarray:
        """(..., 3) float64 unit directions in camera space through image points (u, v) (continuous
        coordinates, arrays broadcast). A fisheye's points beyond its image circle get the direction at
        max_angle (fisheye_undistort)."""
        u, v = np.broadcast_arrays(*(np.asarray(a, dtype=np.float64) for a in (u, v)))
        mx, my = (u - self.cx) / self.fx, (v - self.cy) / self.fy
        if self.model == "fisheye":
            theta_d = np.hypot(mx, my)
            theta = fisheye_undistort(theta_d, self.distortion, self.max_angle)
            s = np.where(theta_d > 0, np.sin(theta) / np.where(theta_d > 0, theta_d, 1.0), 1.0)
            return np.stack([mx * s, my * s, np.cos(theta)], -1)
        d = np.stack([mx, my, np.ones_like(mx)], -1)
        return d / np.linalg.norm(d, axis=-1, keepdims=True)

    def unproject(self, u, v, depth) -> np.ndarray:
        """World points (..., 3) at camera-space depth `depth` (z, not distance) on the rays through image
        points (u, v) (continuous coordinates; a pixel centre is (column + 0.5, row + 0.5)); arrays
        broadcast. A fisheye ray at or beyond 90 degrees off the axis has no point at depth > 0: its
        points are non-finite."""
        u, v, depth = np.broadcast_arrays(*(np.asarray(a, dtype=np.float64) for a in (u, v, depth)))
        if self.model == "fisheye":
            d = self.camera_rays(u, v)
            with np.errstate(divide="ignore", invalid="ignore"):
                x_cam = d * (depth / np.where(d[..., 2] > 0, d[..., 2], np.nan))[..., None]
        else:
            x_cam = np.stack([(u - self.cx) / self.fx * depth, (v - self.cy) / self.fy * depth, depth], -1)
        return (x_cam - self.t) @ self.R  # R^T (x - t)

    def ray_directions(self) -> np.ndarray:
        """(H, W, 3) float64 unit directions, in world coordinates, through every pixel centre."""
        u = np.arange(self.width) + 0.5
        v = np.arange(self.height) + 0.5
        return self.camera_rays(u[None, :], v[:, None]) @ self.R  # row vector form of R^T d

    # -- serialisation (used by the file format and camera-path files) --------------------------
    def to_dict(self) -> dict:
        """The camera object of formats/stg-v1.md, section 4: a pinhole's intrinsics at the top level,
        a fisheye's (with k1..k4) under "intrinsics" beside "model": "fisheye"."""
        w2c = [float(v) for v in self.world_to_camera.ravel()]
        intrinsics = {"fx": self.fx, "fy": self.fy, "cx": self.cx, "cy": self.cy}
        if self.model == "pinhole":
            return {"name": self.name, "width": self.width, "height": self.height, **intrinsics,
                    "world_to_camera": w2c}
        intrinsics.update(zip(("k1", "k2", "k3", "k4"), self.distortion))
        return {"name": self.name, "width": self.width, "height": self.height, "model": self.model,
                "intrinsics": intrinsics, "world_to_camera": w2c}

    @classmethod
    def from_dict(cls, d: dict) -> "Camera":
        """The inverse of to_dict; KeyError, TypeError or ValueError for a malformed object (an unknown
        model is a ValueError naming it)."""
        model = d["model"] if "model" in d else "pinhole"
        if model not in MODELS:
            raise ValueError(f"unknown camera model {model!r} (this reader knows {', '.join(MODELS)})")
        w2c = np.asarray(d["world_to_camera"], dtype=np.float64).reshape(4, 4)
        if model == "pinhole":
            return cls(d["fx"], d["fy"], d["cx"], d["cy"], d["width"], d["height"], w2c, d.get("name", ""))
        i = d["intrinsics"]
        return cls(i["fx"], i["fy"], i["cx"], i["cy"], d["width"], d["height"], w2c, d.get("name", ""), model,
                   tuple(i[k] for k in ("k1", "k2", "k3", "k4")))


def orbit(cameras, num_frames: int, target=None, radius=None, width=None, height=None) -> list[Camera]:
    """A closed circular camera path of `num_frames` views around the mean of `cameras`.

    The circle lies in the plane orthogonal to the rig's mean viewing direction, centred on the mean
    camera centre (the usual orbit for forward-facing rigs); every view looks at `target`, by default a
    point in front of the rig at 4x the rig's spread (at least 1 unit). `radius` defaults to the rig's
    mean spread, at least 5% of the distance to the target. Intrinsics follow the first camera, resized
    to width x height when given (a fisheye rig's orbit has the first camera's lens).
    """
    cameras = list(cameras)
    if not cameras:
        raise ValueError("orbit: no cameras")
    base = cameras[0] if width is None else cameras[0].resized(width, height or round(width * cameras[0].height / cameras[0].width))
    centers = np.stack([c.center for c in cameras])
    mid = centers.mean(axis=0)
    forward = np.mean([c.R[2] for c in cameras], axis=0)
    forward /= np.linalg.norm(forward)
    down = np.mean([c.R[1] for c in cameras], axis=0)
    if target is None:
        target = mid + forward * max(1.0, 4 * np.linalg.norm(centers - mid, axis=1).max())
    target = np.asarray(target, dtype=np.float64)
    dist = np.linalg.norm(target - mid)
    if radius is None:
        radius = max(np.linalg.norm(centers - mid, axis=1).mean(), 0.05 * dist)
    right = np.cross(down, forward)
    right /= np.linalg.norm(right)
    up_axis = np.cross(forward, right)
    fov = np.degrees(2 * np.arctan(0.5 * base.height / base.fy))
    path = []
    for i in range(num_frames):
        a = 2 * np.pi * i / num_frames
        eye = mid + radius * (np.cos(a) * right + np.sin(a) * up_axis)
        cam = Camera.look_at(eye, target, -down, fov, base.width, base.height, name=f"orbit{i:04d}")
        if base.model != "pinhole":  # the same lens, posed
            cam = replace(base, world_to_camera=cam.world_to_camera, name=cam.name)
        path.append(cam)
    return path


#: The largest image side a camera-path camera may have (pixels).
MAX_PATH_SIDE = 16384


class CameraPathError(ValueError):
    """A camera-path file that is not one; the message names the file, the camera index and the field."""


def load_camera_path(path) -> list[Camera]:
    """Cameras from a camera-path JSON file: a non-empty list of camera objects (formats/stg-v1.md,
    section 4; docs/render.md has the schema and an example). CameraPathError (a ValueError) naming the
    file, the camera's index and the field when it is not one: a missing or mistyped field, a size or
    focal length that is not a positive number, a world_to_camera that is not a rigid 4x4 transform."""
    try:
        text = Path(path).read_text()
    except OSError as e:
        raise CameraPathError(f"{path}: cannot read it ({e.strerror or e})") from None
    except UnicodeDecodeError:
        raise CameraPathError(f"{path}: not a camera path: not a text (JSON) file") from None
    try:
        data = json.loads(text)
    except ValueError as e:
        raise CameraPathError(f"{path}: not a camera path: invalid JSON ({e})") from None
    if not isinstance(data, list) or not data:
        got = "an empty list" if data == [] else f"a JSON {type(data).__name__.replace('dict', 'object')}"
        raise CameraPathError(f"{path}: a camera path is a non-empty JSON list of camera objects, got {got}")
    cameras = []
    for i, entry in enumerate(data):
        try:
            cameras.append(camera_from_object(entry))
        except ValueError as e:
            raise CameraPathError(f"{path}: camera {i}: {e}") from None
    return cameras


def _number(d: dict, key: str, where: str = "", positive: bool = False) -> float:
    if key not in d:
        raise ValueError(f'{where}"{key}" is missing')
    value = d[key]
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not np.isfinite(value):
        raise ValueError(f'{where}"{key}" must be a {"positive " if positive else ""}number, got {json.dumps(value)}')
    if positive and not value > 0:
        raise ValueError(f'{where}"{key}" must be a positive number, got {json.dumps(value)}')
    return float(value)


def _side(d: dict, key: str) -> int:
    value = d.get(key)
    if key not in d:
        raise ValueError(f'"{key}" is missing')
    if isinstance(value, bool) or not isinstance(value, int) or not 1 <= value <= MAX_PATH_SIDE:
        raise ValueError(f'"{key}" must be a whole number of pixels, 1..{MAX_PATH_SIDE}, got {json.dumps(value)}')
    return value


def _rigid(value) -> np.ndarray:
    """A world_to_camera value (16 numbers, row-major, or 4 rows of 4) -> (4, 4), or ValueError."""
    try:
        ok = not isinstance(value, (str, bytes, dict)) and all(
            not isinstance(v, bool) and isinstance(v, (int, float))
            for v in np.asarray(value, dtype=object).ravel())
        m = np.asarray(value, dtype=np.float64) if ok else None
    except (ValueError, TypeError):
        m = None
    if m is None or m.size != 16 or m.shape not in ((16,), (4, 4)):
        raise ValueError(f'"world_to_camera" must be 16 numbers (a row-major 4x4 matrix, or 4 rows of 4), got '
                         f"{json.dumps(value)[:80]}")
    m = m.reshape(4, 4)
    if not np.all(np.isfinite(m)):
        raise ValueError('"world_to_camera" has a non-finite entry')
    if np.abs(m[3] - [0, 0, 0, 1]).max() > 1e-9:
        raise ValueError(f'"world_to_camera": the last row must be 0 0 0 1, got {m[3].tolist()}')
    r = m[:3, :3]
    if np.abs(r @ r.T - np.eye(3)).max() > 1e-4 or np.linalg.det(r) <= 0:
        raise ValueError('"world_to_camera": the upper-left 3x3 block must be a rotation (orthonormal within 1e-4, '
                         f"determinant +1; scale or mirroring is not a camera pose), got {np.round(r, 6).tolist()}")
    return m


def camera_from_object(d) -> Camera:
    """A Camera from one camera object of a camera path (formats/stg-v1.md, section 4), checked field by
    field; ValueError naming the field otherwise."""
    if not isinstance(d, dict):
        raise ValueError(f"expected a camera object {{\"width\": ..., \"fx\": ..., ...}}, got {json.dumps(d)[:60]}")
    model = d.get("model", "pinhole")
    if model not in MODELS:
        raise ValueError(f'"model" must be one of {", ".join(MODELS)}, got {json.dumps(model)}')
    name = d.get("name", "")
    if not isinstance(name, str):
        raise ValueError(f'"name" must be a string, got {json.dumps(name)}')
    width, height = _side(d, "width"), _side(d, "height")
    if "world_to_camera" not in d:
        raise ValueError('"world_to_camera" is missing')
    w2c = _rigid(d["world_to_camera"])
    if model == "pinhole":
        i, where = d, ""
    else:
        i, where = d.get("intrinsics"), "intrinsics: "
        if not isinstance(i, dict):
            raise ValueError(f'"intrinsics" must be an object with fx, fy, cx, cy, k1..k4 (fisheye), got {json.dumps(i)}')
    fx, fy = _number(i, "fx", where, positive=True), _number(i, "fy", where, positive=True)
    cx, cy = _number(i, "cx", where), _number(i, "cy", where)
    if model == "pinhole":
        return Camera(fx, fy, cx, cy, width, height, w2c, name)
    k = tuple(_number(i, key, where) for key in ("k1", "k2", "k3", "k4"))
    return Camera(fx, fy, cx, cy, width, height, w2c, name, model, k)


def save_camera_path(path, cameras: Sequence[Camera]) -> None:
    """Write `cameras` as a camera-path JSON file (see load_camera_path)."""
    write_atomic(path, camera_path_json(cameras))


def camera_path_json(cameras: Sequence[Camera]) -> str:
    """The text of a camera-path JSON file of `cameras` (see load_camera_path)."""
    return json.dumps([c.to_dict() for c in cameras], indent=1)
