"""COLMAP models (read and written with pycolmap) <-> the project's Camera.

COLMAP's conventions are the project's: world-to-camera poses ("cam_from_world") in OpenCV axes, and the
centre of pixel (column u, row v) at (u + 0.5, v + 0.5), so intrinsics and poses are copied unchanged.
Accepted camera models: the undistorted pinholes PINHOLE and SIMPLE_PINHOLE (and SIMPLE_RADIAL, RADIAL
or OPENCV when all their distortion parameters are zero), and OPENCV_FISHEYE (fx, fy, cx, cy, k1..k4:
OpenCV's fisheye model, the project's "fisheye" Camera, formats/stg-v1.md section 1). Every other model
is refused. Cameras written to COLMAP go as PINHOLE or OPENCV_FISHEYE.

A model folder (e.g. `sparse/0`) holds cameras, images and points3D as .bin or .txt files, plus rigs
and frames when written by COLMAP 4; older models without rigs and frames are read as well.
"""
from __future__ import annotations

from pathlib import Path, PurePosixPath
from typing import Callable

import numpy as np

from stg_runtime.camera import Camera

from .dataset import DataError

#: COLMAP camera models accepted (the distortion ones only with zero distortion).
PINHOLE_MODELS = ("PINHOLE", "SIMPLE_PINHOLE")
ZERO_DISTORTION_MODELS = ("SIMPLE_RADIAL", "RADIAL", "OPENCV")
#: COLMAP's fisheye model that is the project's "fisheye" Camera.
FISHEYE_MODEL = "OPENCV_FISHEYE"
MODEL_FILES = ("cameras", "images", "points3D")


def _pycolmap():
    try:
        import pycolmap
    except ImportError as e:  # pragma: no cover - pycolmap is a dependency of stg_train
        raise DataError(f"reading COLMAP models needs pycolmap ({e})") from None
    return pycolmap


def image_stem(image_name: str) -> str:
    """The default camera name of a COLMAP image: its name without the extension ("cam00.png" -> "cam00")."""
    p = PurePosixPath(image_name.replace("\\", "/"))
    return str(p.with_suffix("")) if p.suffix else str(p)


def reconstruction_from_cameras(cameras: list[Camera], image_names: list[str] | None = None):
    """A pycolmap.Reconstruction with one camera (PINHOLE, or OPENCV_FISHEYE for a fisheye Camera) and
    one registered image per Camera.

    camera_id = image_id = index + 1; each camera gets a trivial rig and each image a trivial frame
    (pycolmap 4 registers images through frames); image names default to f"{camera.name}.png"; poses
    are the cameras' world_to_camera; no 3D points.
    """
    pycolmap = _pycolmap()
    if image_names is None:
        image_names = [f"{cam.name}.png" for cam in cameras]
    if len(image_names) != len(cameras):
        raise ValueError(f"{len(image_names)} image names for {len(cameras)} cameras")
    rec = pycolmap.Reconstruction()
    for i, (cam, name) in enumerate(zip(cameras, image_names)):
        fisheye = cam.model == "fisheye"
        ccam = pycolmap.Camera.create_from_model_name(i + 1, FISHEYE_MODEL if fisheye else "PINHOLE", cam.fx,
                                                      cam.width, cam.height)
        ccam.params = [cam.fx, cam.fy, cam.cx, cam.cy] + (list(cam.distortion) if fisheye else [])
        rec.add_camera_with_trivial_rig(ccam)
        image = pycolmap.Image(name=name, camera_id=i + 1, image_id=i + 1)
        rec.add_image_with_trivial_frame(image, pycolmap.Rigid3d(np.asarray(cam.world_to_camera[:3], dtype=np.float64)))
    return rec


