"""The in-memory model: a list of time segments, each a structure of per-Gaussian arrays.

Shapes and meanings are those of formats/stg-v1.md, section 2. Arrays are float32.
"""
from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from .camera import Camera
from .onnx_mlp import canonical, read_mlp

KINDS = ("lite", "full", "sh")
ACTIVATIONS = ("sigmoid", "clamp", "identity")
#: Attribute name -> trailing shape, given position degree P, rotation degree Q and channels C.
ATTRIBUTES = ("opacity", "t_center", "t_scale", "position", "rotation", "scale", "features")
#: Feature channels of the kinds with one layout ("sh" models have 3 (d+1)^2, see SH_CHANNELS).
FEATURE_CHANNELS = {"lite": 3, "full": 9}
#: "sh" models: spherical-harmonics degree d (0..3) -> feature channels 3 (d+1)^2 (stg_runtime/sh.py).
SH_CHANNELS = {0: 3, 1: 12, 2: 27, 3: 48}
#: Trailing feature channels of a full model that are multiplied by tau - t_center (its time features).
TIME_CHANNELS = 3


def sh_degree_of(channels: int) -> int:
    """The SH degree of a feature channel count (3, 12, 27, 48 -> 0, 1, 2, 3); ValueError otherwise."""
    degrees = {c: d for d, c in SH_CHANNELS.items()}
    if channels not in degrees:
        raise ValueError(f"{channels} feature channels is not an SH layout (expected one of {sorted(degrees)})")
    return degrees[channels]


def time_channels(segment: "Segment") -> int:
    """How many trailing feature channels are multiplied by (tau - t_center): 3 for full, 0 for lite and sh."""
    return TIME_CHANNELS if segment.channels == FEATURE_CHANNELS["full"] else 0


def allowed_channels(kind: str) -> tuple[int, ...]:
    """The feature channel counts a segment of a `kind` model may have."""
    return tuple(SH_CHANNELS.values()) if kind == "sh" else (FEATURE_CHANNELS[kind],)


def attribute_shape(name: str, count: int, position_degree: int, rotation_degree: int, channels: int) -> tuple:
    """The full shape of attribute `name` for a segment of `count` Gaussians."""
    return {
        "opacity": (count,),
        "t_center": (count,),
        "t_scale": (count,),
        "position": (count, position_degree + 1, 3),
        "rotation": (count, rotation_degree + 1, 4),
        "scale": (count, 3),
        "features": (count, channels),
    }[name]


