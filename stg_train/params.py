"""The trainable Spacetime Gaussian parameters, raw as the reference implementation stores them.

Per Gaussian (N rows; names and activations are those of stg_train.raw; gaussians_at evaluates them):

| name          | shape      | meaning (raw)                                      | initial value                     |
|---------------|------------|----------------------------------------------------|-----------------------------------|
| xyz           | (N, 3)     | position at the temporal centre (world units)      | the initial points                |
| motion        | (N, 9)     | cubic motion coefficients (per tau, tau^2, tau^3)  | 0                                 |
| features      | (N, 6 / 3) | base rgb + view feature (full) or rgb (lite)       | point colour (logit for full), 0  |
| time_features | (N, 3)     | time feature, multiplied by dt (full only)         | 0                                 |
| log_scale     | (N, 3)     | log standard deviations                            | log sqrt(mean 3-NN sq. distance)  |
| rotation      | (N, 4)     | quaternion wxyz at the centre (normalised at use)  | (1, 0, 0, 0)                      |
| omega         | (N, 4)     | rotation velocity (quaternion units per tau)       | 0                                 |
| opacity_logit | (N, 1)     | logit of the spatial opacity                       | logit(0.1)                        |
| t_center      | (N, 1)     | temporal centre (normalised time)                  | the point's frame time j / frames |
| t_scale_raw   | (N, 1)     | opacity(t) ~ exp(-(dt / exp(t_scale_raw))^2)        | 0                                 |

The full model adds the colour decoder (`DecoderMLP`: 12 -> 6, ReLU, 6 -> 3, no biases, per pixel) and
rgb = sigmoid(F[0:3] + decoder([F[3:9], camera centre, ray direction])); the lite model's rgb is F[0:3]
clamped to [0, 1] (formats/stg-v1.md, section 2).

Ablations (the paper's Table 4) switch components off by freezing raw parameters at their initial
values (`frozen`, names of COMPONENTS): "temporal_opacity" keeps t_scale_raw at STATIC_T_SCALE (temporal
opacity 1 at every time; t_center then only anchors the motion), "motion" keeps motion at 0,
"rotation" keeps omega at 0, "time_features" keeps the time features at 0. A *static* parameter set
(`static=True`, "time terms frozen") freezes all four.
"""
from __future__ import annotations

import math
from dataclasses import asdict, dataclass, replace
from typing import NamedTuple

import numpy as np
import torch
from torch import Tensor

from stg_runtime.camera import Camera

from .raw import RAW_KEYS

#: Per-Gaussian raw parameters, in a fixed order (optimizer groups follow it); lite models have no
#: time_features.
NAMES = RAW_KEYS
#: Parameters that only matter for dynamics: frozen (not trained) in a static model.
TIME_NAMES = ("motion", "omega", "time_features", "t_center", "t_scale_raw")
#: Raw temporal scale of static models: exp(-(dt / e^10)^2) = 1 to float32 precision for |dt| <= 1.
STATIC_T_SCALE = 10.0
KINDS = ("full", "lite")
#: Time components that an ablation can switch off, and the raw parameters each keeps at its initial value.
COMPONENTS = {"temporal_opacity": ("t_center", "t_scale_raw"), "motion": ("motion",), "rotation": ("omega",),
              "time_features": ("time_features",)}


class Gaussians(NamedTuple):
    """Static 3D Gaussians at one instant, as stg_train.render.rasterize takes them.
    means (N, 3); quats (N, 4) unit wxyz; scales (N, 3); opacities (N,); features (N, C), C = 3 or 9."""

    means: Tensor
    quats: Tensor
    scales: Tensor
    opacities: Tensor
    features: Tensor


def temporal_opacity(raw: dict[str, Tensor], tau: float | Tensor) -> Tensor:
    """(N,) sigmoid(opacity_logit) * exp(-((tau - t_center) / exp(t_scale_raw))^2), differentiable in all three;
    tau: one time, or (N,) one per Gaussian."""
    dt = tau - raw["t_center"].reshape(-1)
    s_t = torch.exp(raw["t_scale_raw"].reshape(-1))
    return torch.sigmoid(raw["opacity_logit"].reshape(-1)) * torch.exp(-(dt / s_t) ** 2)


def gaussians_at(raw: dict[str, Tensor], tau: float) -> Gaussians:
    """The Gaussians of raw parameters (stg_train.raw's table) at normalised time tau. As in the
    reference, dt = tau - t_center is detached for motion, rotation and the time features: only the
    temporal opacity sends gradient to t_center."""
    dt = (tau - raw["t_center"].reshape(-1)).detach()[:, None]  # (N, 1), no gradient to t_center
    m = raw["motion"]
    means = raw["xyz"] + dt * (m[:, 0:3] + dt * (m[:, 3:6] + dt * m[:, 6:9]))
    q = raw["rotation"] + dt * raw["omega"]
    quats = q / q.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    features = raw["features"]
    if raw.get("time_features") is not None:
        features = torch.cat([features, dt * raw["time_features"]], dim=-1)
    return Gaussians(means, quats, torch.exp(raw["log_scale"]), temporal_opacity(raw, tau), features)


