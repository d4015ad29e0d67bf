"""The rig measured from its own pictures before training: its lenses' falloff (vignetting), its
cameras' colour gains and whether their stated poses agree with what they see (`TrainConfig`'s
lens_falloff, appearance and pose_refine "auto", the defaults; `stg-train --lens-falloff auto`).

Why not learn the falloff with the scene: a falloff that every lens shares is, for a rig whose cameras
converge, nearly the same thing as a darker rim of the scene, so training takes it into the scene
(docs/training.md, "Real captures"). Two cameras that see one surface point at the same instant see it
at different distances from their principal points, though, and that difference is what this module
measures:

1. For each training camera c and its `neighbours` nearest training cameras c' (by centre), at a few
   frames: dense optical flow from the picture of c to that of c' (OpenCV DIS, on brightness-normalised grey
   images, downscaled to at most `max_side` pixels), kept where it is consistent forwards and
   backwards, the picture is smooth (no edge to misalign) and neither colour is clipped.
2. Every such pixel pair gives, per channel, log I_c - log I_c' = g_c - g_c' + log V(s) - log V(s'),
   with g the cameras' log colour gains (exposure and white balance), s the squared distance from the
   principal point over its value at the farthest corner (stg_train.rig.lens), and log V(s) = a1 s + a2 s^2.
   That is linear in (g, a1, a2): iteratively reweighted least squares (Cauchy weights) with the gains'
   sum held at 0 (only gains relative to the rig's mean can be told from its pictures).
3. The pictures are corrected by the estimate and the flow is computed again (`rounds` times): the
   flow of pictures that still vignette pulls the estimate towards no falloff (docs/notes/real-captures-method.md).

The log-polynomial is then written as the trainer's `1 + k1 s + k2 s^2` (a least-squares fit over
s in [0, 1]). Pinhole and fisheye cameras alike (s is measured in pixels from the principal point).
The same pixel pairs also fit each camera's own falloff (`RigMeasurement.camera_corners`), which tells
whether the lenses share one. The last round's flow on textured pixels, against the epipolar lines of
the stated poses, tells whether those poses are off (`RigMeasurement.epipolar`).

Once the model has a geometry, `measure_rig_with_depth` measures the shared falloff and the cameras'
colour gains again from pixel pairs that the model's rendered depth matches instead of the flow (the
trainer does so a third of the way through a run whose falloff was measured here): the flow's matches
leave the corners about 0.02 too bright, and these gains come 15 times closer to the truth than what
training learns (docs/training.md, "Real captures").

`calibrate_rig` turns the measurement into what training uses, with a quiet fallback: the falloff
(none where the cameras do not overlap, the lenses differ, the estimate is out of range or too small to
matter), whether the cameras' colours disagree enough to learn a per-camera appearance, and whether
the poses are off enough to refine them.
"""
from __future__ import annotations

from dataclasses import replace
from typing import Callable, NamedTuple

import cv2
import numpy as np

from ..config import SAVED_BEFORE_AUTO
from .lens import known_falloff, lens_brightness, radial_grid

#: Flow pairs kept only where forward and backward flow agree to this many pixels (of the scaled image).
FB_TOLERANCE = 0.3
#: and where |Laplacian| of the grey picture (in [0, 1]) is below this: smooth surfaces, no edges.
SMOOTH = 0.05
#: The pose check (the epipolar distances) takes matched pixels whose |Laplacian| is above this: texture.
TEXTURED = 0.02
#: Colours below or above these (in [0, 1], any channel) are dark or clipped: left out.
DARK, CLIPPED = 0.05, 0.98
#: At most this many pixel pairs enter the fit (a random subset beyond).
MAX_PAIRS = 200_000
#: Fewer pixel pairs than this: the cameras do not overlap enough to measure anything.
MIN_PAIRS = 2_000
#: At most this many pixel pairs enter the fit of each camera's own falloff (a random subset beyond).
MAX_CAMERA_PAIRS = 50_000