@dataclass
class Segment:
    """One independently trained model covering frames [start_frame, start_frame + num_frames).

    opacity (N,) in [0, 1]; t_center (N,) normalised time; t_scale (N,) >= 0;
    position (N, P+1, 3) polynomial coefficients; rotation (N, Q+1, 4) quaternion coefficients (wxyz);
    scale (N, 3) standard deviations; features (N, C): C = 3 (lite), 9 (full) or 3 (d+1)^2 (sh: SH
    coefficients of degree d, coefficient-major, see stg_runtime/sh.py).
    decoder: ONNX bytes of a decoder graph (full models; formats/stg-v1.md, the MLP family) or None,
    kept in canonical form (stg_runtime.onnx_mlp.canonical: parsed and re-serialised, so that nothing but
    a valid decoder can ever reach onnxruntime); activation: how the decoder output becomes rgb.
    context_frames: (before, after), how many frames before its first and after its last frame the
    segment was also fitted to (its renders there are as good as inside; format 1.3). crossfade_frames:
    over how many frames players blend the previous segment into this one around their boundary (0: a
    hard cut; formats/stg-v1.md, "Segments and crossfades").
    """

    start_frame: int
    num_frames: int
    opacity: np.ndarray
    t_center: np.ndarray
    t_scale: np.ndarray
    position: np.ndarray
    rotation: np.ndarray
    scale: np.ndarray
    features: np.ndarray
    decoder: bytes | None = None
    activation: str = "sigmoid"
    context_frames: tuple[int, int] = (0, 0)
    crossfade_frames: int = 0

    def __post_init__(self):
        for name in ATTRIBUTES:
            setattr(self, name, np.ascontiguousarray(getattr(self, name), dtype=np.float32))
        self.start_frame, self.num_frames = int(self.start_frame), int(self.num_frames)
        self.context_frames = tuple(int(c) for c in self.context_frames)
        self.crossfade_frames = int(self.crossfade_frames)
        if self.decoder is not None:
            try:
                self.decoder = canonical(bytes(self.decoder))
            except ValueError as e:
                raise ValueError(f"segment: decoder: {e}") from None
        self.validate()

    @property
    def count(self) -> int:
        return int(self.opacity.shape[0])

    @property
    def position_degree(self) -> int:
        return self.position.shape[1] - 1

    @property
    def rotation_degree(self) -> int:
        return self.rotation.shape[1] - 1

    @property
    def channels(self) -> int:
        return self.features.shape[1]

    def arrays(self) -> dict[str, np.ndarray]:
        return {name: getattr(self, name) for name in ATTRIBUTES}

    def validate(self) -> None:
        """Raise ValueError when shapes disagree or values are out of range."""
        if self.num_frames <= 0 or self.start_frame < 0:
            raise ValueError(f"segment: bad frame range start={self.start_frame}, frames={self.num_frames}")
        if self.position.ndim != 3 or self.rotation.ndim != 3 or self.features.ndim != 2:
            raise ValueError("segment: position must be (N, P+1, 3), rotation (N, Q+1, 4), features (N, C)")
        n = self.count
        for name in ATTRIBUTES:
            want = attribute_shape(name, n, self.position_degree, self.rotation_degree, self.channels)
            got = getattr(self, name).shape
            if got != want:
                raise ValueError(f"segment: attribute {name} has shape {got}, expected {want}")
            if not np.all(np.isfinite(getattr(self, name))):
                raise ValueError(f"segment: attribute {name} has non-finite values")
        if self.decoder is not None:
            mlp = read_mlp(self.decoder)
            if (mlp.input_width, mlp.output_width) != (self.channels + 3, 3):
                raise ValueError(f"segment: the decoder maps {mlp.input_width} -> {mlp.output_width} channels; "
                                 f"with {self.channels} features it must map {self.channels + 3} -> 3")
        if self.activation not in ACTIVATIONS:
            raise ValueError(f"segment: activation must be one of {ACTIVATIONS}, got {self.activation!r}")
        if len(self.context_frames) != 2 or min(self.context_frames) < 0:
            raise ValueError(f"segment: context_frames must be two counts >= 0, got {self.context_frames}")
        if self.crossfade_frames < 0:
            raise ValueError(f"segment: crossfade_frames must be >= 0, got {self.crossfade_frames}")

    def subset(self, mask_or_index) -> "Segment":
        """A copy keeping only the Gaussians selected by a boolean mask or an index array."""
        return replace(self, **{name: arr[mask_or_index] for name, arr in self.arrays().items()})

    def retimed(self, start_frame: int, num_frames: int) -> "Segment":
        """The same Gaussians with normalised time over frames [start_frame, start_frame + num_frames)
        instead of this segment's own: every render at a video time is unchanged (up to float32
        rounding). With a = num_frames / self.num_frames and tau' the new normalised time,
        tau - t_center = a (tau' - t_center'), so t_center' = (t_center * n + start - start') / n',
        t_scale' = a^2 t_scale and the coefficients of degree k (position, rotation; the full model's
        time features, degree 1) are multiplied by a^k. context_frames follow the frames they name."""
        a = num_frames / self.num_frames
        arrays = {k: v.astype(np.float64) for k, v in self.arrays().items()}
        arrays["t_center"] = (arrays["t_center"] * self.num_frames + self.start_frame - start_frame) / num_frames
        arrays["t_scale"] = arrays["t_scale"] * a * a
        arrays["position"] = arrays["position"] * a ** np.arange(self.position_degree + 1)[:, None]
        arrays["rotation"] = arrays["rotation"] * a ** np.arange(self.rotation_degree + 1)[:, None]
        if time_channels(self):
            arrays["features"][:, -TIME_CHANNELS:] *= a
        first = self.start_frame - self.context_frames[0]
        last = self.start_frame + self.num_frames + self.context_frames[1]
        context = (max(0, start_frame - first), max(0, last - start_frame - num_frames))
        return replace(self, start_frame=start_frame, num_frames=num_frames, context_frames=context,
                       **{k: v.astype(np.float32) for k, v in arrays.items()})