def check_frozen(frozen) -> tuple[str, ...]:
    """The component names of `frozen` (any iterable of COMPONENTS keys), sorted; ValueError for others."""
    names = tuple(sorted(set(frozen)))
    unknown = [n for n in names if n not in COMPONENTS]
    if unknown:
        raise ValueError(f"unknown component(s) {unknown} to freeze; choose from {sorted(COMPONENTS)}")
    return names


def base_channels(kind: str) -> int:
    """Width of `features`: 6 (rgb + view feature) for full models, 3 (rgb) for lite."""
    return {"full": 6, "lite": 3}[kind]


@dataclass
class LearningRates:
    """Adam learning rates of the reference implementation (N3V settings) for 30k iterations.

    Lengths scale with the scene extent: xyz decays exponentially from xyz_init to xyz_final (times
    extent) over the run; motion is xyz_init x extent x motion_factor, constant. The others are constant.
    The trainer uses them `stretched` to its run's length.
    """

    xyz_init: float = 1.6e-4
    xyz_final: float = 1.6e-6
    motion_factor: float = 0.5 * 3.5
    features: float = 2.5e-3
    time_features: float = 1e-3
    log_scale: float = 5e-3
    rotation: float = 1e-3
    omega: float = 1e-4
    opacity_logit: float = 0.05
    t_center: float = 1e-4
    t_scale_raw: float = 0.03
    decoder: float = 1e-4

    def scaled(self, factor: float) -> "LearningRates":
        """Every rate times `factor` (short runs take bigger steps)."""
        return LearningRates(**{k: (v * factor if k != "motion_factor" else v) for k, v in asdict(self).items()})

    def stretched(self, iterations: int, reference_iterations: int = 30000, most: float = 50.0) -> "LearningRates":
        """These rates for a run of `iterations` steps: the motion and rotation velocities' rates
        (motion_factor, omega) times reference_iterations / iterations, within [1, most] (50 was the
        largest factor measured, at 600 steps), the others unchanged.

        Those velocities start at 0 and must grow to the scene's speeds, and Adam moves a parameter by
        at most about its rate per step: the reference's rates let them grow over its 30k steps, and a
        run stretched to fewer steps (Schedule.scaled) needs proportionally larger ones, or temporal
        opacity ends up doing the motion's work (docs/dynamic.md has the measurements)."""
        f = min(max(1.0, reference_iterations / max(int(iterations), 1)), most)
        return replace(self, motion_factor=self.motion_factor * f, omega=self.omega * f)


class DecoderMLP(torch.nn.Module):
    """The full model's colour decoder, applied per pixel: (P, 12) -> (P, 3), 12 -> 6 ReLU -> 3, no biases.

    Weights are initialised like torch's Linear / the reference's 1x1 Conv2d (Kaiming uniform).
    """

    def __init__(self, in_channels: int = 12, hidden: int = 6):
        super().__init__()
        self.layer1 = torch.nn.Linear(in_channels, hidden, bias=False)
        self.layer2 = torch.nn.Linear(hidden, 3, bias=False)

    def forward(self, x: Tensor) -> Tensor:
        return self.layer2(torch.relu(self.layer1(x)))

    def weights(self) -> list[np.ndarray]:
        """[(6, 12), (3, 6)] float32 (out, in) matrices, as stg_runtime.onnx_mlp.mlp_to_onnx takes them."""
        return [self.layer1.weight.detach().cpu().numpy().astype(np.float32),
                self.layer2.weight.detach().cpu().numpy().astype(np.float32)]


def view_inputs(camera: Camera, device, dtype=torch.float32) -> Tensor:
    """(H, W, 6) [camera centre, unit ray direction of each pixel centre], world coordinates."""
    rays = torch.as_tensor(camera.ray_directions(), dtype=dtype, device=device)
    centre = torch.as_tensor(camera.center, dtype=dtype, device=device).expand_as(rays)
    return torch.cat([centre, rays], dim=-1)


