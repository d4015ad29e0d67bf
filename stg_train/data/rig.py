"""Reader of the plain COLMAP rig layout, for custom captures with a static, calibrated camera rig.

    <root>/images/<camera>/<frame>.png (or .jpg)   frames of each camera, in name order
    <root>/videos/<camera>.mp4 (.mov, .avi, ...)    or one synchronised video per camera
    <root>/sparse/0/cameras.bin, images.bin, ...   ONE COLMAP model of the rig (.bin or .txt)

The model holds one registered image per camera; the image's name says which camera it is:
"<camera>.png" (any extension) or "<camera>/<anything>" (e.g. "cam01/0000.png", the name COLMAP gives
the first frame when it is run on images/). Cameras must be undistorted pinholes or OPENCV_FISHEYE
fisheyes (see colmap.py) with the frames' size. Camera names are the folder (or video) names; cameras are ordered by name. The first
camera in that order is held out unless test_camera names another. fps: the videos', else 30. Near and
far depth bounds come from the model's 3D points when it has them (stg_train.data.bounds).
"""
from __future__ import annotations

from pathlib import Path, PurePosixPath

from .bounds import model_bounds
from .colmap import MODEL_FILES, cameras_from_reconstruction, read_reconstruction
from .dataset import DataError, Dataset
from .frames import VIDEO_EXTENSIONS, FrameSource, build_dataset, image_files


def rig_camera_name(image_name: str) -> str:
    """The camera a model image belongs to: "cam01/0000.png" -> "cam01", "cam01.png" -> "cam01"."""
    parts = PurePosixPath(image_name.replace("\\", "/")).parts
    return parts[0] if len(parts) > 1 else PurePosixPath(parts[0]).stem


def model_folder(root: Path) -> Path:
    """<root>/sparse/0, or <root>/sparse when the model files lie directly in it."""
    sparse = root / "sparse"
    if not (sparse / "0").is_dir() and any((sparse / f"{n}{e}").is_file() for n in MODEL_FILES for e in (".bin", ".txt")):
        return sparse
    return sparse / "0"


def _frame_sources(root: Path, from_video: bool) -> dict[str, FrameSource]:
    images, videos = root / "images", root / "videos"
    if videos.is_dir() and (from_video or not images.is_dir()):
        found: dict[str, FrameSource] = {}
        for p in sorted(videos.iterdir()):
            if p.is_file() and p.suffix.lower() in VIDEO_EXTENSIONS:
                if p.stem in found:
                    raise DataError(f"{p}: a second video of camera {p.stem} ({found[p.stem].video.name})")
                found[p.stem] = FrameSource(video=p)
        if not found:
            raise DataError(f"{videos}: no videos ({', '.join(VIDEO_EXTENSIONS)})")
        return found
    if not images.is_dir():
        raise DataError(f"{root}: no images/ or videos/ folder (the rig layout needs images/<camera>/<frame>.png "
                        "or videos/<camera>.mp4)")
    folders = sorted(p for p in images.iterdir() if p.is_dir() and not p.name.startswith("."))
    if not folders:
        loose = image_files(images)
        hint = f" ({loose[0].name} lies directly in images/)" if loose else ""
        raise DataError(f"{images}: no camera folders{hint}; put each camera's frames in images/<camera>/")
    found = {}
    for folder in folders:
        files = image_files(folder)
        if not files:
            raise DataError(f"{folder}: no frames (png or jpg)")
        found[folder.name] = FrameSource(images=files)
    return found


def load_rig(path, downscale: int = 1, cache_dir=None, num_frames: int | None = None, fps: float | None = None,
             progress=None, from_video: bool = False, test_camera: str | None = None, lazy: bool = False) -> Dataset:
    """Read a rig-layout folder into a Dataset.

    from_video: read videos/ even when images/ exists (default: images/ when both exist). test_camera:
    held-out camera name (default: the first in sorted order). Other arguments as
    stg_train.data.load_dataset. Raises DataError naming the file for every problem with the data.
    """
    root = Path(path)
    if not root.is_dir():
        raise DataError(f"{root}: no such directory")
    sources = _frame_sources(root, from_video)
    model = model_folder(root)
    rec = read_reconstruction(model)
    calibrated = cameras_from_reconstruction(rec, str(model), name_of=rig_camera_name)
    by_name: dict = {}
    for im_name, cam in zip(sorted(im.name for im in rec.images.values()), calibrated):
        if cam.name in by_name:
            raise DataError(f"{model}: holds several images of camera {cam.name} ({by_name[cam.name][0]}, {im_name}); "
                            "the rig model needs exactly one image per camera")
        by_name[cam.name] = (im_name, cam)
    for name, src in sources.items():
        if name not in by_name:
            raise DataError(f"{src.path}: camera {name} has no image in the COLMAP model {model} (its images: "
                            f"{', '.join(sorted(i for i, _ in by_name.values()))})")
    kind = "videos" if next(iter(sources.values())).video is not None else "images"
    for name, (im_name, _) in sorted(by_name.items()):
        if name not in sources:
            where = root / kind / (name if kind == "images" else f"{name}.mp4")
            raise DataError(f"{where}: missing: the COLMAP model {model} has image {im_name} of camera {name} but "
                            f"{kind}/ has no frames for it")
    names = sorted(sources)
    cameras = [by_name[n][1] for n in names]
    if test_camera is None:
        test_camera = names[0]
    bounds = model_bounds(rec, cameras)
    return build_dataset(root, "rig", cameras, [sources[n] for n in names], test_camera=test_camera,
                         downscale=downscale, cache_dir=cache_dir, num_frames=num_frames, fps=fps, progress=progress,
                         lazy=lazy, bounds=bounds, bounds_source="colmap")
