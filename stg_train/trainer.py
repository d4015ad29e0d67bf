"""The training loop: batches of views at one time, loss, Adam, density control, checkpoints, progress.

Each step draws one frame j (normalised time frame_time(dataset, j): j / num_frames, or over the shown
frames of a segment with context, whose context frames lie just outside [0, 1); the video's end frames
TrainConfig.edge_weight times as often, Trainer.sample_frame) and `batch` training cameras, renders
them with the configured splatter (stg_train.render.rasterize), and minimises 0.8 L1 + 0.2 (1 - SSIM)
(stg_train.losses) averaged over the views; the strategies (stg_train.strategy) act around backward(). Ground-truth frames stay on the CPU as uint8 (the dataset's
memory map) and only the batch's frames move to the device, so memory does not grow with the frame count.

A checkpoint holds everything the next step depends on (parameters, Adam state, strategy state, the
step, the numpy / torch / python RNG states), so a run stopped at any moment and resumed from its last
checkpoint reaches the same state as an uninterrupted run (on the same device and thread count).
"""
from __future__ import annotations

import random
import time
from dataclasses import asdict, replace
from pathlib import Path
from typing import Callable

import numpy as np
import torch
from torch import Tensor

from stg_runtime.atomic import atomic_output, remove_leftovers
from stg_runtime.camera import Camera
from stg_runtime.progress import Progress

from .checkpoint import read_checkpoint
from .data.flow import initial_velocity
from .config import MOTION_INITS, TrainConfig  # noqa: F401 (TrainConfig's home is config; re-exported)
from .data.points import InitialPoints, initial_points
from .losses import loss_fn
from .metrics import psnr_of_mse
from .params import LearningRates, STGParams, extent_of, position_lr, view_inputs
from .render import rasterize
from .rig.camera_rig import CameraRig
from .strategy import Schedule, StepContext, Strategy, StrategySetup, build_strategies
from .warm import warm_steps

CHECKPOINT_VERSION = 1
#: The time axis of the checkpoints written here (frame_time): normalised over the shown frames. Those of a
#: segment with context frames written before it ("time" absent) spanned the context frames too.
TIME_AXIS = "shown"


# -- the trainer ------------------------------------------------------------------------------------
def run_steps(iterations: int, dataset) -> int:
    """A run's length in steps: `iterations`, or for a dataset with context frames (a segment's
    neighbouring frames, Dataset.context_frames) that many times its frames over the frames it shows,
    so that the shown frames are drawn as often as without context."""
    before, after = getattr(dataset, "context_frames", (0, 0))
    return round(iterations * dataset.num_frames / (dataset.num_frames - before - after))


def frame_time(dataset, j: int) -> float:
    """Normalised time of frame j (0-based, context frames included) of a dataset: tau = j / num_frames,
    where a dataset with context frames (Dataset.context_frames (before, after)) counts over the frames
    it shows, tau = (j - before) / (num_frames - before - after), so that its context frames lie just
    outside [0, 1) and a segment's time axis is the same with context or without (the exported
    segment's, formats/stg-v1.md; the players render a crossfade's frames at those times)."""
    before, after = getattr(dataset, "context_frames", (0, 0))
    return (j - before) / (dataset.num_frames - before - after)


def shown_frames(dataset):
    """The dataset without its context frames (Dataset.shown; a dataset without them as it is)."""
    return dataset.shown() if hasattr(dataset, "shown") else dataset


#: Schedule overrides of a warm-started segment (stg_train.warm): no opacity reset (it would throw away
#: the opacities carried from the previous segment); density control otherwise stretched to its steps.
WARM_SCHEDULE = {"reset_every": 0}


#: How many frames at each end of the shown frames (trainer.frame_weights) TrainConfig.edge_weight applies to.
EDGE_FRAMES = 3
#: A video's own first and last frames are drawn this many times as often again as the other edge frames
#: (trainer.frame_weights): a video's end has no neighbour to borrow from, and its end frame alone
#: carries the loss (docs/training.md, "Seams").
END_FRAME_FACTOR = 2