# What calibrate_rig decides from a measurement (docs/training.md, "Real captures", has the figures):
#: a falloff whose corner brightness is within this of 1 is taken as none (a clean capture measures
#: 1.014-1.021: the measurement's own bias);
NEGLIGIBLE = 0.03
#: the lenses share one falloff when every camera's own corner brightness is within this of the rig's
#: (up to 0.022 on the synthetic forward-facing captures and 0.049 on the outward-facing pinhole dome,
#: where they do; 0.27-0.29 where one or half of the lenses vignette 30 %);
LENS_SPREAD = 0.1
#: the falloff is trusted when its corner brightness's two standard errors are below this (0.001-0.002 on
#: the synthetic captures; large only where the rig's geometry leaves the falloff undetermined);
UNCERTAIN = 0.05
#: the cameras' colours disagree, and a per-camera appearance is learned, when the RMS of their log
#: colour gains exceeds this (0.004 on a clean capture, 0.09-0.16 with the default `stg-synth --realistic`).
GAIN_SPREAD = 0.03
#: the stated poses are off, and pose refinement is on, when the matched pixels' median distance from
#: their epipolar lines exceeds this many pixels of the pictures as measured (0.09-0.14 on the clean
#: synthetic rigs, 0.27-0.32 with `stg-synth --realistic`'s pose error of 0.15 degrees and 0.01 units).
EPIPOLAR = 0.2


class RigMeasurement(NamedTuple):
    """k: (k1, k2) of the brightness 1 + k1 s + k2 s^2 shared by the rig's lenses; gains: (C, 3) each
    training camera's colour gains relative to the rig's (their geometric mean over the cameras is 1;
    rows in dataset.train_cameras order); pairs: pixel pairs found in the last round; frames: the
    frames used; camera_corners: (C,) each camera's own corner brightness, fitted with a falloff of its
    own; corner_error: two standard errors of the shared corner brightness (from the fit's residuals);
    epipolar: the median distance of the matched textured pixels from the epipolar lines of the stated
    poses, in pixels of the pictures as measured (nan when none); scale: those pictures' size over the
    cameras' (at most 1)."""

    k: tuple[float, float]
    gains: np.ndarray
    pairs: int
    frames: tuple[int, ...]
    camera_corners: np.ndarray
    corner_error: float
    epipolar: float
    scale: float

    @property
    def corner_brightness(self) -> float:
        """The brightness at the farthest image corner (s = 1), 1 + k1 + k2."""
        return float(lens_brightness(1.0, self.k))

    @property
    def lens_spread(self) -> float:
        """How far the camera furthest from the rig's corner brightness is from it (0 for one lens)."""
        return float(np.abs(self.camera_corners - self.corner_brightness).max())

    @property
    def gain_spread(self) -> float:
        """The RMS of the cameras' log colour gains (over cameras and channels): 0 when they agree."""
        return float(np.sqrt(np.mean(np.log(self.gains) ** 2)))

    def describe(self) -> str:
        """The falloff as stg-train prints it: K1, K2, the corner brightness, the pairs and the frames."""
        return (f"K1 {self.k[0]:.3f}, K2 {self.k[1]:.3f} (corner brightness {self.corner_brightness:.3f}; "
                f"{self.pairs} pixel pairs at frames {', '.join(map(str, self.frames))})")


