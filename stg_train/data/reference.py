"""Reader of the reference implementation's preprocessed layout (one COLMAP project per frame).

    <root>/colmap_0/images/cam00.png, cam01.png, ...     frame 0 of every camera
    <root>/colmap_0/sparse/0/cameras.bin, images.bin, points3D.bin (or .txt)
    <root>/colmap_1/...                                  frame 1, ... up to colmap_<F-1>

The cameras come from colmap_0's model (image "cam00.png" -> camera "cam00"); every other frame's model
must hold the same images with the same calibration (the reference triangulates each frame with the
poses held fixed). Frame i of a camera is colmap_<i>/images/<its image name>. The layout stores no
frame rate: fps defaults to 30. cam00 is held out (the first camera when there is none). Near and far
depth bounds come from colmap_0's 3D points when it has them (stg_train.data.bounds).
"""
from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from .bounds import model_bounds
from .colmap import cameras_from_reconstruction, read_reconstruction
from .dataset import DataError, Dataset
from .frames import FrameSource, build_dataset, file_signature, image_files

_FRAME_DIR = re.compile(r"^colmap_(\d+)$")


def frame_folders(root: Path) -> list[Path]:
    """colmap_0, colmap_1, ... in frame order; DataError when there is none or one is missing."""
    numbers = sorted(int(m.group(1)) for p in root.iterdir() if p.is_dir() and (m := _FRAME_DIR.match(p.name)))
    if not numbers:
        raise DataError(f"{root}: no colmap_<i> folders (the reference layout has colmap_0, colmap_1, ...)")
    for expected, n in enumerate(numbers):
        if n != expected:
            raise DataError(f"{root / f'colmap_{expected}'}: missing (found colmap_{n} after colmap_{expected - 1})"
                            if expected else f"{root / 'colmap_0'}: missing (frames start at colmap_0)")
    return [root / f"colmap_{n}" for n in numbers]


def _same_camera(a, b) -> bool:
    scale = 1.0 + np.abs(a.world_to_camera[:3, 3]).max()
    return ((a.width, a.height, a.model) == (b.width, b.height, b.model)
            and np.allclose(a.distortion, b.distortion, rtol=1e-5, atol=1e-8)
            and np.allclose([a.fx, a.fy, a.cx, a.cy], [b.fx, b.fy, b.cx, b.cy], rtol=1e-5, atol=1e-6)
            and np.allclose(a.R, b.R, atol=1e-5) and np.allclose(a.t, b.t, atol=1e-5 * scale))


def load_reference(path, downscale: int = 1, cache_dir=None, num_frames: int | None = None, fps: float | None = None,
                   progress=None, test_camera: str | None = None, lazy: bool = False) -> Dataset:
    """Read the reference implementation's colmap_<i> layout into a Dataset.

    num_frames: use colmap_0 .. colmap_<num_frames-1> only (default: all). fps: default 30. test_camera:
    default "cam00". Other arguments as stg_train.data.load_dataset. Every frame folder's model is
    checked against colmap_0's when the frame cache is built. Raises DataError naming the file.
    """
    root = Path(path)
    if not root.is_dir():
        raise DataError(f"{root}: no such directory")
    folders = frame_folders(root)
    if num_frames is not None:
        if num_frames > len(folders):
            raise DataError(f"{root}: has {len(folders)} colmap_<i> frame folders, fewer than the {num_frames} asked for")
        folders = folders[:num_frames]
    model0 = folders[0] / "sparse" / "0"
    rec0 = read_reconstruction(model0)
    cameras = cameras_from_reconstruction(rec0, str(model0))
    image_names = sorted(im.name for im in rec0.images.values())

    # every frame folder: the model's files and exactly the model's images
    model_files = []
    for folder in folders:
        sparse, images = folder / "sparse" / "0", folder / "images"
        read_files = [p for p in sorted(sparse.glob("*")) if p.suffix in (".bin", ".txt")] if sparse.is_dir() else []
        if not read_files:
            raise DataError(f"{sparse}: missing or empty (each colmap_<i> folder needs its COLMAP model)")
        model_files += read_files
        if not images.is_dir():
            raise DataError(f"{images}: missing (each colmap_<i> folder needs images/camXX.png)")
        for name in image_names:
            if not (images / name).is_file():
                raise DataError(f"{images / name}: missing (camera {Path(name).stem} of {model0} has no frame "
                                f"{folder.name})")
        extra = sorted(p.name for p in image_files(images) if p.name not in image_names)
        if extra:
            raise DataError(f"{images / extra[0]}: this image is not in the COLMAP model {model0} (its images: "
                            f"{', '.join(image_names)})")
    sources = [FrameSource(images=[folder / "images" / name for folder in folders]) for name in image_names]

    def check_models() -> None:
        for folder in folders[1:]:
            sparse = folder / "sparse" / "0"
            cams = cameras_from_reconstruction(read_reconstruction(sparse), str(sparse))
            if [c.name for c in cams] != [c.name for c in cameras]:
                raise DataError(f"{sparse}: has images {', '.join(c.name for c in cams)}; {model0} has "
                                f"{', '.join(c.name for c in cameras)}")
            for a, b in zip(cams, cameras):
                if not _same_camera(a, b):
                    raise DataError(f"{sparse}: camera {a.name} differs from its calibration in {model0} (every "
                                    "frame must share colmap_0's intrinsics and poses)")

    names = [c.name for c in cameras]
    if test_camera is None:
        test_camera = "cam00" if "cam00" in names else names[0]
    signature = {"models": [[str(Path(p).relative_to(root)), s, t] for p, s, t in file_signature(model_files)]}
    return build_dataset(root, "reference", cameras, sources, test_camera=test_camera, downscale=downscale,
                         cache_dir=cache_dir, num_frames=None, fps=fps, progress=progress, signature=signature,
                         check=check_models, lazy=lazy, bounds=model_bounds(rec0, cameras), bounds_source="colmap")
