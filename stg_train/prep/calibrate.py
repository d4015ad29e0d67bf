"""Calibration of a static rig from its pictures with pycolmap: every camera's intrinsics and pose.

The rig does not move, so each camera is one image: its static picture, the per-pixel median of frames
spread over its clip (static_picture), in which moving things fade and the static surfaces, which the
poses must be fitted to, dominate; all of a camera's frames share its intrinsics. The pictures go
through SIFT (CPU), exhaustive matching and incremental mapping, with observations kept only within
MAX_ERROR pixels. Intrinsics: `pinhole` is COLMAP's SIMPLE_PINHOLE (one focal length, the principal
point at the image centre, as the mapper leaves it), `opencv` adds k1, k2, p1, p2 (the frames are then
undistorted, stg_train.prep.write), `fisheye` is OPENCV_FISHEYE (k1..k4; the frames stay as they are),
starting from an equidistant lens 180 degrees across (COLMAP's first guess for every model, a lens
about 45 degrees across, verifies no fisheye match).
Pinhole is the default; where it fits badly (a camera left out, or a mean reprojection error above
FALLBACK_ERROR pixels) opencv is tried and the better of the two kept, the report says so.
Each model is fitted twice, with intrinsics per camera and with one set shared by every camera; the
shared set is kept where it explains the features as well (shared_is_as_good): a rig of identical
cameras then has no per-camera freedom to trade a focal length for the camera's distance from the
scene, the error that per-camera fits of a narrow rig make.

The result is in the project's conventions (formats/stg-v1.md: OpenCV axes, world-to-camera, pixel
centres at +0.5, which are COLMAP's) and in a gauge of its own: the world is the first camera's frame,
scaled so that the median depth of the 3D points from the cameras is 1.
"""
from __future__ import annotations

import contextlib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Sequence

import numpy as np

from stg_runtime.camera import Camera

from .inputs import PrepError

#: --camera-model -> the COLMAP model fitted.
CAMERA_MODELS = {"pinhole": "SIMPLE_PINHOLE", "opencv": "OPENCV", "fisheye": "OPENCV_FISHEYE"}
#: Observations further than this from their point's projection (pixels) are dropped by the mapper.
MAX_ERROR = 1.0
#: A pinhole fit with a mean reprojection error above this (pixels) falls back to opencv.
FALLBACK_ERROR = 0.75
#: Intrinsics shared by all the cameras are kept when their fit's mean reprojection error is within this
#: factor of the per-camera fit's, with at least this share of its observations (shared_is_as_good).
SHARED_ERROR = 1.05
SHARED_OBSERVATIONS = 0.97
#: Frames per camera whose median is its static picture.
STATIC_FRAMES = 9


def static_picture(frames: Sequence[np.ndarray]) -> np.ndarray:
    """The per-pixel median of frames (each (H, W, 3) uint8) -> (H, W, 3) uint8."""
    return np.median(np.stack(frames), axis=0).round().astype(np.uint8)


@dataclass
class Calibration:
    """cameras: one per picture, in the order given, as fitted (a `fisheye` Camera for the fisheye model;
    for opencv a pinhole Camera and its distortion in `distortion`); distortion: name -> (k1, k2, p1, p2)
    of the opencv cameras (OpenCV's model, in the Camera's pixels); points (N, 3) world units and colours
    (N, 3) float32 in [0, 1]; model: the --camera-model used; fallback: why it is not the one asked for
    (None when it is); reprojection_error: mean over all observations, pixels; per_camera: name ->
    (observations, mean reprojection error in pixels); intrinsics: "shared" (one set for every camera)
    or "per camera"; intrinsics_fits: "shared" / "per camera" -> (mean reprojection error in pixels,
    observations) of each that was fitted."""

    cameras: list[Camera]
    points: np.ndarray
    colours: np.ndarray
    model: str
    reprojection_error: float
    per_camera: dict
    distortion: dict = field(default_factory=dict)
    fallback: str | None = None
    intrinsics: str = "per camera"
    intrinsics_fits: dict = field(default_factory=dict)


@contextlib.contextmanager
def _quiet(pycolmap):
    level = pycolmap.logging.minloglevel
    pycolmap.logging.minloglevel = 2
    try:
        yield
    finally:
        pycolmap.logging.minloglevel = level


