"""Initial points from structure-from-motion with the dataset's known poses (pycolmap, no COLMAP binary).

For every `every`-th frame j, the training cameras' images of frame j go through pycolmap's SIFT
extraction (CPU) and exhaustive matching, and the matches are triangulated with the cameras' poses and
intrinsics held fixed (pycolmap.triangulate_points), as the reference preprocessing does with COLMAP per
frame. Fisheye cameras go to COLMAP as OPENCV_FISHEYE (stg_train.data.colmap), and their matches are
verified against the known poses (pycolmap.guided_geometric_verification) rather than by RANSAC. The
frames' points are merged with temporal centre j / num_frames and subsampled as the reference does:
the first frame keeps all its points, every other frame keeps KEEP_FRACTION of its points chosen by
farthest-point sampling (each kept point is the one farthest from the points kept before it), so
repeated static structure is thinned while the coverage of each frame is kept.

The result is cached as an .npz (default folder `<dataset.path>/.stg_cache/sfm/`), keyed by the cameras,
a sample of the frames' pixels and the settings, so a second run does not run pycolmap again.
stg_train.data.points.initial_points falls back to the view-volume sampler with a warning when SfM
finds fewer than MIN_SFM_POINTS points (an untextured scene, too few cameras).
"""
from __future__ import annotations

import contextlib
import hashlib
import json
import tempfile
import warnings
from pathlib import Path
from typing import Callable, Sequence

import numpy as np

from stg_runtime.atomic import atomic_output, remove_leftovers

from .colmap import reconstruction_from_cameras, reconstruction_points
from .dataset import DataError

#: Fewer SfM points than this (over all frames) and initial_points uses the view-volume sampler instead.
MIN_SFM_POINTS = 100
#: Fraction of the points of every frame but the first that is kept (the reference's 1 in 4).
KEEP_FRACTION = 0.25
#: Bumped when the pipeline changes, so older caches are not reused.
CACHE_VERSION = 2


def _pycolmap():
    try:
        import pycolmap
    except ImportError as e:  # pragma: no cover - pycolmap is a dependency of stg_train
        raise DataError(f"SfM initialisation needs pycolmap ({e})") from None
    return pycolmap


@contextlib.contextmanager
def _quiet_pycolmap(pycolmap):
    """Silence pycolmap's (glog) INFO and WARNING lines inside the block."""
    level = pycolmap.logging.minloglevel
    pycolmap.logging.minloglevel = 2
    try:
        yield
    finally:
        pycolmap.logging.minloglevel = level


# -- one frame --------------------------------------------------------------------------------------
def frame_points(dataset, frame: int, work_dir, cameras: Sequence[int] | None = None,
                 max_features: int = 8192, threads: int = -1) -> tuple[np.ndarray, np.ndarray]:
    """SfM points of one frame: xyz (N, 3) float64 world units, rgb (N, 3) float32 in [0, 1].

    cameras: dataset camera indices whose images are used (default: the training cameras); work_dir: an
    empty folder for the images, the feature database and the model. threads: CPU threads (-1: all).
    """
    import cv2

    pycolmap = _pycolmap()
    cameras = list(dataset.train_cameras if cameras is None else cameras)
    work = Path(work_dir)
    images = work / "images"
    images.mkdir(parents=True, exist_ok=True)
    by_name = {}
    for ci in cameras:
        name = f"{ci:04d}.png"
        if not cv2.imwrite(str(images / name), np.ascontiguousarray(dataset.frame(ci, frame)[..., ::-1])):
            raise DataError(f"{images / name}: cannot write the image for SfM")
        by_name[name] = dataset.cameras[ci]
    names = sorted(by_name)
    extraction = pycolmap.FeatureExtractionOptions()
    extraction.num_threads = threads
    extraction.sift.max_num_features = max_features
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = "PINHOLE"
    matching = pycolmap.FeatureMatchingOptions()
    matching.num_threads = threads
    rec = reconstruction_from_cameras([by_name[n] for n in names], names)
    with _quiet_pycolmap(pycolmap):
        pycolmap.extract_features(work / "features.db", images, image_names=names,
                                  camera_mode=pycolmap.CameraMode.PER_IMAGE, reader_options=reader,
                                  extraction_options=extraction, device=pycolmap.Device.cpu)
        # Extraction numbers images in the order its threads finish: copy the features into a database
        # whose rigs, cameras, frames and images are the model's (same ids, known intrinsics).
        database = work / "database.db"
        _database_from_model(pycolmap, rec, work / "features.db", database)
        pycolmap.match_exhaustive(database, matching_options=matching, device=pycolmap.Device.cpu)
        if any(cam.model != "pinhole" for cam in by_name.values()):
            # RANSAC's verification keeps matches through an essential matrix, else a fundamental matrix or
            # homography in pixel coordinates, which no fisheye pair satisfies: verify with the known poses.
            pycolmap.guided_geometric_verification(rec, database, num_threads=threads)
        (work / "sparse").mkdir(exist_ok=True)
        rec = pycolmap.triangulate_points(rec, database, images, work / "sparse")
    return reconstruction_points(rec)


