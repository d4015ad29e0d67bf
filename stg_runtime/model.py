"""The in-memory model: a list of time segments, each a structure of per-Gaussian arrays.

Shapes and meanings are those of formats/stg-v1.md, section 2. Arrays are float32.
"""
from __future__ import annotations

from dataclasses import dataclass, field

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

    def __post_init__(self):
        for name in ATTRIBUTES:
            setattr(self, name, np.ascontiguousarray(getattr(self, name), dtype=np.float32))
        self.start_frame, self.num_frames = int(self.start_frame), int(self.num_frames)
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

    def subset(self, mask_or_index) -> "Segment":
        """A copy keeping only the Gaussians selected by a boolean mask or an index array."""
        kept = {name: arr[mask_or_index] for name, arr in self.arrays().items()}
        return Segment(self.start_frame, self.num_frames, decoder=self.decoder, activation=self.activation, **kept)


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

    def segment_at(self, t: float) -> tuple[Segment, float]:
        """The segment showing time t (seconds since frame 0) and the normalised time tau within it."""
        frame = int(np.floor(t * self.fps + 1e-9))
        for seg in self.segments:
            if frame < seg.start_frame + seg.num_frames:
                break
        start = seg.start_frame / self.fps
        return seg, (t - start) / (seg.num_frames / self.fps)
