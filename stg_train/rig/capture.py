"""What a real rig does to a synthetic scene's pictures and poses: per-camera exposure and white balance,
lens vignetting, sensor noise, and a calibration that is slightly off.

`CaptureModel` holds the knobs (each 0 turns its effect off); `CaptureModel.draw(num_cameras)` draws
one `CameraEffects` per camera from its seed. The writers of stg_train.synthetic render each frame with
the true camera, pass it through `CameraEffects.apply`, and store the *perturbed* pose
(`CameraEffects.perturb`) in the layout, as a calibration error would; the truth goes to scene.json
(`CameraEffects.as_dict`) so that tests and benchmarks can measure what a method recovers.

Image model, on linear rgb in [0, 1] (H, W, 3), pixel centres at +0.5 (formats/stg-v1.md):

    out = clip(gain * white_balance * vignette(r) * image + noise, 0, 1)
    vignette(r) = 1 - vignetting * r^2 / r_corner^2      (r: distance from the principal point, px)
    noise ~ Normal(0, noise)  per pixel and channel, drawn anew for every frame

The pose error is a rotation of `rotation_deg` degrees about a random axis and a translation of
`translation` world units in a random direction, applied to the camera's world-to-camera transform.

`with_vignetting` gives a dataset some lenses of their own (a rig whose lenses differ).
`in_model_frame` places a camera known in the true world where a model trained on the perturbed poses
sees it (pictures fix a model only up to a similarity of the world: stg_train.rig.gauge).
"""
from __future__ import annotations

from dataclasses import asdict, dataclass, replace

import numpy as np

from stg_runtime.camera import Camera

from ..rotations import rotation_from_axis_angle
from .gauge import corrections_between, fit_similarity
from .lens import radial_grid


@dataclass(frozen=True)
class CaptureModel:
    """Knobs of a realistic capture (0 turns an effect off).

    gain: standard deviation of the per-camera exposure, in stops (log2 of the gain);
    white_balance: standard deviation of the per-channel gains around 1 (a ratio); both are then
    normalised to a mean of 1 over the cameras unless there is a reference camera (draw);
    vignetting: brightness lost at the image corners (0.3: 30 % darker there);
    noise: standard deviation of the sensor noise, in [0, 1] units of the 8-bit range;
    rotation_deg, translation: size of the pose error (degrees; world units);
    seed: draws the per-camera values and the noise; reference_camera: index of a camera left exact
    (exposure 1, white balance 1, no pose error; -1: none), like a rig's master camera."""

    gain: float = 0.25
    white_balance: float = 0.05
    vignetting: float = 0.3
    noise: float = 0.01
    rotation_deg: float = 0.15
    translation: float = 0.01
    seed: int = 0
    reference_camera: int = -1

    def draw(self, num_cameras: int, held_out=()) -> list["CameraEffects"]:
        """One CameraEffects per camera, from `seed`. Without a reference camera the exposures and the
        white balances are divided by their means over the cameras trained on (all but the indices
        `held_out`): only colours relative to their mean can be recovered from their pictures (a factor
        shared by every camera belongs to the scene, and a held-out camera's pictures are not seen), so
        the clean capture is their mean response."""
        rng = np.random.default_rng(self.seed)
        gains, balances, axes, directions = [], [], [], []
        for _ in range(num_cameras):
            gains.append(float(2.0 ** rng.normal(0.0, self.gain)) if self.gain else 1.0)
            balances.append(np.clip(1.0 + rng.normal(0.0, self.white_balance, 3), 0.5, 1.5)
                            if self.white_balance else np.ones(3))
            axes.append(rng.normal(size=3))
            directions.append(rng.normal(size=3))
        gains, balances = np.asarray(gains), np.asarray(balances)
        if self.reference_camera < 0:
            trained = [c for c in range(num_cameras) if c not in set(held_out)] or list(range(num_cameras))
            gains, balances = gains / gains[trained].mean(), balances / balances[trained].mean(0)
        effects = []
        for ci in range(num_cameras):
            exact = ci == self.reference_camera
            effects.append(CameraEffects(
                gain=1.0 if exact else float(gains[ci]), white_balance=np.ones(3) if exact else balances[ci],
                vignetting=self.vignetting, noise=self.noise,
                rotation=np.zeros(3) if exact else
                axes[ci] / np.linalg.norm(axes[ci]) * np.radians(self.rotation_deg),
                translation=np.zeros(3) if exact else
                directions[ci] / np.linalg.norm(directions[ci]) * self.translation,
                seed=self.seed * 100003 + ci))
        return effects

    def settings(self) -> dict:
        return asdict(self)


