"""Reader of the Technicolor light-field video layout (Sabater et al. 2017), undistorted version.

    <root>/<Scene>_undist_<frame>_<cam>.png    e.g. Birthday_undist_00151_03.png (5-digit frame, 2-digit camera)
    <root>/cameras_parameters.txt              the undistorted images' calibration

cameras_parameters.txt, as read by the public readers of this dataset (the reference implementation's
Technicolor preprocessing, HyperReel's loader and others, which agree): one header line, then one line per
camera, in camera order (line k + 2 is camera k), of 12 whitespace-separated numbers

    f  cu  cv  ar  sk  qw  qx  qy  qz  tx  ty  tz

focal f in pixels (fx = f, fy = ar * f), principal point (cu, cv), aspect ratio ar, skew sk (must be 0),
and the world-to-camera pose as COLMAP writes it: unit quaternion (qw, qx, qy, qz) of the rotation and the
translation t, x_cam = R x_world + t. The intrinsics refer to the dataset's 2048x1088 images and are
scaled to the PNGs' size; the principal point is used as given, which is COLMAP's (and this project's)
pixel-centre convention, as in the reference code. The "original" (distorted) calibration has 14 numbers
per line (two distortion terms) and is refused. Frames must be consecutive numbers, the same for every
camera. cam10 is held out (the first camera when there is none); fps defaults to 30.
"""
from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from stg_runtime.camera import Camera

from .dataset import DataError, Dataset
from .frames import FrameSource, build_dataset, probe

PARAMETERS = "cameras_parameters.txt"
CALIBRATION_SIZE = (2048, 1088)  # width, height the intrinsics refer to
_FILE = re.compile(r"^(?P<scene>.+)_undist_(?P<frame>\d+)_(?P<cam>\d+)\.png$")


def quaternion_to_matrix(q) -> np.ndarray:
    """(3, 3) rotation of a unit quaternion (w, x, y, z)."""
    w, x, y, z = q
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                     [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                     [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


def read_parameters(path: Path) -> np.ndarray:
    """(num_cameras, 12) float64 rows of cameras_parameters.txt; DataError naming the file and line."""
    if not path.is_file():
        raise DataError(f"{path}: missing (the Technicolor layout needs it beside the PNGs)")
    try:
        lines = path.read_text().splitlines()
    except (OSError, UnicodeDecodeError) as e:
        raise DataError(f"{path}: cannot be read ({e})") from None
    rows = []
    for number, line in enumerate(lines[1:], start=2):
        if not line.strip():
            continue
        try:
            row = [float(v) for v in line.split()]
        except ValueError:
            raise DataError(f"{path}: line {number} is not a list of numbers: {line.strip()[:80]!r}") from None
        if len(row) == 14:
            raise DataError(f"{path}: line {number} has 14 numbers, the distorted ('original') calibration; use "
                            "the undistorted images (<Scene>_undist_*.png) and their cameras_parameters.txt")
        if len(row) != 12 or not np.all(np.isfinite(row)):
            raise DataError(f"{path}: line {number} has {len(row)} numbers, expected 12 finite ones "
                            "(f cu cv ar sk qw qx qy qz tx ty tz)")
        rows.append(row)
    if not rows:
        raise DataError(f"{path}: no camera lines after the header line")
    return np.array(rows, dtype=np.float64)


def parameters_to_camera(row: np.ndarray, width: int, height: int, name: str, where: str) -> Camera:
    """Camera for images of width x height from one cameras_parameters.txt row (see the module docstring)."""
    f, cu, cv, ar, sk = row[:5]
    q, t = row[5:9], row[9:12]
    if abs(sk) > 1e-2:
        raise DataError(f"{where}: camera {name} has skew {sk:g}; only zero-skew pinholes are supported")
    norm = np.linalg.norm(q)
    if not abs(norm - 1) < 1e-3:
        raise DataError(f"{where}: camera {name}'s quaternion (qw qx qy qz) has norm {norm:g}, expected 1")
    if not (f > 0 and ar > 0):
        raise DataError(f"{where}: camera {name} has focal {f:g} and aspect ratio {ar:g}; both must be positive")
    sx, sy = width / CALIBRATION_SIZE[0], height / CALIBRATION_SIZE[1]
    w2c = np.eye(4)
    w2c[:3, :3], w2c[:3, 3] = quaternion_to_matrix(q / norm), t
    return Camera(f * sx, ar * f * sy, cu * sx, cv * sy, width, height, w2c, name)


def load_technicolor(path, downscale: int = 1, cache_dir=None, num_frames: int | None = None, fps: float | None = None,
                     progress=None, test_camera: str | None = None, lazy: bool = False) -> Dataset:
    """Read a Technicolor (undistorted) scene folder into a Dataset.

    num_frames: the first num_frames frames (default: all). fps: default 30. test_camera: default "cam10"
    (the first camera when there is none). Other arguments as stg_train.data.load_dataset. Raises
    DataError naming the file for every problem with the data.
    """
    root = Path(path)
    if not root.is_dir():
        raise DataError(f"{root}: no such directory")
    params_path = root / PARAMETERS
    files: dict[tuple[int, int], Path] = {}
    scenes, digits = set(), {}
    for p in sorted(root.iterdir()):
        m = _FILE.match(p.name)
        if m and p.is_file():
            scenes.add(m.group("scene"))
            files[int(m.group("cam")), int(m.group("frame"))] = p
            digits = {"frame": len(m.group("frame")), "cam": len(m.group("cam"))}
    if not files:
        raise DataError(f"{root}: no <Scene>_undist_<frame>_<cam>.png images")
    if len(scenes) > 1:
        raise DataError(f"{root}: images of several scenes ({', '.join(sorted(scenes))}); keep one per folder")
    scene = scenes.pop()
    rows = read_parameters(params_path)
    cams = sorted({c for c, _ in files})
    frames = sorted({k for _, k in files})
    for c in cams:
        if c >= len(rows):
            example = files[c, min(k for cc, k in files if cc == c)]
            raise DataError(f"{example}: camera {c} has no line in {params_path} (it describes {len(rows)} cameras)")
    for c in range(len(rows)):
        if c not in cams:
            raise DataError(f"{params_path}: camera {c} (line {c + 2}) has no images {scene}_undist_*_"
                            f"{c:0{digits['cam']}d}.png")

    def name(c: int, k: int) -> Path:
        return root / f"{scene}_undist_{k:0{digits['frame']}d}_{c:0{digits['cam']}d}.png"

    for k in range(frames[0], frames[-1] + 1):
        for c in cams:
            if (c, k) not in files:
                raise DataError(f"{name(c, k)}: missing (frames {frames[0]}..{frames[-1]} are present for other "
                                "cameras)")
    if num_frames is not None:
        if num_frames > len(frames):
            raise DataError(f"{root}: has {len(frames)} frames, fewer than the {num_frames} asked for")
        frames = frames[:num_frames]
    sources = [FrameSource(images=[files[c, k] for k in frames]) for c in cams]
    _, width, height, _ = probe(sources[0])
    cameras = [parameters_to_camera(rows[c], width, height, f"cam{c:02d}", str(params_path)) for c in cams]
    names = [c.name for c in cameras]
    if test_camera is None:
        test_camera = "cam10" if "cam10" in names else names[0]
    return build_dataset(root, "technicolor", cameras, sources, test_camera=test_camera, downscale=downscale,
                         cache_dir=cache_dir, num_frames=None, fps=fps, progress=progress, lazy=lazy)
