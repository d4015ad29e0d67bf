"""Reader of the Google Immersive layout (DeepView video; Broxton et al. 2020): fisheye cameras.

    <root>/models.json                     the rig's calibration: a list of camera objects (below)
    <root>/camera_0001.mp4, ...            one synchronised video per camera, named <name>.mp4 (any of
                                           frames.VIDEO_EXTENSIONS)
    <root>/camera_0001/0.png 1.png ...     or extracted frames, one folder per camera, named <name>
                                           (the reference preprocessing's layout); frames in natural
                                           order (0, 1, ..., 10: numeric names by number, others by name)
    <root>/scene.json                      optional (stg-synth): the frame rate

A camera object of models.json (one per camera, in camera order):

    name                 the camera's name: its video is <name>.mp4, its frames folder <name>/
    width, height        the image size in pixels the calibration refers to (the frames' size)
    focal_length         f in pixels: fx = f, fy = f x pixel_aspect_ratio
    pixel_aspect_ratio   optional, default 1 (Google's camera model: fy = focal_length x pixel_aspect_ratio)
    principal_point      [cx, cy] in pixels, continuous coordinates with the centre of pixel (column c,
                         row r) at (c + 0.5, r + 0.5): Google's camera convention, the project's, used
                         as given (the reference code hands the numbers to cv2.fisheye unchanged, which
                         reads them half a pixel off)
    radial_distortion    [k1, k2] (up to four: k1..k4; the missing ones are 0): OpenCV's fisheye model
                         (Kannala-Brandt, cv2.fisheye), image radius f x theta (1 + k1 theta^2 + k2 theta^4
                         + ...) at theta radians off the optical axis
    orientation          [rx, ry, rz]: the world-to-camera rotation as an axis-angle vector (radians;
                         cv2.Rodrigues, scipy's Rotation.from_rotvec), OpenCV axes (x right, y down, z forward)
    position             [x, y, z]: the camera centre in world coordinates
    projection_type      optional: "fisheye" (the default) or "perspective" (a pinhole camera, only with
                         zero radial distortion; stg-synth writes such rigs for comparison)
    skew, tangential_distortion   optional; only zero is accepted

Any other field is ignored. The held-out camera is the rig's centre camera: "camera_0001" when there is
one (the camera the reference code and other published readers hold out), else the camera whose
optical axis is closest to the rig's mean optical axis (the first in file order on a tie). The layout
stores no near/far depth bounds (they come from --near/--far or the SfM points, as for the rig layout)
and no frame rate but the videos' (else scene.json's, else 30).
"""
from __future__ import annotations

import json
import math
import re
from pathlib import Path

import numpy as np

from stg_runtime.camera import Camera

from ..rotations import rotation_from_axis_angle
from .dataset import DataError, Dataset
from .frames import DEFAULT_FPS, IMAGE_EXTENSIONS, VIDEO_EXTENSIONS, FrameSource, build_dataset

MODELS_FILE = "models.json"
#: The camera the reference code holds out, when the rig has it.
CENTRE_NAME = "camera_0001"
REQUIRED_FIELDS = ("name", "width", "height", "focal_length", "principal_point", "radial_distortion",
                   "orientation", "position")
PROJECTIONS = ("fisheye", "perspective")
#: Folders that look like a camera's frames (checked against models.json).
CAMERA_FOLDER = re.compile(r"^camera_\d+$")


# -- models.json <-> Camera --------------------------------------------------------------------------
def axis_angle_from_rotation(R) -> np.ndarray:
    """(3,) axis-angle vector of the rotation matrix R (3, 3) (the inverse of rotation_from_axis_angle;
    cv2.Rodrigues, right at angles near pi; rotations.rotation_vector is the one for tiny angles)."""
    import cv2

    return cv2.Rodrigues(np.asarray(R, dtype=np.float64))[0].ravel()


def _number(entry: dict, key: str, where: str, positive: bool = False) -> float:
    value = entry[key]
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise DataError(f"{where}: {key} must be a finite number, got {value!r}")
    if positive and not value > 0:
        raise DataError(f"{where}: {key} must be positive, got {value!r}")
    return float(value)


def _vector(entry: dict, key: str, where: str, sizes) -> list[float]:
    value = entry[key]
    if (not isinstance(value, list) or len(value) not in sizes
            or any(isinstance(x, bool) or not isinstance(x, (int, float)) for x in value)):
        count = f"{sizes[0]}" if len(sizes) == 1 else f"{sizes[0]} to {sizes[-1]}"
        raise DataError(f"{where}: {key} must be a list of {count} numbers, got {value!r}")
    if not all(math.isfinite(x) for x in value):
        raise DataError(f"{where}: {key} has non-finite numbers {value!r}")
    return [float(x) for x in value]


