"""Camera pose refinement: a small rigid correction of each training camera's stated pose, learned with
the scene, through a transform of the Gaussians (so every splatter gives it gradients, the CPU numba
splatter included, whose kernels have none with respect to the camera).

For training camera c with stated world_to_camera W (4x4, OpenCV, formats/stg-v1.md) the refined
camera is D_c W, where D_c (4x4, camera coordinates) is the rotation exp([w_c]x) (axis-angle w_c,
radians) followed by the translation t_c (world units). Rendering the Gaussians mapped by
A_c = W^-1 D_c W with the stated camera W gives the refined camera's picture of the unmapped Gaussians:
means x -> A_c x, rotations q -> q_A (x) q (wxyz, q_A the quaternion of A_c's rotation), scales,
opacities and features unchanged; the decoder's view inputs become the refined camera's centre and rays
(A_c^-1 applied to the stated ones). w_c and t_c start at 0; cameras that are not trained (held out)
keep their stated pose.

After every step `center` removes from the corrections their part that is a similarity of the whole
world (stg_train.rig.gauge): seven freedoms that pictures cannot reveal, in which the corrections would
otherwise drift and take the scene with them (a drift in scale, invisible to the training cameras,
moves the picture of a view away from the rig). The scene stays where the stated poses put it, at their
scale.
"""
from __future__ import annotations

from dataclasses import replace

import numpy as np
import torch
from torch import Tensor

from stg_runtime.camera import Camera

from .gauge import gauge_projector

#: Adam learning rates of the pose corrections (per step; decayed with the run, see Trainer): rotation in
#: radians, translation in units of the scene's depth (PoseCorrections' `scale`: data.bounds.typical_depth,
#: else params.extent_of), so that both move the pictures alike. gsplat's pose_opt_lr; at 1e-4 the
#: corrections drifted with the scene and cost a novel view 2.4 dB on a clean capture (docs/notes/real-captures.md,
#: "Measured").
POSE_LR = {"rotation": 1e-5, "translation": 1e-5}


def _skew(w: Tensor) -> Tensor:
    zero = torch.zeros((), dtype=w.dtype, device=w.device)
    return torch.stack([torch.stack([zero, -w[2], w[1]]), torch.stack([w[2], zero, -w[0]]),
                        torch.stack([-w[1], w[0], zero])])


def rotation_matrix(w: Tensor) -> Tensor:
    """(3, 3) rotation exp([w]x) of an axis-angle vector w (3,) in radians (differentiable, also at 0)."""
    return torch.linalg.matrix_exp(_skew(w))


def quaternion(w: Tensor) -> Tensor:
    """(4,) unit quaternion wxyz of the rotation exp([w]x) (differentiable, also at 0)."""
    theta = torch.sqrt((w * w).sum() + 1e-24)
    return torch.cat([torch.cos(theta / 2)[None], w * (torch.sin(theta / 2) / theta)])


def quaternion_product(a: Tensor, b: Tensor) -> Tensor:
    """Hamilton product a (x) b of wxyz quaternions, a (4,) or (N, 4), b (N, 4): rotation a after b."""
    aw, ax, ay, az = a.unbind(-1)
    bw, bx, by, bz = b.unbind(-1)
    return torch.stack([aw * bw - ax * bx - ay * by - az * bz, aw * bx + ax * bw + ay * bz - az * by,
                        aw * by - ax * bz + ay * bw + az * bx, aw * bz + ax * by - ay * bx + az * bw], dim=-1)


def correction(rotation: Tensor, translation: Tensor) -> Tensor:
    """(4, 4) rigid D: rotation exp([rotation]x), then translation."""
    top = torch.cat([rotation_matrix(rotation), translation[:, None]], dim=1)
    bottom = torch.tensor([[0.0, 0.0, 0.0, 1.0]], dtype=top.dtype, device=top.device)
    return torch.cat([top, bottom])


