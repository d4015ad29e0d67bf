"""The settings of a training run, without torch: the command lines build their parsers and `--help`
from these (and stg_train.choices) before any heavy module is imported.

    TrainConfig     a run's settings (stored in checkpoints and in the exported file's provenance)
    DEMO_SCENE      the demo's synthetic scene (stg-train --demo, the benchmarks)
    DEMO_TRAINING   the demo's training settings
"""
from __future__ import annotations

from dataclasses import dataclass, field, fields, replace

from .choices import INIT_METHODS, MOTION_INITS  # noqa: F401 (MOTION_INITS re-exported for the trainer)

#: The demo's synthetic scene (stg-train --demo, the benchmarks).
DEMO_SCENE = {"cameras": 12, "frames": 30, "fps": 30.0, "width": 160, "height": 120}
#: Training settings of the demo (docs/performance.md has its time and quality).
DEMO_TRAINING = {"iterations": 1500, "num_points": 8000}


@dataclass
class TrainConfig:
    """Settings of a run (stored in checkpoints and in the exported file's provenance).

    model: "full" (9 features + decoder) or "lite" (rgb); iterations: optimisation steps; batch: views
    per step (one shared time); num_points: initial Gaussians (the most SfM points kept); init: where the
    initial points come from, one of INIT_METHODS: "auto" (or None: default_method of
    the dataset), "sfm" (stg_train.data.sfm on every init_every-th frame), "volume"
    (stg_train.data.volume) or "combined" (SfM points plus view-volume samples where they leave holes);
    depth_candidates: photo-consistency depth search of the view-volume points (0: uniform depths; see
    stg_train.data.volume.sample_view_volume); static: freeze the time terms (ablation); lr_scale:
    multiplies every reference learning rate; stretch_rates: the motion and rotation velocities' rates
    stretched to the run's length (params.LearningRates.stretched; False: the reference's 30k-step
    rates); schedule: Schedule field overrides (iterations of this run) on top of the reference schedule
    stretched to `iterations`; thresholds: Thresholds field overrides; seed: numpy /
    torch / python seeds; device: "cpu" or "cuda"; splatter: the rasteriser backend, "numba", "torch",
    "gsplat" or "auto" (stg_train.render.rasterize and resolve_backend: numba on the CPU, gsplat on CUDA
    where it can run, else torch); guided: guided sampling of Gaussians in high-error patches
    (stg_train.strategy.guided, the paper's Sec. 4.4); frozen: time components
    switched off for ablations (params.COMPONENTS: "temporal_opacity", "motion", "rotation",
    "time_features"; `static` freezes them all); motion_init: the initial motion, "zero" (the
    reference's) or "flow" (each initial point's velocity from the optical flow of its frame in the
    training cameras, stg_train.data.flow); guided_settings: GuidedSettings field overrides;
    learning_rates: params.LearningRates field overrides (before lr_scale and the stretch);
    separate_rotation: the reference's step that keeps the rotation velocity only for moving Gaussians
    (stg_train.strategy.rotation, at Schedule.separate_at); appearance: a learned colour transform per
    training camera (and, with appearance_vignetting, a radial falloff) applied to its renders before
    the loss only (stg_train.rig.appearance): True, False, or "auto" (the default: on when the training
    cameras' colour gains, measured before training from what they see of the same surfaces, disagree;
    stg_train.rig.self_calibration.calibrate_rig); pose_refine: a learned rigid correction of each training
    camera's pose (stg_train.rig.pose_refine): True, False, or "auto" (the default: on when what neighbouring
    training cameras see strays from the epipolar lines of their stated poses); lens_falloff: the
    training cameras' known vignetting (k1, k2), e.g. from a flat-field calibration, applied to their
    renders before the loss as 1 + k1 s + k2 s^2 (stg_train.rig.lens; ValueError outside its range), when
    the appearance then learns none; None: none; "auto" (the default) measures it before training from what the training cameras see of
    the same surfaces, and trains without one where it cannot be measured or is too small to matter
    (stg_train.rig.self_calibration; the checkpoint keeps the choices made);
    camera_learning_rates: overrides of their rates (keys "matrix", "bias", "vignetting" of
    appearance.APPEARANCE_LR, "rotation", "translation" of pose_refine.POSE_LR); segment_context: for a video trained in segments, how many neighbouring
    frames on each side a segment is also fitted to (as context: it shows only its own frames, and the
    players crossfade over the seam where both neighbours have context; stg_train.segments);
    edge_weight: how often the first and last frames a run shows (trainer.EDGE_FRAMES at each end: the
    video's ends, and a segment's frames next to a seam) are drawn for a training step, relative to the
    others, a video's own first and last frame trainer.END_FRAME_FACTOR times that (ours; the reference
    draws every frame alike, 1); camera_gains: {camera name: (r, g, b)} the training cameras' colour
    gains relative to the rig's, as the rig's measurement before training found them where it decided
    on an appearance (stg_train.rig.self_calibration.calibrate_rig; None: not measured): the initial points
    are drawn from the pictures divided by them (CameraRig.initial_brightness), and a long video's
    segments, which are given the measurement's choices, share them; segment_schedule: how a long
    video's segments start, "warm" (each from its predecessor's Gaussians at the seam, stg_train.warm,
    trained for warm_fraction of `iterations`) or "independent" (each from its own initial points, the
    paper's); warm_fraction: a warm segment's share of a cold segment's iterations; warm_chain: with
    "warm", every warm_chain-th segment starts cold (parallel chains; 0: one chain); warm_time_scale:
    the least temporal scale (in the new segment's normalised time) of a carried Gaussian that is
    drawn at the seam (stg_train.warm.extend_at_seam; 0: the exact re-based Gaussians only);
    warm_points: a warm segment also starts from its own initial points (Trainer._add_initial_points).
    docs/training.md says which defaults are the reference's and which are ours, with the measurements behind them.
    """

    model: str = "full"
    iterations: int = 3000
    batch: int = 2
    num_points: int = 20000
    depth_candidates: int = 64
    init: str | None = "auto"
    init_every: int = 1
    static: bool = False
    lr_scale: float = 1.0
    stretch_rates: bool = True
    schedule: dict = field(default_factory=dict)
    thresholds: dict = field(default_factory=dict)
    seed: int = 0
    device: str = "cpu"
    checkpoint_every: int = 500
    splatter: str = "auto"
    guided: bool = True
    frozen: tuple = ()
    motion_init: str = "flow"
    guided_settings: dict = field(default_factory=dict)
    learning_rates: dict = field(default_factory=dict)
    separate_rotation: bool = False
    appearance: bool | str = "auto"
    appearance_vignetting: bool = True
    pose_refine: bool | str = "auto"
    lens_falloff: tuple | str | None = "auto"
    camera_learning_rates: dict = field(default_factory=dict)
    segment_context: int = 4
    edge_weight: float = 3.0
    camera_gains: dict | None = None
    segment_schedule: str = "independent"
    warm_fraction: float = 0.25
    warm_chain: int = 0
    warm_time_scale: float = 0.0
    warm_points: bool = True

    def for_dataset(self, dataset) -> "TrainConfig":
        """These settings with the choices left open made: init "auto" (or None) -> default_method(dataset),
        splatter "auto" -> resolve_backend(splatter, device)."""
        from .data.points import resolve_method  # numpy and the data package, not needed to read settings
        from .render import resolve_backend  # torch

        init = resolve_method(dataset, self.init)
        config = self if init == self.init else replace(self, init=init)
        if config.splatter == "auto":
            config = replace(config, splatter=resolve_backend("auto", config.device))
        return config

    @classmethod
    def from_dict(cls, d: dict) -> "TrainConfig":
        """The settings as saved (asdict); a setting the dict lacks takes its default, except those whose
        default became "auto" later (SAVED_BEFORE_AUTO): a run saved before knew them as off; likewise
        segment_schedule (SAVED_BEFORE): a run saved before trained its segments independently."""
        names = {f.name for f in fields(cls)}
        return cls(**{**SAVED_BEFORE, **{k: v for k, v in d.items() if k in names}})


#: The settings whose default became "auto" (2026-12-04), with the value a checkpoint without them ran with.
SAVED_BEFORE_AUTO = {"appearance": False, "lens_falloff": None, "pose_refine": False}
#: Settings added later whose default is not what a checkpoint without them ran with: warm segments
#: (issue 51, 2026-12-07) came after independent ones, and their own initial points after that.
SAVED_BEFORE = {**SAVED_BEFORE_AUTO, "segment_schedule": "independent", "warm_points": False,
                "warm_time_scale": 0.0}
