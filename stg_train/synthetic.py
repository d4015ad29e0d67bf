"""A small dynamic scene, ray traced analytically (numpy, vectorised over pixels), and writers of the
Neural 3D Video (N3V) layout (a forward-facing pinhole rig) and of the Google Immersive layout (an
outward-facing dome of fisheye, or pinhole, cameras) for it. Used by tests, demos and benchmarks in
place of real datasets.

This is not Gaussian splatting: every pixel centre casts one ray (or `supersample**2` rays) that is
intersected exactly with the scene's primitives.

World axes follow OpenCV (x right, y down, z forward, away from the rig), so cam00 sits at the origin
with a world_to_camera close to the identity. Units are arbitrary ("units"); time t is in seconds.

The scene (layout 0; `seed` only changes the procedural textures and colours, `layout` 1 is a second
object set: other positions, sizes, path and speeds, for measurements on a scene nothing was tuned on):
  - a room, the box [-3, 3] x [-2, 1.5] x [-1, 7] seen from inside: textured back wall (checkers and
    noise), floor (tiles and wood-like stripes), side walls (stripes and noise), ceiling (noise);
  - "static_box": a textured cube on the floor;
  - "shiny_sphere": a static sphere with a Blinn-Phong highlight (view-dependent colour);
  - "moving_sphere": a checkered sphere moving on a smooth closed path (period 3 s);
  - "rotating_box": a checkered box spinning about the vertical axis (1.2 rad/s);
  - "fader": a sphere that fades in at 25-35% of `duration` and out at 65-75% (opacity in [0, 1]).
Shading: Lambertian under one point light plus ambient, with shadows cast by the objects; the image
then goes through a small Gaussian "lens" blur (`blur`, 1 px by default).
"""
from __future__ import annotations

import json
import re
from pathlib import Path

import cv2
import numpy as np

from stg_runtime.atomic import write_atomic
from stg_runtime.camera import Camera, fisheye_distort

from .data.dataset import Dataset
from .data.immersive import MODELS_FILE, entry_from_camera

__all__ = ["SyntheticScene", "write_n3v", "write_immersive", "OBJECT_NAMES", "llff_pose", "NOVEL_VIEWS",
           "novel_view_dataset"]

#: Rig positions (x, y world units from cam00) of two novel views inside the default 12-camera rig
#: (which spans x in [-0.8, 0.8], y in [-0.3, 0.3]), between its cameras.
NOVEL_VIEWS = ((0.2, 0.15), (-0.6, -0.15))

#: Object names in id order (`SyntheticScene.object_ids` returns these indices; -1 is the room).
OBJECT_NAMES = ("static_box", "shiny_sphere", "moving_sphere", "rotating_box", "fader")

ROOM_MIN = np.array([-3.0, -2.0, -1.0])
ROOM_MAX = np.array([3.0, 1.5, 7.0])
LIGHT = np.array([-1.2, -1.7, 1.8])  # point light position (world)
AMBIENT, DIFFUSE = 0.3, 0.75
TARGET = np.array([0.0, 0.3, 4.0])  # where every rig camera looks
#: The dome rig (SyntheticScene.dome_cameras): its sphere's centre and radius, and its cap's half-angle.
DOME_CENTRE, DOME_RADIUS, DOME_POLAR_DEG = np.array([0.0, 0.0, -0.9]), 0.9, 25.0
#: (polar, azimuth) degrees of two novel views on the dome, between the default 12-camera dome's cameras.
DOME_NOVEL_VIEWS = ((11.0, 70.0), (18.0, 250.0))
_EPS = 1e-6
_INF = np.inf


# -- procedural textures ---------------------------------------------------------------------------
class _Noise:
    """Smooth 2D value noise from a seeded 256x256 lattice (period 256 in lattice units)."""

    def __init__(self, rng: np.random.Generator):
        self.table = rng.random((256, 256))

    def __call__(self, u: np.ndarray, v: np.ndarray) -> np.ndarray:
        """Noise in [0, 1] at lattice coordinates u, v (same shape)."""
        iu, iv = np.floor(u), np.floor(v)
        fu, fv = u - iu, v - iv
        fu, fv = fu * fu * (3 - 2 * fu), fv * fv * (3 - 2 * fv)
        i0, j0 = iu.astype(np.int64) & 255, iv.astype(np.int64) & 255
        i1, j1 = (i0 + 1) & 255, (j0 + 1) & 255
        t = self.table
        a = t[i0, j0] + fu * (t[i1, j0] - t[i0, j0])
        b = t[i0, j1] + fu * (t[i1, j1] - t[i0, j1])
        return a + fv * (b - a)

    def fbm(self, u, v, octaves: int = 3) -> np.ndarray:
        """Fractal sum of `octaves` octaves, in [0, 1]."""
        total, amp, norm = 0.0, 1.0, 0.0
        for k in range(octaves):
            total = total + amp * self(u * 2**k + 31.7 * k, v * 2**k + 17.3 * k)
            norm += amp
            amp *= 0.5
        return total / norm

    def solid(self, p: np.ndarray, freq: float) -> np.ndarray:
        """Cheap 3D noise for points p (M, 3): the mean of three 2D slices, in [0, 1]."""
        x, y, z = (p * freq).T
        return (self.fbm(x, y, 2) + self.fbm(y + 57.0, z, 2) + self.fbm(z + 113.0, x, 2)) / 3