def _intrinsics(ccam, where: str) -> tuple[float, float, float, float, str, tuple]:
    """(fx, fy, cx, cy, model, distortion) of the Camera of a COLMAP camera (see the module docstring),
    else DataError."""
    model = ccam.model_name
    params = np.asarray(ccam.params, dtype=np.float64)
    if model == FISHEYE_MODEL:
        fx, fy, cx, cy = params[:4]
        return fx, fy, cx, cy, "fisheye", tuple(params[4:8])
    if model not in PINHOLE_MODELS + ZERO_DISTORTION_MODELS:
        raise DataError(f"{where}: camera {ccam.camera_id} uses the {model} model, which this project cannot "
                        f"represent; supported: {', '.join(PINHOLE_MODELS)} (undistorted pinholes) and "
                        f"{FISHEYE_MODEL}: undistort the images first (e.g. colmap image_undistorter or "
                        "pycolmap.undistort_images)")
    extra = params[list(ccam.extra_params_idxs())] if model in ZERO_DISTORTION_MODELS else np.zeros(0)
    if np.any(extra != 0):
        raise DataError(f"{where}: camera {ccam.camera_id} ({model}) has lens distortion "
                        f"{np.array2string(extra, precision=4)}; the images must be undistorted first "
                        "(e.g. colmap image_undistorter or pycolmap.undistort_images)")
    if model in ("SIMPLE_PINHOLE", "SIMPLE_RADIAL", "RADIAL"):
        f, cx, cy = params[:3]
        return f, f, cx, cy, "pinhole", ()
    fx, fy, cx, cy = params[:4]
    return fx, fy, cx, cy, "pinhole", ()


def cameras_from_reconstruction(rec, source: str, name_of: Callable[[str], str] = image_stem) -> list[Camera]:
    """One Camera per image of a COLMAP model, ordered by image name.

    source: the model's path, named in errors. name_of: image name -> Camera.name (default: the image
    name without its extension). Raises DataError for an image without a pose, a camera model this
    project cannot represent (a distorted pinhole, a fisheye model other than OPENCV_FISHEYE), or invalid
    intrinsics.
    """
    images = sorted(rec.images.values(), key=lambda im: im.name)
    if not images:
        raise DataError(f"{source}: the COLMAP model has no images")
    cams = []
    for im in images:
        if not im.has_pose:
            raise DataError(f"{source}: image {im.name} is not registered (it has no pose)")
        ccam = rec.cameras[im.camera_id]
        fx, fy, cx, cy, model, distortion = _intrinsics(ccam, source)
        w2c = np.eye(4)
        w2c[:3] = im.cam_from_world().matrix()
        try:
            cams.append(Camera(fx, fy, cx, cy, ccam.width, ccam.height, w2c, name_of(im.name), model, distortion))
        except ValueError as e:
            raise DataError(f"{source}: image {im.name}: {e}") from None
    return cams


def read_reconstruction(path):
    """Read a COLMAP model folder (cameras, images, points3D as .bin or .txt) -> pycolmap.Reconstruction.

    Raises DataError naming the folder when it is missing, lacks the model files or cannot be parsed.
    """
    pycolmap = _pycolmap()
    path = Path(path)
    if not path.is_dir():
        raise DataError(f"{path}: missing (expected a COLMAP model folder with cameras, images, points3D "
                        ".bin or .txt)")
    for ext in (".bin", ".txt"):
        if all((path / f"{n}{ext}").is_file() for n in MODEL_FILES):
            break
    else:
        missing = [f"{n}.bin" for n in MODEL_FILES if not (path / f"{n}.bin").is_file()]
        raise DataError(f"{path}: not a COLMAP model (no {', '.join(missing)} nor the .txt equivalents)")
    try:
        return pycolmap.Reconstruction(str(path))
    except Exception as e:  # noqa: BLE001 - pycolmap raises ValueError/RuntimeError for bad files
        raise DataError(f"{path}: cannot read the COLMAP model ({str(e).strip()})") from None


def write_reconstruction(rec, path, text: bool = False) -> None:
    """Write a pycolmap.Reconstruction into folder `path` (created if missing); binary, or text if asked."""
    path = Path(path)
    path.mkdir(parents=True, exist_ok=True)
    if text:
        rec.write_text(str(path))
    else:
        rec.write_binary(str(path))


def reconstruction_points(rec) -> tuple[np.ndarray, np.ndarray]:
    """The model's 3D points: xyz (N, 3) float64 (world units) and rgb (N, 3) float32 in [0, 1]."""
    points = list(rec.points3D.values())
    if not points:
        return np.zeros((0, 3)), np.zeros((0, 3), np.float32)
    xyz = np.array([p.xyz for p in points], dtype=np.float64).reshape(-1, 3)
    rgb = np.array([p.color for p in points], dtype=np.float32).reshape(-1, 3) / 255.0
    return xyz, rgb