@dataclass
class Model:
    """A whole video: its segments in time order, the training cameras and metadata."""

    kind: str
    fps: float
    segments: list[Segment]
    cameras: list[Camera] = field(default_factory=list)
    bounds: tuple | None = None  # ((3,), (3,)) world-space min and max, or None
    provenance: dict = field(default_factory=dict)

    def __post_init__(self):
        self.fps = float(self.fps)
        self.validate()

    @property
    def start_frame(self) -> int:
        return self.segments[0].start_frame

    @property
    def num_frames(self) -> int:
        """Frames covered by the segments (the video starts at frame `start_frame`)."""
        return sum(s.num_frames for s in self.segments)

    @property
    def sh_degree(self) -> int | None:
        """The spherical-harmonics degree of an "sh" model (its segments' highest), None for other kinds."""
        if self.kind != "sh":
            return None
        return max(sh_degree_of(s.channels) for s in self.segments)

    @property
    def duration(self) -> float:
        """Seconds covered, num_frames / fps."""
        return self.num_frames / self.fps

    def validate(self) -> None:
        if self.kind not in KINDS:
            raise ValueError(f"model: kind must be one of {KINDS}, got {self.kind!r}")
        if not (np.isfinite(self.fps) and self.fps > 0):
            raise ValueError(f"model: fps must be positive, got {self.fps}")
        if not self.segments:
            raise ValueError("model: no segments")
        want_c = allowed_channels(self.kind)
        for i, seg in enumerate(self.segments):
            if seg.channels not in want_c:
                raise ValueError(f"model: segment {i} has {seg.channels} feature channels, a {self.kind} model has "
                                 f"{' or '.join(map(str, want_c))}")
            if (seg.decoder is None) != (self.kind != "full"):
                raise ValueError(f"model: segment {i}: a {self.kind} model {'needs' if self.kind == 'full' else 'has no'} decoder")
            if i and seg.start_frame != self.segments[i - 1].start_frame + self.segments[i - 1].num_frames:
                raise ValueError(f"model: segment {i} starts at frame {seg.start_frame}, not right after segment {i - 1}")
        if self.segments[0].crossfade_frames:
            raise ValueError("model: segment 0 has crossfade_frames, but no segment before it to fade from")
        for i, seg in enumerate(self.segments):
            fade_out = self.segments[i + 1].crossfade_frames if i + 1 < len(self.segments) else 0
            if seg.crossfade_frames + fade_out > 2 * seg.num_frames:
                raise ValueError(f"model: segment {i} ({seg.num_frames} frames) is too short for its crossfades "
                                 f"({seg.crossfade_frames} in, {fade_out} out): half of each must fit in it")

    def segment_at(self, t: float) -> tuple[Segment, float]:
        """The segment whose frames hold time t (seconds since frame 0) and the normalised time tau
        within it (where a crossfade blends two segments, the one holding t: see segments_at)."""
        seg = self.segments[self._index_at(t)]
        return seg, self.tau(seg, t)

    def _index_at(self, t: float) -> int:
        """Index of the segment whose frames hold time t (the last one for t at or past the end)."""
        frame = int(np.floor(t * self.fps + 1e-9))
        return next((i for i, s in enumerate(self.segments) if frame < s.start_frame + s.num_frames),
                    len(self.segments) - 1)

    def tau(self, segment: Segment, t: float) -> float:
        """Normalised time of `segment` at t seconds (outside [0, 1] beyond its frames)."""
        return (t - segment.start_frame / self.fps) / (segment.num_frames / self.fps)

    def segments_at(self, t: float) -> list[tuple[Segment, float, float]]:
        """What a player shows at time t: [(segment, tau, weight)], one entry of weight 1, or two (the
        earlier segment first) inside a crossfade, whose weights add up to 1; the image is the weighted
        sum of their renders. A crossfade of b frames into segment B starting at frame s spans
        x = t * fps in [s - 1/2 - b/2, s - 1/2 + b/2], with B's weight rising linearly from 0 to 1
        (formats/stg-v1.md, "Segments and crossfades")."""
        i = self._index_at(t)
        x = t * self.fps
        for later in (i, i + 1):  # the fade into seg, and the fade out of it
            if 0 < later < len(self.segments) and self.segments[later].crossfade_frames:
                b = self.segments[later].crossfade_frames
                w = (x - (self.segments[later].start_frame - 0.5 - 0.5 * b)) / b
                if 0.0 < w < 1.0:
                    a_seg, b_seg = self.segments[later - 1], self.segments[later]
                    return [(a_seg, self.tau(a_seg, t), 1.0 - w), (b_seg, self.tau(b_seg, t), w)]
        return [(self.segments[i], self.tau(self.segments[i], t), 1.0)]
