"""CameraRig: what the training cameras of one run do to the picture and where they really are, the one
object the Trainer asks about its cameras (as it asks its strategies about the Gaussians).

A run's rig is, per training camera: its appearance (CameraAppearance: exposure, white balance, its own
vignetting), the lens falloff it shares with the others (TrainConfig.lens_falloff, stg_train.rig.lens)
and its pose correction (PoseCorrections); each is off unless the run turns it on, and "auto" settings
are decided from the rig's measurement before training (stg_train.rig.self_calibration.calibrate_rig),
which a third of the way through is measured again through the model's geometry
(stg_train.rig.remeasure). The Trainer's calls, in a run's order:

    CameraRig(dataset, config, state)           decide "auto" settings (a fresh run); .config is the run's
    rig.initial_brightness()                    what the initial points' pictures are divided by
    rig.start(dataset, device, extent, steps)   build the camera models and their own Adam
    rig.load_state_dict(state)                  a resumed run's camera models
    rig.view(gaussians, rays, c, camera)        each step: the Gaussians as camera c's corrected pose sees them
    rig.recorded(rgb, c, camera)                ... the canonical render as camera c records it (before the loss)
    rig.end_step(step, render)                  ... after the model's Adam step: the cameras' own step
    rig.state_dict()                            for the checkpoint

Nothing of it reaches the exported `.stg` but the refined training cameras (rig.refined).
"""
from __future__ import annotations

from dataclasses import replace
from typing import Callable

import numpy as np
import torch
from torch import Tensor

from stg_runtime.camera import Camera

from ..data.bounds import typical_depth
from .appearance import CameraAppearance, radial
from .lens import known_falloff, lens_brightness, picture_brightness
from .pose_refine import PoseCorrections
from .remeasure import remeasure_due, remeasure_plan, remeasure_rig
from .self_calibration import calibrate_rig, needs_calibration