def measure_rig(dataset, frames=None, neighbours: int = 4, rounds: int = 3, max_side: int = 320,
                seed: int = 0, progress: Callable[[int, int], None] | None = None) -> RigMeasurement:
    """The training cameras of `dataset` (stg_train.data.Dataset) measured at `frames` (default: the
    first and the middle frame): their lenses' shared falloff, each one's own, their colour gains and how
    far their matches stray from the stated poses' epipolar lines (RigMeasurement). progress(done,
    total) is called per camera pair and round.
    Raises ValueError when the cameras overlap too little (fewer than MIN_PAIRS pixel pairs). The
    estimate may lie outside the range a known falloff must keep (calibrate_rig checks it)."""
    cams = list(dataset.train_cameras)
    if len(cams) < 2:
        raise ValueError(f"measuring the rig needs two or more training cameras, the dataset has {len(cams)}")
    frames = measured_frames(dataset) if frames is None else tuple(int(f) for f in frames)
    scale = min(1.0, max_side / max(dataset.width, dataset.height))
    pictures = {(c, f): _scaled(dataset.image(c, f), scale) for c in cams for f in frames}
    # the colours compared, blurred once: a sub-pixel misalignment of the flow then matters less
    blurred = {key: cv2.GaussianBlur(p, (0, 0), 1.0) for key, p in pictures.items()}
    shape = pictures[cams[0], frames[0]].shape[:2]
    radial = {c: radial_grid(dataset.cameras[c], shape).astype(np.float32) for c in cams}
    pairs = _neighbour_pairs(dataset, cams, neighbours)
    rng = np.random.default_rng(seed)
    logv, gains, total = np.zeros(2), np.zeros((len(cams), 3)), 0
    work, done = rounds * len(pairs) * len(frames), 0
    for round_ in range(rounds):
        rows, distances = [], []  # the epipolar distances: from the last round's flow only
        for f in frames:
            corrected = {c: (pictures[c, f] / _brightness(radial[c], logv, gains[i])[..., None]).astype(np.float32)
                         for i, c in enumerate(cams)}
            for i, j in pairs:
                match = _match(corrected[cams[i]], corrected[cams[j]])
                rows.append(_pixel_pairs(blurred[cams[i], f], blurred[cams[j], f], match, radial[cams[i]],
                                         radial[cams[j]], i, j))
                if round_ == rounds - 1:
                    distances.append(_epipolar_distances(dataset.cameras[cams[i]], dataset.cameras[cams[j]], match))
                done += 1
                if progress is not None:
                    progress(done, work)
        data, total = _pooled(rows, rng, "the training cameras overlap too little to measure them")
        gains, logv, error = _fit(*data, num_cameras=len(cams))
    subset = rng.permutation(len(data[0]))[:MAX_CAMERA_PAIRS]
    corners = _camera_corners(*[d[subset] for d in data], num_cameras=len(cams))
    distances = np.concatenate(distances) if distances else np.zeros(0)
    return RigMeasurement(_as_polynomial(logv), np.exp(gains), total, frames, corners,
                          float(2 * error * np.exp(logv.sum())),
                          float(np.median(distances)) if len(distances) else float("nan"), scale)


class RigCalibration(NamedTuple):
    """What training takes from the measurement (calibrate_rig). lens_falloff: (k1, k2), or None for
    none; appearance: learn a per-camera appearance; pose_refine: refine the training cameras' poses;
    estimate: the RigMeasurement (None when it could not be measured); notes: what was decided and why,
    one line each (for stg-train to print)."""

    lens_falloff: tuple[float, float] | None
    appearance: bool
    pose_refine: bool
    estimate: RigMeasurement | None
    notes: tuple[str, ...]


#: The TrainConfig fields that may be "auto" (those whose default became "auto"): decided by calibrate_rig.
AUTO_FIELDS = tuple(SAVED_BEFORE_AUTO)


def needs_calibration(config) -> bool:
    """Whether a TrainConfig leaves the lens falloff, the appearance or the pose refinement "auto"."""
    return any(getattr(config, name) == "auto" for name in AUTO_FIELDS)