def _checker(u, v, size) -> np.ndarray:
    return ((np.floor(u / size) + np.floor(v / size)) % 2).astype(np.float64)


def _mix(c0, c1, w) -> np.ndarray:
    """Blend colours c0, c1 (3,) with weights w (M,) -> (M, 3)."""
    w = np.clip(w, 0, 1)[:, None]
    return np.asarray(c0) * (1 - w) + np.asarray(c1) * w


# -- primitives ------------------------------------------------------------------------------------
def _dot(a, b) -> np.ndarray:
    """Row-wise dot products of (N, 3) arrays -> (N,)."""
    return np.einsum("ij,ij->i", a, b)


def _sphere_hit(o, d, center, radius, t_min=_EPS) -> np.ndarray:
    """Ray parameter (N,) of the first hit beyond t_min of rays o + t d (o (3,) or (N, 3), d (N, 3)
    unit) with a sphere, inf where missed."""
    oc = np.broadcast_to(o - center, d.shape)
    b = _dot(d, oc)
    c = _dot(oc, oc) - radius * radius
    disc = b * b - c
    with np.errstate(invalid="ignore"):
        s = np.sqrt(disc)
    t0, t1 = -b - s, -b + s
    t = np.where(t0 > t_min, t0, np.where(t1 > t_min, t1, _INF))
    return np.where(disc >= 0, t, _INF)


def _box_hit(o, d, center, half, rot, t_min=_EPS) -> np.ndarray:
    """Ray parameter (N,) of the first hit with an oriented box (rot: (3, 3) box-to-world), inf where
    missed."""
    ol = (o - center) @ rot
    dl = d @ rot
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / dl
        t1, t2 = (-half - ol) * inv, (half - ol) * inv
    lo, hi = np.minimum(t1, t2), np.maximum(t1, t2)  # NaN where a ray lies in a slab's plane
    tn = np.fmax(np.fmax(lo[:, 0], lo[:, 1]), lo[:, 2])
    tf = np.fmin(np.fmin(hi[:, 0], hi[:, 1]), hi[:, 2])
    t = np.where(tn > t_min, tn, tf)
    return np.where((tf >= tn) & (tf > t_min), t, _INF)


def _box_normal(p, center, half, rot) -> tuple[np.ndarray, np.ndarray]:
    """World normals (M, 3) and local coordinates (M, 3) of points p on an oriented box."""
    pl = (p - center) @ rot
    axis = np.argmax(np.abs(pl) / half, axis=-1)
    nl = np.zeros_like(pl)
    nl[np.arange(len(p)), axis] = np.sign(pl[np.arange(len(p)), axis])
    return nl @ rot.T, pl


def _rot_y(angle: float) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])


#: Object sets: static_box (centre, half sizes, y rotation), shiny_sphere (centre, radius), rotating_box
#: (centre, half sizes, rad/s about y), fader (centre, radius), moving_sphere (radius, path: centre +
#: amplitude * (sin wt, sin 2wt, 1 - cos wt), w = 2 pi / period).
LAYOUTS = {
    0: {"static_box": ([-1.3, 1.05, 4.6], [0.45, 0.45, 0.45], 0.5), "shiny_sphere": ([1.3, 0.9, 4.0], 0.6),
        "rotating_box": ([0.25, 0.9, 5.6], [0.4, 0.6, 0.4], 1.2), "fader": ([-1.0, -0.9, 5.5], 0.35),
        "moving_sphere": {"radius": 0.3, "centre": [0.0, -0.2, 3.4], "amplitude": [0.9, 0.3, 0.4], "period": 3.0}},
    1: {"static_box": ([1.4, 0.9, 5.2], [0.6, 0.6, 0.35], -0.7), "shiny_sphere": ([-1.6, 1.0, 4.4], 0.5),
        "rotating_box": ([-0.6, 0.75, 4.2], [0.3, 0.75, 0.5], -2.0), "fader": ([1.2, -0.6, 4.6], 0.45),
        "moving_sphere": {"radius": 0.38, "centre": [0.3, 0.1, 3.9], "amplitude": [-0.7, 0.45, 0.8], "period": 2.0}},
}