@dataclass
class CameraEffects:
    """One camera's share of a CaptureModel: gain (scalar), white_balance (3,), vignetting, noise,
    rotation (3,) axis-angle radians and translation (3,) world units of the pose error, seed of its
    noise."""

    gain: float
    white_balance: np.ndarray
    vignetting: float
    noise: float
    rotation: np.ndarray
    translation: np.ndarray
    seed: int

    def __post_init__(self):
        self._rng = np.random.default_rng(self.seed)

    def vignette(self, camera: Camera) -> np.ndarray:
        """(H, W) brightness factor of the lens falloff (1 at the principal point)."""
        return 1.0 - self.vignetting * radial_grid(camera)

    def apply(self, image: np.ndarray, camera: Camera) -> np.ndarray:
        """The picture the camera records of `image` (H, W, 3) rgb in [0, 1]: float64, clipped to [0, 1].
        Each call draws new noise (call it once per frame, in order, for a repeatable capture)."""
        out = np.asarray(image, dtype=np.float64) * (self.gain * self.white_balance)[None, None, :]
        if self.vignetting:
            out = out * self.vignette(camera)[..., None]
        if self.noise:
            out = out + self._rng.normal(0.0, self.noise, out.shape)
        return np.clip(out, 0.0, 1.0)

    def perturb(self, camera: Camera) -> Camera:
        """The camera as a slightly wrong calibration states it: world_to_camera premultiplied by the
        error rotation, then its translation moved by `translation` (the true camera stays as given)."""
        return corrected(camera, self.rotation, self.translation)

    def as_dict(self) -> dict:
        return {"gain": self.gain, "white_balance": self.white_balance.tolist(), "vignetting": self.vignetting,
                "noise": self.noise, "rotation_rad": self.rotation.tolist(), "translation": self.translation.tolist()}



def capture_record(data_dir) -> dict | None:
    """The "capture" record of `data_dir`/scene.json (the truth a realistic synthetic capture keeps:
    write_n3v(capture=...)), or None when there is none."""
    import json
    from pathlib import Path

    path = Path(data_dir) / "scene.json"
    try:
        return json.loads(path.read_text()).get("capture")
    except (OSError, ValueError, AttributeError):
        return None


def pose_error(camera: Camera, true_world_to_camera) -> tuple[float, float]:
    """(rotation error in degrees, camera-centre distance in world units) of `camera` against the true
    world_to_camera (4, 4)."""
    w2c = np.asarray(camera.world_to_camera, np.float64)
    truth = np.asarray(true_world_to_camera, np.float64)
    relative = w2c[:3, :3] @ truth[:3, :3].T
    angle = np.degrees(np.arccos(np.clip((np.trace(relative) - 1.0) / 2.0, -1.0, 1.0)))
    centre = -w2c[:3, :3].T @ w2c[:3, 3]
    true_centre = -truth[:3, :3].T @ truth[:3, 3]
    return float(angle), float(np.linalg.norm(centre - true_centre))