def calibrate_rig(dataset, config, progress: Callable[[int, int], None] | None = None):
    """(config with its "auto" fields decided, RigCalibration) for a TrainConfig with lens_falloff,
    appearance or pose_refine "auto" (needs_calibration), from measure_rig's measurement of `dataset`.
    The falloff is trained with unless it cannot be measured or trusted (_decide_falloff); the
    appearance is learned when the cameras' colour gains disagree (GAIN_SPREAD) or their lenses do
    (LENS_SPREAD: each camera's appearance then learns its own falloff); the poses are refined when the
    matches stray from the stated poses' epipolar lines (EPIPOLAR). Never raises for the rig: the notes
    say what was decided and why; where an appearance is learned, the measured colour gains go into the
    config's camera_gains. progress: as measure_rig's."""
    try:
        estimate = measure_rig(dataset, progress=progress)
    except ValueError as e:
        estimate, why = None, str(e)
    falloff, appearance, notes = config.lens_falloff, config.appearance, []
    if falloff == "auto":
        if estimate is None:
            falloff, note = None, f"lens falloff: not measured ({why}); training without one"
        else:
            falloff, note = _decide_falloff(estimate)
        notes.append(note)
    if appearance == "auto":
        if estimate is None:
            appearance = False
            notes.append(f"camera colours: not measured ({why}); no per-camera appearance (--appearance learns one)")
        else:
            lenses = estimate.lens_spread > LENS_SPREAD  # then each camera's appearance learns its own falloff
            appearance = estimate.gain_spread > GAIN_SPREAD or lenses
            choice = ("learning a per-camera appearance (--no-appearance: none)" if appearance else
                      "no per-camera appearance (--appearance learns one)")
            notes.append(f"camera colours: the training cameras' colour gains differ by "
                         f"{100 * estimate.gain_spread:.1f} % (RMS){' and their lenses differ' if lenses else ''}: "
                         f"{choice}")
    poses = config.pose_refine
    if poses == "auto":
        if estimate is None or not np.isfinite(estimate.epipolar):
            poses, reason = False, why if estimate is None else "no textured pixel was matched"
            notes.append(f"camera poses: not checked ({reason}); not refined (--pose-refine refines them)")
        else:
            poses = estimate.epipolar > EPIPOLAR
            choice = "refining them (--no-pose-refine: not)" if poses else "not refined (--pose-refine refines them)"
            size = "full-size pictures" if estimate.scale >= 1 else f"pictures scaled to {estimate.scale:.2g}"
            notes.append(f"camera poses: matched pixels lie {estimate.epipolar:.2f} px (median) from the epipolar "
                         f"lines of the stated poses, in {size}: {choice}")
    gains = None if estimate is None or appearance is not True else \
        {dataset.cameras[c].name: tuple(float(g) for g in row) for c, row in zip(dataset.train_cameras, estimate.gains)}
    return (replace(config, lens_falloff=falloff, appearance=appearance, pose_refine=poses, camera_gains=gains),
            RigCalibration(falloff, appearance, poses, estimate, tuple(notes)))


class GeometricMeasurement(NamedTuple):
    """The rig measured with a model's geometry (measure_rig_with_depth): k (k1, k2) of the shared
    falloff 1 + k1 s + k2 s^2; corner_error: two standard errors of its corner brightness; pairs: pixel
    pairs; gains: (C, 3) the training cameras' colour gains as RigMeasurement's (their geometric mean
    over the cameras 1; dataset.train_cameras order)."""

    k: tuple[float, float]
    corner_error: float
    pairs: int
    gains: np.ndarray

    @property
    def corner_brightness(self) -> float:
        return 1.0 + self.k[0] + self.k[1]


#: A pixel is matched through the model's geometry where its render is opaque (alpha over this) and the
#: neighbour's render sees the same surface there (depth within DEPTH_AGREEMENT of it, relative).
OPAQUE, DEPTH_AGREEMENT = 0.99, 0.01