def _database_from_model(pycolmap, rec, features_path: Path, database_path: Path) -> None:
    """Write database_path with rec's rigs, cameras, frames and images (their ids) and the keypoints and
    descriptors of the same-named images of the database features_path."""
    features = pycolmap.Database.open(str(features_path))
    db = pycolmap.Database.open(str(database_path))
    try:
        for rig in rec.rigs.values():
            db.write_rig(rig, use_rig_id=True)
        for cam in rec.cameras.values():
            db.write_camera(cam, use_camera_id=True)
        for frame in rec.frames.values():
            db.write_frame(frame, use_frame_id=True)
        for image in rec.images.values():
            db.write_image(image, use_image_id=True)
            source = features.read_image_with_name(image.name)
            db.write_keypoints(image.image_id, features.read_keypoints(source.image_id))
            db.write_descriptors(image.image_id, features.read_descriptors(source.image_id))
    finally:
        db.close()
        features.close()


# -- merging ----------------------------------------------------------------------------------------
def farthest_point_indices(xyz: np.ndarray, count: int, rng: np.random.Generator) -> np.ndarray:
    """Indices of `count` of the points xyz (N, 3) by farthest-point sampling from a random start."""
    n = len(xyz)
    if count >= n:
        return np.arange(n)
    chosen = np.empty(count, np.int64)
    chosen[0] = rng.integers(n)
    dist = np.full(n, np.inf)
    for k in range(1, count):
        dist = np.minimum(dist, np.sum((xyz - xyz[chosen[k - 1]]) ** 2, axis=1))
        chosen[k] = int(np.argmax(dist))
    return chosen