class STGParams:
    """The trainable model: raw per-Gaussian tensors (`self.raw[name]`, leaf tensors with grad) plus
    the decoder (full models). `kind`: "full" or "lite"; `frozen`: COMPONENTS switched off (see module
    doc); `static=True` freezes them all.
    """

    def __init__(self, raw: dict[str, Tensor], kind: str = "full", static: bool = False,
                 decoder: DecoderMLP | None = None, frozen=()):
        if kind not in KINDS:
            raise ValueError(f"kind must be one of {KINDS}, got {kind!r}")
        self.kind = kind
        self.frozen = tuple(sorted(COMPONENTS)) if static else check_frozen(frozen)
        self.raw: dict[str, Tensor] = {}
        for name in self.names(kind):
            t = raw[name].detach().clone().contiguous()
            t.requires_grad_(self.trainable(name))
            self.raw[name] = t
        if kind == "full":
            self.decoder = decoder if decoder is not None else DecoderMLP()
            self.decoder.to(self.raw["xyz"].device)
        else:
            self.decoder = None

    # -- construction -----------------------------------------------------------------------------
    @classmethod
    def from_points(cls, xyz: np.ndarray, rgb: np.ndarray, t_center: np.ndarray, kind: str = "full",
                    static: bool = False, device="cpu", seed: int = 0, frozen=()) -> "STGParams":
        """Initial parameters from points xyz (N, 3) with colours rgb (N, 3) in [0, 1] and temporal
        centres t_center (N,) in normalised time, as the reference initialises from SfM points.
        `seed` initialises the decoder weights; static / frozen: see the class."""
        frozen = tuple(sorted(COMPONENTS)) if static else check_frozen(frozen)
        xyz = torch.as_tensor(np.asarray(xyz), dtype=torch.float32)
        log_scale = torch.log(torch.sqrt(knn_mean_sq_dist(xyz, 3).clamp_min(1e-7))).clamp(-10, 1)
        raw = initial_raw(xyz, torch.as_tensor(np.asarray(rgb), dtype=torch.float32),
                          torch.as_tensor(np.asarray(t_center), dtype=torch.float32), log_scale, kind, frozen)
        with torch.random.fork_rng():
            torch.manual_seed(seed)
            decoder = DecoderMLP() if kind == "full" else None
        return cls({k: v.to(device) for k, v in raw.items()}, kind, False, decoder, frozen)

    def new_rows(self, xyz: Tensor, rgb: Tensor, t_center: Tensor, opacity: float = 0.1) -> dict[str, Tensor]:
        """Raw values (on this model's device) of new Gaussians at xyz (K, 3) with colours rgb (K, 3) in
        [0, 1], temporal centres t_center (K,) and spatial `opacity`, initialised like from_points (scale
        from the 3 nearest points among the new and the existing ones), for strategy.append_gaussians."""
        xyz = xyz.detach().float().cpu()
        k = xyz.shape[0]
        both = torch.cat([xyz, self.raw["xyz"].detach().float().cpu()])
        log_scale = torch.log(torch.sqrt(knn_mean_sq_dist(both, 3, rows=k).clamp_min(1e-7))).clamp(-10, 1)
        raw = initial_raw(xyz, rgb.detach().float().cpu(), t_center.detach().float().cpu(), log_scale, self.kind,
                          self.frozen, opacity)
        return {name: v.to(self.device) for name, v in raw.items()}

    @staticmethod
    def names(kind: str) -> tuple[str, ...]:
        """The raw parameter names of a model kind (lite models have no time_features)."""
        return tuple(n for n in NAMES if not (kind == "lite" and n == "time_features"))

    def trainable(self, name: str) -> bool:
        """Whether raw parameter `name` is optimised (not kept fixed by a frozen component)."""
        return not any(name in COMPONENTS[c] for c in self.frozen)

    @property
    def static(self) -> bool:
        """True when every time component is frozen (a static scene model)."""
        return len(self.frozen) == len(COMPONENTS)

    # -- properties -------------------------------------------------------------------------------
    @property
    def count(self) -> int:
        return int(self.raw["xyz"].shape[0])

    @property
    def device(self) -> torch.device:
        return self.raw["xyz"].device

    def __getitem__(self, name: str) -> Tensor:
        return self.raw[name]

    # -- evaluation -------------------------------------------------------------------------------
    def at(self, tau: float):
        """The Gaussians at normalised time tau (gaussians_at): means, quats, scales, opacities,
        features, differentiable w.r.t. the raw parameters."""
        return gaussians_at(self.raw, tau)

    def colour(self, features: Tensor, camera: Camera, rays: Tensor | None = None) -> Tensor:
        """Splatted features (H, W, C) -> rgb (H, W, 3). rays: view_inputs(camera), if precomputed."""
        if self.kind == "lite":
            return features[..., :3].clamp(0, 1)
        if rays is None:
            rays = view_inputs(camera, features.device, features.dtype)
        x = torch.cat([features[..., 3:], rays], dim=-1)
        return torch.sigmoid(features[..., :3] + self.decoder(x))

    # -- optimisation -----------------------------------------------------------------------------
    def param_groups(self, lr: LearningRates, extent: float) -> list[dict]:
        """Adam parameter groups, one per trainable tensor ("name" key), with their initial rates."""
        rates = {"xyz": lr.xyz_init * extent, "motion": lr.xyz_init * extent * lr.motion_factor,
                 "features": lr.features, "time_features": lr.time_features, "log_scale": lr.log_scale,
                 "rotation": lr.rotation, "omega": lr.omega, "opacity_logit": lr.opacity_logit,
                 "t_center": lr.t_center, "t_scale_raw": lr.t_scale_raw}
        groups = [{"name": n, "params": [self.raw[n]], "lr": rates[n]} for n in self.raw if self.trainable(n)]
        if self.decoder is not None:
            groups.append({"name": "decoder", "params": list(self.decoder.parameters()), "lr": lr.decoder})
        return groups

    # -- persistence ------------------------------------------------------------------------------
    def state_dict(self) -> dict:
        return {"kind": self.kind, "static": self.static, "frozen": list(self.frozen),
                "raw": {k: v.detach().cpu().clone() for k, v in self.raw.items()},
                "decoder": None if self.decoder is None else {k: v.cpu().clone()
                                                               for k, v in self.decoder.state_dict().items()}}

    @classmethod
    def from_state_dict(cls, state: dict, device="cpu") -> "STGParams":
        decoder = None
        if state["decoder"] is not None:
            decoder = DecoderMLP()
            decoder.load_state_dict(state["decoder"])
        return cls({k: v.to(device) for k, v in state["raw"].items()}, state["kind"], state["static"], decoder,
                   state.get("frozen", ()))