def pose_errors(cameras, record: dict, names=None, depth: float | None = None) -> dict:
    """Pose errors of `cameras` against a capture record's truth (capture_record), matched by name, over
    the cameras named in `names` (default: all that the record has): "rotation_deg" and "translation"
    (means over those cameras), "max_rotation_deg", "max_translation", "cameras" (name -> (degrees,
    distance)); with three cameras or more also "aligned_rotation_deg" and "aligned_translation": the
    means once the part of the errors that moves the whole rig alike (a similarity of the world, which
    pictures cannot reveal: stg_train.rig.gauge) is removed, to first order, the similarity fitted in the
    pictures of points at `depth` (world units, the scene's: data.bounds.typical_depth; default the
    rig's radius, which lets the cameras' shifts decide the rig's turn: gauge.fit_similarity)."""
    truth = {c["name"]: c["true_world_to_camera"] for c in record["cameras"]}
    chosen = [c for c in cameras if c.name in truth and (names is None or c.name in names)]
    if not chosen:
        raise ValueError("pose_errors: no camera of the capture record to compare")
    each = {c.name: pose_error(c, truth[c.name]) for c in chosen}
    rot = [v[0] for v in each.values()]
    dist = [v[1] for v in each.values()]
    out = {"rotation_deg": float(np.mean(rot)), "translation": float(np.mean(dist)),
           "max_rotation_deg": float(np.max(rot)), "max_translation": float(np.max(dist)), "cameras": each}
    if len(chosen) >= 3:
        reference = np.stack([np.asarray(truth[c.name], np.float64) for c in chosen])
        w, t = corrections_between(np.stack([np.asarray(c.world_to_camera, np.float64) for c in chosen]), reference)
        gw, gt = fit_similarity(reference, w, t, depth).corrections(reference)
        out["aligned_rotation_deg"] = float(np.degrees(np.linalg.norm(w - gw, axis=1)).mean())
        out["aligned_translation"] = float(np.linalg.norm(t - gt, axis=1).mean())
    return out


def in_model_frame(cameras, model_poses: np.ndarray, true_poses: np.ndarray, depth: float) -> list[Camera]:
    """`cameras` (posed in the true world) moved into the frame of a model whose training cameras it
    holds at model_poses (K, 4, 4, world_to_camera: stated, or refined) where the truth is true_poses
    (K, 4, 4): each moved by the similarity of the world that best takes the true training poses to the
    model's in their pictures of points at `depth` (world units; gauge.fit_similarity, first order).
    Pictures place a model only up to such a similarity, so a view posed in the truth's frame is compared
    with the model in the model's own frame this way, as pose-refining methods are evaluated (BARF aligns
    its poses to the truth likewise)."""
    model_poses = np.asarray(model_poses, np.float64)
    true_poses = np.asarray(true_poses, np.float64)
    rotation, translation = corrections_between(model_poses, true_poses)
    similarity = fit_similarity(true_poses, rotation, translation, depth)
    poses = np.stack([np.asarray(c.world_to_camera, np.float64) for c in cameras])
    turns, moves = similarity.corrections(poses)
    return [corrected(camera, w, t) for camera, w, t in zip(cameras, turns, moves)]


def corrected(camera: Camera, rotation, translation) -> Camera:
    """The camera with world_to_camera D W: D the rigid correction in camera coordinates, the rotation
    exp([rotation]x) (axis-angle (3,), radians) then the translation (3,) world units (stg_train.rig.gauge's
    convention)."""
    delta = np.eye(4)
    delta[:3, :3], delta[:3, 3] = rotation_from_axis_angle(rotation), translation
    return replace(camera, world_to_camera=delta @ np.asarray(camera.world_to_camera, np.float64))


def with_vignetting(dataset, cameras, amount: float = 0.3):
    """A copy of `dataset` (stg_train.data.Dataset, its frames decoded) whose `cameras` (indices) record
    their pictures through a lens of their own, darker by 1 - amount s (s: stg_train.rig.lens.radial_grid),
    as 8-bit frames: a rig whose lenses differ."""
    from ..data.dataset import Dataset

    frames = np.stack([[dataset.image(c, f) for f in range(dataset.num_frames)] for c in range(len(dataset.cameras))])
    for c in cameras:
        frames[c] *= (1.0 - amount * radial_grid(dataset.cameras[c]))[None, ..., None]
    return Dataset(dataset.cameras, np.clip(frames * 255 + 0.5, 0, 255).astype(np.uint8), dataset.fps,
                   test_cameras=dataset.test_cameras)
