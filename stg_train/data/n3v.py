"""Reader of the Neural 3D Video (N3V) layout.

    <scene>/cam00.mp4, cam01.mp4, ...     one synchronised video per camera
    <scene>/poses_bounds.npy              (num_cameras, 17) LLFF poses, one row per video in camera order
    <scene>/frames/camXX/*.png            optional lossless frames (read with prefer_png=True)

An LLFF row is a flattened 3x5 matrix [R | centre | (H, W, focal)], camera-to-world with the rotation's
columns the camera's [down, right, backwards] axes in world coordinates, followed by the near and far
depth bounds. Principal point at the image centre. cam00 is held out for testing.
"""
from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np

from stg_runtime.camera import Camera

from .dataset import DataError, Dataset
from .frames import DEFAULT_FPS, FrameSource, build_dataset

_VIDEO = re.compile(r"^cam(\d+)\.mp4$")
_FOLDER = re.compile(r"^cam(\d+)$")


def llff_to_camera(row: np.ndarray, width: int, height: int, name: str = "") -> Camera:
    """Camera (OpenCV axes, world-to-camera) from one poses_bounds row (17,) for images of width x height.

    The pose's (H, W, focal) refers to the resolution the poses were made for: the focal is scaled by
    width / W (fx) and height / H (fy); cx = width / 2, cy = height / 2.
    """
    m = np.asarray(row[:15], dtype=np.float64).reshape(3, 5)
    down, right, backwards, centre = m[:, 0], m[:, 1], m[:, 2], m[:, 3]
    h0, w0, focal = m[:, 4]
    R = np.stack([right, down, -backwards])  # rows: camera x, y, z in world coordinates
    w2c = np.eye(4)
    w2c[:3, :3] = R
    w2c[:3, 3] = -R @ centre
    return Camera(focal * width / w0, focal * height / h0, width / 2, height / 2, width, height, w2c, name)


def _load_poses(path: Path) -> np.ndarray:
    if not path.is_file():
        raise DataError(f"{path}: missing (the N3V layout needs poses_bounds.npy beside the videos; "
                        "stg-prep calibrates videos that have no poses)")
    try:
        with open(path, "rb") as f:
            magic = f.read(6)
        if magic != b"\x93NUMPY":
            raise DataError(f"{path}: cannot be read: not a numpy .npy file (it does not start with numpy's "
                            "magic bytes)")
        poses = np.load(path, allow_pickle=False)
    except OSError as e:
        raise DataError(f"{path}: cannot be read ({e.strerror or e})") from None
    except (ValueError, EOFError) as e:  # a damaged .npy: numpy's own message
        raise DataError(f"{path}: cannot be read as a numpy array ({e})") from None
    if poses.ndim != 2 or poses.shape[1] != 17 or not np.issubdtype(poses.dtype, np.number):
        raise DataError(f"{path}: has shape {poses.shape} (dtype {poses.dtype}), expected (num_cameras, 17)")
    poses = poses.astype(np.float64)
    if not np.all(np.isfinite(poses)):
        raise DataError(f"{path}: contains non-finite values")
    for i, row in enumerate(poses):
        R = row[:15].reshape(3, 5)[:, :3]
        if not np.allclose(R @ R.T, np.eye(3), atol=1e-3):
            raise DataError(f"{path}: row {i} does not hold a rotation matrix")
        if row[4] <= 0 or row[9] <= 0 or row[14] <= 0:
            raise DataError(f"{path}: row {i} has a non-positive image size or focal (H, W, focal = "
                            f"{row[4]:g}, {row[9]:g}, {row[14]:g})")
        if not 0 < row[15] < row[16]:
            raise DataError(f"{path}: row {i} has near/far depth bounds {row[15]:g}, {row[16]:g}; they must "
                            "satisfy 0 < near < far")
    return poses


def _cameras_on_disk(root: Path, prefer_png: bool):
    """[(name, video path or None, png folder or None)] sorted by camera number."""
    videos = {int(m.group(1)): root / p.name for p in root.iterdir() if (m := _VIDEO.match(p.name))}
    folders = {}
    if prefer_png and (root / "frames").is_dir():
        folders = {int(m.group(1)): p for p in (root / "frames").iterdir() if p.is_dir() and (m := _FOLDER.match(p.name))}
    numbers = sorted(videos) if videos else sorted(folders)
    if not numbers:
        raise DataError(f"{root}: no camXX.mp4 videos" + (" and no frames/camXX folders" if prefer_png else ""))
    out = []
    for n in numbers:
        video = videos.get(n)
        name = video.stem if video is not None else folders[n].name
        folder = folders.get(n)
        if prefer_png and folders and folder is None:
            raise DataError(f"{root / 'frames' / name}: missing (other cameras have PNG frames)")
        out.append((name, video, folder if prefer_png else None))
    return out


def _scene_fps(root: Path) -> float | None:
    """The fps in scene.json (written by stg-synth), or None."""
    try:
        return float(json.loads((root / "scene.json").read_text()).get("fps"))
    except (OSError, ValueError, TypeError, AttributeError):
        return None


def load_n3v(path, downscale: int = 1, cache_dir=None, prefer_png: bool = False, num_frames: int | None = None,
             fps: float | None = None, progress=None, test_camera: str | None = None, lazy: bool = False) -> Dataset:
    """Read a Neural 3D Video scene folder into a Dataset (frames through stg_train.data.frames).

    downscale: integer factor; frames are resized to (W // downscale, H // downscale) with cv2.INTER_AREA
    and fx, fy, cx, cy are divided by it. cache_dir: where the decoded frames go (default
    `<path>/.stg_cache`). prefer_png: read frames/camXX/*.png (sorted by name) instead of the videos when
    that folder exists. num_frames: use only the first num_frames frames (default: all; every camera
    must then have the same count). fps: override the frame rate (default: the videos', else
    scene.json's, else 30). progress: optional callable(done, total) called per decoded frame while the
    cache is built. test_camera: the held-out camera (default cam00, the first camera when there is no
    cam00). lazy: decode nothing now (stg_train.data.frames.ChunkedFrames).

    Near and far depth bounds per camera come from poses_bounds.npy. Raises DataError, naming the file,
    for every problem with the data.
    """
    root = Path(path)
    if not root.is_dir():
        raise DataError(f"{root}: no such directory")
    entries = _cameras_on_disk(root, prefer_png)
    poses_path = root / "poses_bounds.npy"
    poses = _load_poses(poses_path)
    if len(poses) != len(entries):
        kind = "PNG folders" if entries[0][2] is not None else "camXX.mp4 videos"
        raise DataError(f"{poses_path}: has {len(poses)} cameras but there are {len(entries)} {kind}")
    sources = []
    for name, video, folder in entries:
        if folder is None:
            sources.append(FrameSource(video=video))
            continue
        files = sorted(folder.glob("*.png"))
        if not files:
            raise DataError(f"{folder}: no PNG frames")
        sources.append(FrameSource(images=files))

    def cameras(width: int, height: int) -> list[Camera]:
        return [llff_to_camera(row, width, height, name) for (name, _, _), row in zip(entries, poses)]

    names = [name for name, _, _ in entries]
    if test_camera is None:
        test_camera = "cam00" if "cam00" in names else names[0]
    return build_dataset(root, "n3v", cameras, sources, test_camera=test_camera, downscale=downscale,
                         cache_dir=cache_dir, num_frames=num_frames, fps=fps,
                         default_fps=_scene_fps(root) or DEFAULT_FPS, bounds=poses[:, 15:17], progress=progress, lazy=lazy)