class SyntheticScene:
    """The dynamic room scene (see the module docstring).

    seed: chooses the noise textures and small colour variations; duration: seconds over which the
    fader appears and vanishes (use num_frames / fps); specular: strength of the highlight on
    "shiny_sphere" (0 turns it off); start: the scene's time at t = 0, seconds (a clip that begins
    `start` seconds into the scene, or before it when negative: its motion and its fader's timing are
    those of the scene at start + t); blur: standard deviation in pixels of the camera's optical blur,
    a Gaussian applied to every rendered image (0 turns it off; the default 1 px band-limits the
    textures like a real lens, which keeps aliasing down and the mp4 videos within about 32 dB PSNR
    of the PNG frames); layout: the object set, 0 (the default scene) or 1 (see the module docstring).
    """

    def __init__(self, seed: int = 0, duration: float = 1.0, specular: float = 0.7, shininess: float = 60.0,
                 blur: float = 1.0, layout: int = 0, start: float = 0.0):
        if layout not in LAYOUTS:
            raise ValueError(f"layout must be one of {sorted(LAYOUTS)}, got {layout!r}")
        self.layout = int(layout)
        self.seed = int(seed)
        self.blur = float(blur)
        self.duration = float(duration)
        self.start = float(start)
        self.specular = float(specular)
        self.shininess = float(shininess)
        rng = np.random.default_rng(self.seed)
        self._noise = _Noise(rng)
        jitter = lambda c: np.clip(np.asarray(c) + rng.uniform(-0.06, 0.06, 3), 0, 1)  # noqa: E731
        self._colors = {
            "wall_a": jitter([0.80, 0.74, 0.62]), "wall_b": jitter([0.45, 0.52, 0.62]),
            "floor_a": jitter([0.55, 0.38, 0.22]), "floor_b": jitter([0.78, 0.62, 0.40]),
            "side": jitter([0.60, 0.70, 0.55]), "ceiling": jitter([0.85, 0.85, 0.82]),
            "box_a": jitter([0.20, 0.45, 0.80]), "box_b": jitter([0.90, 0.85, 0.30]),
            "shiny": jitter([0.75, 0.12, 0.10]),
            "mover_a": jitter([0.95, 0.80, 0.10]), "mover_b": jitter([0.10, 0.20, 0.60]),
            "rot_a": jitter([0.85, 0.30, 0.60]), "rot_b": jitter([0.95, 0.95, 0.95]),
            "fader": jitter([0.15, 0.75, 0.30]),
        }
        objects = LAYOUTS[self.layout]
        self.static_box = (np.array(objects["static_box"][0]), np.array(objects["static_box"][1]),
                           _rot_y(objects["static_box"][2]))
        self.shiny_sphere = (np.array(objects["shiny_sphere"][0]), objects["shiny_sphere"][1])
        self.rotating_box_center = np.array(objects["rotating_box"][0])
        self.rotating_box_half = np.array(objects["rotating_box"][1])
        self._spin = objects["rotating_box"][2]
        self.fader_sphere = (np.array(objects["fader"][0]), objects["fader"][1])
        self.moving_sphere_radius = objects["moving_sphere"]["radius"]
        self._path = objects["moving_sphere"]

    # -- animation -------------------------------------------------------------------------------
    def moving_sphere_center(self, t: float) -> np.ndarray:
        """(3,) centre of "moving_sphere" at time t (seconds); a closed path (period 3 s in layout 0)."""
        p, t = self._path, self.start + t
        w = 2 * np.pi / p["period"]
        (cx, cy, cz), (ax, ay, az) = p["centre"], p["amplitude"]
        return np.array([cx + ax * np.sin(w * t), cy + ay * np.sin(2 * w * t), cz + az * (1 - np.cos(w * t))])

    def rotating_box_rotation(self, t: float) -> np.ndarray:
        """(3, 3) box-to-world rotation of "rotating_box" at time t (about the y axis; 1.2 rad/s in
        layout 0)."""
        return _rot_y(self._spin * (self.start + t))

    def fader_alpha(self, t: float) -> float:
        """Opacity of "fader" at time t: 0, ramps to 1 over [0.25, 0.35] x duration, 1, back to 0 over
        [0.65, 0.75] x duration."""
        x = (self.start + t) / self.duration if self.duration > 0 else 0.0
        return float(np.clip(min((x - 0.25) / 0.1, (0.75 - x) / 0.1), 0.0, 1.0))

    def object_center(self, name: str, t: float = 0.0) -> np.ndarray:
        """(3,) world centre of the object `name` (one of OBJECT_NAMES) at time t."""
        return {"static_box": lambda: self.static_box[0], "shiny_sphere": lambda: self.shiny_sphere[0],
                "moving_sphere": lambda: self.moving_sphere_center(t),
                "rotating_box": lambda: self.rotating_box_center,
                "fader": lambda: self.fader_sphere[0]}[name]().copy()

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """Scene bounds (min (3,), max (3,)) in world units: the room, which contains everything."""
        return ROOM_MIN.copy(), ROOM_MAX.copy()

    # -- the rig ---------------------------------------------------------------------------------
    def cameras(self, num_cameras: int = 12, width: int = 160, height: int = 120,
                focal: float | None = None, spacing: tuple[float, float] = (0.4, 0.3)) -> list[Camera]:
        """A forward-facing rig like Neural 3D Video's: `num_cameras` pinhole cameras on a grid of
        `spacing` (horizontal, vertical) units, bent onto a sphere around the look-at point (0, 0.3, 4),
        all looking at it. cam00 is at the origin, in the middle; the others follow by distance from it
        (wider than tall). focal: in pixels, fx = fy, default 0.9 x width (about 58 degrees across);
        principal point at the image centre."""
        if num_cameras < 1:
            raise ValueError("num_cameras must be at least 1")
        grid = [(i, j) for i in range(-4, 5) for j in range(-8, 9)]
        grid.sort(key=lambda ij: (round(np.hypot(ij[1] * spacing[0], 1.6 * ij[0] * spacing[1]), 9),
                                  round(np.arctan2(ij[0], ij[1]) % (2 * np.pi), 9)))
        if num_cameras > len(grid):
            raise ValueError(f"at most {len(grid)} cameras")
        return [self.rig_camera(j * spacing[0], i * spacing[1], width, height, focal, name=f"cam{k:02d}")
                for k, (i, j) in enumerate(grid[:num_cameras])]

    @staticmethod
    def rig_camera(x: float, y: float, width: int = 160, height: int = 120, focal: float | None = None,
                   name: str = "") -> Camera:
        """A camera of the rig's shape at rig position (x, y) (world units right and down of cam00),
        on the sphere around the look-at point and looking at it; positions between the rig's cameras
        give novel views inside the rig. focal: in pixels, default 0.9 x width."""
        focal = 0.9 * width if focal is None else float(focal)
        dist = np.linalg.norm(TARGET)
        eye = np.array([x, y, dist - np.sqrt(dist * dist - x * x - y * y)])  # on the sphere around the target
        forward = (TARGET - eye) / np.linalg.norm(TARGET - eye)
        right = np.cross([0.0, 1.0, 0.0], forward)  # world y is down
        right /= np.linalg.norm(right)
        R = np.stack([right, np.cross(forward, right), forward])  # rows: camera x, y (down), z
        w2c = np.eye(4)
        w2c[:3, :3], w2c[:3, 3] = R, -R @ eye
        return Camera(focal, focal, width / 2, height / 2, width, height, w2c, name=name)

    @staticmethod
    def dome_camera(polar_deg: float, azimuth_deg: float, width: int = 160, height: int = 120,
                    hfov_deg: float = 120.0, model: str = "fisheye", distortion=(0.0, 0.0, 0.0, 0.0),
                    name: str = "") -> Camera:
        """A camera of the outward-facing dome rig (dome_cameras) at `polar_deg` degrees from the dome's
        axis (+z, towards the scene) and `azimuth_deg` around it, on the sphere of radius DOME_RADIUS
        around DOME_CENTRE, looking outwards (away from the centre), image up = world up (-y).

        hfov_deg: horizontal field of view, the angle between the rays through the middles of the image's
        left and right edges: fisheye (OpenCV's model with `distortion` k1..k4; all zero: equidistant)
        f = (width / 2) / theta_d(hfov / 2), pinhole f = (width / 2) / tan(hfov / 2) (below 180). fx = fy,
        principal point at the image centre."""
        polar, azimuth = np.radians(polar_deg), np.radians(azimuth_deg)
        out = np.array([np.sin(polar) * np.cos(azimuth), np.sin(polar) * np.sin(azimuth), np.cos(polar)])
        eye = DOME_CENTRE + DOME_RADIUS * out
        half = np.radians(hfov_deg) / 2
        if model == "fisheye":
            distortion = tuple(float(k) for k in distortion)
            f = 0.5 * width / float(fisheye_distort(half, distortion))
        else:
            if not half < np.pi / 2:
                raise ValueError(f"a pinhole camera's field of view must be below 180 degrees, got {hfov_deg:g}")
            f, distortion = 0.5 * width / np.tan(half), ()
        pose = Camera.look_at(eye, eye + out, (0.0, -1.0, 0.0), 60.0, width, height)
        return Camera(f, f, width / 2, height / 2, width, height, pose.world_to_camera, name, model, distortion)

    def dome_cameras(self, num_cameras: int = 12, width: int = 160, height: int = 120, hfov_deg: float = 120.0,
                     model: str = "fisheye", distortion=(0.0, 0.0, 0.0, 0.0)) -> list[Camera]:
        """An outward-facing dome rig like the Google Immersive dataset's: `num_cameras` cameras on a cap
        of the sphere of radius DOME_RADIUS around DOME_CENTRE, up to DOME_POLAR_DEG degrees from its axis
        (+z), each looking outwards (dome_camera). Camera k (named camera_<k+1:04d>) sits at polar angle
        DOME_POLAR_DEG x sqrt(k / (num_cameras - 1)) and azimuth k x 137.5 degrees (a sunflower spiral:
        evenly spread); camera_0001 is the centre camera, on the axis, at the origin. Every camera sees
        the scene's objects. model "pinhole" gives the same rig with pinhole lenses of the same hfov_deg."""
        if num_cameras < 1:
            raise ValueError("num_cameras must be at least 1")
        golden = 180.0 * (3.0 - np.sqrt(5.0))
        return [self.dome_camera(DOME_POLAR_DEG * np.sqrt(k / max(num_cameras - 1, 1)), k * golden, width, height,
                                 hfov_deg, model, distortion, name=f"camera_{k + 1:04d}") for k in range(num_cameras)]

    def dome_novel_cameras(self, width: int = 160, height: int = 120, hfov_deg: float = 90.0,
                           model: str = "pinhole", views=DOME_NOVEL_VIEWS) -> list[Camera]:
        """Novel views inside the dome rig: dome_camera at each (polar, azimuth) of `views` (degrees;
        by default between the 12-camera dome's cameras), named "novel0", ...; pinholes by default (the
        views novel_view_dataset renders to compare fisheye- and pinhole-trained models)."""
        return [self.dome_camera(polar, azimuth, width, height, hfov_deg, model, name=f"novel{k}")
                for k, (polar, azimuth) in enumerate(views)]

    # -- ray tracing -----------------------------------------------------------------------------
    def _solids(self, t: float):
        """Opaque objects at time t as (name, kind, params)."""
        c, h, r = self.static_box
        return [("static_box", "box", (c, h, r)),
                ("shiny_sphere", "sphere", self.shiny_sphere),
                ("moving_sphere", "sphere", (self.moving_sphere_center(t), self.moving_sphere_radius)),
                ("rotating_box", "box", (self.rotating_box_center, self.rotating_box_half,
                                         self.rotating_box_rotation(t)))]

    @staticmethod
    def _hit(kind, params, o, d, t_min=_EPS):
        return _sphere_hit(o, d, *params, t_min=t_min) if kind == "sphere" else _box_hit(o, d, *params, t_min=t_min)

    @staticmethod
    def _room_hit(o, d) -> tuple[np.ndarray, np.ndarray]:
        """Exit distance (N,) of rays from inside the room and the face hit (N,) in 0..5:
        x-, x+, y- (ceiling), y+ (floor), z- (front), z+ (back)."""
        with np.errstate(divide="ignore"):
            far = np.where(d > 0, ROOM_MAX, ROOM_MIN)
            ts = (far - o) / d
        ts = np.where(np.abs(d) < 1e-12, _INF, ts)
        axis = np.argmin(ts, axis=-1)
        t = ts[np.arange(len(d)), axis]
        face = 2 * axis + (d[np.arange(len(d)), axis] > 0)
        return t, face

    def _nearest(self, o, d, t):
        """Nearest opaque hit: ray parameter (N,), object index (N,) (-1 room) and room face (N,)."""
        t_room, face = self._room_hit(o, d)
        ts = np.stack([t_room] + [self._hit(k, p, o, d) for _, k, p in self._solids(t)])
        idx = np.argmin(ts, axis=0)
        return ts[idx, np.arange(len(d))], idx - 1, face

    def _room_albedo(self, p, face) -> np.ndarray:
        n, c = self._noise, self._colors
        out = np.empty((len(p), 3))
        x, y, z = p.T
        for f in range(6):
            m = face == f
            if not m.any():
                continue
            xm, ym, zm = x[m], y[m], z[m]
            if f == 5:  # back wall
                base = _mix(c["wall_a"], c["wall_b"], _checker(xm, ym, 0.5))
                out[m] = base * (0.3 + 0.9 * n.fbm(xm * 4, ym * 4, 3))[:, None]
            elif f == 3:  # floor
                grain = 0.5 + 0.5 * np.sin(2 * np.pi * xm / 0.3 + 6 * n.fbm(xm * 2 + 50, zm * 0.5, 3))
                base = _mix(c["floor_a"], c["floor_b"], grain)
                out[m] = base * (0.75 + 0.25 * _checker(xm, zm, 1.0))[:, None]
            elif f in (0, 1):  # side walls
                stripes = (np.floor(zm / 0.4) % 2) * 0.5 + n.fbm(zm * 4 + 9 * f, ym * 4, 3)
                out[m] = _mix(c["side"] * 0.5, c["side"], stripes / 1.5)
            else:  # ceiling, front wall
                out[m] = c["ceiling"] * (0.7 + 0.3 * n.fbm(xm * 3 + 70, (zm + ym) * 3, 3))[:, None]
        return out

    def _surface(self, name, params, p, t):
        """Normals (M, 3) and albedo (M, 3) of points p on object `name`."""
        n, c = self._noise, self._colors
        if name in ("static_box", "rotating_box"):
            normal, pl = _box_normal(p, *params)
            if name == "static_box":
                w = 0.65 * _checker(pl[:, 0] + pl[:, 2], pl[:, 1], 0.15) + 0.7 * n.solid(pl, 8.0) - 0.2
                return normal, _mix(c["box_a"], c["box_b"], w)
            w = np.floor(pl / 0.2 + 0.5).sum(axis=-1) % 2  # cell edges off the faces
            return normal, _mix(c["rot_a"], c["rot_b"], w)
        center, radius = params
        normal = (p - center) / radius
        if name == "moving_sphere":
            lon = np.arctan2(normal[:, 0], normal[:, 2])
            lat = np.arcsin(np.clip(normal[:, 1], -1, 1))
            return normal, _mix(c["mover_a"], c["mover_b"], _checker(lon, lat, np.pi / 6))
        if name == "shiny_sphere":
            return normal, c["shiny"] * (0.85 + 0.15 * n.solid(normal, 3.0))[:, None]
        return normal, _mix(c["fader"], c["fader"] * 0.5, _checker(normal[:, 0], normal[:, 1], 0.25))

    def _shade(self, p, normal, albedo, view, ks, t) -> np.ndarray:
        """Colour (M, 3): albedo x (ambient + diffuse x visibility) + Blinn-Phong specular."""
        to_light = LIGHT - p
        dist = np.sqrt(_dot(to_light, to_light))
        l = to_light / dist[:, None]
        ndotl = _dot(normal, l)
        vis = np.where(ndotl > 0, 1.0, 0.0)
        o = p + 1e-4 * normal
        lit = ndotl > 0
        if lit.any():
            vo, vl, vd = o[lit], l[lit], dist[lit]
            v = np.ones(len(vo))
            for _, kind, params in self._solids(t):
                v[self._hit(kind, params, vo, vl) < vd] = 0.0
            a = self.fader_alpha(t)
            if a > 0:
                v *= np.where(_sphere_hit(vo, vl, *self.fader_sphere) < vd, 1 - a, 1.0)
            vis[lit] = v
        rgb = albedo * (AMBIENT + DIFFUSE * np.maximum(ndotl, 0) * vis)[:, None]
        if np.any(ks > 0):
            h = l + view
            h /= np.sqrt(_dot(h, h))[:, None]
            spec = ks * vis * np.maximum(_dot(normal, h), 0) ** self.shininess
            rgb += spec[:, None]
        return rgb

    def _trace(self, o, d, t) -> tuple[np.ndarray, np.ndarray]:
        """Colour (N, 3) and ray parameter of the visible surface (N,) for rays o (3,) + s d (N, 3)."""
        s, idx, face = self._nearest(o, d, t)
        p = o + s[:, None] * d
        normal, albedo, ks = np.empty_like(p), np.empty_like(p), np.zeros(len(d))
        room = idx < 0
        normal[room] = 0.0
        normal[room, face[room] // 2] = np.where(face[room] % 2 == 1, -1.0, 1.0)  # pointing inwards
        albedo[room] = self._room_albedo(p[room], face[room])
        for k, (name, _, params) in enumerate(self._solids(t)):
            m = idx == k
            if m.any():
                normal[m], albedo[m] = self._surface(name, params, p[m], t)
                if name == "shiny_sphere":
                    ks[m] = self.specular
        rgb = self._shade(p, normal, albedo, -d, ks, t)
        a = self.fader_alpha(t)
        if a > 0:
            sf = _sphere_hit(o, d, *self.fader_sphere)
            front = sf < s
            if front.any():
                pf = o + sf[front, None] * d[front]
                nf, af = self._surface("fader", self.fader_sphere, pf, t)
                rgb[front] = a * self._shade(pf, nf, af, -d[front], np.zeros(len(pf)), t) + (1 - a) * rgb[front]
                if a >= 0.5:
                    s = np.where(front, sf, s)
        return rgb, s

    @staticmethod
    def _rays(camera: Camera, supersample: int) -> np.ndarray:
        """(S, H*W, 3) unit world directions through S = supersample^2 sub-pixel positions, through the
        camera's lens (Camera.camera_rays: pinhole or fisheye)."""
        offs = (np.arange(supersample) + 0.5) / supersample
        out = []
        for oy in offs:
            for ox in offs:
                u, v = np.arange(camera.width) + ox, np.arange(camera.height) + oy
                dc = camera.camera_rays(u[None, :], v[:, None]).reshape(-1, 3)
                out.append(dc @ camera.R)
        return np.stack(out)

    def render(self, camera: Camera, t: float, return_depth: bool = False, supersample: int = 1):
        """Render the scene at time t (seconds) through `camera`.

        Returns rgb (H, W, 3) float32 in [0, 1] (after the optical blur); with return_depth also depth
        (H, W) float32, the camera-space z (along +z, world units) of the surface seen through each
        pixel centre, unblurred (the fader counts once its opacity reaches 0.5). supersample: s x s rays
        per pixel, averaged (the depth still comes from the pixel centre).
        """
        o = camera.center
        dirs = self._rays(camera, supersample)
        traced = [self._trace(o, d, t) for d in dirs]
        rgb = np.mean([c for c, _ in traced], axis=0).reshape(camera.height, camera.width, 3).astype(np.float32)
        if self.blur > 0:
            rgb = cv2.GaussianBlur(rgb, (0, 0), self.blur, borderType=cv2.BORDER_REFLECT)
        rgb = np.clip(rgb, 0, 1)
        if not return_depth:
            return rgb
        if supersample == 1:
            s, d = traced[0][1], dirs[0]
        else:
            d = self._rays(camera, 1)[0]
            s = self._depth_param(o, d, t)
        depth = (s * (d @ camera.R[2])).reshape(camera.height, camera.width).astype(np.float32)
        return rgb, depth

    def _depth_param(self, o, d, t):
        s, _, _ = self._nearest(o, d, t)
        if self.fader_alpha(t) >= 0.5:
            s = np.minimum(s, _sphere_hit(o, d, *self.fader_sphere))
        return s

    def object_ids(self, camera: Camera, t: float) -> np.ndarray:
        """(H, W) int8: index into OBJECT_NAMES of the object seen through each pixel centre, -1 for the
        room (the fader counts once its opacity reaches 0.5)."""
        d = self._rays(camera, 1)[0]
        s, idx, _ = self._nearest(camera.center, d, t)
        if self.fader_alpha(t) >= 0.5:
            idx = np.where(_sphere_hit(camera.center, d, *self.fader_sphere) < s, OBJECT_NAMES.index("fader"), idx)
        return idx.reshape(camera.height, camera.width).astype(np.int8)

    # -- provenance --------------------------------------------------------------------------------
    def settings(self) -> dict:
        return {"generator": "stg_train.synthetic.SyntheticScene", "seed": self.seed, "layout": self.layout,
                "duration": self.duration, "start": self.start,
                "specular": self.specular, "shininess": self.shininess, "blur": self.blur,
                "world_axes": "OpenCV: x right, y down, z forward"}


def llff_pose(camera: Camera) -> np.ndarray:
    """(3, 5) LLFF pose of a camera: camera-to-world columns [down, right, backwards], the centre, and
    (height, width, focal). Uses fx as the focal."""
    c2w = camera.R.T  # columns: camera x (right), y (down), z (forward) in world coordinates
    out = np.empty((3, 5))
    out[:, 0], out[:, 1], out[:, 2] = c2w[:, 1], c2w[:, 0], -c2w[:, 2]
    out[:, 3] = camera.center
    out[:, 4] = (camera.height, camera.width, camera.fx)
    return out


def _to_uint8(rgb: np.ndarray) -> np.ndarray:
    """(H, W, 3) float in [0, 1] -> uint8, rounding to nearest."""
    return np.rint(np.clip(rgb, 0, 1) * 255).astype(np.uint8)


def _remove_layout_files(out: Path) -> None:
    """Delete the files of either synthetic layout in out (so an earlier, larger run, or a run in the other
    layout, leaves nothing behind): N3V's camXX.mp4, frames/camXX/*.png and poses_bounds.npy, the
    Immersive layout's camera_NNNN.mp4, camera_NNNN/*.png and models.json."""
    for video in list(out.glob("cam*.mp4")):
        if re.fullmatch(r"cam(era_)?\d+\.mp4", video.name):
            video.unlink()
    folders = [f for f in out.glob("frames/cam*") if re.fullmatch(r"cam\d+", f.name)]
    folders += [f for f in out.glob("camera_*") if re.fullmatch(r"camera_\d+", f.name)]
    for folder in folders:
        if folder.is_dir():
            for png in folder.glob("*.png"):
                png.unlink()
            if not any(folder.iterdir()):
                folder.rmdir()
    for name in ("poses_bounds.npy", "models.json"):
        if (out / name).is_file():
            (out / name).unlink()


VIDEO_CODEC = "mp4v"  # MPEG-4 Part 2: written and read back by OpenCV's bundled FFmpeg


def _write_camera(scene: SyntheticScene, cam: Camera, video: Path, png_folder: Path | None, num_frames: int,
                  fps: float, supersample: int, tick, effects=None) -> tuple[float, float]:
    """Render frames k / fps, k < num_frames, of `cam` into `video` ('mp4v') and, when png_folder is
    given, <png_folder>/<k:06d>.png; tick() after each frame. effects: a capture.CameraEffects that
    each frame goes through (None: the ideal picture). Returns (near, far): the smallest and largest
    depth the camera sees."""
    writer = cv2.VideoWriter(str(video), cv2.VideoWriter_fourcc(*VIDEO_CODEC), float(fps), (cam.width, cam.height))
    if not writer.isOpened():
        raise RuntimeError(f"{video}: OpenCV cannot write '{VIDEO_CODEC}' video here")
    if png_folder is not None:
        png_folder.mkdir(parents=True, exist_ok=True)
    near, far = np.inf, 0.0
    try:
        for k in range(num_frames):
            rgb, depth = scene.render(cam, k / fps, return_depth=True, supersample=supersample)
            near, far = min(near, float(depth.min())), max(far, float(depth.max()))
            if effects is not None:
                rgb = effects.apply(rgb, cam)
            bgr = np.ascontiguousarray(_to_uint8(rgb)[..., ::-1])
            writer.write(bgr)
            if png_folder is not None:
                cv2.imwrite(str(png_folder / f"{k:06d}.png"), bgr)
            tick()
    finally:
        writer.release()
    return near, far


def _ticker(total: int, progress):
    done = [0]

    def tick():
        done[0] += 1
        if progress is not None:
            progress(done[0], total)
    return tick


def write_n3v(out_dir, scene: SyntheticScene, num_cameras: int = 12, num_frames: int = 30, fps: float = 30,
              width: int = 160, height: int = 120, png: bool = True, focal: float | None = None,
              supersample: int = 1, progress=None, capture=None) -> list[Camera]:
    """Render `scene` with its rig and write the Neural 3D Video layout into out_dir:

      camXX.mp4          one video per camera ('mp4v', lossy), frame k shows time k / fps;
      poses_bounds.npy   (num_cameras, 17) float64, LLFF: flattened 3x5 [down, right, backwards | centre |
                         (H, W, focal)] camera-to-world, then near and far: the smallest and largest depth
                         seen by that camera over all frames;
      frames/camXX/000000.png  lossless frames (when png);
      scene.json         the generator's settings.

    Files of either synthetic layout left in out_dir by an earlier run are removed (_remove_layout_files).
    progress: optional callable(done, total) called after each rendered frame. capture: a
    stg_train.rig.capture.CaptureModel: each camera's frames go through its exposure, white balance,
    vignetting and noise, and poses_bounds.npy holds its perturbed pose; scene.json then records the
    model, each camera's effects and its true world_to_camera. Returns the true cameras.
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    cams = scene.cameras(num_cameras, width, height, focal=focal)
    effects = capture.draw(num_cameras, held_out=[0]) if capture is not None else [None] * num_cameras  # cam00
    _remove_layout_files(out)
    poses = np.zeros((num_cameras, 17))
    tick = _ticker(num_cameras * num_frames, progress)
    for ci, cam in enumerate(cams):
        near, far = _write_camera(scene, cam, out / f"{cam.name}.mp4", out / "frames" / cam.name if png else None,
                                  num_frames, fps, supersample, tick, effects[ci])
        stated = cam if effects[ci] is None else effects[ci].perturb(cam)
        poses[ci, :15] = llff_pose(stated).ravel()
        poses[ci, 15:] = near, far
    np.save(out / "poses_bounds.npy", poses)
    meta = dict(scene.settings(), fps=float(fps), num_frames=int(num_frames), num_cameras=int(num_cameras),
                width=int(width), height=int(height), focal=float(cams[0].fx), supersample=int(supersample),
                video_codec=VIDEO_CODEC, png=bool(png), held_out="cam00")
    if capture is not None:
        meta["capture"] = dict(capture.settings(), cameras=[
            dict(e.as_dict(), name=c.name, true_world_to_camera=c.world_to_camera.tolist()) for e, c in zip(effects, cams)])
    write_atomic(out / "scene.json", json.dumps(meta, indent=2) + "\n")
    return cams


def write_immersive(out_dir, scene: SyntheticScene, num_cameras: int = 12, num_frames: int = 30, fps: float = 30,
                    width: int = 160, height: int = 120, hfov_deg: float = 120.0, model: str = "fisheye",
                    distortion=(0.0, 0.0, 0.0, 0.0), png: bool = True, supersample: int = 1,
                    progress=None) -> list[Camera]:
    """Render `scene` with its outward-facing dome rig (SyntheticScene.dome_cameras: `model` "fisheye"
    with `distortion`, equidistant by default, or "pinhole", of horizontal field of view hfov_deg) and
    write the Google Immersive layout into out_dir (stg_train.data.immersive):

      camera_0001.mp4, ...          one video per camera ('mp4v', lossy), frame k shows time k / fps;
      camera_0001/000000.png, ...   lossless frames (when png);
      models.json                   the cameras (a pinhole as projection_type "perspective");
      scene.json                    the generator's settings, with each camera's near and far depth.

    camera_0001, the centre camera, is the one the reader holds out. Files of either synthetic layout
    left in out_dir by an earlier run are removed. progress: optional callable(done, total) called after
    each rendered frame. Returns the cameras.
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    cams = scene.dome_cameras(num_cameras, width, height, hfov_deg, model, distortion)
    _remove_layout_files(out)
    tick = _ticker(num_cameras * num_frames, progress)
    bounds = [_write_camera(scene, cam, out / f"{cam.name}.mp4", out / cam.name if png else None, num_frames, fps,
                            supersample, tick) for cam in cams]
    write_atomic(out / MODELS_FILE, json.dumps([entry_from_camera(c) for c in cams], indent=1) + "\n")
    meta = dict(scene.settings(), fps=float(fps), num_frames=int(num_frames), num_cameras=int(num_cameras),
                width=int(width), height=int(height), model=model, hfov_deg=float(hfov_deg),
                distortion=list(cams[0].distortion), supersample=int(supersample), video_codec=VIDEO_CODEC,
                png=bool(png), held_out=cams[0].name, depth_bounds=[list(b) for b in bounds])
    write_atomic(out / "scene.json", json.dumps(meta, indent=2) + "\n")
    return cams


def novel_view_dataset(scene: SyntheticScene, num_frames: int, fps: float, width: int = 160, height: int = 120,
                       positions=NOVEL_VIEWS, focal: float | None = None, supersample: int = 1,
                       cameras=None) -> Dataset:
    """Ground truth at novel views: a Dataset (in memory, uint8 frames rounded as the PNG frames are)
    of `scene` rendered at frames k / fps, k < num_frames, by rig cameras at `positions` (rig_camera;
    named "novel0", ...), or by `cameras` when given (e.g. SyntheticScene.dome_camera views between the
    dome rig's cameras), every one of them a test camera. Evaluate a model trained on the scene's rig
    with it (stg_train.metrics.evaluate_images, evaluate_player)."""
    cams = list(cameras) if cameras is not None else [
        scene.rig_camera(x, y, width, height, focal, name=f"novel{k}") for k, (x, y) in enumerate(positions)]
    frames = np.stack([np.stack([_to_uint8(scene.render(cam, k / fps, supersample=supersample))
                                 for k in range(num_frames)]) for cam in cams])
    return Dataset(cams, frames, fps, test_cameras=range(len(cams)))