def _size(entry: dict, key: str, where: str) -> int:
    value = entry[key]
    if isinstance(value, bool) or not isinstance(value, (int, float)) or value != int(value) or value < 1:
        raise DataError(f"{where}: {key} must be a positive whole number of pixels, got {value!r}")
    return int(value)


def camera_from_entry(entry, where: str) -> Camera:
    """The Camera of one models.json camera object (see the module docstring); DataError starting with
    `where` (the file and the camera) for anything this reader cannot represent."""
    if not isinstance(entry, dict):
        raise DataError(f"{where}: a camera must be a JSON object, got {type(entry).__name__}")
    missing = [k for k in REQUIRED_FIELDS if k not in entry]
    if missing:
        raise DataError(f"{where}: missing field{'s' if len(missing) > 1 else ''} {', '.join(missing)}")
    projection = entry.get("projection_type", "fisheye")
    if projection not in PROJECTIONS:
        raise DataError(f"{where}: projection_type {projection!r} is not supported (this reader knows "
                        f"{', '.join(PROJECTIONS)})")
    width, height = _size(entry, "width", where), _size(entry, "height", where)
    f = _number(entry, "focal_length", where, positive=True)
    aspect = _number(entry, "pixel_aspect_ratio", where, positive=True) if "pixel_aspect_ratio" in entry else 1.0
    cx, cy = _vector(entry, "principal_point", where, (2,))
    radial = entry["radial_distortion"]
    if isinstance(radial, list) and len(radial) > 4:
        raise DataError(f"{where}: radial_distortion has {len(radial)} coefficients, an unsupported distortion "
                        "model (OpenCV's fisheye model takes at most 4, k1..k4)")
    k = _vector(entry, "radial_distortion", where, range(0, 5))
    k = k + [0.0] * (4 - len(k))
    for key in ("skew", "tangential_distortion"):
        if key in entry:
            value = entry[key]
            values = value if isinstance(value, list) else [value]
            if any(isinstance(x, bool) or not isinstance(x, (int, float)) or x != 0 for x in values):
                raise DataError(f"{where}: {key} {value!r} is not supported (only zero)")
    if projection == "perspective" and any(k):
        raise DataError(f"{where}: a perspective camera with radial_distortion {entry['radial_distortion']!r} "
                        "is not supported (undistort its frames, or use projection_type fisheye)")
    rotation = rotation_from_axis_angle(_vector(entry, "orientation", where, (3,)))
    centre = np.array(_vector(entry, "position", where, (3,)))
    w2c = np.eye(4)
    w2c[:3, :3], w2c[:3, 3] = rotation, -rotation @ centre
    model = "fisheye" if projection == "fisheye" else "pinhole"
    try:
        return Camera(f, f * aspect, cx, cy, width, height, w2c, entry["name"], model,
                      tuple(k) if model == "fisheye" else ())
    except ValueError as e:
        raise DataError(f"{where}: {e}") from None


def entry_from_camera(camera: Camera) -> dict:
    """The models.json camera object of a Camera (fx = focal_length, fy / fx = pixel_aspect_ratio; a
    pinhole is written with projection_type "perspective"); camera_from_entry reads it back."""
    entry = {"name": camera.name, "width": camera.width, "height": camera.height, "focal_length": camera.fx,
             "pixel_aspect_ratio": camera.fy / camera.fx, "principal_point": [camera.cx, camera.cy],
             "radial_distortion": list(camera.distortion) if camera.model == "fisheye" else [0.0, 0.0],
             "orientation": axis_angle_from_rotation(camera.R).tolist(), "position": camera.center.tolist(),
             "projection_type": "fisheye" if camera.model == "fisheye" else "perspective"}
    return entry


def read_models(path: Path) -> list[Camera]:
    """The cameras of a models.json file, in file order; DataError naming the file (and the camera) for
    a file that is missing, not JSON, not a non-empty list of camera objects, or has duplicate names."""
    if not path.is_file():
        raise DataError(f"{path}: missing (the Immersive layout needs models.json beside the videos)")
    try:
        data = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError) as e:
        raise DataError(f"{path}: cannot be read ({e})") from None
    except ValueError as e:
        raise DataError(f"{path}: not a JSON file ({e})") from None
    if not isinstance(data, list) or not data:
        raise DataError(f"{path}: must hold a non-empty JSON list of camera objects, got "
                        f"{'an empty list' if data == [] else type(data).__name__}")
    cameras, seen = [], set()
    for i, entry in enumerate(data):
        name = entry.get("name") if isinstance(entry, dict) else None
        where = f"{path}: camera {i}" + (f" ({name})" if isinstance(name, str) else "")
        if isinstance(entry, dict) and "name" in entry and (not isinstance(name, str) or not name
                                                             or "/" in name or "\\" in name or name.startswith(".")):
            raise DataError(f"{where}: name must be a plain file name, got {name!r}")
        camera = camera_from_entry(entry, where)
        if camera.name in seen:
            raise DataError(f"{where}: a second camera named {camera.name}")
        seen.add(camera.name)
        cameras.append(camera)
    return cameras


