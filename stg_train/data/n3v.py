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

from .dataset import DataError, Dataset, build_frame_cache, common_frames, file_signature

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


def _probe_video(path: Path) -> tuple[int, int, int, float]:
    """(frame count, width, height, fps) of a video, or DataError."""
    import cv2

    cap = cv2.VideoCapture(str(path))
    try:
        if not cap.isOpened():
            raise DataError(f"{path}: cannot be opened as a video")
        count = int(cap.get(cv2.CAP_PROP_FRAME_COUNT))
        width, height = int(cap.get(cv2.CAP_PROP_FRAME_WIDTH)), int(cap.get(cv2.CAP_PROP_FRAME_HEIGHT))
        fps = float(cap.get(cv2.CAP_PROP_FPS))
        if count <= 0:  # no frame count in the container: count by decoding
            count = 0
            while cap.grab():
                count += 1
        if count <= 0 or width <= 0 or height <= 0:
            raise DataError(f"{path}: the video has zero frames")
        return count, width, height, fps
    finally:
        cap.release()


def _read_png(path: Path) -> np.ndarray:
    """(H, W, 3) uint8 RGB, or DataError."""
    import cv2

    img = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if img is None:
        raise DataError(f"{path}: cannot be read as an image")
    return img[..., ::-1]


def _load_poses(path: Path) -> np.ndarray:
    if not path.is_file():
        raise DataError(f"{path}: missing (the N3V layout needs poses_bounds.npy beside the videos)")
    try:
        poses = np.load(path, allow_pickle=False)
    except Exception as e:  # noqa: BLE001 - any failure to parse is a data error
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


def load_n3v(path, downscale: int = 1, cache_dir=None, prefer_png: bool = False, num_frames: int | None = None,
             fps: float | None = None, progress=None) -> Dataset:
    """Read a Neural 3D Video scene folder into a Dataset.

    downscale: integer factor; frames are resized to (W // downscale, H // downscale) with cv2.INTER_AREA
    and fx, fy, cx, cy are divided by it. cache_dir: where the decoded frames go (default
    `<path>/.stg_cache`; a subfolder per source and downscale). prefer_png: read frames/camXX/*.png
    (sorted by name) instead of the videos when that folder exists. num_frames: use only the first
    num_frames frames (default: all; every camera must then have the same count). fps: override the
    frame rate (default: the first video's, else scene.json's, else 30). progress: optional
    callable(done, total) called per decoded frame while the cache is built.

    The held-out test camera is cam00 (the first camera when there is no cam00). Raises DataError,
    naming the file, for every problem with the data.
    """
    root = Path(path)
    if not root.is_dir():
        raise DataError(f"{root}: no such directory")
    if int(downscale) != downscale or downscale < 1:
        raise ValueError(f"downscale must be a positive integer, got {downscale}")
    downscale = int(downscale)
    entries = _cameras_on_disk(root, prefer_png)
    poses_path = root / "poses_bounds.npy"
    poses = _load_poses(poses_path)
    if len(poses) != len(entries):
        kind = "PNG folders" if entries[0][2] is not None else "camXX.mp4 videos"
        raise DataError(f"{poses_path}: has {len(poses)} cameras but there are {len(entries)} {kind}")

    # frame counts and sizes of every camera
    sources, counts, sizes, video_fps = [], [], [], None
    for name, video, folder in entries:
        if folder is not None:
            files = sorted(folder.glob("*.png"))
            if not files:
                raise DataError(f"{folder}: no PNG frames")
            h, w = _read_png(files[0]).shape[:2]
            sources.append((folder, files))
            counts.append(len(files))
        else:
            count, w, h, vfps = _probe_video(video)
            video_fps = video_fps or (vfps if vfps > 0 else None)
            sources.append((video, None))
            counts.append(count)
        sizes.append((w, h))
    labels = [str(src.relative_to(root)) for src, _ in sources]
    num_frames, width, height = common_frames(root, [src for src, _ in sources], labels, counts, sizes, num_frames)
    out_w, out_h = width // downscale, height // downscale
    if out_w < 1 or out_h < 1:
        raise ValueError(f"downscale {downscale} leaves no pixels of {width}x{height} frames")

    cameras = []
    for (name, _, _), row in zip(entries, poses):
        cam = llff_to_camera(row, width, height, name)
        cameras.append(Camera(cam.fx / downscale, cam.fy / downscale, cam.cx / downscale, cam.cy / downscale,
                              out_w, out_h, cam.world_to_camera, name))

    if fps is None:
        fps = video_fps
    if fps is None and (root / "scene.json").is_file():
        try:
            fps = float(json.loads((root / "scene.json").read_text()).get("fps"))
        except (ValueError, TypeError, AttributeError):
            fps = None
    fps = 30.0 if fps is None else float(fps)

    kind = "png" if entries[0][2] is not None else "mp4"
    files = [f for src, pngs in sources for f in (pngs if pngs is not None else [src])]
    signature = {"layout": "n3v", "source": kind, "downscale": downscale, "num_frames": num_frames,
                 "files": [[str(Path(p).relative_to(root)), s, t] for p, s, t in file_signature(files)]}
    shape = (len(cameras), num_frames, out_h, out_w, 3)
    cache_root = Path(cache_dir) if cache_dir is not None else root / ".stg_cache"

    def fill(arr: np.ndarray) -> None:
        total, done = len(cameras) * num_frames, 0
        for ci, (src, pngs) in enumerate(sources):
            frames = _png_frames(pngs, num_frames) if pngs is not None else _video_frames(src, num_frames)
            for k, rgb in enumerate(frames):
                if rgb.shape[:2] != (height, width):
                    where = pngs[k] if pngs is not None else f"{src} frame {k}"
                    raise DataError(f"{where}: is {rgb.shape[1]}x{rgb.shape[0]}, expected {width}x{height}")
                arr[ci, k] = _resize(rgb, out_w, out_h) if downscale > 1 else rgb
                done += 1
                if progress is not None:
                    progress(done, total)

    frames = build_frame_cache(cache_root / f"n3v_{kind}_x{downscale}_f{num_frames}", signature, shape, fill)
    names = [c.name for c in cameras]
    test = [names.index("cam00")] if "cam00" in names else [0]
    return Dataset(cameras, frames, fps, test_cameras=test, bounds=poses[:, 15:17], path=root)


def _resize(rgb: np.ndarray, width: int, height: int) -> np.ndarray:
    import cv2

    return cv2.resize(rgb, (width, height), interpolation=cv2.INTER_AREA)


def _png_frames(files, num_frames: int):
    for f in files[:num_frames]:
        yield _read_png(f)


def _video_frames(path: Path, num_frames: int):
    """The first num_frames frames of a video as (H, W, 3) uint8 RGB; DataError if it has fewer."""
    import cv2

    cap = cv2.VideoCapture(str(path))
    if not cap.isOpened():
        raise DataError(f"{path}: cannot be opened as a video")
    try:
        for k in range(num_frames):
            ok, bgr = cap.read()
            if not ok or bgr is None:
                raise DataError(f"{path}: decoded only {k} of {num_frames} frames")
            yield np.ascontiguousarray(bgr[..., ::-1])
    finally:
        cap.release()