def _match_counts(pycolmap, database: Path, names: dict[int, str]) -> dict[str, dict[str, int]]:
    """name -> {other name: verified (inlier) matches} of the database's image pairs."""
    counts = {n: {} for n in names.values()}
    db = pycolmap.Database.open(str(database))
    try:
        pairs, inliers = db.read_two_view_geometry_num_inliers()
    finally:
        db.close()
    for pair, n in zip(pairs, inliers):
        i, j = pycolmap.pair_id_to_image_pair(pair)
        counts[names[i]][names[j]] = counts[names[j]][names[i]] = int(n)
    return counts


def _unregistered_error(missing: list[str], counts: dict[str, dict[str, int]]) -> PrepError:
    def describe(name: str) -> str:
        pairs = counts.get(name, {})
        if not pairs or max(pairs.values()) == 0:
            return f"{name} (no verified matches with any camera)"
        best = max(pairs, key=pairs.get)
        return f"{name} ({sum(pairs.values())} verified matches in all, at most {pairs[best]} with {best})"
    return PrepError(f"{', '.join(missing)}: not registered by the calibration: " + "; ".join(map(describe, missing))
                     + " (cameras need overlapping views of textured static surfaces)")


def _run_colmap(pycolmap, work: Path, names: list[str], colmap_model: str, threads: int, size: tuple[int, int],
                progress: Callable[[int, int], None], shared: bool = False):
    """Features, matches and mapping of work/images/<name>.png (size: their (width, height)) -> (the
    largest model or None, match counts); shared: one set of intrinsics for all the pictures (else one
    per picture). progress(done, total): the features, the matches, then each image the mapper
    registers (total 2 + images; a mapper that starts a second model counts on)."""
    total = 2 + len(names)
    extraction = pycolmap.FeatureExtractionOptions()
    extraction.num_threads = threads
    extraction.sift.max_num_features = 8192
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = colmap_model
    if colmap_model == CAMERA_MODELS["fisheye"]:  # COLMAP's first guess, a narrow lens, verifies no match
        w, h = size
        reader.camera_params = f"{w / np.pi},{w / np.pi},{w / 2},{h / 2},0,0,0,0"
    kind = f"{colmap_model}_shared" if shared else colmap_model
    database = work / f"{kind}.db"
    mode = pycolmap.CameraMode.SINGLE if shared else pycolmap.CameraMode.PER_IMAGE
    pycolmap.extract_features(database, work / "images", image_names=[f"{n}.png" for n in names],
                              camera_mode=mode, reader_options=reader,
                              extraction_options=extraction, device=pycolmap.Device.cpu)
    progress(1, total)
    matching = pycolmap.FeatureMatchingOptions()
    matching.num_threads = threads
    pycolmap.match_exhaustive(database, matching_options=matching, device=pycolmap.Device.cpu)
    progress(2, total)
    db = pycolmap.Database.open(str(database))
    try:
        ids = {im.image_id: Path(im.name).stem for im in db.read_all_images()}
    finally:
        db.close()
    counts = _match_counts(pycolmap, database, ids)
    options = pycolmap.IncrementalPipelineOptions()
    options.num_threads = threads
    options.random_seed = 0
    options.mapper.filter_max_reproj_error = MAX_ERROR
    options.triangulation.complete_max_reproj_error = MAX_ERROR
    options.triangulation.merge_max_reproj_error = MAX_ERROR
    out = work / f"{kind}_sparse"
    out.mkdir(exist_ok=True)
    registered = [2]

    def registered_one() -> None:
        registered[0] += 1
        progress(min(registered[0], total), total)

    models = pycolmap.incremental_mapping(database, work / "images", out, options=options,
                                          initial_image_pair_callback=lambda: (registered_one(), registered_one()),
                                          next_image_callback=registered_one)
    if registered[0] < total:
        progress(total, total)
    best = max(models.values(), key=lambda m: (m.num_reg_images(), m.num_points3D()), default=None)
    return best, counts


def _per_camera_errors(rec) -> dict[str, tuple[int, float]]:
    """name -> (observations, mean reprojection error in pixels) of a model's registered images."""
    out = {}
    for im in rec.images.values():
        if not im.has_pose:
            continue
        obs = [p for p in im.points2D if p.has_point3D()]
        if not obs:
            out[Path(im.name).stem] = (0, float("nan"))
            continue
        xyz = np.array([rec.points3D[p.point3D_id].xyz for p in obs])
        cam_points = xyz @ im.cam_from_world().matrix()[:, :3].T + im.cam_from_world().matrix()[:, 3]
        projected = rec.cameras[im.camera_id].img_from_cam(cam_points, check_cheirality=False)
        errors = np.linalg.norm(projected - np.array([p.xy for p in obs]), axis=1)
        out[Path(im.name).stem] = (len(obs), float(errors.mean()))
    return out