def centre_camera(cameras) -> str:
    """The held-out camera's name: CENTRE_NAME when a camera has it, else the camera whose optical axis
    is closest to the mean of the rig's optical axes (the first on a tie)."""
    names = [c.name for c in cameras]
    if CENTRE_NAME in names:
        return CENTRE_NAME
    axes = np.stack([c.R[2] for c in cameras])
    mean = axes.mean(axis=0)
    return names[int(np.argmax(axes @ mean))]


# -- frames on disk ------------------------------------------------------------------------------------
def natural_order(files) -> list[Path]:
    """Files sorted with numeric names by number (0, 1, 2, ..., 10) before the others by name."""
    return sorted(files, key=lambda p: (0, int(p.stem), p.name) if p.stem.isdigit() else (1, 0, p.name))


def _frame_files(folder: Path) -> list[Path]:
    return natural_order(p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in IMAGE_EXTENSIONS)


def frame_sources(root: Path, models: Path, names: list[str], from_video: bool) -> list[FrameSource]:
    """One FrameSource per camera of `names`: its folder of frames when the cameras have them (and not
    from_video), else its video. DataError naming the file for a camera without its video or frames, and
    for a video or frames folder that no camera of models.json owns."""
    videos: dict[str, Path] = {}
    for p in sorted(root.iterdir()):
        if p.is_file() and p.suffix.lower() in VIDEO_EXTENSIONS:
            if p.stem not in names:
                raise DataError(f"{p}: there is no camera {p.stem} in {models}")
            if p.stem in videos:
                raise DataError(f"{p}: a second video of camera {p.stem} ({videos[p.stem].name})")
            videos[p.stem] = p
    folders = {}
    for p in sorted(root.iterdir()):
        if p.is_dir() and (p.name in names or CAMERA_FOLDER.match(p.name)) and _frame_files(p):
            if p.name not in names:
                raise DataError(f"{p}: frames of a camera {p.name} that {models} does not have")
            folders[p.name] = p
    if folders and not from_video:
        for name in names:
            if name not in folders:
                raise DataError(f"{root / name}: missing: camera {name} of {models} has no frames folder (other "
                                "cameras have one)")
        return [FrameSource(images=_frame_files(folders[n])) for n in names]
    for name in names:
        if name not in videos:
            also = "" if from_video else f" nor frames folder {name}/"
            raise DataError(f"{root / (name + '.mp4')}: missing: camera {name} of {models} has no video{also}")
    return [FrameSource(video=videos[n]) for n in names]


def _scene_fps(root: Path) -> float | None:
    """The fps in scene.json (written by stg-synth), or None."""
    try:
        return float(json.loads((root / "scene.json").read_text()).get("fps"))
    except (OSError, ValueError, TypeError, AttributeError):
        return None


def load_immersive(path, downscale: int = 1, cache_dir=None, num_frames: int | None = None,
                   fps: float | None = None, progress=None, from_video: bool = False,
                   test_camera: str | None = None, lazy: bool = False) -> Dataset:
    """Read an Immersive-layout folder (see the module docstring) into a Dataset.

    from_video: decode the videos even when frames folders exist. test_camera: the held-out camera
    (default: centre_camera). Other arguments as stg_train.data.load_dataset. Raises DataError naming
    the file (and the camera) for every problem with the data, before any frame is decoded.
    """
    root = Path(path)
    if not root.is_dir():
        raise DataError(f"{root}: no such directory")
    models = root / MODELS_FILE
    cameras = read_models(models)
    names = [c.name for c in cameras]
    sources = frame_sources(root, models, names, from_video)
    if test_camera is None:
        test_camera = centre_camera(cameras)
    return build_dataset(root, "immersive", cameras, sources, test_camera=test_camera, downscale=downscale,
                         cache_dir=cache_dir, num_frames=num_frames, fps=fps,
                         default_fps=_scene_fps(root) or DEFAULT_FPS, progress=progress, lazy=lazy,
                         signature={"models": [c.to_dict() for c in cameras]})