def frame_weights(num_frames: int, context: tuple[int, int], edge_weight: float) -> np.ndarray | None:
    """(num_frames,) probabilities of drawing each frame of a dataset whose first and last `context`
    frames are context (Trainer.sample_frame): the EDGE_FRAMES first and last frames it shows (a video's
    ends, or a segment's frames next to a seam, its context frames beyond them) `edge_weight` times as
    often as the others, and where edge_weight is over 1, a shown end frame with no context beyond it
    (a video's first or last frame) END_FRAME_FACTOR times that; None when they are all equal."""
    p = np.ones(num_frames)
    before, after = context
    p[before:before + EDGE_FRAMES] = edge_weight
    p[max(before, num_frames - after - EDGE_FRAMES):num_frames - after] = edge_weight
    if edge_weight > 1 and before == 0:
        p[0] *= END_FRAME_FACTOR
    if edge_weight > 1 and after == 0:
        p[-1] *= END_FRAME_FACTOR
    return None if np.all(p == p[0]) else p / p.sum()


class Trainer:
    """Trains STGParams on a Dataset (stg_train.data.Dataset).

    out_dir: where checkpoint.pt goes (None: no checkpoints). Build a fresh run with Trainer(dataset,
    config, out_dir) or continue one with Trainer.resume(dataset, checkpoint_path). init_progress(done, total):
    called per frame while SfM computes the initial points (not when cached); motion_progress(done,
    total): per frame while the optical flow gives them their initial motion (motion_init "flow");
    calibration_progress(done, total): per camera pair while the rig is measured for a lens_falloff,
    appearance or pose_refine "auto" (stg_train.rig.self_calibration). self.rig: the run's CameraRig,
    what its cameras do to the picture (self.config: the choices made of "auto"). initial: the
    stg_train.data.points.InitialPoints of a fresh run (None when resumed). A dataset without near/far
    bounds gets those the initialisation derived (self.dataset is then a view of it with them; a resumed
    run takes them from the checkpoint), so guided sampling clips to them as on N3V.
    """

    def __init__(self, dataset, config: TrainConfig, out_dir=None, _state: dict | None = None,
                 init_progress: Callable[[int, int], None] | None = None,
                 motion_progress: Callable[[int, int], None] | None = None,
                 calibration_progress: Callable[[int, int], None] | None = None, warm=None):
        if config.motion_init not in MOTION_INITS:
            raise ValueError(f"motion_init must be one of {MOTION_INITS}, got {config.motion_init!r}")
        # the cameras' "auto" settings decided from the rig (a resumed run keeps its choices): self.config
        self.rig = CameraRig(dataset, config.for_dataset(dataset), _state, calibration_progress)
        config, self.dataset = self.config, dataset
        self.out_dir = None if out_dir is None else Path(out_dir)
        if self.out_dir is not None:
            remove_leftovers(self.out_dir, "checkpoint.pt")  # of a run killed while saving
        self.device = torch.device(config.device)
        self.extent = extent_of([dataset.cameras[i] for i in dataset.train_cameras])
        self.lr = LearningRates(**config.learning_rates).scaled(config.lr_scale)
        self.warm = warm is not None or bool((_state or {}).get("warm"))
        cold_steps = run_steps(config.iterations, dataset)
        self.steps = run_steps(warm_steps(config.iterations, config.warm_fraction), dataset) if self.warm else cold_steps
        self.frame_p = frame_weights(dataset.num_frames, getattr(dataset, "context_frames", (0, 0)), config.edge_weight)
        if config.stretch_rates:  # a warm start's velocities are trained already: a cold run's rates
            self.lr = self.lr.stretched(cold_steps)
        self.schedule = Schedule.scaled(self.steps, **{**(WARM_SCHEDULE if self.warm else {}), **config.schedule})
        self._rays: dict[int, Tensor] = {}
        if _state is None and warm is not None:
            random.seed(config.seed)
            torch.manual_seed(config.seed)
            self.rng = np.random.default_rng(config.seed)
            self.initial = None
            if dataset.bounds is None and warm.bounds is not None:
                self.dataset = dataset.with_bounds(warm.bounds, warm.bounds_source or "sfm")
            self.params = STGParams.from_state_dict(warm.params.state_dict(), self.device)
            if config.warm_points:
                self._add_initial_points(init_progress)
            self.box = np.asarray(warm.box)
            self.step = 0
        elif _state is None:
            random.seed(config.seed)
            torch.manual_seed(config.seed)
            self.rng = np.random.default_rng(config.seed)
            self.initial = self._initial_points(init_progress)
            xyz, rgb, t_center = self.initial.xyz, self.initial.rgb, self.initial.t_center
            if dataset.bounds is None and self.initial.bounds is not None:
                self.dataset = dataset.with_bounds(self.initial.bounds, self.initial.bounds_source)
            self.params = STGParams.from_points(xyz, rgb, t_center, config.model, config.static,
                                                self.device, seed=config.seed, frozen=config.frozen)
            if config.motion_init == "flow" and self.params.trainable("motion"):
                velocity = initial_velocity(shown_frames(self.dataset), xyz, rgb, t_center, progress=motion_progress)
                with torch.no_grad():
                    self.params.raw["motion"][:, 0:3] = torch.as_tensor(velocity, device=self.device)
            self.box = np.stack([xyz.min(0), xyz.max(0)])
            self.step = 0
        else:
            self.initial = None
            if dataset.bounds is None and _state.get("bounds") is not None:
                self.dataset = dataset.with_bounds(np.asarray(_state["bounds"]), _state.get("bounds_source") or "sfm")
            self.params = STGParams.from_state_dict(_state["params"], self.device)
            self.box = np.asarray(_state["box"])
            self.step = int(_state["step"])
            self.rng = np.random.default_rng()
        self.optimizer = torch.optim.Adam(self.params.param_groups(self.lr, self.extent), eps=1e-15, fused=True)
        self.strategies: list[Strategy] = build_strategies(StrategySetup(config, self.schedule, self.extent, self.box))
        self.rig.start(self.dataset, self.device, self.extent, self.steps)
        self.history: list[dict] = []  # per-step figures: step, loss, psnr, gaussians, seconds
        self.seconds = 0.0  # training time so far (excluding checkpoints and callbacks)
        if _state is not None:
            self.optimizer.load_state_dict(_state["optimizer"])
            self.rig.load_state_dict(_state)
            for s, st in zip(self.strategies, _state["strategies"]):
                s.load_state_dict(st)
            self.history, self.seconds = list(_state["history"]), float(_state["seconds"])
            self.rng.bit_generator.state = _state["rng"]["numpy"]
            torch.set_rng_state(_state["rng"]["torch"])
            if _state["rng"].get("cuda") is not None and torch.cuda.is_available():
                torch.cuda.set_rng_state_all(_state["rng"]["cuda"])
            random.setstate(_state["rng"]["python"])

    @property
    def config(self) -> TrainConfig:
        """The run's settings, its cameras' "auto" ones decided (CameraRig.config)."""
        return self.rig.config

    def refined_cameras(self) -> list[Camera]:
        """The dataset's cameras, the training cameras' poses refined when pose_refine is on."""
        return self.rig.refined(self.dataset.cameras)

    # -- rendering ------------------------------------------------------------------------------------
    def rays(self, camera_index: int) -> Tensor:
        """(H, W, 6) decoder view inputs of a dataset camera, cached on the device."""
        if camera_index not in self._rays:
            if len(self._rays) >= 64:
                self._rays.clear()
            self._rays[camera_index] = view_inputs(self.dataset.cameras[camera_index], self.device)
        return self._rays[camera_index]

    def render(self, camera: Camera, tau: float, gaussians=None, rays: Tensor | None = None):
        """rgb (H, W, 3) and the render.RenderOutput of `camera` at normalised time tau (differentiable)."""
        g = self.params.at(tau) if gaussians is None else gaussians
        out = rasterize(g.means, g.quats, g.scales, g.opacities, g.features, camera, backend=self.config.splatter)
        return self.params.colour(out.features, camera, rays), out

    def ground_truth(self, camera_index: int, frame: int) -> Tensor:
        """(H, W, 3) float in [0, 1] on the device (moved from the CPU uint8 frame)."""
        frame_u8 = torch.from_numpy(self.dataset.frame(camera_index, frame))
        return frame_u8.to(self.device, non_blocking=True).float() / 255.0

    def canonical_truth(self, camera_index: int, frame: int) -> Tensor:
        """(H, W, 3) ground truth of a camera as the canonical scene would look (CameraRig.canonical), what
        guided sampling compares with the canonical render (strategy.guided)."""
        return self.rig.canonical(self.ground_truth(camera_index, frame), camera_index,
                                  self.dataset.cameras[camera_index])

    def _initial_points(self, progress) -> InitialPoints:
        """The initial points, from the frames the dataset shows (not its context frames: those only
        refine what the shown frames start), their t_center normalised over those (frame_time), and from
        those pictures as the canonical scene would look (initial_brightness): the view volume's depth
        search compares the cameras' colours, which their exposures, white balances and vignetting set
        apart (docs/training.md, "Real captures")."""
        config = self.config
        shown = shown_frames(self.dataset)
        brightness = self.rig.initial_brightness()
        return initial_points(shown.corrected(brightness) if brightness else shown, config.init, config.num_points,
                              self.rng, every=config.init_every, depth_candidates=config.depth_candidates,
                              progress=progress)

    def _add_initial_points(self, progress) -> None:
        """A warm start's Gaussians joined by the segment's own initial points (as a cold start's,
        their temporal centres over the segment): the carried ones hold what the seam shows, the new ones
        the rest of the segment (TrainConfig.warm_points)."""
        self.initial = self._initial_points(progress)
        new = self.params.new_rows(*(torch.as_tensor(np.asarray(a), dtype=torch.float32) for a in
                                     (self.initial.xyz, self.initial.rgb, self.initial.t_center)))
        p = self.params
        raw = {k: torch.cat([v.detach(), new[k].to(v.dtype)]) for k, v in p.raw.items()}
        self.params = STGParams(raw, p.kind, p.static, p.decoder, p.frozen)

    # -- one step -------------------------------------------------------------------------------------
    def sample_frame(self) -> int:
        """A frame index of the dataset, uniformly drawn, except that the EDGE_FRAMES first and last frames
        it shows (a video's ends, or a segment's frames next to a seam; Dataset.context_frames lie beyond
        them) are drawn TrainConfig.edge_weight times as often (self.frame_p)."""
        if self.frame_p is None:
            return int(self.rng.integers(self.dataset.num_frames))
        return int(self.rng.choice(len(self.frame_p), p=self.frame_p))

    def train_step(self) -> dict:
        """One optimisation step; returns {"loss", "psnr"} of the batch."""
        cfg, ds = self.config, self.dataset
        self.step += 1
        frame = self.sample_frame()
        train = ds.train_cameras
        views = [train[i] for i in self.rng.choice(len(train), size=min(cfg.batch, len(train)), replace=False)]
        tau = frame_time(ds, frame)
        for group in self.optimizer.param_groups:
            if group["name"] == "xyz":
                group["lr"] = position_lr(self.lr, self.extent, self.step, self.steps)
        gaussians = self.params.at(tau)
        images, renders = [], []
        for ci in views:
            rgb, out = self.render(ds.cameras[ci], tau, *self.rig.view(gaussians, self.rays(ci), ci, ds.cameras[ci]))
            images.append(self.rig.recorded(rgb, ci, ds.cameras[ci]))
            renders.append((ds.cameras[ci], out))
        img = torch.stack(images)
        gt = torch.stack([self.ground_truth(ci, frame) for ci in views])
        context = StepContext(ds, frame, tau, renders,
                              lambda ci, t: self.render(ds.cameras[ci], t, rays=self.rays(ci)), self.canonical_truth)
        for strategy in self.strategies:
            strategy.step_pre_backward(self.params, self.optimizer, self.step, context)
        loss = loss_fn(img, gt)
        loss.backward()
        with torch.no_grad():
            mse = ((img.detach() - gt) ** 2).mean().item()
        for strategy in self.strategies:
            strategy.step_post_backward(self.params, self.optimizer, self.step, context)
        self.optimizer.step()
        self.optimizer.zero_grad(set_to_none=True)
        self.rig.end_step(self.step, lambda camera, f: self.render(camera, frame_time(ds, f)))
        return {"loss": loss.item(), "psnr": psnr_of_mse(max(mse, 1e-12))}

    def train(self, progress: bool = True, callback: Callable[["Trainer"], None] | None = None,
              label: str = "train", job: tuple[int, int] | None = None) -> None:
        """Run to self.steps, checkpointing every config.checkpoint_every steps and at the end.
        callback(trainer) runs after each step (its time is not counted in self.seconds). label: the
        progress bar's title (a long video's: its segment); job: (steps of the job before this run,
        the job's steps), shown on the bar as the whole job's share done."""
        cfg = self.config
        bar = Progress(total=self.steps - self.step, desc=label if self.step == 0 else f"{label} from {self.step}",
                       enabled=progress)
        try:
            while self.step < self.steps:
                t0 = time.perf_counter()
                figures = self.train_step()
                self.seconds += time.perf_counter() - t0
                self.history.append({"step": self.step, **figures, "gaussians": self.params.count,
                                     "seconds": self.seconds})
                bar.set(loss=round(figures["loss"], 4), psnr=round(figures["psnr"], 2), gaussians=self.params.count)
                if job is not None:
                    bar.set(job=f"{100 * (job[0] + self.step) / max(job[1], 1):.0f}%")
                bar.update()
                if self.out_dir is not None and (self.step % cfg.checkpoint_every == 0 or self.step == self.steps):
                    self.save_checkpoint(self.out_dir / "checkpoint.pt")
                if callback is not None:
                    callback(self)
        finally:
            bar.close()

    # -- evaluation -----------------------------------------------------------------------------------
    @torch.no_grad()
    def render_numpy(self, camera: Camera, tau: float) -> np.ndarray:
        """(H, W, 3) float32 rgb in [0, 1] (no gradient)."""
        return self.render(camera, tau)[0].clamp(0, 1).cpu().numpy()

    @torch.no_grad()
    def heldout_psnr(self, frames=None) -> float:
        """Mean PSNR (dB) over the test cameras at `frames` (default: every frame), torch renderer."""
        ds = self.dataset
        frames = range(ds.num_frames) if frames is None else frames
        values = []
        for ci in ds.test_cameras:
            for j in frames:
                img = self.render_numpy(ds.cameras[ci], frame_time(ds, j))
                mse = float(np.mean((img.astype(np.float64) - ds.image(ci, j)) ** 2))
                values.append(psnr_of_mse(max(mse, 1e-12)))
        return float(np.mean(values))

    # -- checkpoints ----------------------------------------------------------------------------------
    def state_dict(self) -> dict:
        return {"version": CHECKPOINT_VERSION, "time": TIME_AXIS, "warm": self.warm, "config": asdict(self.config),
                "step": self.step,
                "params": self.params.state_dict(), "optimizer": self.optimizer.state_dict(),
                "strategies": [s.state_dict() for s in self.strategies], "box": self.box.tolist(),
                "history": self.history, "seconds": self.seconds,
                "bounds": None if self.dataset.bounds is None else self.dataset.bounds.tolist(),
                "bounds_source": self.dataset.bounds_source, **self.rig.state_dict(),
                "rng": {"numpy": self.rng.bit_generator.state, "torch": torch.get_rng_state(),
                        "cuda": torch.cuda.get_rng_state_all() if torch.cuda.is_available() else None,
                        "python": random.getstate()}}

    def save_checkpoint(self, path) -> None:
        """Write the state to `path` atomically (stg_runtime.atomic)."""
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        with atomic_output(path) as tmp:
            torch.save(self.state_dict(), tmp)

    @classmethod
    def resume(cls, dataset, path, out_dir=None, device: str | None = None, splatter: str | None = None,
               changes: dict | None = None) -> "Trainer":
        """Continue the run saved in checkpoint `path` (its settings win; `device` and `splatter` may
        move it to another device or rasteriser backend; `changes`, TrainConfig fields, replace others:
        the caller decides which may change mid-run, as stg_train.pipeline does). ValueError (the
        checkpoint's CheckpointError among them) naming the file when it cannot be continued."""
        state = read_checkpoint(path)
        if state.get("version") != CHECKPOINT_VERSION:
            raise ValueError(f"{path}: checkpoint version {state.get('version')} is not {CHECKPOINT_VERSION}")
        if any(getattr(dataset, "context_frames", (0, 0))) and state.get("time") != TIME_AXIS:
            raise ValueError(f"{path}: this segment was trained with context frames by an earlier version, whose "
                             "time axis also spanned them; it cannot continue here: remove its folder to retrain it")
        config = TrainConfig.from_dict(state["config"])
        if device is not None:
            config.device = device
        if splatter is not None:
            config.splatter = splatter
        if changes:
            config = replace(config, **changes)
        return cls(dataset, config, Path(path).parent if out_dir is None else out_dir, _state=state)