def measure_rig_with_depth(dataset, cameras, depths: dict, frames, neighbours: int = 4, max_side: int = 320,
                           seed: int = 0) -> GeometricMeasurement:
    """The training cameras' shared falloff and colour gains measured as measure_rig does, the pixel
    pairs matched by a model's geometry instead of the flow: depths[(c, f)] = (depth, alpha), (H, W)
    each at the camera's full size, the camera-space z and the opacity the model renders for training
    camera c at frame f through cameras[c] (the poses the model holds: refined, or stated). A pixel of
    c is matched to where its surface lands in each of c's `neighbours` nearest training cameras, where
    both renders see that surface (OPAQUE, DEPTH_AGREEMENT), all of it on pictures and depths scaled to at
    most `max_side` pixels on a side, as measure_rig's. One round: the matches do not depend on the
    brightness. Raises ValueError when fewer than MIN_PAIRS pixel pairs are found."""
    cams = list(dataset.train_cameras)
    scale = {c: min(1.0, max_side / max(cameras[c].width, cameras[c].height)) for c in cams}
    rows = []
    for f in frames:
        pictures = {c: _scaled(dataset.image(c, f).astype(np.float32), scale[c]) for c in cams}
        seen = {c: tuple(_scaled(np.asarray(m, np.float32), scale[c]) for m in depths[c, f]) for c in cams}
        blurred = {c: cv2.GaussianBlur(p, (0, 0), 1.0) for c, p in pictures.items()}
        radial = {c: radial_grid(cameras[c], p.shape[:2]).astype(np.float32) for c, p in pictures.items()}
        scaled = {c: cameras[c].resized(p.shape[1], p.shape[0]) for c, p in pictures.items()}
        for i, j in _neighbour_pairs(dataset, cams, neighbours):
            a, b = cams[i], cams[j]
            match = _geometric_match(scaled[a], scaled[b], seen[a], seen[b], pictures[a])
            rows.append(_pixel_pairs(blurred[a], blurred[b], match, radial[a], radial[b], i, j))
    data, total = _pooled(rows, np.random.default_rng(seed), "the model's geometry matches too few pixels")
    gains, logv, error = _fit(*data, num_cameras=len(cams))
    return GeometricMeasurement(_as_polynomial(logv), float(2 * error * np.exp(logv.sum())), total, np.exp(gains))


def _geometric_match(camera_a, camera_b, seen_a, seen_b, picture_a) -> _Match:
    """Where each pixel of camera a lands in camera b through the rendered depth (seen_a, seen_b:
    (depth, alpha) of each), as a _Match: ok where a's render is opaque, b's render sees the same
    surface there and it lands inside."""
    depth_a, alpha_a = seen_a
    depth_b = np.asarray(seen_b[0], np.float32)
    h, w = depth_a.shape
    v, u = np.mgrid[0:h, 0:w].astype(np.float64)
    with np.errstate(invalid="ignore"):
        uv, z = camera_b.project(camera_a.unproject(u + 0.5, v + 0.5, depth_a))
    u2, v2 = (uv[..., 0] - 0.5).astype(np.float32), (uv[..., 1] - 0.5).astype(np.float32)
    hb, wb = depth_b.shape
    inside = np.isfinite(u2) & np.isfinite(v2) & (u2 > 1) & (u2 < wb - 2) & (v2 > 1) & (v2 < hb - 2)
    u2, v2 = np.where(inside, u2, 0).astype(np.float32), np.where(inside, v2, 0).astype(np.float32)
    there = cv2.remap(depth_b, u2, v2, cv2.INTER_LINEAR)
    ok = inside & (np.asarray(alpha_a) > OPAQUE) & (z > 0) & (np.abs(there - z) < DEPTH_AGREEMENT * z)
    grey = _grey(picture_a).astype(np.float32) / 255
    return _Match(u2, v2, ok, np.abs(cv2.Laplacian(grey, cv2.CV_32F)))


