"""Writing the prepared rig (the "rig" layout of docs/datasets.md, read by stg_train.data.rig):

    OUT/images/<camera>/<frame:05d>.png   the synchronised frames, frame 0 of every camera the same moment
    OUT/sparse/0/cameras.bin images.bin points3D.bin   the calibration: one image per camera
    OUT/prep.json                           the report (stg_train.prep.prepare)

Cameras fitted with OpenCV's distortion (k1, k2, p1, p2) are undistorted into the written frames (same
size, same focal length and principal point) and written as PINHOLE; fisheyes go as OPENCV_FISHEYE,
the frames as recorded.
"""
from __future__ import annotations

import json
from pathlib import Path
from typing import Callable

import numpy as np

from stg_runtime.atomic import write_atomic
from stg_runtime.camera import Camera

from .inputs import Clip, PrepError

REPORT = "prep.json"


def undistorter(camera: Camera, distortion) -> Callable[[np.ndarray], np.ndarray]:
    """rgb (H, W, 3) of a pinhole `camera` with OpenCV distortion (k1, k2, p1, p2) -> the undistorted
    picture of the same camera without it (bilinear). The camera's principal point is in the project's
    convention (pixel centres at +0.5), OpenCV's half a pixel less."""
    import cv2

    k = np.array([[camera.fx, 0, camera.cx - 0.5], [0, camera.fy, camera.cy - 0.5], [0, 0, 1]])
    maps = cv2.initUndistortRectifyMap(k, np.asarray(distortion, np.float64), None, k,
                                       (camera.width, camera.height), cv2.CV_32FC1)
    return lambda rgb: cv2.remap(rgb, maps[0], maps[1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)


def write_frames(out: Path, clips: list[Clip], offsets: list[int], num_frames: int, cameras: list[Camera],
                 distortion: dict, progress: Callable[[int, int], None] | None = None) -> None:
    """Frames offsets[c] .. offsets[c] + num_frames - 1 of every clip into out/images/<name>/<k:05d>.png
    (k from 0), undistorted where `distortion` (name -> k1, k2, p1, p2) has the camera."""
    import cv2

    total, done = len(clips) * num_frames, 0
    for clip, offset, camera in zip(clips, offsets, cameras):
        folder = out / "images" / clip.name
        folder.mkdir(parents=True, exist_ok=True)
        fix = undistorter(camera, distortion[clip.name]) if clip.name in distortion else None
        for k, rgb in enumerate(clip.read(offset, num_frames)):
            rgb = fix(rgb) if fix is not None else rgb
            if not cv2.imwrite(str(folder / f"{k:05d}.png"), np.ascontiguousarray(rgb[..., ::-1])):
                raise PrepError(f"{folder / f'{k:05d}.png'}: cannot be written")
            done += 1
            if progress is not None:
                progress(done, total)


def write_model(out: Path, cameras: list[Camera], points: np.ndarray, colours: np.ndarray) -> None:
    """The COLMAP model of the rig into out/sparse/0: one image per camera, named <camera>.png, and the
    3D points (without tracks: they give the depth bounds)."""
    import pycolmap

    from ..data.colmap import reconstruction_from_cameras, write_reconstruction

    rec = reconstruction_from_cameras(cameras)
    rgb = np.clip(np.round(np.asarray(colours) * 255), 0, 255).astype(np.uint8)
    for xyz, c in zip(np.asarray(points, np.float64), rgb):
        rec.add_point3D(xyz, pycolmap.Track(), c)
    write_reconstruction(rec, out / "sparse" / "0")


def write_report(out: Path, report: dict) -> None:
    """out/prep.json, atomically."""
    write_atomic(out / REPORT, json.dumps(report, indent=2) + "\n")


def read_report(folder) -> dict | None:
    """A prepared folder's prep.json, or None when it has none (or an unreadable one)."""
    try:
        return json.loads((Path(folder) / REPORT).read_text())
    except (OSError, ValueError):
        return None