class CameraRig:
    """The training cameras' models of one run (module docstring).

    dataset: the stg_train.data.Dataset; config: the run's TrainConfig (for_dataset applied); state: a
    resumed run's checkpoint (its "auto" choices were made: not measured again);
    progress(done, total): per camera pair while the rig is measured. self.config: the run's settings
    with "auto" decided and, after remeasure_rig, the falloff measured again; self.calibration: the
    RigCalibration of the measurement before training (None when nothing was measured);
    self.remeasure: {"falloff", "gains"}: what is measured again (remeasure_plan); self.remeasure_note:
    what that found, for stg-train to say; self.lens_falloff: (k1, k2) or None.
    """

    def __init__(self, dataset, config, state: dict | None = None,
                 progress: Callable[[int, int], None] | None = None):
        self.calibration = None
        if needs_calibration(config) and state is None:
            measured = config.lens_falloff == "auto"
            config, self.calibration = calibrate_rig(dataset, config, progress=progress)
            self.remeasure = remeasure_plan(measured, config, self.calibration)
        else:  # what was measured before training is to be measured again (remeasure_rig)
            self.remeasure = dict((state or {}).get("remeasure") or {"falloff": False, "gains": False})
        self.remeasure_note: str | None = None
        # (k1, k2) of a known vignetting, checked (a ValueError) before anything is computed
        self.lens_falloff = None if config.lens_falloff is None else known_falloff(config.lens_falloff)
        self.config, self.dataset, self.device = config, dataset, None
        self.appearance = self.poses = self.optimizer = None
        self.step, self.steps = 0, 1
        self._falloffs: dict[int, Tensor] = {}

    def initial_brightness(self) -> dict[int, np.ndarray]:
        """{training camera index: (H, W, 3) brightness of its pictures against the canonical scene}
        (lens.picture_brightness), which the initial points' pictures are divided by: the lens falloff
        trained with, times the camera's colour gains where the rig's measurement before training found
        them for an appearance (TrainConfig.camera_gains); {} when there is neither (a clean capture: its
        initial points are as they were)."""
        gains = self.config.camera_gains if self.config.appearance is True else None
        if self.lens_falloff is None and not gains:
            return {}
        cameras = self.dataset.cameras
        return {c: picture_brightness(cameras[c], self.lens_falloff, (gains or {}).get(cameras[c].name))
                for c in self.dataset.train_cameras}

    def start(self, dataset, device, extent: float, steps: int) -> None:
        """Build the appearance and pose corrections the run turns on, and their own Adam (self.optimizer;
        None when both are off). dataset: the run's (with the bounds the initialisation derived);
        device: the torch.device they live on; extent: the training cameras' extent (world units), the
        poses' scale without bounds; steps: the run's length (the cameras' rates decay to a tenth over it)."""
        cfg, ds = self.config, dataset
        self.dataset, self.device, self.steps = dataset, device, steps
        groups = []
        if cfg.appearance:
            self.appearance = CameraAppearance(len(ds.cameras), ds.train_cameras, self.device,
                                               cfg.appearance_vignetting and cfg.lens_falloff is None)
            groups += self.appearance.param_groups(cfg.camera_learning_rates)
        if cfg.pose_refine:
            depth = None if ds.bounds is None else typical_depth(ds.bounds[ds.train_cameras])
            self.poses = PoseCorrections(ds.train_cameras, ds.cameras, self.device, depth=depth,
                                         scale=extent if depth is None else depth)
            groups += self.poses.param_groups(cfg.camera_learning_rates)
        if groups:
            for group in groups:
                group["initial_lr"] = group["lr"]
            self.optimizer = torch.optim.Adam(groups, eps=1e-15)

    # -- each step ------------------------------------------------------------------------------------
    def view(self, gaussians, rays: Tensor, camera_index: int, camera: Camera):
        """(gaussians, rays (H, W, 6)) as the camera at its corrected pose sees them (PoseCorrections.apply);
        as they are where poses are not refined."""
        return (gaussians, rays) if self.poses is None else self.poses.apply(gaussians, rays, camera_index, camera)

    def recorded(self, rgb: Tensor, camera_index: int, camera: Camera) -> Tensor:
        """(H, W, 3) canonical render of a training camera as the camera records it: its appearance
        (CameraAppearance.apply), then the lens falloff trained with."""
        if self.appearance is not None:
            rgb = self.appearance.apply(rgb, camera_index, camera)
        if self.lens_falloff is not None:
            rgb = rgb * self.falloff_map(camera_index)[..., None]
        return rgb

    @torch.no_grad()
    def canonical(self, picture: Tensor, camera_index: int, camera: Camera) -> Tensor:
        """(H, W, 3) a camera's picture as the canonical scene would look: the lens falloff divided out
        (training cameras) and its appearance undone (CameraAppearance.undo); the picture where the
        cameras are not modelled."""
        if self.lens_falloff is not None and camera_index in self.dataset.train_cameras:
            picture = picture / self.falloff_map(camera_index)[..., None]
        if self.appearance is not None:
            picture = self.appearance.undo(picture, camera_index, camera)
        return picture

    def end_step(self, step: int, render: Callable) -> None:
        """After the model's step `step`: step the camera models (rates decayed to a tenth over the run),
        keep the appearance's mean the identity and the pose corrections' mean zero, and at the planned
        step measure the rig again (remeasure_rig; render(camera, frame) -> (rgb, RenderOutput) at a frame
        index of the dataset)."""
        self.step = step
        if self.optimizer is not None:
            for group in self.optimizer.param_groups:
                group["lr"] = group["initial_lr"] * 0.1 ** min(step / self.steps, 1.0)
            self.optimizer.step()
            self.optimizer.zero_grad(set_to_none=True)
            if self.appearance is not None:
                self.appearance.center()
            if self.poses is not None:
                self.poses.center()
        if remeasure_due(self.remeasure, step, self.steps):
            self.remeasure_rig(render)

    def remeasure_rig(self, render: Callable, frames=None) -> None:
        """Measure the rig again through the model's geometry (stg_train.rig.remeasure.remeasure_rig)."""
        remeasure_rig(self, render, frames)

    # -- what the rig holds ---------------------------------------------------------------------------
    def falloff_map(self, camera_index: int) -> Tensor:
        """(H, W) the lens falloff trained with, over a training camera's pixels, cached."""
        if camera_index not in self._falloffs:
            self._falloffs[camera_index] = lens_brightness(radial(self.dataset.cameras[camera_index], self.device),
                                                           self.lens_falloff)
        return self._falloffs[camera_index]

    def take_falloff(self, k: tuple[float, float]) -> None:
        """Train on with lens falloff k (k1, k2), which the run's config then records."""
        self.lens_falloff, self._falloffs = k, {}
        self.config = replace(self.config, lens_falloff=k)

    def hold_appearance(self, gains: np.ndarray) -> None:
        """Set each training camera's colour transform to its measured gains (CameraAppearance.set_gains;
        gains (C, 3) in train_cameras order) and hold it for the rest of the run: what Adam learns of
        them stays about 1 % off the truth, where these are within 0.1 % (docs/notes/real-captures-method.md)."""
        self.appearance.set_gains(gains)
        for group in self.optimizer.param_groups:
            if group["name"] in ("appearance_matrix", "appearance_bias"):
                group["initial_lr"] = group["lr"] = 0.0
                for param in group["params"]:
                    self.optimizer.state.pop(param, None)

    def refined(self, cameras: list[Camera]) -> list[Camera]:
        """`cameras` (the dataset's), the training cameras' poses refined when pose_refine is on."""
        return list(cameras) if self.poses is None else self.poses.refined(list(cameras))

    # -- checkpoints ----------------------------------------------------------------------------------
    def state_dict(self) -> dict:
        """The checkpoint's keys "remeasure" (the plan of what is measured again), "appearance", "poses" and
        "camera_optimizer" (each model's state; None when off)."""
        return {"remeasure": self.remeasure,
                "appearance": None if self.appearance is None else self.appearance.state_dict(),
                "poses": None if self.poses is None else self.poses.state_dict(),
                "camera_optimizer": None if self.optimizer is None else self.optimizer.state_dict()}

    def load_state_dict(self, state: dict) -> None:
        """The models' state from a checkpoint (left as new where the checkpoint has none: turned on at resume)."""
        if self.appearance is not None and state.get("appearance") is not None:
            self.appearance.load_state_dict(state["appearance"])
        if self.poses is not None and state.get("poses") is not None:
            self.poses.load_state_dict(state["poses"])
        saved = state.get("camera_optimizer")
        if self.optimizer is not None and saved is not None and \
                len(saved["param_groups"]) == len(self.optimizer.param_groups):
            self.optimizer.load_state_dict(saved)