def _decide_falloff(estimate: RigMeasurement) -> tuple[tuple[float, float] | None, str]:
    """(the falloff to train with or None, the note saying which and why)."""
    said = f"lens falloff measured from the cameras' overlap: {estimate.describe()}"
    corners = estimate.camera_corners
    if estimate.lens_spread > LENS_SPREAD:
        return None, (f"{said}; but the cameras' own corner brightness ranges over {corners.min():.3f}-"
                      f"{corners.max():.3f}, not one lens: training without a shared falloff (a per-camera "
                      "appearance learns each camera's own; --lens-falloff K1,K2 gives a known one)")
    if estimate.corner_error > UNCERTAIN:
        return None, (f"{said}; but it is uncertain (+-{estimate.corner_error:.3f}: the cameras see the "
                      "scene at too alike distances from their centres): training without one")
    try:
        k = known_falloff(estimate.k)
    except ValueError as e:
        return None, f"{said}; but {e}: training without one"
    if abs(estimate.corner_brightness - 1.0) <= NEGLIGIBLE:
        return None, f"{said}: within {NEGLIGIBLE} of none, training without one"
    return k, f"{said}: training with it"


def measured_frames(dataset) -> tuple[int, ...]:
    """The frames the rig is measured at by default: the first and the middle one."""
    return tuple(sorted({0, dataset.num_frames // 2}))


def _pooled(rows: list, rng: np.random.Generator, too_few: str) -> tuple[list, int]:
    """(the pixel pairs of every camera pair (_pixel_pairs rows) together, at most MAX_PAIRS of them drawn
    by `rng`; how many there were). Raises ValueError(too_few ...) below MIN_PAIRS."""
    data = [np.concatenate(parts) for parts in zip(*rows)]
    total = len(data[0])
    if total < MIN_PAIRS:
        raise ValueError(f"{too_few} ({total} pixel pairs, at least {MIN_PAIRS} needed)")
    if total > MAX_PAIRS:
        keep = rng.choice(total, MAX_PAIRS, replace=False)
        data = [d[keep] for d in data]
    return data, total


def _scaled(image: np.ndarray, scale: float) -> np.ndarray:
    """(H, W[, 3]) float32 picture (or depth, or opacity) resized by `scale` (area averaging)."""
    if scale == 1.0:
        return image.astype(np.float32)
    h, w = image.shape[:2]
    return cv2.resize(image, (max(1, round(w * scale)), max(1, round(h * scale))), interpolation=cv2.INTER_AREA)


def _neighbour_pairs(dataset, cams: list, neighbours: int) -> list[tuple[int, int]]:
    """(i, j) positions in `cams` of each camera and its `neighbours` nearest (by centre)."""
    centres = np.array([dataset.cameras[c].center for c in cams])
    out = []
    for i in range(len(cams)):
        order = np.argsort(np.linalg.norm(centres - centres[i], axis=1), kind="stable")
        out += [(i, int(j)) for j in order[1:neighbours + 1]]
    return out


def _brightness(s: np.ndarray, logv: np.ndarray, log_gain: np.ndarray) -> np.ndarray:
    """(h, w) the falloff's brightness times the camera's mean gain (for the flow's pictures only)."""
    return np.exp(logv[0] * s + logv[1] * s * s + log_gain.mean())


def _grey(picture: np.ndarray) -> np.ndarray:
    """uint8 grey picture scaled to a mean of 0.4 (the flow compares patterns, not exposures)."""
    g = cv2.cvtColor(picture, cv2.COLOR_RGB2GRAY)
    return np.clip(g * (0.4 * 255 / max(float(g.mean()), 1e-3)), 0, 255).astype(np.uint8)


class _Match(NamedTuple):
    """Dense flow from a picture to another: (h, w) float32 u2, v2, where each pixel (column, row) of the
    first lands in the second; ok: (h, w) where forward and backward flow agree within FB_TOLERANCE and
    the pixel lands inside; laplacian: (h, w) |Laplacian| of the first's grey picture (in [0, 1])."""

    u2: np.ndarray
    v2: np.ndarray
    ok: np.ndarray
    laplacian: np.ndarray


def _match(a_flow: np.ndarray, b_flow: np.ndarray) -> _Match:
    """The flow between two pictures (h, w, 3; corrected for the falloff and gains estimated so far)."""
    dis = cv2.DISOpticalFlow_create(cv2.DISOPTICAL_FLOW_PRESET_MEDIUM)
    ga, gb = _grey(a_flow), _grey(b_flow)
    fwd, bwd = dis.calc(ga, gb, None), dis.calc(gb, ga, None)
    h, w = ga.shape
    v, u = np.mgrid[0:h, 0:w].astype(np.float32)
    u2, v2 = u + fwd[..., 0], v + fwd[..., 1]
    back = cv2.remap(bwd, u2, v2, cv2.INTER_LINEAR)
    ok = (np.hypot(fwd[..., 0] + back[..., 0], fwd[..., 1] + back[..., 1]) < FB_TOLERANCE)
    ok &= (u2 > 1) & (u2 < w - 2) & (v2 > 1) & (v2 < h - 2)
    return _Match(u2, v2, ok, np.abs(cv2.Laplacian(ga.astype(np.float32) / 255, cv2.CV_32F)))


def _epipolar_distances(camera_a, camera_b, match: _Match) -> np.ndarray:
    """(n,) for the textured matched pixels (|Laplacian| above TEXTURED): how far, in pixels of the
    scaled picture, each lands from the epipolar line its stated poses allow (the angle between the
    second camera's ray and the plane through the first camera's ray and both centres, times the second
    camera's focal length scaled). Pinhole and fisheye alike (Camera.camera_rays). Empty when the two
    cameras share a centre."""
    baseline = camera_b.center - camera_a.center
    if np.linalg.norm(baseline) < 1e-9:
        return np.zeros(0)
    h, w = match.ok.shape
    keep = match.ok & (match.laplacian > TEXTURED)
    v, u = np.nonzero(keep)
    sx, sy = camera_a.width / w, camera_a.height / h  # scaled picture -> the camera's pixels
    ray_a = camera_a.camera_rays((u + 0.5) * sx, (v + 0.5) * sy) @ camera_a.R  # world directions
    ray_b = camera_b.camera_rays((match.u2[keep] + 0.5) * (camera_b.width / w),
                                 (match.v2[keep] + 0.5) * (camera_b.height / h)) @ camera_b.R
    normal = np.cross(baseline, ray_a)
    normal /= np.maximum(np.linalg.norm(normal, axis=1, keepdims=True), 1e-12)
    angle = np.arcsin(np.clip(np.abs((normal * ray_b).sum(1)), 0.0, 1.0))
    return angle * camera_b.fx * (w / camera_b.width)


def _pixel_pairs(a, b, match: _Match, s_a, s_b, i, j):
    """Pixels of picture a (h, w, 3; blurred) matched in picture b (`match`, smooth pixels only):
    (camera i, camera j, s at a, s at b, log colour at a (n, 3), log colour at b (n, 3))."""
    u2, v2 = match.u2, match.v2
    ok = match.ok & (match.laplacian < SMOOTH)
    ca = a[ok]
    cb = np.stack([cv2.remap(np.ascontiguousarray(b[..., k]), u2, v2, cv2.INTER_LINEAR)[ok] for k in range(3)], 1)
    good = (ca.min(1) > DARK) & (cb.min(1) > DARK) & (ca.max(1) < CLIPPED) & (cb.max(1) < CLIPPED)
    n = int(good.sum())
    return (np.full(n, i), np.full(n, j), s_a[ok][good], cv2.remap(s_b, u2, v2, cv2.INTER_LINEAR)[ok][good],
            np.log(ca[good]), np.log(cb[good]))


def _fit(ci, cj, si, sj, li, lj, num_cameras: int, iterations: int = 8, scale: float = 0.05):
    """IRLS (Cauchy weights, `scale` in log units) of li - lj = g_i - g_j + a1 (si - sj) + a2 (si^2 - sj^2)
    per channel, (a1, a2) shared by the channels and each channel's gains summing to 0: returns
    (g (C, 3), (a1, a2), the standard error of a1 + a2, the log corner brightness, as if the pairs' errors
    were independent: neighbouring pixels' are not, so it is small unless the geometry leaves the falloff
    undetermined). The normal equations are summed per camera pair (np.bincount), O(pairs)."""
    c = num_cameras
    d = np.stack([si - sj, si * si - sj * sj], 1)  # (n, 2)
    t = li - lj  # (n, 3)
    w = np.ones_like(t)
    x = np.zeros(3 * c + 2)
    for _ in range(iterations):
        normal, rhs = np.zeros((3 * c + 2, 3 * c + 2)), np.zeros(3 * c + 2)
        for k in range(3):
            wk, g = w[:, k], slice(k * c, (k + 1) * c)
            pair = np.bincount(ci * c + cj, wk, c * c).reshape(c, c)
            normal[g, g] = np.diag(pair.sum(1) + pair.sum(0)) - pair - pair.T + 1e4  # + the gauge, sum g = 0
            for m in range(2):
                cross = np.bincount(ci, wk * d[:, m], c) - np.bincount(cj, wk * d[:, m], c)
                normal[g, 3 * c + m] = normal[3 * c + m, g] = cross
            normal[3 * c:, 3 * c:] += (d * wk[:, None]).T @ d
            rhs[g] = np.bincount(ci, wk * t[:, k], c) - np.bincount(cj, wk * t[:, k], c)
            rhs[3 * c:] += (d * wk[:, None]).T @ t[:, k]
        x = np.linalg.solve(normal, rhs)
        gains = x[:3 * c].reshape(3, c).T
        r = t - (gains[ci] - gains[cj] + (d @ x[3 * c:])[:, None])
        w = 1.0 / (1.0 + (r / scale) ** 2)
    variance = float((w * r * r).sum() / w.sum())  # of a residual, the weights as in the last solve
    corner = np.zeros(3 * c + 2)
    corner[3 * c:] = 1.0
    error = np.sqrt(variance * corner @ np.linalg.solve(normal, corner))
    return x[:3 * c].reshape(3, c).T, x[3 * c:], float(error)


def _camera_corners(ci, cj, si, sj, li, lj, num_cameras: int, iterations: int = 8, scale: float = 0.05):
    """(C,) each camera's corner brightness exp(a1_c + a2), fitted as _fit does but with a falloff a1_c s
    of its own per camera (a2 shared) on the pairs' mean log colour over the channels: dense weighted
    least squares over (C gains, C slopes, a2), the gains' sum held at 0 by one heavy row."""
    c, n = num_cameras, len(ci)
    t = (li - lj).mean(1)
    design = np.zeros((n, 2 * c + 1))
    rows = np.arange(n)
    np.add.at(design, (rows, ci), 1.0)
    np.add.at(design, (rows, cj), -1.0)
    np.add.at(design, (rows, c + ci), si)
    np.add.at(design, (rows, c + cj), -sj)
    design[:, 2 * c] = si * si - sj * sj
    gauge = np.r_[np.full(c, 100.0), np.zeros(c + 1)]
    w = np.ones(n)
    for _ in range(iterations):
        root = np.sqrt(w)
        x, *_ = np.linalg.lstsq(np.vstack([design * root[:, None], gauge]), np.r_[t * root, 0.0], rcond=None)
        w = 1.0 / (1.0 + ((t - design @ x) / scale) ** 2)
    return np.exp(x[c:2 * c] + x[2 * c])


def _as_polynomial(logv: np.ndarray) -> tuple[float, float]:
    """(k1, k2) of 1 + k1 s + k2 s^2 closest to exp(a1 s + a2 s^2) over s in [0, 1]."""
    s = np.linspace(0.0, 1.0, 101)
    k, *_ = np.linalg.lstsq(np.stack([s, s * s], 1), np.exp(logv[0] * s + logv[1] * s * s) - 1.0, rcond=None)
    return float(k[0]), float(k[1])
