"""Per-camera appearance learned during training: what each camera of a real rig does to the colours it
records (exposure, white balance, colour response, lens vignetting), so that the model keeps one
canonical scene.

For training camera c, the rendered rgb image x (H, W, 3) becomes, before the loss only,

    y = v_c(r) * (x @ M_c^T + b_c),      v_c(r) = 1 + k1_c * s + k2_c * s^2,   s = r^2 / r_corner^2

M_c (3, 3) starts at the identity, b_c (3,) and k_c (2,) at 0; r is a pixel centre's distance from
the principal point (pixel centres at +0.5, formats/stg-v1.md), r_corner the largest at the image's
corners. After every optimiser step the transforms are projected so that their mean over the training
cameras is exactly the identity (mean M_c = I, mean b_c = 0): a colour change shared by all cameras
belongs to the scene, not to the cameras. The vignetting is not centred this way (the canonical scene
has none). Held-out and novel cameras, the evaluation and the exported `.stg` never see any of it.

Each camera's values are their own tensors, so a step that does not render a camera leaves its Adam
state alone (its gradient stays None).
"""
from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from stg_runtime.camera import Camera

from .lens import corner_r2, lens_brightness

#: Adam learning rates of the per-camera appearance (per step; decayed with the run, see Trainer).
APPEARANCE_LR = {"matrix": 1e-2, "bias": 3e-3, "vignetting": 5e-3}


def radial(camera: Camera, device, dtype=torch.float32) -> Tensor:
    """(H, W) squared distance of each pixel centre from the principal point over the largest such
    distance at the image corners (0 at the principal point, 1 at the farthest corner)."""
    u = torch.arange(camera.width, device=device, dtype=dtype) + 0.5 - camera.cx
    v = torch.arange(camera.height, device=device, dtype=dtype) + 0.5 - camera.cy
    r2 = u[None, :] ** 2 + v[:, None] ** 2
    return r2 / corner_r2(camera)


class CameraAppearance:
    """Learned colour transform (and vignetting, when `vignetting`) of each camera in `train_cameras`
    (dataset indices) of a dataset with `num_cameras` cameras; other cameras are left as rendered."""

    def __init__(self, num_cameras: int, train_cameras, device, vignetting: bool = True):
        self.train_cameras = [int(c) for c in train_cameras]
        self.vignetting = bool(vignetting)
        self.device = torch.device(device)
        eye = torch.eye(3, device=self.device)
        self.matrix = {c: eye.clone().requires_grad_(True) for c in self.train_cameras}
        self.bias = {c: torch.zeros(3, device=self.device, requires_grad=True) for c in self.train_cameras}
        self.falloff = {c: torch.zeros(2, device=self.device, requires_grad=True) for c in self.train_cameras}
        self._radial: dict[int, Tensor] = {}
        self.num_cameras = int(num_cameras)

    def param_groups(self, lr: dict | None = None) -> list[dict]:
        """Adam parameter groups ("name": appearance_matrix / _bias / _vignetting)."""
        lr = {**APPEARANCE_LR, **(lr or {})}
        groups = [{"name": "appearance_matrix", "params": list(self.matrix.values()), "lr": lr["matrix"]},
                  {"name": "appearance_bias", "params": list(self.bias.values()), "lr": lr["bias"]}]
        if self.vignetting:
            groups.append({"name": "appearance_vignetting", "params": list(self.falloff.values()),
                           "lr": lr["vignetting"]})
        return groups

    def apply(self, image: Tensor, camera_index: int, camera: Camera) -> Tensor:
        """(H, W, 3) rgb of `camera` (dataset index camera_index) as that camera records it
        (differentiable in the image and the camera's appearance); unchanged for other cameras."""
        if camera_index not in self.matrix:
            return image
        out = image @ self.matrix[camera_index].T + self.bias[camera_index]
        return out * self._brightness(camera_index, camera, image)[..., None] if self.vignetting else out

    @torch.no_grad()
    def undo(self, image: Tensor, camera_index: int, camera: Camera) -> Tensor:
        """(H, W, 3) rgb that `camera` (dataset index camera_index) recorded, as the canonical scene would
        look: the inverse of `apply` (its falloff divided out, its transform inverted), so that
        apply(undo(y)) == y; unchanged for other cameras. Not differentiable."""
        if camera_index not in self.matrix:
            return image
        if self.vignetting:
            image = image / self._brightness(camera_index, camera, image)[..., None]
        return (image - self.bias[camera_index]) @ torch.linalg.inv(self.matrix[camera_index]).T

    def _brightness(self, camera_index: int, camera: Camera, image: Tensor) -> Tensor:
        """(H, W) the camera's learned falloff over its picture (its radial grid cached on first use)."""
        if camera_index not in self._radial:
            self._radial[camera_index] = radial(camera, image.device, image.dtype)
        return lens_brightness(self._radial[camera_index], self.falloff[camera_index])

    @torch.no_grad()
    def center(self) -> None:
        """Project the transforms so that their mean over the training cameras is the identity."""
        if not self.train_cameras:
            return
        excess = torch.stack(list(self.matrix.values())).mean(0) - torch.eye(3, device=self.device)
        offset = torch.stack(list(self.bias.values())).mean(0)
        for c in self.train_cameras:
            self.matrix[c].sub_(excess)
            self.bias[c].sub_(offset)

    @torch.no_grad()
    def set_gains(self, gains: np.ndarray) -> None:
        """Start each training camera's transform again from a measured colour gain: matrix diag(gain),
        bias 0; gains (C, 3) in train_cameras order, divided by their mean over the cameras (the
        transforms' mean stays the identity)."""
        gains = np.asarray(gains, np.float64)
        gains = gains / gains.mean(0)
        for c, gain in zip(self.train_cameras, gains):
            self.matrix[c].copy_(torch.diag(torch.as_tensor(gain, dtype=self.matrix[c].dtype)))
            self.bias[c].zero_()

    def state_dict(self) -> dict:
        return {"train_cameras": self.train_cameras, "vignetting": self.vignetting,
                "matrix": torch.stack([self.matrix[c].detach().cpu() for c in self.train_cameras]),
                "bias": torch.stack([self.bias[c].detach().cpu() for c in self.train_cameras]),
                "falloff": torch.stack([self.falloff[c].detach().cpu() for c in self.train_cameras])}

    def load_state_dict(self, state: dict) -> None:
        if [int(c) for c in state["train_cameras"]] != self.train_cameras:
            raise ValueError(f"appearance: the checkpoint's training cameras {state['train_cameras']} are not "
                             f"this dataset's {self.train_cameras}")
        with torch.no_grad():
            for i, c in enumerate(self.train_cameras):
                self.matrix[c].copy_(state["matrix"][i])
                self.bias[c].copy_(state["bias"][i])
                self.falloff[c].copy_(state["falloff"][i])

    def summary(self) -> list[dict]:
        """Per training camera: "camera" (index), "matrix" (3x3), "bias" (3), "vignetting" (k1, k2)."""
        return [{"camera": c, "matrix": self.matrix[c].detach().cpu().tolist(),
                 "bias": self.bias[c].detach().cpu().tolist(), "vignetting": self.falloff[c].detach().cpu().tolist()}
                for c in self.train_cameras]