class PoseCorrections:
    """Learned pose corrections (w_c, t_c) of the cameras `train_cameras` (dataset indices); `scale`:
    the translation's parameter unit in world units (the scene's depth from the cameras, where a shift by
    it moves the pictures as much as a turn by a radian), so one learning rate fits any scene."""

    def __init__(self, train_cameras, cameras: list[Camera], device, scale: float = 1.0, depth: float | None = None):
        """cameras: the dataset's stated cameras (indexed like it), whose poses `center` needs to find
        the gauge in world coordinates; depth: the scene's depth from them (world units,
        data.bounds.typical_depth), at which the gauge is measured in their pictures
        (gauge.fit_similarity; None: the rig's radius)."""
        self.train_cameras = [int(c) for c in train_cameras]
        self.device = torch.device(device)
        self.scale = float(scale)
        self.depth = depth
        stated = np.stack([np.asarray(cameras[c].world_to_camera, np.float64) for c in self.train_cameras])
        self._projector = gauge_projector(stated, depth) if self.train_cameras else None
        self._gauge = self._scaled_gauge()
        self.rotation = {c: torch.zeros(3, device=self.device, requires_grad=True) for c in self.train_cameras}
        self.translation = {c: torch.zeros(3, device=self.device, requires_grad=True) for c in self.train_cameras}

    def _scaled_gauge(self) -> Tensor | None:
        """gauge.gauge_projector for the parameters (rotations in radians, translations in units of
        `scale`, where the projector takes world units), float64 on the device."""
        if self._projector is None:
            return None
        units = np.repeat([1.0, self.scale], 3 * len(self.train_cameras))
        return torch.as_tensor(self._projector * units[None, :] / units[:, None], device=self.device)

    def param_groups(self, lr: dict | None = None) -> list[dict]:
        lr = {**POSE_LR, **(lr or {})}
        return [{"name": "pose_rotation", "params": list(self.rotation.values()), "lr": lr["rotation"]},
                {"name": "pose_translation", "params": list(self.translation.values()), "lr": lr["translation"]}]

    def delta(self, camera_index: int) -> Tensor:
        """(4, 4) D_c of a training camera (float32, differentiable)."""
        return correction(self.rotation[camera_index], self.translation[camera_index] * self.scale)

    def apply(self, gaussians, rays: Tensor, camera_index: int, camera: Camera):
        """(Gaussians mapped by A_c = W^-1 D_c W, view inputs (H, W, 6) of the refined camera) for
        rendering training camera `camera_index` with its stated `camera`; unchanged for other cameras.
        gaussians: params.Gaussians; rays: params.view_inputs of the stated camera."""
        if camera_index not in self.rotation:
            return gaussians, rays
        w2c = torch.as_tensor(np.array(camera.world_to_camera), dtype=gaussians.means.dtype, device=gaussians.means.device)
        c2w = torch.linalg.inv(w2c)
        delta = self.delta(camera_index).to(gaussians.means.dtype)
        a = c2w @ delta @ w2c
        a_inv = c2w @ torch.linalg.inv(delta) @ w2c
        means = gaussians.means @ a[:3, :3].T + a[:3, 3]
        w = self.rotation[camera_index].to(gaussians.means.dtype)
        q_a = quaternion(w2c[:3, :3].T @ w)  # A's rotation R_W^T R_D R_W: D's axis in world coordinates
        quats = quaternion_product(q_a, gaussians.quats)
        centre = rays[..., :3] @ a_inv[:3, :3].T + a_inv[:3, 3]
        directions = rays[..., 3:] @ a_inv[:3, :3].T
        return gaussians._replace(means=means, quats=quats), torch.cat([centre, directions], dim=-1)

    @torch.no_grad()
    def center(self) -> None:
        """Project the gauge out of the corrections (module docstring): a similarity shared by every
        camera is a motion of the whole scene, which the data cannot fix."""
        if not self.train_cameras:
            return
        x = torch.cat([torch.stack([self.rotation[c] for c in self.train_cameras]).reshape(-1),
                       torch.stack([self.translation[c] for c in self.train_cameras]).reshape(-1)])
        part = (self._gauge @ x.double()).reshape(2, -1, 3)
        for i, c in enumerate(self.train_cameras):
            self.rotation[c].sub_(part[0, i].to(self.rotation[c].dtype))
            self.translation[c].sub_(part[1, i].to(self.translation[c].dtype))

    @torch.no_grad()
    def refined(self, cameras: list[Camera]) -> list[Camera]:
        """`cameras` (the dataset's, indexed as it is) with the training cameras' poses refined: D_c W."""
        out = list(cameras)
        for c in self.train_cameras:
            d = self.delta(c).double().cpu().numpy()
            out[c] = replace(cameras[c], world_to_camera=d @ np.asarray(cameras[c].world_to_camera, np.float64))
        return out

    def state_dict(self) -> dict:
        return {"train_cameras": self.train_cameras, "scale": self.scale,
                "rotation": torch.stack([self.rotation[c].detach().cpu() for c in self.train_cameras]),
                "translation": torch.stack([self.translation[c].detach().cpu() for c in self.train_cameras])}

    def load_state_dict(self, state: dict) -> None:
        if [int(c) for c in state["train_cameras"]] != self.train_cameras:
            raise ValueError(f"pose refinement: the checkpoint's training cameras {state['train_cameras']} are not "
                             f"this dataset's {self.train_cameras}")
        self.scale = float(state["scale"])
        self._gauge = self._scaled_gauge()
        with torch.no_grad():
            for i, c in enumerate(self.train_cameras):
                self.rotation[c].copy_(state["rotation"][i])
                self.translation[c].copy_(state["translation"][i])