def merge_frames(per_frame: Sequence[tuple[np.ndarray, np.ndarray, float]], keep: float = KEEP_FRACTION,
                 seed: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Merge per-frame (xyz (N, 3), rgb (N, 3), t) lists: the first frame keeps every point, the others
    round(keep x N) chosen by farthest-point sampling. Returns xyz (M, 3) float32, rgb (M, 3) float32,
    t_center (M,) float32."""
    rng = np.random.default_rng(seed)
    xs, cs, ts = [np.zeros((0, 3), np.float32)], [np.zeros((0, 3), np.float32)], [np.zeros(0, np.float32)]
    for k, (xyz, rgb, t) in enumerate(per_frame):
        idx = np.arange(len(xyz)) if k == 0 else farthest_point_indices(xyz, int(round(keep * len(xyz))), rng)
        xs.append(np.asarray(xyz, np.float32)[idx])
        cs.append(np.asarray(rgb, np.float32)[idx])
        ts.append(np.full(len(idx), t, np.float32))
    return np.concatenate(xs), np.concatenate(cs), np.concatenate(ts)


# -- the cache --------------------------------------------------------------------------------------
def select_frames(dataset, frames: Sequence[int] | None = None, every: int = 1) -> list[int]:
    """The frames SfM runs on: every `every`-th of `frames` (default: all of the dataset's)."""
    if every < 1:
        raise ValueError(f"every must be a positive integer, got {every}")
    frames = list(range(dataset.num_frames)) if frames is None else [int(j) for j in frames]
    for j in frames:
        if not 0 <= j < dataset.num_frames:
            raise ValueError(f"frame {j} out of range 0..{dataset.num_frames - 1}")
    return frames[::every]


def cache_key(dataset, frames: Sequence[int], settings: dict) -> str:
    """A hex digest of the training cameras (names, intrinsics, poses), the frames (and the segment's
    first frame), a strided sample of the pixels of each used frame, and the settings."""
    h = hashlib.sha256()
    cams = [dataset.cameras[i].to_dict() for i in dataset.train_cameras]
    h.update(json.dumps({"version": CACHE_VERSION, "cameras": cams, "frames": list(frames),
                         "num_frames": dataset.num_frames, "start_frame": int(getattr(dataset, "start_frame", 0)),
                         "settings": settings}, sort_keys=True).encode())
    for j in frames:
        for ci in dataset.train_cameras:
            h.update(np.ascontiguousarray(dataset.frames[ci, j, ::5, ::5]).tobytes())
    return h.hexdigest()[:24]


def _cache_path(dataset, cache_dir, key: str) -> Path | None:
    if cache_dir is None:
        if getattr(dataset, "path", None) is None:
            return None
        cache_dir = Path(dataset.path) / ".stg_cache" / "sfm"
    return Path(cache_dir) / f"sfm_{key}.npz"


def _save(path: Path, **arrays) -> None:
    """np.savez atomically (stg_runtime.atomic); a folder that cannot be written only warns."""
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        remove_leftovers(path.parent, path.name)
        with atomic_output(path) as tmp:
            np.savez(tmp, **arrays)
    except OSError as e:  # a read-only dataset folder: work without the cache
        warnings.warn(f"{path}: cannot write the SfM cache ({e})", stacklevel=3)


# -- the entry points -------------------------------------------------------------------------------
def sfm_points(dataset, frames: Sequence[int] | None = None, every: int = 1, cache_dir=None,
               progress: Callable[[int, int], None] | None = None, keep: float = KEEP_FRACTION,
               max_features: int = 8192, threads: int = -1) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """SfM points of every `every`-th frame (of `frames`, default all), merged (see the module doc).

    Returns xyz (N, 3) float32 world units, rgb (N, 3) float32 in [0, 1], t_center (N,) float32 (frame
    j / dataset.num_frames). Cached in cache_dir (default `<dataset.path>/.stg_cache/sfm`; no cache when
    the dataset has no path). progress(done, total) is called after each frame that is computed.
    """
    frames = select_frames(dataset, frames, every)
    settings = {"keep": keep, "max_features": max_features, "cameras": dataset.train_cameras}
    path = _cache_path(dataset, cache_dir, cache_key(dataset, frames, settings))
    if path is not None and path.is_file():
        try:
            with np.load(path) as z:
                return z["xyz"], z["rgb"], z["t_center"]
        except (OSError, ValueError, KeyError):
            pass  # a damaged cache is recomputed
    per_frame = []
    for k, j in enumerate(frames):
        with tempfile.TemporaryDirectory(prefix=f"stg_sfm_{j}_") as work:
            try:
                xyz, rgb = frame_points(dataset, j, work, max_features=max_features, threads=threads)
            except (RuntimeError, ValueError) as e:  # pycolmap's failed checks
                raise DataError(f"{dataset.path or dataset}: structure-from-motion failed on frame {j} "
                                f"({str(e).strip()}); try --init volume") from None
        per_frame.append((xyz, rgb, j / dataset.num_frames))
        if progress is not None:
            progress(k + 1, len(frames))
    xyz, rgb, t_center = merge_frames(per_frame, keep)
    if path is not None:
        _save(path, xyz=xyz, rgb=rgb, t_center=t_center,
              points_per_frame=np.array([len(p[0]) for p in per_frame]), frames=np.array(frames))
    return xyz, rgb, t_center