def _normalised(cameras: list[Camera], points: np.ndarray) -> tuple[list[Camera], np.ndarray]:
    """The gauge of the module docstring: world = the first camera's frame, median point depth 1."""
    first = np.asarray(cameras[0].world_to_camera, np.float64)
    moved = [np.asarray(c.world_to_camera, np.float64) @ np.linalg.inv(first) for c in cameras]
    pts = points @ first[:3, :3].T + first[:3, 3]
    depths = np.concatenate([pts @ m[:3, :3][2] + m[2, 3] for m in moved]) if len(pts) else np.ones(1)
    scale = 1.0 / float(np.median(depths[depths > 0])) if np.any(depths > 0) else 1.0
    out = []
    for cam, m in zip(cameras, moved):
        m = m.copy()
        m[:3, 3] *= scale
        out.append(Camera(cam.fx, cam.fy, cam.cx, cam.cy, cam.width, cam.height, m, cam.name, cam.model,
                          cam.distortion))
    return out, pts * scale


def _calibration(rec, names: list[str], model: str) -> Calibration:
    """A registered model -> Calibration (module docstring), cameras in the order of `names`."""
    from ..data.colmap import reconstruction_points

    by_name = {Path(im.name).stem: im for im in rec.images.values() if im.has_pose}
    cameras, distortion = [], {}
    for name in names:
        im = by_name[name]
        ccam = rec.cameras[im.camera_id]
        p = np.asarray(ccam.params, np.float64)
        w2c = np.eye(4)
        w2c[:3] = im.cam_from_world().matrix()
        if model == "pinhole":
            cam = Camera(p[0], p[0], p[1], p[2], ccam.width, ccam.height, w2c, name)
        elif model == "opencv":
            cam = Camera(p[0], p[1], p[2], p[3], ccam.width, ccam.height, w2c, name)
            distortion[name] = tuple(p[4:8])
        else:
            cam = Camera(p[0], p[1], p[2], p[3], ccam.width, ccam.height, w2c, name, "fisheye", tuple(p[4:8]))
        cameras.append(cam)
    xyz, rgb = reconstruction_points(rec)
    cameras, xyz = _normalised(cameras, xyz)
    per_camera = _per_camera_errors(rec)
    return Calibration(cameras, xyz, rgb, model, float(rec.compute_mean_reprojection_error()),
                       {n: per_camera[n] for n in names}, distortion)


#: A fitted focal length outside this many picture widths is a degenerate fit, not a lens.
FOCAL_WIDTHS = (0.05, 50.0)


def implausible_focal(rec, width: int) -> tuple[str, float] | None:
    """(name's stem, focal length in pixels) of the first registered image of a pycolmap model whose
    focal length (its camera's first parameter) is outside FOCAL_WIDTHS x width, else None."""
    lo, hi = (f * width for f in FOCAL_WIDTHS)
    for im in rec.images.values():
        focal = float(rec.cameras[im.camera_id].params[0])
        if im.has_pose and not lo < focal < hi:
            return Path(im.name).stem, focal
    return None


def _fit(pycolmap, work: Path, names: list[str], model: str, threads: int, size, stage) -> Calibration:
    """The rig fitted with one set of intrinsics per camera and with one shared by all of them: the
    shared fit where it explains the features as well (shared_is_as_good), else the per-camera one."""
    per_camera = _fit_intrinsics(pycolmap, work, names, model, threads, size, stage, shared=False)
    try:
        shared = _fit_intrinsics(pycolmap, work, names, model, threads, size, stage, shared=True)
    except PrepError:
        return per_camera
    kept = shared if shared_is_as_good(shared, per_camera) else per_camera
    kept.intrinsics_fits = {fit.intrinsics: (fit.reprojection_error, observations(fit)) for fit in (shared, per_camera)}
    return kept


def observations(calibration: Calibration) -> int:
    """The observations (2D features with a 3D point) of a calibration, over all its cameras."""
    return sum(n for n, _ in calibration.per_camera.values())