def initial_raw(xyz: Tensor, rgb: Tensor, t_center: Tensor, log_scale: Tensor, kind: str, frozen=(),
                opacity: float = 0.1) -> dict[str, Tensor]:
    """Initial raw parameters (CPU) of K Gaussians: xyz (K, 3), rgb (K, 3) in [0, 1], t_center (K,),
    log_scale (K,) isotropic; identity rotation, no motion, spatial `opacity`, temporal scale 0 (or
    STATIC_T_SCALE when "temporal_opacity" is frozen). The full model's base colour is logit(rgb) (the
    decoder adds sigmoid)."""
    n = xyz.shape[0]
    base = torch.zeros(n, base_channels(kind))
    base[:, :3] = rgb
    if kind == "full":
        base[:, :3] = torch.logit(rgb.clamp(0.02, 0.98))
    rotation = torch.zeros(n, 4)
    rotation[:, 0] = 1
    raw = {"xyz": xyz, "motion": torch.zeros(n, 9), "features": base,
           "time_features": torch.zeros(n, 3), "log_scale": log_scale.reshape(n, 1).repeat(1, 3),
           "rotation": rotation, "omega": torch.zeros(n, 4),
           "opacity_logit": torch.full((n, 1), math.log(opacity / (1 - opacity))),
           "t_center": t_center.reshape(n, 1),
           "t_scale_raw": torch.full((n, 1), STATIC_T_SCALE if "temporal_opacity" in frozen else 0.0)}
    return {k: v for k, v in raw.items() if k in STGParams.names(kind)}


def position_lr(lr: LearningRates, extent: float, step: int, total: int) -> float:
    """The exponentially decaying position rate at `step` of `total` (3DGS's schedule, no delay)."""
    frac = min(max(step / max(total, 1), 0.0), 1.0)
    return extent * math.exp((1 - frac) * math.log(lr.xyz_init) + frac * math.log(lr.xyz_final))


def knn_mean_sq_dist(points: Tensor, k: int = 3, rows: int | None = None) -> Tensor:
    """(N,) float32 mean squared distance of each point of points (N, 3) to its k nearest other points
    (a k-d tree: O(N log N) time, O(N) memory); only for the first `rows` points ((rows,) result) when
    given."""
    from scipy.spatial import cKDTree

    n = points.shape[0]
    m = n if rows is None else min(int(rows), n)
    if n <= 1:
        return torch.ones(m)
    k = min(k, n - 1)
    p = points.detach().cpu().double().numpy()
    dist, _ = cKDTree(p).query(p[:m], k=k + 1)  # the first of each row is the point itself
    return torch.from_numpy((dist[:, 1:] ** 2).mean(1)).float()


def extent_of(cameras) -> float:
    """Scene extent as 3DGS measures it: 1.1 x the largest distance of a camera centre from their mean
    (world units); at least 1e-3 x the rig's distance scale for a single camera."""
    centres = np.stack([c.center for c in cameras])
    radius = float(np.linalg.norm(centres - centres.mean(0), axis=1).max()) * 1.1
    return radius if radius > 0 else 1.0