def shared_is_as_good(shared: Calibration, per_camera: Calibration) -> bool:
    """Whether the shared intrinsics explain the features as well as one set per camera: a mean
    reprojection error within SHARED_ERROR of the per-camera one's, with SHARED_OBSERVATIONS of its
    observations or more (cameras that differ lose observations to the mapper's MAX_ERROR)."""
    return (shared.reprojection_error <= SHARED_ERROR * per_camera.reprojection_error
            and observations(shared) >= SHARED_OBSERVATIONS * observations(per_camera))


def _fit_intrinsics(pycolmap, work: Path, names: list[str], model: str, threads: int, size, stage,
                    shared: bool) -> Calibration:
    """One fit (_run_colmap) of `model`, intrinsics shared or per camera, checked: a degenerate focal
    length is mapped once more on one thread, then a PrepError, as is a camera left unregistered."""
    label = f"{model}, shared intrinsics" if shared else model

    def run(threads: int, again: str = ""):
        return _run_colmap(pycolmap, work, names, CAMERA_MODELS[model], threads, size,
                           stage(f"stg-prep calibrate ({label}{again})"), shared)

    rec, counts = run(threads)
    bad = None if rec is None else implausible_focal(rec, size[0])
    if bad and threads != 1:
        # the multi-threaded mapper's result depends on the threads' timing: once more on one thread
        rec, counts = run(1, ", again on one thread")
        bad = None if rec is None else implausible_focal(rec, size[0])
    if bad:
        raise PrepError(f"{bad[0]}: the calibration is degenerate (a focal length of {bad[1]:.1f} px for pictures "
                        f"{size[0]} px wide): the cameras need more texture or more parallax between them")
    registered = set() if rec is None else {Path(im.name).stem for im in rec.images.values() if im.has_pose}
    missing = [n for n in names if n not in registered]
    if missing:
        raise _unregistered_error(missing, counts)
    calibration = _calibration(rec, names, model)
    calibration.intrinsics = "shared" if shared else "per camera"
    return calibration


def calibrate(pictures: dict[str, np.ndarray], work_dir, camera_model: str = "pinhole", threads: int = -1,
              progress: Callable[[str], Callable[[int, int], None]] | None = None) -> Calibration:
    """Calibrate the rig from one static picture per camera (name -> (H, W, 3) uint8 RGB), in a scratch
    folder work_dir; camera_model one of CAMERA_MODELS (module docstring). progress(stage) -> report(done,
    total): a callback per model fitted (stg_runtime.progress.progress_stages). PrepError naming the
    cameras that do not register, with their verified match counts."""
    stage = progress or (lambda name: lambda done, total: None)
    import cv2
    import pycolmap

    if camera_model not in CAMERA_MODELS:
        raise ValueError(f"camera_model must be one of {', '.join(CAMERA_MODELS)}, got {camera_model!r}")
    work = Path(work_dir)
    (work / "images").mkdir(parents=True, exist_ok=True)
    names = list(pictures)
    size = next(iter(pictures.values())).shape[1::-1]
    for name, rgb in pictures.items():
        if not cv2.imwrite(str(work / "images" / f"{name}.png"), np.ascontiguousarray(rgb[..., ::-1])):
            raise PrepError(f"{work / 'images' / name}.png: cannot write the calibration picture")
    with _quiet(pycolmap):
        try:
            result = _fit(pycolmap, work, names, camera_model, threads, size, stage)
        except PrepError as e:
            if camera_model != "pinhole":
                raise
            return _fall_back(pycolmap, work, names, threads, size, stage, str(e), e)
        if camera_model == "pinhole" and result.reprojection_error > FALLBACK_ERROR:
            reason = f"mean reprojection error {result.reprojection_error:.2f} px above {FALLBACK_ERROR} px"
            return _fall_back(pycolmap, work, names, threads, size, stage, reason, result)
    return result


def _fall_back(pycolmap, work: Path, names: list[str], threads: int, size, stage, reason: str, pinhole):
    """The opencv fit where the pinhole one failed (pinhole a PrepError) or fit badly (a Calibration):
    the opencv one when it registers every camera with a lower error, else the pinhole outcome."""
    try:
        opencv = _fit(pycolmap, work, names, "opencv", threads, size, stage)
    except PrepError:
        if isinstance(pinhole, PrepError):
            raise pinhole from None
        return pinhole
    if isinstance(pinhole, Calibration) and pinhole.reprojection_error <= opencv.reprojection_error:
        return pinhole
    opencv.fallback = f"pinhole: {reason}; opencv fitted instead"
    return opencv
